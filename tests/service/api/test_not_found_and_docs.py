"""404s name the field and the value that named a missing thing; ``GET /`` leads to the preview;
``/docs`` and ``/redoc`` load their assets from the app itself (they work offline)."""

from __future__ import annotations

import hashlib
import re
from typing import Any

from fastapi.testclient import TestClient

from tests.service.api.conftest import small_scene

MISSING = "0123456789abcdef" * 4


def _missing(r: Any, field: str, value: str) -> None:
    assert r.status_code == 404, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    body = r.json()
    name = field.removeprefix("path.")
    assert body["detail"] == f"{name} {value!r} not found", body
    assert [(e["field"], e["type"]) for e in body["errors"]] == [(field, "not_found")], body


def test_missing_things_are_named_by_field_and_value(client: TestClient) -> None:
    _missing(client.post("/v1/renders", json={"scene_id": MISSING}), "scene_id", MISSING)
    _missing(client.get("/v1/jobs/render-nope"), "path.job_id", "render-nope")
    _missing(client.post("/v1/jobs/render-nope/cancel"), "path.job_id", "render-nope")
    _missing(client.get(f"/v1/datasets/{MISSING}"), "path.dataset_id", MISSING)
    _missing(client.get(f"/v1/scenes/{MISSING}"), "path.scene_id", MISSING)
    _missing(client.post(f"/v1/scenes/{MISSING}/bakes", json={}), "path.scene_id", MISSING)
    _missing(client.get(f"/v1/artifacts/{MISSING}"), "path.key", MISSING)
    # a stored scene: the render is accepted (queued), so the 404 above was about the id, not the route
    scene_id = client.post("/v1/scenes", json={"scene": small_scene()}).json()["id"]
    assert client.post("/v1/renders", json={"scene_id": scene_id}).status_code in (200, 202)
    _missing(client.get(f"/v1/scenes/{scene_id}/bakes/{MISSING}"), "path.bake_key", MISSING)


def test_another_keys_scene_reads_like_an_absent_one(make_app: Any) -> None:
    hashes = [hashlib.sha256(k.encode()).hexdigest() for k in ("k1", "k2")]
    with TestClient(make_app(api_keys=hashes)) as c:
        scene_id = c.post("/v1/scenes", json={"scene": small_scene()},
                          headers={"Authorization": "Bearer k1"}).json()["id"]
        r = c.post("/v1/renders", json={"scene_id": scene_id}, headers={"Authorization": "Bearer k2"})
        _missing(r, "scene_id", scene_id)


def test_root_leads_to_the_preview(client: TestClient) -> None:
    r = client.get("/", follow_redirects=False)
    assert r.status_code in (302, 307) and r.headers["location"] == "/preview/"
    assert client.get("/").status_code == 200


def test_docs_load_nothing_from_another_host(client: TestClient) -> None:
    for page, must in (("/docs", ("swagger-ui-bundle.js", "swagger-ui.css")), ("/redoc", ("redoc.standalone.js",))):
        r = client.get(page)
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
        html = r.text
        refs = re.findall(r"""(?:src|href)\s*=\s*["']([^"']+)["']""", html)
        refs += re.findall(r"""(?:url|openapi_url|specUrl)\s*:\s*["']([^"']+)["']""", html)
        assert not re.search(r"(?:https?:)?//[A-Za-z0-9]", html), (page, re.findall(r"\S*//\S*", html))
        for name in must:
            assert any(ref.endswith(name) for ref in refs), (page, name, refs)
        for ref in refs:
            a = client.get(ref)
            assert a.status_code == 200, (page, ref)
            assert len(a.content) > (100_000 if ref.endswith((".js", ".css")) else 100), (ref, len(a.content))
    assert client.get("/openapi.json").json()["info"]["title"] == "ibr-service"
