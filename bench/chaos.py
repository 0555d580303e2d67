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
from rq import Worker
from rq.scheduler import SCHEDULER_KEY_TEMPLATE, RQScheduler

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


def render_params(args: argparse.Namespace, seed: int, long: bool = False) -> dict[str, Any]:
    return {"spp": args.loss_spp if long else args.spp, "area_light_samples": args.light_samples, "seed": seed}


def bake_params(args: argparse.Namespace, seed: int, long: bool = False) -> dict[str, Any]:
    return {"ldc_resolution": args.loss_ldc_resolution if long else args.ldc_resolution, "max_layers": 8,
            "seed": seed, "llf": "never", "indirect": {"mode": "off"}}


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


def render_state(client: Client, job_id: str, key: str) -> str:
    try:
        return client.job(job_id).state
    except ApiError as exc:
        if exc.status != 404:
            raise
    try:
        client.artifact(key)
        return "finished"
    except ApiError:
        return "lost"


def bake_state(client: Client, scene_id: str, key: str) -> str:
    s = client.get_bake(scene_id, key).state
    return "lost" if s == "missing" else s


def submit(client: Client, args: argparse.Namespace, ids: dict[str, str], seed: int,
           long: bool = False) -> dict[str, Any]:
    r = client.render(ids["render"], params=render_params(args, seed, long))
    assert r.job is not None, f"render {seed} was cached"
    b = client.bake(ids["bake"], bake_params(args, seed, long))
    assert not b.cached, f"bake {seed} was cached"
    return {"render_job": r.job.id, "render_key": r.artifact_key, "bake_key": b.key}


def both_running(run: Run, job: dict[str, Any], redis: Redis) -> bool:
    return job["render_job"] in started(redis, "render") and bool(started(redis, "bake"))


def outcome(client: Client, job: dict[str, Any], t_fault: float, timeout: float, ids: dict[str, str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    ended: dict[str, float] = {}
    deadline = t_fault + timeout
    while time.monotonic() < deadline and len(ended) < 2:
        for kind in ("render", "bake"):
            if kind in ended:
                continue
            try:
                s = (render_state(client, job["render_job"], job["render_key"]) if kind == "render"
                     else bake_state(client, ids["bake"], job["bake_key"]))
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
    job = submit(run.client, args, ids, seed)
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
    res.update(outcome(run.client, job, t_fault, args.timeout, ids))
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
    res.update(outcome(run.client, job, t_fault, args.timeout, ids))
    res["processes_survived"] = all(run.stack.procs[n].pid == pid and run.stack.procs[n].poll() is None
                                    for n, pid in pids.items())
    return res


def _alive(pid: int) -> bool:
    try:
        return bool(psutil.Process(pid).status() != psutil.STATUS_ZOMBIE)
    except psutil.NoSuchProcess:
        return False


# -- host losses: the service spread over network namespaces (tests/deployment/cluster.py) ---------

LOSS_KINDS: tuple[QueueName, ...] = ("render", "bake")


def _text(value: Any) -> str | None:
    return value.decode() if isinstance(value, bytes) else value


def worker_of(redis: Redis, job_id: str) -> str | None:
    return _text(redis.hget(f"rq:job:{job_id}", "worker_name"))


def scheduler_host(redis: Redis, queue: str) -> str | None:
    """The hostname of the scheduler holding ``queue``'s scheduler lock (it enqueues due retries)."""
    name = _text(redis.get(RQScheduler.get_locking_key(queue)))
    return _text(redis.hget(SCHEDULER_KEY_TEMPLATE % name, "hostname")) if name else None


def worker_names(redis: Redis) -> set[str]:
    return {w.name for w in Worker.all(connection=redis)}


def add_worker_host(cluster: Any, name: str) -> None:
    """A worker host ``name`` running a bake and a render worker with the default liveness timings."""
    cluster.worker_hosts[name] = cluster.hosts.add(name)
    for queue in LOSS_KINDS:
        cluster.start_worker(name, queue, liveness=())


def loss_cycle(cluster: Any, client: Client, redis: Redis, args: argparse.Namespace, ids: dict[str, str],
               seed: int, victim: str, fresh: str) -> dict[str, Any]:
    """Submit a render and a bake while ``victim`` is the only worker host (so it runs both, and its
    schedulers hold both queues' scheduler locks), start host ``fresh``'s workers, and once they
    are registered take ``victim`` away (link cut, every process SIGKILLed). Measured from the loss:
    when ``fresh``'s schedulers hold the locks, when the lost jobs started again on ``fresh``, and
    how each job ended."""
    job = submit(client, args, ids, seed, long=True)
    names = {kind: f"{kind}-{victim}" for kind in LOSS_KINDS}

    def on_victim(kind: QueueName) -> list[str]:
        return [j for j in started(redis, kind) if worker_of(redis, j) == names[kind]]

    if not wait(lambda: job["render_job"] in on_victim("render") and on_victim("bake"), 120):
        return {"seed": seed, "skipped": SKIPPED}
    add_worker_host(cluster, fresh)
    joined = wait(lambda: {f"{k}-{fresh}" for k in LOSS_KINDS} <= worker_names(redis), 120)
    lost = {"render": [job["render_job"]], "bake": on_victim("bake")}
    mid_job = bool(joined) and job["render_job"] in on_victim("render") and bool(lost["bake"])
    locks_on_victim = all(scheduler_host(redis, q) == victim for q in LOSS_KINDS)
    t_fault = time.monotonic()
    killed = cluster.hosts.take_down(cluster.worker_hosts[victim])
    res: dict[str, Any] = {"seed": seed, "mid_job": mid_job, "victim": victim, "processes_killed": killed,
                           "locks_on_victim": locks_on_victim, "lost_bake_jobs": lost["bake"],
                           "fresh_joined": bool(joined)}
    ended: dict[str, float] = {}
    marks: dict[str, float] = {}
    deadline = t_fault + args.timeout
    while time.monotonic() < deadline:
        now = time.monotonic()
        try:
            for q in LOSS_KINDS:
                if f"{q}_lock_s" not in marks and scheduler_host(redis, q) == fresh:
                    marks[f"{q}_lock_s"] = now - t_fault
                if f"{q}_rerun_s" not in marks and lost[q] and \
                        all(worker_of(redis, j) == f"{q}-{fresh}" for j in lost[q]):
                    marks[f"{q}_rerun_s"] = now - t_fault
            for kind in LOSS_KINDS:
                if kind not in ended:
                    st = (render_state(client, job["render_job"], job["render_key"]) if kind == "render"
                          else bake_state(client, ids["bake"], job["bake_key"]))
                    if st in ("finished", "failed", "canceled", "lost"):
                        ended[kind], res[kind] = now, st
        except Exception:  # noqa: BLE001 - report what was seen; the loop goes on until the deadline
            pass
        if len(ended) == len(LOSS_KINDS) and (len(marks) == 2 * len(LOSS_KINDS) or now > max(ended.values()) + 60):
            break
        time.sleep(0.1)
    for kind in LOSS_KINDS:
        if kind not in ended:
            res[kind] = "stuck"
        else:
            res[f"{kind}_recovery_s"] = round(ended[kind] - t_fault, 2)
    res.update({k: round(v, 2) for k, v in marks.items()})
    return res


def median_max(values: list[float]) -> dict[str, float] | None:
    return {"median": round(statistics.median(values), 1), "max": round(max(values), 1)} if values else None


def host_losses(args: argparse.Namespace) -> dict[str, Any]:
    """``--host-losses`` cycles on the service spread over hosts (module docstring, 3.)."""
    from tests.deployment.cluster import Cluster
    from tests.fixtures.netns import Hosts, netns_unavailable_reason

    reason = netns_unavailable_reason()
    if reason is not None:
        raise SystemExit(f"--host-losses needs the several-hosts setup: {reason}")
    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="ibr-hosts-", dir="/tmp") as tmp_dir:
        root = Path(args.keep) / "hosts" if args.keep else Path(tmp_dir)
        root.mkdir(parents=True, exist_ok=True)
        hosts = Hosts(root)
        try:
            hosts.start()
            c = Cluster(hosts, hosts.add("redis"), hosts.add("s3"), hosts.add("api"), {})
            c.start_redis()
            c.start_s3()
            c.wait_redis()
            c.make_bucket()
            c.start_api()
            redis = redis_from_url(c.redis_url)
            live = "w0"
            add_worker_host(c, live)
            c.wait_api(timeout=180)
            if not wait(lambda: all(scheduler_host(redis, q) == live for q in LOSS_KINDS), 180):
                raise SystemExit(f"the workers of {live} never held the scheduler locks:\n{c.logs()}")
            with Client(c.api_url, timeout=30) as client:
                w, h = (int(v) for v in args.loss_size.split("x"))
                big = {**RENDER_SCENE, "camera": {**RENDER_SCENE["camera"], "width": w, "height": h}}  # type: ignore[dict-item]
                ids = {"render": client.create_scene(big).id, "bake": client.create_scene(BAKE_SCENE).id}
                t0 = time.monotonic()
                o = outcome(client, submit(client, args, ids, 0, long=True), t0, 1800, ids)
                print(f"hosts warm-up: {o} in {time.monotonic() - t0:.0f} s", flush=True)
                t0 = time.monotonic()
                clean = outcome(client, submit(client, args, ids, 1, long=True), t0, 600, ids)
                print(f"hosts clean run (no fault): {clean}", flush=True)
                for i in range(args.host_losses):
                    fresh = f"w{i + 1}"
                    rows.append(loss_cycle(c, client, redis, args, ids, 2000 + i, live, fresh))
                    print(f"host loss {i + 1}/{args.host_losses}: {rows[-1]}", flush=True)
                    if "skipped" not in rows[-1]:
                        live = fresh
            redis.close()
        finally:
            hosts.close()
    done = [r for r in rows if "skipped" not in r]
    out = summarize(rows, LOSS_KINDS)
    out.update({
        "clean_run_s": {k: clean.get(f"{k}_recovery_s") for k in LOSS_KINDS},
        "locks_on_victim": sum(bool(r.get("locks_on_victim")) for r in done),
        "lock_taken_over_s": {q: median_max([r[f"{q}_lock_s"] for r in done if f"{q}_lock_s" in r])
                              for q in LOSS_KINDS},
        "rerun_started_s": {q: median_max([r[f"{q}_rerun_s"] for r in done if f"{q}_rerun_s" in r])
                            for q in LOSS_KINDS},
        "rerun_started_max_s": max((r[f"{q}_rerun_s"] for r in done for q in LOSS_KINDS if f"{q}_rerun_s" in r),
                                   default=None),
        "processes_killed": sum(r.get("processes_killed", 0) for r in done),
        "rows": rows,
    })
    return out


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


def single_host(args: argparse.Namespace, rng: random.Random) -> dict[str, Any]:
    """The ``--kills`` and ``--redis-restarts`` cycles on the ``ibr up`` stack (module docstring, 1. and 2.)."""
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
            job = submit(run.client, args, ids, 0)
            o = outcome(run.client, job, time.monotonic(), 1800, ids)
            print(f"warm-up: {o} in {time.monotonic() - t0:.0f} s", flush=True)
            t0 = time.monotonic()
            job = submit(run.client, args, ids, 1)
            clean = outcome(run.client, job, t0, 600, ids)
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
    return {
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
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kills", type=int, default=20, help="cycles of SIGKILL of both workers mid-job")
    ap.add_argument("--redis-restarts", type=int, default=5, help="cycles of SIGKILL of Redis mid-job")
    ap.add_argument("--host-losses", type=int, default=0,
                    help="cycles of a worker host lost mid-render and mid-bake, on the service spread over network "
                         "namespaces (needs root and `ip`)")
    ap.add_argument("--bombs", action="store_true",
                    help="also run bench.upload_bombs (upload bombs against an API under a 1 GiB memory ceiling)")
    ap.add_argument("--timeout", type=float, default=180.0, help="seconds after a fault before a job counts as stuck")
    ap.add_argument("--spp", type=int, default=16, help="reference render samples per pixel (job length)")
    ap.add_argument("--light-samples", type=int, default=16, help="reference render area light samples (job length)")
    ap.add_argument("--ldc-resolution", type=int, default=128, help="bake LDC resolution (job length)")
    ap.add_argument("--loss-size", default="640x480",
                    help="host losses: the reference render's size, WxH (its job must outlast the start-up of the "
                         "next host's workers)")
    ap.add_argument("--loss-spp", type=int, default=16, help="host losses: reference render spp")
    ap.add_argument("--loss-ldc-resolution", type=int, default=512, help="host losses: bake LDC resolution")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-write", action="store_true")
    ap.add_argument("--keep", default=None, metavar="DIR",
                    help="run the stack in DIR (short path) and keep its logs there, instead of a temporary directory")
    args = ap.parse_args()
    rng = random.Random(args.seed)
    t_start = time.monotonic()
    result: dict[str, Any] = {
        "settings": {"kills": args.kills, "redis_restarts": args.redis_restarts, "host_losses": args.host_losses,
                     "timeout_s": args.timeout, "spp": args.spp, "light_samples": args.light_samples,
                     "ldc_resolution": args.ldc_resolution, "loss_size": args.loss_size, "loss_spp": args.loss_spp,
                     "loss_ldc_resolution": args.loss_ldc_resolution,
                     "render_scene": "384x288 reference render, one area light",
                     "liveness": "defaults (heartbeat every 10 s, 20 s grace, maintenance every 30 s)"},
    }
    if args.kills or args.redis_restarts:
        result.update(single_host(args, rng))
    elif not args.no_write and DATA.exists():
        # only host losses this time: the doc keeps the one-host results of the last run that had them
        before = json.loads(DATA.read_text())
        if "worker_kills" in before:
            result.update({k: v for k, v in before.items() if k not in ("settings", "host_losses", "wall_s")})
            result["single_host_settings"] = before["settings"]
    if args.host_losses:
        result["host_losses"] = host_losses(args)
    result["wall_s"] = round(time.monotonic() - t_start, 1)
    print(json.dumps({k: v for k, v in result.items() if k not in ("cycles", "supervisor_log")}, indent=2,
                     default=str))
    if args.bombs:
        from bench.upload_bombs import main as bombs_main

        bombs_main(["--no-write"] if args.no_write else [])
    if args.no_write:
        return
    DATA.parent.mkdir(parents=True, exist_ok=True)
    DATA.write_text(json.dumps(result, indent=2) + "\n")
    replace_block(DOC, "chaos", table(result))


def _rec(v: dict[str, Any] | None) -> str:
    return f"{v['median']} / {v['max']}" if v else "-"


def table(res: dict[str, Any]) -> str:
    s = res["settings"]

    def row(fault: str, kind: str, part: dict[str, Any], n: int) -> str:
        p = part[kind]
        return (f"| {fault} | {kind} | {n} | {p['finished']} | {p['failed']} | {p['stuck']} | {p['lost']} | "
                f"{_rec(p['recovery_s'])} |")

    cmd = f"flock /tmp/bench.lock python -m bench.chaos --kills {s['kills']} --redis-restarts {s['redis_restarts']}"
    if s.get("host_losses"):
        cmd += f" --host-losses {s['host_losses']}"
    lines = [
        f"`{cmd}` (2 shared cores; liveness {s['liveness']}; a job not ended {s['timeout_s']:g} s after the fault "
        "counts as stuck). Recovery = fault to the job's end, rerun included.",
        "",
    ]
    if "worker_kills" in res:
        wk, rr = res["worker_kills"], res["redis_restarts"]
        one = res.get("single_host_settings")
        earlier = ""
        if one:
            s = {**s, **{k: one[k] for k in ("spp", "light_samples", "ldc_resolution", "render_scene") if k in one}}
            earlier = f", from an earlier run: `--kills {one['kills']} --redis-restarts {one['redis_restarts']}`"
        lines += [
            f"**One host** (the `ibr up` stack{earlier}): "
            f"{s['render_scene']}, spp {s['spp']}, {s['light_samples']} light "
            f"samples; bake at LDC resolution {s['ldc_resolution']}. Without faults the render took "
            f"{res['clean_run_s']['render']} s and the bake {res['clean_run_s']['bake']} s.",
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
            f"- Worker and API processes alive through the Redis restarts: "
            f"{res['processes_survived_redis_restarts']} of {rr['cycles'] - rr['skipped']} restarts (no worker "
            "restarted).",
            "",
        ]
    if "host_losses" in res:
        hl = res["host_losses"]
        n = hl["cycles"] - hl["skipped"]
        lines += [
            f"**Several hosts** (network namespaces as in `tests/deployment/`: Redis, S3, the API and worker "
            f"hosts, each worker host a bake and a render worker): a {s['loss_size']} reference render (spp "
            f"{s['loss_spp']}, {s['light_samples']} light samples) and a bake "
            f"(LDC resolution {s['loss_ldc_resolution']}) run on the only worker host, whose schedulers hold both "
            "queues' scheduler locks; a new worker host joins, and once its workers are registered the first "
            "host is lost (its link cut, every process SIGKILLed). Without faults the render took "
            f"{hl['clean_run_s']['render']} s and the bake {hl['clean_run_s']['bake']} s.",
            "",
            "| fault | job | faults | finished | failed | stuck | lost | scheduler lock taken over (s) | "
            "lost job running again (s) | job ended (s) |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for kind in LOSS_KINDS:
            p = hl[kind]
            lines.append(f"| worker host lost mid-job | {kind} | {n} | {p['finished']} | {p['failed']} | "
                         f"{p['stuck']} | {p['lost']} | {_rec(hl['lock_taken_over_s'][kind])} | "
                         f"{_rec(hl['rerun_started_s'][kind])} | {_rec(p['recovery_s'])} |")
        lines += [
            "",
            "Times are median / max from the loss. A bake's lost job is the part (or plan, or merge) the lost "
            "host was running.",
            "",
            f"- Both jobs were running on the lost host the instant before the loss in {hl['mid_job']} of {n} "
            f"losses; it held both scheduler locks in {hl['locks_on_victim']} of {n}; processes killed with "
            f"the hosts: {hl['processes_killed']}.",
            "",
        ]
    lines.append(f"Wall time {res['wall_s']:.0f} s; every cycle in `docs/data/chaos.json`.")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
