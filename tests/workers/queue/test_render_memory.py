"""The render-memory estimate that the API refuses renders by (``producer.costs``) bounds
what the real render job takes: a render sized so its estimate is the limit grows a warm worker's
peak RSS by no more than the limit, and by a good part of it (the estimate is not vacuous)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from api_schemas.service import RenderRequest
from producer.costs import estimate_render_bytes

REPO = Path(__file__).resolve().parents[3]


def _grew(method: str, width: int, height: int, params: dict[str, Any]) -> int:
    spp = int(params.get("spp", 4))
    rest = {k: v for k, v in params.items() if k != "spp"}
    out = subprocess.run(
        [sys.executable, "-m", "tests.workers.queue.render_rss", method, str(width), str(height), str(spp),
         json.dumps(rest)],
        cwd=REPO, env={**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])},
        capture_output=True, text=True, timeout=900, check=False,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return int(json.loads(out.stdout.strip().splitlines()[-1])["grew_bytes"])


@pytest.mark.slow
@pytest.mark.parametrize(("method", "width", "height", "params"), [
    ("reference", 1024, 768, {"spp": 4}),
    ("reference", 512, 512, {"spp": 8, "glossy_samples": 4, "area_light_samples": 4}),
    ("ldc+llf", 1024, 1024, {}),
])
def test_a_render_at_its_estimate_stays_under_it(method: str, width: int, height: int,
                                                  params: dict[str, Any]) -> None:
    req = RenderRequest(scene_id="0" * 64, method=method,  # type: ignore[arg-type]
                        params=params if method == "reference" else {})
    limit = estimate_render_bytes(req, width, height)  # IBR_MAX_RENDER_BYTES = this: accepted, just
    grew = _grew(method, width, height, params)
    assert grew <= limit, f"{method} {width}x{height} {params}: grew {grew >> 20} MiB, estimate {limit >> 20} MiB"
    assert grew >= limit / 4, f"estimate {limit >> 20} MiB far above the {grew >> 20} MiB the render took"
