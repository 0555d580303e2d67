"""Worker-side settings: the ONLY place worker code reads the environment.

Every variable has the prefix ``IBR_`` (``IBR_REDIS_URL``, ``IBR_STORE_URL``, ...). The job
functions and the runner call :func:`get_settings` once per process; the settings are validated
when the worker starts (``python -m workers.runner`` exits with status 2 and a message naming the
variable when one is malformed), never in the middle of a job.

Defaults follow the embedded mode of ``ibr up``: with no ``IBR_REDIS_URL`` the workers talk to
the embedded Redis on ``unix://<data_dir>/redis.sock`` and, with no ``IBR_STORE_URL``, store
objects under ``<data_dir>/store``. ``data_dir`` defaults to ``~/.ibr``.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Annotated
from urllib.parse import urlsplit

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from workers.store import ObjectStore, open_configured_store

__all__ = ["WorkerSettings", "get_settings", "open_worker_store", "reset_settings_cache"]

EMBEDDED_SOCKET_NAME = "redis.sock"
"""File name of the embedded Redis unix socket inside ``data_dir`` (see workers/embedded.py)."""


class WorkerSettings(BaseSettings):
    """Settings of a worker process (environment variables ``IBR_<FIELD>``, case-insensitive)."""

    model_config = SettingsConfigDict(env_prefix="IBR_", extra="ignore", frozen=True)

    data_dir: Path = Field(default_factory=lambda: Path.home() / ".ibr")
    """Data directory: embedded Redis socket and files, default local object store."""
    redis_url: str | None = None
    """``redis://``, ``rediss://`` or ``unix://`` URL; None = the embedded server in ``data_dir``."""
    store_url: str | None = None
    """``file:///path``, ``/path`` or ``s3://bucket/prefix``; None = ``<data_dir>/store``."""
    s3_endpoint_url: str | None = None
    """S3 endpoint for ``s3://`` store URLs (MinIO, moto); None = AWS."""
    s3_region: str | None = None
    s3_access_key: str | None = None
    s3_secret_key: SecretStr | None = None
    cache_bytes: Annotated[int, Field(gt=0)] = 2 << 30
    """Byte budget of the render worker's LRU of loaded scenes / warm renderers (default 2 GiB)."""

    # --- RQ worker tuning (the runner's command-line flags override these) -----------------------
    maintenance_interval_s: Annotated[int, Field(ge=1, le=3600)] = 30
    """How often a worker cleans its queue's registries (abandoned 'started' jobs, HARD_CASES 20)."""
    job_monitoring_interval_s: Annotated[int, Field(ge=1, le=600)] = 10
    """How often a busy worker refreshes the heartbeat of its running job."""
    heartbeat_grace_s: Annotated[int, Field(ge=1, le=3600)] = 20
    """A running job whose heartbeat is older than ``job_monitoring_interval_s + heartbeat_grace_s``
    counts as abandoned (its worker died) and is retried or failed by the next maintenance pass."""
    worker_ttl_s: Annotated[int, Field(ge=15, le=86400)] = 420
    """TTL of the worker's own registration key (RQ's default); refreshed while the worker lives."""
    worker_warmup: bool = True
    """Render workers: run ``workers.warmup.warm_up`` (every engine path of the render queue's jobs on
    tiny built-in data, so numba compiles or loads its kernels) before taking jobs; ``--no-warmup``
    overrides. Bake workers never warm up (their parent must not run a kernel before forking)."""
    malloc_keep_mib: Annotated[int, Field(ge=0, le=2047)] = 256
    """Freed memory (MiB) a worker keeps mapped for its next job instead of returning it to the
    kernel, and blocks up to 32 MiB served from the heap (``engine.memory.keep_freed_memory``):
    image-sized buffers are then reused, not page-faulted in anew by each render (LDC and reference
    renders alternating: ~1.2x faster each with it). 0: glibc's defaults."""

    @field_validator("redis_url")
    @classmethod
    def _check_redis_url(cls, v: str | None) -> str | None:
        if v is None or v == "":
            return None
        parts = urlsplit(v)
        if parts.scheme not in ("redis", "rediss", "unix"):
            raise ValueError(f"must be a redis://, rediss:// or unix:// URL, got scheme {parts.scheme!r}")
        if parts.scheme == "unix" and not parts.path:
            raise ValueError("unix:// URL needs a socket path, e.g. unix:///var/run/redis.sock")
        if parts.scheme != "unix" and not parts.hostname:
            raise ValueError("redis:// URL needs a host, e.g. redis://localhost:6379/0")
        return v

    @field_validator("store_url")
    @classmethod
    def _check_store_url(cls, v: str | None) -> str | None:
        if v is None or v == "":
            return None
        if v.startswith("/"):
            return v
        parts = urlsplit(v)
        if parts.scheme == "file" and parts.path:
            return v
        if parts.scheme == "s3" and parts.netloc:
            return v
        raise ValueError(f"must be file:///path, /path or s3://bucket/prefix, got {v!r}")

    # --- resolved values --------------------------------------------------------------------------
    @property
    def effective_redis_url(self) -> str:
        """The Redis URL to use: ``redis_url`` or the embedded server's socket in ``data_dir``."""
        if self.redis_url:
            return self.redis_url
        return f"unix://{(self.data_dir / EMBEDDED_SOCKET_NAME).expanduser().resolve()}"

    @property
    def effective_store_url(self) -> str:
        """The object store URL to use: ``store_url`` or ``<data_dir>/store``."""
        if self.store_url:
            return self.store_url
        return (self.data_dir / 'store').expanduser().resolve().as_uri()  # percent-encodes '%', spaces


@lru_cache(maxsize=1)
def get_settings() -> WorkerSettings:
    """The process's settings, read from the environment once."""
    return WorkerSettings()


def reset_settings_cache() -> None:
    """Forget the cached settings (tests that change the environment)."""
    get_settings.cache_clear()


def open_worker_store(settings: WorkerSettings | None = None) -> ObjectStore:
    """The object store named by the worker's settings (never by a job payload)."""
    return open_configured_store(settings or get_settings())
