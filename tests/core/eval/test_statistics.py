"""Properties of evaluation statistics over every size (Hypothesis), and pictures that fail.

The bug these hold down: ``wilson_interval(n, n)`` came back with an upper bound of
0.9999999999999999 for 57 of the sizes 1..200, ``draw_difficulty``'s error bar went negative and
matplotlib refused it, which failed every evaluation of a policy good enough to clear a bin.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from quicknav_core.eval.aggregate import interval, iqm, mean, performance_profile
from quicknav_core.eval.statistics import spl, wilson_interval

sizes = st.integers(min_value=1, max_value=100_000)


@st.composite
def counts(draw):
    n = draw(sizes)
    k = draw(st.one_of(st.just(0), st.just(n), st.integers(min_value=0, max_value=n)))
    return k, n


@given(counts())
@settings(max_examples=2000, deadline=None)
def test_wilson__bounds_in_unit_interval_and_around_the_rate(kn):
    k, n = kn
    lo, hi = wilson_interval(k, n)
    p = k / n
    assert 0.0 <= lo <= p <= hi <= 1.0
    if k == n:
        assert hi == 1.0  # exactly, not 0.9999999999999999
    if k == 0:
        assert lo == 0.0


def test_wilson__every_size_up_to_500_at_both_edges():
    # the exhaustive form of the property at the edges, where rounding bit before
    for n in range(1, 501):
        assert wilson_interval(n, n)[1] == 1.0 and wilson_interval(0, n)[0] == 0.0
        for k in range(n + 1):
            lo, hi = wilson_interval(k, n)
            assert lo <= k / n <= hi


def test_wilson__refuses_impossible_counts_and_is_nan_for_nothing():
    with pytest.raises(ValueError, match="successes"):
        wilson_interval(5, 4)
    with pytest.raises(ValueError, match="successes"):
        wilson_interval(-1, 4)
    assert all(np.isnan(wilson_interval(0, 0)))


@given(st.lists(st.tuples(st.booleans(), st.floats(0, 50), st.floats(0, 50)), min_size=1, max_size=200))
@settings(max_examples=500, deadline=None)
def test_spl__inside_unit_interval(rows):
    success, path, ref = (np.array(c) for c in zip(*rows, strict=True))
    value = spl(success, path.astype(np.float32), ref.astype(np.float32))
    assert 0.0 <= value <= 1.0
    if success.all() and np.all(path <= ref) and np.all(ref > 0.01):  # as short as the oracle's
        assert value == pytest.approx(1.0)


@given(
    st.integers(2, 5).flatmap(
        lambda seeds: st.lists(
            st.lists(st.sampled_from([0.0, 0.92, 1.0, 0.5]), min_size=3, max_size=3),
            min_size=seeds, max_size=seeds,
        )
    ),
    st.sampled_from([mean, iqm]),
)
@settings(max_examples=60, deadline=None)
def test_bootstrap_interval__holds_its_point_inside_the_data_range(matrix, statistic):
    scores = np.array(matrix)
    point, lo, hi = interval(scores, statistic, resamples=200)
    assert scores.min() <= lo <= point <= hi <= scores.max()


def test_bootstrap_interval__the_found_case_an_iqm_of_equal_scores_one_ulp_above_them():
    """Hypothesis found it in CI: the IQM of 0.92s computed as 0.9200000000000002, above the
    data's maximum; the point is pinned to the data's range as the interval is."""
    scores = np.array([[0.0, 0.0, 0.92], [0.92, 0.92, 0.92], [0.92, 0.92, 0.92]])
    point, lo, hi = interval(scores, iqm, resamples=200)
    assert scores.min() <= lo <= point <= hi <= scores.max() and point == 0.92


def test_performance_profile__bands_hold_the_curve():
    rng = np.random.default_rng(0)
    scores = np.clip(rng.normal(0.9, 0.1, size=(3, 40)), 0, 1)
    taus = np.linspace(0, 1, 21)
    point, lo, hi = performance_profile(scores, taus, resamples=300)
    assert np.all((lo >= 0) & (lo <= point) & (point <= hi) & (hi <= 1))


def test_difficulty_picture__draws_a_bin_where_every_episode_succeeded(tmp_path):
    """The reported case: a bin of 7 episodes all reached (wilson's upper end was 1 - 1e-16)."""
    from quicknav_core.eval.pictures import draw_difficulty

    rows = [{"path_m": [0.0, 2.0], "episodes": n, "success_rate": 1.0,
             "success_ci95": list(wilson_interval(n, n)), "spl": 0.9} for n in (7, 13, 200)]  # fmt: skip
    # and a row as an older eval.json wrote it, with the rounded upper end
    rows.append({"path_m": [2.0, None], "episodes": 7, "success_rate": 1.0,
                 "success_ci95": [0.6457, 0.9999999999999999], "spl": 0.9})  # fmt: skip
    out = draw_difficulty(rows, tmp_path / "difficulty.png")
    assert out.stat().st_size > 1000


def test_evaluate__a_picture_that_fails_is_a_warning_and_the_numbers_stay(tmp_path, monkeypatch):
    """Every picture of the evaluation raises: eval.json and replay.json are written anyway, and
    the result (and eval.json) names each picture that is missing."""
    from quicknav_core.config import EnvConfig, EvalConfig
    from quicknav_core.eval import pictures
    from quicknav_core.eval.evaluate import evaluate
    from quicknav_core.eval.scripted import baseline_agent

    def broken(*args, **kwargs):
        raise ValueError("'yerr' must not contain negative values")

    for name in ("draw_trajectories", "draw_difficulty", "draw_gif"):
        monkeypatch.setattr(pictures, name, broken)
    env = EnvConfig(grid_size=8, train_rooms=8, test_rooms=8, max_steps=40)
    cfg = EvalConfig(policy="oracle", episodes=4, gif_episodes=1, pictures=True)
    result, _ = evaluate(env, baseline_agent("oracle", env), cfg, tmp_path)
    assert sorted(w.split(" ")[0] for w in result["warnings"]) == [
        "difficulty.png", "episodes.gif", "trajectories.png"]  # fmt: skip
    assert "negative values" in result["warnings"][0]
    stored = json.loads((tmp_path / "eval.json").read_text())
    assert stored["warnings"] == result["warnings"]
    assert stored["metrics"]["episodes"] == 4 and (tmp_path / "replay.json").exists()
    assert not any((tmp_path / n).exists() for n in ("difficulty.png", "episodes.gif", "trajectories.png"))


def test_pictures__an_episode_a_collision_ended_is_called_collided_not_timed_out():
    from types import SimpleNamespace

    from quicknav_core.config import EnvConfig
    from quicknav_core.eval.episodes import outcome

    ep = SimpleNamespace(success=np.array([True, False, False, False]),
                         collisions=np.array([0, 1, 0, 2]), steps=np.array([40, 17, 300, 300]))  # fmt: skip
    ends = EnvConfig(end_on_collision=True)
    assert [outcome(ep, i, ends) for i in range(4)] == ["reached", "collided", "timed out", "timed out"]
    slides = EnvConfig()  # the paper's env: a collision never ends an episode
    assert [outcome(ep, i, slides) for i in range(4)] == ["reached", "timed out", "timed out", "timed out"]


def test_pictures__a_corridors_trajectories_side_by_side_not_strips_of_a_square():
    """``draw_trajectories``' panels follow the maps' shape: nine views of a 2 m x 16 m corridor
    in a row of tall panels, of a 16 m x 2 m one in a column of wide panels, square-ish rooms
    (or a mix) in the 3 x 3 grid."""
    from quicknav_core.eval.pictures import trajectory_panels

    rows, cols, (w, h) = trajectory_panels([(2.0, 16.0)] * 9)
    assert (rows, cols) == (1, 9) and h == 9.6 and 9 * 1.1 < w < 18, (w, h)
    rows, cols, (w, h) = trajectory_panels([(16.0, 2.0)] * 9)
    assert (rows, cols) == (9, 1) and w == 9.4 and h > 9 * 1.1, (w, h)
    assert trajectory_panels([(8.0, 8.0)] * 9) == (3, 3, (9.0, 9.4))
    assert trajectory_panels([(2.0, 16.0), (8.0, 8.0)])[:2] == (3, 3)  # one map not narrow: the grid
    assert trajectory_panels([(2.0, 16.0)] * 3)[:2] == (1, 3)  # as many panels as episodes shown
