"""One contract, two job stores: the embedded SQLite store and the Redis store (a real server)."""

import time
import uuid

import pytest
import redis

from quicknav_service.jobs.models import IdempotencyConflict, JobNotFound, JobStateError, JobStatus
from quicknav_service.jobs.redis_store import RedisJobStore
from quicknav_service.jobs.sqlite_store import SQLiteJobStore

REDIS_URL = "redis://127.0.0.1:6379/14"  # this suite's own DB index


@pytest.fixture(params=["sqlite", "redis"])
def store(request, tmp_path):
    if request.param == "sqlite":
        s = SQLiteJobStore(tmp_path / "jobs.db", max_attempts=2)
        yield s
        s.close()
    else:
        client = redis.Redis.from_url(REDIS_URL)
        client.ping()  # no Redis reachable is a failure here, not a skip
        client.flushdb()
        s = RedisJobStore(REDIS_URL, prefix=f"t{uuid.uuid4().hex[:8]}", max_attempts=2)
        yield s
        s.close()
        client.flushdb()


def test_submit_get_list_and_filters(store):
    a, created = store.submit("train", {"preset": "demo"}, {"total_steps": 8, "env": {"grid_size": 8}})
    assert created and a.status == JobStatus.queued
    b, _ = store.submit("eval", {"policy": "random"}, {})
    c, _ = store.submit("train", {"preset": "paper-ppo"}, {})
    assert store.get(a.id).request == {"preset": "demo"}
    assert store.get(a.id).config == {"total_steps": 8, "env": {"grid_size": 8}}
    jobs, total = store.list()
    assert total == 3 and [j.id for j in jobs] == [c.id, b.id, a.id]  # newest first
    jobs, total = store.list(kind="train")
    assert total == 2 and {j.id for j in jobs} == {a.id, c.id}
    jobs, total = store.list(limit=1, offset=1)
    assert total == 3 and [j.id for j in jobs] == [b.id]
    with pytest.raises(JobNotFound):
        store.get("nope")


def test_idempotency_key(store):
    a, created = store.submit("train", {"preset": "demo"}, {}, idempotency_key="k1")
    again, created2 = store.submit("train", {"preset": "demo"}, {}, idempotency_key="k1")
    assert created and not created2 and again.id == a.id
    with pytest.raises(IdempotencyConflict):
        store.submit("train", {"preset": "other"}, {}, idempotency_key="k1")
    assert store.list()[1] == 1


def test_claim_is_fifo_and_exclusive(store):
    a, _ = store.submit("train", {"n": 1}, {})
    b, _ = store.submit("train", {"n": 2}, {})
    first = store.claim("w1", lease_s=30)
    second = store.claim("w2", lease_s=30)
    assert (first.id, second.id) == (a.id, b.id)
    assert first.status == JobStatus.running and first.worker == "w1" and first.attempts == 1
    assert store.claim("w3", lease_s=30) is None
    assert store.counts()["running"] == 2


def test_heartbeat_progress_events_and_finish(store):
    a, _ = store.submit("train", {}, {})
    job = store.claim("w1", 30)
    assert store.heartbeat(job.id, "w1", 30)
    assert not store.heartbeat(job.id, "w2", 30)
    ids = [store.publish(job.id, {"type": "progress", "chunk": i}) for i in range(3)]
    assert ids == sorted(ids) and len(set(ids)) == 3
    store.progress(job.id, "w1", 0.5, {"mean_return": 1.5})
    assert store.get(job.id).progress == 0.5 and store.get(job.id).metrics == {"mean_return": 1.5}
    # resumable: events after a given id
    tail = store.events(job.id, after=ids[0])
    assert [e[1]["chunk"] for e in tail] == [1, 2]
    with pytest.raises(JobStateError):
        store.finish(job.id, "w2", JobStatus.succeeded)
    done = store.finish(job.id, "w1", JobStatus.succeeded, result={"ok": True})
    assert (
        done.status == JobStatus.succeeded and done.result == {"ok": True} and done.progress == 1.0
    )
    last = store.events(job.id, after=ids[-1])
    assert last[-1][1]["type"] == "succeeded"
    assert not store.heartbeat(job.id, "w1", 30)
    assert store.claim("w1", 30) is None


def test_cancel_queued_and_running(store):
    q, _ = store.submit("train", {"n": 1}, {})
    assert store.cancel(q.id).status == JobStatus.cancelled
    assert store.cancel(q.id).status == JobStatus.cancelled  # idempotent
    r, _ = store.submit("train", {"n": 2}, {})
    job = store.claim("w1", 30)
    assert job.id == r.id, "a cancelled queued job is never handed out"
    flagged = store.cancel(r.id)
    assert flagged.status == JobStatus.running and flagged.cancel_requested
    done = store.finish(r.id, "w1", JobStatus.cancelled)
    assert done.status == JobStatus.cancelled


def test_release_requeues_without_spending_an_attempt(store):
    a, _ = store.submit("train", {}, {})
    job = store.claim("w1", 30)
    store.release(job.id, "w1")
    assert store.get(a.id).status == JobStatus.queued
    again = store.claim("w2", 30)
    assert again.id == a.id and again.attempts == 1


def test_expired_lease_is_reclaimed_then_given_up(store):
    a, _ = store.submit("train", {}, {})
    store.claim("dead-1", lease_s=0.2)
    time.sleep(0.35)
    second = store.claim("w2", lease_s=0.2)
    assert (
        second is not None and second.id == a.id and second.attempts == 2 and second.worker == "w2"
    )
    time.sleep(0.35)  # the second worker dies too: max_attempts=2 reached
    assert store.claim("w3", lease_s=0.2) is None
    failed = store.get(a.id)
    assert failed.status == JobStatus.failed and "gave up after 2 attempts" in failed.error
    assert store.events(a.id)[-1][1]["type"] == "failed"


def test_an_orphaned_job_is_taken_before_queued_ones(store):
    a, _ = store.submit("train", {}, {})
    store.claim("dead-1", lease_s=0.2)
    b, _ = store.submit("train", {}, {})
    time.sleep(0.35)  # dead-1 never renews its lease (every worker has the same lease_s)
    assert store.claim("w2", lease_s=0.2).id == a.id  # not b, which was only queued
    assert store.claim("w3", lease_s=0.2).id == b.id


def test_a_live_lease_is_not_taken_by_a_worker_with_a_shorter_lease(store):
    a, _ = store.submit("train", {}, {})
    store.claim("slow-beat", lease_s=30)  # a worker configured with a long lease
    time.sleep(0.35)
    assert store.claim("quick", lease_s=0.2) is None  # its lease runs for 29 s more: not orphaned
    assert store.heartbeat(a.id, "slow-beat", 30)
    assert store.get(a.id).worker == "slow-beat" and store.get(a.id).attempts == 1


def test_delete_only_finished(store):
    a, _ = store.submit("train", {}, {})
    with pytest.raises(JobStateError):
        store.delete(a.id)
    store.cancel(a.id)
    store.delete(a.id)
    with pytest.raises(JobNotFound):
        store.get(a.id)
    assert store.list()[1] == 0


def test_rollout_endpoints_expire_unless_renewed(store):
    """An endpoint lives for its ttl from its last registration. The times are deadlines from the
    first registration, with margins of 0.7 s or more, so a loaded test machine's stalls (a CI run
    on 2 cores) do not decide the outcome."""
    t0 = time.monotonic()

    def at(t: float) -> None:  # sleep until t seconds after the first registration
        time.sleep(max(0.0, t0 + t - time.monotonic()))

    store.register_endpoint({"worker": "w1", "address": "gpu-a:50051", "device": "cuda"}, ttl_s=1.0)
    at(0.05)
    store.register_endpoint({"worker": "w2", "address": "gpu-b:50051", "device": "cuda"}, ttl_s=30)
    listed = store.endpoints()
    assert [e["worker"] for e in listed] == ["w1", "w2"]  # oldest first
    assert listed[0]["address"] == "gpu-a:50051" and listed[0]["since"] <= listed[1]["since"]
    since = listed[0]["since"]
    at(0.3)
    store.register_endpoint({"worker": "w1", "address": "gpu-a:50051", "sessions": 3}, ttl_s=2.0)
    renewed = time.monotonic() - t0
    assert renewed < 1.0, f"renewed {renewed:.2f} s after registering: past its first ttl"
    at(1.1)  # past the first ttl, within the renewed one (until at least 2.3 s)
    w1 = store.endpoints()[0]
    assert w1["worker"] == "w1" and w1["sessions"] == 3 and w1["since"] == since
    at(renewed + 2.1)  # w1 stopped renewing: its renewed ttl has run out
    assert [e["worker"] for e in store.endpoints()] == ["w2"]
    store.unregister_endpoint("w2")
    assert store.endpoints() == []


def test_browser_sessions_are_kept_until_they_expire_or_are_closed(store):
    assert store.session_proof("k1") is None
    store.create_session("k1", "proof-1", ttl_s=60)
    store.create_session("k2", "proof-2", ttl_s=0.3)
    assert store.session_proof("k1") == "proof-1" and store.session_proof("k2") == "proof-2"
    time.sleep(0.5)
    assert store.session_proof("k2") is None  # expired
    store.delete_session("k1")
    assert store.session_proof("k1") is None  # signed out


def test_filters_counts_and_pages_follow_every_state_change(store):
    """Listing by status, kind or both, counting by status and by kind, and pages with their totals
    agree with the records through submit, claim, finish, cancel and delete."""
    jobs = [store.submit(kind, {"i": i}, {})[0]
            for i, kind in enumerate(["train", "eval", "train", "sweep", "eval", "train"])]  # fmt: skip
    first = store.claim("w1", lease_s=30)
    second = store.claim("w1", lease_s=30)
    store.finish(first.id, "w1", "succeeded", result={})
    store.cancel(jobs[5].id)
    store.delete(jobs[5].id)
    records = [store.get(j.id) for j in jobs[:5]]
    for status in JobStatus:
        for kind in ("train", "eval", "sweep", "trial"):
            want = [j.id for j in reversed(records) if j.status == status and j.kind.value == kind]
            page, total = store.list(status=status, kind=kind, limit=50)
            assert total == len(want) and [j.id for j in page] == want, (status, kind)
        want = [j.id for j in reversed(records) if j.status == status]
        assert store.list(status=status)[1] == len(want) == store.counts()[status.value]
    by_kind = store.counts_by_kind()
    assert set(by_kind) == {"train", "eval", "sweep", "trial"}
    assert by_kind["train"]["succeeded"] == 1 and by_kind["eval"]["running"] == 1
    assert sum(n for k in by_kind.values() for n in k.values()) == 5
    assert second.status == JobStatus.running
    page, total = store.list(kind="eval", limit=1, offset=1)
    assert total == 2 and [j.id for j in page] == [jobs[1].id]
    assert store.list(offset=10) == ([], 5)


def test_wait_events_wakes_on_news_and_times_out_without(store):
    a, _ = store.submit("train", {}, {})
    b, _ = store.submit("train", {}, {})
    t0 = time.monotonic()
    assert store.wait_events({a.id: 0, b.id: 0}, timeout_s=0.3) == set()
    assert time.monotonic() - t0 >= 0.25
    seq = store.publish(b.id, {"type": "progress"})
    assert store.wait_events({a.id: 0, b.id: 0}, timeout_s=5) == {b.id}
    assert store.wait_events({a.id: 0, b.id: seq}, timeout_s=0.2) == set()
    # an event published while a viewer waits wakes it at once
    import threading

    # (the publisher is joined before the test ends: its publish never meets the next test's store)
    publisher = threading.Timer(0.2, lambda: store.publish(a.id, {"type": "progress"}))
    publisher.start()
    t0 = time.monotonic()
    try:
        assert store.wait_events({a.id: 0, b.id: seq}, timeout_s=5) == {a.id}
        assert time.monotonic() - t0 < 2.0
    finally:
        publisher.join()
    with pytest.raises(JobNotFound):
        store.publish("0" * 32, {"type": "progress"})  # no job: nothing written


def test_redis__a_store_written_before_the_indexes_is_indexed_once():
    client = redis.Redis.from_url(REDIS_URL, decode_responses=True)
    client.flushdb()
    prefix = f"t{uuid.uuid4().hex[:8]}"
    old = RedisJobStore(REDIS_URL, prefix=prefix)
    made = [old.submit(kind, {"i": i}, {})[0] for i, kind in enumerate(["train", "eval", "train"])]
    old.cancel(made[1].id)
    # as a store of the previous release left it: records, the creation-time set, status sets
    for key in client.scan_iter(f"{prefix}:st:*"):
        client.delete(key)
    for key in [*client.scan_iter(f"{prefix}:sk:*"), *client.scan_iter(f"{prefix}:kd:*"), f"{prefix}:index"]:
        client.delete(key)
    client.sadd(f"{prefix}:status:queued", made[0].id, made[2].id)
    client.sadd(f"{prefix}:status:cancelled", made[1].id)
    new = RedisJobStore(REDIS_URL, prefix=prefix)
    assert new.counts()["queued"] == 2 and new.counts()["cancelled"] == 1
    assert [j.id for j in new.list(kind="train")[0]] == [made[2].id, made[0].id]
    assert new.list(status="cancelled", kind="eval")[1] == 1
    assert not client.exists(f"{prefix}:status:queued") and client.get(f"{prefix}:index") == "2"
    client.flushdb()


def test_claim_takes_only_what_the_worker_can_run_in_queue_order(store):
    big, _ = store.submit("train", {"n": "big"}, {})
    small1, _ = store.submit("train", {"n": "small1"}, {})
    small2, _ = store.submit("train", {"n": "small2"}, {})
    one_device = lambda job: job.request["n"] != "big"  # noqa: E731
    assert store.claim("w1", 30, can_run=one_device).id == small1.id
    assert store.claim("w1", 30, can_run=lambda job: False) is None
    assert store.get(big.id).status == JobStatus.queued  # passed over, still queued
    assert store.claim("w1", 30, can_run=one_device).id == small2.id
    assert store.claim("w1", 30, can_run=one_device) is None
    assert store.claim("w2", 30).id == big.id  # a worker that can run it takes it


def test_an_orphan_waits_for_a_worker_that_can_run_it(store):
    big, _ = store.submit("train", {"n": "big"}, {})
    assert store.claim("w2", lease_s=0.2).id == big.id
    time.sleep(0.4)  # its worker died
    assert store.claim("w1", lease_s=0.2, can_run=lambda job: False) is None
    assert store.get(big.id).status == JobStatus.running
    time.sleep(0.4)
    again = store.claim("w3", lease_s=0.2)
    assert again is not None and again.id == big.id and again.attempts == 2


def test_worker_announcements_expire_unless_renewed(store):
    store.announce_worker({"worker": "a", "devices": 1}, ttl_s=0.3)
    store.announce_worker({"worker": "b", "devices": 2}, ttl_s=5)
    assert [w["worker"] for w in store.live_workers()] == ["a", "b"]
    assert store.live_workers()[1]["devices"] == 2
    time.sleep(0.5)
    assert [w["worker"] for w in store.live_workers()] == ["b"]
    store.withdraw_worker("b")
    assert store.live_workers() == []
