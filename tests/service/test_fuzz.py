"""A bounded fuzz of the OpenAPI schema (schemathesis, in-process ASGI): no request gets a 5xx."""

from __future__ import annotations

import schemathesis
from hypothesis import HealthCheck, settings

from service.api.app import create_app
from service.jobs.sqlite_store import SQLiteJobStore
from service.settings import Settings

_data = __import__("tempfile").mkdtemp(prefix="quicknav-fuzz-")
_settings = Settings(data_dir=_data, embedded_worker=False)
app = create_app(_settings, SQLiteJobStore(f"{_data}/jobs.db"), start_workers=False)
schema = schemathesis.openapi.from_asgi("/openapi.json", app)


@schema.exclude(path_regex=".*/events$").parametrize()
@settings(max_examples=15, deadline=None, suppress_health_check=list(HealthCheck))
def test_api_never_answers_5xx(case):
    response = case.call()
    assert response.status_code < 500, (
        case.method,
        case.path,
        response.status_code,
        response.text[:500],
    )
