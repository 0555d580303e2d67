"""The one settings class of every process (API, workers, ``ibr up``): ``IBR_*`` environment variables.

Every variable has the prefix ``IBR_`` (``IBR_REDIS_URL``, ``IBR_STORE_URL``, ...), read
case-insensitively. Settings are validated when a process starts, with a message naming the
variable (``create_app`` and ``python -m workers.runner`` read them before serving), never in the
middle of a request or a job. Worker code reads the environment only through :func:`get_settings`.

Defaults follow the embedded mode of ``ibr up``: with no ``IBR_REDIS_URL`` every process talks to
the embedded Redis on ``unix://<data_dir>/redis.sock`` and, with no ``IBR_STORE_URL``, stores
objects under ``<data_dir>/store``. ``data_dir`` defaults to ``~/.ibr``.
"""

from __future__ import annotations

import json
import re
from functools import lru_cache
from pathlib import Path
from typing import Annotated, Any
from urllib.parse import urlsplit

from pydantic import Field, SecretStr, ValidationError, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from producer.store import ObjectStore, open_configured_store

__all__ = [
    "EMBEDDED_SOCKET_NAME",
    "Settings",
    "get_settings",
    "load_settings",
    "open_settings_store",
    "reset_settings_cache",
    "settings_error_text",
]

EMBEDDED_SOCKET_NAME = "redis.sock"
"""File name of the embedded Redis unix socket inside ``data_dir`` (see producer/embedded.py)."""

_SHA256_HEX = re.compile(r"^[0-9a-f]{64}$")
_MIB = 1 << 20


def _split_list(value: Any) -> Any:
    """Accept a JSON list or a comma / whitespace separated string (env friendly)."""
    if isinstance(value, str):
        text = value.strip()
        if text.startswith("["):
            try:
                return json.loads(text)
            except json.JSONDecodeError as exc:
                raise ValueError(f"not a JSON list: {exc.msg}") from exc
        return [part for part in re.split(r"[,\s]+", text) if part]
    return value


class Settings(BaseSettings):
    """Configuration of the service's processes (environment variables ``IBR_<FIELD>``)."""

    model_config = SettingsConfigDict(env_prefix="IBR_", extra="forbid", frozen=True)

    # --- shared: where state lives ----------------------------------------------------------------
    data_dir: Path = Field(default_factory=lambda: Path.home() / ".ibr")
    """Data directory: the embedded Redis socket and files, the default local object store."""
    redis_url: str | None = None
    """``redis://``, ``rediss://`` or ``unix://`` URL; None = the embedded server's socket
    ``<data_dir>/redis.sock`` (started by ``ibr up``)."""
    store_url: str | None = None
    """``file:///path``, ``/path`` or ``s3://bucket/prefix``; None = ``<data_dir>/store``."""
    s3_endpoint_url: str | None = None
    """S3 endpoint for ``s3://`` store URLs (MinIO, moto); None = AWS."""
    s3_region: str | None = None
    s3_access_key: str | None = None
    s3_secret_key: SecretStr | None = None
    store_temp_grace_s: Annotated[float, Field(gt=0)] = 3600.0
    """A local store's temp file (a write in progress) older than this is the leftover of a killed
    writer and is removed by the store upkeep (``producer.upkeep``): longer than any one write."""
    store_upkeep_interval_s: Annotated[float, Field(ge=0)] = 3600.0
    """How often the API runs the store upkeep after the one at start-up; 0 = only at start-up."""

    # --- the HTTP API -------------------------------------------------------------------------------
    api_keys: Annotated[list[str], NoDecode] = []
    """SHA-256 hex digests of the accepted API keys; empty turns authentication off."""
    max_body_bytes: Annotated[int, Field(ge=1024)] = 64 * _MIB
    """Largest request body, enforced while streaming (413 beyond it)."""
    max_json_bytes: Annotated[int, Field(ge=1024)] = 8 * _MIB
    """Largest JSON document in a request: a JSON body (a scene, a batch, a manifest, ...) or the
    ``scene``, ``batch`` or ``manifest`` part of a multipart one, enforced while streaming (413 beyond
    it; the smaller of this and ``max_body_bytes`` applies). Parsing holds about 25-30x the document's
    size in Python objects (inline mesh vertices: a 20 MiB scene peaks at 552 MiB in the API, a
    48 MiB one at 1.15 GiB, docs/reliability.md), so large meshes go as PLY/OBJ file parts, which
    are parsed into compact arrays."""
    max_upload_bytes: Annotated[int, Field(ge=1)] = 32 * _MIB
    """Largest single uploaded file in a multipart request."""
    max_upload_files: Annotated[int, Field(ge=1, le=10_000)] = 256
    """Most file parts in one multipart request."""
    max_image_pixels: Annotated[int, Field(ge=1)] = 64_000_000
    """Largest width * height accepted in a render request."""
    max_decoded_image_bytes: Annotated[int, Field(ge=1024)] = 256 * _MIB
    """Largest uploaded image the API decodes, as width * height * channels * 4 bytes (float32),
    read from the header before any pixel is decoded (422 beyond it): a few KiB of compressed PNG
    or EXR can declare gigabytes of pixels."""
    max_concurrent_decodes: Annotated[int, Field(ge=1, le=64)] = 2
    """Uploaded images the API process validates at once (each holds up to
    ``max_decoded_image_bytes``); further uploads wait for a slot, 503 after 30 s."""
    max_render_bytes: Annotated[int, Field(ge=_MIB)] = 6 << 30
    """Largest estimated peak memory of one job (a render, a relight, a composite, a walkthrough bake or
    frame chunk, a dataset generation or bake, a calibration, a verification: every job but the parts of
    a scene bake; ``producer.costs``, from the image size, the method, the samples per pixel and the
    scene's triangles): a request over it is refused with 422 naming the estimate and the limit before
    it is queued. 6 GiB: a reference render of about 4200 x 4200 at
    the default samples, an LDC render of about 5200 x 5200."""
    max_render_cpu_s: Annotated[float, Field(gt=0)] = 1200.0
    """Largest estimated CPU time (seconds of one core, ``producer.costs``) of one job on the render
    queue: over it the request is refused with 422 naming the estimate and the limit. 1200: the render
    job's 600 s timeout with both cores of this project's machine busy for it; a job estimated above it
    would most likely be killed by its timeout."""
    max_scene_triangles: Annotated[int, Field(ge=1)] = 8_000_000
    """Most triangles of one scene after tessellation (spheres, cylinders, planes, disks, inline meshes
    and mesh files), counted from the document and the mesh files' headers before anything is built:
    a scene over it is refused with 422 when it is stored, and every job of a stored scene over it
    (a limit lowered later) is refused. 8 M triangles: ~4.2 GiB for the built scene and its BVH."""
    max_bake_job_cpu_s: Annotated[float, Field(gt=0)] = 3600.0
    """Largest estimated CPU time (seconds of one core) of one job on the bake queue (a scene bake part,
    a dataset generation or bake, a walkthrough bake, a calibration): the bake jobs' timeout (3600 s)."""
    contract_error_margin: Annotated[float, Field(gt=0, le=1)] = 0.85
    """Quality contracts are planned for ``max_error`` times this (``engine.quality.plan``) for the
    settings of a model calibrated before its fits carried their own margins (calibrated from the
    probe views' spread: ``engine.quality.calibrated_margin``, used instead when present): the error
    model holds for the probe views, and a view a little noisier than them would otherwise miss a
    target that sits just above a prediction. 1: no margin; lower: more contracts met, at a higher cost."""
    contract_time_margin: Annotated[float, Field(gt=0, le=1)] = 0.7
    """Quality contracts are planned for ``max_ms`` times this: the time model is fitted when the
    calibration runs, and a worker busier than it was then renders slower (~1.6x measured on the shared
    2-core machine). 1: no margin."""
    rate_limit_per_minute: Annotated[int, Field(ge=0)] = 0
    """Requests per minute per API key (per client address when auth is off); 0 = no limit."""
    rate_limit_burst: Annotated[int, Field(ge=0)] = 0
    """Token-bucket capacity; 0 = same as ``rate_limit_per_minute``."""
    cors_origins: Annotated[list[str], NoDecode] = []
    """Origins allowed by CORS (``*`` for any); empty = no CORS headers."""
    log_level: str = "INFO"
    log_json: bool = True

    # --- workers (the runner's command-line flags override the RQ tuning) ----------------------------
    cache_bytes: Annotated[int, Field(gt=0)] = 2 << 30
    """Byte budget of the render worker's LRU of loaded scenes / warm renderers (default 2 GiB)."""
    maintenance_interval_s: Annotated[int, Field(ge=1, le=3600)] = 30
    """How often a worker cleans its queue's registries (abandoned 'started' jobs)."""
    job_monitoring_interval_s: Annotated[int, Field(ge=1, le=600)] = 10
    """How often a busy worker refreshes the heartbeat of its running job."""
    heartbeat_grace_s: Annotated[int, Field(ge=1, le=3600)] = 20
    """A running job whose heartbeat is older than ``job_monitoring_interval_s + heartbeat_grace_s``
    counts as abandoned (its worker died) and is retried or failed by the next maintenance pass."""
    worker_ttl_s: Annotated[int, Field(ge=15, le=86400)] = 420
    """TTL of the worker's own registration key (RQ's default); refreshed while the worker lives."""
    worker_warmup: bool = True
    """Render workers: run ``workers.warmup`` (every engine path of the render queue's jobs on tiny
    built-in data, so numba compiles or loads its kernels) in background processes while taking jobs,
    publishing per-method readiness (``GET /v1/methods``); ``--no-warmup`` overrides. Bake workers never
    warm up (their parent must not run a kernel before forking)."""
    max_bake_part_bytes: Annotated[int, Field(ge=_MIB)] = 2 << 30
    """Largest estimated memory of one job of a scene bake (an LDC axis at its worst case, an indirect
    chunk with its axis and path-tracing batch, an LLF chunk; the scene it builds included): the API
    refuses a bake over it (``producer.costs.bake_cost``), and the plan job checks it again on the
    built scene, before anything is baked."""
    max_bake_cpu_s: Annotated[float, Field(gt=0)] = 24 * 3600.0
    """Largest estimated CPU time of one bake (all its jobs on one core, dominated by the indirect
    pass): the plan job refuses a bake over it with the estimate and what to lower. 24 h."""
    bake_paths_per_s: Annotated[float, Field(gt=0)] = 8.0e5
    """Indirect paths one bake worker traces per second at 3 bounces, for the plan's time estimate:
    on this project's 2-core machine ~0.86 M per second of chunk job time and ~0.84 M per CPU second
    of the whole bake on the Cornell box with the fixed sampler (``bench/bake_scaling.py --gi``
    prints both; docs/scaling.md); the default rounds down. Set it to the deployment's own
    measurement."""
    malloc_keep_mib: Annotated[int, Field(ge=0, le=2047)] = 256
    """Freed memory (MiB) a worker keeps mapped for its next job instead of returning it to the
    kernel, and blocks up to 32 MiB served from the heap (``engine.memory.keep_freed_memory``):
    image-sized buffers are then reused, not page-faulted in anew by each render (LDC and reference
    renders alternating: ~1.2x faster each with it). 0: glibc's defaults."""

    @field_validator("api_keys", "cors_origins", mode="before")
    @classmethod
    def _lists(cls, value: Any) -> Any:
        return _split_list(value)

    @field_validator("api_keys")
    @classmethod
    def _hashes(cls, value: list[str]) -> list[str]:
        out: list[str] = []
        for i, h in enumerate(value):
            h = h.strip().lower()
            if not _SHA256_HEX.match(h):
                raise ValueError(
                    f"entry {i} is not a sha256 hex digest (64 hex characters); configure the hash of a key, "
                    "e.g. `printf %s \"$KEY\" | sha256sum`, never the key itself"
                )
            out.append(h)
        return out

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
        if parts.scheme == "s3" and parts.netloc and not parts.netloc.startswith("/"):
            return v
        raise ValueError(f"must be file:///absolute/path, /absolute/path or s3://bucket/prefix, got {v!r}")

    @field_validator("log_level")
    @classmethod
    def _level(cls, value: str) -> str:
        level = value.upper()
        if level not in {"DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"}:
            raise ValueError("must be one of DEBUG, INFO, WARNING, ERROR, CRITICAL")
        return level

    @model_validator(mode="after")
    def _consistent(self) -> Settings:
        if self.max_upload_bytes > self.max_body_bytes:
            raise ValueError(
                f"max_upload_bytes ({self.max_upload_bytes}) must not exceed max_body_bytes ({self.max_body_bytes})"
            )
        if (self.s3_access_key is None) != (self.s3_secret_key is None):
            raise ValueError("set both s3_access_key and s3_secret_key, or neither")
        return self

    # --- resolved values --------------------------------------------------------------------------
    @property
    def json_limit_bytes(self) -> int:
        """The JSON-document limit in force: ``max_json_bytes``, capped by ``max_body_bytes``."""
        return min(self.max_json_bytes, self.max_body_bytes)

    @property
    def auth_enabled(self) -> bool:
        return bool(self.api_keys)

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
        return (self.data_dir / "store").expanduser().resolve().as_uri()  # percent-encodes '%', spaces


def settings_error_text(exc: ValidationError) -> str:
    """One line per bad variable: ``  IBR_REDIS_URL: <what is wrong>``."""
    lines = []
    for err in exc.errors(include_url=False):
        name = "IBR_" + ".".join(str(p) for p in err["loc"][:1]).upper() if err["loc"] else "settings"
        lines.append(f"  {name}: {err['msg']}")
    return "\n".join(lines)


def load_settings() -> Settings:
    """Settings read from the environment now; raises ``SystemExit`` with a readable message when invalid."""
    try:
        return Settings()
    except ValidationError as exc:
        raise SystemExit("invalid configuration:\n" + settings_error_text(exc)) from None


@lru_cache(maxsize=1)
def get_settings() -> Settings:
    """The process's settings, read from the environment once (worker code: job functions)."""
    return Settings()


def reset_settings_cache() -> None:
    """Forget the cached settings (tests that change the environment)."""
    get_settings.cache_clear()


def open_settings_store(settings: Settings | None = None) -> ObjectStore:
    """The object store named by the process's settings (never by a job payload)."""
    return open_configured_store(settings or get_settings())
