"""Trainers (rejax PPO/SAC/TD3, QuickNav's recurrent PPO), batched trials and run folders.

Names are imported lazily so that importing the package does not pull in JAX.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "PRESETS": "quicknav_core.config.presets",
    "get_preset": "quicknav_core.config.presets",
    "train_batch": "quicknav_core.train.batched",
    "load_run": "quicknav_core.train.run",
    "read_metrics": "quicknav_core.train.run",
    "train_run": "quicknav_core.train.run",
    "Policy": "quicknav_core.train.trainers",
    "Trainer": "quicknav_core.train.trainers",
    "make_trainer": "quicknav_core.train.trainers",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name in _EXPORTS:
        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'quicknav_core.train' has no attribute {name!r}")
