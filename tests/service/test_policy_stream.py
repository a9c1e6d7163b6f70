"""`PolicyService.Act` over a real gRPC channel: a trained job's policy asked by robots, each
row's recurrent state kept by the server, the streams of one policy batched together, and the
status codes the proto documents."""

from __future__ import annotations

import asyncio
import threading

import grpc
import jax
import numpy as np
import pytest
from quicknav_client import RemotePolicy, RolloutError

from quicknav_core.config import TrainConfig
from quicknav_core.export import random_observations
from quicknav_core.train import train_run
from quicknav_core.train.run import load_run
from quicknav_service.rollout.server import BackgroundServer
from quicknav_service.settings import Settings

TOKEN = "policy-s3cret"
JOB = "job-lstm"


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    """A server with a token whose artifacts hold a briefly trained LSTM job."""
    settings = Settings(data_dir=tmp_path_factory.mktemp("data"), host="127.0.0.1", grpc_port=0,
                        api_token=TOKEN, rollout_max_sessions=4)  # fmt: skip
    cfg = TrainConfig.model_validate({
        "env": {"grid_size": 8, "train_rooms": 16, "test_rooms": 8, "lidar_beams": 8, "max_steps": 40},
        "algorithm": {"name": "ppo", "num_steps": 16, "num_minibatches": 2, "num_epochs": 1},
        "network": {"kind": "lstm", "hidden_size": 8, "num_layers": 1},
        "num_envs": 8, "total_steps": 256, "chunk_steps": 128,
    })  # fmt: skip
    train_run(cfg, settings.artifacts_dir / JOB)
    config, trainer, state, _ = load_run(settings.artifacts_dir / JOB)
    srv = BackgroundServer(settings, port=0).start()
    yield srv, config, trainer.policy(state)
    srv.stop()


def reference(policy, observations, starts):
    """The same rows stepped by the JAX policy directly, the state carried along."""
    carry = policy.initial_carry(observations[0].shape[0])
    out = []
    for obs, start in zip(observations, starts, strict=True):
        carry, action = policy.act(carry, obs, start, None, True)
        out.append(np.asarray(action))
    return out


def test_policy_stream__two_robots_streams_keep_their_own_state(served):
    srv, config, policy = served
    target = f"127.0.0.1:{srv.port}"
    rng = np.random.default_rng(0)
    plans = {}
    for rows in (2, 3):
        observations = [random_observations(config.env, rows, seed=rows * 100 + t) for t in range(6)]
        starts = [np.ones(rows, bool)] + [rng.random(rows) < 0.3 for _ in range(5)]
        plans[rows] = (observations, starts)
    results: dict[int, list[np.ndarray]] = {}
    barrier = threading.Barrier(2)

    def robot(rows):
        with RemotePolicy(target, token=TOKEN) as rp:
            manifest = rp.load(JOB, rows=rows)
            assert manifest["observation"]["size"] == config.env.obs_dim and rp.rows == rows
            assert manifest["recurrent"] and manifest["state"], manifest["state"]
            got = []
            for obs, start in zip(*plans[rows], strict=True):
                barrier.wait(timeout=60)  # both streams ask at once: the server may batch them
                got.append(rp.act(obs, start))
            results[rows] = got

    threads = [threading.Thread(target=robot, args=(rows,)) for rows in plans]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=300)
    for rows, (observations, starts) in plans.items():
        want = reference(policy, observations, starts)
        for t, (a, b) in enumerate(zip(results[rows], want, strict=True)):
            np.testing.assert_allclose(a, b, atol=1e-5, err_msg=f"rows={rows}, step {t}")
    # whether two network requests meet in one batch depends on timing; the batcher's own test
    # below holds that requests arriving together are one call
    assert srv.servicer.policy_servicer.policies[JOB].requests == 12


def test_policy_stream__a_server_keeps_its_cache_of_policies_not_every_one_it_loaded(served, tmp_path):
    """QUICKNAV_ROLLOUT_POLICY_CACHE=1: a server that loads a second job's policy lets the first
    go (it kept every one it ever loaded, for as long as it ran), and a stream that loaded the
    first still acts with it, as the JAX policy does."""
    import shutil

    _, config, policy = served
    settings = Settings(data_dir=tmp_path, host="127.0.0.1", grpc_port=0, rollout_policy_cache=1)
    for job in ("job-a", "job-b"):
        shutil.copytree(served[0].settings.artifacts_dir / JOB, settings.artifacts_dir / job)
    srv = BackgroundServer(settings, port=0).start()
    target = f"127.0.0.1:{srv.port}"
    obs = [random_observations(config.env, 2, seed=t) for t in range(3)]
    starts = [np.ones(2, bool), np.zeros(2, bool), np.zeros(2, bool)]
    try:
        with RemotePolicy(target) as first, RemotePolicy(target) as second:
            first.load("job-a", rows=2)
            got = [first.act(obs[0], starts[0])]
            second.load("job-b", rows=2)
            cache = srv.servicer.policy_servicer.policies
            assert len(cache) == 1 and "job-b" in cache and "job-a" not in cache
            got += [first.act(o, s) for o, s in zip(obs[1:], starts[1:], strict=True)]
            second.act(obs[0], starts[0])
        for t, (a, b) in enumerate(zip(got, reference(policy, obs, starts), strict=True)):
            np.testing.assert_allclose(a, b, atol=1e-5, err_msg=f"step {t}")
    finally:
        srv.stop()


def test_policy_batcher__requests_of_one_loop_tick_run_as_one_call(served):
    """The batcher itself: three streams' requests that arrive together are one jitted call, and
    each gets back exactly what it would have got alone."""
    from concurrent.futures import ThreadPoolExecutor

    from quicknav_service.rollout.policy import LoadedPolicy

    _, config, policy = served
    loaded = LoadedPolicy(policy, config.env.obs_dim, "{}", ThreadPoolExecutor(1))
    sizes = (1, 2, 4)
    obs = [random_observations(config.env, n, seed=n) for n in sizes]
    starts = [np.ones(n, bool) for n in sizes]

    async def together():
        carries = [loaded.initial(n) for n in sizes]
        return await asyncio.gather(*(loaded.act(c, o, s) for c, o, s in zip(carries, obs, starts, strict=True)))

    results = asyncio.run(together())
    assert loaded.batches == 1 and loaded.requests == 3
    for (carry, actions), o, s, n in zip(results, obs, starts, sizes, strict=True):
        want_carry, want = policy.act(policy.initial_carry(n), o, s, None, True)
        np.testing.assert_allclose(actions, np.asarray(want), atol=1e-6)
        for a, b in zip(jax.tree.leaves(carry), jax.tree.leaves(want_carry), strict=True):
            np.testing.assert_allclose(a, np.asarray(b), atol=1e-6)


def test_policy_batcher__streams_waiting_together_are_split_into_calls_of_at_most_max_rows(served):
    """Many streams' requests at once never make one call larger than one stream's most rows (the
    memory admission counted): four requests of 4, 2, 4 and 8 rows with a cap of 8 are three calls
    (6, 4 and 8 rows), and each stream still gets exactly what it would have got alone."""
    from concurrent.futures import ThreadPoolExecutor

    from quicknav_service.rollout.policy import MAX_ROWS, LoadedPolicy

    _, config, policy = served
    assert LoadedPolicy(policy, config.env.obs_dim, "{}", ThreadPoolExecutor(1)).max_rows == MAX_ROWS
    loaded = LoadedPolicy(policy, config.env.obs_dim, "{}", ThreadPoolExecutor(1), max_rows=8)
    sizes = (4, 2, 4, 8)
    obs = [random_observations(config.env, n, seed=i) for i, n in enumerate(sizes)]
    starts = [np.ones(n, bool) for n in sizes]

    async def together():
        carries = [loaded.initial(n) for n in sizes]
        return await asyncio.gather(*(loaded.act(c, o, s) for c, o, s in zip(carries, obs, starts, strict=True)))

    results = asyncio.run(together())
    assert (loaded.batches, loaded.requests, loaded.largest_call) == (3, 4, 8)
    for (carry, actions), o, s, n in zip(results, obs, starts, sizes, strict=True):
        want_carry, want = policy.act(policy.initial_carry(n), o, s, None, True)
        np.testing.assert_allclose(actions, np.asarray(want), atol=1e-6)
        for a, b in zip(jax.tree.leaves(carry), jax.tree.leaves(want_carry), strict=True):
            np.testing.assert_allclose(a, np.asarray(b), atol=1e-6)


def _code(fn) -> tuple[grpc.StatusCode, str]:
    with pytest.raises(RolloutError) as e:
        fn()
    return e.value.code, e.value.message


def test_policy_stream__status_codes_as_the_proto_documents(served):
    srv, config, _ = served
    target = f"127.0.0.1:{srv.port}"
    with RemotePolicy(target) as rp:  # no token
        code, msg = _code(lambda: rp.load(JOB))
        assert code == grpc.StatusCode.UNAUTHENTICATED and "Bearer" in msg
    with RemotePolicy(target, token=TOKEN) as rp:
        code, msg = _code(lambda: rp.act(np.zeros((1, config.env.obs_dim), np.float32)))
        assert code == grpc.StatusCode.FAILED_PRECONDITION and "act before load" in msg
    with RemotePolicy(target, token=TOKEN) as rp:
        code, msg = _code(lambda: rp.load("no-such-job"))
        assert code == grpc.StatusCode.NOT_FOUND and "no-such-job" in msg and "/" not in msg
    with RemotePolicy(target, token=TOKEN) as rp:
        rp.load(JOB, rows=2)
        code, msg = _code(lambda: rp.act(np.zeros((3, config.env.obs_dim), np.float32)))
        assert code == grpc.StatusCode.INVALID_ARGUMENT and f"[2, {config.env.obs_dim}]" in msg
    with RemotePolicy(target, token=TOKEN) as rp:
        rp.load(JOB, rows=1)
        bad = np.full((1, config.env.obs_dim), np.nan, np.float32)
        code, msg = _code(lambda: rp.act(bad))
        assert code == grpc.StatusCode.INVALID_ARGUMENT and "NaN" in msg
    with RemotePolicy(target, token=TOKEN) as rp:
        code, msg = _code(lambda: rp.load(JOB, rows=100_000))
        assert code == grpc.StatusCode.RESOURCE_EXHAUSTED and "load.rows=100000" in msg
