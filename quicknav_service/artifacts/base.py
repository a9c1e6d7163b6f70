"""The artifact store's interface, its error, and the rules for artifact names."""

from __future__ import annotations

import re
from abc import ABC, abstractmethod
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from quicknav_core.layout import CHECKPOINT, RUN

# files a run folder holds while a chunk is written or a checkpoint swapped: never listed
PARTIAL_DIRS = (RUN.checkpoint + CHECKPOINT.new_suffix, RUN.checkpoint + CHECKPOINT.old_suffix)


class ArtifactUnavailable(Exception):
    """The artifact store could not be reached (or refused the credentials). Its message names the
    store as the operator configured it (``s3://bucket/prefix``), what was being done and the kind
    of failure; never the credentials, and never the client library's own words (they name the
    store's internal endpoint): those are in ``error``, for the log."""

    def __init__(self, store: str, doing: str, error: object):
        self.store = store
        self.doing = doing
        self.error = str(error).splitlines()[0][:300] if str(error) else type(error).__name__
        self.cause = failure_kind(self.error)
        super().__init__(f"artifact store {store} unavailable while {doing}: {self.cause}")


# the kinds of failure a client may be told, by words of the client library's message
_KINDS = (("refused", "connection refused"), ("timed out", "timed out"),
          ("dns", "the store's host name does not resolve"),
          ("resolve", "the store's host name does not resolve"),
          ("403", "access denied (check the credentials)"),
          ("denied", "access denied (check the credentials)"),
          ("nosuchbucket", "no such bucket"), ("reset", "connection reset"))  # fmt: skip
# what names a place: a URL, or a host and port
_PLACE = re.compile(r"://|\b\d{1,3}(\.\d{1,3}){3}\b|\[[0-9a-f:]+\]|:\d{2,5}\b", re.I)


def failure_kind(error: str) -> str:
    """What kind of failure a client library's message describes, in words that name no place:
    the message itself when it names none (QuickNav's own, "the stored object is not ... bytes"),
    else its kind ("connection refused", "timed out", ...)."""
    if not _PLACE.search(error):
        return error
    text = error.lower()
    for needle, kind in _KINDS:
        if needle in text:
            return kind
    return "the store did not answer"


@dataclass(frozen=True)
class ArtifactInfo:
    name: str  # a path inside the job's folder, e.g. checkpoint/state.msgpack
    bytes: int


@dataclass
class RemoteFile:
    """A download from an object store: its size, and its bytes as a stream of chunks."""

    size: int
    chunks: Iterator[bytes]


def bad_name(name: str) -> str | None:
    """Why ``name`` is not a file path inside a job's folder (None when it is one)."""
    if "\x00" in name:
        return "artifact name holds a NUL byte; names are file paths inside the job's folder"
    parts = PurePosixPath(name).parts
    if not parts or name.startswith("/") or ".." in parts or "\\" in name:
        return f"artifact name {name!r} leaves the job's folder"
    return None


class ArtifactStore(ABC):
    """Where jobs' files live. ``url`` names it in messages (no credentials)."""

    url: str
    remote: bool  # files are uploaded from a local scratch folder (an object store)

    # ---------------------------------------------------------------- a running job's folder
    @abstractmethod
    def work_dir(self, job_id: str) -> Path:
        """The local folder a running job writes into (the local store: the artifact folder)."""

    @abstractmethod
    def restore(self, job_id: str) -> Path:
        """The job's folder with its last published checkpoint, config and metrics in it (for a
        resumed job; on an object store they are downloaded, from whichever worker wrote them)."""

    @abstractmethod
    def save(self, job_id: str, checkpoint_only: bool = False) -> None:
        """Publish the job's folder: its checkpoint, config and metrics (``checkpoint_only``), or
        every file. Retried through an outage for up to the store's retry time, then
        ArtifactUnavailable."""

    @abstractmethod
    def save_file(self, job_id: str, path: Path, name: str) -> None:
        """Publish one file as the job's ``name`` (a run copy's edited policy manifest)."""

    @abstractmethod
    def release(self, job_id: str) -> None:
        """The job no longer runs here: drop a scratch copy (the store keeps the files)."""

    def scratch_jobs(self) -> list[str]:
        """The jobs with a scratch copy on this machine (none where the folder is the store)."""
        return []

    @abstractmethod
    def run_copy(self, job_id: str) -> Path | None:
        """A local folder holding a train job's config, last checkpoint and exported policy
        manifest, to evaluate or serve it; None if the job has no checkpoint."""

    # ---------------------------------------------------------------- reading, for the API
    @abstractmethod
    def has_checkpoint(self, job_id: str) -> bool: ...

    @abstractmethod
    def list(self, job_id: str) -> list[ArtifactInfo]:
        """The job's files (complete ones only), sorted by name."""

    @abstractmethod
    def read_bytes(self, job_id: str, name: str) -> bytes | None:
        """One small file's bytes (metrics.jsonl), None if the job has no such file."""

    @abstractmethod
    def download(self, job_id: str, name: str) -> Path | RemoteFile | None:
        """One file to send: a local path, or a stream from the object store; None if absent."""

    @abstractmethod
    def delete(self, job_id: str) -> None:
        """Every file of the job."""

    @abstractmethod
    def check(self) -> None:
        """Raise ArtifactUnavailable when the store cannot be reached."""

    # ---------------------------------------------------------------- folders that are not jobs
    # (uploaded maps: ``maps/<id>/``); list, read_bytes, download and delete take them as well
    @abstractmethod
    def put_bytes(self, folder: str, name: str, data: bytes) -> None:
        """Store one small file as ``folder``'s ``name`` (replacing it whole)."""

    @abstractmethod
    def folders(self, parent: str) -> list[str]:
        """The names of the folders under ``parent``, sorted."""

    @abstractmethod
    def local_folder(self, folder: str) -> Path | None:
        """A local folder holding every file of ``folder`` (an object store's are downloaded
        once into this machine's cache: such folders never change); None if it has none."""
