"""IQM, stratified-bootstrap intervals and performance profiles (quicknav_core.eval.aggregate)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from quicknav_core.eval.aggregate import interval, iqm, mean, performance_profile
from quicknav_core.eval.pictures import draw_profiles


def test_iqm__is_the_mean_of_the_middle_half():
    x = np.array([0.0, 100.0, 1.0, 2.0, 3.0, 4.0, 5.0, -50.0])  # sorted: -50 0 1 2 3 4 5 100
    assert iqm(x) == pytest.approx(np.mean([1.0, 2.0, 3.0, 4.0]))
    assert iqm(np.arange(100.0)) == pytest.approx(np.mean(np.arange(25.0, 75.0)))


def test_interval__stratified_keeps_every_episode():
    """Seeds that agree on every episode leave nothing to resample inside a stratum: the interval
    has zero width, where a bootstrap over all cells pooled would not."""
    per_episode = np.linspace(0.0, 1.0, 40)
    scores = np.tile(per_episode, (3, 1))
    point, lo, hi = interval(scores, iqm)
    assert point == pytest.approx(iqm(per_episode))
    assert lo == pytest.approx(point) and hi == pytest.approx(point)
    rng = np.random.default_rng(0)
    flat = scores.reshape(-1)
    pooled = [iqm(flat[rng.integers(0, flat.size, flat.size)]) for _ in range(500)]
    assert np.percentile(pooled, 97.5) - np.percentile(pooled, 2.5) > 0.05


def test_interval__matches_a_resampling_written_out_by_hand():
    rng = np.random.default_rng(1)
    scores = np.clip(rng.normal(0.7, 0.25, size=(3, 60)) + rng.normal(0, 0.1, size=(3, 1)), 0, 1)
    for statistic in (mean, iqm):
        point, lo, hi = interval(scores, statistic, resamples=4000, seed=3)
        draws = []
        ref_rng = np.random.default_rng(7)
        for _ in range(4000):
            pick = ref_rng.integers(0, 3, size=scores.shape)  # a seed per (slot, episode)
            draws.append(statistic(np.take_along_axis(scores, pick, axis=0).reshape(-1)))
        ref_lo, ref_hi = np.percentile(draws, [2.5, 97.5])
        assert lo < point < hi
        assert lo == pytest.approx(ref_lo, abs=0.01) and hi == pytest.approx(ref_hi, abs=0.01)


def test_interval__one_seed_has_no_interval_and_bad_shapes_are_refused():
    point, lo, hi = interval(np.array([[0.0, 1.0, 1.0, 1.0]]), mean)
    assert point == 0.75 and np.isnan(lo) and np.isnan(hi)
    with pytest.raises(ValueError, match="seeds, episodes"):
        interval(np.zeros(5))


def test_performance_profile__fraction_above_each_threshold(tmp_path):
    rng = np.random.default_rng(2)
    scores = rng.random((3, 50))
    taus = np.array([0.0, 0.25, 0.5, 0.9, 1.0])
    point, lo, hi = performance_profile(scores, taus)
    assert point == pytest.approx([(scores > t).mean() for t in taus])
    assert np.all(lo <= point + 1e-12) and np.all(point <= hi + 1e-12)
    assert point[-1] == 0.0 and hi[-1] == 0.0
    path = draw_profiles([("A", [("row a", scores, False), ("row b", scores * 0.5, True)]),
                          ("B", [])], tmp_path / "p.png")  # fmt: skip
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _run(seed: int, success: list[int], steps: list[int], spl_ratio: float) -> dict:
    n = len(success)
    metrics = {
        "episodes": n, "success_rate": sum(success) / n, "success_ci95": [0.0, 1.0],
        "steps_to_goal_successes": {"mean": 60.0, "std": 5.0},
        "steps_to_goal_failures_as_limit": {"mean": float(np.mean([s if k else 300 for s, k in zip(steps, success, strict=False)])), "std": 9.0},
        "return": {"mean": 90.0, "std": 3.0}, "collisions_per_episode": 0.5, "timeout_rate": 0.0,
        "spl": 0.9, "path_length_successes": {"mean": 5.0, "std": 1.0},
        "reference_length": {"mean": 5.0, "std": 1.0}, "steps_lower_bound": {"mean": 50.0, "std": 1.0},
    }  # fmt: skip
    per = {"success": success, "steps": steps, "return": [0.0] * n, "collisions": [0] * n,
           "path_length": [4.0 / spl_ratio] * n, "reference_length": [4.0] * n}  # fmt: skip
    return {"metrics": metrics, "per_episode": per, "training": {"seed": seed, "minutes": 5.0}}


def test_build_report__aggregates_rows_with_episodes_and_writes_profiles(tmp_path):
    from quicknav_core.bench.learning import build_report, dump_report

    results = {
        "paper-td3-shaped": [_run(s, [1] * 9 + [s % 2], [50 + s] * 10, 0.8) for s in range(3)],
        "paper-td3": [{"metrics": _run(0, [0] * 10, [1] * 10, 1.0)["metrics"], "training": {"seed": 0}}],
    }
    markdown, data = build_report(results, {}, 3, profile_path=tmp_path / "profiles.png")
    agg = data["rows"]["paper-td3-shaped"]["aggregate"]
    assert agg["seeds"] == 3 and agg["episodes"] == 10
    assert agg["success_mean"]["point"] == pytest.approx(28 / 30)
    lo, hi = agg["success_mean"]["ci95"]
    assert lo < 28 / 30 < hi <= 1.0
    # SPL of a success = reference / path: 0.8 here; failures score 0
    assert agg["spl_mean"]["point"] == pytest.approx(0.8 * 28 / 30, rel=1e-3)
    assert data["rows"]["paper-td3-shaped"]["runs"][0]["per_episode"]["steps"][-1] == 300
    assert data["rows"]["paper-td3"]["aggregate"] is None
    assert "| TD3 (MLP 2x128), shaped reward | shaped | 3 x 10 | 0.933 [" in markdown
    assert "| TD3 (MLP 2x128) | paper | - | n/a" in markdown
    target = next(t for t in data["targets"] if t["target"].startswith("TD3"))
    assert target["met"] and target["measured"]["row"] == "paper-td3-shaped"
    assert (tmp_path / "profiles.png").exists()
    text = dump_report(data)
    assert json.loads(text) == json.loads(json.dumps(data))
    assert '"success": [1, 1, 1, 1, 1, 1, 1, 1, 1, 0]' in text  # episode lists on one line
