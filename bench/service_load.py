"""Service load check (loopback only, bounded): cached image GETs and queue overhead.

Starts the real stack on this machine (embedded Redis, one bake and one render worker,
the API via uvicorn) in a temporary data directory, then measures:

1. cached-image GET throughput and p50 / p99 latency of ``GET /v1/artifacts/{key}/image.png``
   with C concurrent clients, for a bounded number of requests;
2. the queue's overhead for a trivial render job (8 x 8 pixels, 1 spp): enqueue-to-start
   latency (job ``started_at - created_at``) and request-to-finished wall time, over N
   distinct jobs submitted one after another (the worker is warm after the first).

    python -m bench.service_load [--requests 2000] [--concurrency 8] [--jobs 30]

Writes the ``service_load`` block of docs/performance.md and docs/data/service_load.json.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import threading
import time
from pathlib import Path

import httpx

from bench.docs_writer import replace_block
from service.client import Client
from service.up import start_stack

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "performance.md"
DATA = ROOT / "docs" / "data" / "service_load.json"

SCENE = {
    "camera": {"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0.5, 0], "width": 256, "height": 256},
    "materials": [{"name": "red", "kd": [0.7, 0.1, 0.1], "ks": [0.2, 0.2, 0.2], "shininess": 50},
                  {"name": "floor", "kd": [0.5, 0.5, 0.5]}],
    "objects": [{"type": "sphere", "material": "red", "center": [0, 0.5, 0], "radius": 0.5},
                {"type": "plane", "material": "floor", "size": [6, 6]}],
    "lights": [{"type": "point", "position": [2, 3, 2], "intensity": [8, 8, 8]}],
}


def pct(xs: list[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, int(round(q * (len(s) - 1))))]


def get_load(api: str, url: str, total: int, conc: int) -> dict:
    lat: list[float] = []
    errors = [0]
    lock = threading.Lock()
    counter = [0]

    def worker() -> None:
        with httpx.Client(base_url=api, timeout=30) as c:
            while True:
                with lock:
                    if counter[0] >= total:
                        return
                    counter[0] += 1
                t0 = time.perf_counter()
                r = c.get(url)
                dt = time.perf_counter() - t0
                with lock:
                    if r.status_code == 200:
                        lat.append(dt)
                    else:
                        errors[0] += 1

    t0 = time.perf_counter()
    threads = [threading.Thread(target=worker) for _ in range(conc)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.perf_counter() - t0
    return {"requests": total, "concurrency": conc, "ok": len(lat), "errors": errors[0], "wall_s": wall,
            "req_per_s": len(lat) / wall, "p50_ms": 1e3 * pct(lat, 0.5), "p99_ms": 1e3 * pct(lat, 0.99)}


def queue_overhead(c: Client, scene_id: str, n: int) -> dict:
    starts, totals, renders = [], [], []
    cam = dict(SCENE["camera"], width=8, height=8)
    for i in range(n + 1):
        t0 = time.perf_counter()
        r = c.render(scene_id, camera=cam, params={"spp": 1, "seed": 1000 + i})
        assert r.job is not None, "a fresh seed must not be cached"
        j = c.wait_job(r.job.id, poll=0.01)
        wall = time.perf_counter() - t0
        if i == 0:
            continue  # first job warms the worker (kernel cache load)
        if j.state != "finished" or j.started_at is None or j.created_at is None or j.ended_at is None:
            raise RuntimeError(f"job {j.id} {j.state}: {j.error}")
        starts.append((j.started_at - j.created_at).total_seconds())
        renders.append((j.ended_at - j.started_at).total_seconds())
        totals.append(wall)
    return {"jobs": n, "enqueue_to_start_p50_ms": 1e3 * statistics.median(starts),
            "enqueue_to_start_p99_ms": 1e3 * pct(starts, 0.99),
            "job_run_p50_ms": 1e3 * statistics.median(renders),
            "request_to_finished_p50_ms": 1e3 * statistics.median(totals),
            "request_to_finished_p99_ms": 1e3 * pct(totals, 0.99)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--requests", type=int, default=2000)
    ap.add_argument("--concurrency", type=int, default=8)
    ap.add_argument("--jobs", type=int, default=30)
    ap.add_argument("--port", type=int, default=8799)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="ibr-load-") as tmp:
        for k in ("IBR_REDIS_URL", "IBR_STORE_URL"):
            os.environ.pop(k, None)
        stack = start_stack(Path(tmp), port=args.port, log=lambda s: None)
        try:
            with Client(stack.api_url) as c:
                sid = c.create_scene(SCENE).id
                r = c.render(sid, params={"spp": 4}, wait=60)
                man = c.wait_render(r)
                url = f"/v1/artifacts/{man.key}/image.png"
                size = len(c.download(man.key, "png"))
                get_load(stack.api_url, url, 100, args.concurrency)  # warm-up
                gets = get_load(stack.api_url, url, args.requests, args.concurrency)
                q = queue_overhead(c, sid, args.jobs)
        finally:
            stack.stop()
    res = {"png_bytes": size, "cached_get": gets, "queue": q}
    DATA.parent.mkdir(parents=True, exist_ok=True)
    DATA.write_text(json.dumps(res, indent=2) + "\n")
    print(json.dumps(res, indent=2))
    g = gets
    body = "\n".join([
        f"Measured with `python -m bench.service_load --requests {args.requests} --concurrency "
        f"{args.concurrency} --jobs {args.jobs}` ({time.strftime('%Y-%m-%d')}, {os.cpu_count()} cores; the "
        "client, the API (one uvicorn process), Redis and the workers share the machine; raw data in "
        "`docs/data/service_load.json`).",
        "",
        "| measurement | value |",
        "|---|---:|",
        f"| cached PNG GET ({size:,} bytes, checksum verified on every read), {g['concurrency']} clients | "
        f"{g['req_per_s']:.0f} req/s |",
        f"| cached PNG GET latency p50 / p99 | {g['p50_ms']:.1f} / {g['p99_ms']:.1f} ms |",
        f"| errors | {g['errors']} of {g['requests']} |",
        f"| queue: enqueue-to-start p50 / p99 (8x8 render, warm render worker) | "
        f"{q['enqueue_to_start_p50_ms']:.1f} / {q['enqueue_to_start_p99_ms']:.1f} ms |",
        f"| the job itself p50 (load scene from cache, render, encode, store) | {q['job_run_p50_ms']:.1f} ms |",
        f"| request-to-finished p50 / p99 (client polling every 10 ms) | "
        f"{q['request_to_finished_p50_ms']:.1f} / {q['request_to_finished_p99_ms']:.1f} ms |",
    ])
    replace_block(DOC, "service_load", body, title="Performance")
    print(f"wrote {DOC}")


if __name__ == "__main__":
    main()
