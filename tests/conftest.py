"""Shared fixtures: small environments built once per session (JAX compile time dominates on CPU)."""

from __future__ import annotations

import pytest

from quicknav_core.config import EnvConfig


@pytest.fixture(scope="session")
def small_config() -> EnvConfig:
    """An 8x8 room, 8 beams, small banks: fast to compile, still has corridors and corners."""
    return EnvConfig(grid_size=8, lidar_beams=8, train_rooms=64, test_rooms=32)


@pytest.fixture(scope="session")
def small_env(small_config):
    return small_config.build("train")


@pytest.fixture(scope="session")
def default_config() -> EnvConfig:
    """The paper's setting (grid 16, 16 beams) with a smaller train bank."""
    return EnvConfig(train_rooms=128, test_rooms=64)


@pytest.fixture(scope="session")
def default_env(default_config):
    return default_config.build("train")
