"""The embedded job store: one SQLite file, safe across threads and processes (WAL, immediate txns)."""

from __future__ import annotations

import contextlib
import errno
import functools
import json
import logging
import os
import re
import sqlite3
import threading
import time
from pathlib import Path
from typing import Any

from quicknav_service.jobs.models import (
    AmbiguousId,
    IdempotencyConflict,
    Job,
    JobKind,
    JobNotFound,
    JobStateError,
    JobStatus,
    StoreUnavailable,
    guard_store_errors,
    new_job,
    request_hash,
)

log = logging.getLogger("quicknav.store")
SHORT_ID = re.compile(r"[0-9a-f]{4,31}")
# how often event viewers of the embedded store look for new events (one query for all of them)
WAIT_POLL_S = 0.1


def unavailable(e: Exception) -> StoreUnavailable | None:
    """SQLite's and the file system's outages as StoreUnavailable (None: a real bug, re-raised)."""
    if isinstance(e, OSError) and e.errno == errno.ENOSPC:
        return StoreUnavailable("disk full: the job database cannot be written", disk_full=True)
    if isinstance(e, sqlite3.OperationalError):
        text = str(e).lower()
        if "full" in text:
            return StoreUnavailable("disk full: the job database cannot be written", disk_full=True)
        if "locked" in text or "busy" in text:
            return StoreUnavailable("the job database is busy", retry_after_s=1)
        if "i/o" in text or "unable to open" in text or "readonly" in text:
            return StoreUnavailable("the job database cannot be read or written")
    return None

_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    id TEXT PRIMARY KEY,
    kind TEXT NOT NULL,
    status TEXT NOT NULL,
    created_at REAL NOT NULL,
    lease_until REAL,
    idempotency_key TEXT UNIQUE,
    data TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS jobs_status_created ON jobs (status, created_at);
CREATE INDEX IF NOT EXISTS jobs_kind_status_created ON jobs (kind, status, created_at);
CREATE TABLE IF NOT EXISTS endpoints (
    worker TEXT PRIMARY KEY,
    since REAL NOT NULL,
    expires_at REAL NOT NULL,
    data TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS workers (
    worker TEXT PRIMARY KEY,
    expires_at REAL NOT NULL,
    data TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS sessions (
    key TEXT PRIMARY KEY,
    proof TEXT NOT NULL,
    expires_at REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS events (
    job_id TEXT NOT NULL,
    seq INTEGER NOT NULL,
    data TEXT NOT NULL,
    PRIMARY KEY (job_id, seq)
);
"""


class SQLiteJobStore:
    """Jobs and their events in one SQLite file.

    Next to the database lie ``<db>.reserve.0..3``, RESERVE_BYTES in all, given up one slice at a
    time when the disk is full and a job must still be ended (finish, release, cancel, delete): a
    job is never stuck as running because the write that fails it found no space, and DELETE, which
    frees space, works on a full disk. The reserve grows back once there is room again (checked on
    submit and claim, at most every few seconds).
    """

    RESERVE_BYTES = 1 << 20
    RESERVE_SLICES = 4
    RESERVE_CHECK_S = 5.0

    def __init__(self, path: str | Path, max_attempts: int = 3, max_events: int = 10_000):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._reserve_checked = 0.0
        self.max_attempts = max_attempts
        self.max_events = max_events
        self._lock = threading.RLock()
        self._db = sqlite3.connect(
            self.path, check_same_thread=False, isolation_level=None, timeout=30
        )
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA busy_timeout=30000")
        self._db.executescript(_SCHEMA)
        self._ensure_reserve(force=True)

    # ------------------------------------------------------------------ disk reserve
    def _reserve_files(self) -> list[Path]:
        return [self.path.with_name(f"{self.path.name}.reserve.{i}") for i in range(self.RESERVE_SLICES)]

    def _ensure_reserve(self, force: bool = False) -> None:
        """Write the missing reserve slices if the disk has room for the whole reserve several times."""
        now = time.monotonic()
        if not force and now - self._reserve_checked < self.RESERVE_CHECK_S:
            return
        self._reserve_checked = now
        missing = [f for f in self._reserve_files() if not f.exists()]
        if not missing:
            return
        try:
            st = os.statvfs(self.path.parent)
            if st.f_bavail * st.f_frsize < 4 * self.RESERVE_BYTES:
                return
            size = self.RESERVE_BYTES // self.RESERVE_SLICES
            for f in missing:
                tmp = f.with_name(f.name + ".tmp")
                with open(tmp, "wb") as out:
                    out.write(b"\0" * size)
                    out.flush()
                    os.fsync(out.fileno())
                os.replace(tmp, f)
        except OSError:
            for f in missing:
                with contextlib.suppress(OSError):
                    f.with_name(f.name + ".tmp").unlink()

    def release_reserve(self) -> bool:
        """Give one slice of the reserve back to the file system; True if there was one."""
        for f in self._reserve_files():
            try:
                f.unlink()
            except OSError:
                continue
            log.warning("disk full: released a %d KiB slice of the reserve next to %s to end a job",
                        (self.RESERVE_BYTES // self.RESERVE_SLICES) >> 10, self.path.name)  # fmt: skip
            return True
        return False

    # ------------------------------------------------------------------ helpers
    def _tx(self):
        store = self

        class _Tx:
            def __enter__(self):
                store._lock.acquire()
                store._db.execute("BEGIN IMMEDIATE")
                return store._db

            def __exit__(self, exc_type, exc, tb):
                try:
                    if exc_type is None:
                        try:
                            store._db.execute("COMMIT")
                        except BaseException:
                            store._rollback()
                            raise
                    else:
                        store._rollback()
                finally:
                    store._lock.release()
                return False

        return _Tx()

    def _rollback(self) -> None:
        """Roll back if a transaction is open (SQLite ends some failed ones itself: a full disk)."""
        if self._db.in_transaction:
            try:
                self._db.execute("ROLLBACK")
            except sqlite3.Error:
                pass

    @staticmethod
    def _save(db, job: Job) -> None:
        job.updated_at = time.time()
        db.execute(
            "INSERT OR REPLACE INTO jobs (id, kind, status, created_at, lease_until, idempotency_key, data)"
            " VALUES (?, ?, ?, ?, ?, ?, ?)",
            (job.id, job.kind.value, job.status.value, job.created_at, job.lease_until,
             job.idempotency_key, job.model_dump_json()),
        )  # fmt: skip

    @staticmethod
    def _load(db, job_id: str) -> Job:
        row = db.execute("SELECT data FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if row is None:
            raise JobNotFound(job_id)
        return Job.model_validate_json(row[0])

    # ------------------------------------------------------------------ protocol
    def submit(self, kind, request, config, idempotency_key=None):
        kind = JobKind(kind)
        with self._tx() as db:
            if idempotency_key is not None:
                row = db.execute(
                    "SELECT data FROM jobs WHERE idempotency_key = ?", (idempotency_key,)
                ).fetchone()
                if row is not None:
                    job = Job.model_validate_json(row[0])
                    if job.request_hash != request_hash(kind, request):
                        raise IdempotencyConflict(idempotency_key)
                    return job, False
            job = new_job(kind, request, config, idempotency_key, self.max_attempts)
            self._save(db, job)
            return job, True

    def get(self, job_id):
        with self._lock:
            return self._load(self._db, job_id)

    def list(self, status=None, kind=None, limit=50, offset=0):
        where, args = [], []
        if status is not None:
            where.append("status = ?")
            args.append(JobStatus(status).value)
        if kind is not None:
            where.append("kind = ?")
            args.append(JobKind(kind).value)
        clause = f" WHERE {' AND '.join(where)}" if where else ""
        with self._lock:
            total = self._db.execute(f"SELECT COUNT(*) FROM jobs{clause}", args).fetchone()[0]
            rows = self._db.execute(
                f"SELECT data FROM jobs{clause} ORDER BY created_at DESC LIMIT ? OFFSET ?",
                [*args, limit, offset],
            ).fetchall()
        return [Job.model_validate_json(r[0]) for r in rows], total

    def claim(self, worker, lease_s, can_run=None):
        fits = can_run or (lambda job: True)
        now = time.time()
        with self._tx() as db:
            # a job whose worker stopped renewing its lease first: it started before the queue
            orphans = db.execute(
                "SELECT data FROM jobs WHERE status = 'running' AND lease_until < ?"
                " ORDER BY lease_until LIMIT 100", (now,),
            ).fetchall()  # fmt: skip
            for (raw,) in orphans:
                job = Job.model_validate_json(raw)
                if job.attempts >= job.max_attempts:  # any worker may give it up
                    job.status = JobStatus.failed
                    job.error = (f"gave up after {job.attempts} attempts: the worker running it"
                                 f" ({job.worker}) stopped renewing its lease")  # fmt: skip
                    job.finished_at = now
                    job.worker = None
                    job.lease_until = None
                    self._save(db, job)
                    self._append(
                        db, job.id, {"type": "failed", "status": "failed", "error": job.error}
                    )
                elif job.cancel_requested:
                    job.status = JobStatus.cancelled
                    job.finished_at = now
                    self._save(db, job)
                    self._append(db, job.id, {"type": "cancelled", "status": "cancelled"})
                elif fits(job):
                    return self._start(db, job, worker, lease_s, now)
            # then the oldest queued job this worker can run
            offset = 0
            while True:
                rows = db.execute(
                    "SELECT data FROM jobs WHERE status = 'queued' ORDER BY created_at"
                    " LIMIT 200 OFFSET ?", (offset,),
                ).fetchall()  # fmt: skip
                if not rows:
                    return None
                for (raw,) in rows:
                    job = Job.model_validate_json(raw)
                    if fits(job):
                        return self._start(db, job, worker, lease_s, now)
                offset += len(rows)

    def _start(self, db, job: Job, worker: str, lease_s: float, now: float) -> Job:
        job.status = JobStatus.running
        job.worker = worker
        job.lease_until = now + lease_s
        job.attempts += 1
        job.started_at = job.started_at or now
        self._save(db, job)
        return job

    def heartbeat(self, job_id, worker, lease_s):
        with self._tx() as db:
            job = self._load(db, job_id)
            if job.status != JobStatus.running or job.worker != worker:
                return False
            job.lease_until = time.time() + lease_s
            self._save(db, job)
            return True

    def progress(self, job_id, worker, progress, metrics):
        with self._tx() as db:
            job = self._load(db, job_id)
            if job.worker == worker and job.status == JobStatus.running:
                job.progress = float(progress)
                job.metrics = metrics
                self._save(db, job)

    def finish(self, job_id, worker, status, result=None, error=None):
        status = JobStatus(status)
        with self._tx() as db:
            job = self._load(db, job_id)
            if job.status.finished:
                return job
            if job.worker != worker:
                raise JobStateError(f"job {job_id} is not held by worker {worker}")
            job.status = status
            job.result = result
            job.error = error
            job.finished_at = time.time()
            job.lease_until = None
            if status == JobStatus.succeeded:
                job.progress = 1.0
            self._save(db, job)
            self._append(db, job_id, {"type": status.value, "status": status.value, "error": error,
                                      "result": result})  # fmt: skip
            return job

    def release(self, job_id, worker):
        with self._tx() as db:
            job = self._load(db, job_id)
            if job.worker != worker or job.status != JobStatus.running:
                return
            job.status = JobStatus.queued
            job.worker = None
            job.lease_until = None
            job.attempts = max(job.attempts - 1, 0)  # a graceful hand-back is not a failed attempt
            self._save(db, job)
            self._append(db, job_id, {"type": "requeued", "status": "queued"})

    def cancel(self, job_id):
        with self._tx() as db:
            job = self._load(db, job_id)
            if job.status == JobStatus.queued:
                job.status = JobStatus.cancelled
                job.finished_at = time.time()
                self._save(db, job)
                self._append(db, job_id, {"type": "cancelled", "status": "cancelled"})
            elif job.status == JobStatus.running and not job.cancel_requested:
                job.cancel_requested = True
                self._save(db, job)
            return job

    def delete(self, job_id):
        with self._tx() as db:
            job = self._load(db, job_id)
            if not job.status.finished:
                raise JobStateError(
                    f"job {job_id} is {job.status.value}; only finished jobs can be deleted"
                )
            db.execute("DELETE FROM jobs WHERE id = ?", (job_id,))
            db.execute("DELETE FROM events WHERE job_id = ?", (job_id,))

    def _append(self, db, job_id: str, event: dict[str, Any]) -> int:
        row = db.execute(
            "SELECT COALESCE(MAX(seq), 0) FROM events WHERE job_id = ?", (job_id,)
        ).fetchone()
        seq = row[0] + 1
        db.execute("INSERT INTO events (job_id, seq, data) VALUES (?, ?, ?)",
                   (job_id, seq, json.dumps({**event, "time": time.time()})))  # fmt: skip
        db.execute(
            "DELETE FROM events WHERE job_id = ? AND seq <= ?", (job_id, seq - self.max_events)
        )
        return seq

    def publish(self, job_id, event):
        with self._tx() as db:
            self._load(db, job_id)
            return self._append(db, job_id, event)

    def events(self, job_id, after=0, limit=1000):
        with self._lock:
            rows = self._db.execute(
                "SELECT seq, data FROM events WHERE job_id = ? AND seq > ? ORDER BY seq LIMIT ?",
                (job_id, after, limit),
            ).fetchall()
        return [(int(s), json.loads(d)) for s, d in rows]

    def resolve_id(self, prefix):
        if not SHORT_ID.fullmatch(prefix):
            raise JobNotFound(prefix)
        with self._lock:
            rows = self._db.execute(
                "SELECT id FROM jobs WHERE id >= ? AND id < ? ORDER BY id LIMIT 6",
                (prefix, prefix + "g"),  # 'g' sorts after every hex digit
            ).fetchall()
        if not rows:
            raise JobNotFound(prefix)
        if len(rows) > 1:
            raise AmbiguousId(prefix, [r[0] for r in rows])
        return rows[0][0]

    def counts(self):
        with self._lock:
            rows = self._db.execute("SELECT status, COUNT(*) FROM jobs GROUP BY status").fetchall()
        out = {s.value: 0 for s in JobStatus}
        out.update({s: int(n) for s, n in rows})
        return out

    def counts_by_kind(self):
        with self._lock:
            rows = self._db.execute(
                "SELECT kind, status, COUNT(*) FROM jobs GROUP BY kind, status"
            ).fetchall()
        out = {k.value: {s.value: 0 for s in JobStatus} for k in JobKind}
        for kind, status, n in rows:
            out[kind][status] = int(n)
        return out

    def wait_events(self, after, timeout_s):
        # the embedded store has no server to push from: one indexed query for every watched job
        # every WAIT_POLL_S, whatever the number of viewers of each (they share this call)
        deadline = time.monotonic() + timeout_s
        ids = list(after)
        while True:
            if ids:
                marks = ",".join("?" * len(ids))
                with self._lock:
                    rows = self._db.execute(
                        f"SELECT job_id, MAX(seq) FROM events WHERE job_id IN ({marks}) GROUP BY job_id",
                        ids,
                    ).fetchall()  # fmt: skip
                news = {job_id for job_id, seq in rows if seq > after[job_id]}
                if news:
                    return news
            left = deadline - time.monotonic()
            if left <= 0:
                return set()
            time.sleep(min(WAIT_POLL_S, left))

    # ------------------------------------------------------------------ workers
    def announce_worker(self, info, ttl_s):
        now = time.time()
        with self._tx() as db:
            db.execute(
                "INSERT INTO workers (worker, expires_at, data) VALUES (?, ?, ?) ON CONFLICT(worker)"
                " DO UPDATE SET expires_at = excluded.expires_at, data = excluded.data",
                (info["worker"], now + ttl_s, json.dumps({**info, "seen": now})),
            )

    def live_workers(self):
        with self._lock:
            rows = self._db.execute(
                "SELECT data FROM workers WHERE expires_at >= ? ORDER BY worker", (time.time(),)
            ).fetchall()
        return [json.loads(r[0]) for r in rows]

    def withdraw_worker(self, worker):
        with self._tx() as db:
            db.execute("DELETE FROM workers WHERE worker = ?", (worker,))

    # ------------------------------------------------------------------ rollout endpoints
    def register_endpoint(self, endpoint, ttl_s):
        now = time.time()
        with self._tx() as db:
            db.execute("DELETE FROM endpoints WHERE expires_at < ?", (now,))
            db.execute(
                "INSERT INTO endpoints (worker, since, expires_at, data) VALUES (?, ?, ?, ?)"
                " ON CONFLICT(worker) DO UPDATE SET expires_at = excluded.expires_at,"
                " data = excluded.data",
                (endpoint["worker"], now, now + ttl_s, json.dumps({**endpoint, "seen": now})),
            )

    def endpoints(self):
        with self._lock:
            rows = self._db.execute(
                "SELECT since, data FROM endpoints WHERE expires_at >= ? ORDER BY since, worker",
                (time.time(),),
            ).fetchall()
        return [{**json.loads(data), "since": since} for since, data in rows]

    def unregister_endpoint(self, worker):
        with self._tx() as db:
            db.execute("DELETE FROM endpoints WHERE worker = ?", (worker,))

    # ------------------------------------------------------------------ browser sessions
    def create_session(self, key, proof, ttl_s):
        now = time.time()
        with self._tx() as db:
            db.execute("DELETE FROM sessions WHERE expires_at < ?", (now,))
            db.execute("INSERT OR REPLACE INTO sessions (key, proof, expires_at) VALUES (?, ?, ?)",
                       (key, proof, now + ttl_s))  # fmt: skip

    def session_proof(self, key):
        with self._lock:
            row = self._db.execute("SELECT proof FROM sessions WHERE key = ? AND expires_at >= ?",
                                   (key, time.time())).fetchone()  # fmt: skip
        return row[0] if row else None

    def delete_session(self, key):
        with self._tx() as db:
            db.execute("DELETE FROM sessions WHERE key = ?", (key,))

    def close(self) -> None:
        with self._lock:
            self._db.close()


guard_store_errors(SQLiteJobStore, unavailable)


def _ends_jobs_on_a_full_disk(cls):
    """Ending a job (finish, release, cancel, delete) may spend the disk reserve; submit and claim
    (which start work) first try to grow it back."""

    def ending(fn):
        @functools.wraps(fn)
        def wrapped(self, *args, **kwargs):
            try:
                return fn(self, *args, **kwargs)
            except StoreUnavailable as e:
                if not e.disk_full or not self.release_reserve():
                    raise
            return fn(self, *args, **kwargs)

        return wrapped

    def starting(fn):
        @functools.wraps(fn)
        def wrapped(self, *args, **kwargs):
            self._ensure_reserve()
            return fn(self, *args, **kwargs)

        return wrapped

    for name in ("finish", "release", "cancel", "delete"):
        setattr(cls, name, ending(getattr(cls, name)))
    for name in ("submit", "claim"):
        setattr(cls, name, starting(getattr(cls, name)))
    return cls


_ends_jobs_on_a_full_disk(SQLiteJobStore)
