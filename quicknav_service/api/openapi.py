"""The published OpenAPI document, with error bodies typed as what they are."""

from __future__ import annotations

import copy
from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi

from quicknav_core.config.base import EXACTLY_ONE_OF


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


def _variant_name(model: str, field: str) -> str:
    return model + "".join(part.capitalize() for part in field.split("_"))


def _exactly_one_as_variants(spec: dict[str, Any]) -> dict[str, Any]:
    # a request that takes exactly one of two fields (x-exactly-one-of, set by the models) is
    # published as a oneOf of two complete objects, one per field: the field required and not
    # null, the other null or absent. A generated client gets a model per variant (a oneOf
    # beside the object's own properties gave it models without the other fields), and a
    # request the document calls valid is one the server accepts.
    schemas = spec.get("components", {}).get("schemas", {})
    for name, schema in list(schemas.items()):
        pair = schema.pop(EXACTLY_ONE_OF, None)
        if not pair:
            continue
        refs = []
        for field, other in (pair, pair[::-1]):
            variant = copy.deepcopy(schema)
            props = variant["properties"]
            given = [s for s in props[field].get("anyOf", [props[field]]) if s.get("type") != "null"]
            keep = {k: v for k, v in props[field].items() if k not in ("anyOf", "default")}
            if "enum" in keep:
                keep["enum"] = [v for v in keep["enum"] if v is not None]
            props[field] = {**keep, **given[0]} if len(given) == 1 else {**keep, "anyOf": given}
            props[other] = {"type": "null", "description": f"not with {field}"}
            variant["required"] = [field, *(f for f in variant.get("required", ()) if f != field)]
            variant["title"] = _variant_name(name, field)
            variant["description"] = f"{schema.get('description', name)} (with {field!r})"
            schemas[variant["title"]] = variant
            refs.append({"$ref": f"#/components/schemas/{variant['title']}"})
        schemas[name] = {"title": name, "description": schema.get("description", ""), "oneOf": refs}
    return spec


def _no_null_where_text_is_sent(spec: dict[str, Any]) -> dict[str, Any]:
    # a multipart form has no null: an optional field is one left out. FastAPI documents an
    # optional form field (and header) as "X or null", and a client that sends the text "null"
    # gets a 422
    schemas = spec.get("components", {}).get("schemas", {})
    for operation in (op for path in spec.get("paths", {}).values() for op in path.values()):
        form = operation.get("requestBody", {}).get("content", {}).get("multipart/form-data", {})
        ref = form.get("schema", {}).get("$ref", "")
        body = schemas.get(ref.rsplit("/", 1)[-1], {}) if ref else form.get("schema", {})
        for name, prop in body.get("properties", {}).items():
            body["properties"][name] = _not_null(prop)
        # a header has no null either (a client that sends "null" sends text)
        for param in operation.get("parameters", ()):
            if param.get("in") == "header":
                param["schema"] = _not_null(param["schema"])
    return spec


def _not_null(prop: dict[str, Any]) -> dict[str, Any]:
    kinds = [k for k in prop.get("anyOf", ()) if k.get("type") != "null"]
    if "anyOf" not in prop or len(kinds) != 1:
        return prop
    return {**{k: v for k, v in prop.items() if k not in ("anyOf", "default")}, **kinds[0]}


def _server_limits(spec: dict[str, Any], max_eval_episodes: int | None) -> dict[str, Any]:
    # an eval job's episodes are capped by this server's QUICKNAV_MAX_EVAL_EPISODES (below the
    # library's own ceiling): the document states the cap this server applies
    if max_eval_episodes is None:
        return spec
    for name, schema in spec.get("components", {}).get("schemas", {}).items():
        episodes = schema.get("properties", {}).get("episodes")
        if name.startswith("EvalJobCreate") and episodes is not None:
            episodes["maximum"] = min(episodes.get("maximum", max_eval_episodes), max_eval_episodes)
            episodes["description"] = "episodes to run (this server's limit: QUICKNAV_MAX_EVAL_EPISODES)"
    return spec


def install(app: FastAPI, api_token: bool = True, metrics_token: bool = False,
            max_eval_episodes: int | None = None) -> None:
    """Build the document once, on first request, from the app's routes (with the token the
    server asks for: none, when it was started without one, and this server's limits)."""

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            spec = get_openapi(title=app.title, version=app.version, description=app.description,
                               routes=app.routes,
                               separate_input_output_schemas=app.separate_input_output_schemas)  # fmt: skip
            spec = _no_null_where_text_is_sent(_exactly_one_as_variants(_errors_as_json(spec)))
            spec = _security_as_configured(spec, api_token, metrics_token)
            app.openapi_schema = _server_limits(spec, max_eval_episodes)
        return app.openapi_schema

    app.openapi = openapi
