"""``GET /v1/methods``: per render method and job kind, whether the render workers' background
warm-up has compiled its kernels (``producer.readiness``)."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.concurrency import run_in_threadpool

from api_schemas.readiness import MethodsReadiness
from producer.readiness import read_readiness
from service.api.deps import RedisDep
from service.api.errors import problem_responses

router = APIRouter(tags=["health"])


@router.get("/v1/methods", response_model=MethodsReadiness, responses=problem_responses(503))
async def methods_readiness(redis: RedisDep) -> MethodsReadiness:
    """Readiness per method (``reference``, ``ldc``, ``ldc+llf``, ``ldc+ibrt``) and job kind
    (``relight``, ``composite``, ``walkthrough``): ``ready`` when a live render worker's warm-up
    compiled its kernels, else ``compiling`` with the estimated ``seconds_left`` (a request works
    meanwhile: its job compiles what it needs), ``failed`` or ``unknown``."""
    return await run_in_threadpool(read_readiness, redis)
