"""The published OpenAPI document is usable by a third party: a client generated from a live
server's ``/openapi.json`` by openapi-python-client (generated here, offline) submits, reads back
and lists jobs, and gets typed 422s that name the bad field; every answer parses into the
generated models. A generation warning (a schema it cannot turn into code) fails the test.

The server has a token and no workers: submitted jobs only queue.
"""

from __future__ import annotations

import importlib
import json
import subprocess
import sys
from types import SimpleNamespace

import httpx
import pytest

from quicknav_core.train.run import CHECKPOINT_DIR, META_FILE, STATE_FILE
from tests.service.conftest import LiveServer

TOKEN = "generated-client-token"
PACKAGE = "quicknav_generated_client"
# The generator in a child process that refuses any network access (an audit hook on the
# socket calls): the document is a local file, so generation needs nothing from outside.
OFFLINE_GENERATOR = """
import sys
def refuse(event, args):
    if event in ("socket.connect", "socket.getaddrinfo"):
        raise RuntimeError(f"openapi-python-client tried the network: {event} {args}")
sys.addaudithook(refuse)
from openapi_python_client.cli import app
sys.argv[0] = "openapi-python-client"
app()
"""


def _module(name: str):
    return importlib.import_module(f"{PACKAGE}.{name}")


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    with LiveServer(tmp_path_factory.mktemp("generated-client"), api_token=TOKEN) as live:
        yield live


@pytest.fixture(scope="module")
def gen(server, tmp_path_factory):
    """The generated package's modules used here, and an AuthenticatedClient on the server."""
    out = tmp_path_factory.mktemp("openapi")
    document = out / "openapi.json"
    document.write_text(json.dumps(httpx.get(f"{server.url}/openapi.json", timeout=10).json()))
    config = out / "config.json"
    config.write_text(json.dumps({"post_hooks": []}))  # no ruff/black formatting pass
    done = subprocess.run(
        [sys.executable, "-c", OFFLINE_GENERATOR, "generate", "--path", str(document),
         "--output-path", str(out / PACKAGE), "--meta", "none", "--config", str(config),
         "--fail-on-warning"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stdout + done.stderr
    # --meta none: the output folder is the package itself
    assert (out / PACKAGE / "client.py").is_file(), sorted(p.name for p in out.iterdir())

    sys.path.insert(0, str(out))
    try:
        client_mod = _module("client")
        yield SimpleNamespace(
            client=client_mod.AuthenticatedClient(base_url=server.url, token=TOKEN, timeout=30),
            anonymous=client_mod.Client(base_url=server.url, timeout=30),
            models=_module("models"),
            submit_train=_module("api.jobs.submit_train_job"),
            submit_eval=_module("api.jobs.submit_eval_job"),
            read_job=_module("api.jobs.read_job"),
            list_jobs=_module("api.jobs.list_jobs"),
        )
    finally:
        sys.path.remove(str(out))
        for name in [n for n in sys.modules if n == PACKAGE or n.startswith(f"{PACKAGE}.")]:
            del sys.modules[name]


def _demo_request(gen, **fields):
    """The generated model of a train request by preset (the document's variant with a preset;
    the presets are an enum there)."""
    return gen.models.TrainRequestPreset(preset=gen.models.TrainRequestPresetPreset.DEMO, **fields)


def _submit_demo(gen):
    answer = gen.submit_train.sync_detailed(client=gen.client,
                                            body=_demo_request(gen))  # fmt: skip
    assert answer.status_code == 202, answer.content
    assert isinstance(answer.parsed, gen.models.JobPublic), answer.parsed
    return answer


def test_generated_client__submits_a_demo_train_job_and_reads_it_back(gen):
    submitted = _submit_demo(gen)
    job = submitted.parsed
    assert submitted.headers["Location"] == f"/jobs/{job.id}"

    answer = gen.read_job.sync_detailed(job.id, client=gen.client)
    assert answer.status_code == 200, answer.content
    read = answer.parsed
    assert isinstance(read, gen.models.JobPublic), read  # the generated model, not a raw dict
    assert read.id == job.id
    assert read.kind == gen.models.JobKind.TRAIN and read.kind.value == "train"
    assert read.status == gen.models.JobStatus.QUEUED and read.status.value == "queued"
    assert read.request.to_dict() == {"preset": "demo"}
    assert read.config.to_dict()["total_steps"] > 0  # the resolved config, as stored
    assert read.links.to_dict()["self"] == f"/jobs/{job.id}"


def test_generated_client__without_the_token_is_a_typed_401(gen):
    answer = gen.submit_train.sync_detailed(client=gen.anonymous,
                                            body=_demo_request(gen))  # fmt: skip
    assert answer.status_code == 401, answer.content
    assert isinstance(answer.parsed, gen.models.HTTPError), answer.parsed


def test_generated_client__a_bad_override_is_a_422_naming_the_field(gen):
    overrides = gen.models.TrainRequestPresetOverrides.from_dict({"env.grid_size": 1000})
    answer = gen.submit_train.sync_detailed(
        client=gen.client, body=_demo_request(gen, overrides=overrides)
    )
    assert answer.status_code == 422, answer.content
    body = answer.parsed
    assert isinstance(body, gen.models.ValidationErrorBody), body
    assert all(isinstance(e, gen.models.FieldError) for e in body.detail)
    [error] = body.detail
    assert error.loc == ["body", "overrides", "env.grid_size"]
    assert error.type_ == "less_than_equal" and "less than or equal to 256" in error.msg, error.msg


def test_generated_client__eval_of_the_train_job_by_job_id_is_accepted(gen, server):
    train = _submit_demo(gen).parsed
    body = gen.models.EvalJobCreateJobId(job_id=train.id)
    # a queued train job has nothing to evaluate yet: a typed 409 that says so
    early = gen.submit_eval.sync_detailed(client=gen.client, body=body)
    assert early.status_code == 409, early.content
    assert isinstance(early.parsed, gen.models.HTTPError) and "no checkpoint" in early.parsed.detail

    # No worker trains here: give the job a checkpoint folder by hand. The eval only queues,
    # so its state is never read; submission checks only that a complete checkpoint exists.
    checkpoint = server.settings.artifacts_dir / train.id / CHECKPOINT_DIR
    checkpoint.mkdir(parents=True)
    (checkpoint / STATE_FILE).write_bytes(b"never read")
    (checkpoint / META_FILE).write_text("{}")
    answer = gen.submit_eval.sync_detailed(client=gen.client, body=body)
    assert answer.status_code == 202, answer.content
    evaluation = answer.parsed
    assert isinstance(evaluation, gen.models.JobPublic), evaluation
    assert evaluation.kind == gen.models.JobKind.EVAL
    assert evaluation.status == gen.models.JobStatus.QUEUED
    assert evaluation.request.to_dict()["job_id"] == train.id


def test_generated_client__lists_the_job(gen):
    train = _submit_demo(gen).parsed
    answer = gen.list_jobs.sync_detailed(client=gen.client, kind=gen.models.JobKind.TRAIN,
                                         limit=500)  # fmt: skip
    assert answer.status_code == 200, answer.content
    listed = answer.parsed
    assert isinstance(listed, gen.models.JobsPublic), listed
    assert all(isinstance(j, gen.models.JobPublic) for j in listed.data)
    assert listed.count == len(listed.data) >= 1
    [mine] = [j for j in listed.data if j.id == train.id]
    assert mine.status == gen.models.JobStatus.QUEUED
