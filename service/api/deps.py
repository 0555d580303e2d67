"""Dependencies shared by the routes (``Annotated`` shortcuts, FastAPI template style).

``StoreDep`` / ``RedisDep`` / ``SettingsDep`` hand out the app's clients;
``OwnerDep`` authenticates the request (401), applies the rate limit (429) and yields
the owner id (first 16 hex chars of the key's sha256, None when auth is off).

Ownership of content-addressed scenes: equal content from two keys is ONE scene, so
the scene record cannot carry a single owner. Each key that created a scene gets a
marker object ``scene-owners/<scene_id>/<owner>``; a key sees a scene iff its marker
exists, deleting removes the key's marker and removes the scene only when no marker is
left. Jobs and artifacts are visible to a key iff their scene is: a shared job or a
cached artifact never reveals anything about scenes the key did not upload itself. The markers
are ``producer.ownership``'s; they are re-exported here for the routes.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request, Security
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from redis import Redis

from producer.ownership import (
    ANON_OWNER,
    SCENE_OWNERS_PREFIX,
    add_scene_owner,
    remove_scene_owner,
    scene_owners,
    scene_visible,
    visible_scene_ids,
)
from producer.settings import Settings
from producer.store import ObjectStore
from service.core.metrics import ServiceMetrics
from service.core.security import AuthError, KeyRing, RateLimiter

__all__ = [
    "MetricsDep",
    "OwnerDep",
    "RedisDep",
    "SettingsDep",
    "StoreDep",
    "ANON_OWNER",
    "SCENE_OWNERS_PREFIX",
    "add_scene_owner",
    "remove_scene_owner",
    "scene_owners",
    "scene_visible",
    "visible_scene_ids",
]

_bearer = HTTPBearer(
    auto_error=False,
    description="API key as a bearer token (only when the server is configured with IBR_API_KEYS)",
)


def get_settings(request: Request) -> Settings:
    settings: Settings = request.app.state.settings
    return settings


def get_store(request: Request) -> ObjectStore:
    store: ObjectStore = request.app.state.store
    return store


def get_redis(request: Request) -> Redis:
    conn: Redis = request.app.state.redis
    return conn


def get_metrics(request: Request) -> ServiceMetrics:
    metrics: ServiceMetrics = request.app.state.metrics
    return metrics


def get_owner(
    request: Request,
    _credentials: Annotated[HTTPAuthorizationCredentials | None, Security(_bearer)] = None,
) -> str | None:
    """Authenticate (401) and rate-limit (429) the request; the owner id or None (auth off)."""
    keyring: KeyRing = request.app.state.keyring
    limiter: RateLimiter = request.app.state.limiter
    address = f"addr:{request.client.host if request.client else '?'}"
    # The raw header, not the parsed credentials: a wrong scheme must be a 401, not "no key".
    try:
        owner = keyring.authenticate(request.headers.get("authorization"))
    except AuthError:
        limiter.hit(address)  # guessing keys costs tokens too: 429 before 401
        raise
    request.scope.setdefault("state", {})["owner"] = owner
    limiter.hit(owner if owner is not None else address)
    return owner


SettingsDep = Annotated[Settings, Depends(get_settings)]
StoreDep = Annotated[ObjectStore, Depends(get_store)]
RedisDep = Annotated[Redis, Depends(get_redis)]
MetricsDep = Annotated[ServiceMetrics, Depends(get_metrics)]
OwnerDep = Annotated[str | None, Depends(get_owner)]
