"""The object-store interface: errors, the ``ObjectStore`` protocol and key validation.

Keys are produced by our own code (``blobs/<sha256>``, ``scenes/<id>.json``,
``artifacts/<key>/<name>``); user-supplied names never become keys. They are still
validated here, in this one place, by every backend before any I/O, so that a bug can
never turn into a write outside the store's root (local) or prefix (S3).
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from typing import Protocol, runtime_checkable

__all__ = [
    "DEFAULT_CHUNK",
    "MAX_KEY_LENGTH",
    "ChecksumMismatch",
    "NotFound",
    "ObjectStore",
    "StoreError",
    "StoreUnavailable",
    "is_valid_key",
    "validate_key",
    "validate_prefix",
]

_Keys = list[str]
"""(A name of the type: inside the classes ``list`` is the method.)"""

MAX_KEY_LENGTH = 1024
DEFAULT_CHUNK = 1 << 20

_KEY_CHARS = re.compile(r"[A-Za-z0-9._/-]+")


class StoreError(Exception):
    """Base of every error the object store raises on purpose."""


class NotFound(StoreError):
    """No object at that key (or, for artifacts and scenes, no committed record)."""


class StoreUnavailable(StoreError):
    """Network, credential, permission or disk trouble: retry later (HTTP 503)."""


class ChecksumMismatch(StoreError):
    """Stored bytes do not match their recorded checksum (or a record is unreadable).

    The bytes are never returned; the record that vouched for them is removed so the
    artifact is recomputed (see ``producer.artifacts``)."""


def _segments_problem(text: str, what: str) -> str | None:
    if not text:
        return f"{what} must not be empty"
    if len(text) > MAX_KEY_LENGTH:
        return f"{what} is {len(text)} characters long, over the {MAX_KEY_LENGTH} limit"
    if _KEY_CHARS.fullmatch(text) is None:
        return f"{what} may only contain [A-Za-z0-9._/-]"
    if text.startswith("/"):
        return f"{what} must be relative (it starts with '/')"
    for segment in text.split("/"):
        if segment == "":
            return f"{what} must not have empty segments ('//' or a trailing '/')"
        if segment in (".", ".."):
            return f"{what} must not have '.' or '..' segments"
    return None


def validate_key(key: str) -> str:
    """Return ``key`` unchanged if it is a valid object key, else raise ValueError.

    Valid: relative, characters ``[A-Za-z0-9._/-]``, '/'-separated segments that are
    neither empty nor '.' / '..', at most 1024 characters."""
    if not isinstance(key, str):
        raise ValueError(f"object key must be a str, not {type(key).__name__}")
    problem = _segments_problem(key, "object key")
    if problem is not None:
        raise ValueError(f"invalid object key {key!r}: {problem}")
    return key


def validate_prefix(prefix: str) -> str:
    """Validate a listing prefix: '' (everything) or a key, optionally ending in '/'.

    Listing is by string prefix, so ``"artifacts/ab"`` lists every key starting with it."""
    if not isinstance(prefix, str):
        raise ValueError(f"prefix must be a str, not {type(prefix).__name__}")
    if prefix == "":
        return prefix
    body = prefix[:-1] if prefix.endswith("/") else prefix
    problem = _segments_problem(body, "prefix")
    if problem is not None:
        raise ValueError(f"invalid prefix {prefix!r}: {problem}")
    return prefix


def is_valid_key(key: str) -> bool:
    """True when :func:`validate_key` would accept ``key`` (used to skip foreign names)."""
    return isinstance(key, str) and _segments_problem(key, "key") is None


@runtime_checkable
class ObjectStore(Protocol):
    """A flat key -> bytes store. Every write is atomic: readers see the old object, the
    new one or nothing, never a partial object. Methods raise ``ValueError`` for an
    invalid key, ``NotFound`` for a missing object and ``StoreUnavailable`` when the
    backend cannot be reached or written."""

    def put_bytes(self, key: str, data: bytes, content_type: str = "application/octet-stream") -> None:
        """Write (or atomically replace) the object at ``key``."""
        ...

    def get_bytes(self, key: str) -> bytes:
        """The object's bytes; NotFound when absent."""
        ...

    def exists(self, key: str) -> bool:
        """True when an object is stored at ``key``."""
        ...

    def delete(self, key: str) -> None:
        """Remove the object; deleting a missing key is not an error."""
        ...

    def list(self, prefix: str) -> list[str]:
        """Keys starting with ``prefix`` (string prefix), sorted."""
        ...

    def list_page(self, prefix: str, start_after: str = "", limit: int = 1000) -> _Keys:
        """At most ``limit`` keys of ``list(prefix)`` that sort after ``start_after``, sorted: one
        page of a listing that keeps its position in the key (an index of small objects)."""
        ...

    def open_stream(self, key: str, chunk: int = DEFAULT_CHUNK) -> Iterator[bytes]:
        """Chunks of the object, for large downloads. NotFound is raised by this call
        (before any chunk), so a caller can answer 404 before it starts a response."""
        ...

    def check(self) -> None:
        """Readiness probe: return if the store can be read and written, else raise
        StoreUnavailable."""
        ...
