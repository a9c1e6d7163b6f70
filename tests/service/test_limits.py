"""The server's limits are checked in one place (``quicknav_core.admission.admit``) and say the
same thing at every door."""

import json

import pytest
from quicknav_client.proto.quicknav.v1 import rollout_pb2 as pb

from quicknav_core.admission import RolloutRequest, admit
from quicknav_service.jobs.limits import server_limits
from quicknav_service.jobs.service import Invalid, JobsService
from quicknav_service.jobs.sqlite_store import SQLiteJobStore
from quicknav_service.rollout.common import Refused
from quicknav_service.rollout.start import admit_start, read_start
from quicknav_service.runtime import service_runtime
from quicknav_service.schemas import EvalJobCreate, TrainJobCreate
from quicknav_service.settings import Settings


def start_admitted(start: pb.Start, settings: Settings) -> None:
    """What the Rollout servicer does with a Start before building anything."""
    admit_start(read_start(start), settings, service_runtime(settings))


@pytest.fixture
def service(tmp_path):
    settings = Settings(data_dir=tmp_path, max_grid_size=32, max_lidar_beams=64)
    store = SQLiteJobStore(tmp_path / "jobs.db")
    yield settings, JobsService(store, settings)
    store.close()


def test_limits__train_eval_and_a_rollout_start_refuse_the_same_grid_in_the_same_words(service):
    settings, jobs = service
    want = ("grid_size=40 exceeds this server's limit max_grid_size=32 (QUICKNAV_MAX_GRID_SIZE);"
            " allowed range 4..32")  # fmt: skip
    with pytest.raises(Invalid) as train:
        jobs.submit_train(TrainJobCreate(preset="demo", overrides={"env.grid_size": 40, "env.room_size": 20}))
    assert [(i["loc"], i["msg"]) for i in train.value.items] == [(["overrides", "env.grid_size"], want)]
    with pytest.raises(Invalid) as evaluation:
        jobs.submit_eval(EvalJobCreate(policy="oracle", env={"grid_size": 40, "room_size": 20}))
    assert [(i["loc"], i["msg"]) for i in evaluation.value.items] == [(["env", "grid_size"], want)]
    with pytest.raises(Refused) as start:
        start_admitted(pb.Start(config_json=json.dumps({"grid_size": 40, "room_size": 20, "lidar_beams": 80})), settings)
    assert str(start.value.message) == (
        f"start.config.{want}; start.config.lidar_beams=80 exceeds this server's limit"
        " max_lidar_beams=64 (QUICKNAV_MAX_LIDAR_BEAMS); allowed range 1..64"
    )


def test_limits__an_env_within_them_passes(service):
    from quicknav_core.config import EnvConfig

    settings, _ = service
    request = RolloutRequest(EnvConfig(grid_size=32, room_size=16, lidar_beams=64), num_envs=16)
    assert admit(request, server_limits(settings), service_runtime(settings)) == []


def test_limits__floor_plans_run_through_the_service_and_map_files_on_the_clients_disk_are_refused(service):
    settings, jobs = service
    job = jobs.submit_train(TrainJobCreate(preset="demo", overrides={"env.rooms": "floorplan"}))
    assert job.config["env"]["rooms"] == "floorplan"
    with pytest.raises(Invalid) as refused:
        jobs.submit_train(TrainJobCreate(preset="demo", overrides={
            "env.rooms": "maps", "env.maps": {"train": ["examples/maps/office.yaml"]},
            "env.grid_size": 32, "env.room_size": 16}))  # fmt: skip
    [item] = refused.value.items
    assert item["loc"] == ["overrides", "env.maps", "train", 0] and "POST /maps" in item["msg"]
    with pytest.raises(Refused, match="is a file on your disk"):
        start_admitted(pb.Start(config_json=json.dumps(
            {"rooms": "maps", "maps": {"train": ["x.yaml"]}})), settings)  # fmt: skip


def test_one_door__rest_cli_and_a_rollout_start_refuse_a_robot_that_fits_in_no_room(service):
    """The same admission at every door: a robot wider than every passage (here 1.8 m across on
    0.5 m cells) is refused naming robot_radius, before anything trains or steps."""
    from typer.testing import CliRunner

    from quicknav_cli.main import app

    settings, jobs = service
    wide = {"env.grid_size": 8, "env.train_rooms": 16, "env.test_rooms": 8, "env.robot_radius": 0.9}
    with pytest.raises(Invalid) as rest:
        jobs.submit_train(TrainJobCreate(preset="demo", overrides=wide))
    [item] = rest.value.items
    assert item["loc"] == ["overrides", "env.robot_radius"] and "fits in fewer than two cells" in item["msg"]
    cli = CliRunner().invoke(app, ["train", "--preset", "demo", *[f"--set={k}={v}" for k, v in wide.items()]])
    assert cli.exit_code != 0 and item["msg"] in " ".join(cli.output.split()), cli.output
    start = {k.removeprefix("env."): v for k, v in wide.items()}
    with pytest.raises(Refused, match="fits in fewer than two cells") as refused:
        start_admitted(pb.Start(config_json=json.dumps(start), num_envs=4), settings)
    assert refused.value.code.name == "INVALID_ARGUMENT"


def test_one_door__a_start_with_a_million_rooms_is_refused_by_its_memory_before_building(service):
    """REST refused this (the job's estimate exceeds the budget); a gRPC Start now does too, at
    once, instead of carving rooms past the client's deadline."""
    import time

    settings, jobs = service
    rooms = {"train_rooms": 1_000_000, "grid_size": 32, "room_size": 16}
    with pytest.raises(Invalid) as rest:
        jobs.submit_train(TrainJobCreate(preset="demo", overrides={f"env.{k}": v for k, v in rooms.items()}))
    assert "needs about" in rest.value.items[0]["msg"]
    t0 = time.perf_counter()
    with pytest.raises(Refused) as start:
        start_admitted(pb.Start(config_json=json.dumps(rooms), num_envs=4), settings)
    assert time.perf_counter() - t0 < 5  # judged by its estimate: nothing was carved
    assert start.value.code.name == "RESOURCE_EXHAUSTED", start.value.message
    message = start.value.message
    assert message.startswith("start.config.train_rooms: the job needs about") and "MAX_JOB_MEMORY_MB" in message


def test_one_door__a_wide_robot_is_checked_on_the_first_rooms_of_each_bank_not_on_200k(service):
    """The API does not build envs: a wide robot is checked against the first FIT_ROOMS rooms of
    each bank (a fuzzed job with 200,000 rooms held one request ~100 s carving them all); the
    worker's env build checks every room. A robot that fits is queued, one that does not is
    refused with how many rooms were checked."""
    import numpy as np

    from quicknav_service.jobs.limits import FIT_ROOMS

    settings, jobs = service
    many = {"env.train_rooms": 200_000, "env.test_rooms": 100_000}
    job = jobs.submit_train(TrainJobCreate(preset="demo", overrides={**many, "env.robot_radius": 0.3}))
    assert job.status == "queued"
    built = sorted((settings.data_dir / "room-banks").glob("bank-*.npz"))
    assert len(built) == 2  # the check ran, on both banks
    for path in built:
        with np.load(path) as bank:
            assert int(bank["shape"][0]) == FIT_ROOMS, path.name
    with pytest.raises(Invalid) as rest:
        jobs.submit_train(TrainJobCreate(preset="demo", overrides={**many, "env.grid_size": 8, "env.robot_radius": 0.9}))
    [item] = rest.value.items
    assert item["loc"] == ["overrides", "env.robot_radius"]
    assert f"of the first {FIT_ROOMS} of the 200,000 train rooms" in item["msg"], item["msg"]
