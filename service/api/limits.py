"""Request size limits, enforced while the body streams in.

Starlette and FastAPI read whatever a client sends (and spool multipart files to disk
without a cap), so a body limit has to sit below them: ``BodyLimitMiddleware`` is a
pure ASGI middleware that

* answers 413 at once when ``Content-Length`` already exceeds the limit (nothing read);
* otherwise counts the bytes of every ``http.request`` message as the application pulls
  them and raises ``BodyTooLarge`` (an ``HTTPException``, so FastAPI re-raises it instead
  of turning it into a 400) as soon as the count passes the limit: a chunked body, or a
  ``Content-Length`` that lies, is stopped after at most one extra chunk. Nothing is
  written to the store because every route reads the whole body before storing.

JSON documents get a smaller limit than the body (``max_json_bytes``): a JSON body becomes Python
objects of 25-30x its size when parsed, while a multipart body's files stay bytes.

``read_multipart`` parses ``multipart/form-data`` in memory with a per-part cap, so an
upload of one oversized mesh is refused while it streams, not after it hit the disk.
"""

from __future__ import annotations

import json
from dataclasses import dataclass

from python_multipart.exceptions import FormParserError
from python_multipart.multipart import MultipartParser, MultipartState, parse_options_header
from starlette.exceptions import HTTPException
from starlette.requests import Request
from starlette.types import ASGIApp, Message, Receive, Scope, Send

__all__ = [
    "JSON_ADVICE",
    "BodyLimitMiddleware",
    "BodyTooLarge",
    "MultipartError",
    "MultipartPart",
    "is_json_document",
    "read_multipart",
]


class BodyTooLarge(HTTPException):
    """The request body (or one part of it) is over a size limit: HTTP 413."""

    def __init__(self, detail: str, field: str = "") -> None:
        super().__init__(status_code=413, detail=detail, headers={"Connection": "close"})
        self.field = field


class MultipartError(ValueError):
    """A multipart body that cannot be parsed (HTTP 400)."""


def _problem_413(detail: str) -> bytes:
    return json.dumps(
        {"type": "about:blank", "title": "Request body too large", "status": 413, "detail": detail, "errors": []}
    ).encode()


JSON_ADVICE = "; send large meshes as PLY or OBJ file parts of a multipart/form-data request (docs/api.md)"


def is_json_document(content_type: str) -> bool:
    """Whether a body of this Content-Type is parsed as one JSON document: ``application/json``,
    ``application/*+json``, or none (the JSON routes take a body without a type as JSON)."""
    ctype = content_type.split(";", 1)[0].strip().lower()
    return ctype in ("", "application/json") or (ctype.startswith("application/") and ctype.endswith("+json"))


class BodyLimitMiddleware:
    """413 for bodies over ``max_body_bytes`` (JSON documents: over ``max_json_bytes``, at most
    ``max_body_bytes``: ``Settings.json_limit_bytes``), with or without ``Content-Length``."""

    def __init__(self, app: ASGIApp, max_body_bytes: int, max_json_bytes: int | None = None) -> None:
        self.app = app
        self.max_body_bytes = max_body_bytes
        self.max_json_bytes = max_body_bytes if max_json_bytes is None else max_json_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = dict(scope.get("headers", []))
        json_body = is_json_document(headers.get(b"content-type", b"").decode("latin-1"))
        limit = self.max_json_bytes if json_body else self.max_body_bytes
        what, advice = ("JSON body", JSON_ADVICE) if json_body and limit < self.max_body_bytes else ("body", "")
        if b"content-length" in headers:
            try:
                declared = int(headers[b"content-length"])
            except ValueError:
                await self._reject(send, "invalid Content-Length header", status=400)
                return
            if declared > limit:
                await self._reject(send, f"{what} of {declared} bytes exceeds the {limit}-byte limit{advice}")
                return

        received = 0
        over = False
        response_started = False

        async def limited_receive() -> Message:
            nonlocal received, over
            if over:  # never pull more from the client once over the limit
                raise BodyTooLarge(f"request {what} exceeds the {limit}-byte limit{advice}")
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit:
                    over = True
                    raise BodyTooLarge(f"request {what} exceeds the {limit}-byte limit{advice}")
            return message

        async def tracking_send(message: Message) -> None:
            nonlocal response_started
            if message["type"] == "http.response.start":
                response_started = True
            await send(message)

        try:
            await self.app(scope, limited_receive, tracking_send)
        except BodyTooLarge as exc:
            # Normally the app's exception handler answers; this covers code paths that
            # let the exception escape (e.g. a body read in a background stream).
            if response_started:
                raise
            await self._reject(send, str(exc.detail))

    @staticmethod
    async def _reject(send: Send, detail: str, status: int = 413) -> None:
        body = _problem_413(detail) if status == 413 else json.dumps(
            {"type": "about:blank", "title": "Bad request", "status": status, "detail": detail, "errors": []}
        ).encode()
        await send(
            {
                "type": "http.response.start",
                "status": status,
                "headers": [
                    (b"content-type", b"application/problem+json"),
                    (b"content-length", str(len(body)).encode()),
                    (b"connection", b"close"),
                ],
            }
        )
        await send({"type": "http.response.body", "body": body})


@dataclass
class MultipartPart:
    name: str
    """The form field name (for mesh files: the ``mesh_file`` path the part satisfies)."""
    filename: str | None
    """Client-side file name: metadata only, never used as a path."""
    content_type: str | None
    data: bytes


class _Collector:
    def __init__(self, max_part_bytes: int, max_parts: int, field_limits: dict[str, int]) -> None:
        self.max_part_bytes = max_part_bytes
        self.max_parts = max_parts
        self.field_limits = field_limits
        self.parts: list[MultipartPart] = []
        self._header_name = b""
        self._header_value = b""
        self._headers: dict[bytes, bytes] = {}
        self._data = bytearray()
        self._limit = max_part_bytes
        self._name = ""

    def on_part_begin(self) -> None:
        if len(self.parts) >= self.max_parts:
            raise MultipartError(f"too many parts: at most {self.max_parts}")
        self._headers = {}
        self._data = bytearray()

    def on_header_field(self, data: bytes, start: int, end: int) -> None:
        self._header_name += data[start:end]

    def on_header_value(self, data: bytes, start: int, end: int) -> None:
        self._header_value += data[start:end]
        if len(self._header_value) > 16384:
            raise MultipartError("multipart header too long")

    def on_header_end(self) -> None:
        self._headers[self._header_name.lower()] = self._header_value
        self._header_name = b""
        self._header_value = b""

    def on_headers_finished(self) -> None:
        disposition = self._headers.get(b"content-disposition")
        if disposition is None:
            raise MultipartError(f"part {len(self.parts)} has no Content-Disposition header")
        _, options = parse_options_header(disposition)
        raw_name = options.get(b"name")
        if raw_name is None:
            raise MultipartError(f"part {len(self.parts)} has no name in its Content-Disposition")
        try:
            self._name = raw_name.decode("utf-8")
        except UnicodeDecodeError:
            raise MultipartError(f"part {len(self.parts)}: its name is not valid UTF-8") from None
        self._limit = self.field_limits.get(self._name, self.max_part_bytes)

    def on_part_data(self, data: bytes, start: int, end: int) -> None:
        if len(self._data) + (end - start) > self._limit:
            if self._name in self.field_limits:
                raise BodyTooLarge(f"part {self._name!r} exceeds the {self._limit}-byte limit for JSON documents"
                                   f"{JSON_ADVICE}", field=self._name)
            raise BodyTooLarge(f"part {self._name!r} exceeds the {self._limit}-byte limit per file", field=self._name)
        self._data += data[start:end]

    def on_part_end(self) -> None:
        disposition = self._headers.get(b"content-disposition", b"")
        _, options = parse_options_header(disposition)
        filename = options.get(b"filename")
        ctype = self._headers.get(b"content-type")
        self.parts.append(
            MultipartPart(
                name=self._name,
                filename=filename.decode("utf-8", "replace") if filename is not None else None,
                content_type=ctype.decode("latin-1") if ctype is not None else None,
                data=bytes(self._data),
            )
        )
        self._data = bytearray()


async def read_multipart(
    request: Request,
    *,
    max_part_bytes: int,
    max_parts: int,
    field_limits: dict[str, int] | None = None,
) -> list[MultipartPart]:
    """All parts of a ``multipart/form-data`` body, each capped at ``max_part_bytes``
    (``field_limits`` overrides the cap for named fields). Raises MultipartError for a
    malformed body and BodyTooLarge for an oversized part, both while streaming."""
    _, params = parse_options_header(request.headers.get("content-type", ""))
    boundary = params.get(b"boundary")
    if not boundary:
        raise MultipartError("multipart/form-data without a boundary parameter")
    collector = _Collector(max_part_bytes, max_parts, field_limits or {})
    parser = MultipartParser(
        boundary,
        {
            "on_part_begin": collector.on_part_begin,
            "on_part_data": collector.on_part_data,
            "on_part_end": collector.on_part_end,
            "on_header_field": collector.on_header_field,
            "on_header_value": collector.on_header_value,
            "on_header_end": collector.on_header_end,
            "on_headers_finished": collector.on_headers_finished,
        },
    )
    try:
        async for chunk in request.stream():
            parser.write(chunk)
        parser.finalize()
    except FormParserError as exc:
        raise MultipartError(f"malformed multipart body: {exc}") from None
    if parser.state != MultipartState.END:  # finalize() does not check for a truncated body
        raise MultipartError("truncated multipart body: the closing boundary is missing")
    if not collector.parts:
        raise MultipartError("empty multipart body")
    return collector.parts
