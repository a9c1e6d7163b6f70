"""Where a test run's CPU goes, per module: an opt-in pytest plugin for work on the suite's time.

    uv run pytest -m "not slow" -p tests.cpu_profile

At the end it prints one row per test module (the costliest first): wall seconds, CPU seconds of
the test process, CPU of the child processes it reaped (CLI commands, workers, servers; a module
fixture's server is counted where its teardown reaps it), and JAX's share of the test process: XLA
compiles, the seconds of XLA's step (compiling, or loading from JAX's persistent cache), the seconds
tracing and lowering to MLIR (paid on a cache hit too), and the programs loaded from that cache.
Then the costliest programs by JAX's name for them (``jit(run)``: the evaluation's episode runner,
``jit(<lambda>)``: every jitted lambda), summed over the test processes. Every test's row is
written, as JSON lines, to the folder it names (``QUICKNAV_CPU_PROFILE``, a temporary folder if
unset), one file per process, and each process's seconds per program beside it.

The modules' wall seconds, the order xdist is given them in (``tests/conftest.py``), come from such a
run of both suites: ``python -m tests.cpu_profile FOLDER`` writes them to
``tests/module_seconds.json``.

On the fast suite of 2026-11 (2-core AMD EPYC VM): the test processes' CPU was 670 s, 602 s of it
JAX's (3,266 programs compiled and 1,703 loaded from the cache, 358 s; tracing 106 s; lowering
138 s): a test that builds fewer programs is quicker, one that runs a little less rarely is.
"""

from __future__ import annotations

import contextlib
import json
import os
import resource
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import pytest

FOLDER = "QUICKNAV_CPU_PROFILE"
_EVENTS = {
    "/jax/core/compile/backend_compile_duration": "compile_s",
    "/jax/core/compile/jaxpr_trace_duration": "trace_s",
    "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower_s",
}
COLUMNS = ("wall_s", "cpu_s", "children_s", "compiles", "compile_s", "trace_s", "lower_s", "cache_hits")


class Recorder:
    """Counts JAX's compile events in this process and measures a block's CPU and wall time."""

    def __init__(self) -> None:
        import jax.monitoring as monitoring

        self.totals: dict[str, float] = defaultdict(float)
        # per program name (JAX's ``fun_name``): [XLA step s, tracing s, lowering s, XLA steps]
        self.programs: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0, 0.0, 0])
        monitoring.register_event_duration_secs_listener(self._duration)
        monitoring.register_event_listener(self._event)

    def _duration(self, event: str, duration: float, fun_name: str = "?", **_) -> None:
        if event in _EVENTS:
            self.totals[_EVENTS[event]] += duration
            # JAX names a trace by the function ("run") and its lowering and XLA step by the
            # program ("jit(run)"): one row per program
            if event == "/jax/core/compile/jaxpr_trace_duration" and not fun_name.startswith("jit("):
                fun_name = f"jit({fun_name})"
            per = self.programs[fun_name]
            per[("compile_s", "trace_s", "lower_s").index(_EVENTS[event])] += duration
            per[3] += event == "/jax/core/compile/backend_compile_duration"
            # JAX times its XLA step with a persistent cache read inside: a hit counts here too
            self.totals["programs"] += event == "/jax/core/compile/backend_compile_duration"

    def _event(self, event: str, **_) -> None:
        if event == "/jax/compilation_cache/cache_hits":
            self.totals["cache_hits"] += 1

    @contextlib.contextmanager
    def measure(self, row: dict):
        """Fill ``row`` with the block's figures (COLUMNS)."""
        before, wall = dict(self.totals), time.perf_counter()
        own, children = _cpu(resource.RUSAGE_SELF), _cpu(resource.RUSAGE_CHILDREN)
        try:
            yield row
        finally:
            row["wall_s"] = time.perf_counter() - wall
            row["cpu_s"] = _cpu(resource.RUSAGE_SELF) - own
            row["children_s"] = _cpu(resource.RUSAGE_CHILDREN) - children
            for key in ("programs", "compile_s", "trace_s", "lower_s", "cache_hits"):
                row[key] = self.totals.get(key, 0.0) - before.get(key, 0.0)
            row["compiles"] = row.pop("programs") - row["cache_hits"]


def _cpu(who: int) -> float:
    usage = resource.getrusage(who)
    return usage.ru_utime + usage.ru_stime


def summary(folder: Path) -> list[dict]:
    """One row per test module from every process's file in ``folder``, the costliest first."""
    modules: dict[str, dict] = {}
    for path in folder.glob("*.jsonl"):
        for line in path.read_text().splitlines():
            test = json.loads(line)
            row = modules.setdefault(test["test"].split("::", 1)[0], dict.fromkeys(COLUMNS, 0.0))
            for key in COLUMNS:
                row[key] += test[key]
    rows = [{"module": name, **row} for name, row in modules.items()]
    return sorted(rows, key=lambda r: -(r["cpu_s"] + r["children_s"]))


_recorder: Recorder | None = None


def pytest_configure(config) -> None:
    global _recorder  # this plugin's own state, in a test process only
    if not os.environ.get(FOLDER):  # the first process names it; xdist workers inherit it
        os.environ[FOLDER] = tempfile.mkdtemp(prefix="quicknav-cpu-profile-")
    Path(os.environ[FOLDER]).mkdir(parents=True, exist_ok=True)  # a folder the user named
    _recorder = Recorder()


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    row = {"test": item.nodeid, "slow": item.get_closest_marker("slow") is not None}
    with _recorder.measure(row):
        yield
    with open(Path(os.environ[FOLDER]) / f"{os.getpid()}.jsonl", "a") as out:
        out.write(json.dumps(row) + "\n")


def pytest_sessionfinish(session) -> None:
    """This process's seconds per program name, for the summary's list of the costliest."""
    if _recorder is not None:
        out = Path(os.environ[FOLDER]) / f"{os.getpid()}.programs.json"
        out.write_text(json.dumps(dict(_recorder.programs)))


def programs(folder: Path) -> list[tuple[str, list[float]]]:
    """Every test process's seconds per program name in ``folder``, summed, the costliest first:
    (name, [XLA step s, tracing s, lowering s, XLA steps])."""
    total: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0, 0.0, 0])
    for path in folder.glob("*.programs.json"):
        for name, figures in json.loads(path.read_text()).items():
            total[name] = [a + b for a, b in zip(total[name], figures, strict=True)]
    return sorted(total.items(), key=lambda kv: -sum(kv[1][:3]))


def pytest_terminal_summary(terminalreporter) -> None:
    if hasattr(terminalreporter.config, "workerinput"):
        return  # an xdist worker: the controller prints
    folder = Path(os.environ[FOLDER])
    rows = summary(folder)
    write = terminalreporter.write_line
    write("")
    write(f"CPU per test module (tests.cpu_profile; every test's row in {folder})")
    write(f"{'module':58s} {'wall':>6s} {'cpu':>6s} {'child':>6s} {'XLA n':>6s} {'XLA s':>6s}"
          f" {'trace':>6s} {'lower':>6s} {'hits':>5s}")  # fmt: skip
    for r in rows:
        write(f"{r['module'][-58:]:58s} {r['wall_s']:6.1f} {r['cpu_s']:6.1f} {r['children_s']:6.1f}"
              f" {r['compiles']:6.0f} {r['compile_s']:6.1f} {r['trace_s']:6.1f} {r['lower_s']:6.1f}"
              f" {r['cache_hits']:5.0f}")  # fmt: skip
    total = {k: sum(r[k] for r in rows) for k in COLUMNS}
    write(f"{'all':58s} {total['wall_s']:6.1f} {total['cpu_s']:6.1f} {total['children_s']:6.1f}"
          f" {total['compiles']:6.0f} {total['compile_s']:6.1f} {total['trace_s']:6.1f}"
          f" {total['lower_s']:6.1f} {total['cache_hits']:5.0f}")  # fmt: skip
    write("")
    write("The costliest programs by name (test processes; XLA's step counts a cache load too)")
    write(f"{'program':58s} {'XLA s':>6s} {'trace':>6s} {'lower':>6s} {'steps':>6s}")
    for name, (xla, trace, lower, steps) in programs(folder)[:30]:
        write(f"{name[-58:]:58s} {xla:6.1f} {trace:6.1f} {lower:6.1f} {steps:6.0f}")


MODULE_SECONDS = Path(__file__).with_name("module_seconds.json")


def module_seconds(folder: Path) -> dict[str, dict[str, float]]:
    """Each test module's wall seconds in ``folder``'s rows, per suite (``fast``: its tests not
    marked slow, ``slow``: those marked), a module's tests of a suite being one xdist work unit."""
    out: dict[str, dict[str, float]] = {"fast": {}, "slow": {}}
    for path in sorted(folder.glob("*.jsonl")):
        for line in path.read_text().splitlines():
            test = json.loads(line)
            suite = out["slow" if test.get("slow") else "fast"]
            module = test["test"].split("::", 1)[0]
            suite[module] = suite.get(module, 0.0) + test["wall_s"]
    return {k: {m: round(s, 1) for m, s in sorted(v.items())} for k, v in out.items()}


def main(argv: list[str] | None = None) -> None:
    import argparse
    import platform

    parser = argparse.ArgumentParser(description="Write tests/module_seconds.json from a profiled run"
                                     " of both suites (the folder QUICKNAV_CPU_PROFILE named).")  # fmt: skip
    parser.add_argument("folder", type=Path)
    parser.add_argument("--machine", default=platform.processor() or platform.machine(),
                        help="the machine the run was on, in words")  # fmt: skip
    args = parser.parse_args(argv)
    seconds = module_seconds(args.folder)
    if not seconds["fast"] or not seconds["slow"]:
        raise SystemExit(f"{args.folder} holds rows of {'the slow suite only' if seconds['slow'] else 'the fast suite only'}"
                         " (or none): profile both suites into one folder")  # fmt: skip
    doc = {"about": "wall seconds of each test module per suite, from one profiled run of both (tests/"
                    "cpu_profile.py); tests/conftest.py hands xdist the modules longest first",
           "machine": args.machine, "recorded": time.strftime("%Y-%m-%d"), **seconds}  # fmt: skip
    MODULE_SECONDS.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"wrote {MODULE_SECONDS}: {len(seconds['fast'])} modules of the fast suite, {len(seconds['slow'])} of the slow")


if __name__ == "__main__":
    main()
