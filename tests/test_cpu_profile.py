"""The opt-in plugin that says where a test run's CPU goes (``tests/cpu_profile.py``)."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np

from tests.cpu_profile import COLUMNS, MODULE_SECONDS, Recorder, module_seconds, programs, summary


def test_cpu_profile__counts_a_compile_and_its_cpu():
    recorder = Recorder()
    row: dict = {}
    with recorder.measure(row):  # a program no other test compiles: traced, lowered, compiled
        jax.jit(lambda x: jnp.sin(x) * 2.7182817 + 0.1234567)(np.ones((13, 3), np.float32)).block_until_ready()
    assert set(COLUMNS) <= set(row)
    assert row["compiles"] + row["cache_hits"] == 1 and row["trace_s"] > 0 and row["lower_s"] > 0
    assert row["cpu_s"] > 0 and row["wall_s"] > 0
    quiet: dict = {}
    with recorder.measure(quiet):  # nothing compiled: nothing counted
        sum(range(1000))
    assert quiet["compiles"] == quiet["cache_hits"] == 0 and quiet["compile_s"] == 0
    # and by program, in one row: XLA's step, tracing and lowering of the jitted lambda (JAX names
    # its trace "<lambda>", its lowering and XLA step "jit(<lambda>)")
    xla, trace, lower, steps = recorder.programs["jit(<lambda>)"]
    assert steps == 1 and xla > 0 and lower > 0 and trace == row["trace_s"] > 0
    assert "<lambda>" not in recorder.programs


def test_cpu_profile__sums_each_programs_seconds_over_the_processes_costliest_first(tmp_path):
    (tmp_path / "1.programs.json").write_text(json.dumps({"jit(run)": [4.0, 0.0, 1.0, 2], "jit(add)": [0.1, 0.0, 0.1, 9]}))
    (tmp_path / "2.programs.json").write_text(json.dumps({"jit(run)": [2.0, 0.0, 0.5, 1], "run": [0.0, 3.0, 0.0, 0]}))
    assert programs(tmp_path) == [("jit(run)", [6.0, 0.0, 1.5, 3]), ("run", [0.0, 3.0, 0.0, 0]),
                                  ("jit(add)", [0.1, 0.0, 0.1, 9])]  # fmt: skip


def test_cpu_profile__sums_every_process_by_module_costliest_first(tmp_path):
    def row(test, cpu, children=0.0):
        return json.dumps({"test": test, **dict.fromkeys(COLUMNS, 1.0), "cpu_s": cpu, "children_s": children})

    (tmp_path / "1.jsonl").write_text("\n".join([row("a.py::x", 2.0), row("b.py::y", 1.0, 9.0)]) + "\n")
    (tmp_path / "2.jsonl").write_text(row("a.py::z", 3.0) + "\n")
    rows = summary(tmp_path)
    assert [r["module"] for r in rows] == ["b.py", "a.py"]  # 10 s against 5 s
    assert rows[1]["cpu_s"] == 5.0 and rows[1]["compiles"] == 2.0


def test_module_seconds__sums_each_modules_rows_per_suite(tmp_path):
    def row(test, wall, slow=False):
        return json.dumps({"test": test, **dict.fromkeys(COLUMNS, 0.0), "wall_s": wall, "slow": slow})

    (tmp_path / "1.jsonl").write_text("\n".join([row("a.py::x", 2.0), row("a.py::y", 30.0, slow=True)]) + "\n")
    (tmp_path / "2.jsonl").write_text("\n".join([row("a.py::z", 1.5), row("b.py::w", 4.0)]) + "\n")
    assert module_seconds(tmp_path) == {"fast": {"a.py": 3.5, "b.py": 4.0}, "slow": {"a.py": 30.0}}


class _Item:
    def __init__(self, nodeid: str, slow: bool = False):
        self.nodeid, self.slow = nodeid, slow

    def get_closest_marker(self, name):
        return object() if name == "slow" and self.slow else None


def test_module_order__unknown_first_then_the_longest_counting_the_suites_this_run_holds(monkeypatch, tmp_path):
    from tests import conftest, cpu_profile

    recorded = tmp_path / "module_seconds.json"
    recorded.write_text(json.dumps({"fast": {"a.py": 5.0, "b.py": 40.0, "c.py": 20.0}, "slow": {"a.py": 100.0}}))
    monkeypatch.setattr(cpu_profile, "MODULE_SECONDS", recorded)
    items = [_Item("a.py::f"), _Item("b.py::g"), _Item("c.py::h"), _Item("c.py::i"), _Item("new.py::j")]
    conftest.pytest_collection_modifyitems(items)
    assert [i.nodeid for i in items] == ["new.py::j", "b.py::g", "c.py::h", "c.py::i", "a.py::f"]
    # a's slow test in the run: its 100 s count, it goes first of the known
    items = [_Item("a.py::f"), _Item("b.py::g"), _Item("a.py::s", slow=True)]
    conftest.pytest_collection_modifyitems(items)
    assert [i.nodeid for i in items] == ["a.py::f", "a.py::s", "b.py::g"]


def test_module_seconds__names_only_modules_that_exist():
    """A renamed or removed module's entry would only mislead the order: the file is refreshed
    (``python -m tests.cpu_profile FOLDER``) when modules move."""
    doc = json.loads(MODULE_SECONDS.read_text())
    root = MODULE_SECONDS.parent.parent
    missing = [m for suite in ("fast", "slow") for m in doc[suite] if not (root / m).is_file()]
    assert not missing, f"tests/module_seconds.json names modules that are gone: {missing}"
