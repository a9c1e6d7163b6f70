"""`quicknav jobs` and the SDK against a scripted service (httpx.MockTransport): names the CLI, the
SDK and the API share, the compiling phase, a failed job's reason, warnings, stderr, 80 columns.

No JAX runs here: the service's answers are written out, so each test looks at exactly one thing.
"""

from __future__ import annotations

import inspect
import io
import json
import re
import time
from importlib.metadata import version as package_version
from pathlib import Path

import httpx
import pytest
import quicknav_client
from quicknav_client import AsyncQuickNavClient, QuickNavClient
from rich.console import Console
from typer.main import get_command
from typer.testing import CliRunner

from quicknav_cli import jobs as jobs_cli
from quicknav_cli.main import app
from quicknav_core.config.resolve import EvalRequest, SweepRequest, TrainRequest

JOB_ID = "0123456789abcdef0123456789abcdef"
runner = CliRunner()


def job_json(**fields) -> dict:
    """A job as GET /jobs/{id} answers it."""
    base = {"id": JOB_ID, "kind": "train", "status": "running", "progress": 0.0, "metrics": {},
            "attempts": 1, "worker": "w1", "error": None, "result": None,
            "cancel_requested": False, "created_at": time.time() - 30, "started_at": time.time(),
            "finished_at": None, "request": {"preset": "demo"}, "config": {}, "links": {},
            "warnings": []}  # fmt: skip
    return {**base, **fields}


def sse(*events: dict) -> str:
    return "".join(
        f"id: {i}\nevent: {e['type']}\ndata: {json.dumps(e)}\n\n" for i, e in enumerate(events, 1)
    )


class FakeService:
    """Answers the few routes a test needs and remembers every request."""

    def __init__(self, job: dict | None = None, events: str = "", jobs: list[dict] | None = None):
        self.job = job or job_json()
        self.events = events
        self.jobs = jobs
        self.maps: list[dict] = []
        self.requests: list[httpx.Request] = []

    def __call__(self, request: httpx.Request) -> httpx.Response:
        self.requests.append(request)
        path = request.url.path
        if request.method == "POST" and path.startswith("/jobs/"):
            kind = path.rsplit("/", 1)[-1]
            return httpx.Response(202, json=job_json(kind=kind, status="queued"))
        if path == "/maps":
            return httpx.Response(200, json={"data": self.maps})
        if path == "/jobs":
            data = self.jobs if self.jobs is not None else [self.job]
            return httpx.Response(200, json={"data": data, "count": len(data)})
        if path.endswith("/events"):
            return httpx.Response(200, text=self.events,
                                  headers={"content-type": "text/event-stream"})  # fmt: skip
        if path.startswith("/jobs/") and path.count("/") == 4 and "/artifacts/" in path:
            return httpx.Response(200, content=b"artifact bytes")
        if path == f"/jobs/{JOB_ID}":
            return httpx.Response(200, json=self.job)
        return httpx.Response(404, json={"detail": f"no job {path.rsplit('/', 1)[-1]!r}"})

    def bodies(self) -> list[dict]:
        return [json.loads(r.content) for r in self.requests if r.method == "POST"]


@pytest.fixture
def service(monkeypatch):
    """A FakeService that `quicknav jobs` talks to (its client gets the mock transport)."""
    fake = FakeService()

    def client(url, token=None, **kw):
        return QuickNavClient(url, token=token, transport=httpx.MockTransport(fake), **kw)

    monkeypatch.setattr(quicknav_client, "QuickNavClient", client)
    return fake


def cli(*args: str, **env: str):
    return runner.invoke(app, list(args), env={"COLUMNS": "80", **env})


# --------------------------------------------------------------------------- names agree
def cli_params(*path: str) -> set[str]:
    command = get_command(app)
    for name in path:
        command = command.commands[name]
    return {p.name for p in command.params}


def sdk_params(method) -> set[str]:
    return {n for n, p in inspect.signature(method).parameters.items()
            if n != "self" and p.kind is not p.VAR_KEYWORD}  # fmt: skip


def api_fields(model) -> set[str]:
    return set(model.model_fields)


# For each operation the CLI and the SDK share: the CLI options it uses, how a CLI name maps to the
# SDK's where the two differ, and what only one side has. Any other difference fails the test.
SUBMIT = {
    "train": dict(cli={"preset", "config", "set_", "total_steps"}, sdk="train",
                  renamed={"set_": "overrides", "total_steps": "overrides"},
                  sdk_only={"idempotency_key"}, api=TrainRequest),
    "sweep": dict(cli={"space", "base", "config", "set_", "trials", "parallel", "total_steps",
                       "preset"},
                  sdk="sweep", renamed={"set_": "overrides", "preset": "space"},
                  sdk_only={"idempotency_key"}, api=SweepRequest),
    "eval": dict(cli={"job", "policy", "episodes", "seed", "split", "deterministic", "stochastic",
                      "set_", "robustness", "shield", "map"},
                 sdk="evaluate", renamed={"set_": "env"}, sdk_only={"idempotency_key"},
                 api=EvalRequest),
}  # fmt: skip
# the SDK's `job` takes a Job or an id and sends it as the API's `job_id` (the documented field;
# `source` is the field's name inside the library, which reads a run folder as well)
SDK_TO_API = {"job": "source", "idempotency_key": None}
CLI_ONLY = {"kind", "follow"}


@pytest.mark.parametrize("kind", sorted(SUBMIT))
def test_names__submit_options_match_the_sdk_and_the_api(kind):
    spec = SUBMIT[kind]
    cli = cli_params("jobs", "submit")
    assert spec["cli"] <= cli, f"the CLI lost {spec['cli'] - cli}"
    mapped = {spec["renamed"].get(n, n) for n in spec["cli"]}
    sdk = sdk_params(getattr(QuickNavClient, spec["sdk"])) - spec["sdk_only"]
    assert mapped == sdk, f"CLI only: {mapped - sdk}; SDK only: {sdk - mapped}"
    api = api_fields(spec["api"])
    to_api = {SDK_TO_API.get(n, n) for n in sdk} - {None}
    assert to_api <= api, f"the SDK sends what the API does not take: {to_api - api}"
    # and every field the API takes has a door in the SDK
    assert api <= to_api, f"the SDK cannot send {api - to_api}"


def test_names__every_submit_option_belongs_to_an_operation():
    used = set().union(*(spec["cli"] for spec in SUBMIT.values())) | CLI_ONLY
    assert cli_params("jobs", "submit") == used


@pytest.mark.parametrize(("command", "method", "renamed"), [
    ("list", "jobs", {}), ("show", "job", {"as_json": None}), ("follow", "job", {}),
    ("download", "download", {}), ("cancel", "job", {}), ("artifacts", "job", {}),
])  # fmt: skip
def test_names__other_commands_match_the_sdk(command, method, renamed):
    cli = {renamed.get(n, n) for n in cli_params("jobs", command)} - {None}
    sdk = sdk_params(getattr(QuickNavClient, method)) - {"path"}  # path: deprecated name of out
    assert cli == sdk, f"CLI only: {cli - sdk}; SDK only: {sdk - cli}"


def test_names__sync_and_async_clients_take_the_same_parameters():
    for name, method in inspect.getmembers(QuickNavClient, inspect.isfunction):
        if name.startswith("_") or name in ("close",):
            continue
        other = getattr(AsyncQuickNavClient, name)
        assert list(inspect.signature(method).parameters) == list(
            inspect.signature(other).parameters
        ), name
    for name in ("download", "wait", "events", "cancel"):
        sync, aio = getattr(quicknav_client.Job, name), getattr(quicknav_client.AsyncJob, name)
        assert list(inspect.signature(sync).parameters) == list(inspect.signature(aio).parameters)


def test_names__old_spellings_still_work_and_say_they_are_deprecated(service, tmp_path):
    with QuickNavClient("http://qn", transport=httpx.MockTransport(service)) as qn:
        with pytest.warns(DeprecationWarning, match="out="):
            path = qn.download(JOB_ID, "config.json", path=tmp_path / "a.json")
        assert path.read_bytes() == b"artifact bytes"
        assert qn.download(JOB_ID, "config.json", out=tmp_path / "b.json").exists()
        with pytest.warns(DeprecationWarning, match="deterministic"):
            qn.evaluate(policy="random", stochastic=True)
        qn.sweep(space="ppo", trials=2)
        qn.sweep("ppo")  # a name as the first argument is a space, as before
    sent = service.bodies()
    assert sent[0]["deterministic"] is False and "stochastic" not in sent[0]
    assert sent[1] == {"space": "ppo", "trials": 2} and sent[2] == {"space": "ppo"}

    r = cli("jobs", "submit", "sweep", "--preset", "lstm", "--trials", "3")
    assert r.exit_code == 0, r.output
    assert "--preset is deprecated" in r.stderr and "--space lstm" in r.stderr
    r = cli("jobs", "submit", "eval", "--policy", "oracle", "--stochastic")
    assert r.exit_code == 0 and "--no-deterministic" in r.stderr
    r = cli("jobs", "submit", "eval", "--policy", "oracle", "--no-deterministic")
    assert r.exit_code == 0 and not r.stderr
    assert service.bodies()[-3:] == [
        {"space": "lstm", "trials": 3},
        {"episodes": 100, "seed": 0, "split": "test", "deterministic": False, "policy": "oracle"},
        {"episodes": 100, "seed": 0, "split": "test", "deterministic": False, "policy": "oracle"},
    ]
    r = cli("jobs", "download", JOB_ID, "config.json", "--out", str(tmp_path / "c.json"))
    assert r.exit_code == 0 and (tmp_path / "c.json").read_bytes() == b"artifact bytes"


# --------------------------------------------------------------------------- progress
def render(progress: jobs_cli.JobProgress, width: int = 80) -> str:
    out = Console(width=width, file=io.StringIO(), force_terminal=False, color_system=None)
    out.print(progress.renderable())
    return out.file.getvalue()


class Clock:
    def __init__(self, now: float):
        self.now = now

    def __call__(self) -> float:
        return self.now


def test_progress__compiling_shows_its_elapsed_time_ticking_not_zero_percent():
    clock = Clock(1000.0)
    job = quicknav_client.Job(None, job_json(metrics={"phase": "compiling", "phase_since": 988.0}))
    bar = jobs_cli.JobProgress(job, Console(file=io.StringIO()), clock=clock)
    shown = render(bar)
    assert "compiling 12 s" in shown and "0%" not in shown and "running" not in shown
    clock.now += 3
    assert "compiling 15 s" in render(bar)  # ticks between events
    bar.update({"type": "progress", "progress": 0.25,
                "metrics": {"phase": "training", "success_rate": 0.5, "env_steps": 4096}})  # fmt: skip
    shown = render(bar)
    assert "compiling" not in shown and "running" in shown and "25%" in shown
    assert "success 50%" in shown


def test_progress__is_readable_at_80_columns():
    job = quicknav_client.Job(None, job_json(progress=0.5, metrics={
        "success_rate": 0.875, "mean_return": 123.456, "steps_per_s": 123456.7}))  # fmt: skip
    bar = jobs_cli.JobProgress(job, Console(file=io.StringIO()))
    lines = render(bar, 80).splitlines()
    assert all(len(line) <= 80 for line in lines)
    first = lines[0]
    assert f"train {JOB_ID[:8]} running" in first
    # half done: 50% of the bar drawn, the rest blank (no colours here); at least 20 columns
    bar_columns = first.index("50%") - first.index("━")
    assert bar_columns >= 20 and first.count("━") >= 10, f"the bar is squeezed: {first!r}"
    assert re.search(r"50%\s+\d+:\d\d:\d\d", first), f"elapsed time cut: {first!r}"
    assert "success 88%" in lines[1] and "123,457 steps/s" in lines[1]


def test_follow__shows_compiling_then_the_result_and_the_jobs_warnings(service):
    since = time.time() - 7
    service.job = job_json(status="succeeded", progress=1.0, finished_at=time.time(),
                           warnings=["trajectories.png failed to render: ValueError"])  # fmt: skip
    service.events = sse(
        {"type": "started"},
        {"type": "progress", "progress": 0.0,
         "metrics": {"phase": "compiling", "phase_since": since}},
        {"type": "progress", "progress": 1.0, "metrics": {"phase": "training"}},
        {"type": "succeeded"},
    )  # fmt: skip
    first = job_json(metrics={"phase": "compiling", "phase_since": since})
    job = quicknav_client.Job(None, first)
    bar = jobs_cli.JobProgress(job, Console(file=io.StringIO()))
    assert re.search(r"compiling [7-9] s", render(bar))
    r = cli("jobs", "follow", JOB_ID)
    assert r.exit_code == 0, r.output
    assert "succeeded" in r.stdout
    assert "warning: trajectories.png failed to render" in r.stderr
    r = cli("jobs", "show", JOB_ID)
    assert r.exit_code == 0 and "trajectories.png failed to render" in r.stdout


# --------------------------------------------------------------------------- list, errors
def test_list__a_failed_job_shows_its_reason_not_a_full_bar(service):
    reason = "ValueError: 'yerr' must not contain negative values"
    service.jobs = [
        job_json(status="failed", progress=1.0, error=f"Traceback (most recent call last):\n  ...\n{reason}"),
        job_json(id="f" * 32, status="running", progress=0.0,
                 metrics={"phase": "compiling", "phase_since": time.time()}),
        job_json(id="e" * 32, status="succeeded", progress=1.0, metrics={"success_rate": 0.99}),
    ]  # fmt: skip
    r = cli("jobs", "list")
    assert r.exit_code == 0, r.output
    text = r.stdout
    # the reason's last line (the exception), folded in its cell, without the traceback
    assert "ValueError: 'yerr' must not contain" in text and "Traceback" not in text
    failed = next(line for line in text.splitlines() if JOB_ID in line)
    assert "100%" not in failed and "failed" in failed
    compiling = next(line for line in text.splitlines() if "f" * 32 in line)
    assert "compiling" in compiling and "0%" not in compiling
    assert "100%" in next(line for line in text.splitlines() if "e" * 32 in line)


def test_text__names_and_ids_print_as_written_never_as_markup_or_emoji(service):
    """A map's name is the uploader's free text and a map id reads "map:<hex>:" in an error: the
    CLI prints both as written (rich read "[/]" as a closing tag and crashed `maps list`, and
    ":abcd:" as the emoji it names)."""
    name = "site [/]b [bold]x :abcd: map"
    service.maps = [{"id": "ab" * 8, "name": name, "width_px": 40, "height_px": 20,
                     "resolution": 0.05, "width_m": 2.0, "height_m": 1.0, "free_fraction": 0.5,
                     "used_by": []}]  # fmt: skip
    r = runner.invoke(app, ["maps", "list"], env={"COLUMNS": "200"})
    assert r.exit_code == 0, r.output
    assert name in r.stdout
    office = str(Path(__file__).parents[2] / "examples/maps/office.yaml")
    r = cli("jobs", "submit", "eval", "--job", JOB_ID, "--map", office)
    assert r.exit_code == 2 and f"(quicknav maps upload {office})" in r.stderr, r.stderr
    assert not service.bodies()  # a file the server cannot read is not sent
    r = cli("eval", "--policy", "oracle", "--map", "map:abcd")  # a server's map, to the library
    assert r.exit_code == 2 and not r.stdout
    assert "--map: map:abcd: names a map uploaded to a QuickNav service" in r.stderr, r.stderr


def test_bench__an_option_before_a_subcommand_is_refused_not_ignored(tmp_path):
    """`quicknav bench --grid 300 rooms` ran rooms' default grids, the --grid (the env
    benchmark's) ignored: refused, saying where the option goes; nothing runs."""
    r = cli("bench", "--grid", "300", "rooms", "--out", str(tmp_path))
    assert r.exit_code == 2 and "put it after the command: quicknav bench rooms --grid" in r.stderr
    r = cli("bench", "--steps", "1000", "train", "--out", str(tmp_path))
    assert r.exit_code == 2 and "`train` has no --steps" in r.stderr, r.stderr
    assert not any(tmp_path.iterdir())
    r = cli("bench", "rooms", "--grid", "300", "--out", str(tmp_path))
    assert r.exit_code == 2 and "--grid 300: allowed range 4..256 (EnvConfig.grid_size)" in r.stderr


def test_errors__go_to_stderr_with_a_nonzero_exit(service):
    r = cli("jobs", "submit", "deploy")
    assert r.exit_code == 2 and "train, sweep and eval" in r.stderr and not r.stdout
    r = cli("jobs", "show", "nope")
    assert r.exit_code == 1 and "no job 'nope'" in r.stderr and not r.stdout
    r = cli("jobs", "submit", "train", "--trials", "3")
    assert r.exit_code == 2 and "--trials" in r.stderr


@pytest.mark.parametrize("args", [
    ["train", "--set", "total_steps", "1000"],
    ["jobs", "submit", "train", "--set", "total_steps", "1000"],
    ["sweep", "--space", "ppo", "--set", "total_steps", "1000"],
])  # fmt: skip
def test_errors__set_with_a_space_says_to_write_key_equals_value(args):
    r = cli(*args)
    assert r.exit_code == 2, r.output
    assert "--set total_steps=1000" in r.stderr and "key=value" in r.stderr
    assert "unexpected extra argument" not in r.output


def test_eval_sets__env_prefix_spelt_as_maps_upload_prints_it_works_for_eval_jobs(service):
    """`quicknav maps upload` prints `--set env.maps.train=...` (a train job's spelling); an eval's
    --set takes env fields, and both spellings name the same field, for jobs and local evals."""
    ref = '["map:0123456789abcdef"]'
    for spelling in ("env.", ""):
        r = cli("jobs", "submit", "eval", "--policy", "oracle", "--set", f"{spelling}maps.train={ref}",
                "--set", f"{spelling}grid_size=18")  # fmt: skip
        assert r.exit_code == 0, r.output
        assert service.bodies()[-1]["env"] == {"maps.train": ["map:0123456789abcdef"], "grid_size": 18}
    local = cli("eval", "--policy", "oracle", "--set", "env.grid_size=8", "--print-config")
    assert local.exit_code == 0 and json.loads(local.stdout)["env"]["grid_size"] == 8, local.output


def test_version__prints_the_packages_version():
    r = cli("--version")
    assert r.exit_code == 0 and r.stdout.strip() == f"quicknav {package_version('quicknav')}"


# --------------------------------------------------------------------------- export
def test_export__job_downloads_the_policy_and_its_manifest(service, tmp_path):
    out = tmp_path / "policy"
    ran = cli("export", "--job", JOB_ID, "--out", str(out))
    assert ran.exit_code == 0, ran.output
    assert (out / "policy.onnx").read_bytes() == (out / "policy.json").read_bytes() == b"artifact bytes"
    fetched = [r.url.path for r in service.requests if r.method == "GET"]
    assert f"/jobs/{JOB_ID}/artifacts/policy.onnx" in fetched and f"/jobs/{JOB_ID}/artifacts/policy.json" in fetched


def test_export__bad_arguments_say_what_is_allowed(tmp_path):
    assert "give either a run folder or --job ID" in cli("export").output
    assert "give either a run folder or --job ID" in cli("export", str(tmp_path), "--job", "x").output
    bad = cli("export", str(tmp_path), "--format", "tflite")
    assert bad.exit_code != 0 and "--format 'tflite': allowed values are onnx" in bad.output
    missing = cli("export", str(tmp_path / "nope"))
    assert missing.exit_code != 0 and "does not exist" in missing.output
    empty = cli("export", str(tmp_path))
    assert empty.exit_code != 0 and "is not a run folder: no config.json" in empty.output
