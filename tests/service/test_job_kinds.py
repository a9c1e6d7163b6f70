"""The worker is mechanics plus a registry: every job kind has its runner, trials a typed spec."""

import pytest
from pydantic import ValidationError

from quicknav_core.config import resolve_sweep
from quicknav_service.job_kinds import RUNNERS, TrialSpec
from quicknav_service.jobs.models import JobKind


def test_registry__every_kind_of_job_has_one_runner():
    assert set(RUNNERS) == set(JobKind)
    assert {fn.__name__ for fn in RUNNERS.values()} == {"train", "evaluate", "sweep", "trial"}


def test_trial_spec__round_trips_through_json_and_refuses_what_it_cannot_run():
    sweep = resolve_sweep({"space": "ppo", "trials": 4, "parallel": 2})
    spec = TrialSpec(parent="a" * 32, batch=1, trials=2, sweep=sweep)
    assert TrialSpec.model_validate(spec.model_dump(mode="json")) == spec
    with pytest.raises(ValidationError, match="batch"):
        TrialSpec(parent="a" * 32, batch=-1, trials=2, sweep=sweep)
    with pytest.raises(ValidationError, match="sweep"):
        TrialSpec.model_validate({"parent": "a" * 32, "batch": 0, "trials": 1})
