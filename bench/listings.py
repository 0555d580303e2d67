"""Listing latency with many jobs and a large scene stored (docs/reliability.md, "Listings and store
hygiene").

Builds, in a temporary directory, the state an operator's fault test left the service in: an
embedded Redis holding ``--jobs`` render jobs (queued: enqueued by the producer, no worker runs
them; nine in ten asked for by key A, the rest by key B) and a store holding a ``--scene-mib`` MiB
scene (an inline mesh, stored by both keys through the API) and 20 small scenes of key A. Then
times, through the app (FastAPI's TestClient, in process: no network), ``--n`` requests each of

- ``GET /v1/jobs?limit=100`` as key A and as key B,
- ``GET /v1/scenes?limit=100`` as key A,

and prints p50 / p99 / max in milliseconds. Only these two query parameters are sent, so the same
script times code whose listings read every job and every scene document.

    flock /tmp/bench.lock python -m bench.listings [--jobs 10000] [--scene-mib 30] [--n 200]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from fastapi.testclient import TestClient

from api_schemas.service import RenderRequest
from producer.embedded import start_embedded_redis
from producer.queue import redis_from_url
from producer.renders import enqueue_render
from producer.settings import Settings
from service.core.security import hash_key, owner_of
from service.main import create_app
from tests.service.api.conftest import small_scene

A = {"Authorization": "Bearer alice"}
B = {"Authorization": "Bearer bob"}
CAM = {"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0, 0], "width": 8, "height": 8}


def big_scene(target_mib: float) -> dict:
    """A legal scene of at least ``target_mib`` MiB of JSON: one inline mesh (a triangle strip)."""
    n = int(target_mib * 24_000)
    rng = np.random.default_rng(0)
    idx = np.arange(n - 2)
    doc = small_scene(name="big")
    doc["objects"].append({"type": "mesh", "material": "white", "vertices": np.round(rng.random((n, 3)), 4).tolist(),
                           "faces": np.stack([idx, idx + 1, idx + 2], 1).tolist()})
    return doc


def timed(c: TestClient, url: str, headers: dict[str, str], n: int) -> tuple[float, float, float]:
    ms = []
    for _ in range(n):
        t0 = time.perf_counter()
        r = c.get(url, headers=headers)
        ms.append((time.perf_counter() - t0) * 1e3)
        assert r.status_code == 200, r.text[:300]
    return float(np.percentile(ms, 50)), float(np.percentile(ms, 99)), max(ms)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--jobs", type=int, default=10_000)
    ap.add_argument("--scene-mib", type=float, default=30.0)
    ap.add_argument("--n", type=int, default=200)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        server = start_embedded_redis(d / "redis")
        try:
            redis = redis_from_url(server.url)
            defaults, scene_limit = Settings(), int((args.scene_mib + 1) * 2**20)  # the big scene must fit
            settings = Settings(redis_url=server.url, store_url=f"file://{d / 'store'}", data_dir=d / "data",
                                api_keys=[hash_key("alice"), hash_key("bob")], log_level="WARNING",
                                max_json_bytes=max(defaults.max_json_bytes, scene_limit),
                                max_body_bytes=max(defaults.max_body_bytes, scene_limit))
            with TestClient(create_app(settings)) as c:
                body = json.dumps({"scene": big_scene(args.scene_mib)}).encode()
                t0 = time.perf_counter()
                for who in (A, B):
                    r = c.post("/v1/scenes", content=body, headers={**who, "content-type": "application/json"})
                    assert r.status_code in (200, 201), r.text[:300]
                t_scene = time.perf_counter() - t0
                sids = [c.post("/v1/scenes", json={"scene": small_scene(name=f"s{i}")}, headers=A).json()["id"]
                        for i in range(20)]
                t0 = time.perf_counter()
                alice, bob = owner_of(hash_key("alice")), owner_of(hash_key("bob"))
                for i in range(args.jobs):
                    req = RenderRequest.model_validate({"scene_id": sids[0], "camera": CAM,
                                                        "params": {"spp": 1, "seed": i}})
                    enqueue_render(redis, req, alice if i % 10 else bob)
                t_jobs = time.perf_counter() - t0
                print(f"stored a {len(body) / 2**20:.1f} MiB scene twice in {t_scene:.1f} s; "
                      f"enqueued {args.jobs} renders in {t_jobs:.1f} s")
                print("| request | p50 ms | p99 ms | max ms |\n|---|---|---|---|")
                for what, url, who in (
                    (f"`GET /v1/jobs?limit=100`, key A ({args.jobs * 9 // 10} jobs)", "/v1/jobs?limit=100", A),
                    (f"`GET /v1/jobs?limit=100`, key B ({args.jobs // 10} jobs)", "/v1/jobs?limit=100", B),
                    (f"`GET /v1/scenes?limit=100`, key A (21 scenes, one of {args.scene_mib:g} MiB)",
                     "/v1/scenes?limit=100", A),
                ):
                    p50, p99, worst = timed(c, url, who, args.n)
                    print(f"| {what} | {p50:.1f} | {p99:.1f} | {worst:.1f} |")
            redis.close()
        finally:
            server.stop()


if __name__ == "__main__":
    main()
