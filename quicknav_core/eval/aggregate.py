"""Aggregate scores over seeds x episodes the way rliable does (Agarwal et al., 2021).

A row of the learning benchmark is a score matrix: one line per training seed, one column per
held-out episode (the same episodes for every seed: the test bank with a fixed episode seed). Its
point estimates are the mean and the interquartile mean (IQM, the mean of the middle 50 % of all
scores) and its 95 % intervals come from the *stratified* bootstrap: each episode is a stratum and
the seeds are resampled with replacement inside it, so every resample keeps every episode. The
resampling is SciPy's ``scipy.stats.bootstrap`` (one sample per episode, ``paired=False``,
percentile intervals as in rliable); nothing here draws resamples by hand.

``performance_profile`` gives, for thresholds τ, the fraction of (seed, episode) scores above τ
with the same stratified intervals; ``eval.pictures.draw_profiles`` plots them for several rows.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

CONFIDENCE = 0.95
RESAMPLES = 2000


def _stats():
    """``scipy.stats``, imported where a statistic is computed: ~0.45 s and ~40 MB that every
    process importing the evaluation (``eval.pictures`` imports this module) would otherwise pay
    without computing any (2-core AMD EPYC VM)."""
    from scipy import stats

    return stats


def iqm(x: np.ndarray, axis: int = -1) -> np.ndarray:
    """Interquartile mean: the mean of the scores between the 25th and 75th percentiles."""
    return _stats().trim_mean(x, 0.25, axis=axis)


def mean(x: np.ndarray, axis: int = -1) -> np.ndarray:
    return np.mean(x, axis=axis)


def _pooled(statistic: Callable[..., np.ndarray]) -> Callable[..., np.ndarray]:
    """A statistic of all strata pooled, in the form ``scipy.stats.bootstrap`` calls it."""

    def pooled(*strata: np.ndarray, axis: int = -1) -> np.ndarray:
        return statistic(np.concatenate(strata, axis=axis), axis=axis)

    return pooled


def interval(
    scores: np.ndarray,
    statistic: Callable[..., np.ndarray] = iqm,
    resamples: int = RESAMPLES,
    seed: int = 0,
) -> tuple[float, float, float]:
    """(point estimate, low, high) of ``statistic`` over a (seeds, episodes) score matrix, with a
    95 % stratified-bootstrap interval (episodes are the strata, seeds are resampled).

    With one seed there is nothing to resample inside a stratum: the interval is (nan, nan)."""
    scores = np.asarray(scores, dtype=np.float64)
    if scores.ndim != 2:
        raise ValueError(f"scores must be (seeds, episodes), got shape {scores.shape}")
    # a mean or IQM lies inside the data's range, up to rounding (the IQM of 0.92s can come back
    # as 0.9200000000000002): pinned to it, as the interval is below
    lo_data, hi_data = float(scores.min()), float(scores.max())
    point = min(hi_data, max(lo_data, float(statistic(scores.reshape(-1), axis=-1))))
    if scores.shape[0] < 2:
        return point, float("nan"), float("nan")
    if np.all(scores == scores.flat[0]):  # every resample is the same matrix
        return point, point, point
    res = _stats().bootstrap(
        tuple(scores.T), _pooled(statistic), n_resamples=resamples, paired=False,
        vectorized=True, confidence_level=CONFIDENCE, method="percentile",
        rng=np.random.default_rng(seed),
    )  # fmt: skip
    # a percentile interval of a mean or IQM lies inside the data's range and holds the point up
    # to rounding: pin both ends
    low = min(point, max(lo_data, float(res.confidence_interval.low)))
    high = max(point, min(hi_data, float(res.confidence_interval.high)))
    return point, low, high


def performance_profile(
    scores: np.ndarray, taus: np.ndarray, resamples: int = RESAMPLES, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fraction of scores > τ for each τ, with stratified-bootstrap 95 % bands (nan with one seed)."""
    scores = np.asarray(scores, dtype=np.float64)
    taus = np.asarray(taus, dtype=np.float64)

    def above(x: np.ndarray, axis: int = -1) -> np.ndarray:
        x = np.moveaxis(x, axis, -1)
        return np.moveaxis((x[..., None, :] > taus[:, None]).mean(-1), -1, 0)

    point = above(scores.reshape(-1))
    if scores.shape[0] < 2 or np.all(scores == scores.flat[0]):
        band = point if scores.shape[0] >= 2 else np.full_like(point, np.nan)
        return point, band, band
    res = _stats().bootstrap(
        tuple(scores.T), _pooled(above), n_resamples=resamples, paired=False, vectorized=True,
        confidence_level=CONFIDENCE, method="percentile", rng=np.random.default_rng(seed),
    )  # fmt: skip
    # fractions: inside [0, 1] and around the point, whatever the rounding
    low = np.minimum(point, np.clip(res.confidence_interval.low, 0.0, 1.0))
    high = np.maximum(point, np.clip(res.confidence_interval.high, 0.0, 1.0))
    return point, low, high
