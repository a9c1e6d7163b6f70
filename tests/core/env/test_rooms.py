import hashlib

import jax
import numpy as np
import pytest

from quicknav_core.config import EnvConfig
from quicknav_core.env.numpy_env import carve_room_np
from quicknav_core.env.room_sources import free_cell_table, make_room_bank
from quicknav_core.env.rooms import carve_bank_steps
from tests.core.env.reference import block_walk_reference, flood_fill_component

# sha256 of the default banks' bytes (EnvConfig(), grid 16), taken on 2026-11-23 from commit 85691ec,
# before the carver became a block loop: the ``paper`` carver must keep them bit for bit
DEFAULT_TRAIN_SHA256 = "b2d32983d369b3c761ceaafd3dbca751ec85022826b06dd6b0c107c7dfdc5424"
DEFAULT_TEST_SHA256 = "5fc64bada262aa8b2383982a8a636327246ef61eda2f0ed2d7f0eefbff5e664f"


def _big(grid: int, **kwargs) -> EnvConfig:
    """A config for a large grid: cells of 0.5 m, as in the default 8 m room of grid 16."""
    return EnvConfig(grid_size=grid, room_size=grid * 0.5, **kwargs)


def _assert_valid_rooms(rooms: np.ndarray, cfg: EnvConfig) -> None:
    """Outer ring wall, exactly the carve target free, every free cell reachable from the centre."""
    g = cfg.grid_size
    assert rooms.shape[1:] == (g, g)
    assert rooms[:, 0, :].all() and rooms[:, -1, :].all()
    assert rooms[:, :, 0].all() and rooms[:, :, -1].all()
    assert ((~rooms).sum(axis=(1, 2)) == cfg.carve_target).all()
    for walls in rooms:
        free = ~walls
        assert (flood_fill_component(free, (g // 2, g // 2)) == free).all()


@pytest.fixture(scope="module")
def bank16():
    cfg = EnvConfig(train_rooms=200, test_rooms=100)
    return cfg, make_room_bank(cfg, "train"), make_room_bank(cfg, "test")


def test_rooms__outer_ring_is_wall(bank16):
    _, train, test = bank16
    for rooms in (train, test):
        assert rooms[:, 0, :].all() and rooms[:, -1, :].all()
        assert rooms[:, :, 0].all() and rooms[:, :, -1].all()


def test_rooms__free_fraction_meets_target(bank16):
    cfg, train, test = bank16
    for rooms in (train, test):
        free = (~rooms).sum(axis=(1, 2))
        assert (free >= cfg.carve_target).all()
        assert (free / cfg.inner_cells >= cfg.carve_fraction).all()
        # the walk stops as soon as the target is met
        assert (free == cfg.carve_target).all()


def test_rooms__all_free_cells_connected(bank16):
    cfg, train, _ = bank16
    g = cfg.grid_size
    for walls in train[:100]:
        free = ~walls
        reach = flood_fill_component(free, (g // 2, g // 2))
        assert (reach == free).all()


def test_rooms__train_and_test_banks_share_no_room(bank16):
    _, train, test = bank16
    train_set = {r.tobytes() for r in train}
    assert not any(r.tobytes() in train_set for r in test)
    # and the banks are varied, not one room repeated
    assert len({r.tobytes() for r in train}) > 190


def test_rooms__deterministic_and_seeded():
    cfg = EnvConfig(grid_size=8, train_rooms=16)
    a, b = make_room_bank(cfg, "train"), make_room_bank(cfg, "train")
    assert (a == b).all()
    c = make_room_bank(cfg.model_copy(update={"room_seed": 1}), "train")
    assert not (a == c).all()


def test_rooms__full_carving_is_reachable():
    cfg = EnvConfig(grid_size=8, carve_fraction=1.0, train_rooms=8)
    rooms = make_room_bank(cfg, "train")
    assert (~rooms[:, 1:-1, 1:-1]).all()


def test_rooms__tiny_grid_cannot_have_disjoint_test_bank():
    cfg = EnvConfig(grid_size=4, robot_radius=0.15, train_rooms=4, test_rooms=4)
    with pytest.raises(ValueError, match="too few distinct layouts"):
        make_room_bank(cfg, "test")


def test_free_cell_table__lists_exactly_the_free_cells(bank16):
    _, train, _ = bank16
    table, counts = free_cell_table(train[:10])
    for walls, row, n in zip(train[:10], table, counts, strict=True):
        expected = np.flatnonzero(~walls.reshape(-1))
        assert n == expected.size
        assert (row[:n] == expected).all()


def test_rooms__default_bank_is_bit_identical_to_generator_1():
    cfg = EnvConfig()
    assert cfg.resolved_carver == "paper"
    train, test = make_room_bank(cfg, "train"), make_room_bank(cfg, "test")
    assert hashlib.sha256(train.tobytes()).hexdigest() == DEFAULT_TRAIN_SHA256
    assert hashlib.sha256(test.tobytes()).hexdigest() == DEFAULT_TEST_SHA256


@pytest.mark.parametrize("carver", ["paper", "centre", "carved"])
def test_rooms__every_carver_makes_connected_rooms_of_the_target_size(carver):
    cfg = EnvConfig(grid_size=16, carver=carver, train_rooms=40, test_rooms=20)
    train, test = make_room_bank(cfg, "train"), make_room_bank(cfg, "test")
    _assert_valid_rooms(train, cfg)
    _assert_valid_rooms(test, cfg)
    assert not {r.tobytes() for r in train} & {r.tobytes() for r in test}


@pytest.mark.parametrize("grid", [64, 128])
def test_rooms__large_grids_build_connected_rooms_with_auto(grid):
    cfg = _big(grid, train_rooms=4, test_rooms=2)
    assert cfg.resolved_carver == "carved"  # a centre return never gets across these grids
    train, test = make_room_bank(cfg, "train"), make_room_bank(cfg, "test")
    _assert_valid_rooms(train, cfg)
    _assert_valid_rooms(test, cfg)


@pytest.mark.parametrize(("carver", "grid"), [("centre", 12), ("carved", 12), ("carved", 24)])
def test_carve_bank__block_carvers_match_a_step_by_step_walk(carver, grid):
    # the block loop (scatter stamps, running counts, the stop inside a block) against the same
    # random words replayed one step at a time, with the return rule spelt out
    cfg = EnvConfig(grid_size=grid, room_size=grid * 0.5, carver=carver, return_prob=0.1)
    keys = jax.random.split(jax.random.PRNGKey(3), 6)
    walls, steps = carve_bank_steps(keys, grid, cfg.carve_target, cfg.carve_step_cap,
                                    cfg.return_prob, carver)  # fmt: skip
    assert int(np.max(steps)) > 240  # several blocks, so the carved-before-the-block rule shows
    for key, room, n in zip(np.asarray(keys), np.asarray(walls), np.asarray(steps), strict=True):
        ref, ref_steps = block_walk_reference(key, grid, cfg.carve_target, cfg.carve_step_cap,
                                              cfg.return_prob, carver == "carved")  # fmt: skip
        assert n == ref_steps
        assert (room == ref).all()


def test_carve_bank__step_cap_stops_rooms_short():
    keys = jax.random.split(jax.random.PRNGKey(0), 4)
    for carver in ("paper", "centre", "carved"):
        walls, steps = carve_bank_steps(keys, 16, 150, 300, 0.05, carver)
        assert (np.asarray(steps) == 300).all()  # mid-block: 300 = one block and 60 steps
        free = (~np.asarray(walls)).sum(axis=(1, 2))
        assert (free < 150).all() and (free > 1).all()


@pytest.mark.parametrize("carver", ["centre", "carved"])
def test_rooms__block_carvers_deterministic_and_seeded(carver):
    cfg = _big(48, carver=carver, train_rooms=8, test_rooms=2, return_prob=0.01)
    a = make_room_bank(cfg, "train")
    b = make_room_bank(cfg.model_copy(update={"train_rooms": 9}), "train")
    assert (a == b[:8]).all()  # room i is the same whatever the bank's size
    c = make_room_bank(cfg.model_copy(update={"room_seed": 1}), "train")
    assert not (a == c).all()


def test_room_bank__built_once_per_runtime_and_no_caller_can_change_it():
    from quicknav_core.env.room_sources import room_source
    from quicknav_core.runtime import Runtime

    cfg = EnvConfig(grid_size=8, train_rooms=8, test_rooms=4)
    runtime = Runtime()
    a = room_source(cfg, runtime).bank("train")
    with pytest.raises(ValueError, match="read-only"):
        a[:] = False  # the test bank is built from the train bank the runtime keeps
    b = room_source(cfg, runtime).bank("train")
    assert b is a and b[:, 0, :].all() and len(runtime.banks) == 1
    test = room_source(cfg, runtime).bank("test")
    assert not {r.tobytes() for r in b} & {r.tobytes() for r in test}
    # another runtime shares nothing, and builds the same rooms
    assert np.array_equal(make_room_bank(cfg, "train"), a) and make_room_bank(cfg, "train") is not a


@pytest.mark.parametrize("to_carved", [False, True])
def test_carve_room_np__twin_rooms_are_connected_and_meet_the_target(to_carved):
    rng = np.random.default_rng(0)
    cfg = EnvConfig(grid_size=16)
    for _ in range(5):
        walls = carve_room_np(rng, 16, cfg.carve_target, cfg.carve_step_cap, 0.05, to_carved)
        _assert_valid_rooms(walls[None], cfg)
