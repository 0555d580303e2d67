"""Where a deployment saturates: jobs per second the queue sustains, and what one bake part and one
render cost Redis and the object store.

Starts the embedded Redis (producer/embedded.py) and an S3 endpoint (moto's server) behind a small
counting HTTP proxy in this process, then:

1. **Queue throughput.** For each queue kind (``render``: in-process jobs; ``bake``: a forked work
   horse per job) and each worker count: enqueues ``--jobs`` no-op jobs the way the API enqueues
   (``producer.enqueue.enqueue_unique``: a Redis lock per job id, de-duplication), starts that many
   real ``python -m workers.runner`` processes and measures the drain rate from the first job's
   start to the last job's end (RQ's own timestamps: worker start-up is not counted). Redis
   commands per job from INFO commandstats deltas, split into enqueue and run.
2. **Costs per bake part and per render.** One real render worker and one real bake worker on the
   S3 store: a small bake with direct light only, a bake with indirect light in chunks, an LDC
   render of the first bake (cold: the worker loads the bake) and a second view (warm: the bake is
   in the worker's LRU), and a reference render. Each: Redis commands (commandstats delta; the
   benchmark waits by reading the store, never Redis) and S3 requests / bytes as the proxy counted
   them (request bodies written, response bodies read), split between what the enqueueing side
   (the API's calls) and the workers cost.

    flock /tmp/bench.lock python -m bench.queue_throughput [--jobs 300] [--workers 1 2] [--no-docs]

Writes the ``queue_throughput`` block of docs/deployment.md and docs/data/queue_throughput.json.
"""

from __future__ import annotations

import argparse
import http.client
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from bench.docs_writer import replace_block

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "deployment.md"
DATA = ROOT / "docs" / "data" / "queue_throughput.json"
BUCKET = "bench-queue"
S3_KEYS = {"IBR_S3_REGION": "us-east-1", "IBR_S3_ACCESS_KEY": "bench", "IBR_S3_SECRET_KEY": "bench-secret"}
NOOP = "bench.queue_throughput.noop_job"


def noop_job(payload: dict[str, Any]) -> dict[str, Any]:
    """The job of the throughput runs: returns at once, so what is measured is the queue's own cost."""
    return {"i": payload.get("i")}


# ------------------------------------------------------------------------------- the S3 byte meter


class S3Meter:
    """Per HTTP method: requests, request body bytes, response body bytes (thread-safe)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.requests: Counter[str] = Counter()
        self.sent: Counter[str] = Counter()
        self.received: Counter[str] = Counter()

    def add(self, method: str, sent: int, received: int) -> None:
        with self.lock:
            self.requests[method] += 1
            self.sent[method] += sent
            self.received[method] += received

    def snapshot(self) -> dict[str, dict[str, int]]:
        with self.lock:
            return {m: {"requests": self.requests[m], "bytes_written": self.sent[m], "bytes_read": self.received[m]}
                    for m in sorted(self.requests)}


def meter_delta(after: dict[str, dict[str, int]], before: dict[str, dict[str, int]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for m, v in after.items():
        b = before.get(m, {})
        d = {k: v[k] - b.get(k, 0) for k in v}
        if d["requests"]:
            out[m] = d
    out["total"] = {k: sum(d[k] for m, d in out.items() if m != "total")
                    for k in ("requests", "bytes_written", "bytes_read")}
    return out


def start_counting_proxy(upstream: str, meter: S3Meter) -> tuple[ThreadingHTTPServer, str]:
    """An HTTP/1.1 proxy on 127.0.0.1 that forwards every request to ``upstream`` and counts the
    bodies both ways: the object-store traffic of whoever uses it as their S3 endpoint."""
    up = urlsplit(upstream)

    class Handler(BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"

        def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - the base class's name
            pass

        def _body(self) -> bytes:
            if self.headers.get("Transfer-Encoding", "").lower() == "chunked":
                parts = []
                while True:
                    size = int(self.rfile.readline().split(b";")[0].strip() or b"0", 16)
                    if size == 0:
                        while self.rfile.readline() not in (b"\r\n", b"\n", b""):
                            pass
                        return b"".join(parts)
                    parts.append(self.rfile.read(size))
                    self.rfile.readline()
            n = int(self.headers.get("Content-Length") or 0)
            return self.rfile.read(n) if n else b""

        def _forward(self) -> None:
            body = self._body()
            headers = {k: v for k, v in self.headers.items()
                       if k.lower() not in ("transfer-encoding", "connection", "content-length")}
            headers["Content-Length"] = str(len(body))
            conn = http.client.HTTPConnection(up.hostname, up.port, timeout=60)
            try:
                conn.request(self.command, self.path, body=body, headers=headers)
                resp = conn.getresponse()
                data = resp.read()
            finally:
                conn.close()
            meter.add(self.command, len(body), len(data))
            self.send_response_only(resp.status, resp.reason)
            for k, v in resp.getheaders():
                if k.lower() not in ("transfer-encoding", "connection", "content-length", "date", "server"):
                    self.send_header(k, v)
            if self.command != "HEAD":
                self.send_header("Content-Length", str(len(data)))
            else:
                self.send_header("Content-Length", resp.getheader("Content-Length") or "0")
            self.end_headers()
            if self.command != "HEAD":
                self.wfile.write(data)

        do_GET = do_PUT = do_POST = do_DELETE = do_HEAD = _forward

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    server.daemon_threads = True
    threading.Thread(target=server.serve_forever, name="s3-meter", daemon=True).start()
    return server, f"http://127.0.0.1:{server.server_address[1]}"


# ------------------------------------------------------------------------------------ processes


class Workers:
    """Real ``python -m workers.runner`` processes; stopped (SIGTERM, then SIGKILL) on exit."""

    def __init__(self, env: dict[str, str], logdir: Path):
        self.env, self.logdir = env, logdir
        self.procs: list[subprocess.Popen[bytes]] = []

    def start(self, queue: str, name: str) -> subprocess.Popen[bytes]:
        env = {**self.env, "IBR_DATA_DIR": str(self.logdir / name)}
        log = open(self.logdir / f"{name}.log", "wb")  # noqa: SIM115 - closed with the process
        p = subprocess.Popen([sys.executable, "-m", "workers.runner", "--queue", queue, "--name", name,
                              "--no-warmup", "--maintenance-interval", "5"],
                             cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        self.procs.append(p)
        return p

    def stop(self) -> None:
        for p in self.procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGTERM)
        for p in self.procs:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
        self.procs = []


def wait_registered(redis: Any, queue: str, n: int, timeout: float = 120.0) -> None:
    from rq import Worker

    from producer.queue import get_queue

    deadline = time.monotonic() + timeout
    while Worker.count(connection=redis, queue=get_queue(redis, queue)) < n:  # type: ignore[arg-type]
        if time.monotonic() > deadline:
            raise RuntimeError(f"{n} {queue} workers did not register within {timeout} s")
        time.sleep(0.1)


def commandstats(redis: Any) -> dict[str, int]:
    """Calls per command since the server started, plus ``_cpu_us``: the server's own CPU time."""
    calls = {k.removeprefix("cmdstat_"): int(v["calls"]) for k, v in redis.info("commandstats").items()}
    cpu = redis.info("cpu")
    calls["_cpu_us"] = int(1e6 * (float(cpu["used_cpu_sys"]) + float(cpu["used_cpu_user"])))
    return calls


def split_cpu(stats: dict[str, int]) -> tuple[dict[str, int], float]:
    """(command counts, Redis CPU seconds) of a commandstats delta."""
    rest = dict(stats)
    return rest, rest.pop("_cpu_us", 0) / 1e6


def stats_delta(after: dict[str, int], before: dict[str, int], minus: dict[str, int] | None = None) -> dict[str, int]:
    d = {k: v - before.get(k, 0) - (minus or {}).get(k, 0) for k, v in after.items()}
    return dict(sorted(((k, v) for k, v in d.items() if v > 0), key=lambda kv: -kv[1]))


# INFO itself and the benchmark's own reads between the two snapshots
_OWN = {"info": 1}


# ------------------------------------------------------------------------------------ measurements


def queue_run(redis: Any, workers: Workers, queue: str, n_workers: int, n_jobs: int) -> dict[str, Any]:
    from rq.job import Job
    from rq.serializers import JSONSerializer

    from producer.enqueue import enqueue_unique

    redis.flushdb()
    s0 = commandstats(redis)
    t0 = time.perf_counter()
    ids = []
    for i in range(n_jobs):
        jid = f"{queue}-bench-{n_workers}-{i}"
        enqueue_unique(redis, queue, NOOP, {"i": i}, jid, timeout=60, meta={"kind": "bench"}, retry=None,  # type: ignore[arg-type]
                       description="no-op")
        ids.append(jid)
    enqueue_s = time.perf_counter() - t0
    s1 = commandstats(redis)
    for w in range(n_workers):
        workers.start(queue, f"bench-{queue}-{n_workers}-{w}-{os.getpid()}")
    deadline = time.monotonic() + 600
    last = ids[-1]
    while True:
        ends = redis.hmget(f"rq:job:{last}", ["status"])
        done = redis.llen(f"rq:queue:{queue}") == 0 and ends[0] in (b"finished", b"failed")
        if done:
            break
        if time.monotonic() > deadline:
            raise RuntimeError(f"{queue} queue not drained within 600 s")
        time.sleep(0.2)
    time.sleep(0.5)  # the last jobs' end bookkeeping
    jobs = Job.fetch_many(ids, connection=redis, serializer=JSONSerializer)
    states = Counter(j.get_status(refresh=False) for j in jobs if j is not None)
    started = min(j.started_at for j in jobs if j is not None and j.started_at)
    ended = max(j.ended_at for j in jobs if j is not None and j.ended_at)
    drain_s = (ended - started).total_seconds()
    workers.stop()
    s2 = commandstats(redis)
    run, run_cpu = split_cpu(stats_delta(s2, s1, _OWN))
    # what the polling loop above sent is not the jobs' cost: llen / hmget are only sent by it
    for own in ("llen", "hmget"):
        run.pop(own, None)
    enq, enq_cpu = split_cpu(stats_delta(s1, s0, _OWN))
    return {"queue": queue, "workers": n_workers, "jobs": n_jobs, "states": {str(k): v for k, v in states.items()},
            "enqueue_s": enqueue_s, "enqueue_jobs_per_s": n_jobs / enqueue_s,
            "drain_s": drain_s, "jobs_per_s": n_jobs / drain_s,
            "redis_per_job_enqueue": sum(enq.values()) / n_jobs,
            "redis_cpu_us_per_job_enqueue": 1e6 * enq_cpu / n_jobs,
            "redis_cpu_us_per_job_run_incl_polls": 1e6 * run_cpu / n_jobs,
            "redis_per_job_run_incl_worker_idle_and_startup": sum(run.values()) / n_jobs,
            "redis_enqueue_by_command": {k: round(v / n_jobs, 2) for k, v in list(enq.items())[:10]},
            "redis_run_by_command": {k: round(v / n_jobs, 2) for k, v in list(run.items())[:12]}}


def wait_manifest(store: Any, key: str, what: str, timeout: float = 600.0) -> Any:
    from producer.artifacts import read_manifest

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        m = read_manifest(store, key)
        if m is not None:
            return m
        time.sleep(0.2)
    raise RuntimeError(f"{what} not stored within {timeout} s")


def measured(redis: Any, meter: S3Meter, action: Any) -> dict[str, Any]:
    """Run ``action(mark)``: Redis commands and S3 traffic before ``mark()`` (the enqueueing side)
    and after it (the workers), in total."""
    marks: list[tuple[dict[str, int], dict[str, dict[str, int]]]] = []

    def mark() -> None:
        marks.append((commandstats(redis), meter.snapshot()))

    mark()
    t0 = time.perf_counter()
    result = action(mark)
    wall = time.perf_counter() - t0
    time.sleep(1.5)  # workers record the job's end after the manifest lands
    mark()
    (r0, m0), (r1, m1), (r2, m2) = marks
    (api_redis, api_cpu), (work_redis, work_cpu) = (split_cpu(stats_delta(r1, r0, _OWN)),
                                                    split_cpu(stats_delta(r2, r1, _OWN)))
    return {"wall_s": wall, "result": result,
            "enqueue": {"redis": sum(api_redis.values()), "redis_cpu_ms": 1e3 * api_cpu, "s3": meter_delta(m1, m0)},
            "workers": {"redis": sum(work_redis.values()), "redis_cpu_ms": 1e3 * work_cpu,
                        "redis_by_command": dict(list(work_redis.items())[:10]), "s3": meter_delta(m2, m1)}}


def part_bytes(direct: Any, prefix: str) -> int:
    total = 0
    for page in direct.get_paginator("list_objects_v2").paginate(Bucket=BUCKET, Prefix=prefix):
        total += sum(int(o["Size"]) for o in page.get("Contents", []))
    return total


def cost_runs(redis: Any, store: Any, direct: Any, meter: S3Meter, workers: Workers) -> dict[str, Any]:
    from api_schemas.scene import Scene
    from api_schemas.service import BakeParams, RenderRequest
    from producer import bakes
    from producer.artifacts import artifact_prefix, put_scene
    from producer.renders import enqueue_render

    redis.flushdb()
    workers.start("bake", f"bench-cost-bake-{os.getpid()}")
    workers.start("render", f"bench-cost-render-{os.getpid()}")
    wait_registered(redis, "bake", 1)
    wait_registered(redis, "render", 1)
    time.sleep(2.0)
    scene = Scene.model_validate({
        "name": "bench-queue",
        "camera": {"type": "perspective", "eye": [0, 1.5, 4], "look_at": [0, 0.5, 0], "width": 160, "height": 120},
        "materials": [{"name": "m", "kd": [0.6, 0.5, 0.4]}, {"name": "floor", "kd": [0.5, 0.5, 0.5]}],
        "objects": [{"type": "sphere", "center": [0, 0.6, 0], "radius": 0.6, "material": "m"},
                    {"type": "plane", "material": "floor", "size": [4.0, 4.0]}],
        "lights": [{"type": "point", "position": [1, 3, 2], "intensity": [3.0] * 3}],
    })
    sid = put_scene(store, scene, {}, None).id
    out: dict[str, Any] = {}
    direct_params = BakeParams.model_validate({"ldc_resolution": 64, "max_layers": 8, "indirect": {"mode": "off"}})
    gi_params = BakeParams.model_validate({"ldc_resolution": 64, "max_layers": 8, "seed": 1, "indirect": {
        "noise": 0.05, "min_paths": 4, "max_paths": 8, "round_paths": 2, "bounces": 2, "chunks": 2}})

    for name, params in (("bake_direct", direct_params), ("bake_indirect", gi_params)):
        def bake(mark: Any, params: BakeParams = params, name: str = name) -> dict[str, Any]:
            key, job = bakes.enqueue_bake(redis, store, sid, params, owner=None)
            assert job is not None, "bake cached: the database was not empty"
            mark()
            manifest = wait_manifest(store, key, name)
            return {"key": key, "parts": [p["name"] for p in manifest.result["parts"]],
                    "part_bytes": {p["name"]: part_bytes(direct, artifact_prefix(p["key"]))
                                   for p in manifest.result["parts"]},
                    "bake_manifest_bytes": part_bytes(direct, artifact_prefix(key))}
        out[name] = measured(redis, meter, bake)
        out[name]["jobs"] = len(out[name]["result"]["parts"]) + 2

    views = [("render_ldc_cold", "ldc", [0, 1.5, 4]), ("render_ldc_warm", "ldc", [1, 1.5, 4]),
             ("render_reference", "reference", [0, 1.5, 4])]
    for name, method, eye in views:
        def render(mark: Any, method: str = method, eye: list[float] = eye, name: str = name) -> dict[str, Any]:
            req = RenderRequest.model_validate({
                "scene_id": sid, "method": method, "bake": direct_params.model_dump(mode="json"),
                "params": {"spp": 4}, "outputs": ["preview", "radiance"],
                "camera": {"type": "perspective", "eye": eye, "look_at": [0, 0.5, 0], "width": 160, "height": 120}})
            key, job = enqueue_render(redis, req, None, store=store)
            assert job is not None
            mark()
            m = wait_manifest(store, key, name)
            return {"key": key, "artifact_bytes": part_bytes(direct, artifact_prefix(key)),
                    "blobs": [b.name for b in m.blobs]}
        out[name] = measured(redis, meter, render)
    workers.stop()
    return out


# ------------------------------------------------------------------------------------ report


def _mib(n: float) -> str:
    return f"{n / 2**20:.2f} MiB" if n >= 2**20 else f"{n / 1024:.1f} KiB"


def report(data: dict[str, Any]) -> str:
    cmd = "flock /tmp/bench.lock python -m bench.queue_throughput " + " ".join(data["argv"])
    lines = [f"`{cmd}` -- {data['machine']}. Embedded Redis on a unix socket, moto's S3 server behind a "
             "counting proxy, workers as real `python -m workers.runner` processes.", "",
             "**Queue throughput** (no-op jobs; drain = first job started to last job ended, worker start-up "
             "excluded; enqueue by one client through the API's de-duplicating `enqueue_unique`):", "",
             "| queue (job runs in) | workers | jobs | enqueued / s | drained / s "
             "| Redis commands per job: enqueue / run | Redis CPU per job: enqueue / run |",
             "|---|---|---|---|---|---|---|"]
    for r in data["queue"]:
        where = "the worker" if r["queue"] == "render" else "a forked horse"
        lines.append(f"| {r['queue']} ({where}) | {r['workers']} | {r['jobs']} | {r['enqueue_jobs_per_s']:.0f} | "
                     f"{r['jobs_per_s']:.0f} | {r['redis_per_job_enqueue']:.1f} / "
                     f"{r['redis_per_job_run_incl_worker_idle_and_startup']:.1f} | "
                     f"{r['redis_cpu_us_per_job_enqueue']:.0f} / {r['redis_cpu_us_per_job_run_incl_polls']:.0f} µs |")
    lines += ["", "**Per bake and per render** (1 bake + 1 render worker; S3 bytes are HTTP bodies through the "
              "proxy; \"API side\" = the enqueueing calls the API makes, \"workers\" = everything after):", "",
              "| work | jobs | wall | Redis cmds: API side / workers | Redis CPU (all) | S3 requests (workers) | "
              "S3 written (workers) | S3 read (workers) |", "|---|---|---|---|---|---|---|---|"]
    for name in ("bake_direct", "bake_indirect", "render_ldc_cold", "render_ldc_warm", "render_reference"):
        c = data["costs"][name]
        s3 = c["workers"]["s3"]["total"]
        lines.append(f"| {name.replace('_', ' ')} | {c.get('jobs', 1)} | {c['wall_s']:.1f} s | "
                     f"{c['enqueue']['redis']} / {c['workers']['redis']} | "
                     f"{c['enqueue']['redis_cpu_ms'] + c['workers']['redis_cpu_ms']:.0f} ms | {s3['requests']} | "
                     f"{_mib(s3['bytes_written'])} | {_mib(s3['bytes_read'])} |")
    for name in ("bake_direct", "bake_indirect"):
        pb = data["costs"][name]["result"]["part_bytes"]
        lines.append("")
        lines.append(f"Stored bytes per part ({name.replace('_', ' ')}): " +
                     ", ".join(f"{k} {_mib(v)}" for k, v in pb.items()) +
                     f"; bake manifest {_mib(data['costs'][name]['result']['bake_manifest_bytes'])}.")
    lines += ["", f"Raw data: `docs/data/{DATA.name}`."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--jobs", type=int, default=300, help="no-op jobs per throughput run")
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2], help="worker counts to measure")
    ap.add_argument("--no-docs", action="store_true", help="print only; do not rewrite docs/")
    args = ap.parse_args(argv)

    import logging

    import boto3  # type: ignore[import-untyped]
    from moto.server import ThreadedMotoServer

    from producer.embedded import start_embedded_redis
    from producer.queue import redis_from_url
    from producer.store import open_store

    logging.getLogger("werkzeug").setLevel(logging.ERROR)  # moto's server logs every request
    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="ibr-qt-", dir="/tmp") as tmp:
        tmpd = Path(tmp)
        redis_server = start_embedded_redis(tmpd / "redis")
        moto = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
        moto.start()
        host, port = moto.get_host_and_port()
        meter = S3Meter()
        proxy, proxy_url = start_counting_proxy(f"http://{host}:{port}", meter)
        workers = Workers({}, tmpd)
        try:
            direct = boto3.session.Session(aws_access_key_id="bench", aws_secret_access_key="bench-secret",
                                           region_name="us-east-1").client("s3", endpoint_url=f"http://{host}:{port}")
            direct.create_bucket(Bucket=BUCKET)
            env = {**os.environ, "IBR_REDIS_URL": redis_server.url, "IBR_STORE_URL": f"s3://{BUCKET}",
                   "IBR_S3_ENDPOINT_URL": proxy_url, **S3_KEYS, "IBR_WORKER_WARMUP": "false",
                   "PYTHONPATH": str(ROOT), "NUMBA_NUM_THREADS": "1"}
            workers.env = env
            redis = redis_from_url(redis_server.url)
            store = open_store(f"s3://{BUCKET}", endpoint_url=f"http://{host}:{port}", region="us-east-1",
                               access_key="bench", secret_key="bench-secret")
            queue_runs = []
            for q in ("render", "bake"):
                for n in args.workers:
                    r = queue_run(redis, workers, q, n, args.jobs if q == "render" else max(50, args.jobs // 3))
                    print(f"{q} x{n}: {r['jobs_per_s']:.0f} jobs/s drained, {r['enqueue_jobs_per_s']:.0f} enqueued/s, "
                          f"Redis/job {r['redis_per_job_enqueue']:.1f} + "
                          f"{r['redis_per_job_run_incl_worker_idle_and_startup']:.1f}", flush=True)
                    queue_runs.append(r)
            costs = cost_runs(redis, store, direct, meter, workers)
            for name, c in costs.items():
                print(f"{name}: {c['wall_s']:.1f} s, Redis {c['enqueue']['redis']} + {c['workers']['redis']} "
                      f"({c['workers']['redis_cpu_ms']:.0f} ms CPU), "
                      f"S3 {c['workers']['s3']['total']}", flush=True)
        finally:
            workers.stop()
            proxy.shutdown()
            moto.stop()
            redis_server.stop()
    load1 = os.getloadavg()
    data = {"argv": argv if argv is not None else sys.argv[1:], "queue": queue_runs, "costs": costs,
            "machine": f"{os.cpu_count()} cores shared with other work, 1-minute load {load0[0]:.1f} before, "
                       f"{load1[0]:.1f} after"}
    text = report(data)
    print(text)
    if not args.no_docs:
        DATA.parent.mkdir(parents=True, exist_ok=True)
        DATA.write_text(json.dumps(data, indent=1, default=str) + "\n")
        replace_block(DOC, "queue_throughput", text, title="Deployment")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
