"""Real workers (``python -m workers.runner`` subprocesses) against a real embedded Redis that goes
away while they work, and workers killed with SIGKILL (docs/reliability.md):

- Redis killed (or shut down) mid-job and started again on the same socket with its append-only
  file: the busy worker stays alive, its job ends ``finished`` (queued again at the front and
  rerun, no retry spent), never stays ``started``; an idle worker survives too;
- a SIGKILLed worker leaves no scheduler process behind, so the next job is not handed to the
  dead worker's still-open dequeue and starts at once;
- a SIGKILLed busy worker's job is taken over by a worker of the same host at its next
  maintenance pass, not after the heartbeat expiry and the dead scheduler's lock (30 + 61 s).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import psutil
import pytest
from redis import Redis
from rq import Retry, Worker

from producer.embedded import EmbeddedRedis, start_embedded_redis
from producer.queue import QueueName, fetch_job, get_queue, redis_from_url
from tests.fixtures.redis import REPO_ROOT, WorkerProcess, spawn_worker, wait_for

pytestmark = pytest.mark.slow

SLEEPY = "tests.workers.queue.jobs_for_tests.sleepy"
QUICK = "tests.workers.queue.jobs_for_tests.quick"


class OwnRedis:
    """An embedded Redis of this test alone, so the test can kill and restart it."""

    def __init__(self, data_dir: Path):
        self.data_dir = data_dir
        self.server: EmbeddedRedis = start_embedded_redis(data_dir)
        self.url = self.server.url

    def client(self) -> Redis:
        return redis_from_url(self.url)

    def kill(self, how: str) -> None:
        proc = self.server.process
        assert proc is not None
        if how == "sigkill":
            proc.send_signal(signal.SIGKILL)
            proc.wait(timeout=10)
        else:
            self.server.stop()

    def start(self) -> None:
        self.server = start_embedded_redis(self.data_dir)
        assert self.server.url == self.url

    def stop(self) -> None:
        proc = self.server.process
        if proc is not None and proc.poll() is None:
            proc.kill()
            proc.wait(timeout=10)


@pytest.fixture
def own_redis() -> Iterator[OwnRedis]:
    with tempfile.TemporaryDirectory(prefix="ibr-o-", dir="/tmp") as d:  # short unix socket path
        r = OwnRedis(Path(d))
        try:
            yield r
        finally:
            r.stop()


@pytest.fixture
def start_worker(own_redis: OwnRedis, tmp_path: Path) -> Iterator[Callable[..., WorkerProcess]]:
    started: list[WorkerProcess] = []

    def start(queue: str, *args: str, fast: bool = True) -> WorkerProcess:
        wp = spawn_worker(queue, *args, redis_url=own_redis.url, store_dir=tmp_path / "store",
                          data_dir=tmp_path / "data", log_dir=tmp_path, fast=fast)
        started.append(wp)
        return wp

    yield start
    for wp in started:
        wp.kill(signal.SIGKILL)


def status(redis: Redis, job_id: str) -> str | None:
    try:
        job = fetch_job(redis, job_id)
    except Exception:  # noqa: BLE001 - Redis may be restarting: no answer is an answer here
        return None
    s = None if job is None else job.get_status()
    return None if s is None else s.value


def registered(redis: Redis, name: str) -> bool:
    return any(w.name == name for w in Worker.all(connection=redis))


def other(queue: QueueName) -> QueueName:
    return "bake" if queue == "render" else "render"


def alive(pid: int) -> bool:
    try:
        return bool(psutil.Process(pid).status() != psutil.STATUS_ZOMBIE)
    except psutil.NoSuchProcess:
        return False


@pytest.mark.parametrize("queue", ["render", "bake"])
@pytest.mark.parametrize("how", ["sigkill", "shutdown"])
def test_redis_restart_mid_job_the_job_finishes_and_workers_live(
    own_redis: OwnRedis, start_worker: Callable[..., WorkerProcess], queue: QueueName, how: str
) -> None:
    r = own_redis.client()
    busy = start_worker(queue, "--name", "busy")
    idle = start_worker(other(queue), "--name", "idle")
    wait_for(lambda: registered(r, "busy") and registered(r, "idle"), 60, "both workers to register")
    job = get_queue(r, queue).enqueue(SLEEPY, {"seconds": 4.0}, job_id=f"{queue}-slow",
                                      retry=Retry(max=2, interval=[1, 1]))
    wait_for(lambda: status(r, job.id) == "started", 30, "the job to start")
    time.sleep(1.0)  # mid-job, progress being written

    own_redis.kill(how)
    time.sleep(3.0)  # Redis away for 3 s: longer than redis-py's own short retries
    assert busy.alive() and idle.alive(), busy.log()
    own_redis.start()
    r = own_redis.client()

    t0 = time.monotonic()
    final = wait_for(lambda: (s := status(r, job.id)) in ("finished", "failed") and s, 40, "the job to end")
    assert final == "finished", busy.log()
    took = time.monotonic() - t0
    assert took < 30, f"job ended {took:.1f} s after Redis came back"
    j = fetch_job(r, job.id)
    assert j is not None and j.retries_left == 2, "the outage must not spend the job's retries"
    assert busy.alive() and idle.alive(), busy.log()

    # both workers take work again after the outage
    for q, jid in ((queue, "after-busy"), (other(queue), "after-idle")):
        get_queue(r, q).enqueue(QUICK, {"n": 1}, job_id=jid)
    wait_for(lambda: status(r, "after-busy") == "finished" and status(r, "after-idle") == "finished", 30,
             "both workers to run a job after the outage")
    assert get_queue(r, queue).started_job_registry.get_job_count(cleanup=False) == 0


def test_sigkilled_idle_worker_leaves_no_scheduler_and_the_next_job_starts_at_once(
    own_redis: OwnRedis, start_worker: Callable[..., WorkerProcess]
) -> None:
    r = own_redis.client()
    # w1 blocks in its dequeue first, so Redis would hand the next job to w1's connection
    w1 = start_worker("render", "--name", "w1", "--maintenance-interval", "60", fast=False)
    wait_for(lambda: registered(r, "w1"), 60, "w1 to register")
    scheduler = wait_for(lambda: psutil.Process(w1.pid).children(), 10, "w1's scheduler process")
    time.sleep(0.5)
    w2 = start_worker("render", "--name", "w2", "--maintenance-interval", "60", fast=False)
    wait_for(lambda: registered(r, "w2"), 60, "w2 to register")
    time.sleep(0.5)

    os.kill(w1.pid, signal.SIGKILL)  # the worker alone, not its process group
    w1.proc.wait(timeout=10)
    t0 = time.monotonic()
    wait_for(lambda: not any(alive(p.pid) for p in scheduler), 3, "w1's scheduler to die with it")
    gone_after = time.monotonic() - t0

    t1 = time.monotonic()
    get_queue(r, "render").enqueue(QUICK, {"n": 2}, job_id="next")
    wait_for(lambda: status(r, "next") == "finished", 10, "the next job to run on w2")
    started = time.monotonic() - t1
    assert started < 5, f"next job took {started:.1f} s"
    assert gone_after < 3
    assert w2.alive()


def test_sigkilled_busy_worker_job_is_taken_over_at_the_next_maintenance(
    own_redis: OwnRedis, start_worker: Callable[..., WorkerProcess]
) -> None:
    """Default-like liveness timings (heartbeat every 10 s, 20 s grace): without the same-host
    check the job would wait 30 s for its heartbeat to expire and then up to 61 s for the dead
    scheduler's lock before its scheduled retry runs."""
    r = own_redis.client()
    slow_args = ("--maintenance-interval", "3", "--job-monitoring-interval", "10", "--heartbeat-grace", "20")
    w1 = start_worker("render", "--name", "k1", *slow_args, fast=False)
    wait_for(lambda: registered(r, "k1"), 60, "k1 to register")
    job = get_queue(r, "render").enqueue(SLEEPY, {"seconds": 3.0}, job_id="killed",
                                         retry=Retry(max=2, interval=[1, 1]))
    wait_for(lambda: status(r, job.id) == "started", 30, "the job to start on k1")
    w2 = start_worker("render", "--name", "k2", *slow_args, fast=False)
    wait_for(lambda: registered(r, "k2"), 60, "k2 to register")

    os.kill(w1.pid, signal.SIGKILL)
    w1.proc.wait(timeout=10)
    t0 = time.monotonic()
    final = wait_for(lambda: (s := status(r, job.id)) in ("finished", "failed") and s, 40, "the job to end")
    took = time.monotonic() - t0
    assert final == "finished", w2.log()
    assert took < 15, f"recovered after {took:.1f} s (measured ~7 s; 31-35 s without); log:\n{w2.log()}"
    assert w2.alive()


def test_an_idle_worker_wakes_for_maintenance_when_a_heartbeat_expires(
    own_redis: OwnRedis, start_worker: Callable[..., WorkerProcess]
) -> None:
    """Maintenance every 60 s, heartbeat every 2 s with a 2 s grace: the idle worker ends its
    blocking dequeue when the dead worker's job's heartbeat expires, so the job is retried seconds
    after the expiry, not at the next 60 s maintenance pass (it was blocked before the job started:
    its rounds last at most the 4 s heartbeat expiry)."""
    r = own_redis.client()
    args = ("--maintenance-interval", "60", "--job-monitoring-interval", "2", "--heartbeat-grace", "2")
    w1 = start_worker("render", "--name", "e1", "--no-warmup", *args, fast=False)
    wait_for(lambda: registered(r, "e1"), 60, "e1 to register")
    w2 = start_worker("render", "--name", "e2", "--no-warmup", *args, fast=False)
    wait_for(lambda: registered(r, "e2"), 60, "e2 to register")
    time.sleep(1.0)  # both past their start-up maintenance pass, blocked in their dequeue
    job = get_queue(r, "render").enqueue(SLEEPY, {"seconds": 30.0}, job_id="expires",
                                         retry=Retry(max=2, interval=[1, 1]))
    # Both workers block on the same queue and either may take the job (each re-blocks every few
    # seconds, so which one Redis serves first is a race): kill whichever started it.
    first = wait_for(lambda: status(r, job.id) == "started" and r.hget("rq:job:expires", "worker_name"), 30,
                     "the job to start")
    doomed, survivor, survivor_name = (w1, w2, b"e2") if first == b"e1" else (w2, w1, b"e1")
    os.kill(doomed.pid, signal.SIGKILL)
    doomed.proc.wait(timeout=10)
    t0 = time.monotonic()
    wait_for(lambda: r.hget("rq:job:expires", "worker_name") == survivor_name and status(r, job.id) == "started",
             40, f"the job to be retried on {survivor_name.decode()}; log:\n{survivor.log()}")
    took = time.monotonic() - t0
    assert took < 15, f"retried {took:.1f} s after the kill (next maintenance pass: ~60 s); log:\n{survivor.log()}"
    assert survivor.alive()


def test_worker_healthcheck_answers_from_redis(own_redis: OwnRedis, start_worker: Callable[..., WorkerProcess],
                                               tmp_path: Path) -> None:
    """``python -m workers.runner --queue Q --healthcheck`` (the compose health check): 0 while a
    worker of Q on this host has a fresh heartbeat, 1 when none does, non-zero without Redis."""
    env = {**os.environ, "IBR_REDIS_URL": own_redis.url, "IBR_STORE_URL": f"file://{tmp_path / 'store'}",
           "PYTHONPATH": os.pathsep.join([str(REPO_ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}

    def check(queue: str) -> int:
        return subprocess.run([sys.executable, "-m", "workers.runner", "--queue", queue, "--healthcheck"],
                              cwd=REPO_ROOT, env=env, capture_output=True, timeout=60).returncode

    assert check("bake") == 1  # nobody registered yet
    r = own_redis.client()
    w = start_worker("bake", "--name", "hc")
    wait_for(lambda: registered(r, "hc"), 60, "the worker to register")
    assert check("bake") == 0
    assert check("render") == 1
    w.kill(signal.SIGKILL)  # its registration stays in Redis, but its process is gone
    assert check("bake") == 1
    own_redis.kill("sigkill")
    assert check("bake") != 0
