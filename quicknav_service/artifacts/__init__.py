"""The artifact store: where a job's files live, and the only code that knows a run folder's layout.

Two stores behind one interface (``ArtifactStore``):

- ``LocalArtifacts``: a folder (``<data>/artifacts/<job id>/``), the embedded default. A job writes
  straight into its folder, as `quicknav train` writes a run folder.
- ``S3Artifacts``: any S3-compatible object store (``QUICKNAV_ARTIFACTS_URL=s3://bucket/prefix``),
  so that a fleet needs no shared filesystem. A worker writes a job's files into a local scratch
  folder first and uploads them: the checkpoint (with ``config.json`` and ``metrics.jsonl``) after
  every checkpoint the run writes, everything else when the job ends. A checkpoint is published
  atomically: its files go to a new version under ``<job>/.checkpoint/``, are verified, and only
  then does the pointer object ``<job>/.checkpoint.json`` name them (a reader sees the previous
  checkpoint or the new one, never a mix). Any worker on any machine resumes a job from there.

Every name a client sees is the same on both stores (``checkpoint/state.msgpack``, ``eval.json``):
the API, the SDK and the web view never learn which store runs.
"""

from quicknav_service.artifacts.base import (
    ArtifactInfo,
    ArtifactStore,
    ArtifactUnavailable,
    RemoteFile,
    bad_name,
)
from quicknav_service.artifacts.local import LocalArtifacts

__all__ = ["ArtifactInfo", "ArtifactStore", "ArtifactUnavailable", "LocalArtifacts", "RemoteFile",
           "bad_name", "make_artifacts"]  # fmt: skip

_made: dict[tuple, ArtifactStore] = {}


def make_artifacts(settings) -> ArtifactStore:
    """The artifact store the settings name (one per URL and data folder in a process)."""
    key = (settings.artifacts_url, str(settings.data_dir), settings.artifacts_retry_s)
    if key not in _made:
        if settings.artifacts_url:
            from quicknav_service.artifacts.s3 import S3Artifacts

            _made[key] = S3Artifacts(settings.artifacts_url, settings.data_dir,
                                     retry_s=settings.artifacts_retry_s)  # fmt: skip
        else:
            _made[key] = LocalArtifacts(settings.artifacts_dir)
    return _made[key]
