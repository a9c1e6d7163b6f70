"""The published OpenAPI document, with error bodies typed as what they are."""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi


def _errors_as_json(spec: dict[str, Any]) -> dict[str, Any]:
    # FastAPI files an error's model under the route's own media type: text/event-stream for
    # the event stream, the file's for a download. Errors are JSON on every route.
    for operation in (op for path in spec.get("paths", {}).values() for op in path.values()):
        for status, response in operation.get("responses", {}).items():
            content = response.get("content")
            if status.isdigit() and int(status) >= 400 and content and "application/json" not in content:
                response["content"] = {"application/json": next(iter(content.values()))}
    return spec


def install(app: FastAPI) -> None:
    """Build the document once, on first request, from the app's routes."""

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = _errors_as_json(get_openapi(
                title=app.title, version=app.version, description=app.description,
                routes=app.routes, separate_input_output_schemas=app.separate_input_output_schemas,
            ))  # fmt: skip
        return app.openapi_schema

    app.openapi = openapi
