"""Warm-up readiness in Redis: each render worker's background warm-up publishes, per render method
and job kind, whether its kernels are compiled (``workers.warmup_readiness`` writes, ``GET
/v1/methods`` reads).

One key per render worker and warm-up lane (a process of the warm-up: the kinds it compiles),
``ibr:readiness:<worker name>:<lane>``, holding a JSON document::

    {"worker": name, "updated_at": unix seconds, "finished": bool,
     "methods": {"reference": {"state": "ready", "seconds_left": null}, "ldc": {...}, ...}}

(``methods``: the kinds of that lane.)

A reader counts only workers whose RQ registration (``rq:worker:<name>``) still exists, so a
killed worker's last word is ignored at once; the key itself expires after :data:`TTL_S` (a
safety net, the worker deletes it when it stops).
"""

from __future__ import annotations

import json
from typing import Any

from redis import Redis
from rq.worker import Worker

from api_schemas.readiness import READINESS_METHODS, MethodReadiness, MethodsReadiness
from producer.queue import KEY_PREFIX

PREFIX = f"{KEY_PREFIX}readiness:"
TTL_S = 7 * 86400
MAX_LANES = 4
_RANK = {"ready": 3, "compiling": 2, "failed": 1, "unknown": 0}


def readiness_key(worker: str, lane: int = 0) -> str:
    if not 0 <= lane < MAX_LANES:
        raise ValueError(f"lane {lane} is not in [0, {MAX_LANES})")
    return f"{PREFIX}{worker}:{lane}"


def publish_readiness(redis: Redis, worker: str, doc: dict[str, Any], lane: int = 0) -> None:
    """Store ``doc`` (the module docstring's document) as the readiness of ``worker``'s lane ``lane``."""
    redis.set(readiness_key(worker, lane), json.dumps(doc), ex=TTL_S)


def clear_readiness(redis: Redis, worker: str) -> None:
    """Withdraw every lane's readiness of ``worker``."""
    redis.delete(*(readiness_key(worker, lane) for lane in range(MAX_LANES)))


def _live_documents(redis: Redis) -> list[dict[str, Any]]:
    keys = sorted(redis.scan_iter(match=f"{PREFIX}*", count=200))
    if not keys:
        return []
    docs = []
    for raw in redis.mget(keys):
        if raw is None:
            continue
        try:
            doc = json.loads(raw)
        except ValueError:
            continue
        if isinstance(doc, dict) and isinstance(doc.get("worker"), str):
            docs.append(doc)
    if not docs:
        return []
    with redis.pipeline(transaction=False) as pipe:
        for doc in docs:
            pipe.exists(f"{Worker.redis_worker_namespace_prefix}{doc['worker']}")
        alive = pipe.execute()
    return [d for d, a in zip(docs, alive, strict=True) if a]


def merge_readiness(docs: list[dict[str, Any]]) -> MethodsReadiness:
    """Per kind the best state over ``docs``: ready, else compiling (the shortest estimate), else
    failed, else unknown."""
    out = []
    for method in READINESS_METHODS:
        best: MethodReadiness = MethodReadiness(method=method, state="unknown")
        for doc in docs:
            entry = doc.get("methods", {}).get(method)
            if not isinstance(entry, dict) or entry.get("state") not in _RANK:
                continue
            left = entry.get("seconds_left")
            cand = MethodReadiness(method=method, state=entry["state"],
                                   seconds_left=max(0.0, float(left)) if isinstance(left, int | float) else None)
            if (_RANK[cand.state], -(cand.seconds_left or 0.0)) > (_RANK[best.state], -(best.seconds_left or 0.0)):
                best = cand
        out.append(best)
    return MethodsReadiness(methods=out, workers=len({d["worker"] for d in docs}))


def read_readiness(redis: Redis) -> MethodsReadiness:
    """The merged readiness of the live render workers (module docstring)."""
    return merge_readiness(_live_documents(redis))
