"""Service settings: one ``Settings`` object read from ``IBR_*`` environment variables.

Bad values fail at start-up (``create_app`` builds the settings before serving), with a
message naming the variable, instead of surfacing as 500s on the first request.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Any

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

__all__ = ["Settings", "get_settings"]

_SHA256_HEX = re.compile(r"^[0-9a-f]{64}$")
_MIB = 1 << 20


def _split_list(value: Any) -> Any:
    """Accept a JSON list or a comma / whitespace separated string (env friendly)."""
    if isinstance(value, str):
        text = value.strip()
        if text.startswith("["):
            import json

            try:
                return json.loads(text)
            except json.JSONDecodeError as exc:
                raise ValueError(f"not a JSON list: {exc.msg}") from exc
        return [part for part in re.split(r"[,\s]+", text) if part]
    return value


class Settings(BaseSettings):
    """Configuration of the HTTP API process (environment prefix ``IBR_``)."""

    model_config = SettingsConfigDict(env_prefix="IBR_", extra="forbid", frozen=True)

    redis_url: str | None = None
    """``redis://``, ``rediss://`` or ``unix://`` URL; None = the embedded server's socket
    ``<data_dir>/redis.sock`` (started by ``ibr up``), as for the workers."""
    store_url: str | None = None
    """``file:///path``, ``/path`` or ``s3://bucket/prefix``; None = ``<data_dir>/store``."""
    s3_endpoint_url: str | None = None
    s3_access_key: str | None = None
    s3_secret_key: SecretStr | None = None
    s3_region: str | None = None
    data_dir: Path = Field(default_factory=lambda: Path.home() / ".ibr")
    """Local state: the default object store and the embedded Redis socket."""
    api_keys: Annotated[list[str], NoDecode] = []
    """SHA-256 hex digests of the accepted API keys; empty turns authentication off."""
    max_body_bytes: Annotated[int, Field(ge=1024)] = 64 * _MIB
    """Largest request body, enforced while streaming (413 beyond it)."""
    max_upload_bytes: Annotated[int, Field(ge=1)] = 32 * _MIB
    """Largest single uploaded file in a multipart request."""
    max_upload_files: Annotated[int, Field(ge=1, le=10_000)] = 256
    """Most file parts in one multipart request."""
    max_image_pixels: Annotated[int, Field(ge=1)] = 64_000_000
    """Largest width * height accepted in a render request."""
    rate_limit_per_minute: Annotated[int, Field(ge=0)] = 0
    """Requests per minute per API key (per client address when auth is off); 0 = no limit."""
    rate_limit_burst: Annotated[int, Field(ge=0)] = 0
    """Token-bucket capacity; 0 = same as ``rate_limit_per_minute``."""
    cors_origins: Annotated[list[str], NoDecode] = []
    """Origins allowed by CORS (``*`` for any); empty = no CORS headers."""
    log_level: str = "INFO"
    log_json: bool = True

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
    def _redis(cls, value: str | None) -> str | None:
        if value is not None and not value.startswith(("redis://", "rediss://", "unix://")):
            raise ValueError("must start with redis://, rediss:// or unix://")
        return value

    @field_validator("store_url")
    @classmethod
    def _store(cls, value: str | None) -> str | None:
        if value is None:
            return None
        if value.startswith("s3://"):
            if len(value) <= len("s3://") or value[len("s3://")] == "/":
                raise ValueError("s3:// URL needs a bucket: s3://bucket/prefix")
        elif not (value.startswith("file://") or value.startswith("/")):
            raise ValueError("must be file:///absolute/path, /absolute/path or s3://bucket/prefix")
        return value

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

    @property
    def auth_enabled(self) -> bool:
        return bool(self.api_keys)

    @property
    def effective_redis_url(self) -> str:
        if self.redis_url:
            return self.redis_url
        return f"unix://{(self.data_dir / 'redis.sock').expanduser().resolve()}"

    @property
    def effective_store_url(self) -> str:
        if self.store_url:
            return self.store_url
        return (self.data_dir / 'store').expanduser().resolve().as_uri()  # percent-encodes '%', spaces


def get_settings() -> Settings:
    """Settings from the environment; raises ``SystemExit`` with a readable message when invalid."""
    from pydantic import ValidationError

    try:
        return Settings()
    except ValidationError as exc:
        lines = []
        for err in exc.errors(include_url=False):
            name = "IBR_" + ".".join(str(p) for p in err["loc"][:1]).upper() if err["loc"] else "settings"
            lines.append(f"  {name}: {err['msg']}")
        raise SystemExit("invalid configuration:\n" + "\n".join(lines)) from None
