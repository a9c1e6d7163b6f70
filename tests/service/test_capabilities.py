"""What a job needs, what a worker has, and why a job waits."""

import pytest

from quicknav_core.config import apply_overrides, get_preset, resolve_eval
from quicknav_service.jobs.capabilities import Capabilities, Needs, job_needs, unmet, waiting_reason
from quicknav_service.jobs.models import JobKind, new_job


def _train(**overrides):
    cfg = apply_overrides(get_preset("demo"), [f"{k}={v}" for k, v in overrides.items()])
    return new_job(JobKind.train, {}, cfg.model_dump(mode="json"), None, 3)


def _caps(devices=1, memory_mb=8000, worker="w"):
    return Capabilities(worker=worker, backend="cpu", devices=devices, device_kind="cpu", memory_mb=memory_mb)


def test_needs__read_from_the_stored_config():
    two = job_needs(_train(devices=2))
    assert two.devices == 2 and two.num_envs == 64 and 100 < two.memory_mb < 8000
    assert job_needs(_train()).devices == 1
    ev = new_job(JobKind.eval, {}, resolve_eval({"policy": "oracle"}).model_dump(mode="json"), None, 3)
    assert job_needs(ev).devices == 1 and job_needs(ev).memory_mb > 0
    assert job_needs(new_job(JobKind.train, {}, {"nonsense": 1}, None, 3)) == Needs()


@pytest.mark.parametrize(
    "needs, caps, why",
    [
        (Needs(2, 64, 500), _caps(1), "2 devices"),
        (Needs(2, 64, 500), _caps(2), None),
        (Needs(1, 64, 9000), _caps(4, 8000), "9,000 MB of memory"),
        (Needs("all", 64, 500), _caps(3), "devices='all' needs a device count dividing num_envs=64"),
        (Needs("all", 64, 500), _caps(4), None),
    ],
)
def test_unmet__names_what_is_missing(needs, caps, why):
    assert unmet(needs, caps) == why


def test_waiting_reason__says_what_the_job_needs_and_what_the_live_workers_have():
    needs = Needs(2, 64, 500)
    assert waiting_reason(needs, []) is None  # no worker yet: it waits for any, like every job
    assert waiting_reason(needs, [_caps(1), _caps(2)]) is None
    assert waiting_reason(needs, [_caps(1)]) == (
        "waiting for a worker with 2 devices; the 1 live worker has 1 device and up to 8,000 MB per job"
    )
    assert waiting_reason(needs, [_caps(1, worker="a"), _caps(1, 4000, "b")]).endswith(
        "the 2 live workers have 1 device and up to 8,000 MB per job"
    )
