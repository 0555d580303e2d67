"""API keys and per-key rate limits.

Keys are configured as SHA-256 hex digests (``IBR_API_KEYS``), so the configuration
never holds a usable secret. A request presents ``Authorization: Bearer <key>``; the
key is hashed and compared against every configured digest with
``hmac.compare_digest`` (no early exit, so timing does not reveal which digest
matched how far). The owner of everything a key creates is the first 16 hex
characters of its digest.

The rate limiter is an in-process token bucket: exact for one API process (the
default deployment); with N API replicas each enforces its own limit, so the
effective limit is N times the setting (a Redis bucket would be needed to share it).
"""

from __future__ import annotations

import hashlib
import hmac
import math
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass

__all__ = ["AuthError", "KeyRing", "RateLimited", "RateLimiter", "hash_key", "owner_of"]

OWNER_HEX_CHARS = 16


class AuthError(Exception):
    """Missing or wrong credentials (HTTP 401)."""

    def __init__(self, detail: str) -> None:
        super().__init__(detail)
        self.detail = detail


class RateLimited(Exception):
    """Over the request rate (HTTP 429)."""

    def __init__(self, retry_after_s: float) -> None:
        super().__init__(f"rate limit exceeded; retry after {retry_after_s:.1f} s")
        self.retry_after_s = retry_after_s


def hash_key(key: str) -> str:
    """SHA-256 hex digest of an API key (what ``IBR_API_KEYS`` lists)."""
    return hashlib.sha256(key.encode("utf-8", "surrogatepass")).hexdigest()


def owner_of(key_hash: str) -> str:
    return key_hash[:OWNER_HEX_CHARS]


class KeyRing:
    """The configured key digests."""

    def __init__(self, hashes: Sequence[str]) -> None:
        self._hashes = [h.lower() for h in hashes]

    @property
    def enabled(self) -> bool:
        return bool(self._hashes)

    def authenticate(self, authorization: str | None) -> str | None:
        """Owner id for an ``Authorization`` header value; None when auth is off.

        Raises AuthError when keys are configured and the header is missing, malformed
        or holds an unknown key."""
        if not self._hashes:
            return None
        if not authorization:
            raise AuthError("missing API key: send 'Authorization: Bearer <key>'")
        scheme, _, token = authorization.partition(" ")
        token = token.strip()
        if scheme.lower() != "bearer" or not token:
            raise AuthError("malformed Authorization header: expected 'Bearer <key>'")
        digest = hash_key(token).encode("ascii")
        match: str | None = None
        for h in self._hashes:  # compare with every digest: constant time in the match position
            if hmac.compare_digest(digest, h.encode("ascii")):
                match = h
        if match is None:
            raise AuthError("invalid API key")
        return owner_of(match)


@dataclass
class _Bucket:
    tokens: float
    updated: float


class RateLimiter:
    """Token bucket per client id: ``per_minute`` tokens per minute, ``burst`` capacity.

    Memory is bounded: the least recently seen buckets beyond ``max_clients`` are
    dropped (a dropped client simply starts with a full bucket)."""

    def __init__(
        self,
        per_minute: int,
        burst: int = 0,
        clock: Callable[[], float] = time.monotonic,
        max_clients: int = 100_000,
    ) -> None:
        self.per_minute = per_minute
        self.capacity = float(burst or per_minute)
        self.rate = per_minute / 60.0
        self._clock = clock
        self._max_clients = max_clients
        self._buckets: OrderedDict[str, _Bucket] = OrderedDict()
        self._lock = threading.Lock()

    @property
    def enabled(self) -> bool:
        return self.per_minute > 0

    def hit(self, client: str) -> None:
        """Take one token for ``client`` or raise RateLimited."""
        if not self.enabled:
            return
        now = self._clock()
        with self._lock:
            bucket = self._buckets.pop(client, None)
            if bucket is None:
                bucket = _Bucket(self.capacity, now)
            else:
                bucket.tokens = min(self.capacity, bucket.tokens + (now - bucket.updated) * self.rate)
                bucket.updated = now
            self._buckets[client] = bucket
            while len(self._buckets) > self._max_clients:
                self._buckets.popitem(last=False)
            if bucket.tokens >= 1.0:
                bucket.tokens -= 1.0
                return
            wait = (1.0 - bucket.tokens) / self.rate
        raise RateLimited(max(1.0, math.ceil(wait)))
