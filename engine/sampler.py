"""Stratified, low-discrepancy sample values for Monte Carlo estimators: Owen-scrambled Sobol.

Every value is a pure function of ``(key, pixel, index, component)``:

- ``key`` (uint64) names one *dimension pair* of a path (the pixel position, the position on
  one rectangular light at one vertex, the BSDF direction at one vertex, ...), folded from the
  render's seed and where the pair is used (``sample_key``, ``derive_key``);
- ``pixel`` is the integral's owner (an image pixel, a shaded hit);
- ``index`` is the sample's number among that pixel's samples of that pair (int64);
- ``component`` is 0 or 1, the two coordinates of the pair.

So a render split over threads, chunks or jobs draws exactly the values a single render draws,
and any value can be computed on its own, without shared state.

Construction (Burley 2020, "Practical Hash-based Owen Scrambling"): each pair is the 2-D Sobol
sequence, a (0, 2)-sequence in base 2, with its index shuffled by a nested uniform scramble and
each coordinate Owen-scrambled, all seeded by a hash of (key, pixel). Consequences:

- for every pixel and pair, the first ``2^m`` samples (and every aligned block of ``2^m``) form a
  (0, m, 2)-net: each elementary interval ``[a/2^p, (a+1)/2^p) x [b/2^q, (b+1)/2^q)`` with
  ``p + q = m`` holds exactly one of them (so any even count of samples puts exactly half in each
  half of the square, in both coordinates);
- every single value is uniform on [0, 1) (Owen scrambling), so every estimator stays unbiased;
- different pairs, and different pixels, are decorrelated by their independent index shuffles
  (the "padding" of a high-dimensional path with 2-D sequences);
- the integration error of a smooth 2-D integrand falls like ``n^-1.5`` rather than ``n^-0.5``.

The index is 64-bit: its low 32 bits index the sequence, its high bits are folded into the
scramble seed (branching paths number their samples ``parent * branches + branch``).

Kernel API (call from ``@njit`` code): ``sample_2d``, ``sample_1d``, ``derive_key``.
NumPy API: ``sample_key``, ``points``.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.rng import mix64, stream_key

_U0 = np.uint64(0)
_U1 = np.uint64(1)
_M32 = np.uint64(0xFFFFFFFF)
_S1 = np.uint64(1)
_S2 = np.uint64(2)
_S4 = np.uint64(4)
_S8 = np.uint64(8)
_S16 = np.uint64(16)
_S21 = np.uint64(21)
_S32 = np.uint64(32)
_S43 = np.uint64(43)
_B1 = np.uint64(0x55555555)
_B2 = np.uint64(0x33333333)
_B4 = np.uint64(0x0F0F0F0F)
_B8 = np.uint64(0x00FF00FF)
_B16 = np.uint64(0x0000FFFF)
_H1 = np.uint64(0x3D20ADEA)
_H2 = np.uint64(0x05526C56)
_H3 = np.uint64(0x53A22864)
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_PIX = np.uint64(0xD1B54A32D192ED03)
_INV53 = 1.0 / 9007199254740992.0  # 2^-53


@nb.njit(cache=True, error_model="numpy")
def _reverse32(x):
    """The 32 low bits of x in reverse order (x < 2^32)."""
    x = ((x >> _S1) & _B1) | ((x & _B1) << _S1)
    x = ((x >> _S2) & _B2) | ((x & _B2) << _S2)
    x = ((x >> _S4) & _B4) | ((x & _B4) << _S4)
    x = ((x >> _S8) & _B8) | ((x & _B8) << _S8)
    return ((x >> _S16) & _B16) | ((x & _B16) << _S16)


@nb.njit(cache=True, error_model="numpy")
def _lk_permute(x, seed):
    """A seeded permutation of 32-bit integers in which every output bit depends only on the
    input bits at and below it (Laine-Karras, with Vegdahl's constants): applied to reversed
    bits it is a nested uniform (Owen) scramble."""
    x ^= (x * _H1) & _M32
    x = (x + seed) & _M32
    x = (x * ((seed >> _S16) | _U1)) & _M32
    x ^= (x * _H2) & _M32
    x ^= (x * _H3) & _M32
    return x


@nb.njit(cache=True, error_model="numpy")
def _owen(x, seed):
    """Nested uniform scramble of a 32-bit binary fraction x (bit 31 is the first digit)."""
    return _reverse32(_lk_permute(_reverse32(x), seed))


@nb.njit(cache=True, error_model="numpy")
def _sobol1_reversed(i):
    """Second coordinate of the 2-D Sobol sequence at 32-bit index i, bits reversed (bit r is
    digit r + 1 of the binary fraction); the first coordinate reversed is i itself.

    Its generator matrix is Pascal's triangle mod 2 (direction numbers v_0 = 2^31,
    v_k = v_(k-1) xor v_(k-1) >> 1): digit r is the xor of index bits k with C(k, r) odd, i.e.
    (Lucas) with k a superset of r's bits; a superset-xor transform over the 5 bits of the bit
    position, one shift-and-mask per bit instead of a loop over the index's 32 bits."""
    i ^= (i >> _S1) & _B1
    i ^= (i >> _S2) & _B2
    i ^= (i >> _S4) & _B4
    i ^= (i >> _S8) & _B8
    return i ^ ((i >> _S16) & _B16)


@nb.njit(cache=True, error_model="numpy")
def _to_unit(x, h):
    """A float64 in [0, 1) whose first 32 binary digits are x, the next 21 the top bits of h."""
    return np.float64((x << _S21) | (h >> _S43)) * _INV53


@nb.njit(cache=True, error_model="numpy")
def sample_2d(key, pixel, index):
    """(u, v) in [0, 1)^2: sample ``index`` (int64 >= 0) of ``pixel`` (int64) in the dimension
    pair ``key`` (uint64)."""
    idx = np.uint64(index)
    s = mix64(key ^ mix64(np.uint64(pixel) * _PIX + (idx >> _S32) * _GOLDEN))
    s2 = mix64(s ^ _GOLDEN)
    h = (s2 ^ (idx * _PIX)) * _GOLDEN  # the digits past the 32nd (need no strong hash)
    i = _owen(idx & _M32, s & _M32)  # shuffled index: an aligned block of 2^m stays one
    # Owen scrambling of a coordinate c is _reverse32(_lk_permute(_reverse32(c), seed)), and
    # _reverse32(c) is what the Sobol functions give
    x = _reverse32(_lk_permute(i, s >> _S32))
    y = _reverse32(_lk_permute(_sobol1_reversed(i), s2 & _M32))
    return _to_unit(x, h), _to_unit(y, h << _S21)


@nb.njit(cache=True, error_model="numpy")
def sample_1d(key, pixel, index):
    """The first coordinate of ``sample_2d(key, pixel, index)`` (a stratified 1-D sample)."""
    idx = np.uint64(index)
    s = mix64(key ^ mix64(np.uint64(pixel) * _PIX + (idx >> _S32) * _GOLDEN))
    h = (mix64(s ^ _GOLDEN) ^ (idx * _PIX)) * _GOLDEN
    i = _owen(idx & _M32, s & _M32)
    return _to_unit(_reverse32(_lk_permute(i, s >> _S32)), h)


@nb.njit(cache=True, error_model="numpy")
def derive_key(key, a, b):
    """The key of a sub-dimension of ``key`` named by two integers (e.g. a path vertex and a
    purpose): keys derived from different (a, b) give independent sequences."""
    return mix64(key ^ (np.uint64(a) * _GOLDEN + (np.uint64(b) + _U1) * _PIX))


def sample_key(seed: int, *parts: int) -> np.uint64:
    """The root key of a render (``seed``) and of a use inside it (``parts``)."""
    return stream_key(0x5A3B1E, seed, *parts)


@nb.njit(cache=True, error_model="numpy")
def _points(key, pixel, offset, out):
    for j in range(out.shape[0]):
        u, v = sample_2d(key, pixel, offset + j)
        out[j, 0] = u
        out[j, 1] = v


def points(key: np.uint64 | int, pixel: int, n: int, offset: int = 0) -> np.ndarray:
    """(n, 2) float64: samples ``offset .. offset + n - 1`` of ``pixel`` in the pair ``key``."""
    out = np.empty((int(n), 2))
    _points(np.uint64(key), np.int64(pixel), np.int64(offset), out)
    return out
