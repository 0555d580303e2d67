"""docs/hard-cases.md #19: property-based tests of every operation against the app's own OpenAPI
document, with valid and invalid (negative) data: no 5xx, and status codes, content types,
headers and bodies as documented. ``IBR_SCHEMATHESIS_EXAMPLES`` (default 10 per operation
and mode) and ``IBR_SCHEMATHESIS_RANDOM=1`` (a new random draw, not the fixed one) widen it.

Why 10: every operation is still drawn in both modes (positive and negative data, up to ~1,100
requests in all), and the draw is the fixed one (derandomized), so each run replays the same cases;
more examples only widen that fixed sample, at ~1 s per operation for 20 per mode (~90 s in all,
among the full run's largest costs). ``IBR_SCHEMATHESIS_EXAMPLES=100 IBR_SCHEMATHESIS_RANDOM=1`` is
the wide search.

The operations are driven by hand (``as_strategy`` + ``given``) rather than with
``schemathesis.pytest.from_fixture``, whose lazy fixture support does not work with
pytest 9 (it reads the removed ``Node._nodeid``)."""

from __future__ import annotations

import os
import time
from typing import Any

import pytest
import schemathesis
from fastapi import FastAPI
from hypothesis import HealthCheck, given, settings
from hypothesis.errors import Unsatisfiable
from schemathesis import checks
from schemathesis.core.errors import InvalidSchema
from schemathesis.core.result import Ok
from schemathesis.generation import GenerationMode
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
)

CHECKS = [
    checks.not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_headers_conformance,
    response_schema_conformance,
]
MAX_EXAMPLES = int(os.environ.get("IBR_SCHEMATHESIS_EXAMPLES", "10"))
DERANDOMIZE = os.environ.get("IBR_SCHEMATHESIS_RANDOM", "") != "1"


@pytest.mark.slow
def test_api_conforms_to_its_openapi(make_app: Any) -> None:
    app: FastAPI = make_app(max_body_bytes=1 << 20, max_upload_bytes=1 << 19)
    schema = schemathesis.openapi.from_asgi("/openapi.json", app)
    failures: list[str] = []
    n_ops = 0
    timings: dict[str, float] = {}
    skipped: list[str] = []
    for result in schema.get_all_operations():
        if not isinstance(result, Ok):
            failures.append(f"an operation could not be loaded from the OpenAPI document: {result.err()}")
            continue
        operation = result.ok()
        n_ops += 1
        t0 = time.perf_counter()
        for mode in (GenerationMode.POSITIVE, GenerationMode.NEGATIVE):

            @given(case=operation.as_strategy(mode))
            @settings(max_examples=MAX_EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck),
                      database=None, derandomize=DERANDOMIZE)
            def run(case: Any) -> None:
                case.call_and_validate(checks=CHECKS)

            try:
                run()
            except (InvalidSchema, Unsatisfiable) as exc:
                # limits of the data generator (an operation without inputs has no negative data;
                # some array constraints cannot be negated), not of the API
                skipped.append(f"{operation.label} ({mode}): {type(exc).__name__}")
            except Exception as exc:  # collect every operation's failure, then report them together
                failures.append(f"{operation.label} ({mode}): {type(exc).__name__}: {exc}"[:3000])
        timings[operation.label] = time.perf_counter() - t0
    print({k: round(v, 2) for k, v in timings.items()}, skipped)
    assert n_ops >= 14
    assert not failures, "\n\n".join(failures)
