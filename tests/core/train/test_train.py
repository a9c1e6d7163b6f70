"""Trainers: the recurrent-PPO invariant, every algorithm x network trains, learning, checkpoints."""

import json
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from typer.testing import CliRunner

from quicknav_cli.main import app
from quicknav_core.config import TrainConfig, get_preset
from quicknav_core.networks import gaussian_log_prob
from quicknav_core.train import make_trainer, read_metrics, train_run
from quicknav_core.train.recurrent_ppo import RecurrentPPO

TINY_ENV = {"grid_size": 8, "lidar_beams": 8, "train_rooms": 32, "test_rooms": 16, "max_steps": 40}


def tiny(network, algorithm=None, **kw):
    data = {
        "env": TINY_ENV, "network": network,
        "algorithm": algorithm or {"name": "ppo", "num_steps": 16, "num_minibatches": 2, "num_epochs": 2},
        "num_envs": 8, "total_steps": 8 * 16 * 4, "chunk_steps": 8 * 16 * 2, "seed": 3,
    }  # fmt: skip
    data.update(kw)
    return TrainConfig.model_validate(data)


RECURRENT = {
    "mlp-memory": {"kind": "mlp", "hidden_sizes": [16], "memory_size": 8},
    "mlp-frames": {"kind": "mlp", "hidden_sizes": [16], "frames": 3},
    "lstm": {"kind": "lstm", "num_layers": 2, "hidden_size": 8},
    "gtrxl": {
        "kind": "gtrxl",
        "embed_size": 8,
        "head_size": 4,
        "num_layers": 1,
        "memory_length": 6,
    },
}


@pytest.mark.parametrize("name", list(RECURRENT))
def test_recurrent_ppo__replay_reproduces_acting_log_probs(name):
    trainer = make_trainer(tiny(RECURRENT[name], env={**TINY_ENV, "max_steps": 7}))
    algo: RecurrentPPO = trainer.algo
    state = trainer.init_state()
    state, traj, carry0 = jax.jit(algo.collect)(state)
    starts = np.asarray(traj.start)
    assert starts[0].all() and starts[1:].any(), "the rollout should cross episode boundaries"
    out = jax.jit(algo.replay)(state.params, carry0, traj)
    replayed = gaussian_log_prob(out.mean, out.log_std, traj.action)
    np.testing.assert_allclose(np.asarray(replayed), np.asarray(traj.log_prob), atol=2e-5)
    np.testing.assert_allclose(np.asarray(out.value), np.asarray(traj.value), atol=2e-5)


def _gae_reference(reward, value, done, last_value, gamma, lam):
    """GAE written out step by step in NumPy: (T, B) advantages and value targets."""
    T = reward.shape[0]
    adv = np.zeros_like(reward)
    next_adv, next_value = np.zeros_like(last_value), last_value
    for t in reversed(range(T)):
        live = 1.0 - done[t]
        delta = reward[t] + gamma * next_value * live - value[t]
        next_adv = delta + gamma * lam * live * next_adv
        adv[t], next_value = next_adv, value[t]
    return adv, adv + value


def test_recurrent_ppo__gae_and_explained_variance_match_a_numpy_reference():
    trainer = make_trainer(tiny(RECURRENT["lstm"], env={**TINY_ENV, "max_steps": 7}))
    algo: RecurrentPPO = trainer.algo
    state = trainer.init_state()
    after, traj, _ = jax.jit(algo.collect)(state)
    assert np.asarray(traj.done).any(), "the rollout should end episodes"
    last_value = jax.jit(algo.policy_step, static_argnames="deterministic")(
        after.params, after.carry, after.obs, after.start, after.key, deterministic=True
    )[3]
    gamma, lam = 0.9, 0.8
    adv, targets = jax.jit(algo.gae)(traj, last_value, gamma, lam)
    ref_adv, ref_targets = _gae_reference(
        *(np.asarray(x, np.float64) for x in (traj.reward, traj.value, traj.done, last_value)),
        gamma, lam,
    )  # fmt: skip
    np.testing.assert_allclose(np.asarray(adv), ref_adv, rtol=1e-4, atol=1e-4)
    # the update reports how much of its value targets' variance the critic explained
    state = state.replace(hyper=state.hyper.replace(gamma=jnp.float32(gamma), gae_lambda=jnp.float32(lam)))
    _, metrics = jax.jit(algo.update)(state)
    v = np.asarray(traj.value, np.float64)
    expected = 1.0 - np.var(ref_targets - v) / np.var(ref_targets)
    assert float(metrics["explained_variance"]) == pytest.approx(expected, abs=1e-3)


COMBOS = {
    "ppo-mlp (rejax)": ({"kind": "mlp", "hidden_sizes": [16]}, None),
    "ppo-mlp (quicknav)": ({"kind": "mlp", "hidden_sizes": [16]},
                           {"name": "ppo", "num_steps": 16, "num_minibatches": 2, "num_epochs": 2,
                            "implementation": "quicknav"}),
    **{f"ppo-{k}": (v, None) for k, v in RECURRENT.items()},
    "sac-mlp": ({"kind": "mlp", "hidden_sizes": [16]},
                {"name": "sac", "batch_size": 32, "buffer_size": 512, "fill_buffer": 64}),
    "td3-mlp": ({"kind": "mlp", "hidden_sizes": [16]},
                {"name": "td3", "batch_size": 32, "buffer_size": 512, "fill_buffer": 64}),
}  # fmt: skip


# GTrXL's compile alone takes ~20 s on 2 cores: its combination runs with the slow tests (its
# network and its recurrent PPO replay are checked in the fast ones)
SLOW_COMBOS = {"ppo-gtrxl"}


@pytest.mark.parametrize(
    "combo", [pytest.param(c, marks=pytest.mark.slow) if c in SLOW_COMBOS else c for c in COMBOS]
)
def test_every_algorithm_network_combination_trains_without_nans(combo, tmp_path):
    network, algorithm = COMBOS[combo]
    cfg = tiny(network, algorithm)
    if algorithm and algorithm["name"] in ("sac", "td3"):
        cfg = cfg.model_copy(update={"total_steps": 256, "chunk_steps": 128})
    trainer = make_trainer(cfg)
    summary = train_run(cfg, tmp_path, trainer=trainer)
    assert summary["chunks_done"] == 2
    state = trainer.from_bytes((tmp_path / "checkpoint" / "state.msgpack").read_bytes())
    params = trainer.policy(state).params
    assert all(bool(jnp.isfinite(x).all()) for x in jax.tree.leaves(params))
    for row in read_metrics(tmp_path):
        for key, value in row.items():
            if key not in ("mean_return", "success_rate", "mean_length", "collisions_per_episode"):
                assert np.isfinite(value), (key, value)
    # the policy acts through the shared interface
    policy = trainer.policy(state)
    carry = policy.initial_carry(4)
    _, action = policy.act(
        carry, jnp.zeros((4, trainer.env.obs_dim)), jnp.ones(4, bool), jax.random.PRNGKey(0)
    )
    assert action.shape == (4, 2) and bool((jnp.abs(action) <= 1).all())


@pytest.mark.slow  # trains to a success target: ~20 s on 2 cores
def test_ppo__improves_success_on_an_easy_room(tmp_path):
    cfg = TrainConfig.model_validate({
        "env": {"grid_size": 8, "train_rooms": 64, "test_rooms": 16, "max_steps": 100},
        "algorithm": {"name": "ppo", "learning_rate": 1e-3, "num_steps": 32, "num_minibatches": 4,
                      "num_epochs": 4, "gamma": 0.97, "ent_coef": 0.005},
        "network": {"kind": "mlp", "hidden_sizes": [64, 64]},
        "num_envs": 32, "total_steps": 400_000, "chunk_steps": 32 * 32 * 8, "seed": 0,
    })  # fmt: skip
    train_run(cfg, tmp_path)
    rows = read_metrics(tmp_path)
    first, last = rows[0]["success_rate"], np.mean([r["success_rate"] for r in rows[-3:]])
    assert last > first + 0.2 and last > 0.7, (first, last)


# a recurrent carry across a checkpoint: ~17 s on 2 cores, with the slow tests
@pytest.mark.parametrize("network", ["mlp", pytest.param("lstm", marks=pytest.mark.slow)])
def test_resume__equals_an_uninterrupted_run(network, tmp_path):
    net = {"kind": "mlp", "hidden_sizes": [16]} if network == "mlp" else RECURRENT["lstm"]
    cfg = tiny(net, total_steps=8 * 16 * 6)
    straight = train_run(cfg, tmp_path / "a")
    stopped = train_run(cfg, tmp_path / "b", callback=lambda r: r.chunk == 1)
    assert stopped["stopped"] and stopped["chunks_done"] == 1
    resumed = train_run(cfg, tmp_path / "b", resume=True)
    assert resumed["chunks_done"] == straight["chunks_done"] == 3
    ma, mb = read_metrics(tmp_path / "a"), read_metrics(tmp_path / "b")
    drop = ("wall_s", "steps_per_s")
    assert [{k: v for k, v in r.items() if k not in drop} for r in ma] == [
        {k: v for k, v in r.items() if k not in drop} for r in mb
    ]
    a = (tmp_path / "a" / "checkpoint" / "state.msgpack").read_bytes()
    b = (tmp_path / "b" / "checkpoint" / "state.msgpack").read_bytes()
    assert a == b


def test_same_seed_same_metrics(tmp_path):
    cfg = tiny(RECURRENT["mlp-memory"])
    train_run(cfg, tmp_path / "a")
    train_run(cfg, tmp_path / "b")
    drop = ("wall_s", "steps_per_s")
    clean = lambda rows: [{k: v for k, v in r.items() if k not in drop} for r in rows]  # noqa: E731
    assert clean(read_metrics(tmp_path / "a")) == clean(read_metrics(tmp_path / "b"))
    other = cfg.model_copy(update={"seed": 4})
    train_run(other, tmp_path / "c")
    assert clean(read_metrics(tmp_path / "a")) != clean(read_metrics(tmp_path / "c"))


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--set", "algorithm.num_minibatches=7"], "algorithm.num_minibatches=7 must divide"),
        (["--set", "algorithm.learning_rate=-1"], "--set algorithm.learning_rate: Input should be greater than 0"),
        (["--preset", "nope"], "unknown preset 'nope'"),
        (["--network", "cnn"], "--network 'cnn'"),
        (["--algo", "sac", "--network", "lstm"], "trains memoryless MLPs only"),
        (["--algo", "td3", "--set", "network.frames=2"], "memory_size>0, frames>1 or recurrent"),
        (["--set", "algorithm.implementation=rejax", "--set", "network.frames=2"],
         "needs a memoryless MLP network (network.kind='mlp', memory_size=0, frames=1)"),
        (["--set", "network.frames=2", "--set", "network.memory_size=8"],
         "frames=2 with memory_size=8: an MLP reads past observations or keeps a memory head"),
        (["--set", "network.frames=9"], "network.frames: Input should be less than or equal to 8"),
        (["--set", "network.frame_stride=3"], "frame_stride=3 with frames=1: the stride is the distance"),
        (["--set", "num_envs=0"], "num_envs"),
    ],
)
def test_cli_train__bad_input_fails_before_compiling(args, expected, tmp_path):
    result = CliRunner().invoke(app, ["train", "--out", str(tmp_path / "run"), *args])
    assert result.exit_code == 2, result.output
    assert expected in result.output, result.output
    assert not (tmp_path / "run").exists()


def test_cli_train__writes_run_folder_and_resumes(tmp_path):
    run = tmp_path / "run"
    args = ["train", "--preset", "demo", "--out", str(run), "--total-steps", "8192",
            "--set", "chunk_steps=4096", "--set", "env.grid_size=8"]  # fmt: skip
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    for name in ("config.json", "metrics.jsonl", "learning_curve.png", "checkpoint/state.msgpack"):
        assert (run / name).exists(), name
    assert json.loads((run / "config.json").read_text())["env"]["grid_size"] == 8
    assert len(read_metrics(run)) == 2
    # TensorBoard event files beside metrics.jsonl: the same figures at the same env steps
    # (each finite figure of every chunk; NaN, e.g. success before any episode ended, is left out)
    board = tensorboard_scalars(run)
    expected: dict[str, list] = {}
    for r in read_metrics(run):
        for k, v in r.items():
            if k not in ("chunk", "env_steps") and math.isfinite(v):
                expected.setdefault(f"train/{k}", []).append((r["env_steps"], v))
    assert {"train/steps_per_s", "train/episodes"} <= set(expected)
    assert board.keys() == expected.keys()
    for tag, points in expected.items():
        assert [s for s, _ in board[tag]] == [s for s, _ in points], tag
        assert [v for _, v in board[tag]] == pytest.approx([v for _, v in points], rel=1e-6), tag
    result = CliRunner().invoke(app, ["train", "--resume", str(run)])
    assert result.exit_code == 0, result.output
    # it had trained all of its steps: said so, not "training ... done"
    assert "nothing left to train" in result.output and "done:" not in result.output, result.output
    assert len(read_metrics(run)) == 2
    # --resume continues the run as its config.json says: an option that would change it is
    # refused, naming it (it was ignored: --total-steps trained nothing more)
    longer = CliRunner().invoke(app, ["train", "--resume", str(run), "--total-steps", "16384"])
    assert longer.exit_code == 2 and "--total-steps would change it" in longer.output, longer.output
    # training again into the folder would leave its checkpoint, evaluations and exports beside
    # another policy: refused, pointing at --resume
    again = CliRunner().invoke(app, args)
    assert again.exit_code == 2 and f"--out {run} holds a run already" in again.output, again.output
    assert f"--resume {run}" in again.output and len(read_metrics(run)) == 2
    # a run stopped before its first checkpoint (Ctrl-C in the first chunk) trains from the start
    # as its config says (it was a FileNotFoundError traceback)
    import shutil

    shutil.rmtree(run / "checkpoint")
    restarted = CliRunner().invoke(app, ["train", "--resume", str(run)])
    assert restarted.exit_code == 0, restarted.output
    assert "no complete checkpoint yet: training it from the start" in restarted.output
    assert (run / "checkpoint" / "state.msgpack").exists() and len(read_metrics(run)) == 2
    # its TensorBoard curve is this training's alone, each chunk once
    assert [s for s, _ in tensorboard_scalars(run)["train/episodes"]] == [
        r["env_steps"] for r in read_metrics(run)]  # fmt: skip


def test_cli_train__the_default_folder_never_holds_an_earlier_run(tmp_path, monkeypatch):
    """Without --out, a second run of the same preset and seed trains into runs/NAME-2, not over
    the first (whose evaluations and exports would be left beside another policy)."""
    from quicknav_cli.train import free_folder

    monkeypatch.chdir(tmp_path)
    first = Path("runs/demo-s0")
    assert free_folder(first) == first
    (first / "checkpoint").mkdir(parents=True)
    assert free_folder(first) == Path("runs/demo-s0-2")
    Path("runs/demo-s0-2").mkdir()  # an empty folder holds no run
    assert free_folder(first) == Path("runs/demo-s0-2")
    (Path("runs/demo-s0-2") / "config.json").write_text("{}")
    assert free_folder(first) == Path("runs/demo-s0-3")


def test_cli_train__two_trainings_started_at_once_take_two_folders(tmp_path, monkeypatch):
    """Both find the default folder free in the same instant: the first to create its config.json
    takes it, the other the next name (they trained into one folder); a run refused before it
    trains gives its folder back."""
    import threading

    from quicknav_cli.train import free_folder

    monkeypatch.chdir(tmp_path)
    start, got = threading.Barrier(8), []

    def take(i: int) -> None:
        start.wait()
        got.append(free_folder(Path("runs/demo-s0"), claim=json.dumps({"run": i})))

    threads = [threading.Thread(target=take, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(got) == sorted([Path("runs/demo-s0"), *(Path(f"runs/demo-s0-{n}") for n in range(2, 9))])
    # each folder holds the config of the run that took it
    assert sorted(json.loads((p / "config.json").read_text())["run"] for p in got) == list(range(8))
    said = CliRunner().invoke(app, ["train", "--preset", "demo", "--seed", "5", "--set", "devices=2"])
    assert said.exit_code != 0 and "devices=2" in said.output, said.output
    assert not Path("runs/demo-s5").exists()  # refused: nothing claimed is left behind


def tensorboard_scalars(folder) -> dict[str, list[tuple[int, float]]]:
    """Scalars of the TensorBoard event files in ``folder``, read as TensorBoard does: TFRecord
    frames (length, its CRC, the serialised Event, its CRC) of ``Event`` protos."""
    import struct

    from tensorboardX.proto.event_pb2 import Event

    out: dict[str, list[tuple[int, float]]] = {}
    files = sorted(folder.glob("events.out.tfevents.*"))
    assert files, "no event file"
    for path in files:
        data = path.read_bytes()
        at = 0
        while at < len(data):
            (length,) = struct.unpack("<Q", data[at : at + 8])
            event = Event.FromString(data[at + 12 : at + 12 + length])
            at += 12 + length + 4
            for v in event.summary.value:
                out.setdefault(v.tag, []).append((event.step, v.simple_value))
    return out


@pytest.mark.parametrize("combo", ["ppo-mlp (rejax)", "ppo-lstm", "sac-mlp"])
def test_randomized_env__trains_with_every_trainer_family(combo, tmp_path):
    """What paper-ppo-robust names trains: the perturbations ride in the env state through rejax's
    PPO and SAC and QuickNav's recurrent PPO, and the checkpoint carries the randomised config."""
    network, algorithm = COMBOS[combo]
    cfg = tiny(network, algorithm)
    randomize = get_preset("paper-ppo-robust").env.randomize
    assert randomize is not None and randomize.latency_steps == (0, 2)
    cfg = cfg.model_copy(update={"env": cfg.env.model_copy(update={"randomize": randomize})})
    cfg = TrainConfig.model_validate(cfg.model_dump())
    if algorithm and algorithm["name"] == "sac":
        cfg = cfg.model_copy(update={"total_steps": 256, "chunk_steps": 128})
    trainer = make_trainer(cfg)
    assert trainer.env.randomized
    summary = train_run(cfg, tmp_path, trainer=trainer)
    assert summary["chunks_done"] == 2
    state = trainer.from_bytes((tmp_path / "checkpoint" / "state.msgpack").read_bytes())
    assert all(bool(jnp.isfinite(x).all()) for x in jax.tree.leaves(trainer.policy(state).params))
    stored = TrainConfig.model_validate_json((tmp_path / "config.json").read_text())
    assert stored.env.randomize == randomize
