"""Admission of evaluations against their measured peaks: the estimate (``eval_memory``) of every
evaluation case of ``quicknav_core.bench.memory`` (maps from 45 to 203 cells a side, 100 episodes)
is within 10 % of the peak RSS the benchmark measured, and never more than 3 % under it.

The measurements are the benchmark's (a 203-cell evaluation runs for half an hour on 2 cores); this
test holds the estimate to them, so a change of the formula that drifts from what was measured
fails here, and a change of the evaluation's memory shows when the benchmark runs again."""

from __future__ import annotations

import json

import pytest

from quicknav_core.bench.memory import EVAL_CASES, eval_case
from quicknav_core.train.memory import MB, eval_memory
from tests.journeys.readme import ROOT

MEASURED = {r["case"]: r for r in json.loads((ROOT / "benchmarks/results/memory.json").read_text())["eval_rows"]}


@pytest.mark.parametrize("name,map_path,cell_m,policy", EVAL_CASES, ids=[c[0] for c in EVAL_CASES])
def test_eval_admission__estimate_within_ten_percent_of_the_measured_peak(name, map_path, cell_m, policy):
    row = MEASURED[name]  # every case has been measured
    cfg = eval_case(str(ROOT / map_path), cell_m, policy)
    # the grid that was measured: the map's own rows x cols, not a square around it
    assert (cfg.env.grid_size, list(cfg.env.grid_shape), cfg.episodes) == (
        row["grid_size"], row["grid"], row["episodes"]), row  # fmt: skip
    est = eval_memory(cfg)
    ratio = est.total / (row["measured_mb"] * MB)
    assert 0.97 <= ratio <= 1.1, f"{name}: estimate {est.describe()}; measured {row['measured_mb']} MB"
