"""Admission is honest: the memory the service admits a training job by (``train_memory``) is
within 10 % of the peak RSS of a process that trains it as a worker does, for every algorithm and
network kind at two sizes (each case in a fresh process: ``quicknav_core.bench.memory``)."""

from __future__ import annotations

import pytest

from quicknav_core.bench.memory import CASES, MB, case_request, estimate, peak_rss
from tests.compile_settings import as_a_user_runs

pytestmark = pytest.mark.long_module(230)  # twelve measured processes, ~230 s


@pytest.mark.slow  # a fresh process per case, compile included: 20-60 s each on 2 cores
@pytest.mark.parametrize("name,preset,overrides", CASES, ids=[c[0] for c in CASES])
def test_admission__estimate_within_ten_percent_of_measured_peak(name, preset, overrides):
    request = case_request(preset, overrides)
    # the process compiles as a worker does (every optimisation on; tests/compile_settings.py)
    measured, est = peak_rss(request, env=as_a_user_runs()), estimate(request)
    ratio = est / measured
    assert 0.9 <= ratio <= 1.1, (f"{name}: estimate {est / MB:.0f} MB, measured peak"
                                 f" {measured / MB:.0f} MB (ratio {ratio:.2f})")  # fmt: skip
