"""Liveness, readiness and Prometheus metrics."""

from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, Response
from fastapi.concurrency import run_in_threadpool
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from api_schemas.common import FrozenModel
from service.api.deps import MetricsDep, RedisDep, StoreDep
from service.api.errors import RETRY_AFTER_S

router = APIRouter(tags=["health"])


class Liveness(FrozenModel):
    status: Literal["ok"] = "ok"


class Readiness(FrozenModel):
    status: Literal["ready", "unavailable"]
    checks: dict[str, str]
    """``ok`` or the reason a dependency failed, per dependency (``redis``, ``store``)."""


@router.get("/healthz", response_model=Liveness)
def healthz() -> Liveness:
    """Liveness: 200 whenever the process serves requests."""
    return Liveness()


@router.get(
    "/readyz",
    response_model=Readiness,
    responses={503: {"model": Readiness, "description": "Redis or the object store is unreachable",
                     "headers": {"Retry-After": {"schema": {"type": "integer"}}}}},
)
async def readyz(response: Response, store: StoreDep, redis: RedisDep) -> Readiness:
    """Readiness: 200 only when Redis answers PING and the object store can be read and written."""
    checks: dict[str, str] = {}
    try:
        await run_in_threadpool(redis.ping)
        checks["redis"] = "ok"
    except Exception as exc:  # any failure means not ready; the reason is reported
        checks["redis"] = f"{type(exc).__name__}: {exc}"[:300]
    try:
        await run_in_threadpool(store.check)
        checks["store"] = "ok"
    except Exception as exc:
        checks["store"] = f"{type(exc).__name__}: {exc}"[:300]
    ready = all(v == "ok" for v in checks.values())
    if not ready:
        response.status_code = 503
        response.headers["Retry-After"] = str(RETRY_AFTER_S)
    return Readiness(status="ready" if ready else "unavailable", checks=checks)


@router.get(
    "/metrics",
    response_class=Response,
    responses={200: {"content": {CONTENT_TYPE_LATEST.split(";")[0]: {"schema": {"type": "string"}}},
                     "description": "Prometheus text exposition format"}},
)
def metrics(metrics: MetricsDep) -> Response:
    """Prometheus metrics: queue depths, recent job durations, cache hits and misses, HTTP requests."""
    return Response(generate_latest(metrics.registry), media_type=CONTENT_TYPE_LATEST)
