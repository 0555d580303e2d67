"""Dependencies shared by the routes (``Annotated`` shortcuts, FastAPI template style).

``StoreDep`` / ``RedisDep`` / ``SettingsDep`` hand out the app's clients;
``OwnerDep`` authenticates the request (401), applies the rate limit (429) and yields
the owner id (first 16 hex chars of the key's sha256, None when auth is off).

Ownership of content-addressed scenes: equal content from two keys is ONE scene, so
the scene record cannot carry a single owner. Each key that created a scene gets a
marker object ``scene-owners/<scene_id>/<owner>``; a key sees a scene iff its marker
exists, deleting removes the key's marker and removes the scene only when no marker is
left. Jobs and artifacts are visible to a key iff their scene is: a shared job or a
cached artifact never reveals anything about scenes the key did not upload itself.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request, Security
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from redis import Redis

from service.core.config import Settings
from service.core.metrics import ServiceMetrics
from service.core.security import KeyRing, RateLimiter
from workers.store import ObjectStore

__all__ = [
    "MetricsDep",
    "OwnerDep",
    "RedisDep",
    "SettingsDep",
    "StoreDep",
    "add_scene_owner",
    "remove_scene_owner",
    "scene_owners",
    "scene_visible",
    "visible_scene_ids",
]

SCENE_OWNERS_PREFIX = "scene-owners/"
ANON_OWNER = "_"
"""Marker name for scenes created while authentication is off."""

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
    # The raw header, not the parsed credentials: a wrong scheme must be a 401, not "no key".
    owner = keyring.authenticate(request.headers.get("authorization"))
    request.scope.setdefault("state", {})["owner"] = owner
    client = owner if owner is not None else f"addr:{request.client.host if request.client else '?'}"
    limiter.hit(client)
    return owner


SettingsDep = Annotated[Settings, Depends(get_settings)]
StoreDep = Annotated[ObjectStore, Depends(get_store)]
RedisDep = Annotated[Redis, Depends(get_redis)]
MetricsDep = Annotated[ServiceMetrics, Depends(get_metrics)]
OwnerDep = Annotated[str | None, Depends(get_owner)]


# ----------------------------------------------------------------------------- ownership


def _marker(scene_id: str, owner: str | None) -> str:
    return f"{SCENE_OWNERS_PREFIX}{scene_id}/{owner or ANON_OWNER}"


def add_scene_owner(store: ObjectStore, scene_id: str, owner: str | None) -> None:
    store.put_bytes(_marker(scene_id, owner), b"", "text/plain")


def remove_scene_owner(store: ObjectStore, scene_id: str, owner: str | None) -> None:
    store.delete(_marker(scene_id, owner))


def scene_owners(store: ObjectStore, scene_id: str) -> list[str]:
    prefix = f"{SCENE_OWNERS_PREFIX}{scene_id}/"
    return [k[len(prefix):] for k in store.list(prefix)]


def scene_visible(store: ObjectStore, scene_id: str, owner: str | None) -> bool:
    """Can ``owner`` see scene ``scene_id``? With auth off (owner None) every scene is visible."""
    if owner is None:
        return True
    return store.exists(_marker(scene_id, owner))


def visible_scene_ids(store: ObjectStore, owner: str | None) -> set[str] | None:
    """Scene ids ``owner`` may see (one listing); None means all (auth off)."""
    if owner is None:
        return None
    out: set[str] = set()
    for key in store.list(SCENE_OWNERS_PREFIX):
        scene_id, _, who = key[len(SCENE_OWNERS_PREFIX):].partition("/")
        if who == owner:
            out.add(scene_id)
    return out
