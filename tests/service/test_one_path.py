"""One path from a request to a config: the same request given as CLI flags, as a REST body, through
the SDK and through `quicknav jobs submit` is stored as the same resolved config.

No job runs here (no worker): the configs are compared as the service stored them and as
`quicknav train|sweep|eval --print-config` resolves them locally.
"""

from __future__ import annotations

import json

import httpx
import pytest
from quicknav_client import QuickNavClient
from typer.testing import CliRunner

from quicknav_cli.main import app
from quicknav_core.config import get_preset, resolve_sweep
from quicknav_core.config.train import with_trainer_defaults
from tests.service.conftest import LiveServer

runner = CliRunner()


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    with LiveServer(tmp_path_factory.mktemp("one-path")) as server:
        yield server


def local(*args: str) -> dict:
    """A config as the CLI resolves it (``--print-config``)."""
    result = runner.invoke(app, [*args, "--print-config"])
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)  # warnings (a deprecated flag) go to stderr


def rest(live, kind: str, body: dict) -> dict:
    r = httpx.post(f"{live.url}/jobs/{kind}", json=body)
    assert r.status_code == 202, r.text
    stored = live.store.get(r.json()["id"])
    assert stored.config == r.json()["config"], "the response shows what was stored"
    return stored.config


def jobs_cli(live, *args: str) -> dict:
    """A config as stored after `quicknav jobs submit ...` (CLI -> SDK -> REST)."""
    result = runner.invoke(app, ["jobs", "--url", live.url, "submit", *args])
    assert result.exit_code == 0, result.output
    job_id = result.output.split(" job ")[1].split()[0]
    return live.store.get(job_id).config


def sdk(live, method: str, *args, **kwargs) -> dict:
    with QuickNavClient(live.url) as qn:
        job = getattr(qn, method)(*args, **kwargs)
        return job.config


def assert_same(*configs: dict) -> None:
    first = configs[0]
    for other in configs[1:]:
        assert other == first


def test_train__preset_with_overrides(live):
    flags = local("train", "--preset", "demo", "--algo", "ppo", "--total-steps", "200000",
                  "--seed", "3", "--set", "env.grid_size=8", "--set", "algorithm.learning_rate=0.002")  # fmt: skip
    overrides = {"env.grid_size": 8, "algorithm.learning_rate": 0.002}
    body = rest(live, "train", {"preset": "demo", "overrides": {
        "algorithm.name": "ppo", "total_steps": 200000, "seed": 3, **overrides}})  # fmt: skip
    client = sdk(live, "train", preset="demo", overrides=overrides, total_steps=200000, seed=3)
    submitted = jobs_cli(live, "train", "--preset", "demo", "--set", "total_steps=200000",
                         "--set", "seed=3", "--set", "env.grid_size=8",
                         "--set", "algorithm.learning_rate=0.002")  # fmt: skip
    assert_same(flags, body, client, submitted)
    assert flags["env"]["grid_size"] == 8 and flags["algorithm"]["learning_rate"] == 0.002
    assert flags["total_steps"] == 200000 and flags["seed"] == 3
    assert flags["network"] == with_trainer_defaults(get_preset("demo")).network.model_dump(mode="json")


def test_train__custom_config_file_with_overrides(live, tmp_path):
    custom = get_preset("paper-lstm").model_copy(update={"num_envs": 32, "total_steps": 2_000_000})
    data = custom.model_dump(mode="json")
    data["algorithm"]["num_minibatches"] = 8
    path = tmp_path / "train.json"
    path.write_text(json.dumps(data))
    flags = local("train", "--config", str(path), "--network", "lstm",
                  "--set", "env.max_steps=100", "--set", "network.hidden_size=8")  # fmt: skip
    overrides = {"network.kind": "lstm", "env.max_steps": 100, "network.hidden_size": 8}
    body = rest(live, "train", {"config": data, "overrides": overrides})
    client = sdk(live, "train", config=data, overrides=overrides)
    submitted = jobs_cli(live, "train", "--config", str(path), "--set", "env.max_steps=100",
                         "--set", "network.hidden_size=8")  # fmt: skip
    assert_same(flags, body, client, submitted)
    assert flags["network"]["hidden_size"] == 8 and flags["algorithm"]["num_minibatches"] == 8


def test_sweep__builtin_space_with_overrides(live):
    flags = local("sweep", "--space", "lstm", "--trials", "4", "--total-steps", "262144",
                  "--set", "env.grid_size=8", "--set", "eval_episodes=10")  # fmt: skip
    body = rest(live, "sweep", {"space": "lstm", "trials": 4, "total_steps": 262144,
                                "overrides": {"env.grid_size": 8, "eval_episodes": 10}})  # fmt: skip
    client = sdk(live, "sweep", "lstm", trials=4, total_steps=262144,
                 overrides={"env.grid_size": 8, "eval_episodes": 10})  # fmt: skip
    submitted = jobs_cli(live, "sweep", "--space", "lstm", "--set", "trials=4",
                         "--set", "total_steps=262144", "--set", "env.grid_size=8",
                         "--set", "eval_episodes=10")  # fmt: skip
    old_flag = local("sweep", "--preset", "lstm", "--trials", "4", "--total-steps", "262144",
                     "--set", "env.grid_size=8", "--set", "eval_episodes=10")  # fmt: skip
    said = runner.invoke(app, ["sweep", "--preset", "lstm", "--print-config"])
    assert "--preset is deprecated for sweeps: write --space lstm" in said.stderr
    assert_same(flags, body, client, submitted, old_flag)
    assert flags["base"]["total_steps"] == 262144 and flags["base"]["env"]["grid_size"] == 8
    assert flags["trials"] == 4 and flags["eval_episodes"] == 10 and flags["study_name"] == "lstm"
    # a built-in sweep trains the same budget per trial whichever door it came through
    assert local("sweep", "--space", "ppo")["base"]["total_steps"] == rest(
        live, "sweep", {"space": "ppo"})["base"]["total_steps"]  # fmt: skip


def test_sweep__a_space_on_a_preset_of_the_users_choice(live):
    """`--base building`: the space's trials start from the building preset, not from the space's
    paper preset; every door resolves it alike, and a preset the space cannot tune is refused,
    naming `base`, what it lacks and the spaces it takes."""
    flags = local("sweep", "--space", "ppo", "--base", "building", "--trials", "4")
    body = rest(live, "sweep", {"space": "ppo", "base": "building", "trials": 4})
    client = sdk(live, "sweep", space="ppo", base="building", trials=4)
    submitted = jobs_cli(live, "sweep", "--space", "ppo", "--base", "building", "--trials", "4")
    assert_same(flags, body, client, submitted)
    building = with_trainer_defaults(get_preset("building")).model_dump(mode="json")
    assert flags["base"]["env"] == building["env"] and flags["base"]["network"] == building["network"]
    assert flags["base"]["total_steps"] == local("sweep", "--space", "ppo")["base"]["total_steps"]
    assert flags["study_name"] == "ppo-building" and "algorithm.learning_rate" in flags["space"]
    bad = httpx.post(f"{live.url}/jobs/sweep", json={"space": "lstm", "base": "building"})
    assert bad.status_code == 422, bad.text
    (err,) = bad.json()["detail"]
    assert err["loc"] == ["body", "base"] and "network.num_layers" in err["msg"], err
    assert "spaces it takes: ppo, mlp" in err["msg"], err
    said = runner.invoke(app, ["sweep", "--space", "ppo", "--base", "nope", "--print-config"])
    assert said.exit_code == 2 and "base: unknown preset 'nope'" in said.output, said.output
    # a preset given as the space (the deprecated --preset was the space): which space tunes it
    for given, hint in (("building", "--space ppo --base building tunes it"),
                        ("paper-sac", "--space sac starts from it")):  # fmt: skip
        said = runner.invoke(app, ["sweep", "--space", given, "--print-config"])
        assert said.exit_code == 2 and hint in said.output.replace("\n", ""), said.output
    # the API says the same in its own words (it answered with the list of spaces alone)
    for given, hint in (("building", '"space": "ppo", "base": "building" tunes it'),
                        ("paper-sac", '"space": "sac" starts from it')):  # fmt: skip
        said = httpx.post(f"{live.url}/jobs/sweep", json={"space": given})
        (err,) = said.json()["detail"]
        assert said.status_code == 422 and err["loc"] == ["body", "space"], said.text
        assert f"{given!r} is a training preset, not a search space" in err["msg"] and hint in err["msg"], err
    config = resolve_sweep({"space": "ppo", "total_steps": 131072}).model_dump(mode="json")
    both = httpx.post(f"{live.url}/jobs/sweep", json={"config": config, "base": "building"})
    assert both.status_code == 422 and "'base' goes with 'space'" in both.text, both.text


def test_sweep__custom_config_with_overrides(live, tmp_path):
    data = resolve_sweep({"space": "ppo", "total_steps": 131072}).model_dump(mode="json")
    data["objective"] = "spl"
    path = tmp_path / "sweep.json"
    path.write_text(json.dumps(data))
    flags = local("sweep", "--config", str(path), "--parallel", "2", "--set", "num_envs=128")
    body = rest(live, "sweep", {"config": data, "parallel": 2, "overrides": {"num_envs": 128}})
    client = sdk(live, "sweep", data, parallel=2, overrides={"num_envs": 128})
    assert_same(flags, body, client)
    assert flags["parallel"] == 2 and flags["base"]["num_envs"] == 128 and flags["objective"] == "spl"


def test_eval__baseline(live):
    flags = local("eval", "--policy", "oracle", "--episodes", "50", "--seed", "2", "--split",
                  "train", "--stochastic", "--set", "grid_size=8")  # fmt: skip
    body = rest(live, "eval", {"policy": "oracle", "episodes": 50, "seed": 2, "split": "train",
                               "deterministic": False, "env": {"grid_size": 8}})  # fmt: skip
    client = sdk(live, "evaluate", policy="oracle", episodes=50, seed=2, split="train",
                 deterministic=False, env={"grid_size": 8})  # fmt: skip
    submitted = jobs_cli(live, "eval", "--policy", "oracle", "--episodes", "50", "--seed", "2",
                         "--split", "train", "--stochastic", "--set", "grid_size=8")  # fmt: skip
    assert_same(flags, body, client, submitted)
    assert flags["env"]["grid_size"] == 8 and flags["split"] == "train"
    assert flags["deterministic"] is False and flags["policy"] == "oracle"


def test_eval__trained_job_and_its_run_folder(tmp_path):
    """A train job's checkpoint (made by hand here: resolving needs only its config) evaluated
    from its run folder (CLI) and by its id (REST, SDK, jobs CLI)."""
    with LiveServer(tmp_path) as live:
        _trained_job_and_its_run_folder(live)


def _trained_job_and_its_run_folder(live):
    train_body = {"preset": "demo", "overrides": {"env.grid_size": 8, "env.lidar_beams": 8}}
    train = httpx.post(f"{live.url}/jobs/train", json=train_body).json()
    store = live.store
    assert store.claim("by-hand", 60).id == train["id"]
    run_dir = live.settings.artifacts_dir / train["id"]
    (run_dir / "checkpoint").mkdir(parents=True)
    (run_dir / "config.json").write_text(json.dumps(train["config"]))
    (run_dir / "checkpoint" / "state.msgpack").write_bytes(b"not read when resolving")
    (run_dir / "checkpoint" / "meta.json").write_text(json.dumps({"chunk": 1}))
    store.finish(train["id"], "by-hand", "succeeded")

    flags = local("eval", str(run_dir), "--episodes", "20", "--set", "max_steps=100")
    body = rest(live, "eval", {"job_id": train["id"], "episodes": 20, "env": {"max_steps": 100}})
    client = sdk(live, "evaluate", job=train["id"], episodes=20, env={"max_steps": 100})
    submitted = jobs_cli(live, "eval", "--job", train["id"], "--episodes", "20",
                         "--set", "max_steps=100")  # fmt: skip
    assert flags.pop("source") == str(run_dir)  # the CLI names a folder, the service a job
    for stored in (body, client, submitted):
        assert stored.pop("source") == train["id"]
    assert_same(flags, body, client, submitted)
    assert flags["policy"] == "trained" and flags["env"]["max_steps"] == 100
    assert flags["env"]["lidar_beams"] == 8, "the train job's env, not the defaults"
