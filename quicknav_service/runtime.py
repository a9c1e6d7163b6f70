"""The ``Runtime`` of a service process (API, worker, Rollout server): built once when the process
starts and passed down to everything that builds envs.

Room banks are kept on the data disk (``<data>/room-banks``: a bank is carved once per config, then
read back by every process on that disk), and ``map:<id>`` names are read from the artifact store's
uploaded maps (``quicknav_service.maps``).
"""

from __future__ import annotations

from quicknav_core.runtime import Runtime
from quicknav_service.artifacts import ArtifactStore, make_artifacts
from quicknav_service.settings import Settings


def service_runtime(settings: Settings, artifacts: ArtifactStore | None = None) -> Runtime:
    """The process's runtime: banks on its data disk, uploaded maps from its artifact store."""
    from quicknav_service.maps import MapLibrary

    artifacts = artifacts if artifacts is not None else make_artifacts(settings)
    maps = MapLibrary(artifacts, settings.max_map_pixels)
    return Runtime(bank_folder=settings.data_dir / "room-banks", map_resolver=maps.local_yaml,
                   map_name=maps.name, artifacts=artifacts)  # fmt: skip
