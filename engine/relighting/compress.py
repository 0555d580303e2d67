"""Low-rank compression of a baked illumination-dataset store (docs/relighting.md).

The stack of one tile of ``TILE`` stored pixels is a matrix ``M_t`` of (3 TILE) rows (pixel x
channel) by K columns (lights). It is replaced by a rank-``r_t`` factorisation
``M_t ~ U_t B_t^T``: ``U_t`` (3 TILE, r_t) per-pixel coefficients, ``B_t`` (K, r_t) per-light
basis weights, both float32. A value is the dot product of a ``U`` row and a ``B`` row, so
relighting reads ``U`` once per pixel and channel and three ``B`` rows per light sample,
without decompressing (``engine.relighting.kernel`` does exactly that).

Error control. The requested error ``tol`` is a relative RMS error of the whole stack:
``||M - M~||_F <= tol ||M||_F``. Every tile gets the same share: its RMS error must be <=
``tol x`` the RMS value of the whole stack, so bright and dark tiles get the same absolute
accuracy (the relit image's error is in image units, not relative to each tile). The rank of a
tile is the smallest that meets its share according to the eigenvalues of the tile's Gram
matrix; the reconstruction is then measured against the float32 input and the rank raised
until the *measured* error meets the share (the Gram route squares the condition number). The
measured numbers go into the report: the global relative RMS error, the worst tile's, the
largest absolute error, ranks and bytes.

Pixel order: a compressed store keeps its pixels in 16 x 16 image blocks (row-major blocks,
row-major inside), so a tile of 256 consecutive stored pixels is a compact image patch
(lower rank than a 256-pixel strip of image rows).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.sched import run_pieces_parallel

BLOCK = 16  # image block side for the pixel order of a compressed store
TILE = 256  # stored pixels per compressed tile (equal to engine.relighting.bake.TILE)


def block_order(mask: np.ndarray, block: int = BLOCK) -> np.ndarray:
    """Flat (row-major) indices of the mask's pixels, ordered by ``block x block`` image blocks."""
    h, w = mask.shape
    ys, xs = np.nonzero(mask)
    nbx = (w + block - 1) // block
    key = ((ys // block) * nbx + xs // block) * (block * block) + (ys % block) * block + xs % block
    order = np.argsort(key, kind="stable")
    return (ys[order] * w + xs[order]).astype(np.int64)


@dataclass(frozen=True)
class LowRankStore:
    """Per-tile factors, flattened. Tile t: ``u[u_off[t]:]`` is (3 TILE, rank[t]) row-major
    (row = local pixel x 3 + channel), ``b[b_off[t]:]`` is (n_lights, rank[t]) row-major.
    Values are in the dataset's units (no per-light scale)."""

    u: np.ndarray
    b: np.ndarray
    u_off: np.ndarray
    b_off: np.ndarray
    rank: np.ndarray
    n_lights: int
    n_rows: int

    @property
    def nbytes(self) -> int:
        return int(self.u.nbytes + self.b.nbytes + self.u_off.nbytes + self.b_off.nbytes + self.rank.nbytes)

    def kernel_args(self) -> tuple:
        return (self.u, self.b, self.u_off, self.b_off, self.rank)

    def light_values(self, k: int) -> np.ndarray:
        """(n_rows, 3) float32 reconstructed values of light k."""
        out = np.empty((self.rank.size * TILE, 3), np.float32)
        run_pieces_parallel(lambda t0, t1: _light_values(self.u, self.b, self.u_off, self.b_off, self.rank, int(k),
                                                         out, t0, t1), self.rank.size, 4)
        return out[: self.n_rows]


@nb.njit(cache=True, nogil=True)
def _light_values(u, b, u_off, b_off, rank, k, out, t0, t1):
    """Light k's reconstructed values of tiles t0 .. t1 - 1 (TILE x 3 dot products of rank length each)."""
    for t in range(t0, t1):
        r = rank[t]
        b0 = b_off[t] + k * r
        for q in range(TILE * 3):
            u0 = u_off[t] + q * r
            s = np.float32(0.0)
            for j in range(r):
                s += u[u0 + j] * b[b0 + j]
            out[t * TILE + q // 3, q % 3] = s


def _tile_matrix(flat: np.ndarray, keep: np.ndarray, pix: np.ndarray) -> np.ndarray:
    """(3 TILE, K) float64 matrix of one tile (rows past the last pixel are zero)."""
    m = np.zeros((TILE, 3, keep.size))
    vals = flat[keep[:, None], pix[None, :], :]  # (K, n, 3), without copying the other pixels
    m[: pix.size] = vals.transpose(1, 2, 0)
    return m.reshape(3 * TILE, keep.size)


def _factor(m: np.ndarray, budget2: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Smallest-rank (U, B) with ||m - U B^T||_F^2 <= budget2 (measured in float32 factors).
    Returns U (rows, r) float32, B (K, r) float32 and the measured squared error."""
    rows, k = m.shape
    total = float(np.sum(m * m))
    if total <= budget2:
        return np.zeros((rows, 0), np.float32), np.zeros((k, 0), np.float32), total
    small_side_rows = rows <= k
    g = m @ m.T if small_side_rows else m.T @ m
    ev, vec = np.linalg.eigh(g)
    ev, vec = ev[::-1], vec[:, ::-1]
    ev = np.maximum(ev, 0.0)
    resid = total - np.cumsum(ev)  # predicted squared error for rank 1, 2, ...
    r = int(np.searchsorted(-resid, -budget2)) + 1  # first rank whose residual <= budget
    full = min(rows, k)
    r = min(max(r, 1), full)
    while True:
        if small_side_rows:
            u = vec[:, :r]
            bm = m.T @ u  # (K, r)
        else:
            bm = vec[:, :r]
            u = m @ bm  # (rows, r)
        u32, b32 = u.astype(np.float32), bm.astype(np.float32)
        err = m - u32.astype(np.float64) @ b32.astype(np.float64).T
        e2 = float(np.sum(err * err))
        if e2 <= budget2 or r >= full:
            return u32, b32, e2
        r = min(full, max(r + 1, int(math.ceil(r * 1.25))))


def compress_store(flat: np.ndarray, keep: np.ndarray, pix: np.ndarray, tol: float
                   ) -> tuple[LowRankStore, dict]:
    """Low-rank factors of ``flat[keep][:, pix]`` ((K, h*w, 3) float32 images, kept lights, stored
    pixels in tile order) with relative RMS error <= ``tol`` per the module docstring; the
    report holds the measured errors."""
    n = pix.size
    k = keep.size
    n_tiles = (n + TILE - 1) // TILE
    sq = 0.0
    vmax = 0.0
    for t in range(n_tiles):
        v = flat[keep[:, None], pix[None, t * TILE:(t + 1) * TILE], :].astype(np.float64)
        sq += float(np.sum(v * v))
        vmax = max(vmax, float(np.max(np.abs(v))) if v.size else 0.0)
    def one(t: int):
        p = pix[t * TILE:(t + 1) * TILE]
        m = _tile_matrix(flat, keep, p)
        u, b, e2 = _factor(m, tol * tol * sq * (p.size / n))  # this tile's share of the squared error
        if u.shape[1]:
            mx = float(np.max(np.abs(m - u.astype(np.float64) @ b.astype(np.float64).T)))
        else:
            mx = float(np.max(np.abs(m)))
        return u, b, e2, mx, p.size

    # tiles in parallel threads (LAPACK releases the GIL), each with a single-threaded BLAS: a
    # multi-threaded OpenBLAS on a shared 2-core machine was measured 5-10x slower per call
    from concurrent.futures import ThreadPoolExecutor

    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"), ThreadPoolExecutor(max(1, nb.get_num_threads())) as pool:
        results = list(pool.map(one, range(n_tiles)))
    us, bs, ranks = [], [], np.zeros(n_tiles, np.int64)
    e2_total = 0.0
    worst_tile = 0.0
    max_abs = 0.0
    for t, (u, b, e2, mx, npx) in enumerate(results):
        ranks[t] = u.shape[1]
        us.append(u.ravel())
        bs.append(b.ravel())
        e2_total += e2
        worst_tile = max(worst_tile, math.sqrt(e2 / (3 * npx * k)))
        max_abs = max(max_abs, mx)
    u_sizes = 3 * TILE * ranks
    b_sizes = k * ranks
    u_off = np.concatenate([[0], np.cumsum(u_sizes)[:-1]]).astype(np.int64)
    b_off = np.concatenate([[0], np.cumsum(b_sizes)[:-1]]).astype(np.int64)
    store = LowRankStore(u=np.ascontiguousarray(np.concatenate(us)).astype(np.float32),
                         b=np.ascontiguousarray(np.concatenate(bs)).astype(np.float32),
                         u_off=u_off, b_off=b_off, rank=ranks, n_lights=int(k), n_rows=int(n))
    rms = math.sqrt(sq / (3 * n * k)) if n and k else 0.0
    report = dict(method="svd_per_tile", tile_pixels=TILE, pixel_order=f"{BLOCK}x{BLOCK} blocks",
                  requested_rel_rms=float(tol), rel_rms_error=math.sqrt(e2_total / sq) if sq > 0 else 0.0,
                  worst_tile_rel_rms=worst_tile / rms if rms > 0 else 0.0,
                  max_abs_error=max_abs, max_abs_error_rel_to_max=max_abs / vmax if vmax > 0 else 0.0,
                  rank_mean=float(ranks.mean()) if n_tiles else 0.0, rank_max=int(ranks.max()) if n_tiles else 0,
                  n_tiles=int(n_tiles), bytes=store.nbytes)
    return store, report
