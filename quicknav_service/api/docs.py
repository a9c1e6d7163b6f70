"""The interactive API docs (/docs) and the static files the API serves."""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles

from quicknav_service.web import routes as web

STATIC_DIR = Path(__file__).resolve().parent / "static"


def install(app: FastAPI) -> None:
    """Mount the static folders and the /docs page."""
    app.mount("/static", StaticFiles(directory=STATIC_DIR), name="static")
    app.mount("/web/static", StaticFiles(directory=web.STATIC_DIR), name="web-static")

    # /docs is served from files inside the package (Swagger UI's own distribution, Apache-2.0):
    # FastAPI's default page loads it from a CDN and is blank without internet
    @app.get("/docs", include_in_schema=False)
    async def docs() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=app.openapi_url, title="QuickNav API",
            swagger_js_url="/static/swagger-ui/swagger-ui-bundle.js",
            swagger_css_url="/static/swagger-ui/swagger-ui.css",
            swagger_favicon_url="/static/swagger-ui/favicon-32x32.png",
        )  # fmt: skip
