"""API keys and per-key rate limits.

Keys are configured as SHA-256 hex digests (``IBR_API_KEYS``), so the configuration
never holds a usable secret. A request presents ``Authorization: Bearer <key>``; the
key is hashed and compared against every configured digest with
``hmac.compare_digest`` (no early exit, so timing does not reveal which digest
matched how far). The owner of everything a key creates is the first 16 hex
characters of its digest.

The rate limiter is a token bucket per client kept in Redis (:class:`RateLimiter`), updated by
one Lua script per request, so every API replica draws from the same bucket: N replicas allow
the configured rate, not N times it. Requests with a missing or wrong key are limited too, by
client address, before the 401.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
import math
import time
from collections.abc import Callable, Sequence
from typing import Any

from redis.exceptions import ConnectionError as RedisConnectionError
from redis.exceptions import TimeoutError as RedisTimeoutError

__all__ = ["AuthError", "KeyRing", "RateLimited", "RateLimiter", "hash_key", "owner_of"]

OWNER_HEX_CHARS = 16
REDIS_ERRORS = (RedisConnectionError, RedisTimeoutError, OSError)
log = logging.getLogger(__name__)


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


_TAKE_TOKEN = """
local rate = tonumber(ARGV[1])
local capacity = tonumber(ARGV[2])
local now = tonumber(ARGV[3])
local b = redis.call('HMGET', KEYS[1], 'tokens', 'updated')
local tokens = tonumber(b[1]) or capacity
local updated = tonumber(b[2]) or now
tokens = math.min(capacity, tokens + math.max(0, now - updated) * rate)
local wait = 0
if tokens >= 1 then tokens = tokens - 1 else wait = (1 - tokens) / rate end
redis.call('HSET', KEYS[1], 'tokens', tostring(tokens), 'updated', tostring(math.max(now, updated)))
redis.call('EXPIRE', KEYS[1], math.ceil(capacity / rate) + 60)
return tostring(wait)
"""
"""Refill by the time since the bucket's last update, take one token or say how long until there is
one; atomic in Redis, so concurrent requests on any replica see one bucket. The key expires once it
would be full again (an absent bucket is a full one)."""


class RateLimiter:
    """Token bucket per client id, shared through Redis: ``per_minute`` tokens per minute, ``burst``
    capacity. ``redis``: a callable giving the connection (the app's), so that tests and the app build
    it the same way; ``clock``: seconds (wall clock, comparable across replicas). Redis unreachable:
    the request is let through (the limiter must not turn a Redis outage into 429s; ``/readyz``
    reports the outage)."""

    KEY_PREFIX = "ibr:rate:"

    def __init__(
        self,
        per_minute: int,
        burst: int = 0,
        redis: Callable[[], Any] | None = None,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.per_minute = per_minute
        self.capacity = float(burst or per_minute)
        self.rate = per_minute / 60.0
        self._redis = redis
        self._clock = clock
        self._script: Any = None

    @property
    def enabled(self) -> bool:
        return self.per_minute > 0 and self._redis is not None

    def hit(self, client: str) -> None:
        """Take one token for ``client`` or raise RateLimited."""
        if not self.enabled:
            return
        assert self._redis is not None
        conn = self._redis()
        try:
            if self._script is None:
                self._script = conn.register_script(_TAKE_TOKEN)
            wait = float(self._script(keys=[self.KEY_PREFIX + client],
                                      args=[self.rate, self.capacity, self._clock()], client=conn))
        except REDIS_ERRORS as exc:
            log.warning("rate limit not applied, Redis unreachable: %s", exc)
            return
        if wait > 0:
            raise RateLimited(max(1.0, math.ceil(wait)))
