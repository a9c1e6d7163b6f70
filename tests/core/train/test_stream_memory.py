"""Admission of the gRPC server's streams against their measured peaks: the estimate of a Rollout
stream (``rollout_memory``) and of a Policy stream (``policy_memory``) for every case of
``quicknav_core.bench.memory`` is within 10 % of the peak RSS the benchmark measured (a fresh
process with the server's imports doing what one stream does, compiling every program).

The measurements are the benchmark's; this test holds the estimates to them, so a change of the
formula that drifts from what was measured fails here. Before they were measured, both streams
were admitted by one 900 MB guess, 1.3-2.6 times what they took."""

from __future__ import annotations

import json

import pytest

from quicknav_core.bench.memory import (
    POLICY_CASES,
    ROLLOUT_CASES,
    ROLLOUT_TOGETHER_CASES,
    rollout_case,
    rollout_estimate,
)
from quicknav_core.config import EnvConfig, resolve_train
from quicknav_core.train.memory import MB, POLICY_MAX_ROWS, policy_memory, rollout_memory
from tests.journeys.readme import ROOT

RESULTS = json.loads((ROOT / "benchmarks/results/memory.json").read_text())
ROLLOUTS = {r["case"]: r for r in RESULTS["rollout_rows"]}
POLICIES = {r["case"]: r for r in RESULTS["policy_rows"]}


def _check(name: str, est, measured_mb: int) -> None:
    ratio = est.total / (measured_mb * MB)
    assert 0.9 <= ratio <= 1.1, f"{name}: estimate {est.describe()}; measured {measured_mb} MB (ratio {ratio:.2f})"


def test_stream_admission__every_case_has_been_measured():
    assert set(ROLLOUTS) == {c[0] for c in ROLLOUT_CASES + ROLLOUT_TOGETHER_CASES}
    assert set(POLICIES) == {c[0] for c in POLICY_CASES}
    # a policy of every network kind, and rollouts with and without the plan's programs
    assert {resolve_train({"preset": p}).network.kind for _, p in POLICY_CASES} == {"mlp", "lstm", "gtrxl"}
    assert {resolve_train({"preset": p}).env.observe_plan for _, p, _ in ROLLOUT_CASES} == {True, False}


@pytest.mark.parametrize("name,preset,num_envs", ROLLOUT_CASES, ids=[c[0] for c in ROLLOUT_CASES])
def test_rollout_admission__estimate_within_ten_percent_of_the_measured_peak(name, preset, num_envs):
    row = ROLLOUTS[name]
    assert (row["preset"], row["num_envs"]) == (preset, num_envs), row  # the case that was measured
    env = EnvConfig.model_validate(rollout_case(preset, num_envs)["env"])
    _check(name, rollout_memory(env, num_envs), row["measured_mb"])


@pytest.mark.parametrize("name,preset,num_envs,streams", ROLLOUT_TOGETHER_CASES,
                         ids=[c[0] for c in ROLLOUT_TOGETHER_CASES])  # fmt: skip
def test_rollout_admission__streams_open_together_within_ten_percent(name, preset, num_envs, streams):
    """Several streams in one server (QUICKNAV_ROLLOUT_MEMORY_MB): the runtime once and every
    stream's banks and envs added up (``train.memory.together``), against the measured peak of
    one process stepping them side by side; counting the runtime per stream would be far above."""
    from quicknav_core.train.memory import together

    row = ROLLOUTS[name]
    assert (row["preset"], row["num_envs"], row["streams"]) == (preset, num_envs, streams), row
    case = rollout_case(preset, num_envs, streams)
    _check(name, rollout_estimate(case), row["measured_mb"])
    one = rollout_memory(EnvConfig.model_validate(case["env"]), num_envs)
    assert together([one] * streams).total == rollout_estimate(case).total
    assert streams * one.total > 1.1 * row["measured_mb"] * MB  # the naive sum would not pass


@pytest.mark.parametrize("name,preset", POLICY_CASES, ids=[c[0] for c in POLICY_CASES])
def test_policy_admission__estimate_within_ten_percent_of_the_measured_peak(name, preset):
    row = POLICIES[name]
    assert (row["preset"], row["rows"]) == (preset, POLICY_MAX_ROWS), row
    _check(name, policy_memory(resolve_train({"preset": preset})), row["measured_mb"])


def test_policy_admission__the_door_counts_one_streams_most_rows():
    """The Policy stream is admitted (``admit``, the door its ``load`` passes) by the estimate for
    the most rows a stream may ask for: a budget that would hold the policy acting for 8 rows but
    not for POLICY_MAX_ROWS refuses it, naming the estimate; the full estimate's budget admits it."""
    from quicknav_core.admission import Limits, PolicyRequest, admit
    from quicknav_core.train.memory import megabytes

    cfg = resolve_train({"preset": "paper-gtrxl"})
    full, few = megabytes(policy_memory(cfg).total), megabytes(policy_memory(cfg, 8).total)
    assert few < full
    [refused] = admit(PolicyRequest(cfg), Limits(max_job_memory_mb=full - 1))
    assert refused.get("capacity") and f"needs about {full:,} MB" in refused["msg"], refused
    assert admit(PolicyRequest(cfg), Limits(max_job_memory_mb=full)) == []


def test_stream_estimate__names_the_field_as_the_start_does():
    """A policy-mode stream's estimate is an evaluation's; the field it names is the Start's:
    its episodes are the stream's envs, its env the Start's config (not ``env.grid_size``)."""
    from quicknav_core.admission import RolloutRequest, stream_estimate

    big_grid = EnvConfig(grid_size=128, room_size=64.0, train_rooms=16, test_rooms=8)
    assert stream_estimate(RolloutRequest(big_grid, 4, policy=True))[1] == "grid_size"
    many = EnvConfig(grid_size=8, train_rooms=16, test_rooms=8, max_steps=2000)
    assert stream_estimate(RolloutRequest(many, 1024, policy=True))[1] == "num_envs"
