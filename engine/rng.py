"""Counter-based random numbers for kernels: deterministic, parallel-safe, allocation-free.

``uniform(stream, index, dim)`` hashes (stream, index, dim) with the splitmix64
finaliser, so any thread can draw the number for any ray without shared state, and a
render is reproducible bit for bit for a given seed regardless of thread count. The
``stream`` key separates renders, chunks, bounces and stages (``stream_key``).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)

_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_S30 = np.uint64(30)
_S27 = np.uint64(27)
_S31 = np.uint64(31)
_S11 = np.uint64(11)
_INV53 = 1.0 / 9007199254740992.0  # 2^-53


@nb.njit(cache=True, error_model="numpy")
def mix64(z):
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@nb.njit(cache=True, error_model="numpy")
def uniform(stream, index, dim):
    """A float64 in [0, 1) for (stream: uint64, index: int, dim: int)."""
    z = mix64(stream ^ mix64(np.uint64(index) * _GOLDEN + np.uint64(dim)))
    return np.float64(z >> _S11) * _INV53


def stream_key(*parts: int) -> np.uint64:
    """Fold integers (seed, chunk, bounce, stage, ...) into one uint64 stream key."""
    z = np.uint64(0x243F6A8885A308D3)
    with np.errstate(over="ignore"):
        for p in parts:
            z = _mix_py(z ^ np.uint64(int(p) & 0xFFFFFFFFFFFFFFFF) * _GOLDEN)
    return z


def _mix_py(z: np.uint64) -> np.uint64:
    with np.errstate(over="ignore"):
        z = (z ^ (z >> _S30)) * _M1
        z = (z ^ (z >> _S27)) * _M2
        return z ^ (z >> _S31)


@nb.njit(cache=True, error_model="numpy")
def _fill(stream, out):
    n, k = out.shape
    for i in range(n):
        for j in range(k):
            out[i, j] = uniform(stream, i, j)


def uniforms(stream: np.uint64, n: int, k: int) -> np.ndarray:
    """(n, k) float64 uniforms of a stream (for tests and NumPy-side code)."""
    out = np.empty((n, k))
    _fill(np.uint64(stream), out)
    return out
