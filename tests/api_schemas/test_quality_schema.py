"""The ``quality`` field of a render request: ranges with the allowed range in the message, no
explicit method beside it, and the limit that mirrors the render job's timeout."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from api_schemas.service import MAX_CONTRACT_MS, QualityContract, RenderRequest
from producer.queue import RENDER_TIMEOUT_S
from producer.renders import render_artifact_key

SID = "a" * 64


def test_max_ms_limit_is_the_render_job_timeout() -> None:
    assert MAX_CONTRACT_MS == RENDER_TIMEOUT_S * 1000


@pytest.mark.parametrize("quality,needle", [
    ({"max_error": 0}, "(0, 1)"), ({"max_error": 1}, "(0, 1)"), ({"max_error": 1.5}, "(0, 1)"),
    ({"max_ms": 0}, "(0, 600000]"), ({"max_ms": -1}, "(0, 600000]"), ({"max_ms": 600_000.5}, "(0, 600000]"),
    ({}, "max_error, max_ms or both"), ({"max_error": 0.1, "on_miss": "maybe"}, "best_effort")])
def test_out_of_range_targets_name_the_range(quality: dict, needle: str) -> None:
    with pytest.raises(ValidationError) as exc:
        RenderRequest.model_validate({"scene_id": SID, "quality": quality})
    assert needle in str(exc.value)
    assert exc.value.errors()[0]["loc"][0] == "quality"


def test_quality_with_an_explicit_method_or_params_is_refused() -> None:
    for extra in ({"method": "ldc"}, {"method": "reference"}, {"params": {"spp": 8}}, {"view": {"supersample": 2}}):
        with pytest.raises(ValidationError, match="leave out"):
            RenderRequest.model_validate({"scene_id": SID, "quality": {"max_error": 0.05}, **extra})
    with pytest.raises(ValidationError, match="provenance"):
        RenderRequest.model_validate({"scene_id": SID, "quality": {"max_ms": 50}, "outputs": ["provenance"]})
    ok = RenderRequest.model_validate({"scene_id": SID, "quality": {"max_error": 0.05, "max_ms": 100},
                                       "bake": {"ldc_resolution": 64}, "missing_bake": "bake"})
    assert ok.quality == QualityContract(max_error=0.05, max_ms=100.0)


def test_keys_of_plain_requests_are_unchanged_by_the_quality_field() -> None:
    plain = RenderRequest(scene_id=SID, method="ldc")
    # the key hashes the request without quality (None is dropped), as before the field existed
    from engine import ENGINE_VERSION
    from producer.artifacts import artifact_key

    params = plain.model_dump(mode="json", exclude={"scene_id", "missing_bake", "quality", "outputs", "params",
                                                    "view"})
    assert render_artifact_key(plain) == artifact_key("render", {"scene": SID}, params, ENGINE_VERSION)
