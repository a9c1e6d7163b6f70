"""A bounded fuzz of the OpenAPI schema (schemathesis, in-process ASGI): no request gets a 5xx.

The app and its data folder are built by a fixture when the test runs, not when the module is
collected; each API operation is fuzzed with Hypothesis from schemathesis' strategy for it.
"""

from __future__ import annotations

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings

from quicknav_service.api.main import create_app
from quicknav_service.jobs.sqlite_store import SQLiteJobStore
from quicknav_service.settings import Settings

EXAMPLES_PER_OPERATION = 15


@pytest.fixture(scope="module")
def api_schema(tmp_path_factory):
    data = tmp_path_factory.mktemp("fuzz")
    app = create_app(Settings(data_dir=data, embedded_worker=False),
                     SQLiteJobStore(data / "jobs.db"), start_workers=False)  # fmt: skip
    return schemathesis.openapi.from_asgi("/openapi.json", app)


def test_api_never_answers_5xx(api_schema):
    operations = [
        result.ok()
        for result in api_schema.exclude(path_regex=".*/events$").get_all_operations()
    ]
    assert len(operations) >= 12, [f"{op.method} {op.path}" for op in operations]
    for operation in operations:

        @given(case=operation.as_strategy())
        @settings(max_examples=EXAMPLES_PER_OPERATION, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck))  # fmt: skip
        def never_5xx(case):
            response = case.call()
            assert response.status_code < 500, (
                case.method,
                case.path,
                response.status_code,
                response.text[:500],
            )

        never_5xx()
