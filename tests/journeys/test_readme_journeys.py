"""The journeys a new user walks, read out of README.md (see ``readme.py``) and run as written,
with the demo preset's policy trained for real: a policy that learned, not a random or an oracle
agent (evaluation of a good policy once failed while every part's own test passed).

- quick start: ``quicknav serve``; demo train with ``--follow``; eval of that job by its short
  id, held-out success >= 0.9; its artifacts listed and downloaded; the curl examples, each with
  its HTTP status; no command prints a warning, no job carries one. This is the journey that trains
  the demo to its target from README's text.
- in-process: ``quicknav env demo``, ``quicknav train --preset demo`` (the test run's one training
  of that command, ``tests/trained.py``), ``quicknav eval RUN_DIR`` (held-out success >= 0.9), the
  robustness eval, ``quicknav export``.

The service journeys of this module share one ``quicknav serve`` (started as README says, on free
ports); its log is checked for tracebacks when the module ends.

The long runs are ``slow`` (CI runs them after the fast suite); that README still marks its
journeys, and that the runner knows how to run every line of them, is checked in the fast suite.
"""

from __future__ import annotations

import json
import shlex

import httpx
import pytest

from quicknav_core.config.resolve import resolve_train
from tests.journeys.readme import ROOT, Runner, doc_files, http_status, journey, journey_blocks
from tests.service.conftest import free_port

JOURNEYS = ("quickstart", "in-process")


def walk(runner: Runner, name: str) -> list:
    """Run a journey's blocks in reading order: shell lines one by one, python blocks whole."""
    ran = []
    for block in journey(name):
        if block.language == "python":
            ran.append((block, None, runner.run_python(block.source)))
        else:
            ran += [(block, c, runner.run(c)) for c in block.commands]
    return [r for r in ran if r[2] is not None]


def commands(name: str) -> list[str]:
    """The shell lines of a journey (its python blocks are run whole, by ``run_journey``)."""
    return [c for block in journey(name) if block.language == "bash" for c in block.commands]


# --------------------------------------------------------------------------- fast: README still says it
def test_readme__marks_both_journeys_and_each_line_is_one_the_runner_runs():
    found = {b.journey for b in journey_blocks()}
    assert set(JOURNEYS) <= found, f"README.md lost a journey marker: found {sorted(found)}"
    for name in found:
        for command in commands(name):
            words = shlex.split(command, comments=True)
            assert words[:2] == ["uv", "sync"] or words[:3] == ["uv", "run", "quicknav"] or (
                words[0] == "curl"), f"journey {name}: the runner cannot run {command!r}"  # fmt: skip
    quick = commands("quickstart")
    assert any("quicknav serve" in c for c in quick)
    assert any("jobs submit train --preset demo" in c and "--follow" in c for c in quick)
    assert any("jobs submit eval" in c and "<id>" in c for c in quick)
    assert any(c.startswith("curl") for c in quick)
    local = commands("in-process")
    assert any("quicknav train --preset demo" in c for c in local)
    assert any("quicknav eval <run-dir>" in c for c in local)
    assert any("quicknav env demo" in c for c in local)


def test_readme__journey_blocks_are_found_in_reading_order(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("intro\n\n<!-- journey: a -->\n```bash\nuv run quicknav env demo \\\n"
                    "  --out x   # drawn\n# a comment\n\n```\n\n```bash\nuv run quicknav nope\n```\n\n"
                    "<!-- journey: b -->\n```bash\ncurl -s localhost:8000/healthz\n```\n")  # fmt: skip
    blocks = journey_blocks([page])
    assert [(b.journey, b.line, b.commands) for b in blocks] == [
        ("a", 4, ["uv run quicknav env demo    --out x   # drawn"]),
        ("b", 16, ["curl -s localhost:8000/healthz"]),
    ]
    assert doc_files()[0].name == "README.md"


# --------------------------------------------------------------------------- slow: walked
@pytest.fixture(scope="module")
def service(tmp_path_factory):
    """The module's one ``uv run quicknav serve`` (README's command), for every service journey."""
    r = Runner(workdir=tmp_path_factory.mktemp("service"), port=free_port(), grpc_port=free_port())
    started = False

    def start():
        nonlocal started
        if not started:
            r.start_server("uv run quicknav serve")
            started = True
        return r

    yield start
    log = r.stop()
    assert "Traceback" not in log, log[-4000:]


@pytest.fixture
def runner(tmp_path):
    r = Runner(workdir=tmp_path, port=free_port(), grpc_port=free_port())
    yield r
    r.stop()


def ok(ran) -> None:
    assert ran.code == 0, str(ran)
    assert "warning" not in ran.stderr.lower(), str(ran)


def assert_policy_folder(folder, held_out: float | None) -> None:
    """policy.onnx answers a batch of observations with actions in [-1, 1] (onnxruntime only), and
    policy.json describes it; with ``held_out``, the manifest's held-out success is at least that."""
    import numpy as np
    import onnxruntime as ort

    doc = json.loads((folder / "policy.json").read_text())
    session = ort.InferenceSession(str(folder / "policy.onnx"), providers=["CPUExecutionProvider"])
    obs = np.random.default_rng(0).uniform(0, 1, (5, doc["observation"]["size"])).astype(np.float32)
    feed = {"obs": obs}
    if doc["recurrent"]:
        feed["start"] = np.ones(5, bool)
        feed.update({s["input"]: np.full([5, *s["shape"][1:]], s["initial"], s["dtype"]) for s in doc["state"]})
    action = session.run(["action"], feed)[0]
    assert action.shape == (5, 2) and np.all(np.abs(action) <= 1)
    if held_out is None:
        assert doc["held_out"] is None  # exported before any evaluation
    else:
        assert doc["held_out"]["success_rate"] >= held_out, doc["held_out"]


@pytest.mark.slow  # trains the demo (CLI; curl a shorter run of it) and evaluates: ~1-2 min on 2 cores
def test_journey__quick_start(runner, service):
    runner.attach(service())
    evaluated = train_id = None
    for command in commands("quickstart"):
        ran = runner.run(command)
        if ran is None:
            continue
        if command.startswith("curl"):
            assert ran.code == 0, str(ran)
            status = http_status(ran)
            if "-X POST" in command:
                assert status == 202, str(ran)
                assert json.loads(ran.stdout.rsplit("\n", 1)[0])["status"] == "queued", str(ran)
            else:
                assert status == 200, str(ran)
            if "/events" in command:  # the stream ran to the job's end, and the job learned
                assert "event: started" in ran.stdout and "event: succeeded" in ran.stdout, str(ran)
            continue
        ok(ran)
        if "jobs submit train" in command:
            assert f"job {runner.last_id}: succeeded" in ran.stdout, str(ran)
            train_id = runner.last_id
            trained = httpx.get(f"{runner.url}/jobs/{train_id}").json()
            # the preset runs what it names: no "not a whole number of updates" note, no warning
            assert "note" not in trained["result"] and trained["warnings"] == [], trained["result"]
            assert trained["result"]["env_steps"] == trained["config"]["total_steps"]
        elif "quicknav export --job" in command:
            # the train job's policy, exported by its worker, runs in onnxruntime as the manifest says
            out = runner.workdir / shlex.split(command, comments=True)[-1]
            assert_policy_folder(out, held_out=None)
            assert json.loads((out / "policy.json").read_text())["provenance"]["job_id"] == train_id
        elif "jobs submit eval" in command:
            evaluated = runner.last_id
            assert evaluated != train_id and f"job {evaluated}: succeeded" in ran.stdout, str(ran)
            job = httpx.get(f"{runner.url}/jobs/{evaluated}").json()
            assert job["config"]["source"] == train_id  # the short id found the train job
            success = job["result"]["metrics"]["success_rate"]
            assert success >= 0.9, f"the demo policy did not learn: held-out success {success}"
            assert job["warnings"] == [] and job["result"]["warnings"] == []
            # the train job's exported policy now names this held-out success
            manifest = httpx.get(f"{runner.url}/jobs/{train_id}/artifacts/policy.json").json()
            assert manifest["held_out"]["eval_job_id"] == evaluated
            assert manifest["held_out"]["success_rate"] == success
        elif "jobs artifacts" in command:
            assert "<eval-id>" in command  # README names the eval job, not the train job
            listed = httpx.get(f"{runner.url}/jobs/{evaluated}/artifacts").json()["artifacts"]
            names = {f["name"] for f in listed}
            for name in ("eval.json", "replay.json", "trajectories.png", "difficulty.png"):
                assert name in names and name in ran.stdout, (name, str(ran))
        elif "jobs download" in command:
            out = shlex.split(command, comments=True)[-1]
            served = httpx.get(f"{runner.url}/jobs/{evaluated}/artifacts/eval.json").content
            assert (runner.workdir / out).read_bytes() == served
            assert json.loads(served)["metrics"]["episodes"] == 100
    assert evaluated is not None, "the quick start has no eval"
    ran_commands = [r.command for r in runner.history]
    assert len(ran_commands) == len(commands("quickstart")) - 2  # all but `uv sync` and `serve`


@pytest.mark.slow  # evaluates the trained demo in-process, with robustness, and exports it: ~1 min
def test_journey__in_process(runner, trained_demo_run):
    runner.trained["uv run quicknav train --preset demo"] = trained_demo_run
    for command in commands("in-process"):
        ran = runner.run(command)
        if ran is None:
            continue
        ok(ran)
        if "quicknav env demo" in command:
            out = runner.workdir / shlex.split(command, comments=True)[-1]
            assert (out / "demo.png").stat().st_size > 1000 and (out / "demo.gif").exists()
        elif "quicknav train" in command:
            assert runner.run_dir, f"train printed no run folder:\n{ran}"
            assert (runner.workdir / runner.run_dir / "learning_curve.png").exists()
        elif "quicknav eval" in command and "--robustness" in command:
            out = runner.workdir / shlex.split(command, comments=True)[-1]
            assert_robustness(json.loads((out / "eval.json").read_text()), ran.stdout)
            assert (out / "robustness.png").stat().st_size > 10_000
        elif "quicknav eval" in command:
            result = json.loads((runner.workdir / runner.run_dir / "eval" / "eval.json").read_text())
            success = result["metrics"]["success_rate"]
            assert success >= 0.9, f"the demo policy did not learn: held-out success {success}"
            assert result["warnings"] == [] and "success rate" in ran.stdout
        elif "quicknav export" in command:
            out = runner.workdir / shlex.split(command, comments=True)[-1]
            assert_policy_folder(out, held_out=0.9)
            assert "held-out success" in ran.stdout, str(ran)
    assert runner.server is None  # the in-process journey needs no service


def assert_robustness(result: dict, printed: str) -> None:
    """A learned policy's robustness rows: every level, the unperturbed one as good as the plain
    evaluation, and the perturbations reaching the policy (rows that differ from it)."""
    from quicknav_core.eval.robustness import LEVELS

    rows = result["robustness"]
    assert [r["label"] for r in rows] == [lv.label for lv in LEVELS]
    none = rows[0]
    assert none["success_rate"] == result["metrics"]["success_rate"] >= 0.9, none
    moved = [r["label"] for r in rows[1:] if (r["mean_steps"], r["collisions_per_episode"])
             != (none["mean_steps"], none["collisions_per_episode"])]  # fmt: skip
    assert len(moved) >= 10, f"only {moved} changed the policy's episodes"
    assert result["warnings"] == [] and "robustness" in printed and "latency 3 steps" in printed


@pytest.mark.slow  # the service pages (docs/service.md, sdk.md, grpc.md) on the live server: ~1 min
def test_journey__the_service_pages_curl_sdk_and_grpc(runner, service):
    runner.attach(service())
    for _, command, ran in walk(runner, "service-http"):
        assert ran.code == 0, str(ran)
        status = http_status(ran)
        body = ran.stdout.rsplit("\n", 1)[0]
        if "-X POST" in command:
            assert status == 202 and json.loads(body)["status"] == "queued", str(ran)
        else:
            assert status == 200, str(ran)
        if "/events" in command:
            assert "event: started" in ran.stdout and "event: succeeded" in ran.stdout, str(ran)
        if "/artifacts" in command:
            names = {a["name"] for a in json.loads(body)["artifacts"]}
            assert {"config.json", "metrics.jsonl", "learning_curve.png"} <= names, names
    evaluated = runner.last_id
    finished = httpx.get(f"{runner.url}/jobs/{evaluated}?wait=0").json()
    assert finished["kind"] == "eval", finished

    (sdk,) = walk(runner, "sdk")
    assert sdk[2].code == 0, str(sdk[2])
    printed = sdk[2].stdout.strip().splitlines()
    assert printed[0].startswith("succeeded"), str(sdk[2])
    grid = resolve_train({"preset": "demo"}).env.grid_size
    assert printed[-1] == f"{grid} True", str(sdk[2])  # the demo's grid; the eval ran the job's env
    assert (runner.workdir / "curve.png").stat().st_size > 1000
    assert_policy_folder(runner.workdir / "policy", held_out=None)  # download_policy

    (grpc,) = walk(runner, "grpc")
    assert grpc[2].code == 0, str(grpc[2])


def test_journey__the_service_pages_maps(runner, service):
    """docs/service.md's maps journey: upload the shipped office map, list it, draw it, and run the
    oracle on it as an eval job (every goal reached: the map's rooms are connected and drivable)."""
    (runner.workdir / "examples").symlink_to(ROOT / "examples")  # the page's paths, from a checkout
    runner.attach(service())
    ran = walk(runner, "maps")
    for _, _, result in ran:
        ok(result)
    upload, listed, shown, evaluated = (r[2] for r in ran)
    assert upload.stdout.startswith(f"map {runner.map_id} (office):"), str(upload)
    assert runner.map_id in listed.stdout and "office" in listed.stdout, str(listed)
    assert (runner.workdir / "office.png").read_bytes()[:4] == b"\x89PNG", str(shown)
    job = httpx.get(f"{runner.url}/jobs/{runner.last_id}").json()
    assert job["status"] == "succeeded" and job["config"]["env"]["maps"]["train"] == [f"map:{runner.map_id}"]
    assert job["result"]["metrics"]["success_rate"] == 1.0, job["result"]["metrics"]
