"""The Redis job store: a Streams consumer group as the queue, a record per job, an event stream per job.

Keys (``prefix`` defaults to ``quicknav``):
  {p}:job:{id}        the job record (JSON)
  {p}:jobs            sorted set of job ids by creation time (listing)
  {p}:st:{status}     sorted set of job ids per status, by creation time
  {p}:kd:{kind}       sorted set of job ids per kind, by creation time
  {p}:sk:{status}:{kind}  the same per (status, kind)
  {p}:index           the version of those indexes (a store written before them is indexed once)
  {p}:worker:{name}   a worker's announcement of what it has (expires); {p}:workers-live names
                      the announced workers by the end of their announcement
  {p}:idem:{key}      idempotency key -> job id
  {p}:queue           stream of job ids; consumer group "workers" delivers each to one worker
  {p}:events:{id}     capped stream of progress events, ids "<seq>-1" so Last-Event-ID is a number
  {p}:evseq:{id}      the event counter
Delivery is at least once: a claimed entry stays pending until the job finishes; a heartbeat resets
its idle time; an entry idle longer than the lease (its worker died) is reclaimed by another worker
with XAUTOCLAIM. Record updates are optimistic transactions (WATCH/MULTI) so a heartbeat and a
cancel never overwrite each other; the indexes change in the same transaction as the record, so a
page of a listing or a count is one or two sorted-set reads however many jobs the store holds.
An event is numbered and appended by one script (atomic); viewers block on the event streams.
"""

from __future__ import annotations

import json
import re
import time
from collections.abc import Callable
from typing import Any

import redis
from redis.backoff import ExponentialBackoff
from redis.retry import Retry

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

GROUP = "workers"
SHORT_ID = re.compile(r"[0-9a-f]{4,31}")
INDEX_VERSION = "2"
PASS_MAX = 16  # jobs one claim may pass over (others' jobs) before it says there is nothing
# KEYS: events stream, event counter, job record; ARGV: event JSON, max events. Returns the event's
# number, or -1 when the job does not exist (nothing is written).
PUBLISH = """
if redis.call('EXISTS', KEYS[3]) == 0 then return -1 end
local seq = redis.call('INCR', KEYS[2])
redis.call('XADD', KEYS[1], 'MAXLEN', '~', ARGV[2], seq .. '-1', 'data', ARGV[1])
return seq
"""


def unavailable(e: Exception) -> StoreUnavailable | None:
    """Redis outages as StoreUnavailable, in words without the server's address."""
    if isinstance(e, redis.BusyLoadingError):
        return StoreUnavailable("redis is loading its data after a restart", retry_after_s=2)
    if isinstance(e, redis.ConnectionError | redis.TimeoutError):
        return StoreUnavailable("redis is unreachable")
    if isinstance(e, redis.ReadOnlyError):
        return StoreUnavailable("redis is read-only (a replica)")
    if isinstance(e, redis.ResponseError) and str(e).startswith(("MISCONF", "OOM", "LOADING")):
        return StoreUnavailable("redis refuses writes (persistence error or out of memory)")
    return None


class RedisJobStore:
    def __init__(
        self, url: str, prefix: str = "quicknav", max_attempts: int = 3, max_events: int = 10_000
    ):
        # a dropped connection is retried a few times at once (a restart, a failover); after that
        # calls raise StoreUnavailable and the caller backs off (the API answers 503)
        self.r = redis.Redis.from_url(
            url, decode_responses=True, socket_connect_timeout=2.0, socket_timeout=10.0,
            health_check_interval=15, retry=Retry(ExponentialBackoff(cap=0.5, base=0.05), 3),
            retry_on_error=[redis.ConnectionError, redis.TimeoutError],
        )  # fmt: skip
        self.p = prefix
        self.max_attempts = max_attempts
        self.max_events = max_events
        self._group_ready = False
        self._publish = self.r.register_script(PUBLISH)
        self._indexed = False

    def _ensure_group(self, force: bool = False) -> None:
        """Create the queue's consumer group (once; again after Redis lost it, force=True)."""
        if self._group_ready and not force:
            return
        try:
            self.r.xgroup_create(self._k("queue"), GROUP, id="0", mkstream=True)
        except redis.ResponseError as e:
            if "BUSYGROUP" not in str(e):
                raise
        self._group_ready = True

    def _k(self, *parts: str) -> str:
        return ":".join((self.p, *parts))

    # ------------------------------------------------------------------ records
    def _read(self, job_id: str, conn=None) -> Job:
        raw = (conn or self.r).get(self._k("job", job_id))
        if raw is None:
            raise JobNotFound(job_id)
        return Job.model_validate_json(raw)

    def _index_keys(self, status: JobStatus, kind: JobKind) -> tuple[str, str]:
        return self._k("st", status.value), self._k("sk", status.value, kind.value)

    def _write(self, pipe, job: Job, old_status: JobStatus | None) -> None:
        job.updated_at = time.time()
        pipe.set(self._k("job", job.id), job.model_dump_json())
        if old_status == job.status:
            return
        if old_status is not None:
            pipe.zrem(self._k("st", old_status.value), job.id)
            pipe.zrem(self._k("sk", old_status.value, job.kind.value), job.id)
        else:
            pipe.zadd(self._k("jobs"), {job.id: job.created_at})
            pipe.zadd(self._k("kd", job.kind.value), {job.id: job.created_at})
        for key in self._index_keys(job.status, job.kind):
            pipe.zadd(key, {job.id: job.created_at})

    def _ensure_indexes(self) -> None:
        """Index a store written before the indexes existed (once; what a listing reads)."""
        if self._indexed:
            return
        if self.r.get(self._k("index")) != INDEX_VERSION:
            ids = self.r.zrange(self._k("jobs"), 0, -1)
            for start in range(0, len(ids), 1000):
                chunk = ids[start : start + 1000]
                with self.r.pipeline(transaction=False) as pipe:
                    for raw in self.r.mget([self._k("job", i) for i in chunk]):
                        if raw is None:
                            continue
                        job = Job.model_validate_json(raw)
                        for key in (self._k("kd", job.kind.value), *self._index_keys(job.status, job.kind)):
                            pipe.zadd(key, {job.id: job.created_at})
                    pipe.execute()
            self.r.delete(*[self._k("status", s.value) for s in JobStatus])  # the old sets
            self.r.set(self._k("index"), INDEX_VERSION)
        self._indexed = True

    def _update(self, job_id: str, fn: Callable[[Job, Any], Any]) -> Any:
        """Read-modify-write of one job under WATCH; ``fn(job, pipe)`` mutates the job and may queue
        extra commands; its return value is returned. ``fn`` returning ``NotImplemented`` skips the write."""
        key = self._k("job", job_id)
        with self.r.pipeline() as pipe:
            while True:
                try:
                    pipe.watch(key)
                    job = self._read(job_id, pipe)
                    old = job.status
                    pipe.multi()
                    out = fn(job, pipe)
                    if out is not NotImplemented:
                        self._write(pipe, job, old)
                    pipe.execute()
                    return job if out is None or out is NotImplemented else out
                except redis.WatchError:
                    continue

    # ------------------------------------------------------------------ protocol
    def submit(self, kind, request, config, idempotency_key=None):
        kind = JobKind(kind)
        job = new_job(kind, request, config, idempotency_key, self.max_attempts)
        if idempotency_key is not None:
            idem = self._k("idem", idempotency_key)
            if not self.r.set(idem, job.id, nx=True):
                existing = self.r.get(idem)
                for _ in range(50):  # the first submitter may still be writing its record
                    try:
                        other = self._read(existing)
                        break
                    except JobNotFound:
                        time.sleep(0.01)
                else:
                    raise JobNotFound(existing)
                if other.request_hash != request_hash(kind, request):
                    raise IdempotencyConflict(idempotency_key)
                return other, False
        self._ensure_group()
        self._ensure_indexes()
        with self.r.pipeline() as pipe:
            self._write(pipe, job, None)
            pipe.xadd(self._k("queue"), {"job": job.id})
            pipe.execute()
        return job, True

    def get(self, job_id):
        return self._read(job_id)

    def list(self, status=None, kind=None, limit=50, offset=0):
        self._ensure_indexes()
        if status is not None and kind is not None:
            key = self._k("sk", JobStatus(status).value, JobKind(kind).value)
        elif status is not None:
            key = self._k("st", JobStatus(status).value)
        elif kind is not None:
            key = self._k("kd", JobKind(kind).value)
        else:
            key = self._k("jobs")
        with self.r.pipeline(transaction=True) as pipe:
            pipe.zcard(key)
            pipe.zrevrange(key, offset, offset + limit - 1)
            total, ids = pipe.execute()
        raws = self.r.mget([self._k("job", i) for i in ids]) if ids else []
        # a job deleted between the two reads is left out of the page
        return [Job.model_validate_json(raw) for raw in raws if raw is not None], int(total)

    def _take(self, worker: str, lease_s: float) -> tuple[str, str, bool] | None:
        """Next stream entry for this worker: (entry id, job id, reclaimed). A job whose worker
        stopped renewing its lease comes first: it was started before anything still queued."""
        queue = self._k("queue")
        self._ensure_group()
        try:
            res = self.r.xautoclaim(
                queue, GROUP, worker, min_idle_time=int(lease_s * 1000), start_id="0-0", count=1
            )
        except redis.ResponseError as e:
            if "NOGROUP" not in str(e):
                raise
            self._ensure_group(force=True)  # a Redis that came back without its data
            res = None
        entries = [e for e in (res[1] if res else []) if e and e[1]]
        if entries:
            entry_id, fields = entries[0]
            return entry_id, fields["job"], True
        got = self.r.xreadgroup(GROUP, worker, {queue: ">"}, count=1)
        if got:
            entry_id, fields = got[0][1][0]
            return entry_id, fields["job"], False
        return None

    def _drop_entry(self, entry_id: str) -> None:
        self.r.xack(self._k("queue"), GROUP, entry_id)
        self.r.xdel(self._k("queue"), entry_id)

    def claim(self, worker, lease_s, can_run=None):
        fits = can_run or (lambda job: True)
        passed = 0  # entries of jobs this worker cannot run, put back behind the queue
        while True:
            taken = self._take(worker, lease_s)
            if taken is None:
                return None
            entry_id, job_id, reclaimed = taken
            now = time.time()

            def start(job: Job, pipe, reclaimed=reclaimed, now=now):
                if (reclaimed and job.status == JobStatus.running and job.lease_until is not None
                        and job.lease_until > now):  # fmt: skip
                    # idle entry, live lease (its worker has a longer lease_s than this one):
                    # not orphaned; its next heartbeat claims the entry back
                    return "alive"
                if job.status == JobStatus.queued or (
                    reclaimed and job.status == JobStatus.running
                ):
                    if (
                        reclaimed
                        and job.status == JobStatus.running
                        and job.attempts >= job.max_attempts
                    ):
                        job.status = JobStatus.failed
                        job.error = (f"gave up after {job.attempts} attempts: the worker running it"
                                     f" ({job.worker}) stopped renewing its lease")  # fmt: skip
                        job.finished_at = now
                        job.worker = None
                        job.lease_until = None
                        return "failed"
                    if reclaimed and job.cancel_requested:
                        job.status = JobStatus.cancelled
                        job.finished_at = now
                        return "cancelled"
                    if not fits(job):
                        return "pass"
                    job.status = JobStatus.running
                    job.worker = worker
                    job.lease_until = now + lease_s
                    job.attempts += 1
                    job.started_at = job.started_at or now
                    return "run"
                return NotImplemented  # already finished or cancelled: just drop the entry

            try:
                outcome = self._update(job_id, start)
            except JobNotFound:
                self._drop_entry(entry_id)
                continue
            if outcome == "run":
                self.r.set(self._k("entry", job_id), entry_id)
                return self._read(job_id)
            if outcome == "alive":
                continue  # its idle time was just reset: the next look finds other entries
            if outcome == "pass":
                # another worker's job: a queued one goes back behind the queue for the workers
                # that can run it; an orphaned one stays pending until its idle time runs out
                # again, when a worker that can run it reclaims it
                if not reclaimed:
                    self._drop_entry(entry_id)
                    self.r.xadd(self._k("queue"), {"job": job_id})
                passed += 1
                if passed >= PASS_MAX:
                    return None
                continue
            self._drop_entry(entry_id)
            if outcome in ("failed", "cancelled"):
                job = self._read(job_id)
                self.publish(job_id, {"type": outcome, "status": outcome, "error": job.error})

    def heartbeat(self, job_id, worker, lease_s):
        def beat(job: Job, pipe):
            if job.status != JobStatus.running or job.worker != worker:
                return False
            job.lease_until = time.time() + lease_s
            return True

        try:
            ok = self._update(job_id, beat)
        except JobNotFound:
            return False
        if ok:
            entry = self.r.get(self._k("entry", job_id))
            if entry:  # reset the pending entry's idle time so no one reclaims it
                self.r.xclaim(self._k("queue"), GROUP, worker, 0, [entry], justid=True)
        return bool(ok)

    def progress(self, job_id, worker, progress, metrics):
        def upd(job: Job, pipe):
            if job.worker != worker or job.status != JobStatus.running:
                return NotImplemented
            job.progress = float(progress)
            job.metrics = metrics
            return None

        self._update(job_id, upd)

    def finish(self, job_id, worker, status, result=None, error=None):
        status = JobStatus(status)

        def done(job: Job, pipe):
            if job.status.finished:
                return NotImplemented
            if job.worker != worker:
                raise JobStateError(f"job {job_id} is not held by worker {worker}")
            job.status = status
            job.result = result
            job.error = error
            job.finished_at = time.time()
            job.lease_until = None
            if status == JobStatus.succeeded:
                job.progress = 1.0
            return None

        self._update(job_id, done)
        entry = self.r.get(self._k("entry", job_id))
        if entry:
            self._drop_entry(entry)
            self.r.delete(self._k("entry", job_id))
        self.publish(
            job_id, {"type": status.value, "status": status.value, "error": error, "result": result}
        )
        return self._read(job_id)

    def release(self, job_id, worker):
        def back(job: Job, pipe):
            if job.worker != worker or job.status != JobStatus.running:
                return NotImplemented
            job.status = JobStatus.queued
            job.worker = None
            job.lease_until = None
            job.attempts = max(job.attempts - 1, 0)  # a graceful hand-back is not a failed attempt
            return None

        self._update(job_id, back)
        entry = self.r.get(self._k("entry", job_id))
        if entry:
            self._drop_entry(entry)
            self.r.delete(self._k("entry", job_id))
        if self._read(job_id).status == JobStatus.queued:
            self.r.xadd(self._k("queue"), {"job": job_id})
            self.publish(job_id, {"type": "requeued", "status": "queued"})

    def cancel(self, job_id):
        state = {}

        def cancel(job: Job, pipe):
            if job.status == JobStatus.queued:
                job.status = JobStatus.cancelled
                job.finished_at = time.time()
                state["event"] = True
                return None
            if job.status == JobStatus.running and not job.cancel_requested:
                job.cancel_requested = True
                return None
            return NotImplemented

        job = self._update(job_id, cancel)
        if state.get("event"):
            self.publish(job_id, {"type": "cancelled", "status": "cancelled"})
        return job

    def delete(self, job_id):
        job = self._read(job_id)
        if not job.status.finished:
            raise JobStateError(
                f"job {job_id} is {job.status.value}; only finished jobs can be deleted"
            )
        with self.r.pipeline() as pipe:
            pipe.delete(self._k("job", job_id), self._k("events", job_id), self._k("evseq", job_id))
            pipe.zrem(self._k("jobs"), job_id)
            pipe.zrem(self._k("kd", job.kind.value), job_id)
            for key in self._index_keys(job.status, job.kind):
                pipe.zrem(key, job_id)
            if job.idempotency_key:
                pipe.delete(self._k("idem", job.idempotency_key))
            pipe.execute()

    def publish(self, job_id, event):
        data = json.dumps({**event, "time": time.time()})
        keys = [self._k("events", job_id), self._k("evseq", job_id), self._k("job", job_id)]
        seq = int(self._publish(keys=keys, args=[data, self.max_events]))
        if seq < 0:
            raise JobNotFound(job_id)
        return seq

    def events(self, job_id, after=0, limit=1000):
        rows = self.r.xrange(
            self._k("events", job_id), min=f"({after}-1" if after else "-", count=limit
        )
        return [(int(i.split("-")[0]), json.loads(f["data"])) for i, f in rows]

    def counts(self):
        self._ensure_indexes()
        with self.r.pipeline(transaction=False) as pipe:
            for s in JobStatus:
                pipe.zcard(self._k("st", s.value))
            return {s.value: int(n) for s, n in zip(JobStatus, pipe.execute(), strict=True)}

    def counts_by_kind(self):
        self._ensure_indexes()
        pairs = [(k, s) for k in JobKind for s in JobStatus]
        with self.r.pipeline(transaction=False) as pipe:
            for k, s in pairs:
                pipe.zcard(self._k("sk", s.value, k.value))
            counted = pipe.execute()
        out = {k.value: {} for k in JobKind}
        for (k, s), n in zip(pairs, counted, strict=True):
            out[k.value][s.value] = int(n)
        return out

    def wait_events(self, after, timeout_s):
        streams = {self._k("events", job_id): f"{seq}-1" if seq else "0-0"
                   for job_id, seq in after.items()}  # fmt: skip
        if not streams:
            time.sleep(timeout_s)
            return set()
        got = self.r.xread(streams, count=1, block=max(1, int(timeout_s * 1000)))
        prefix = len(self._k("events", ""))
        return {name[prefix:] for name, _ in got or []}

    # ------------------------------------------------------------------ workers
    # a sorted set of worker names by the end of their announcement, beside each announcement:
    # listing the live ones reads the fleet, never the whole key space
    def announce_worker(self, info, ttl_s):
        now = time.time()
        with self.r.pipeline() as pipe:
            pipe.set(self._k("worker", info["worker"]), json.dumps({**info, "seen": now}),
                     px=max(1, int(ttl_s * 1000)))  # fmt: skip
            pipe.zadd(self._k("workers-live"), {info["worker"]: now + ttl_s})
            pipe.zremrangebyscore(self._k("workers-live"), "-inf", now)
            pipe.execute()

    def live_workers(self):
        names = self.r.zrangebyscore(self._k("workers-live"), time.time(), "+inf")
        raws = self.r.mget([self._k("worker", n) for n in names]) if names else []
        return sorted((json.loads(raw) for raw in raws if raw), key=lambda w: w["worker"])

    def withdraw_worker(self, worker):
        with self.r.pipeline() as pipe:
            pipe.delete(self._k("worker", worker))
            pipe.zrem(self._k("workers-live"), worker)
            pipe.execute()

    # ------------------------------------------------------------------ rollout endpoints
    def register_endpoint(self, endpoint, ttl_s):
        key = self._k("endpoint", endpoint["worker"])
        first = self.r.set(key + ":since", json.dumps(time.time()), nx=True, px=int(ttl_s * 1000))
        if not first:
            self.r.pexpire(key + ":since", int(ttl_s * 1000))
        self.r.set(key, json.dumps({**endpoint, "seen": time.time()}), px=int(ttl_s * 1000))

    def endpoints(self):
        out = []
        for key in self.r.scan_iter(match=self._k("endpoint", "*"), count=500):
            if key.endswith(":since"):
                continue
            raw, since = self.r.get(key), self.r.get(key + ":since")
            if raw:
                out.append({**json.loads(raw), "since": json.loads(since) if since else None})
        return sorted(out, key=lambda e: (e.get("since") or 0.0, e["worker"]))

    def unregister_endpoint(self, worker):
        key = self._k("endpoint", worker)
        self.r.delete(key, key + ":since")

    # ------------------------------------------------------------------ browser sessions
    def create_session(self, key, proof, ttl_s):
        self.r.set(self._k("session", key), proof, px=max(1, int(ttl_s * 1000)))

    def session_proof(self, key):
        return self.r.get(self._k("session", key))

    def delete_session(self, key):
        self.r.delete(self._k("session", key))

    def resolve_id(self, prefix):
        if not SHORT_ID.fullmatch(prefix):
            raise JobNotFound(prefix)
        matches = sorted({m for m, _ in self.r.zscan_iter(self._k("jobs"), match=f"{prefix}*")})
        if not matches:
            raise JobNotFound(prefix)
        if len(matches) > 1:
            raise AmbiguousId(prefix, matches[:6])
        return matches[0]

    def close(self) -> None:
        self.r.close()


guard_store_errors(RedisJobStore, unavailable)
