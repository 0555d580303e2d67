"""The API process never loads numba, Embree or worker code: it builds the app, validates requests through the
render-method registry and decodes and measures images with ``engine.imageio`` / ``engine.metrics``,
all numba-free, while the compiled engine runs in the workers. Checked in a fresh interpreter, since
this test process may have imported the engine's kernels already."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]

CODE = """
import json, sys
import service.main
from producer.settings import Settings
app = service.main.create_app(Settings(redis_url="redis://127.0.0.1:1/0", store_url=sys.argv[1]))
app.openapi()
# what the preview routes compute in this process: decode an EXR and a PNG, compare, colour a heatmap
import numpy as np
from engine.imageio import decode_image
from service.api.routes import preview
img = np.full((4, 5, 3), 0.25, np.float32)
exr = preview.png_bytes(preview.to_srgb8(img, 1.0))
assert decode_image("x.png", exr)[0].shape == (4, 5, 3)
assert preview.heatmap(img, img * 1.5, preview.coverage_mask(img)).shape == (4, 5, 3)
assert preview.capabilities_of(["/v1/scenes/{scene_id}/bakes"]).methods
print(json.dumps(sorted(m for m in sys.modules)))
"""


def test_the_api_imports_no_numba(tmp_path: Path) -> None:
    out = subprocess.run([sys.executable, "-c", CODE, str(tmp_path / "store")], cwd=REPO_ROOT, capture_output=True,
                         text=True, timeout=180)
    assert out.returncode == 0, out.stdout + out.stderr
    modules = set(json.loads(out.stdout.strip().splitlines()[-1]))
    assert "service.main" in modules and "engine.methods" in modules and "engine.metrics" in modules
    bad = sorted(m for m in modules if m.split(".")[0] in ("numba", "llvmlite", "embreex", "workers"))
    assert not bad, bad
    # no engine module that compiles kernels: they all import the numba setup first
    assert "engine._numba_setup" not in modules and "engine._srgb8_kernel" not in modules
