"""Admission is honest: the memory the service admits a training job by (``train_memory``) is
within 10 % of the peak RSS of a process that trains it as a worker does (each case in a fresh
process, compile included: ``quicknav_core.bench.memory``).

Every case (each algorithm and network kind at two sizes) is held to the benchmark's recorded
measurement (``benchmarks/results/memory.json``) in the fast suite, so a change of the formula that
drifts from what was measured fails at once. The slow suite measures the larger size of each kind
again, live: the size where the size-dependent parts (replay buffers, env batches, rollouts) weigh
most, so a change of what training holds in memory fails there without waiting for the benchmark
to run again."""

from __future__ import annotations

import json

import pytest

from quicknav_core.bench.memory import CASES, MB, case_request, estimate, peak_rss
from tests.compile_settings import as_a_user_runs
from tests.journeys.readme import ROOT

RECORDED = {r["case"]: r for r in json.loads((ROOT / "benchmarks/results/memory.json").read_text())["rows"]}
# the larger size of each algorithm and network kind
LIVE = ("ppo-mlp-2048", "sac-1m", "td3-1m", "mlp-memory-1024", "lstm-1024", "gtrxl-2048")


def _check(name: str, est: int, measured: int) -> None:
    ratio = est / measured
    assert 0.9 <= ratio <= 1.1, (f"{name}: estimate {est / MB:.0f} MB, measured peak"
                                 f" {measured / MB:.0f} MB (ratio {ratio:.2f})")  # fmt: skip


def test_admission__the_live_cases_are_the_larger_size_of_every_kind():
    kinds = {name.rsplit("-", 1)[0] for name, _, _ in CASES}
    assert set(LIVE) <= {name for name, _, _ in CASES}
    assert {name.rsplit("-", 1)[0] for name in LIVE} == kinds
    assert set(RECORDED) == {name for name, _, _ in CASES}  # every case has been measured


@pytest.mark.parametrize("name,preset,overrides", CASES, ids=[c[0] for c in CASES])
def test_admission__estimate_within_ten_percent_of_the_recorded_peak(name, preset, overrides):
    row = RECORDED[name]
    assert (row["preset"], row["overrides"]) == (preset, overrides), row  # the case that was measured
    _check(name, estimate(case_request(preset, overrides)), row["measured_mb"] * MB)


@pytest.mark.slow  # a fresh process per case, compile included: 15-30 s each on 2 cores
@pytest.mark.parametrize("name,preset,overrides", [c for c in CASES if c[0] in LIVE],
                         ids=[c[0] for c in CASES if c[0] in LIVE])
def test_admission__estimate_within_ten_percent_of_measured_peak(name, preset, overrides):
    request = case_request(preset, overrides)
    # the process compiles as a worker does (every optimisation on; tests/compile_settings.py)
    est, measured = estimate(request), peak_rss(request, env=as_a_user_runs())
    for _ in range(2):
        if est <= 1.1 * measured:
            break
        # a process's peak varies from run to run: mlp-memory-1024 read 910-1003 MB in six runs,
        # lstm-1024 835 MB twice in one run against 888 MB recorded (2-core AMD EPYC VMs; XLA
        # compiles in threads, and how their work overlaps varies). The estimate must cover the
        # highest, so a low reading is measured again, up to twice, and the highest counts; a
        # reading above the estimate is never measured again
        measured = max(measured, peak_rss(request, env=as_a_user_runs()))
    _check(name, est, measured)
