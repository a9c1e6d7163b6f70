"""The gRPC Rollout service over a real channel to an in-process server on a free port."""

from __future__ import annotations

import threading
import time

import grpc
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from quicknav_client.proto.quicknav.v1 import rollout_pb2 as pb
from quicknav_client.rollout import RolloutClient, RolloutError
from quicknav_client.tensors import encode

from quicknav_core.config import EnvConfig
from quicknav_core.env.batch import env_and_params, step_keys
from quicknav_service.rollout.server import BackgroundServer
from quicknav_service.settings import Settings

CONFIG = {"grid_size": 8, "train_rooms": 16, "test_rooms": 8, "lidar_beams": 8, "max_steps": 12}
N = 4


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    settings = Settings(data_dir=tmp_path_factory.mktemp("data"), host="127.0.0.1", grpc_port=0,
                        max_envs=64, rollout_max_sessions=3)  # fmt: skip
    srv = BackgroundServer(settings, port=0).start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def strict_server(tmp_path_factory):
    """Token required, short idle timeout."""
    settings = Settings(data_dir=tmp_path_factory.mktemp("data"), host="127.0.0.1", grpc_port=0,
                        api_token="s3cret-token", rollout_idle_s=0.5)  # fmt: skip
    srv = BackgroundServer(settings, port=0).start()
    yield srv
    srv.stop()


def close(actual, desired):
    """Equal up to float32 rounding: the served step fuses differently from vmap(env.step)."""
    np.testing.assert_allclose(actual, desired, rtol=1e-4, atol=1e-5)


def _target(srv) -> str:
    return f"127.0.0.1:{srv.port}"


def _actions(rng, n=N):
    return rng.uniform(-1, 1, (n, 2)).astype(np.float32)


def _reference(seed: int, n: int, actions: list[np.ndarray]):
    """The same session computed with the JAX env directly (vmapped gymnax step, no service)."""
    env, params = env_and_params(EnvConfig(**CONFIG), "train")
    rng = jax.random.PRNGKey(seed)
    rng, sub, word = jax.random.split(rng, 3)
    counter = jnp.stack([jax.random.bits(word, (), jnp.uint32), jnp.uint32(0)])
    obs, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(sub, n), params)
    out = [np.asarray(obs)]
    for a in actions:
        keys = step_keys(counter, n)
        obs, state, reward, done, info = jax.vmap(env.step, in_axes=(0, 0, 0, None))(
            keys, state, jnp.asarray(a), params
        )
        counter = counter.at[1].add(1)
        out.append((np.asarray(obs), np.asarray(reward), np.asarray(info["terminated"]),
                    np.asarray(info["truncated"]), np.asarray(info["final_obs"])))  # fmt: skip
    return out


def test_rollout__full_session_matches_the_jax_env(server):
    rng = np.random.default_rng(0)
    actions = [_actions(rng) for _ in range(30)]
    ref = _reference(7, N, actions)
    with RolloutClient(_target(server)) as rc:
        started = rc.start(num_envs=N, seed=7, config=CONFIG)
        assert started.num_envs == N and started.max_steps == 12
        obs_dim = EnvConfig(**CONFIG).obs_dim
        assert started.observation_space.shape == (obs_dim,)
        assert started.action_space.shape == (2,)
        assert np.all(started.action_space.low == -1) and np.all(started.action_space.high == 1)
        assert started.env_config["grid_size"] == 8
        close(started.observations, ref[0])
        ended = 0
        for a, (obs, reward, term, trunc, final) in zip(actions, ref[1:], strict=True):
            t = rc.step(a)
            close(t.observations, obs)
            close(t.rewards, reward)
            np.testing.assert_array_equal(t.terminated, term)
            np.testing.assert_array_equal(t.truncated, trunc)
            # auto-reset: exactly the envs that ended carry their final observation
            np.testing.assert_array_equal(t.done_indices, np.flatnonzero(term | trunc))
            close(t.final_observations, final[term | trunc])
            assert np.all(started.observation_space.low <= t.observations)
            assert np.all(t.observations <= started.observation_space.high)
            ended += t.done_indices.size
        assert ended >= N * 2  # max_steps=12 over 30 steps: every env ended at least twice
        closed = rc.close()
    assert closed.steps == 30 and closed.env_steps == 30 * N and closed.episodes == ended


def test_rollout__truncated_envs_restart_and_final_obs_is_the_last_pose(server):
    with RolloutClient(_target(server)) as rc:
        rc.start(num_envs=N, seed=1, config=CONFIG)
        prev = None
        for i in range(12):
            t = rc.step(np.zeros((N, 2), np.float32))  # standing still: only truncation ends it
            if i < 11:
                assert t.done_indices.size == 0
                prev = t.observations
        assert np.all(t.truncated) and not np.any(t.terminated)
        np.testing.assert_array_equal(t.done_indices, np.arange(N))
        np.testing.assert_allclose(t.final_observations, prev)  # the robot did not move
        assert not np.allclose(t.observations[:, :2], prev[:, :2])  # new episodes, new starts


def test_rollout__reset_with_a_seed_repeats_the_episodes(server):
    with RolloutClient(_target(server)) as rc:
        first = rc.start(num_envs=N, seed=3, config=CONFIG).observations
        rc.step(_actions(np.random.default_rng(1)))
        again = rc.reset(seed=3)
        other = rc.reset(seed=4)
    np.testing.assert_array_equal(again, first)
    assert not np.array_equal(first, other)


def _code(fn) -> tuple[grpc.StatusCode, str]:
    with pytest.raises(RolloutError) as e:
        fn()
    return e.value.code, e.value.message


def test_rollout__errors_are_exact_status_codes(server):
    t = _target(server)

    def step_before_start():
        with RolloutClient(t) as rc:
            rc.step(np.zeros((1, 2), np.float32))

    code, msg = _code(step_before_start)
    assert code == grpc.StatusCode.FAILED_PRECONDITION and "Start" in msg

    def session(action):
        with RolloutClient(t) as rc:
            rc.start(num_envs=N, config=CONFIG)
            rc.step(action)

    code, msg = _code(lambda: session(np.zeros((N + 1, 2), np.float32)))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "[5, 2]" in msg and "[4, 2]" in msg
    nan = np.zeros((N, 2), np.float32)
    nan[2, 1] = np.nan
    code, msg = _code(lambda: session(nan))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "NaN" in msg and "[2]" in msg

    def start(**kw):
        with RolloutClient(t) as rc:
            rc.start(**kw)

    code, msg = _code(lambda: start(num_envs=N, config={**CONFIG, "grid_size": 2}))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "start.config.grid_size" in msg
    code, msg = _code(lambda: start(num_envs=N, config={**CONFIG, "bogus": 1}))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "bogus" in msg
    code, msg = _code(lambda: start(num_envs=65, config=CONFIG))
    assert code == grpc.StatusCode.RESOURCE_EXHAUSTED and "1..64" in msg and "MAX_ENVS" in msg

    def start_twice():
        with RolloutClient(t) as rc:
            rc.start(num_envs=N, config=CONFIG)
            rc.start(num_envs=N, config=CONFIG)

    code, msg = _code(start_twice)
    assert code == grpc.StatusCode.FAILED_PRECONDITION and "already" in msg

    # the session still works after all of that
    with RolloutClient(t) as rc:
        rc.start(num_envs=N, config=CONFIG)
        assert rc.step(np.zeros((N, 2), np.float32)).observations.shape[0] == N


def test_rollout__a_robot_that_fits_the_checked_rooms_but_not_a_later_one_is_invalid_argument(
    server, monkeypatch
):
    """Admission checks a wide robot against the first rooms of each bank (FIT_ROOMS); the env
    build checks every room, and a room past those is still the Start's mistake, named, not an
    INTERNAL error. Room 6 of CONFIG's train bank has no two cells a 0.9 m robot fits in."""
    import quicknav_service.jobs.limits as limits

    monkeypatch.setattr(limits, "FIT_ROOMS", 4)

    def start():
        with RolloutClient(_target(server)) as rc:
            rc.start(num_envs=N, config={**CONFIG, "robot_radius": 0.9})

    code, msg = _code(start)
    assert code == grpc.StatusCode.INVALID_ARGUMENT, msg
    assert msg.startswith("start.config.robot_radius: a robot of radius 0.9 m") and "(room 6 first)" in msg, msg


def test_rollout__hostile_starts_are_invalid_argument_not_internal(server):
    """A client's mistake is INVALID_ARGUMENT, however it is made: JSON nested 100,000 deep, a
    Struct holding NaN."""
    from quicknav_client.proto.quicknav.v1 import rollout_pb2_grpc as pb_grpc

    nan = pb.Start(num_envs=1)
    nan.config_fields.update({"grid_size": float("nan")})
    starts = {
        "deep JSON": pb.Start(num_envs=1, config_json="[" * 100_000 + "]" * 100_000),
        "deep object": pb.Start(num_envs=1, config_json='{"a":' * 100_000 + "1" + "}" * 100_000),
        "NaN in a Struct": nan,
    }
    with grpc.insecure_channel(_target(server)) as channel:
        stub = pb_grpc.RolloutServiceStub(channel)
        for what, start in starts.items():
            with pytest.raises(grpc.RpcError) as e:
                list(stub.Rollout(iter([pb.AgentMessage(start=start)]), timeout=30))
            assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT, (what, e.value.details())
            assert "start.config" in e.value.details(), what


@pytest.mark.parametrize("method,message", [("/quicknav.v1.RolloutService/Rollout", "AgentMessage"),
                                            ("/quicknav.v1.PolicyService/Act", "PolicyRequest")])  # fmt: skip
def test_streams__corrupt_protobuf_is_invalid_argument_and_the_server_serves_on(server, method, message):
    """Bytes that are not the stream's message (a truncated varint, another message type's bytes)
    are the client's mistake: INVALID_ARGUMENT naming the message, not INTERNAL."""
    with grpc.insecure_channel(_target(server)) as channel:
        raw = channel.stream_stream(method, request_serializer=lambda b: b,
                                    response_deserializer=lambda b: b)  # fmt: skip
        for junk in (b"\x0a\xff\xff\xff\xff\x0f", b"\x0a\x05\x01"):
            with pytest.raises(grpc.RpcError) as e:
                list(raw(iter([junk]), timeout=30))
            assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT, e.value.details()
            assert f"not a quicknav.v1.{message}" in e.value.details()
    with RolloutClient(_target(server)) as rc:
        rc.start(num_envs=N, config=CONFIG)
        assert rc.step(np.zeros((N, 2), np.float32)).observations.shape[0] == N


def test_rollout__policy_job_that_does_not_exist_is_not_found(server):
    rc = RolloutClient(_target(server))
    rc.start(num_envs=2, config=CONFIG, policy_job="no-such-job")
    code, msg = _code(lambda: list(rc.policy_frames()))
    assert code == grpc.StatusCode.NOT_FOUND and "no-such-job" in msg
    assert "/" not in msg  # no server path in what a client reads


def test_rollout__session_limit_is_resource_exhausted(server):
    clients = [RolloutClient(_target(server)) for _ in range(3)]
    try:
        for c in clients:
            c.start(num_envs=N, config=CONFIG)

        def fourth():
            with RolloutClient(_target(server)) as rc:
                rc.start(num_envs=N, config=CONFIG)

        code, msg = _code(fourth)
        assert code == grpc.StatusCode.RESOURCE_EXHAUSTED and "ROLLOUT_MAX_SESSIONS" in msg
    finally:
        for c in clients:
            c.close()
    deadline = time.time() + 5  # the slots come back once the streams end
    while server.servicer.active_sessions and time.time() < deadline:
        time.sleep(0.05)
    assert server.servicer.active_sessions == 0


def test_rollout__open_streams_together_stay_within_the_servers_memory_budget(tmp_path):
    """QUICKNAV_ROLLOUT_MEMORY_MB: each stream's estimate alone fits any budget, but the server
    holds its runtime once and every open stream's envs together; a Start that would take the sum
    past the budget is RESOURCE_EXHAUSTED naming the field, the held total and the setting, and a
    stream that ends gives its part back."""
    from quicknav_core.admission import RolloutRequest, stream_estimate
    from quicknav_core.train.memory import MB, megabytes, together

    n = 4096
    est, _ = stream_estimate(RolloutRequest(EnvConfig(**CONFIG), n))
    two, three = together([est] * 2).total, together([est] * 3).total
    assert three - two > 1 * MB  # (the resident envs of 4,096 of them; what the streams add up)
    budget = megabytes(two)  # room for two streams, not three
    settings = Settings(data_dir=tmp_path, host="127.0.0.1", grpc_port=0, rollout_memory_mb=budget)
    srv = BackgroundServer(settings, port=0).start()
    clients = []
    try:
        for _ in range(2):
            clients.append(RolloutClient(_target(srv)))
            clients[-1].start(num_envs=n, config=CONFIG)
        assert srv.servicer.memory.held_mb == megabytes(two)
        # what the server announces (GET /rollout/endpoints, /metrics) says the same
        from quicknav_service.rollout.announce import EndpointAnnouncer

        said = EndpointAnnouncer(None, "w", "a:1", srv.servicer, 1.0, 16, probe_device=False).endpoint()
        assert (said["memory_held_mb"], said["memory_budget_mb"]) == (megabytes(two), budget)

        def third():
            with RolloutClient(_target(srv)) as rc:
                rc.start(num_envs=n, config=CONFIG)

        code, msg = _code(third)
        assert code == grpc.StatusCode.RESOURCE_EXHAUSTED, msg
        assert msg.startswith("start.num_envs: this stream adds about") and "2 open stream(s)" in msg
        assert f"above the {budget:,} MB this server gives its streams (QUICKNAV_ROLLOUT_MEMORY_MB)" in msg
        clients.pop().close()  # one ends: its part comes back, and a third fits again
        deadline = time.time() + 5
        while srv.servicer.memory.streams > 1 and time.time() < deadline:
            time.sleep(0.05)
        clients.append(RolloutClient(_target(srv)))
        clients[-1].start(num_envs=n, config=CONFIG)
        assert srv.servicer.memory.streams == 2
    finally:
        for c in clients:
            c.close()
        srv.stop()
    assert srv.servicer.memory.streams == 0 and srv.servicer.memory.held_mb == 0


def test_rollout__token_and_idle_timeout(strict_server):
    t = _target(strict_server)
    code, msg = _code(lambda: RolloutClient(t).start(num_envs=1, config=CONFIG))
    assert code == grpc.StatusCode.UNAUTHENTICATED and "authorization" in msg
    code, _ = _code(lambda: RolloutClient(t, token="wrong-token").start(num_envs=1, config=CONFIG))
    assert code == grpc.StatusCode.UNAUTHENTICATED
    rc = RolloutClient(t, token="s3cret-token")
    rc.start(num_envs=1, config=CONFIG)
    time.sleep(1.0)  # longer than rollout_idle_s=0.5
    code, msg = _code(lambda: rc.step(np.zeros((1, 2), np.float32)))
    assert code == grpc.StatusCode.DEADLINE_EXCEEDED and "ROLLOUT_IDLE_S" in msg


def test_rollout__concurrent_streams_are_isolated(server):
    rng = np.random.default_rng(5)
    plans = {seed: [_actions(rng) for _ in range(20)] for seed in (11, 12)}

    def run(seed, out):
        with RolloutClient(_target(server)) as rc:
            rows = [rc.start(num_envs=N, seed=seed, config=CONFIG).observations]
            for a in plans[seed]:
                rows.append(rc.step(a).observations)
                time.sleep(0.001)  # interleave the two streams
        out[seed] = np.stack(rows)

    together: dict[int, np.ndarray] = {}
    threads = [threading.Thread(target=run, args=(s, together)) for s in plans]
    for th in threads:
        th.start()
    for th in threads:
        th.join(60)
    for seed, actions in plans.items():
        ref = _reference(seed, N, actions)
        alone = np.stack([ref[0]] + [r[0] for r in ref[1:]])
        close(together[seed], alone)


def test_rollout__policy_mode_streams_a_trained_jobs_episodes(server):
    from quicknav_core.config import TrainConfig
    from quicknav_core.train import train_run

    cfg = TrainConfig.model_validate({
        "env": {"grid_size": 8, "train_rooms": 32, "test_rooms": 16, "max_steps": 40},
        "algorithm": {"name": "ppo", "num_steps": 16, "num_minibatches": 2, "num_epochs": 1},
        "network": {"kind": "mlp", "hidden_sizes": [16]},
        "num_envs": 8, "total_steps": 256, "chunk_steps": 128,
    })  # fmt: skip
    train_run(cfg, server.settings.artifacts_dir / "job-policy")
    rc = RolloutClient(_target(server))
    assert rc.start(num_envs=3, seed=2, split="test", policy_job="job-policy") is None
    frames = list(rc.policy_frames())
    first, last = frames[0], frames[-1]
    assert [f.step for f in frames] == list(range(len(frames)))
    assert first.walls.shape == (3, 8, 8) and first.goals.shape == (3, 2)
    assert first.actions.shape == (0, 2) and frames[1].actions.shape == (3, 2)
    assert all(f.poses.shape == (3, 3) and f.lidar.shape == (3, 16) for f in frames)
    assert np.all(np.abs(np.stack([f.actions for f in frames[1:]])) <= 1.0)
    assert last.done.all() and len(frames) - 1 <= 40 and rc.closed.episodes == 3
    # success means the last pose is within the goal radius (0.3 m) of the goal
    dist = np.linalg.norm(last.poses[:, :2] - first.goals, axis=1)
    np.testing.assert_array_equal(last.success, dist <= 0.3 + 1e-5)
    # poses stay inside the room, off the walls' cells
    cell = 1.0  # room_size 8 m / grid_size 8
    for f in frames:
        rc_ = np.floor(f.poses[:, 1::-1] / cell).astype(int)
        assert not first.walls[np.arange(3), rc_[:, 0], rc_[:, 1]].any()
    # the Start's fields apply to the env the policy trained in (once validated and then
    # dropped): episodes cut at max_steps=5, in that env's 8x8 rooms
    rc = RolloutClient(_target(server))
    rc.start(num_envs=2, seed=2, split="test", policy_job="job-policy", config={"max_steps": 5})
    frames = list(rc.policy_frames())
    assert len(frames) - 1 <= 5 and frames[0].walls.shape == (2, 8, 8)
    # a field that changes what the policy reads is refused, naming it
    rc = RolloutClient(_target(server))
    rc.start(num_envs=2, policy_job="job-policy", config={"lidar_beams": 8})
    code, msg = _code(lambda: list(rc.policy_frames()))
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "lidar_beams=16" in msg, msg


# --------------------------------------------------------------------------- asynchronous mode
def test_rollout__async_groups_each_step_as_their_own_lock_step_session(server):
    """groups=2: each group of N envs is exactly a lock-step session of N envs with its group's
    seed, whatever order the groups are sent and come back in; totals count every group."""
    from quicknav_service.rollout.servicer import group_seed

    rng = np.random.default_rng(3)
    plans = [[_actions(rng) for _ in range(14)] for _ in range(2)]
    refs = [_reference(group_seed(7, g), N, plans[g]) for g in range(2)]
    got: list[list] = [[], []]
    with RolloutClient(_target(server)) as rc:
        started = rc.start(num_envs=2 * N, seed=7, config=CONFIG, groups=2)
        assert started.groups == 2 and started.observations.shape[0] == 2 * N
        for g in range(2):
            close(rc.group_observations(started.observations, g), refs[g][0])
        rc.send(plans[1][0], group=1)  # group 1 first, then group 0
        rc.send(plans[0][0], group=0)
        sent = [1, 1]
        while len(got[0]) + len(got[1]) < 28:
            t = rc.recv()
            got[t.group].append(t)
            assert t.step_count == len(got[t.group]) and t.observations.shape[0] == N
            if sent[t.group] < 14:
                rc.send(plans[t.group][sent[t.group]], group=t.group)
                sent[t.group] += 1
            if t.group == 0 and len(got[0]) % 3 == 0:
                time.sleep(0.01)  # the agent is slow on group 0 now and then: group 1 runs ahead
        closed = rc.close()
    for g in range(2):
        for t, (obs, reward, term, trunc, final) in zip(got[g], refs[g][1:], strict=True):
            close(t.observations, obs)
            close(t.rewards, reward)
            np.testing.assert_array_equal(t.terminated, term)
            np.testing.assert_array_equal(t.done_indices, np.flatnonzero(term | trunc))
            close(t.final_observations, final[term | trunc])
    ended = sum(t.done_indices.size for g in range(2) for t in got[g])
    assert closed.steps == 28 and closed.env_steps == 28 * N and closed.episodes == ended


def test_rollout__async_refusals_name_the_group(server):
    code, msg = _code(lambda: RolloutClient(_target(server)).start(num_envs=6, config=CONFIG,
                                                                    groups=4))  # fmt: skip
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "start.groups=4" in msg
    rc = RolloutClient(_target(server))
    rc.start(num_envs=4, config=CONFIG, groups=2)
    rc.send(np.zeros((2, 2), np.float32), group=0)
    # a second Step for the same group before its Transition (past the client's own check)
    rc._outbox.put(pb.AgentMessage(step=pb.Step(actions=encode(np.zeros((2, 2), np.float32)),
                                                group=0)))  # fmt: skip
    code, msg = _code(lambda: [rc.recv(), rc.recv()])
    assert code == grpc.StatusCode.FAILED_PRECONDITION and "step.group=0" in msg, msg
    rc = RolloutClient(_target(server))
    rc.start(num_envs=4, config=CONFIG, groups=2)
    rc.send(np.zeros((2, 2), np.float32), group=2)
    code, msg = _code(rc.recv)
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "allowed range 0..1" in msg
    rc = RolloutClient(_target(server))
    rc.start(num_envs=4, config=CONFIG)
    rc._outbox.put(pb.AgentMessage(step=pb.Step(actions=encode(np.zeros((4, 2), np.float32)),
                                                group=1)))  # fmt: skip
    code, msg = _code(rc._next)
    assert code == grpc.StatusCode.INVALID_ARGUMENT and "lock-step" in msg


def test_rollout__async_reset_with_a_seed_repeats_every_group(server):
    with RolloutClient(_target(server)) as rc:
        first = rc.start(num_envs=2 * N, seed=5, config=CONFIG, groups=2).observations
        rc.send(_actions(np.random.default_rng(2)), group=1)
        with pytest.raises(RuntimeError, match="in flight"):
            rc.reset(seed=5)
        rc.recv()
        np.testing.assert_array_equal(rc.reset(seed=5), first)


def test_gym__remote_vector_env_async_send_recv(server):
    """EnvPool's interface on the gymnasium adapter: recv the ready group, send its actions."""
    from quicknav_client.gym import RemoteVectorEnv

    env = RemoteVectorEnv(_target(server), num_envs=2 * N, config=CONFIG, seed=4, groups=2)
    env.async_reset()
    seen = {0: 0, 1: 0}
    for _ in range(12):
        obs, rew, term, trunc, info = env.recv()
        ids = info["env_id"]
        assert obs.shape == (N, env.single_observation_space.shape[0]) and rew.shape == (N,)
        assert ids.tolist() in (list(range(N)), list(range(N, 2 * N)))
        seen[int(ids[0]) // N] += 1
        env.send(np.zeros((N, 2), np.float32), ids)
    assert seen[0] >= 3 and seen[1] >= 3
    with pytest.raises(ValueError, match="one group's ids"):
        env.send(np.zeros((N, 2), np.float32), np.arange(1, N + 1))
    env.close()


def test_rollout_client__a_config_string_that_is_no_json_object_is_refused_before_sending():
    """``config`` as a string is an EnvConfig's JSON text; a preset's name or a file's path is
    refused in the client, saying what it takes (no server is needed to say so)."""
    client = RolloutClient("127.0.0.1:9")  # nothing listens: nothing is sent
    try:
        for wrong in ("building", "env.json"):
            with pytest.raises(ValueError, match=rf"config='{wrong}': an EnvConfig as a dict of fields or the"
                                                 " text of its JSON object.*--print-config"):  # fmt: skip
                client.start(num_envs=2, config=wrong)
    finally:
        client.close()
