"""Import an engine module as of another git revision, next to the current one (A/B benchmarks).

``module_at("HEAD~3", "engine/ibrt.py", "ibrt_ab_old")`` -> (module, short sha). The file is
written under the temp directory with its relative imports made absolute (it uses the
current ``engine`` package for everything else) and rewritten only when it changed, so
numba's on-disk cache of the old kernels stays valid between runs. ``imports`` maps module
names to the names of other old modules already loaded this way, so an old module uses old
versions of its siblings: ``module_at(rev, "engine/ldc_render.py", "ldc_render_ab_old",
imports={"engine.warp": "warp_ab_old"})``.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def module_at(rev: str, relpath: str, name: str, imports: dict[str, str] | None = None):
    src = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:{relpath}"], capture_output=True, text=True,
                         check=True).stdout
    src = src.replace("from .", "from engine.")
    for old, new in (imports or {}).items():
        src = src.replace(f"from {old} import", f"from {new} import")
    sha = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", rev], capture_output=True, text=True,
                         check=True).stdout.strip()
    path = Path(tempfile.gettempdir()) / f"{name}_{sha}" / f"{name}.py"
    path.parent.mkdir(exist_ok=True)
    if not path.exists() or path.read_text() != src:  # unchanged file: numba's cache stays valid
        path.write_text(src)
    spec = importlib.util.spec_from_file_location(name, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod, sha
