"""The engine's numba disk cache is keyed by the engine's whole source (engine/_numba_setup.py)."""

import hashlib
from pathlib import Path

import numba

import engine
from engine import _numba_setup
from engine.newviews import warp


def test_cache_dir_is_keyed_by_every_engine_source_file():
    root = Path(engine.__file__).resolve().parent
    h = hashlib.sha256()
    for p in sorted(root.rglob("*.py")):
        h.update(str(p.relative_to(root)).encode())
        h.update(p.read_bytes())
    assert _numba_setup.NUMBA_CACHE_DIR.endswith(f"ibr-engine-{h.hexdigest()[:16]}")
    assert numba.config.CACHE_DIR == _numba_setup.NUMBA_CACHE_DIR


def test_kernels_cache_under_that_directory():
    # a cache=True kernel's locator: the user-provided (keyed) directory, not the in-tree
    # __pycache__ that numba would otherwise use
    path = warp._init_buffers._cache._cache_path
    assert Path(path).resolve().is_relative_to(Path(_numba_setup.NUMBA_CACHE_DIR).resolve())
