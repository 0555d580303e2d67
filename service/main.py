"""The FastAPI application: ``create_app(settings)``.

Run with ``uvicorn --factory service.main:create_app`` (or ``service.main:app``, built on
first access from the ``IBR_*`` environment). This process never imports numba or the
engine's kernels: jobs are enqueued by import path (``producer``) and run in workers.
"""

from __future__ import annotations

import importlib.resources
import importlib.util
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI, Request
from fastapi.middleware.cors import CORSMiddleware
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.responses import HTMLResponse
from fastapi.staticfiles import StaticFiles
from redis import Redis

from producer.queue import redis_from_url
from producer.settings import Settings, load_settings
from producer.store import ObjectStore, open_configured_store
from producer.upkeep import StoreUpkeep
from service.api.errors import install_exception_handlers
from service.api.limits import BodyLimitMiddleware
from service.api.routes import (
    artifacts,
    bakes,
    batches,
    calibrations,
    datasets,
    health,
    jobs,
    methods,
    preview,
    renders,
    scenes,
    walkthroughs,
)
from service.core.logging import RequestContextMiddleware, configure_logging
from service.core.metrics import MetricsMiddleware, ServiceMetrics
from service.core.security import KeyRing, RateLimiter

__all__ = ["create_app"]

API_VERSION = "1.0.0"
log = logging.getLogger("ibr.api")

TAGS = [
    {"name": "scenes", "description": "Content-addressed scenes; mesh files are uploaded with them (multipart)."},
    {"name": "renders", "description": "Render requests: served from the artifact cache or by a shared job."},
    {"name": "jobs", "description": "Queued and running work, progress, errors, cancellation."},
    {"name": "artifacts", "description": "Results: manifests and images, verified against their checksums."},
    {"name": "batches", "description": "Many scenes and renders in one request."},
    {"name": "health", "description": "Liveness, readiness and Prometheus metrics."},
]


DOCS_ASSETS_URL = "/docs-assets"
"""Where the app serves Swagger UI's and ReDoc's JavaScript and CSS (``/docs`` and ``/redoc`` load
nothing from another host, so they work offline)."""


def _docs_assets_dir() -> str | None:
    """The Swagger UI and ReDoc builds shipped by the ``fastapi-offline`` package (a dependency;
    its licence file names the Apache-2.0 / MIT licences of those builds); None when an install
    predates that dependency."""
    if importlib.util.find_spec("fastapi_offline") is None:
        return None
    return str(importlib.resources.files("fastapi_offline") / "static")


def _install_docs(app: FastAPI) -> None:
    """``/docs`` (Swagger UI) and ``/redoc`` (ReDoc) on assets served by the app itself."""
    assets = _docs_assets_dir()
    openapi_url = app.openapi_url or "/openapi.json"
    oauth2_redirect_url = app.swagger_ui_oauth2_redirect_url or "/docs/oauth2-redirect"
    if assets is None:
        log.warning("fastapi-offline is not installed (reinstall the package): /docs and /redoc load their "
                    "scripts from a CDN and stay blank offline")
    else:
        app.mount(DOCS_ASSETS_URL, StaticFiles(directory=assets), name="docs-assets")

    @app.get("/docs", include_in_schema=False)
    async def swagger_ui(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        url, title, redirect = f"{root}{openapi_url}", f"{app.title} - Swagger UI", f"{root}{oauth2_redirect_url}"
        if assets is None:
            return get_swagger_ui_html(openapi_url=url, title=title, oauth2_redirect_url=redirect)
        return get_swagger_ui_html(
            openapi_url=url, title=title, oauth2_redirect_url=redirect,
            swagger_js_url=f"{root}{DOCS_ASSETS_URL}/swagger-ui-bundle.js",
            swagger_css_url=f"{root}{DOCS_ASSETS_URL}/swagger-ui.css",
            swagger_favicon_url=f"{root}{DOCS_ASSETS_URL}/favicon.png",
        )

    @app.get(oauth2_redirect_url, include_in_schema=False)
    async def swagger_ui_redirect() -> HTMLResponse:
        return get_swagger_ui_oauth2_redirect_html()

    @app.get("/redoc", include_in_schema=False)
    async def redoc(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        url, title = f"{root}{openapi_url}", f"{app.title} - ReDoc"
        if assets is None:
            return get_redoc_html(openapi_url=url, title=title)
        return get_redoc_html(
            openapi_url=url, title=title, redoc_js_url=f"{root}{DOCS_ASSETS_URL}/redoc.standalone.js",
            redoc_favicon_url=f"{root}{DOCS_ASSETS_URL}/favicon.png", with_google_fonts=False,
        )


def _open_store(settings: Settings) -> ObjectStore:
    return open_configured_store(settings)


def create_app(
    settings: Settings | None = None, *, store: ObjectStore | None = None, redis: Redis | None = None
) -> FastAPI:
    """Build the API. ``settings`` defaults to the environment (exits with a message naming
    the bad variable); ``store`` / ``redis`` override the clients the settings name (tests)."""
    settings = settings if settings is not None else load_settings()
    configure_logging(settings.log_level, settings.log_json)
    try:
        store = store if store is not None else _open_store(settings)
        redis = redis if redis is not None else redis_from_url(settings.effective_redis_url)
    except ValueError as exc:
        raise SystemExit(f"invalid configuration: {exc}") from None

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        log.info(
            "api starting",
            extra={"store": type(store).__name__, "redis": settings.effective_redis_url.split("@")[-1],
                   "auth": settings.auth_enabled, "rate_limit_per_minute": settings.rate_limit_per_minute},
        )
        upkeep = StoreUpkeep(store, settings.store_temp_grace_s, settings.store_upkeep_interval_s, redis).start()
        app.state.store_upkeep = upkeep
        yield
        upkeep.stop()
        redis.close()

    app = FastAPI(
        title="ibr-service",
        version=API_VERSION,
        summary="Image-based rendering as a service: scenes in, rendered images out.",
        description="Errors are `application/problem+json` (RFC 9457) with `errors[].field` naming each "
                    "invalid field. See docs/api.md.",
        openapi_tags=TAGS,
        lifespan=lifespan,
        docs_url=None,  # served by _install_docs, on local assets
        redoc_url=None,
    )
    app.state.settings = settings
    app.state.store = store
    app.state.redis = redis
    app.state.keyring = KeyRing(settings.api_keys)
    app.state.limiter = RateLimiter(settings.rate_limit_per_minute, settings.rate_limit_burst,
                                    redis=lambda: app.state.redis)
    metrics = ServiceMetrics(lambda: redis)
    app.state.metrics = metrics

    install_exception_handlers(app)
    _install_docs(app)
    for module in (scenes, renders, jobs, artifacts, batches, health, methods, preview, datasets, bakes,
                   calibrations, walkthroughs):
        app.include_router(module.router)

    # add_middleware wraps: the LAST added is the outermost.
    app.add_middleware(BodyLimitMiddleware, max_body_bytes=settings.max_body_bytes,
                       max_json_bytes=settings.json_limit_bytes)
    if settings.cors_origins:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=settings.cors_origins,
            allow_methods=["GET", "POST", "DELETE"],
            allow_headers=["Authorization", "Content-Type", "X-Request-ID"],
            expose_headers=["Location", "Retry-After", "X-Request-ID"],
        )
    app.add_middleware(MetricsMiddleware, metrics=metrics)
    app.add_middleware(RequestContextMiddleware)
    return app


def __getattr__(name: str) -> Any:
    # ``service.main:app`` for uvicorn without --factory: built on first access, not at import
    # (importing this module must not read the environment or connect anywhere).
    if name == "app":
        app = create_app()
        globals()["app"] = app
        return app
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
