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


def _security_as_configured(spec: dict[str, Any], api_token: bool, metrics_token: bool) -> dict[str, Any]:
    # the routes declare the bearer token; a server started without one asks for none, and its
    # document says so (only /metrics keeps it when a metrics token alone is set)
    for path, item in spec.get("paths", {}).items():
        needed = (api_token or metrics_token) if path == "/metrics" else api_token
        for operation in item.values():
            if not needed and isinstance(operation, dict):
                operation.pop("security", None)
    if not (api_token or metrics_token):
        spec.get("components", {}).pop("securitySchemes", None)
    return spec


def install(app: FastAPI, api_token: bool = True, metrics_token: bool = False) -> None:
    """Build the document once, on first request, from the app's routes (with the token the
    server asks for: none, when it was started without one)."""

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = _security_as_configured(_errors_as_json(get_openapi(
                title=app.title, version=app.version, description=app.description,
                routes=app.routes, separate_input_output_schemas=app.separate_input_output_schemas,
            )), api_token, metrics_token)  # fmt: skip
        return app.openapi_schema

    app.openapi = openapi
