"""Import an engine module as of another git revision, next to the current one (A/B benchmarks).

``module_at("HEAD~3", "engine/newviews/ibrt.py", "ibrt_ab_old")`` -> (module, short sha). The file is
written under the temp directory with its relative imports made absolute (it uses the
current ``engine`` package for everything else) and rewritten only when it changed, so
numba's on-disk cache of the old kernels stays valid between runs. ``imports`` maps module
names to the names of other old modules already loaded this way, so an old module uses old
versions of its siblings: ``module_at(rev, "engine/newviews/renderer.py", "ldc_render_ab_old",
imports={"engine.newviews.warp": "warp_ab_old"})``.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


# Where engine modules lived before the engine was split by technique: an A/B against a revision
# from before the split reads the file from its old path, and the old file's imports of its siblings
# (``from .warp import``) are matched by their old names.
FORMER_PATHS = {
    "engine/newviews/ldi.py": "engine/ldi.py", "engine/newviews/ldc.py": "engine/ldc.py",
    "engine/newviews/llf.py": "engine/llf.py", "engine/newviews/warp.py": "engine/warp.py",
    "engine/newviews/view_pass.py": "engine/view_pass.py", "engine/newviews/ibrt.py": "engine/ibrt.py",
    "engine/newviews/effects.py": "engine/effects.py", "engine/newviews/renderer.py": "engine/ldc_render.py",
    "engine/relighting/relight.py": "engine/relight.py", "engine/relighting/compress.py": "engine/relight_compress.py",
    "engine/relighting/generate.py": "engine/relight_gen.py", "engine/relighting/composite.py": "engine/composite.py",
    "engine/walkthrough/animation.py": "engine/animation.py",
}


def _module_name(relpath: str) -> str:
    return relpath.removesuffix(".py").replace("/", ".")


def _show(rev: str, relpath: str) -> tuple[str, str]:
    """The file's text at ``rev`` and the path it had there (its current path, else its former one)."""
    for path in (relpath, FORMER_PATHS.get(relpath)):
        if path is None:
            continue
        r = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:{path}"], capture_output=True, text=True)
        if r.returncode == 0:
            return r.stdout, path
    raise FileNotFoundError(f"{relpath} (or its former path) is not in revision {rev}")


def module_at(rev: str, relpath: str, name: str, imports: dict[str, str] | None = None):
    src, _ = _show(rev, relpath)
    src = src.replace("from .", "from engine.")
    former = {_module_name(new): _module_name(old) for new, old in FORMER_PATHS.items()}
    for old, new in (imports or {}).items():
        src = src.replace(f"from {old} import", f"from {new} import")
        if old in former:
            src = src.replace(f"from {former[old]} import", f"from {new} import")
    for new, old in former.items():  # the old file's other siblings: the current modules
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
