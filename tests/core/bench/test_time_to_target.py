"""`quicknav bench time-to-target`: the evaluation schedule, the summary, the table, and one real
run (slow): the clock counts training and compilation, never the evaluations."""

from __future__ import annotations

import json

import pytest

from quicknav_core.bench import time_to_target as ttt


def test_schedule__evaluates_after_ten_percent_more_training_time():
    assert ttt.evaluation_due(1.0, 0.0)
    assert not ttt.evaluation_due(0.5, 0.0)
    assert not ttt.evaluation_due(100.0, 100.0) and not ttt.evaluation_due(110.9, 100.0)
    assert ttt.evaluation_due(111.5, 100.0)


def _run(reached, t, cap=600.0):
    return {"reached": reached, "time_to_target_s": t if reached else None, "cap_s": cap}


def test_summary__median_only_when_every_seed_reached_the_target():
    s = ttt.summarize([_run(True, 12.0), _run(True, 9.0), _run(True, 30.0)])
    assert (s["median_s"], s["min_s"], s["max_s"], s["reached"]) == (12.0, 9.0, 30.0, 3)
    s = ttt.summarize([_run(True, 12.0), _run(False, None), _run(True, 30.0)])
    assert s["median_s"] is None and s["reached"] == 2 and s["times_s"] == [12.0, None, 30.0]


def test_report__each_row_beside_its_peer_with_the_ratio(tmp_path):
    ours = {"machine": {"cpu": "Test CPU", "cores": 2}, "rows": {
        "ppo": {"label": "PPO (MLP 2x128)", "cap_s": 600, "cold": _run(True, 20.0),
                "warm_summary": ttt.summarize([_run(True, 10.0), _run(True, 12.0), _run(True, 11.0)])},
        "lstm": {"label": "PPO + LSTM", "cap_s": 600, "cold": _run(False, None),
                 "warm_summary": ttt.summarize([_run(False, None)] * 3)}}}  # fmt: skip
    peers = {"machine": {"cpu": "Peer CPU", "cores": 2}, "rows": {
        "ppo": {"label": "SB3 PPO", "beside": "ppo", "runs": [_run(True, 55.0, 1800)] * 3,
                "summary": ttt.summarize([_run(True, 55.0), _run(True, 44.0), _run(True, 66.0)])},
        "lstm": {"label": "RecurrentPPO", "beside": "lstm", "runs": [_run(False, None, 1800)] * 3,
                 "summary": ttt.summarize([_run(False, None, 1800)] * 3)}}}  # fmt: skip
    (tmp_path / "a.json").write_text(json.dumps(ours))
    (tmp_path / "b.json").write_text(json.dumps(peers))
    table = ttt.report(tmp_path / "a.json", tmp_path / "b.json")
    ppo = next(line for line in table.splitlines() if line.startswith("| PPO (MLP"))
    assert "11.0 s (10.0 s–12.0 s)" in ppo and "20.0 s" in ppo and "SB3 PPO: 55.0 s" in ppo
    assert ppo.rstrip(" |").endswith("5.0x")
    lstm = next(line for line in table.splitlines() if line.startswith("| PPO + LSTM"))
    assert "0/3 seeds reached 90 %" in lstm and "not reached" in lstm
    # each figure names the machine it was measured on
    assert "[A] Test CPU, 2 cores" in table and "[B] Peer CPU, 2 cores" in table
    assert "[A]" in ppo and "[B]" in ppo and "cap 30.0 min per run" in lstm


@pytest.mark.slow  # trains a small PPO until it reaches the target or a minute: ~20 s
def test_run__the_clock_counts_training_not_evaluations(tmp_path):
    row = ttt.Row("tiny", "tiny", "fast-ppo", cap_minutes=1.0, overrides=(
        ("env.grid_size", 8), ("env.train_rooms", 64), ("env.test_rooms", 32)))  # fmt: skip
    cold = ttt.run_one(row, 0, 60.0, "cold")
    assert cold.evaluations and cold.first_chunk_s > 0
    times = [e.train_s for e in cold.evaluations]
    assert times == sorted(times) and all(e.eval_s > 0 for e in cold.evaluations)
    # the evaluations' time is kept apart: training time + evaluation time is the wall time
    assert cold.train_s >= times[-1] - 1e-3 and cold.eval_s == pytest.approx(
        sum(e.eval_s for e in cold.evaluations), abs=0.01)  # fmt: skip
    if cold.reached:
        assert cold.time_to_target_s == pytest.approx(times[-1], abs=1e-3)
        assert cold.evaluations[-1].success >= 0.9
        assert all(e.success < 0.9 for e in cold.evaluations[:-1])


def test_pages__readme_and_the_performance_page_show_the_recorded_table():
    """README's and docs/performance.md's tables are what the recorded results say (written there
    by `quicknav bench time-to-target --report --write-to PAGE`), so the two cannot drift."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[3]
    results = root / "benchmarks/results"
    table = ttt.report(results / "time_to_target.json", results / "time_to_target_peers.json")
    for page in ("README.md", "docs/performance.md"):
        assert ttt.between_markers((root / page).read_text()) == table.strip(), page


def test_pages__writing_the_table_keeps_the_rest_of_the_page(tmp_path):
    page = tmp_path / "page.md"
    page.write_text(f"# Title\n\n{ttt.MARKERS[0]}\nold\n{ttt.MARKERS[1]}\n\nafter\n")
    ttt.write_between_markers(page, "| new |")
    assert page.read_text() == f"# Title\n\n{ttt.MARKERS[0]}\n| new |\n{ttt.MARKERS[1]}\n\nafter\n"
    other = tmp_path / "other.md"
    other.write_text("no markers")
    with pytest.raises(ValueError, match=r"other\.md: no <!-- time-to-target:start -->"):
        ttt.write_between_markers(other, "x")
