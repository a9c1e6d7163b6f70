import numpy as np
import pytest

from quicknav_core.config import EnvConfig
from quicknav_core.env.rooms import free_cell_table, make_room_bank
from tests.core.reference import flood_fill_component


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
