"""Object store in an S3 bucket (AWS, MinIO, Ceph, moto, ... : any endpoint).

Configuration is explicit: the caller passes endpoint, region and credentials (from the
service settings); this class never looks them up itself. boto3 still reads its config
file for settings we do not pin, so everything that matters is pinned here: endpoint
(``ignore_configured_endpoint_urls``), region, credentials (anonymous unless given, or
the default chain only with ``use_default_credentials=True``), retries, timeouts,
addressing style, checksum behaviour.

Failure policy: an unreachable or misbehaving endpoint raises ``StoreUnavailable``
quickly (short connect / read timeouts, few attempts); a missing object raises
``NotFound``. A PUT is atomic in S3 (the object appears whole or not at all) and carries
a Content-MD5 the server checks, so nothing half-written can appear.
"""

from __future__ import annotations

import base64
import hashlib
import re
import threading
from collections.abc import Iterator
from typing import Any

import boto3  # type: ignore[import-untyped]
import urllib3.exceptions
from botocore import UNSIGNED  # type: ignore[import-untyped]
from botocore.config import Config  # type: ignore[import-untyped]
from botocore.exceptions import BotoCoreError, ClientError  # type: ignore[import-untyped]

from producer.store.base import (
    DEFAULT_CHUNK,
    NotFound,
    StoreError,
    StoreUnavailable,
    is_valid_key,
    validate_key,
    validate_prefix,
)

__all__ = ["S3Store"]

_Keys = list[str]
"""(A name of the type: inside the classes ``list`` is the method.)"""

_BUCKET = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{1,254}")
_NOT_FOUND_CODES = frozenset({"NoSuchKey", "404", "NotFound"})
_UNAVAILABLE_CODES = frozenset(
    {
        "NoSuchBucket",
        "AccessDenied",
        "AllAccessDisabled",
        "InvalidAccessKeyId",
        "SignatureDoesNotMatch",
        "ExpiredToken",
        "InvalidToken",
        "TokenRefreshRequired",
        "RequestTimeout",
        "RequestTimeTooSkewed",
        "SlowDown",
        "ServiceUnavailable",
        "InternalError",
        "XMinioServerNotInitialized",
        "XMinioStorageFull",
    }
)
_TRANSPORT_ERRORS = (BotoCoreError, urllib3.exceptions.HTTPError, OSError)

_session_lock = threading.Lock()
_session: Any = None


def _new_client(**kwargs: Any) -> Any:
    """An S3 client from one shared boto3 session (it caches the service model, so a
    client costs milliseconds instead of ~100 ms). Sessions are not thread-safe: lock.
    Clients are, and each store has its own (credentials are per client)."""
    global _session
    with _session_lock:
        if _session is None:
            _session = boto3.session.Session()
        return _session.client("s3", **kwargs)


class S3Store:
    """Objects in ``bucket`` under ``prefix`` (key ``a/b`` -> object ``<prefix>/a/b``).

    ``endpoint_url`` selects a non-AWS server (``http://minio:9000``); path-style
    addressing is used whenever an endpoint is given (MinIO and most self-hosted servers
    need it). Without ``access_key``/``secret_key`` requests are anonymous unless
    ``use_default_credentials`` asks for boto3's default chain (env, files, IAM role).
    """

    list_page_size = 1000
    """Keys per ListObjectsV2 request (the S3 maximum)."""

    def __init__(
        self,
        bucket: str,
        endpoint_url: str | None = None,
        region: str | None = None,
        access_key: str | None = None,
        secret_key: str | None = None,
        prefix: str = "",
        *,
        session_token: str | None = None,
        use_default_credentials: bool = False,
        connect_timeout: float = 2.0,
        read_timeout: float = 10.0,
        max_attempts: int = 2,
        addressing_style: str | None = None,
        verify: bool | str | None = None,
    ) -> None:
        if _BUCKET.fullmatch(bucket) is None:
            raise ValueError(f"invalid bucket name {bucket!r}")
        if (access_key is None) != (secret_key is None):
            raise ValueError("give both access_key and secret_key, or neither")
        if max_attempts < 1:
            raise ValueError("max_attempts must be >= 1")
        prefix = prefix.strip("/")
        if prefix:
            validate_key(prefix)
            prefix += "/"
        self.bucket = bucket
        self.prefix = prefix
        self.endpoint_url = endpoint_url
        signed = access_key is not None or use_default_credentials
        config = Config(
            connect_timeout=connect_timeout,
            read_timeout=read_timeout,
            retries={"total_max_attempts": max_attempts, "mode": "standard"},
            s3={"addressing_style": addressing_style or ("path" if endpoint_url else "auto")},
            ignore_configured_endpoint_urls=True,
            # Newer botocore adds CRC checksums by default, which some S3-compatible
            # servers reject; we send Content-MD5 ourselves and verify sha256 on read.
            request_checksum_calculation="when_required",
            response_checksum_validation="when_required",
            signature_version=None if signed else UNSIGNED,
        )
        self._client: Any = _new_client(
            endpoint_url=endpoint_url,
            config=config,
            verify=verify,
            region_name=region or "us-east-1",
            aws_access_key_id=access_key,
            aws_secret_access_key=secret_key,
            aws_session_token=session_token,
        )

    def __repr__(self) -> str:
        where = f" at {self.endpoint_url}" if self.endpoint_url else ""
        return f"S3Store({self.url!r}{where})"

    @property
    def url(self) -> str:
        return f"s3://{self.bucket}/{self.prefix}"

    # ------------------------------------------------------------------ helpers

    def _key(self, key: str) -> str:
        return self.prefix + validate_key(key)

    def _error(self, exc: Exception, what: str, key: str = "") -> StoreError:
        if isinstance(exc, ClientError):
            err = exc.response.get("Error", {})
            code = str(err.get("Code", ""))
            status = int(exc.response.get("ResponseMetadata", {}).get("HTTPStatusCode", 0) or 0)
            if code in _NOT_FOUND_CODES:
                return NotFound(key or what)
            if code in _UNAVAILABLE_CODES or status >= 500 or status in (401, 403, 429):
                return StoreUnavailable(f"s3 {self.bucket}: {what}: {code or status} {err.get('Message', '')}".rstrip())
            return StoreError(f"s3 {self.bucket}: {what}: {code or status} {err.get('Message', '')}".rstrip())
        return StoreUnavailable(f"s3 {self.bucket}: {what}: {exc}")

    def _get_object(self, key: str) -> Any:
        try:
            return self._client.get_object(Bucket=self.bucket, Key=self._key(key))
        except (ClientError, *_TRANSPORT_ERRORS) as exc:
            raise self._error(exc, f"cannot read {key}", key) from exc

    # ------------------------------------------------------------------ protocol

    def put_bytes(self, key: str, data: bytes, content_type: str = "application/octet-stream") -> None:
        k = self._key(key)
        body = bytes(data)
        md5 = base64.b64encode(hashlib.md5(body, usedforsecurity=False).digest()).decode("ascii")
        try:
            self._client.put_object(Bucket=self.bucket, Key=k, Body=body, ContentType=content_type, ContentMD5=md5)
        except (ClientError, *_TRANSPORT_ERRORS) as exc:
            raise self._error(exc, f"cannot write {key}") from exc

    def get_bytes(self, key: str) -> bytes:
        body = self._get_object(key)["Body"]
        try:
            data: bytes = body.read()
        except _TRANSPORT_ERRORS as exc:
            raise self._error(exc, f"cannot read {key}") from exc
        finally:
            body.close()
        return data

    def exists(self, key: str) -> bool:
        try:
            self._client.head_object(Bucket=self.bucket, Key=self._key(key))
        except (ClientError, *_TRANSPORT_ERRORS) as exc:
            err = self._error(exc, f"cannot stat {key}", key)
            if isinstance(err, NotFound):
                return False
            raise err from exc
        return True

    def delete(self, key: str) -> None:
        try:
            self._client.delete_object(Bucket=self.bucket, Key=self._key(key))
        except (ClientError, *_TRANSPORT_ERRORS) as exc:
            err = self._error(exc, f"cannot delete {key}", key)
            if isinstance(err, NotFound):
                return
            raise err from exc

    def list(self, prefix: str) -> list[str]:
        validate_prefix(prefix)
        keys: list[str] = []
        try:
            pages = self._client.get_paginator("list_objects_v2").paginate(
                Bucket=self.bucket, Prefix=self.prefix + prefix, PaginationConfig={"PageSize": self.list_page_size}
            )
            for page in pages:
                for item in page.get("Contents", []):
                    key = str(item["Key"])[len(self.prefix) :]
                    if is_valid_key(key):
                        keys.append(key)
        except (ClientError, *_TRANSPORT_ERRORS) as exc:
            raise self._error(exc, f"cannot list {prefix!r}") from exc
        keys.sort()
        return keys

    def list_page(self, prefix: str, start_after: str = "", limit: int = 1000) -> _Keys:
        if limit < 1:
            raise ValueError(f"limit must be positive, got {limit}")
        validate_prefix(prefix)
        keys: list[str] = []
        after = self.prefix + start_after if start_after > prefix else ""
        try:
            while len(keys) < limit:  # S3 lists in key order: one request per page, unless keys are skipped
                args: dict[str, Any] = {"Bucket": self.bucket, "Prefix": self.prefix + prefix,
                                        "MaxKeys": min(self.list_page_size, limit - len(keys))}
                if after:
                    args["StartAfter"] = after
                page = self._client.list_objects_v2(**args)
                contents = page.get("Contents", [])
                for item in contents:
                    key = str(item["Key"])[len(self.prefix):]
                    if is_valid_key(key):
                        keys.append(key)
                if not contents or not page.get("IsTruncated"):
                    break
                after = str(contents[-1]["Key"])
        except (ClientError, *_TRANSPORT_ERRORS) as exc:
            raise self._error(exc, f"cannot list {prefix!r}") from exc
        return sorted(keys)[:limit]

    def open_stream(self, key: str, chunk: int = DEFAULT_CHUNK) -> Iterator[bytes]:
        if chunk <= 0:
            raise ValueError(f"chunk must be positive, got {chunk}")
        return self._iter_body(self._get_object(key)["Body"], key, chunk)

    def _iter_body(self, body: Any, key: str, chunk: int) -> Iterator[bytes]:
        try:
            chunks = body.iter_chunks(chunk)
            while True:
                try:
                    block = next(chunks)
                except StopIteration:
                    return
                except _TRANSPORT_ERRORS as exc:
                    raise self._error(exc, f"cannot read {key}") from exc
                yield block
        finally:
            body.close()

    def check(self) -> None:
        try:
            self._client.head_bucket(Bucket=self.bucket)
        except (ClientError, *_TRANSPORT_ERRORS) as exc:
            err = self._error(exc, "bucket not reachable")
            if isinstance(err, NotFound):  # head_bucket answers a bare 404 for a missing bucket
                err = StoreUnavailable(f"s3 {self.bucket}: bucket does not exist")
            if not isinstance(err, StoreUnavailable):
                err = StoreUnavailable(str(err))
            raise err from exc
