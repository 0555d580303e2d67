"""The browser preview page (issue 7): static files at ``/preview/``, ``/`` redirects there.

No build step: ``service/static/{index.html,app.js,app.css}`` are served as they are.
``/preview/sample-cameras.json`` lists the shipped sample scenes' cameras by scene name,
because the API stores scenes without offering their JSON back: the page starts a sample
scene from its own camera and any other scene from a default camera (see the page's help).
"""

from __future__ import annotations

import json
from functools import lru_cache
from pathlib import Path
from typing import Any

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import FileResponse, JSONResponse, RedirectResponse

router = APIRouter(include_in_schema=False)

STATIC_DIR = Path(__file__).resolve().parents[2] / "static"
_FILES = {
    "index.html": "text/html; charset=utf-8",
    "app.js": "text/javascript; charset=utf-8",
    "app.css": "text/css; charset=utf-8",
}
_HEADERS = {"Cache-Control": "no-cache"}

PIVOTS: dict[str, list[float]] = {"cornell_box": [278.0, 273.0, 279.6]}
"""Orbit centres for samples whose camera looks at a point right in front of the eye."""


@lru_cache(maxsize=1)
def sample_cameras() -> dict[str, dict[str, Any]]:
    """Scene name -> {"camera": the sample's camera, "pivot": the point to orbit around}."""
    try:
        from samples import SCENES_DIR
    except ImportError:  # deployed without the samples package
        return {}
    out: dict[str, dict[str, Any]] = {}
    for path in sorted(SCENES_DIR.glob("*.json")):
        doc = json.loads(path.read_text())
        cam = doc.get("camera")
        name = doc.get("name") or path.stem
        if isinstance(cam, dict):
            out[str(name)] = {"camera": cam, "pivot": PIVOTS.get(str(name), cam.get("look_at"))}
    return out


def _to_page(request: Request) -> RedirectResponse:
    query = request.url.query
    return RedirectResponse("/preview/" + (f"?{query}" if query else ""), status_code=307)


@router.get("/")
def root(request: Request) -> RedirectResponse:
    return _to_page(request)


@router.get("/preview")
def preview_no_slash(request: Request) -> RedirectResponse:
    return _to_page(request)


@router.get("/preview/sample-cameras.json")
def cameras() -> JSONResponse:
    return JSONResponse(sample_cameras(), headers=_HEADERS)


@router.get("/preview/")
def index() -> FileResponse:
    return static_file("index.html")


@router.get("/preview/{name}")
def static_file(name: str) -> FileResponse:
    media_type = _FILES.get(name)
    if media_type is None:
        raise HTTPException(404, f"no file {name}")
    return FileResponse(STATIC_DIR / name, media_type=media_type, headers=_HEADERS)
