"""Every exception the API can meet, mapped to an RFC 9457 problem in ONE place.

``application/problem+json`` bodies follow ``api_schemas.service.Problem``; invalid
input lists one ``errors[]`` entry per field, located with ``api_schemas.errors`` (the
leading ``"body"`` of FastAPI's locations is dropped, so a body error reads
``scene.objects.2.radius``; query / path / header errors keep their source:
``query.wait``).

| exception | status |
|---|---|
| RequestValidationError, ValidationProblem | 422 (400 for an unparseable body) |
| AuthError | 401 + ``WWW-Authenticate: Bearer`` |
| MissingResource, store NotFound, UnknownScene, JobNotFound | 404 ``<field> '<value>' not found`` (*) |
| LacksPart | 404 with its own message (the caller can see the resource; it lacks the part asked for) |
| producer.store.ChecksumMismatch | 404, "stored data corrupt" (the manifest is gone: request it again to rebake) |
| queues.BakeMissing (an LDC render without its bake) | 409, "bake missing", naming the bake to request |
| CalibrationMissing (a quality contract on an uncalibrated scene) | 409, "calibration missing", naming the request |
| ContractUnmet (no setting meets a quality contract, ``on_miss: fail``) | 422, one error per unmet target |
| BodyTooLarge | 413 |
| MultipartError | 400 |
| OverflowError (a validator overflowing on numbers near 1e308) | 422 |
| RateLimited | 429 + ``Retry-After`` |
| StoreUnavailable, redis ConnectionError / TimeoutError | 503 + ``Retry-After`` |
| HTTPException | its status |
| anything else | 500, logged with the request id |

(*) naming the body field or path parameter that names the missing thing, the same answer for
another key's resource; a 404 nothing in the request names stays ``no such resource: <path>``.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterable, Mapping, Sequence
from http import HTTPStatus
from typing import Any

import redis.exceptions
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException

from api_schemas.errors import FieldError, format_error_details
from api_schemas.service import Problem, ProblemField
from producer.costs import CostOverLimit
from producer.errors import BakeMissing, CalibrationMissing, ContractUnmet, JobNotFound, UnknownScene
from producer.store import ChecksumMismatch, NotFound, StoreError, StoreUnavailable
from service.api.limits import BodyTooLarge, MultipartError
from service.core.security import AuthError, RateLimited

__all__ = [
    "PROBLEM_MEDIA_TYPE",
    "MissingResource",
    "RETRY_AFTER_S",
    "ValidationProblem",
    "install_exception_handlers",
    "problem_response",
    "problem_responses",
]

log = logging.getLogger("ibr.api")

PROBLEM_MEDIA_TYPE = "application/problem+json"
RETRY_AFTER_S = 5
"""Seconds a client should wait after a 503 (store or Redis unreachable)."""


class ValidationProblem(Exception):
    """Invalid input found by a route itself (not by FastAPI's parameter validation)."""

    def __init__(self, errors: Sequence[FieldError], detail: str = "", status: int = 422) -> None:
        super().__init__(detail or "; ".join(f"{e['field'] or '(body)'}: {e['message']}" for e in errors))
        self.errors = list(errors)
        self.detail = detail
        self.status = status

    @classmethod
    def from_pydantic(
        cls, exc: ValidationError, root: type[BaseModel] | None, prefix: Sequence[str | int] = ()
    ) -> ValidationProblem:
        """Locate ``exc``'s errors relative to ``root`` and put them under ``prefix``."""
        formatted = format_error_details(exc.errors(include_url=False), root)
        if prefix:
            pre = ".".join(str(p) for p in prefix)
            formatted = [FieldError(field=f"{pre}.{f['field']}" if f["field"] else pre, message=f["message"],
                                    type=f["type"]) for f in formatted]
        return cls(formatted)


class LacksPart(NotFound):
    """The resource the request names exists and the caller may see it, but it has no such part
    (e.g. a reference render's provenance image): 404 with this message as it is, since it names
    only what the caller sent and may see."""


class MissingResource(NotFound):
    """A request field names something that does not exist (or that the caller may not see): 404
    ``<field> '<value>' not found``, with the field in ``errors[]``. ``field`` is located like a
    validation error's: a body field bare (``scene_id``), a path parameter as ``path.job_id``."""

    def __init__(self, field: str, value: str) -> None:
        super().__init__(f"{field} {value!r} not found")
        self.field = field
        self.value = value


_UNKNOWN_SCENE = re.compile(r"scene '?([^'\s]+)'? does not exist")


def _missing_field(request: Request, exc: Exception) -> tuple[str, str] | None:
    """(field, value) of the request that names the missing thing of ``exc``: the path parameter
    whose value the exception carries (the last one in the path when several do), or the scene id of
    an UnknownScene sent in the body. None when nothing the request sent matches (the exception's
    own text may hold storage keys, so it is never echoed)."""
    if isinstance(exc, StarletteHTTPException):
        text = str(exc.detail)
    else:
        text = str(exc.args[0]) if exc.args else ""
    params = [(k, v) for k, v in request.path_params.items() if isinstance(v, str) and v]
    for k, v in params:
        if text == v:
            return f"path.{k}", v
    for k, v in reversed(params):
        if v in text:
            return f"path.{k}", v
    if isinstance(exc, UnknownScene):
        m = _UNKNOWN_SCENE.search(text)
        if m:
            return "scene_id", m.group(1)
    return None


def _missing_response(field: str, value: str) -> JSONResponse:
    name = field.removeprefix("path.")
    shown = value if len(value) <= 80 else value[:77] + "..."
    message = f"{name} {shown!r} not found"
    return problem_response(404, message, errors=[FieldError(field=field, message=message, type="not_found")])


def problem_response(
    status: int,
    detail: str = "",
    *,
    title: str | None = None,
    errors: Iterable[Mapping[str, Any]] = (),
    headers: Mapping[str, str] | None = None,
    type_: str = "about:blank",
) -> JSONResponse:
    body = Problem(
        type=type_,
        title=title or _phrase(status),
        status=status,
        detail=detail,
        errors=[ProblemField(field=str(e["field"]), message=str(e["message"]), type=str(e["type"])) for e in errors],
    )
    return JSONResponse(
        body.model_dump(mode="json"), status_code=status, headers=dict(headers or {}), media_type=PROBLEM_MEDIA_TYPE
    )


def _phrase(status: int) -> str:
    try:
        return HTTPStatus(status).phrase
    except ValueError:
        return "Error"


def _body_root(request: Request) -> Any:
    """The model FastAPI validated the body against (for tag-aware field paths)."""
    route = request.scope.get("route")
    body_field = getattr(route, "body_field", None)
    if body_field is None:
        return None
    return getattr(body_field.field_info, "annotation", None)


def validation_errors(request: Request, exc: RequestValidationError) -> list[FieldError]:
    root = _body_root(request)
    out: list[FieldError] = []
    for err in exc.errors():
        loc = tuple(err.get("loc", ()))
        if err.get("type") == "json_invalid":
            ctx = err.get("ctx") or {}
            pos = loc[1] if len(loc) > 1 else "?"
            out.append(
                FieldError(field="", message=f"invalid JSON at character {pos}: {ctx.get('error', '')}".strip(),
                           type="json_invalid")
            )
            continue
        if loc and loc[0] == "body":
            out.extend(format_error_details([{**err, "loc": loc[1:]}], root))
        else:
            # query / path / header / cookie: keep the source so "query.wait" is unambiguous
            out.extend(format_error_details([err], None))
    return out


def problem_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` entries for problem statuses (so clients and schemathesis know them)."""
    descriptions = {
        400: "Malformed request (unparseable body or multipart)",
        401: "Missing or invalid API key",
        404: "No such resource (or it belongs to another API key)",
        409: "Conflict with the resource's current state",
        413: "Request body or an uploaded file over the size limit",
        415: "Unsupported Content-Type",
        422: "Invalid input; `errors[]` names each field",
        429: "Rate limit exceeded; see Retry-After",
        503: "Redis or the object store is unreachable; see Retry-After",
    }
    return {
        s: {"model": Problem, "description": descriptions.get(s, _phrase(s)), "content": {PROBLEM_MEDIA_TYPE: {}}}
        for s in statuses
    }


def install_exception_handlers(app: FastAPI) -> None:
    """Register the mapping above on ``app``."""

    @app.exception_handler(RequestValidationError)
    async def _request_validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = validation_errors(request, exc)
        return problem_response(422, f"{len(errors)} invalid field(s)", title="Invalid input", errors=errors)

    @app.exception_handler(ValidationProblem)
    async def _validation_problem(request: Request, exc: ValidationProblem) -> JSONResponse:
        title = "Invalid input" if exc.status == 422 else _phrase(exc.status)
        detail = exc.detail or f"{len(exc.errors)} invalid field(s)"
        return problem_response(exc.status, detail, title=title, errors=exc.errors)

    @app.exception_handler(AuthError)
    async def _auth(request: Request, exc: AuthError) -> JSONResponse:
        return problem_response(
            401, exc.detail, headers={"WWW-Authenticate": 'Bearer realm="ibr", error="invalid_token"'}
        )

    @app.exception_handler(RateLimited)
    async def _rate(request: Request, exc: RateLimited) -> JSONResponse:
        return problem_response(429, str(exc), headers={"Retry-After": str(int(exc.retry_after_s))})

    @app.exception_handler(LacksPart)
    async def _lacks(request: Request, exc: LacksPart) -> JSONResponse:
        return problem_response(404, str(exc))

    @app.exception_handler(MissingResource)
    async def _missing(request: Request, exc: MissingResource) -> JSONResponse:
        return _missing_response(exc.field, exc.value)

    async def _not_found(request: Request, exc: Exception) -> JSONResponse:
        # Names only what the request sent, so it reads the same for "absent" and "another key's".
        named = _missing_field(request, exc)
        if named is None:
            return problem_response(404, f"no such resource: {request.url.path}")
        return _missing_response(*named)

    for cls in (NotFound, UnknownScene, JobNotFound):
        app.add_exception_handler(cls, _not_found)

    @app.exception_handler(ChecksumMismatch)
    async def _corrupt(request: Request, exc: ChecksumMismatch) -> JSONResponse:
        log.error("checksum mismatch: %s", exc)
        return problem_response(
            404,
            f"{exc}. The corrupt copy is never served: request the render again to rebake it "
            "(or upload the scene again)",
            title="Stored data corrupt",
            type_="urn:ibr:problem:corrupt",
        )

    @app.exception_handler(BakeMissing)
    async def _bake_missing(request: Request, exc: BakeMissing) -> JSONResponse:
        return problem_response(409, str(exc), title="Bake missing", type_="urn:ibr:problem:bake-missing")

    @app.exception_handler(CalibrationMissing)
    async def _calibration_missing(request: Request, exc: CalibrationMissing) -> JSONResponse:
        return problem_response(409, str(exc), title="Calibration missing", type_="urn:ibr:problem:calibration-missing")

    @app.exception_handler(ContractUnmet)
    async def _contract_unmet(request: Request, exc: ContractUnmet) -> JSONResponse:
        return problem_response(422, str(exc), title="Quality contract cannot be met",
                                type_="urn:ibr:problem:contract-unmet",
                                errors=[{"field": f"quality.{t}", "message": str(exc), "type": "contract_unmet"}
                                        for t in exc.unmet])

    @app.exception_handler(CostOverLimit)
    async def _over_limit(request: Request, exc: CostOverLimit) -> JSONResponse:
        return problem_response(422, exc.message, title="Over this server's limits", type_="urn:ibr:problem:over-limit",
                                errors=[{"field": exc.field, "message": exc.message, "type": exc.type}])

    @app.exception_handler(StoreError)
    async def _store_error(request: Request, exc: StoreError) -> JSONResponse:
        rid = getattr(request.state, "request_id", None)
        log.error("store error: %s", exc, extra={"request_id": rid})
        return problem_response(500, f"stored data could not be read ({exc}); request id {rid}")

    @app.exception_handler(StoreUnavailable)
    async def _store_down(request: Request, exc: StoreUnavailable) -> JSONResponse:
        log.warning("object store unavailable: %s", exc)
        return problem_response(
            503, "the object store is unreachable; retry later", headers={"Retry-After": str(RETRY_AFTER_S)}
        )

    async def _redis_down(request: Request, exc: Exception) -> JSONResponse:
        log.warning("redis unavailable: %s", exc)
        return problem_response(
            503, "the job queue (Redis) is unreachable; retry later", headers={"Retry-After": str(RETRY_AFTER_S)}
        )

    app.add_exception_handler(redis.exceptions.ConnectionError, _redis_down)
    app.add_exception_handler(redis.exceptions.TimeoutError, _redis_down)

    @app.exception_handler(OverflowError)
    async def _overflow(request: Request, exc: OverflowError) -> JSONResponse:
        # Only input reaches float arithmetic that can overflow (validators summing numbers near
        # 1e308); pydantic does not wrap ArithmeticError into a ValidationError, so it lands here.
        rid = getattr(request.state, "request_id", None)
        log.warning("numeric overflow while validating input: %s", exc, extra={"request_id": rid})
        return problem_response(
            422, f"a number in the request is too large to process ({exc})", title="Invalid input",
            errors=[FieldError(field="", message=f"numeric overflow: {exc}", type="overflow")],
        )

    @app.exception_handler(MultipartError)
    async def _multipart(request: Request, exc: MultipartError) -> JSONResponse:
        return problem_response(400, str(exc))

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        errors: list[FieldError] = []
        if isinstance(exc, BodyTooLarge) and exc.field:
            errors.append(FieldError(field=exc.field, message=str(exc.detail), type="too_large"))
        if exc.status_code == 404 and not errors:
            named = _missing_field(request, exc)
            if named is not None:
                return _missing_response(*named)
        title = "Request body too large" if exc.status_code == 413 else None
        return problem_response(exc.status_code, str(exc.detail), title=title, errors=errors, headers=exc.headers)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        rid = getattr(request.state, "request_id", None)
        log.exception("unhandled error", extra={"request_id": rid})
        return problem_response(500, f"internal error; quote request id {rid} when reporting it")
