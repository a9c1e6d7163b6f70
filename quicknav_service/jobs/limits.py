"""This server's limits (QUICKNAV_MAX_*) as the library's ``Limits``, and where a field of a
resolved config came from in the request body (``Origin``).

Admission itself is one function for every door, ``quicknav_core.admission.admit``: REST
submissions (``jobs.service``), gRPC ``Start`` and the ``Policy`` stream call it with
``server_limits(settings)``; the CLI with the machine's limits. Each problem is an error item
(``{"loc", "msg", "type"}``) whose ``loc`` names the field of the request that set the value: an
override's key (down to the field of a section sent as an object), the field of a full config, or
the preset it came from.
"""

from __future__ import annotations

from typing import Any

from quicknav_core.admission import Limits
from quicknav_service.settings import Settings

# the rooms of each bank the API checks a wide robot against before it queues a job: the API does
# not build envs, and one request must not carve 200,000 rooms (a fuzzed train job held the API's
# request ~100 s on 2 cores doing so); the worker's env build checks every room and fails the job
# with the same message
FIT_ROOMS = 256


def server_limits(s: Settings) -> Limits:
    """What this server admits, from its settings; messages name the variable that raises each."""
    return Limits(
        max_grid_size=s.max_grid_size, max_lidar_beams=s.max_lidar_beams, max_envs=s.max_envs,
        max_total_steps=s.max_total_steps, max_eval_episodes=s.max_eval_episodes,
        max_sweep_trials=s.max_sweep_trials, max_devices=s.max_devices,
        max_job_memory_mb=s.max_job_memory_mb, fit_rooms=FIT_ROOMS, stored_maps_only=True,
        own_sweep_storage=True,
        owner="this server's", setting=lambda name: f" (QUICKNAV_{name.upper()})",
    )  # fmt: skip


class Origin:
    """Where a field of the resolved config came from in the request body."""

    def __init__(self, body: dict[str, Any], config_key: str = "config", fallback: str = "preset",
                 shorthands: tuple[str, ...] = (), prefix: str = ""):  # fmt: skip
        self.body = body
        self.config_key = config_key
        self.fallback = fallback
        self.shorthands = shorthands  # top-level request fields that set a config field
        self.prefix = prefix  # path of the config inside the resolved one (sweep: "base.")

    def loc(self, path: str) -> list[str]:
        overrides = self.body.get("overrides") or {}
        for key in (path, path.removeprefix(self.prefix)):
            if key in overrides:
                return ["overrides", key]
            # a section sent as an object ({"env": {"grid_size": 100}}): down to the field
            sections = [k for k in overrides if key.startswith(k + ".")]
            if sections:
                section = max(sections, key=len)
                return ["overrides", section, *key[len(section) + 1 :].split(".")]
        short = path.removeprefix(self.prefix)
        if short in self.shorthands and self.body.get(short) is not None:
            return [short]
        if self.body.get(self.config_key) is not None:
            return [self.config_key, *path.split(".")]
        return [self.fallback]
