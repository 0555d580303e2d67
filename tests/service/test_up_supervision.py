"""``ibr up`` supervises its processes (service/up.py, ``Stack.supervise``): a dead worker is
started again with backoff and never takes the API down; the embedded Redis is started again on
its socket and append-only file; only an API that crash-loops stops the stack."""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Any, cast

import httpx
import psutil
import pytest
from redis import Redis
from rq import Worker

from producer.queue import QueueName, fetch_job, get_queue, redis_from_url
from service.up import API_CRASH_LOOP, Stack
from tests.fixtures.redis import wait_for
from tests.fixtures.stack import own_stack

PY = sys.executable


def _stack(tmp_path: Path, cmds: dict[str, list[str]]) -> Stack:
    st = Stack(tmp_path, "http://127.0.0.1:1", dict(os.environ), cmds=cmds)
    st.logs.mkdir(parents=True, exist_ok=True)
    for name in cmds:
        st.spawn(name)
    return st


def test_a_dying_worker_is_restarted_with_doubling_backoff(tmp_path: Path) -> None:
    st = _stack(tmp_path, {"render-worker": [PY, "-c", "import sys; sys.exit(4)"],
                           "api": [PY, "-c", "import time; time.sleep(120)"]})
    lines: list[str] = []
    try:
        delays = []
        for restart in range(1, 4):
            proc = st.procs["render-worker"]
            proc.wait(timeout=30)
            died = st.restarts["render-worker"].started_at + 0.1  # a quick death
            assert st.supervise(lines.append, now=died) is None
            due = st.restarts["render-worker"].due
            assert due is not None
            delays.append(round(due - died, 6))
            assert st.supervise(lines.append, now=due - 0.05) is None and st.procs["render-worker"] is proc
            assert st.supervise(lines.append, now=due) is None
            assert st.procs["render-worker"] is not proc and st.restarts["render-worker"].count == restart
        assert delays == [1.0, 2.0, 4.0]
        assert st.procs["api"].poll() is None  # the API never noticed
        # a worker that ran past the quick-death window is started again at once
        st.procs["render-worker"].wait(timeout=30)
        late = st.restarts["render-worker"].started_at + 60
        st.supervise(lines.append, now=late)
        assert st.restarts["render-worker"].count == 4 and st.restarts["render-worker"].quick_deaths == 0
        assert any("exited with status 4" in line and "again in 0 s" in line for line in lines)
        # a SIGKILLed worker (OOM killer, operator) is started again at once, however young
        st.cmds["render-worker"] = [PY, "-c", "import time; time.sleep(120)"]
        st.spawn("render-worker")
        st.procs["render-worker"].kill()
        st.procs["render-worker"].wait(timeout=10)
        st.supervise(lines.append, now=st.restarts["render-worker"].started_at + 0.1)
        assert st.restarts["render-worker"].count == 5 and st.procs["render-worker"].poll() is None
    finally:
        for p in st.procs.values():
            p.kill()
            p.wait(timeout=10)


def test_an_api_that_crash_loops_stops_the_stack(tmp_path: Path) -> None:
    st = _stack(tmp_path, {"api": [PY, "-c", "import sys; sys.exit(5)"]})
    lines: list[str] = []
    fatal = None
    try:
        for _ in range(API_CRASH_LOOP):
            st.procs["api"].wait(timeout=30)
            died = st.restarts["api"].started_at + 0.1
            fatal = st.supervise(lines.append, now=died)
            if fatal:
                break
            st.supervise(lines.append, now=st.restarts["api"].due)
        assert fatal is not None and f"{API_CRASH_LOOP} times in a row" in fatal and "status 5" in fatal
        assert st.restarts["api"].count == API_CRASH_LOOP - 1
    finally:
        for p in st.procs.values():
            p.kill()
            p.wait(timeout=10)


def test_stopping_busy_processes_takes_one_deadline_not_one_per_process(tmp_path: Path) -> None:
    """Workers busy with a long job (they finish it on SIGTERM: here they ignore it) are waited
    for together under one deadline, then killed; the API, which exits on SIGTERM, goes first."""
    busy = [PY, "-c", "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
                      "print('ready', flush=True); time.sleep(120)"]
    st = _stack(tmp_path, {"api": [PY, "-c", "import time; time.sleep(120)"], "render-worker": busy,
                           "bake-worker": busy})
    try:
        wait_for(lambda: all((st.logs / f"{n}.log").exists() and b"ready" in (st.logs / f"{n}.log").read_bytes()
                             for n in ("render-worker", "bake-worker")), 30, "workers ready")
        t0 = time.monotonic()
        st.stop(timeout=3.0)
        took = time.monotonic() - t0
        assert st.procs["api"].returncode == -signal.SIGTERM
        assert st.procs["render-worker"].returncode == -signal.SIGKILL
        assert st.procs["bake-worker"].returncode == -signal.SIGKILL
        assert 3.0 <= took < 5.5, took  # one 3 s deadline for all of them (it was 3 s per process)
    finally:
        for p in st.procs.values():
            if p.poll() is None:
                p.kill()
                p.wait(timeout=10)


@pytest.mark.slow
def test_ibr_up_restarts_a_killed_worker_and_redis_while_the_api_stays_up() -> None:
    with own_stack() as st:
        stop = threading.Event()
        log: list[str] = []
        api_down: list[float] = []

        def supervise() -> None:
            while not stop.is_set():
                assert st.supervise(log.append) is None
                time.sleep(0.2)

        def probe() -> None:  # the API's liveness, every 0.1 s
            with httpx.Client(base_url=st.api_url, timeout=2) as c:
                while not stop.is_set():
                    try:
                        ok = c.get("/healthz").status_code == 200
                    except httpx.HTTPError:
                        ok = False
                    if not ok:
                        api_down.append(time.monotonic())
                    time.sleep(0.1)

        threads = [threading.Thread(target=supervise, daemon=True), threading.Thread(target=probe, daemon=True)]
        for t in threads:
            t.start()
        try:
            redis = redis_from_url(st.env["IBR_REDIS_URL"])

            def live_workers(queue: QueueName) -> list[Any]:
                return [w for w in Worker.all(connection=redis, queue=get_queue(redis, queue))
                        if w.pid and _exists(w.pid)]

            wait_for(lambda: live_workers("render") and live_workers("bake"), 120, "both workers to register")
            api_pid = st.procs["api"].pid
            queues: tuple[tuple[str, QueueName], ...] = (("render-worker", "render"), ("bake-worker", "bake"))
            for name, queue in queues:
                old = st.procs[name]
                scheduler = [c.pid for c in psutil.Process(old.pid).children()]
                t0 = time.monotonic()
                os.kill(old.pid, signal.SIGKILL)

                def replaced(n: str = name, o: Any = old) -> bool:
                    return st.procs[n] is not o

                def new_registered(q: QueueName = queue, o: Any = old) -> bool:
                    return any(w.pid != o.pid for w in live_workers(q))

                wait_for(replaced, 10, f"{name} to be started again")
                restarted = time.monotonic() - t0
                wait_for(new_registered, 120, f"the new {queue} worker to register")
                assert not any(_exists(p) for p in scheduler), "the killed worker's scheduler survived it"
                assert restarted < 5, f"{name} restarted after {restarted:.1f} s"
                # the new worker takes work
                get_queue(redis, queue).enqueue("tests.workers.queue.jobs_for_tests.quick", {"q": queue},
                                                job_id=f"after-{queue}")
                def done(jid: str = f"after-{queue}") -> bool:
                    return finished(redis, jid)

                wait_for(done, 60, f"a {queue} job after the restart")
            assert st.procs["api"].pid == api_pid and not api_down, (api_down, log)

            # the embedded Redis killed: started again on the same socket; queued work survives
            redis_proc = cast(Any, st.redis).process
            os.kill(redis_proc.pid, signal.SIGKILL)
            wait_for(lambda: cast(Any, st.redis).process is not redis_proc, 20, "Redis to be started again")
            redis = redis_from_url(st.env["IBR_REDIS_URL"])
            job = get_queue(redis, "render").enqueue("tests.workers.queue.jobs_for_tests.quick", {"after": "redis"},
                                                     job_id="after-redis")
            wait_for(lambda: finished(redis, job.id), 60, "a render job after the Redis restart")
            assert st.procs["api"].pid == api_pid and not api_down, (api_down, log)
            assert st.procs["render-worker"].poll() is None and st.procs["bake-worker"].poll() is None
        finally:
            stop.set()
            for t in threads:
                t.join(timeout=10)


def finished(redis: Redis, job_id: str) -> bool:
    job = fetch_job(redis, job_id)
    return job is not None and job.get_status() == "finished"


def _exists(pid: int) -> bool:
    try:
        return bool(psutil.Process(pid).status() != psutil.STATUS_ZOMBIE)
    except psutil.NoSuchProcess:
        return False
