"""The gymnasium adapters over a real gRPC channel: env checker, parity with the local JAX env."""

from __future__ import annotations

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode
from quicknav_client.gym import RemoteEnv, RemoteVectorEnv

from quicknav_service.rollout.server import BackgroundServer
from quicknav_service.settings import Settings
from tests.service.test_rollout import CONFIG, _reference, close

N = 4


@pytest.fixture(scope="module")
def target(tmp_path_factory):
    settings = Settings(data_dir=tmp_path_factory.mktemp("data"), host="127.0.0.1", grpc_port=0)
    srv = BackgroundServer(settings, port=0).start()
    yield f"127.0.0.1:{srv.port}"
    srv.stop()


def test_remote_env__passes_gymnasium_env_checker(target):
    env = RemoteEnv(target, config=CONFIG, seed=0)
    try:
        check_env(env, skip_render_check=True)
        obs, _ = env.reset(seed=5)
        assert env.observation_space.contains(obs)
        ended = False
        for _ in range(CONFIG["max_steps"]):
            obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
            assert env.observation_space.contains(obs) and isinstance(info["collision"], bool)
            if terminated or truncated:
                ended = True
                break
        assert ended  # max_steps=12 truncates at the latest
    finally:
        env.close()


def test_remote_vector_env__matches_the_local_jax_env(target):
    rng = np.random.default_rng(3)
    actions = [rng.uniform(-1, 1, (N, 2)).astype(np.float32) for _ in range(30)]
    ref = _reference(9, N, actions)
    env = RemoteVectorEnv(target, num_envs=N, config=CONFIG, seed=9)
    try:
        assert env.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
        assert env.observation_space.shape == (N, ref[0].shape[1])
        assert env.action_space.shape == (N, 2)
        obs, _ = env.reset()
        close(obs, ref[0])
        finals = 0
        for a, (r_obs, r_rew, r_term, r_trunc, r_final) in zip(actions, ref[1:], strict=True):
            obs, rew, term, trunc, info = env.step(a)
            close(obs, r_obs)
            close(rew, r_rew)
            np.testing.assert_array_equal(term, r_term)
            np.testing.assert_array_equal(trunc, r_trunc)
            done = r_term | r_trunc
            if done.any():
                np.testing.assert_array_equal(info["_final_obs"], done)
                for i in np.flatnonzero(done):
                    close(info["final_obs"][i], r_final[i])
                finals += int(done.sum())
            else:
                assert "final_obs" not in info
        assert finals >= N
        # a seeded reset repeats the episodes of that seed
        a1, _ = env.reset(seed=21)
        a2, _ = env.reset(seed=21)
        np.testing.assert_array_equal(a1, a2)
        with pytest.raises(ValueError, match="one int seed"):
            env.reset(seed=[1, 2, 3, 4])
    finally:
        env.close()
