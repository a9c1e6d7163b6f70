"""`quicknav export`: every network kind to ONNX, held to the JAX policy by onnxruntime on 10,000
random observations and along 20 held-out episodes driven side by side (recurrent state carried
through whole episodes), and the manifest a robot's code reads."""

from __future__ import annotations

import itertools
import json
import subprocess
import sys

import numpy as np
import pytest

from quicknav_core import export as ex
from quicknav_core.config import resolve_train
from quicknav_core.train.run import load_run, train_run

SMALL = {"env.grid_size": 8, "env.train_rooms": 16, "env.test_rooms": 8, "env.lidar_beams": 8}
# (kind, preset, overrides)
KINDS = {
    "ppo-mlp": ("demo", {"num_envs": 16, "algorithm.num_steps": 32, "total_steps": 1024}),
    "sac-mlp": ("paper-sac", {"num_envs": 16, "total_steps": 4096}),
    "td3-mlp": ("paper-td3", {"num_envs": 16, "total_steps": 4096}),
    "mlp-memory": ("paper-mlp", {"num_envs": 16, "algorithm.num_steps": 16, "total_steps": 512}),
    # the building preset's network: an MLP reading the observation before this one too
    "mlp-frames": ("paper-mlp", {"num_envs": 16, "algorithm.num_steps": 16, "total_steps": 512,
                                 "network.memory_size": 0, "network.frames": 2}),
    # frames two steps apart: state_0 holds the last two observations
    "mlp-strided": ("paper-mlp", {"num_envs": 16, "algorithm.num_steps": 16, "total_steps": 512,
                                  "network.memory_size": 0, "network.frames": 2,
                                  "network.frame_stride": 2}),
    "lstm": ("paper-lstm", {"num_envs": 16, "algorithm.num_steps": 16, "total_steps": 512}),
    "gtrxl": ("paper-gtrxl", {"num_envs": 16, "algorithm.num_steps": 16, "total_steps": 512}),
}


@pytest.fixture(scope="module", params=list(KINDS))
def exported(request, tmp_path_factory):
    """Each kind's policy exported. The PPO one goes the whole way from a trained run folder
    (``export_run``); the others export their initial parameters, which exercise the same
    conversion without compiling a trainer's update for each kind."""
    from quicknav_core.train.trainers import make_trainer

    preset, overrides = KINDS[request.param]
    cfg = resolve_train({"preset": preset, "overrides": {**SMALL, **overrides}})
    root = tmp_path_factory.mktemp(request.param)
    out = root / "policy"
    if request.param == "ppo-mlp":
        run_dir = root / "run"
        train_run(cfg, run_dir)
        doc = ex.export_run(run_dir, out, provenance={"job_id": "test"})
        config, trainer, state, _ = load_run(run_dir)
        return request.param, config, trainer.policy(state), out, doc
    trainer = make_trainer(cfg)
    policy = trainer.policy(trainer.init_state())
    out.mkdir()
    (out / ex.ONNX_FILE).write_bytes(ex.to_onnx_model(policy, cfg.env.obs_dim).SerializeToString())
    doc = ex.manifest(cfg, policy, {"env_steps": 0}, {"job_id": "test", "env_steps": 0}, None)
    (out / ex.MANIFEST_FILE).write_text(json.dumps(doc, indent=2))
    return request.param, cfg, policy, out, doc


def test_export__onnx_matches_jax_on_ten_thousand_random_observations(exported):
    kind, config, policy, out, _ = exported
    worst = ex.check_parity(policy, out / ex.ONNX_FILE, config.env.obs_dim, samples=10_000,
                            env_config=config.env)  # fmt: skip
    assert worst <= 1e-5, f"{kind}: max |action or state difference| {worst:.2e}"


def test_export__same_actions_along_twenty_held_out_episodes(exported):
    kind, config, policy, out, _ = exported
    r = ex.check_episodes(policy, out / ex.ONNX_FILE, config.env, episodes=20)
    # every step of every episode, the recurrent state carried on both sides
    assert r["max_action_diff"] <= 1e-5, (kind, r)
    # driven alone, the ONNX model ends the episodes as the JAX policy does (success, steps);
    # one may drift where a contact amplifies float rounding
    assert r["same_outcome"] >= 19 and abs(r["success_jax"] - r["success_onnx"]) <= 1, (kind, r)


def test_export__dynamic_batch_and_the_manifest_a_robot_reads(exported):
    kind, config, policy, out, doc = exported
    session = ex.onnx_session(out / ex.ONNX_FILE)
    names = [i.name for i in session.get_inputs()]
    assert names == doc["onnx"]["inputs"] and [o.name for o in session.get_outputs()] == doc["onnx"]["outputs"]
    assert all(i.shape[0] == "B" for i in session.get_inputs())  # a dynamic batch axis
    on_disk = json.loads((out / ex.MANIFEST_FILE).read_text())
    assert on_disk == doc
    # the observation layout covers every entry once, in order
    layout = doc["observation"]["layout"]
    edges = [s["slice"] for s in layout]
    assert edges[0][0] == 0 and edges[-1][1] == doc["observation"]["size"] == config.env.obs_dim
    assert all(a[1] == b[0] for a, b in itertools.pairwise(edges))
    assert len(doc["lidar"]["beam_angles_rad"]) == config.env.lidar_beams
    assert doc["action"]["max_wheel_speed_mps"] == config.env.max_wheel_speed
    assert doc["provenance"]["job_id"] == "test"
    assert doc["provenance"]["env_steps"] > 0 or kind != "ppo-mlp"  # the trained run says how far
    assert doc["env"] == config.env.model_dump(mode="json")
    assert doc["recurrent"] == (kind in ("mlp-memory", "mlp-frames", "mlp-strided", "lstm", "gtrxl"))
    # any batch size runs; a state starts from its documented initial value
    for batch in (1, 7):
        rng = np.random.default_rng(batch)
        feed = {"obs": ex.random_observations(config.env, batch, seed=batch)}
        if doc["recurrent"]:
            feed["start"] = np.ones(batch, bool)
            for s in doc["state"]:
                shape = [batch, *s["shape"][1:]]
                dtype = np.dtype(s["dtype"])
                random = rng.random(shape) > 0.5 if dtype == np.bool_ else rng.normal(size=shape)
                feed[s["input"]] = random.astype(dtype)
        action, *state = session.run(None, feed)
        assert action.shape == (batch, 2) and np.all(np.abs(action) <= 1.0)
        if doc["recurrent"]:  # start=True: the state given was replaced by the initial one first
            fresh = {**feed, **{s["input"]: np.full([batch, *s["shape"][1:]], s["initial"],
                                                   np.dtype(s["dtype"])) for s in doc["state"]}}  # fmt: skip
            again, *_ = session.run(None, fresh)
            np.testing.assert_array_equal(action, again)
            assert [x.shape for x in state] == [(batch, *s["shape"][1:]) for s in doc["state"]]


def test_export__held_out_success_joins_the_manifest_only_from_the_trained_env(tmp_path):
    env = {"grid_size": 8}
    (tmp_path / ex.MANIFEST_FILE).write_text(json.dumps({"env": env, "held_out": None}))
    metrics = {"episodes": 100, "success_rate": 0.97, "success_ci95": [0.9, 0.99], "spl": 0.9, "x": 1}
    assert not ex.record_held_out(tmp_path, metrics, {"eval_job_id": "e"}, {"grid_size": 16})
    assert json.loads((tmp_path / ex.MANIFEST_FILE).read_text())["held_out"] is None
    assert ex.record_held_out(tmp_path, metrics, {"eval_job_id": "e"}, env)
    held = json.loads((tmp_path / ex.MANIFEST_FILE).read_text())["held_out"]
    assert held == {"eval_job_id": "e", "episodes": 100, "success_rate": 0.97,
                    "success_ci95": [0.9, 0.99], "spl": 0.9}  # fmt: skip


def test_export__imports_only_the_converters_plugins_for_flax_and_jax():
    """The first conversion imports jax2onnx's jax and flax plugins, not its equinox plugins and
    examples (seconds of every export, none of them used); a conversion after it still works (the
    module fixture's exports of every network kind check that it is the JAX policy)."""
    code = (
        "import sys\n"
        "from quicknav_core.export import import_onnx_plugins\n"
        "from jax2onnx.plugins import plugin_system\n"
        "import_onnx_plugins()\n"
        "print(plugin_system._already_imported_plugins,"
        " 'jax2onnx.plugins.flax.linen.dense' in sys.modules,"
        " any(m.startswith(('jax2onnx.plugins.equinox', 'jax2onnx.plugins.examples'))"
        " for m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["True", "True", "False"], out.stdout


def test_export__a_map_for_the_robot_is_its_map_server_yaml(tmp_path):
    """`export --map` takes the map_server .yaml: its origin is the robot's map frame, which a
    picture alone lacks. Refused before the run is read, naming the map and what to give."""
    from quicknav_core.env.maps import MapError
    from quicknav_core.export import export_run

    with pytest.raises(MapError, match=r"plan\.png: export --map takes the map_server \.yaml the robot"
                                       r" localises in.*write one naming the picture"):  # fmt: skip
        export_run(tmp_path / "no-run", tmp_path / "out", map_path=tmp_path / "plan.png")
    assert not (tmp_path / "out").exists()
    # the command says so before it announces a minute of tracing
    from typer.testing import CliRunner

    from quicknav_cli.main import app

    (tmp_path / "run").mkdir()
    r = CliRunner().invoke(app, ["export", str(tmp_path / "run"), "--map", str(tmp_path / "plan.png"),
                                 "--out", str(tmp_path / "out")])  # fmt: skip
    assert r.exit_code == 2 and "export --map takes the map_server .yaml" in r.output, r.output
    assert "exporting" not in r.output, r.output
