"""Object storage: one small interface (``ObjectStore``), two backends.

``open_store("file:///srv/ibr")`` or ``open_store("/srv/ibr")`` -> :class:`LocalStore`
(the default; temp file + fsync + rename); ``open_store("s3://bucket/prefix",
endpoint_url=..., access_key=..., ...)`` -> :class:`S3Store`. What lives under which key
(blobs, scenes, artifacts) is decided in ``producer.artifacts``, not here.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol
from urllib.parse import unquote, urlsplit

from producer.store.base import (
    DEFAULT_CHUNK,
    MAX_KEY_LENGTH,
    ChecksumMismatch,
    NotFound,
    ObjectStore,
    StoreError,
    StoreUnavailable,
    is_valid_key,
    validate_key,
    validate_prefix,
)
from producer.store.local import LocalStore

if TYPE_CHECKING:
    from producer.store.s3 import S3Store

__all__ = [
    "DEFAULT_CHUNK",
    "MAX_KEY_LENGTH",
    "ChecksumMismatch",
    "LocalStore",
    "NotFound",
    "ObjectStore",
    "S3Store",
    "StoreError",
    "StoreUnavailable",
    "is_valid_key",
    "open_configured_store",
    "open_store",
    "validate_key",
    "validate_prefix",
]


def __getattr__(name: str) -> Any:
    # boto3 takes a noticeable time to import: only pay for it when S3 is used.
    if name == "S3Store":
        from producer.store.s3 import S3Store  # deferred on purpose: boto3 is slow to import

        return S3Store
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def open_store(url: str, **s3_kwargs: Any) -> ObjectStore:
    """The store a URL names.

    - ``file:///abs/path`` (or ``file://localhost/abs/path``) or a plain path -> LocalStore;
    - ``s3://bucket`` or ``s3://bucket/some/prefix`` -> S3Store(bucket, prefix=..., **s3_kwargs)
      (``endpoint_url``, ``region``, ``access_key``, ``secret_key``, ... as the caller's
      settings give them).

    ``s3_kwargs`` are ignored for a local store, so a caller can always pass its S3
    settings whatever the URL. Any other scheme raises ValueError.
    """
    if not url:
        raise ValueError("store URL is empty")
    parts = urlsplit(url)
    scheme = parts.scheme.lower()
    if scheme == "" or (len(scheme) == 1 and url[1:2] == ":"):  # a plain path (or a Windows drive)
        return LocalStore(Path(url))
    if scheme == "file":
        if parts.netloc not in ("", "localhost"):
            raise ValueError(f"file URL {url!r} names a remote host; use file:///absolute/path")
        path = unquote(parts.path)
        if not path.startswith("/"):
            raise ValueError(f"file URL {url!r} must hold an absolute path (file:///abs/path)")
        return LocalStore(Path(path))
    if scheme == "s3":
        if not parts.netloc:
            raise ValueError(f"S3 URL {url!r} has no bucket (s3://bucket/prefix)")
        from producer.store.s3 import S3Store  # deferred on purpose: boto3 is slow to import

        return S3Store(parts.netloc, prefix=unquote(parts.path).strip("/"), **s3_kwargs)
    raise ValueError(f"unsupported store URL scheme {parts.scheme!r} in {url!r} (use file:// or s3://)")


class _SecretLike(Protocol):
    def get_secret_value(self) -> str: ...


class StoreSettings(Protocol):
    """The store fields of ``producer.settings.Settings`` (a protocol, so the store needs no settings import)."""

    @property
    def effective_store_url(self) -> str: ...
    @property
    def s3_endpoint_url(self) -> str | None: ...
    @property
    def s3_region(self) -> str | None: ...
    @property
    def s3_access_key(self) -> str | None: ...
    @property
    def s3_secret_key(self) -> _SecretLike | None: ...


def open_configured_store(settings: StoreSettings) -> ObjectStore:
    """The store a process's settings name (the S3 fields are ignored for a local store)."""
    secret = settings.s3_secret_key
    return open_store(settings.effective_store_url, endpoint_url=settings.s3_endpoint_url,
                      region=settings.s3_region, access_key=settings.s3_access_key,
                      secret_key=secret.get_secret_value() if secret is not None else None)
