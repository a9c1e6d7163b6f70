"""/docs works without internet: Swagger UI comes from files inside the package, not a CDN."""

from __future__ import annotations

import re

from fastapi.testclient import TestClient

from quicknav_service.api.main import create_app
from quicknav_service.settings import Settings


def test_docs_page_and_its_assets_are_served_by_the_api(tmp_path):
    client = TestClient(create_app(Settings(_env_file=None, data_dir=tmp_path), start_workers=False))
    page = client.get("/docs")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    refs = re.findall(r"""(?:src|href)=["']([^"']+)["']""", page.text)
    refs += re.findall(r"""url: ?['"]([^'"]+)['"]""", page.text)  # the spec the page loads
    assert refs, page.text
    external = [r for r in refs if re.match(r"(https?:)?//", r)]
    assert not external, f"/docs loads from elsewhere: {external}"
    kinds = {}
    for ref in refs:
        r = client.get(ref)
        assert r.status_code == 200, ref
        kinds[ref.rsplit(".", 1)[-1]] = r.headers["content-type"]
    assert "javascript" in kinds["js"] and "css" in kinds["css"] and "json" in kinds["json"]
    assert "SwaggerUIBundle" in client.get("/static/swagger-ui/swagger-ui-bundle.js").text
    assert client.get("/redoc").status_code == 404  # ReDoc also loads from a CDN: not offered
