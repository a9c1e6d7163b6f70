import math

import jax
import numpy as np
import pytest

from quicknav_core.env import carving
from quicknav_core.env.rooms import carve_bank_steps


@pytest.mark.parametrize(("grid", "return_prob", "fraction"), [(16, 0.2, 1.0), (32, 0.05, 0.8),
                                                                (48, 0.5, 0.3)])  # fmt: skip
def test_expected_steps_carved__brackets_the_real_carver(grid, return_prob, fraction):
    target = math.ceil(fraction * (grid - 2) ** 2 - 1e-9)
    keys = jax.random.split(jax.random.PRNGKey(7), 64)
    _, steps = carve_bank_steps(keys, grid, target, 10**8, return_prob, "carved")
    steps = np.asarray(steps)
    estimate = carving.expected_steps_carved(grid, return_prob, target)
    assert 0.2 * estimate < steps.mean() < 1.5 * estimate
    assert steps.max() <= carving.SLOWEST_ROOM_FACTOR * estimate  # what the config check allows


def test_choose_carver__paper_while_quick_then_centre_then_carved():
    target = lambda g: math.ceil(0.8 * (g - 2) ** 2 - 1e-9)  # noqa: E731
    assert carving.choose_carver(16, 0.05, target(16)) == "paper"
    assert carving.choose_carver(32, 0.05, target(32)) == "centre"
    assert carving.choose_carver(64, 0.05, target(64)) == "carved"
    # a lower return_prob lets the centre walk reach further: the paper walk stays longer
    assert carving.choose_carver(24, 0.01, target(24)) == "paper"


def test_feasible__carved_returns_reach_what_centre_returns_cannot():
    target, cap = math.ceil(0.8 * 126**2), 1000 * 126**2
    assert not carving.feasible(128, 0.05, target, cap, "paper")
    assert carving.feasible(128, 0.05, target, cap, "carved")
    assert not carving.feasible(128, 0.05, target, target, "carved")


def test_refusal__solves_the_walk_once_per_grid_and_return_prob_tried(monkeypatch):
    """A refused config's message names three ways out (return_prob, carve_fraction, grid_size).
    Each occupation is one sparse solve (~35 ms at grid 128): the fractions tried share the
    config's own, and the grid sizes are bisected, not walked one by one (a grid-128 refusal
    solved 173 times, 7 s of CPU in the request that sent it)."""
    from quicknav_core.config import EnvConfig

    solved = []
    real = carving.occupation
    monkeypatch.setattr(carving, "occupation", lambda g, p: solved.append((g, p)) or real(g, p))
    with pytest.raises(ValueError, match="grid_size <= ") as refused:
        EnvConfig(grid_size=128, room_size=64.0, carver="centre")
    at_128 = [p for g, p in solved if g == 128]
    assert len(at_128) == len(set(at_128)), "the same walk solved twice"
    assert len(solved) <= 30, len(solved)
    # the suggested grid is accepted, the next one up refused
    g_max = int(str(refused.value).split("grid_size <= ")[1].split(",")[0].split()[0])
    EnvConfig(grid_size=g_max, room_size=g_max / 2, carver="centre")
    with pytest.raises(ValueError, match="grid_size <= "):
        EnvConfig(grid_size=g_max + 1, room_size=(g_max + 1) / 2, carver="centre")


@pytest.mark.parametrize("return_prob", [1e-17, 1e-300, 5e-324])
def test_occupation__a_chance_too_small_to_resolve_is_the_even_spread_of_no_resets(return_prob):
    # 1 - 1e-17 is 1.0 in float64: the walk's system is singular (it gave NaN, found by the API's
    # fuzz test); the answer is the limit, a walk without resets, spread evenly
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for grid in (4, 16, 64):
            pi = carving.occupation(grid, return_prob)
            assert np.all(np.isfinite(pi)) and pi.sum() == pytest.approx(1.0)
            np.testing.assert_allclose(pi, carving.occupation(grid, 0.0), rtol=1e-6)
            assert math.isfinite(carving.expected_steps(grid, return_prob, (grid - 2) ** 2 // 2))

