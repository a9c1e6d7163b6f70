"""One training run over several devices (TrainConfig.devices): the env batch is split over the
devices, parameters replicated, and the run learns what the one-device run learns, up to the order
of float reductions. Two XLA CPU devices stand in for two GPUs (a subprocess, since the device count
is fixed when JAX starts)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from fastapi.testclient import TestClient

from quicknav_core.config import TrainConfig
from quicknav_core.train.trainers import make_trainer
from tests.compile_settings import with_cpu_devices

_TWO_DEVICES = """
import json, sys
import jax, numpy as np
from quicknav_core.config import TrainConfig
from quicknav_core.train.trainers import make_trainer

assert jax.local_device_count() == 2
split = jax.sharding.PartitionSpec("envs")
report = {}
for net in ("mlp", "lstm"):
    base = {"env": {"grid_size": 8, "room_size": 4.0, "train_rooms": 32, "test_rooms": 8,
                    "lidar_beams": 8, "max_steps": 20},
            "algorithm": {"name": "ppo", "num_steps": 16, "num_minibatches": 4, "num_epochs": 2},
            "network": {"kind": net, **({"hidden_sizes": [16, 16]} if net == "mlp" else {})},
            "num_envs": 8, "total_steps": 8 * 16 * 4, "chunk_steps": 8 * 16, "seed": 3}
    runs = {}
    for devices in (1, 2):
        trainer = make_trainer(TrainConfig.model_validate({**base, "devices": devices}))
        state = trainer.init_state()
        curve = []
        for _ in range(4):
            state, metrics = trainer.run_chunk(state)
            curve.append(metrics)
        leaves = jax.tree_util.tree_leaves_with_path(state)
        runs[devices] = {
            "kind": type(trainer).__name__,
            "curve": curve,
            "leaves": [np.asarray(jax.device_get(l), np.float64).ravel().tolist()
                       for _, l in leaves if np.asarray(l).dtype.kind == "f"],
            "split": sorted(jax.tree_util.keystr(p) for p, l in leaves
                            if getattr(l.sharding, "spec", None) == split),
            "on_devices": sorted({len(l.sharding.device_set) for _, l in leaves}),
        }
    report[net] = runs
json.dump(report, sys.stdout)
"""


@pytest.fixture(scope="module")
def two_device_runs():
    env = with_cpu_devices(2)
    out = subprocess.run([sys.executable, "-c", _TWO_DEVICES], env=env, capture_output=True,
                         text=True, timeout=600)  # fmt: skip
    assert out.returncode == 0, out.stderr[-4000:]
    return json.loads(out.stdout)


@pytest.mark.parametrize("net,kind", [("mlp", "RejaxTrainer"), ("lstm", "RecurrentPPOTrainer")])
def test_data_parallel__two_devices_learn_the_one_device_curve(two_device_runs, net, kind):
    one, two = two_device_runs[net]["1"], two_device_runs[net]["2"]
    assert one["kind"] == two["kind"] == kind
    assert len(one["curve"]) == len(two["curve"]) == 4
    for a, b in zip(one["curve"], two["curve"], strict=True):
        assert a.keys() == b.keys()
        for k in a:
            if a[k] is None or (isinstance(a[k], float) and np.isnan(a[k])):
                assert b[k] is None or np.isnan(b[k]), k
            else:
                np.testing.assert_allclose(b[k], a[k], rtol=1e-3, atol=1e-5, err_msg=k)
    assert sum(r["episodes"] for r in one["curve"]) > 0  # episodes ended: the curve is not empty
    for a, b in zip(one["leaves"], two["leaves"], strict=True):  # params, optimiser, env state
        np.testing.assert_allclose(b, a, rtol=1e-3, atol=1e-4)
    # the env batch really was split: env state and observations per device, the rest replicated
    assert one["split"] == [] and one["on_devices"] == [1]
    assert two["on_devices"] == [2]
    assert any(".env_state" in p for p in two["split"]) and any("obs" in p for p in two["split"])
    assert not [p for p in two["split"] if "params" in p or "opt_state" in p]


def test_data_parallel__more_devices_than_the_process_has_is_refused_before_compiling():
    cfg = TrainConfig(devices=2, num_envs=8, total_steps=8 * 128)  # this process has one CPU device
    with pytest.raises(ValueError, match=r"devices=2 but this process sees 1 cpu device\(s\); allowed: 1..1"):
        make_trainer(cfg)


def test_data_parallel__device_count_must_divide_the_env_batch():
    with pytest.raises(ValueError, match=r"devices=3 must divide num_envs=64.*allowed: 1, 2, 4, 8"):
        TrainConfig(devices=3)
    assert TrainConfig(devices="all").devices == "all"


def test_data_parallel__api_refuses_more_devices_than_its_workers_have(tmp_path):
    from quicknav_service.api.main import create_app
    from quicknav_service.settings import Settings

    client = TestClient(create_app(Settings(_env_file=None, data_dir=tmp_path, max_devices=2),
                                   start_workers=False))  # fmt: skip
    ok = client.post("/jobs/train", json={"preset": "demo", "overrides": {"devices": 2}})
    assert ok.status_code == 202 and ok.json()["config"]["devices"] == 2
    too_many = client.post("/jobs/train", json={"preset": "demo", "overrides": {"devices": 4}})
    assert too_many.status_code == 422
    (err,) = too_many.json()["detail"]
    assert err["loc"] == ["body", "overrides", "devices"] and "allowed: 1..2" in err["msg"]
    odd = client.post("/jobs/train", json={"preset": "demo", "overrides": {"devices": 3}})
    assert odd.status_code == 422 and odd.json()["detail"][0]["loc"] == ["body", "overrides", "devices"]
    assert "must divide num_envs=64" in odd.json()["detail"][0]["msg"]
