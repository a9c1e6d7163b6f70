"""Artifacts on an S3-compatible object store, through obstore.

obstore (Rust's ``object_store`` crate behind a small Python API) was chosen over fsspec + s3fs:
one wheel with no aiobotocore/botocore tree, a synchronous API that the worker's threads call
directly, multipart uploads of large files from a path, streamed downloads, and bounded retries
with backoff that we configure. Credentials and the endpoint come from the usual ``AWS_*``
variables (``AWS_ACCESS_KEY_ID``, ``AWS_SECRET_ACCESS_KEY``, ``AWS_ENDPOINT_URL``, ``AWS_REGION``);
an ``http://`` endpoint (a store on the cluster's network) is allowed without saying so twice.

Layout under ``s3://bucket/prefix/``::

    <job>/config.json, metrics.jsonl, eval.json, *.png, policy.onnx, ...   plain files
    <job>/.checkpoint.json                 the pointer: the published checkpoint's files
    <job>/.checkpoint/<version>/<file>     the checkpoint versions' objects

The pointer is written last, after every object it names is uploaded and its size checked, so a
reader (a resuming worker, a download) sees a whole checkpoint; a replay buffer that did not change
since the last checkpoint is not uploaded again (the pointer names the version that holds it).
``config.json`` and ``metrics.jsonl`` go up before the pointer, so the metrics in the bucket always
reach the published checkpoint's chunk (a resume drops the rows past it).
What is not here: room-bank caches and JAX's compilation cache stay on each machine's disk (both
are rebuilt from the config in seconds, and a local read beats a fetch); a sweep's study lives in
the job store's backend (Optuna's journal on Redis), never as a SQLite file on the object store.
"""

from __future__ import annotations

import json
import os
import shutil
import time
import uuid
from datetime import timedelta
from pathlib import Path
from urllib.parse import urlparse

from quicknav_core.layout import CHECKPOINT, RUN, RunFolder, read_meta
from quicknav_service.artifacts.base import (
    PARTIAL_DIRS,
    ArtifactInfo,
    ArtifactStore,
    ArtifactUnavailable,
    RemoteFile,
)

FETCH_SUFFIX = ".fetch-"  # a checkpoint being fetched: checkpoint.fetch-<random>/
POINTER = ".checkpoint.json"
VERSIONS = ".checkpoint"
RUN_FILES = (RUN.config, RUN.metrics)  # published with every checkpoint
COPY_FILES = (RUN.config, RUN.manifest)  # a run copy (eval, serving) needs these
STREAM_CHUNK = 1 << 20


def parse_url(url: str) -> tuple[str, str]:
    """(bucket, prefix) of ``s3://bucket/prefix``; ValueError naming what is wrong."""
    parsed = urlparse(url)
    if parsed.scheme != "s3" or not parsed.netloc:
        raise ValueError(f"QUICKNAV_ARTIFACTS_URL={url!r} is not s3://bucket[/prefix]"
                         " (unset it to keep artifacts in the data folder)")  # fmt: skip
    if parsed.query or parsed.fragment or parsed.username or parsed.password:
        raise ValueError(f"QUICKNAV_ARTIFACTS_URL={url!r}: only s3://bucket[/prefix]; credentials"
                         " and the endpoint go in AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY and"
                         " AWS_ENDPOINT_URL")  # fmt: skip
    return parsed.netloc, parsed.path.strip("/")


class S3Artifacts(ArtifactStore):
    remote = True

    def __init__(self, url: str, data_dir: Path, retry_s: float = 60.0):
        from obstore.store import S3Store

        bucket, prefix = parse_url(url)
        self.url = f"s3://{bucket}/{prefix}".rstrip("/")
        self.scratch = Path(data_dir) / "work"
        self.cache = Path(data_dir) / "cache" / "runs"
        self.retry_s = retry_s
        config = {"region": os.environ.get("AWS_REGION") or os.environ.get("AWS_DEFAULT_REGION")
                  or "us-east-1"}  # fmt: skip
        endpoint = os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL")
        if endpoint:
            config["endpoint"] = endpoint
            if endpoint.startswith("http://"):
                config["allow_http"] = "true"
        # each call gives up within seconds (the worker's own loop retries uploads for retry_s;
        # the API answers 503 at once instead of holding a request)
        self.store = S3Store(
            bucket, prefix=prefix or None, config=config,
            client_options={"connect_timeout": "3s", "timeout": "300s"},
            retry_config={"max_retries": 2, "retry_timeout": timedelta(seconds=8),
                          "backoff": {"init_backoff": timedelta(milliseconds=100),
                                      "max_backoff": timedelta(seconds=2), "base": 2}},
        )  # fmt: skip

    # ---------------------------------------------------------------- calls
    def _call(self, doing: str, fn, *args, **kwargs):
        """One obstore call; FileNotFoundError (no such object) passes through, anything else is
        ArtifactUnavailable."""
        try:
            return fn(*args, **kwargs)
        except FileNotFoundError:
            raise
        except Exception as e:  # obstore's errors, connection errors, credentials refused
            raise ArtifactUnavailable(self.url, doing, e) from e

    def _retrying(self, doing: str, fn):
        """``fn()`` retried with backoff through an outage for up to retry_s seconds."""
        deadline = time.monotonic() + self.retry_s
        wait = 0.5
        while True:
            try:
                return fn()
            except ArtifactUnavailable as e:
                if time.monotonic() + wait > deadline:
                    raise ArtifactUnavailable(self.url, f"{doing} (retried for {self.retry_s:g} s)",
                                              e.error) from e  # fmt: skip
                time.sleep(wait)
                wait = min(wait * 2, 5.0)

    def _get(self, key: str) -> bytes | None:
        import obstore
        try:
            return bytes(self._call(f"reading {key}", lambda: obstore.get(self.store, key).bytes()))
        except FileNotFoundError:
            return None

    def _put(self, key: str, data: bytes | Path) -> None:
        import obstore

        self._call(f"writing {key}", obstore.put, self.store, key, data)

    def _size(self, key: str) -> int | None:
        import obstore
        try:
            return int(self._call(f"reading {key}", obstore.head, self.store, key)["size"])
        except FileNotFoundError:
            return None

    def _keys(self, prefix: str) -> list[tuple[str, int]]:
        import obstore

        def listing():
            return [(m["path"], int(m["size"])) for page in obstore.list(self.store, prefix)
                    for m in page]  # fmt: skip

        return self._call(f"listing {prefix}", listing)

    def _fetch(self, key: str, dest: Path) -> None:
        """Stream an object into ``dest`` (written beside it, then renamed into place)."""
        import obstore

        tmp = dest.with_name(f"{dest.name}.{uuid.uuid4().hex[:8]}.tmp")
        dest.parent.mkdir(parents=True, exist_ok=True)

        def fetch():
            with open(tmp, "wb") as f:
                for chunk in obstore.get(self.store, key).stream(min_chunk_size=STREAM_CHUNK):
                    f.write(chunk)

        try:
            self._call(f"downloading {key}", fetch)
            tmp.replace(dest)
        finally:
            tmp.unlink(missing_ok=True)

    def pointer(self, job_id: str) -> dict | None:
        data = self._get(f"{job_id}/{POINTER}")
        return json.loads(data) if data is not None else None

    # ---------------------------------------------------------------- a running job's folder
    def work_dir(self, job_id: str) -> Path:
        return self.scratch / job_id

    def restore(self, job_id: str) -> Path:
        folder = self.work_dir(job_id)
        folder.mkdir(parents=True, exist_ok=True)
        pointer = self._retrying(f"reading job {job_id}'s checkpoint", lambda: self.pointer(job_id))
        if pointer is None:
            return folder  # nothing published: the job starts from the beginning
        for name in RUN_FILES:
            self._retrying(f"downloading job {job_id}'s {name}",
                           lambda n=name: self._fetch_optional(f"{job_id}/{n}", folder / n))  # fmt: skip
        self._retrying(f"downloading job {job_id}'s checkpoint",
                       lambda: self._fetch_checkpoint(pointer, folder))  # fmt: skip
        return folder

    def _fetch_optional(self, key: str, dest: Path) -> None:
        try:
            self._fetch(key, dest)
        except FileNotFoundError:
            dest.unlink(missing_ok=True)

    def _fetch_checkpoint(self, pointer: dict, folder: Path) -> None:
        """The pointer's checkpoint as ``folder/checkpoint/`` (skipped when the local one is it)."""
        run = RunFolder(folder)
        here = run.checkpoint()
        if here is not None and here == run.checkpoint_folder:
            meta = read_meta(here)
            if meta.state_sha256 == pointer.get("state_sha256") and meta.chunk == pointer["chunk"]:
                return  # this machine wrote (or already fetched) this very checkpoint
        new = folder / f"{RUN.checkpoint}{FETCH_SUFFIX}{uuid.uuid4().hex[:8]}"
        try:
            for name, entry in pointer["files"].items():
                self._fetch(entry["key"], new / name)
            target = run.checkpoint_folder
            shutil.rmtree(target, ignore_errors=True)
            new.rename(target)
        finally:
            shutil.rmtree(new, ignore_errors=True)

    def save(self, job_id: str, checkpoint_only: bool = False) -> None:
        folder = self.work_dir(job_id)
        if not folder.exists():
            return
        # the run files before the pointer: a published checkpoint never names a chunk whose
        # metrics row is not in the bucket (a resume drops rows past its checkpoint; it cannot
        # bring back one that was never uploaded)
        first = [n for n in RUN_FILES if (folder / n).is_file()]
        for name in first:  # part of publishing the checkpoint (its chunk's metrics)
            self._retrying(f"uploading job {job_id}'s checkpoint ({name})",
                           lambda n=name: self._put(f"{job_id}/{n}", folder / n))  # fmt: skip
        self._retrying(f"uploading job {job_id}'s checkpoint", lambda: self._publish_checkpoint(job_id, folder))
        if checkpoint_only:
            return
        names = [p.relative_to(folder).as_posix() for p in sorted(folder.rglob("*"))
                 if p.is_file() and not _private(p.relative_to(folder))
                 and p.relative_to(folder).as_posix() not in first]  # fmt: skip
        for name in names:
            self._retrying(f"uploading job {job_id}'s {name}",
                           lambda n=name: self._put(f"{job_id}/{n}", folder / n))  # fmt: skip

    def _publish_checkpoint(self, job_id: str, folder: Path) -> None:
        """Upload the folder's last complete checkpoint as a new version, verify it, then point
        at it; versions no longer named are deleted (best effort)."""
        import obstore

        ckpt = RunFolder(folder).checkpoint()
        if ckpt is None:
            return
        meta = read_meta(ckpt)
        old = self.pointer(job_id)
        if old is not None and old.get("chunk") == meta.chunk and old.get("state_sha256") == meta.state_sha256:
            return  # published already
        digests = {CHECKPOINT.state: meta.state_sha256,
                   CHECKPOINT.replay: (meta.replay or {}).get("sha256")}  # fmt: skip
        version = f"{meta.chunk:06d}-{uuid.uuid4().hex[:8]}"
        files = {}
        for path in sorted(p for p in ckpt.iterdir() if p.is_file()):
            size, digest = path.stat().st_size, digests.get(path.name)
            before = (old or {}).get("files", {}).get(path.name)
            if before and digest and before.get("sha256") == digest and before["bytes"] == size:
                files[path.name] = before  # unchanged (a replay buffer between its saves)
                continue
            key = f"{job_id}/{VERSIONS}/{version}/{path.name}"
            self._put(key, path)
            if self._size(key) != size:
                raise ArtifactUnavailable(self.url, f"verifying {key}", f"the stored object is not {size} bytes")
            files[path.name] = {"key": key, "bytes": size, "sha256": digest}
        doc = {"chunk": meta.chunk, "env_steps": meta.env_steps,
               "state_sha256": meta.state_sha256, "files": files}  # fmt: skip
        self._put(f"{job_id}/{POINTER}", json.dumps(doc, indent=1).encode())
        named = {e["key"] for e in files.values()}
        stale = [k for k, _ in self._keys(f"{job_id}/{VERSIONS}/") if k not in named]
        if stale:
            try:
                obstore.delete(self.store, stale)
            except Exception:  # what is not named is never read; a later save retries
                pass

    def save_file(self, job_id: str, path: Path, name: str) -> None:
        self._retrying(f"uploading job {job_id}'s {name}", lambda: self._put(f"{job_id}/{name}", path))

    def release(self, job_id: str) -> None:
        shutil.rmtree(self.work_dir(job_id), ignore_errors=True)

    def scratch_jobs(self) -> list[str]:
        if not self.scratch.is_dir():
            return []
        return sorted(p.name for p in self.scratch.iterdir() if p.is_dir())

    def run_copy(self, job_id: str) -> Path | None:
        """config.json, the checkpoint and policy.json in ``<data>/cache/runs/<job>/<version>/``,
        one folder per published checkpoint (complete before it is used; reused while current)."""
        pointer = self._retrying(f"reading job {job_id}'s checkpoint", lambda: self.pointer(job_id))
        if pointer is None:
            return None
        version = Path(next(iter(pointer["files"].values()))["key"]).parent.name
        folder = self.cache / job_id / version
        if not folder.exists():
            tmp = folder.with_name(f"{version}.{uuid.uuid4().hex[:8]}.tmp")
            try:
                tmp.mkdir(parents=True)
                self._retrying(f"downloading job {job_id}'s checkpoint",
                               lambda: self._fetch_checkpoint(pointer, tmp))  # fmt: skip
                self._retrying(f"downloading job {job_id}'s {RUN.config}",
                               lambda: self._fetch(f"{job_id}/{RUN.config}", tmp / RUN.config))  # fmt: skip
                try:
                    tmp.rename(folder)
                except OSError:
                    if not folder.exists():  # another process made it first: use theirs
                        raise
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
            for stale in folder.parent.iterdir():  # earlier versions of this run
                if stale != folder and not stale.name.endswith(".tmp"):
                    shutil.rmtree(stale, ignore_errors=True)
        # the manifest changes after an evaluation (its held-out figures): always the current one
        self._retrying(f"downloading job {job_id}'s {RUN.manifest}",
                       lambda: self._fetch_optional(f"{job_id}/{RUN.manifest}", folder / RUN.manifest))  # fmt: skip
        return folder

    # ---------------------------------------------------------------- reading, for the API
    def has_checkpoint(self, job_id: str) -> bool:
        return self.pointer(job_id) is not None

    def list(self, job_id: str) -> list[ArtifactInfo]:
        base = f"{job_id}/"
        out = [ArtifactInfo(k[len(base):], size) for k, size in self._keys(base)
               if not _private(Path(k[len(base):])) and not k.endswith(".tmp")]  # fmt: skip
        pointer = self.pointer(job_id)
        for name, entry in (pointer or {}).get("files", {}).items():
            out.append(ArtifactInfo(f"{RUN.checkpoint}/{name}", entry["bytes"]))
        return sorted(out, key=lambda a: a.name)

    def _key(self, job_id: str, name: str) -> str | None:
        """The object holding the job's ``name`` (checkpoint files through the pointer)."""
        if name.startswith("checkpoint/"):
            entry = ((self.pointer(job_id) or {}).get("files") or {}).get(name.split("/", 1)[1])
            return entry["key"] if entry else None
        if _private(Path(name)):
            return None
        return f"{job_id}/{name}"

    def read_bytes(self, job_id: str, name: str) -> bytes | None:
        key = self._key(job_id, name)
        return self._get(key) if key else None

    def download(self, job_id: str, name: str) -> RemoteFile | None:
        import obstore
        key = self._key(job_id, name)
        if key is None:
            return None
        try:
            result = self._call(f"reading {key}", obstore.get, self.store, key)
        except FileNotFoundError:
            return None
        return RemoteFile(size=int(result.meta["size"]),
                          chunks=(bytes(c) for c in result.stream(min_chunk_size=STREAM_CHUNK)))  # fmt: skip

    def delete(self, job_id: str) -> None:
        import obstore

        keys = [k for k, _ in self._keys(f"{job_id}/")]
        for i in range(0, len(keys), 500):
            self._call(f"deleting job {job_id}'s files", obstore.delete, self.store, keys[i:i + 500])
        shutil.rmtree(self.cache / job_id, ignore_errors=True)

    def check(self) -> None:
        self._size(".quicknav-probe")  # NotFound is an answer: the store is up

    def put_bytes(self, folder: str, name: str, data: bytes) -> None:
        self._put(f"{folder}/{name}", data)

    def folders(self, parent: str) -> list[str]:
        base = f"{parent}/"
        return sorted({k[len(base):].split("/", 1)[0] for k, _ in self._keys(base) if "/" in k[len(base):]})

    def local_folder(self, folder: str) -> Path | None:
        target = self.cache / folder  # removed with the folder by delete()
        done = target / ".complete"
        if done.exists():
            return target
        keys = self._keys(f"{folder}/")
        if not keys:
            return None
        for key, _ in keys:
            self._fetch(key, target / key[len(folder) + 1:])
        done.touch()
        return target


def _private(rel: Path) -> bool:
    """Paths that are the store's bookkeeping or a checkpoint's local files, never listed as
    plain files: the pointer, the versions, and a scratch folder's checkpoint folders."""
    parts = rel.parts
    return bool(parts) and (parts[0] in (POINTER, VERSIONS, RUN.checkpoint, *PARTIAL_DIRS)
                            or parts[0].startswith(RUN.checkpoint + FETCH_SUFFIX)
                            or rel.name.endswith(".tmp"))  # fmt: skip
