"""The opt-in plugin that says where a test run's CPU goes (``tests/cpu_profile.py``)."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np

from tests.cpu_profile import COLUMNS, Recorder, summary


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


def test_cpu_profile__sums_every_process_by_module_costliest_first(tmp_path):
    def row(test, cpu, children=0.0):
        return json.dumps({"test": test, **dict.fromkeys(COLUMNS, 1.0), "cpu_s": cpu, "children_s": children})

    (tmp_path / "1.jsonl").write_text("\n".join([row("a.py::x", 2.0), row("b.py::y", 1.0, 9.0)]) + "\n")
    (tmp_path / "2.jsonl").write_text(row("a.py::z", 3.0) + "\n")
    rows = summary(tmp_path)
    assert [r["module"] for r in rows] == ["b.py", "a.py"]  # 10 s against 5 s
    assert rows[1]["cpu_s"] == 5.0 and rows[1]["compiles"] == 2.0
