"""Fault benchmark: workers SIGKILLed mid-render and mid-bake, Redis killed with jobs running.

Starts the real ``ibr up`` stack (service/up.py: embedded Redis with its append-only file, one
bake worker, one render worker, the API) in a temporary directory, with its supervisor
(``Stack.supervise``) running in a thread as ``ibr up`` runs it, then:

1. ``--kills`` cycles: a reference render and a scene bake are requested through the API
   (distinct seeds, so nothing is cached); once both run -- the render job started, a bake job
   (plan, part or merge) started in its forked horse -- both worker processes are SIGKILLed
   together (the worker alone, not its process group: what an OOM kill does). Measured: whether
   the killed worker's children (RQ scheduler, bake horse) died with it, when the supervisor
   had a new worker running, and whether each job ended ``finished`` (and when), ``failed``,
   stuck (not ended within ``--timeout``) or lost (gone from Redis with no artifact);
2. ``--redis-restarts`` cycles: the same two requests, then the embedded Redis server is
   SIGKILLed mid-job (the supervisor starts it again on the same socket and append-only file).
   Measured: the same outcomes, and whether both worker processes lived through it.

Every cycle's recovery time is from the fault to the job's end (so it includes rerunning it).

    flock /tmp/bench.lock python -m bench.chaos [--kills 20] [--redis-restarts 5] [--timeout 180]

Writes the ``chaos`` block of docs/reliability.md and docs/data/chaos.json.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import statistics
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import psutil
from redis import Redis

from bench.docs_writer import replace_block
from producer.queue import QueueName, get_queue, redis_from_url
from service.client import ApiError, Client
from service.up import Stack, free_port, start_stack

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "reliability.md"
DATA = ROOT / "docs" / "data" / "chaos.json"

RENDER_SCENE = {
    "name": "chaos-render",
    "camera": {"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0.5, 0], "width": 384, "height": 288},
    "materials": [{"name": "red", "kd": [0.7, 0.1, 0.1], "ks": [0.2, 0.2, 0.2], "shininess": 50},
                  {"name": "floor", "kd": [0.5, 0.5, 0.5]}],
    "objects": [{"type": "sphere", "material": "red", "center": [0, 0.5, 0], "radius": 0.5},
                {"type": "plane", "material": "floor", "size": [6, 6]}],
    "lights": [{"type": "rect", "corner": [-0.5, 2.5, -0.5], "edge_u": [1, 0, 0], "edge_v": [0, 0, 1],
                "radiance": [6, 6, 6]}],
}
BAKE_SCENE = {
    "name": "chaos-bake",
    "camera": {"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0.5, 0], "width": 64, "height": 48},
    "materials": [{"name": "a", "kd": [0.6, 0.5, 0.4]}, {"name": "floor", "kd": [0.5, 0.5, 0.5]}],
    "objects": [{"type": "sphere", "material": "a", "center": [0, 0.5, 0], "radius": 0.5},
                {"type": "box", "material": "a", "center": [1.2, 0.3, 0], "size": [0.6, 0.6, 0.6]},
                {"type": "plane", "material": "floor", "size": [6, 6]}],
    "lights": [{"type": "point", "position": [2, 3, 2], "intensity": [8, 8, 8]}],
}


def render_params(args: argparse.Namespace, seed: int) -> dict[str, Any]:
    return {"spp": args.spp, "area_light_samples": args.light_samples, "seed": seed}


def bake_params(args: argparse.Namespace, seed: int) -> dict[str, Any]:
    return {"ldc_resolution": args.ldc_resolution, "max_layers": 8, "seed": seed, "llf": "never",
            "indirect": {"mode": "off"}}


class Run:
    """The stack, its supervisor thread and an API client."""

    def __init__(self, stack: Stack):
        self.stack = stack
        self.client = Client(stack.api_url, timeout=30)
        self.log: list[tuple[float, str]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._supervise, daemon=True)
        self._thread.start()

    def _supervise(self) -> None:
        while not self._stop.is_set():
            fatal = self.stack.supervise(lambda s: self.log.append((time.monotonic(), s)))
            if fatal:
                self.log.append((time.monotonic(), f"FATAL {fatal}"))
                return
            time.sleep(0.2)

    def redis(self) -> Redis:
        return redis_from_url(self.stack.env["IBR_REDIS_URL"])

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)
        self.client.close()


def wait(pred: Callable[[], Any], timeout: float, interval: float = 0.05) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            v = pred()
        except Exception:  # noqa: BLE001 - Redis or the API may be restarting
            v = None
        if v:
            return v
        time.sleep(interval)
    return None


def started(redis: Redis, queue: QueueName) -> list[str]:
    return list(get_queue(redis, queue).started_job_registry.get_job_ids(cleanup=False))


def render_state(run: Run, job_id: str, key: str) -> str:
    try:
        return run.client.job(job_id).state
    except ApiError as exc:
        if exc.status != 404:
            raise
    try:
        run.client.artifact(key)
        return "finished"
    except ApiError:
        return "lost"


def bake_state(run: Run, scene_id: str, key: str) -> str:
    s = run.client.get_bake(scene_id, key).state
    return "lost" if s == "missing" else s


def submit(run: Run, args: argparse.Namespace, ids: dict[str, str], seed: int) -> dict[str, Any]:
    r = run.client.render(ids["render"], params=render_params(args, seed))
    assert r.job is not None, f"render {seed} was cached"
    b = run.client.bake(ids["bake"], bake_params(args, seed))
    assert not b.cached, f"bake {seed} was cached"
    return {"render_job": r.job.id, "render_key": r.artifact_key, "bake_key": b.key}


def both_running(run: Run, job: dict[str, Any], redis: Redis) -> bool:
    return job["render_job"] in started(redis, "render") and bool(started(redis, "bake"))


def outcome(run: Run, job: dict[str, Any], t_fault: float, timeout: float, ids: dict[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    ended: dict[str, float] = {}
    deadline = t_fault + timeout
    while time.monotonic() < deadline and len(ended) < 2:
        for kind in ("render", "bake"):
            if kind in ended:
                continue
            try:
                s = (render_state(run, job["render_job"], job["render_key"]) if kind == "render"
                     else bake_state(run, ids["bake"], job["bake_key"]))
            except Exception:  # noqa: BLE001 - the API may answer 503 while Redis restarts
                continue
            if s in ("finished", "failed", "canceled", "lost"):
                ended[kind] = time.monotonic()
                out[kind] = s
        time.sleep(0.1)
    for kind in ("render", "bake"):
        if kind not in ended:
            out[kind] = "stuck"
        else:
            out[f"{kind}_recovery_s"] = round(ended[kind] - t_fault, 2)
    return out


def start_pair(run: Run, args: argparse.Namespace, ids: dict[str, str], seed: int,
               rng: random.Random) -> dict[str, Any] | None:
    """Submit a render and a bake and return them once both run, a random 0.2-0.8 s into the jobs
    (None when they never ran together)."""
    job = submit(run, args, ids, seed)
    if not wait(lambda: both_running(run, job, run.redis()), 120):
        return None
    time.sleep(rng.uniform(0.2, 0.8))
    return job


SKIPPED = "the render and a bake job were never running together"


def kill_cycle(run: Run, args: argparse.Namespace, ids: dict[str, str], seed: int,
               rng: random.Random) -> dict[str, Any]:
    redis = run.redis()
    job = start_pair(run, args, ids, seed, rng)
    if job is None:
        return {"seed": seed, "skipped": SKIPPED}
    victims = {name: run.stack.procs[name] for name in ("render-worker", "bake-worker")}
    children = {name: [c.pid for c in psutil.Process(p.pid).children(recursive=True)] for name, p in victims.items()}
    mid_job = both_running(run, job, redis)  # still running the instant before the kill
    t_fault = time.monotonic()
    for p in victims.values():
        os.kill(p.pid, signal.SIGKILL)
    for p in victims.values():
        p.wait(timeout=10)
    orphans_gone = wait(lambda: not any(_alive(pid) for pids in children.values() for pid in pids), 5)
    res: dict[str, Any] = {"seed": seed, "mid_job": mid_job,
                           "children_killed": sum(len(v) for v in children.values()),
                           "orphans_after_5s": 0 if orphans_gone else
                           sum(_alive(pid) for pids in children.values() for pid in pids)}
    back = wait(lambda: all(run.stack.procs[n] is not p and run.stack.procs[n].poll() is None
                            for n, p in victims.items()), 60)
    res["workers_restarted_s"] = round(time.monotonic() - t_fault, 2) if back else None
    res.update(outcome(run, job, t_fault, args.timeout, ids))
    return res


def redis_cycle(run: Run, args: argparse.Namespace, ids: dict[str, str], seed: int,
                rng: random.Random) -> dict[str, Any]:
    redis = run.redis()
    job = start_pair(run, args, ids, seed, rng)
    if job is None:
        return {"seed": seed, "skipped": SKIPPED}
    pids = {n: run.stack.procs[n].pid for n in ("render-worker", "bake-worker", "api")}
    mid_job = both_running(run, job, redis)
    server = run.stack.redis
    assert server is not None
    proc = server.process  # type: ignore[attr-defined]
    t_fault = time.monotonic()
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=10)
    back = wait(lambda: run.stack.redis is not server, 30)
    res: dict[str, Any] = {"seed": seed, "mid_job": mid_job,
                           "redis_back_s": round(time.monotonic() - t_fault, 2) if back else None}
    res.update(outcome(run, job, t_fault, args.timeout, ids))
    res["processes_survived"] = all(run.stack.procs[n].pid == pid and run.stack.procs[n].poll() is None
                                    for n, pid in pids.items())
    return res


def _alive(pid: int) -> bool:
    try:
        return bool(psutil.Process(pid).status() != psutil.STATUS_ZOMBIE)
    except psutil.NoSuchProcess:
        return False


def summarize(rows: list[dict[str, Any]], kinds: tuple[str, ...]) -> dict[str, Any]:
    done = [r for r in rows if "skipped" not in r]
    out: dict[str, Any] = {"cycles": len(rows), "skipped": len(rows) - len(done),
                           "mid_job": sum(bool(r.get("mid_job")) for r in done)}
    for kind in kinds:
        states = [r[kind] for r in done]
        rec = [r[f"{kind}_recovery_s"] for r in done if r[kind] == "finished"]
        out[kind] = {
            "finished": states.count("finished"), "failed": states.count("failed"), "stuck": states.count("stuck"),
            "lost": states.count("lost"),
            "recovery_s": {"median": round(statistics.median(rec), 1), "max": round(max(rec), 1)} if rec else None,
        }
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kills", type=int, default=20, help="cycles of SIGKILL of both workers mid-job")
    ap.add_argument("--redis-restarts", type=int, default=5, help="cycles of SIGKILL of Redis mid-job")
    ap.add_argument("--timeout", type=float, default=180.0, help="seconds after a fault before a job counts as stuck")
    ap.add_argument("--spp", type=int, default=16, help="reference render samples per pixel (job length)")
    ap.add_argument("--light-samples", type=int, default=16, help="reference render area light samples (job length)")
    ap.add_argument("--ldc-resolution", type=int, default=128, help="bake LDC resolution (job length)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--keep", default=None, metavar="DIR",
                    help="run the stack in DIR (short path) and keep its logs there, instead of a temporary directory")
    args = ap.parse_args()
    rng = random.Random(args.seed)
    t_start = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="ibr-chaos-", dir="/tmp") as tmp_dir:
        tmp = args.keep or tmp_dir
        os.environ.pop("IBR_REDIS_URL", None)
        os.environ.pop("IBR_STORE_URL", None)
        stack = start_stack(Path(tmp), port=free_port(), log=lambda s: None, ready_timeout=180)
        run = Run(stack)
        try:
            ids = {"render": run.client.create_scene(RENDER_SCENE).id, "bake": run.client.create_scene(BAKE_SCENE).id}
            # warm-up (not counted): loads or compiles the kernels of both job kinds
            t0 = time.monotonic()
            job = submit(run, args, ids, 0)
            o = outcome(run, job, time.monotonic(), 1800, ids)
            print(f"warm-up: {o} in {time.monotonic() - t0:.0f} s", flush=True)
            t0 = time.monotonic()
            job = submit(run, args, ids, 1)
            clean = outcome(run, job, t0, 600, ids)
            print(f"clean run (no fault): {clean}", flush=True)
            kills, restarts = [], []
            for i in range(args.kills):
                kills.append(kill_cycle(run, args, ids, 100 + i, rng))
                print(f"kill {i + 1}/{args.kills}: {kills[-1]}", flush=True)
            for i in range(args.redis_restarts):
                restarts.append(redis_cycle(run, args, ids, 1000 + i, rng))
                print(f"redis restart {i + 1}/{args.redis_restarts}: {restarts[-1]}", flush=True)
            events = [s for _, s in run.log]
        finally:
            run.close()
            stack.stop(timeout=10)
    result = {
        "settings": {"kills": args.kills, "redis_restarts": args.redis_restarts, "timeout_s": args.timeout,
                     "spp": args.spp, "light_samples": args.light_samples, "ldc_resolution": args.ldc_resolution,
                     "render_scene": "384x288 reference render, one area light",
                     "liveness": "defaults (heartbeat every 10 s, 20 s grace, maintenance every 30 s)"},
        "clean_run_s": {k: clean.get(f"{k}_recovery_s") for k in ("render", "bake")},
        "worker_kills": summarize(kills, ("render", "bake")),
        "redis_restarts": summarize(restarts, ("render", "bake")),
        "orphans_left": sum(r.get("orphans_after_5s", 0) for r in kills),
        "children_killed": sum(r.get("children_killed", 0) for r in kills),
        "workers_restarted_s_max": max((r["workers_restarted_s"] for r in kills if r.get("workers_restarted_s")),
                                       default=None),
        "processes_survived_redis_restarts": sum(bool(r.get("processes_survived")) for r in restarts),
        "cycles": {"worker_kills": kills, "redis_restarts": restarts},
        "supervisor_log": events,
        "wall_s": round(time.monotonic() - t_start, 1),
    }
    print(json.dumps({k: v for k, v in result.items() if k not in ("cycles", "supervisor_log")}, indent=2))
    if args.no_write:
        return
    DATA.parent.mkdir(parents=True, exist_ok=True)
    DATA.write_text(json.dumps(result, indent=2) + "\n")
    replace_block(DOC, "chaos", table(result))


def table(res: dict[str, Any]) -> str:
    s = res["settings"]

    def row(fault: str, kind: str, part: dict[str, Any], n: int) -> str:
        rec = part[kind]["recovery_s"]
        rec_s = f"{rec['median']} / {rec['max']}" if rec else "-"
        p = part[kind]
        return f"| {fault} | {kind} | {n} | {p['finished']} | {p['failed']} | {p['stuck']} | {p['lost']} | {rec_s} |"

    wk, rr = res["worker_kills"], res["redis_restarts"]
    lines = [
        f"`flock /tmp/bench.lock python -m bench.chaos --kills {s['kills']} --redis-restarts {s['redis_restarts']}` "
        f"(2 shared cores; {s['render_scene']}, spp {s['spp']}, {s['light_samples']} light samples; "
        f"bake at LDC resolution {s['ldc_resolution']}; "
        f"liveness {s['liveness']}; a job not ended {s['timeout_s']:g} s after the fault counts as stuck). "
        f"Without faults the render took {res['clean_run_s']['render']} s and the bake "
        f"{res['clean_run_s']['bake']} s. Recovery = fault to the job's end, rerun included.",
        "",
        "| fault | job | faults | finished | failed | stuck | lost | recovery median / max (s) |",
        "|---|---|---|---|---|---|---|---|",
        row("both workers SIGKILLed mid-job", "render", wk, wk["cycles"] - wk["skipped"]),
        row("both workers SIGKILLed mid-job", "bake", wk, wk["cycles"] - wk["skipped"]),
        row("Redis SIGKILLed mid-job", "render", rr, rr["cycles"] - rr["skipped"]),
        row("Redis SIGKILLed mid-job", "bake", rr, rr["cycles"] - rr["skipped"]),
        "",
        f"- Both jobs were still running the instant before the fault in {wk['mid_job']} of "
        f"{wk['cycles'] - wk['skipped']} worker kills and {rr['mid_job']} of {rr['cycles'] - rr['skipped']} "
        "Redis kills (otherwise one of them had just ended).",
        f"- Children of the killed workers (RQ schedulers, bake horses): {res['children_killed']}, "
        f"left alive 5 s after the kill: {res['orphans_left']}.",
        f"- The supervisor had both new workers running at most {res['workers_restarted_s_max']} s after the kill.",
        f"- Worker and API processes alive through the Redis restarts: {res['processes_survived_redis_restarts']} "
        f"of {rr['cycles'] - rr['skipped']} restarts (no worker restarted).",
        f"- Wall time {res['wall_s']:.0f} s; every cycle in `docs/data/chaos.json`.",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    main()
