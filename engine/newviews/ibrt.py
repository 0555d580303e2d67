"""Image-based ray tracing (IBRT) through a layered depth cube (paper 000, section 4.3).

A ray is intersected with the LDC's samples instead of the scene's triangles, so the
result only depends on the baked representation (reflections and hole filling in the
LDC renderer need nothing but the bake).

**Surface model.** Every sample of an LDI stands for the piece of its tangent plane (the
plane through the sample with its geometric normal) that lies over its pixel, dilated by
``margin`` pixels on each side (default 0.05, only so rounding can't open a crack between
two patches of one plane). A ray hits a sample when it crosses that patch at ``t_min < t <
t_max``; the nearest crossing over all samples of the three LDIs is the hit. Flat surfaces
are reproduced exactly; on smooth curved ones neighbouring patches meet with steps of
O(h^3 / radius^2), and a ray that slips through a seam in one LDI meets the surface in
another (measured: no grazing ray leaks at margin 0; a wider margin only fattens
silhouettes and makes rays leaving curved surfaces hit their own neighbouring patches, see
docs/ldc.md). Samples whose LDI direction is grazing to the surface (``|n_g . w| <
min_cos``, 0.5 as in the warp) are left to the other LDIs: every normal has a component
>= 1/sqrt(3) along some axis, so every surface is usable in at least one LDI.

**Acceleration** (``build_accel``): per LDI and per depth layer a quadtree over the pixels
(node at level l covers 2^l x 2^l pixels; only live nodes are stored, the children of a node
contiguously in Morton order) with per node

- ``lo``: the minimum patch depth over the node's pixels in this layer AND all deeper
  layers (a suffix minimum, so it also bounds every deeper layer),
- ``hi``: the maximum patch depth of this layer's samples in the node,
- ``link``: the cross-link to the twin node (same block) in the next layer's quadtree, -1
  when the block is empty there (a pixel holds a layer-(i+1) sample only if it holds a
  layer-i one, so the next layer's tree is a subset).

Traversal (the paper's ``Traverse``): with ``[z_in, z_out]`` the depth interval the ray
spans inside the node's (dilated) block, a node is skipped when ``z_out < lo`` (the ray
passes in front of everything from this layer down), handed to its cross-link when
``z_in > hi`` (the ray passes behind this layer: only deeper layers can be hit), else its
live children are visited in the order the ray meets them; a level-1 node tests the patches
of its pixels' samples from its layer down. Node bounds are float32, rounded outwards; the
patch tests are float64 (docs/hard-cases.md #6). The LDIs are traced in the order of decreasing
``|d . w|`` (shortest projection first) sharing the best ``t`` found so far, so the second
and third LDIs only search in front of the first one's hit.

Memory layout of the traversal (built per accel / per ``trace_args``, never stored): one
16-byte record per node (``IBRTAccel.node_records``: lo, hi, first << 4 | mask, link) and one
32-byte record per sample (depth and the geometric normal as float64), the samples of each
LDI re-ordered so the pixels follow their Morton code (a quadtree block's pixels are
consecutive); hits are reported with the LDI's sample indices, bit for bit what the separate
arrays give (``bench/ibrt_throughput.py --ab``).

``trace_linear`` is the same surface model without the quadtree (every pixel whose dilated
square the projected ray crosses, row by row): it returns the same hits and is the baseline
for the quadtree's savings.

Conventions: ``t`` is the distance along the normalised direction; ``side`` 0 when the ray
arrives on the side the geometric normal points to (``d . n_g < 0``), 1 otherwise, as in
``LDCAxis.diffuse``.

**Rays leaving a surface** (reflections, hole-filling rays from a sample) need no spawn
offset: a patch the origin lies on (within ``self_eps`` pixels of its plane, default 0.25,
and over its pixel give or take one) is never hit. On curved surfaces the neighbouring
patches of the origin's surface are up to a few tenths of a pixel off it; pass
``origin_normals`` (the surface normal at each origin) and crossings within
``SELF_PIXELS * h / |cos|`` (2 pixels along the normal) of patches facing like the
origin's surface and crossed outwards are skipped as well. Consequence: surfaces closer
than ``self_eps`` pixels to a ray's origin are treated as the surface it starts on (pass
``self_eps=0`` for rays that start in free space right next to a surface).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

import numba as nb
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.errors import InvalidInputError
from engine.newviews.ldc import LDC
from engine.raycast import check_rays
from engine.sched import next_block

DEFAULT_MARGIN = 0.05
DEFAULT_MIN_COS = 0.5
DEFAULT_SELF_EPS = 0.25
SELF_PIXELS = 2.0
MAX_TREE_LEVELS = 24
_STACK = 4 * MAX_TREE_LEVELS + 8
_CHUNK = 32

_ARRAY_FIELDS = ("root_level", "size", "node_base", "layer_root", "lo", "hi", "first", "mask", "link",
                 "zrange", "uvrange", "n_samples")


@dataclass(frozen=True)
class IBRTAccel:
    """Per-axis, per-layer min/max-depth quadtrees with cross-links (module docstring).

    Nodes of the three axes are concatenated: axis a owns ``node_base[a]:node_base[a+1]``.
    ``layer_root`` (3, L) int32 root node of each layer (-1: layer empty); ``root_level`` (3,)
    and ``size`` (3,) (= 2**root_level, the quadtree's side in pixels); per node ``lo``/``hi``
    float32, ``first`` int32 first child (-1 for level-1 nodes, whose children are pixels),
    ``mask`` uint8 live children (bit ``2 cy + cx``), ``link`` int32; ``zrange`` (3, 2) the
    depth range and ``uvrange`` (3, 4) the pixel box (u0, u1, v0, v1) of all usable patches of
    an axis (rays are clipped to both before the traversal); ``n_samples`` (3,) of the LDC it
    was built for.
    """

    margin: float
    min_cos: float
    root_level: np.ndarray
    size: np.ndarray
    node_base: np.ndarray
    layer_root: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    first: np.ndarray
    mask: np.ndarray
    link: np.ndarray
    zrange: np.ndarray
    uvrange: np.ndarray
    n_samples: np.ndarray

    @cached_property
    def node_records(self) -> np.ndarray:
        """(n_nodes, 4) int32, one 16-byte record per node for the traversal: ``lo`` and ``hi``
        (float32 bit patterns, read through a float32 view), ``first << 4 | mask`` and ``link``.
        Built on first use, not stored (``to_arrays`` keeps the separate arrays): a node visit
        touches one cache line instead of five arrays."""
        n = self.n_nodes
        if n >= 2**27:
            raise InvalidInputError(f"IBRT quadtrees with {n} nodes are too large for the packed node records")
        rec = np.empty((n, 4), dtype=np.int32)
        rec[:, 0] = self.lo.view(np.int32)
        rec[:, 1] = self.hi.view(np.int32)
        rec[:, 2] = (self.first.astype(np.int32) << 4) | self.mask.astype(np.int32)
        rec[:, 3] = self.link
        return rec

    @property
    def n_nodes(self) -> int:
        return int(self.lo.shape[0])

    @property
    def nbytes(self) -> int:
        return int(sum(getattr(self, k).nbytes for k in _ARRAY_FIELDS))

    def to_arrays(self) -> dict[str, np.ndarray]:
        d = {k: getattr(self, k) for k in _ARRAY_FIELDS}
        d["params"] = np.array([self.margin, self.min_cos], dtype=np.float64)
        return d

    @classmethod
    def from_arrays(cls, d) -> IBRTAccel:
        missing = [k for k in (*_ARRAY_FIELDS, "params") if k not in d]
        if missing:
            raise InvalidInputError(f"IBRT accel arrays lack {missing}")
        p = np.asarray(d["params"], dtype=np.float64)
        dt = {"root_level": np.int64, "size": np.int64, "node_base": np.int64, "layer_root": np.int32,
              "lo": np.float32, "hi": np.float32, "first": np.int32, "mask": np.uint8, "link": np.int32,
              "zrange": np.float64, "uvrange": np.float64, "n_samples": np.int64}
        arrs = {k: np.ascontiguousarray(d[k], dtype=dt[k]) for k in _ARRAY_FIELDS}
        n = arrs["lo"].shape[0]
        ok = (p.shape == (2,) and all(arrs[k].shape == (n,) for k in ("hi", "first", "mask", "link"))
              and arrs["root_level"].shape == (3,) and arrs["size"].shape == (3,) and arrs["node_base"].shape == (4,)
              and arrs["zrange"].shape == (3, 2) and arrs["uvrange"].shape == (3, 4) and arrs["n_samples"].shape == (3,)
              and arrs["layer_root"].ndim == 2 and arrs["layer_root"].shape[0] == 3)
        ok = ok and bool(np.all((arrs["root_level"] >= 1) & (arrs["root_level"] <= MAX_TREE_LEVELS))
                         and np.array_equal(arrs["size"], 1 << arrs["root_level"])
                         and arrs["node_base"][0] == 0 and arrs["node_base"][3] == n
                         and np.all(np.diff(arrs["node_base"]) >= 0))
        for k in ("first", "link", "layer_root"):
            ok = ok and bool(np.all((arrs[k] >= -1) & (arrs[k] < n)))
        if not ok:
            raise InvalidInputError("IBRT accel arrays are inconsistent (corrupted or from another version)")
        return cls(margin=float(p[0]), min_cos=float(p[1]), **arrs)


@dataclass
class IBRTHits:
    """First hits of a batch of rays (see the module docstring for t and side)."""

    hit: np.ndarray  # (n,) bool
    axis: np.ndarray  # (n,) int8, -1 on miss
    sample: np.ndarray  # (n,) int64 index into that axis' sample arrays, -1 on miss
    side: np.ndarray  # (n,) int8
    t: np.ndarray  # (n,) float64, inf on miss
    point: np.ndarray  # (n, 3) float64 (0 on miss)
    n_steps: int  # quadtree nodes + pixels visited (trace_linear: pixels visited)
    n_tests: int = 0  # patch tests (sample visits)


# ----------------------------------------------------------------------------- build


def _part1by1(x: np.ndarray) -> np.ndarray:
    x = x.astype(np.uint64) & np.uint64(0xFFFFFFFF)
    for s, m in ((16, 0x0000FFFF0000FFFF), (8, 0x00FF00FF00FF00FF), (4, 0x0F0F0F0F0F0F0F0F),
                 (2, 0x3333333333333333), (1, 0x5555555555555555)):
        x = (x | (x << np.uint64(s))) & np.uint64(m)
    return x


def _morton(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return (_part1by1(x) | (_part1by1(y) << np.uint64(1))).astype(np.int64)


def _f32_down(a: np.ndarray) -> np.ndarray:
    b = a.astype(np.float32)
    with np.errstate(invalid="ignore"):
        up = b.astype(np.float64) > a
    b[up] = np.nextafter(b[up], np.float32(-np.inf))
    return b


def _f32_up(a: np.ndarray) -> np.ndarray:
    b = a.astype(np.float32)
    with np.errstate(invalid="ignore"):
        dn = b.astype(np.float64) < a
    b[dn] = np.nextafter(b[dn], np.float32(np.inf))
    return b


def _frame_arrays(ldc: LDC) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(3, 3) int64 world component of u, v, w per axis, (3, 3) frame origins, (3,) h,
    (3, 2) int64 nu/nv. The LDC's frames are axis-aligned (``axis_frame``); others are refused."""
    perm = np.zeros((3, 3), dtype=np.int64)
    org = np.zeros((3, 3))
    hs = np.zeros(3)
    res = np.zeros((3, 2), dtype=np.int64)
    for a, ax in enumerate(ldc.axes):
        f = ax.ldi.frame
        for j, vec in enumerate((f.u, f.v, f.w)):
            k = int(np.argmax(np.abs(vec)))
            if vec[k] != 1.0 or np.count_nonzero(vec) != 1:
                raise InvalidInputError(f"IBRT needs axis-aligned LDC frames; axis {a} has {vec.tolist()}")
            perm[a, j] = k
        org[a] = f.origin
        hs[a] = f.h
        res[a] = (f.nu, f.nv)
    return perm, org, hs, res


def patch_extents(ldc: LDC, axis: int, margin: float = DEFAULT_MARGIN,
                  min_cos: float = DEFAULT_MIN_COS) -> tuple[np.ndarray, np.ndarray]:
    """(usable (n,) bool, half depth extent (n,) float64) of every sample's dilated patch."""
    ax = ldc.axes[axis]
    f = ax.ldi.frame
    n = ax.geo_normal.astype(np.float64)
    nu, nv, nw = n @ f.u, n @ f.v, n @ f.w
    usable = np.abs(nw) >= min_cos
    with np.errstate(divide="ignore", invalid="ignore"):
        ext = (0.5 + margin) * f.h * (np.abs(nu) + np.abs(nv)) / np.abs(nw)
    return usable, np.where(usable, ext, np.inf)


def _build_axis(ldc: LDC, axis: int, margin: float, min_cos: float):
    ax = ldc.axes[axis]
    f = ax.ldi.frame
    nu, nv = f.nu, f.nv
    counts = ax.ldi.counts()
    n_layers = int(counts.max()) if counts.size else 0
    size = 2
    while size < max(nu, nv):
        size *= 2
    root_level = int(round(math.log2(size)))
    if root_level > MAX_TREE_LEVELS:
        raise InvalidInputError(f"LDI of {nu}x{nv} pixels is too large for the IBRT quadtree")
    usable, ext = patch_extents(ldc, axis, margin, min_cos)
    depth = ax.ldi.depth
    lo_s = np.where(usable, depth - ext, np.inf)
    hi_s = np.where(usable, depth + ext, -np.inf)
    if usable.any():
        zrange = np.array([lo_s[usable].min(), hi_s[usable].max()])
    else:
        zrange = np.array([np.inf, -np.inf])
    starts = ax.ldi.offsets[:-1]
    pix = np.arange(nu * nv)
    suffix = np.full(nu * nv, np.inf)
    # per layer (deepest first for the suffix minimum), per level 1..root_level: (Morton codes
    # sorted, lo, hi, live-children mask, index of each node's first child in the level below)
    layers: list[list[tuple[np.ndarray, ...]]] = [[] for _ in range(n_layers)]
    for L in range(n_layers - 1, -1, -1):
        has = counts > L
        idx = starts[has] + L
        suffix[has] = np.minimum(suffix[has], lo_s[idx])
        hi_px = np.full(nu * nv, -np.inf)
        hi_px[has] = hi_s[idx]
        k = pix[has & (suffix < np.inf)]  # live: a usable sample in this layer or deeper
        code = _morton(k % nu, k // nu)
        order = np.argsort(code, kind="stable")
        code, lo, hi = code[order], suffix[k][order], hi_px[k][order]
        levels = []
        for _lev in range(1, root_level + 1):
            parent = code >> 2
            start = np.flatnonzero(np.r_[True, parent[1:] != parent[:-1]]) if parent.size else np.zeros(0, np.int64)
            bits = (np.uint8(1) << (code & 3).astype(np.uint8)).astype(np.uint8)
            code = parent[start]
            lo = np.minimum.reduceat(lo, start) if start.size else lo[:0]
            hi = np.maximum.reduceat(hi, start) if start.size else hi[:0]
            mask = np.bitwise_or.reduceat(bits, start) if start.size else bits[:0]
            levels.append((code, lo, hi, mask, start))
        layers[L] = levels
    live0 = np.flatnonzero(suffix < np.inf)
    if live0.size:
        uvrange = np.array([(live0 % nu).min(), (live0 % nu).max() + 1, (live0 // nu).min(), (live0 // nu).max() + 1],
                           dtype=np.float64)
    else:
        uvrange = np.array([0.0, 0.0, 0.0, 0.0])
    # global numbering: layer 0 root level first ... level 1, then layer 1, ...
    base: list[list[int]] = []
    total = 0
    for L in range(n_layers):
        bl = [0] * (root_level + 1)
        for lev in range(root_level, 0, -1):
            bl[lev] = total
            total += layers[L][lev - 1][0].shape[0]
        base.append(bl)
    lo_all = np.empty(total)
    hi_all = np.empty(total)
    first = np.full(total, -1, dtype=np.int32)
    mask_all = np.zeros(total, dtype=np.uint8)
    link = np.full(total, -1, dtype=np.int32)
    layer_root = np.full(n_layers, -1, dtype=np.int32)
    if total >= 2**31 - 1:
        raise InvalidInputError("IBRT quadtree has too many nodes")
    for L in range(n_layers):
        for lev in range(root_level, 0, -1):
            code, lo, hi, mask, start = layers[L][lev - 1]
            b = base[L][lev]
            sl = slice(b, b + code.shape[0])
            lo_all[sl] = lo
            hi_all[sl] = hi
            mask_all[sl] = mask
            if lev >= 2:
                first[sl] = base[L][lev - 1] + start
            if L + 1 < n_layers:
                ncode = layers[L + 1][lev - 1][0]
                pos = np.searchsorted(ncode, code)
                ok = pos < ncode.shape[0]
                ok[ok] = ncode[pos[ok]] == code[ok]
                link[sl] = np.where(ok, base[L + 1][lev] + pos, -1)
        if layers[L][root_level - 1][0].shape[0]:
            layer_root[L] = base[L][root_level]
    return (root_level, size, layer_root, _f32_down(lo_all), _f32_up(hi_all), first, mask_all, link, zrange,
            ax.n_samples, uvrange)


def build_accel(ldc: LDC, *, margin: float = DEFAULT_MARGIN, min_cos: float = DEFAULT_MIN_COS) -> IBRTAccel:
    """Build the per-axis, per-layer min/max-depth quadtrees with cross-links for ``ldc``.

    ``margin``: patch dilation in pixels, in [0, 1); ``min_cos``: samples with ``|n_g . w|``
    below it are left to the other LDIs, in (0, 1/sqrt(3)] so every surface stays usable."""
    if not (0.0 <= margin < 1.0):
        raise InvalidInputError(f"margin must be in [0, 1) pixels, got {margin!r}")
    if not (0.0 < min_cos <= 1.0 / math.sqrt(3.0)):
        raise InvalidInputError(f"min_cos must be in (0, {1.0 / math.sqrt(3.0):.4f}], got {min_cos!r}")
    parts = [_build_axis(ldc, a, margin, min_cos) for a in range(3)]
    n_layers = max(1, max(p[2].shape[0] for p in parts))
    layer_root = np.full((3, n_layers), -1, dtype=np.int32)
    node_base = np.zeros(4, dtype=np.int64)
    for a, p in enumerate(parts):
        node_base[a + 1] = node_base[a] + p[3].shape[0]
    if node_base[3] >= 2**31 - 1:
        raise InvalidInputError("IBRT quadtrees have too many nodes")
    firsts, links = [], []
    for a, p in enumerate(parts):
        lr = p[2]
        layer_root[a, :lr.shape[0]] = np.where(lr >= 0, lr + node_base[a], -1)
        firsts.append(np.where(p[5] >= 0, p[5] + node_base[a], -1).astype(np.int32))
        links.append(np.where(p[7] >= 0, p[7] + node_base[a], -1).astype(np.int32))
    return IBRTAccel(
        margin=float(margin), min_cos=float(min_cos),
        root_level=np.array([p[0] for p in parts], dtype=np.int64),
        size=np.array([p[1] for p in parts], dtype=np.int64),
        node_base=node_base, layer_root=layer_root,
        lo=np.concatenate([p[3] for p in parts]), hi=np.concatenate([p[4] for p in parts]),
        first=np.concatenate(firsts), mask=np.concatenate([p[6] for p in parts]), link=np.concatenate(links),
        zrange=np.stack([p[8] for p in parts]), uvrange=np.stack([p[10] for p in parts]),
        n_samples=np.array([p[9] for p in parts], dtype=np.int64))


# ----------------------------------------------------------------------------- kernels


@intrinsic
def _prefetch(typingctx, arr, i):
    """Hint the CPU to load the cache line holding ``arr[i]`` (1-D array). Only a hint: an
    out-of-range i is never dereferenced, so no bounds check is needed."""

    def codegen(context, builder, sig, args):
        aryty = sig.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        r = context.cast(builder, args[1], sig.args[1], types.intp)
        ptr = cgutils.get_item_pointer2(context, builder, data=ary.data, shape=cgutils.unpack_tuple(builder, ary.shape),
                                        strides=cgutils.unpack_tuple(builder, ary.strides), layout=aryty.layout,
                                        inds=[r], wraparound=False, boundscheck=False)
        i8p = ir.PointerType(ir.IntType(8))
        i32 = ir.IntType(32)
        fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32]),
                                            "llvm.prefetch.p0")
        builder.call(fn, [builder.bitcast(ptr, i8p), i32(0), i32(3), i32(1)])  # read, keep in all levels, data
        return context.get_dummy_value()

    return types.void(arr, i), codegen


@nb.njit(cache=True, nogil=True)
def _rank(m, c):
    """Number of live children before child c (bits below c of the 4-bit mask m)."""
    mm = m & ((1 << c) - 1)
    return (mm & 1) + ((mm >> 1) & 1) + ((mm >> 2) & 1)


@nb.njit(cache=True, nogil=True)
def _spread(x):
    """The bits of x (< 2**24) moved to the even bit positions (half a Morton code)."""
    x &= 0xFFFFFF
    x = (x | (x << 16)) & 0x0000FFFF0000FFFF
    x = (x | (x << 8)) & 0x00FF00FF00FF00FF
    x = (x | (x << 4)) & 0x0F0F0F0F0F0F0F0F
    x = (x | (x << 2)) & 0x3333333333333333
    return (x | (x << 1)) & 0x5555555555555555


@nb.njit(cache=True, nogil=True)
def _slab(x0, x1, o, d, inv, t0, t1):
    """Clip [t0, t1] to the parameter range where o + t d lies in [x0, x1] (inv = 1 / d)."""
    if d == 0.0:
        if o < x0 or o > x1:
            return 1.0, 0.0
        return t0, t1
    ta = (x0 - o) * inv
    tb = (x1 - o) * inv
    if ta > tb:
        ta, tb = tb, ta
    return max(t0, ta), min(t1, tb)


@nb.njit(cache=True, nogil=True)
def _icl(x, n):
    """ceil(x) as an int, x clamped to [-1, n + 1] first (far origins: no float -> int overflow)."""
    return int(math.ceil(min(max(x, -1.0), n + 1.0)))


@nb.njit(cache=True, nogil=True)
def _ifl(x, n):
    return int(math.floor(min(max(x, -1.0), n + 1.0)))


@nb.njit(cache=True, nogil=True)
def _patch_t(px, py, dep, g0, g1, g2, pu, pv, pw, ou, ov, ow, du, dv, d0, d1, d2, h, lim, min_cos, self_eps,
             s0, s1, s2, sdn, st, t_lo, t_hi):
    """Parameter t of the ray's crossing with a sample's dilated tangent patch, inf if none.

    Sample: pixel (px, py), depth ``dep``, geometric normal g (world). Ray in the LDI's frame:
    (ou, ov) + t (du, dv) in pixels, ``ow`` depth of the origin; (d0, d1, d2) the world
    direction. s0..s2 / sdn / st: origin normal, d . normal, self distance (module doc)."""
    nw = g0 if pw == 0 else (g1 if pw == 1 else g2)
    if abs(nw) < min_cos:
        return np.inf
    nu_ = g0 if pu == 0 else (g1 if pu == 1 else g2)
    nv_ = g0 if pv == 0 else (g1 if pv == 1 else g2)
    den = g0 * d0 + g1 * d1 + g2 * d2
    if den == 0.0:
        return np.inf
    cu = (px + 0.5 - ou) * h
    cv = (py + 0.5 - ov) * h
    num = cu * nu_ + cv * nv_ + (dep - ow) * nw
    if abs(num) <= self_eps * h and abs(cu) <= (lim + 1.0) * h and abs(cv) <= (lim + 1.0) * h:
        return np.inf  # the ray starts on this patch: it is the surface the ray leaves
    t = num / den
    if not (t > t_lo and t < t_hi):
        return np.inf
    if t < st and den * sdn > 0.0 and g0 * s0 + g1 * s1 + g2 * s2 > 0.5:
        return np.inf  # leaving the origin's surface through a neighbouring patch of it
    if abs(ou + t * du - (px + 0.5)) <= lim and abs(ov + t * dv - (py + 0.5)) <= lim:
        return t
    return np.inf


@nb.njit(cache=True, nogil=True)
def _trace_chunk(ci, o, d, tmin, tmax, selfinfo, perm, org, hs, res, offs_t, samp_t, use_tree, layer_root,
                 root_level, nodef, nodei, zr, uvr, margin, min_cos, self_eps, out_axis, out_sample, out_t, work):
    """Rays ci * _CHUNK ... of a batch, one after the other (the traversal is written out
    here rather than called per ray and axis: numba calls with many array arguments cost
    more than a whole traversal)."""
    n = o.shape[0]
    # scratch written per step: padded so no other thread's scratch shares its cache lines
    stk_i = np.empty((_STACK + 4, 5), dtype=np.int64)[2:_STACK + 2]
    stk_f = np.empty((_STACK + 16, 2))[8:_STACK + 8]
    ct0 = np.empty(36)[16:20]
    ct1 = np.empty(36)[16:20]
    cid = np.empty(36, dtype=np.int64)[16:20]
    order = np.empty(35, dtype=np.int64)[16:19]
    key = np.empty(35)[16:19]
    lim = 0.5 + margin
    n_steps = 0
    n_tests = 0
    for r in range(ci * _CHUNK, min(n, (ci + 1) * _CHUNK)):
        d0, d1, d2 = d[r, 0], d[r, 1], d[r, 2]
        s0, s1, s2, sdn, st = selfinfo[r, 0], selfinfo[r, 1], selfinfo[r, 2], selfinfo[r, 3], selfinfo[r, 4]
        t_lo = tmin[r]
        best_t = tmax[r]
        best_s = -1
        best_a = -1
        for a in range(3):  # shortest projection (largest |d . w|) first
            order[a] = a
            key[a] = -abs(d[r, perm[a, 2]])
        for i in range(1, 3):
            j = i
            while j > 0 and key[order[j - 1]] > key[order[j]]:
                order[j - 1], order[j] = order[j], order[j - 1]
                j -= 1
        for q in range(3):
            a = order[q]
            pu, pv, pw = perm[a, 0], perm[a, 1], perm[a, 2]
            h = hs[a]
            ou = (o[r, pu] - org[a, pu]) / h
            ov = (o[r, pv] - org[a, pv]) / h
            ow = o[r, pw] - org[a, pw]
            du = d[r, pu] / h
            dv = d[r, pv] / h
            dw = d[r, pw]
            iu = 1.0 / du if du != 0.0 else 0.0
            iv = 1.0 / dv if dv != 0.0 else 0.0
            iw = 1.0 / dw if dw != 0.0 else 0.0
            offs = offs_t[a]
            samp = samp_t[a]
            nu = res[a, 0]
            nv = res[a, 1]
            z0 = zr[a, 0]
            z1 = zr[a, 1]
            if not (z0 <= z1):
                continue  # no usable patch in this LDI
            eps = 1e-7 * h + 1e-12 * (abs(ow) + abs(z0) + abs(z1))  # depth slack for rounding
            if not use_tree:
                # ---- linear march: every pixel whose dilated square the projected ray crosses
                t0, t1 = _slab(uvr[a, 0] - margin, uvr[a, 1] + margin, ou, du, iu, t_lo, best_t)
                t0, t1 = _slab(uvr[a, 2] - margin, uvr[a, 3] + margin, ov, dv, iv, t0, t1)
                t0, t1 = _slab(z0 - eps, z1 + eps, ow, dw, iw, t0, t1)
                if not (t0 <= t1):
                    continue
                va = ov + t0 * dv
                vb = ov + t1 * dv
                jlo = max(0, _icl(min(va, vb) - 1.0 - margin, nv))
                jhi = min(nv - 1, _ifl(max(va, vb) + margin, nv))
                for jj in range(jhi - jlo + 1):
                    j = jlo + jj if dv >= 0.0 else jhi - jj
                    r0, r1 = _slab(j - margin, j + 1.0 + margin, ov, dv, iv, t0, min(t1, best_t))
                    if not (r0 <= r1):
                        continue
                    ua = ou + r0 * du
                    ub = ou + r1 * du
                    ilo = max(0, _icl(min(ua, ub) - 1.0 - margin, nu))
                    ihi = min(nu - 1, _ifl(max(ua, ub) + margin, nu))
                    for ii in range(ihi - ilo + 1):
                        i = ilo + ii if du >= 0.0 else ihi - ii
                        n_steps += 1
                        k = _spread(i) | (_spread(j) << 1)
                        for s in range(offs[k], offs[k + 1]):
                            n_tests += 1
                            q = 4 * s
                            t = _patch_t(i, j, samp[q], samp[q + 1], samp[q + 2], samp[q + 3], pu, pv, pw, ou, ov, ow,
                                         du, dv, d0, d1, d2, h, lim, min_cos, self_eps, s0, s1, s2, sdn, st, t_lo,
                                         best_t)
                            if t < best_t:
                                best_t = t
                                best_s = s
                                best_a = a
                continue
            # ---- quadtree with cross-links
            root = layer_root[a, 0]
            if root < 0:
                continue
            rl = root_level[a]
            size = 1 << rl
            t0, t1 = _slab(uvr[a, 0] - margin, uvr[a, 1] + margin, ou, du, iu, t_lo, best_t)
            t0, t1 = _slab(uvr[a, 2] - margin, uvr[a, 3] + margin, ov, dv, iv, t0, t1)
            t0, t1 = _slab(z0 - eps, z1 + eps, ow, dw, iw, t0, t1)
            if not (t0 <= t1):
                continue
            # start at the deepest node whose block holds every pixel the dilated segment can touch
            ua = ou + t0 * du
            ub = ou + t1 * du
            va = ov + t0 * dv
            vb = ov + t1 * dv
            i0 = max(0, _icl(min(ua, ub) - 1.0 - margin, size))
            i1 = min(size - 1, _ifl(max(ua, ub) + margin, size))
            j0 = max(0, _icl(min(va, vb) - 1.0 - margin, size))
            j1 = min(size - 1, _ifl(max(va, vb) + margin, size))
            if i0 > i1 or j0 > j1:
                continue
            lev = rl
            node = root
            while lev > 1:
                sh = lev - 1
                if (i0 >> sh) != (i1 >> sh) or (j0 >> sh) != (j1 >> sh):
                    break
                c = ((j0 >> sh) & 1) * 2 + ((i0 >> sh) & 1)
                w = nodei[4 * node + 2]
                m = w & 15
                if not (m >> c) & 1:
                    node = -1  # nothing usable in this block, in any layer
                    break
                node = (w >> 4) + _rank(m, c)
                lev -= 1
                n_steps += 1
            if node < 0:
                continue
            # the node to visit next is kept in (node, lev, x0, y0, layer, t0, t1) when ``held``
            # (the root, then the first child the ray enters: it would be pushed and popped at
            # once); the other children wait on the stack, so the visiting order is the stack's
            x0 = (i0 >> lev) << lev
            y0 = (j0 >> lev) << lev
            layer = 0
            held = True
            sp = 0
            while True:
                if held:
                    held = False
                elif sp > 0:
                    sp -= 1
                    node = stk_i[sp, 0]
                    lev = stk_i[sp, 1]
                    x0 = stk_i[sp, 2]
                    y0 = stk_i[sp, 3]
                    layer = stk_i[sp, 4]
                    t0 = stk_f[sp, 0]
                    t1 = stk_f[sp, 1]
                else:
                    break
                t1 = min(t1, best_t)
                if not (t0 <= t1):
                    continue
                za = ow + t0 * dw
                zb = ow + t1 * dw
                zin = min(za, zb) - eps
                zout = max(za, zb) + eps
                # the ray passes in front of this layer and every deeper one here: skip; behind
                # this layer: follow the cross-links to the first deeper layer it can meet
                n_steps += 1
                while node >= 0 and zout >= nodef[4 * node] and zin > nodef[4 * node + 1]:
                    node = nodei[4 * node + 3]
                    layer += 1
                    n_steps += 1
                if node < 0 or zout < nodef[4 * node]:
                    continue
                half = 1 << (lev - 1)
                w = nodei[4 * node + 2]
                m = w & 15
                # parameter ranges of the low / high half along u and v (dilated), then the children
                xm = x0 + half
                ym = y0 + half
                ul0, ul1 = _slab(x0 - margin, xm + margin, ou, du, iu, t0, t1)
                uh0, uh1 = _slab(xm - margin, xm + half + margin, ou, du, iu, t0, t1)
                vl0, vl1 = _slab(y0 - margin, ym + margin, ov, dv, iv, t0, t1)
                vh0, vh1 = _slab(ym - margin, ym + half + margin, ov, dv, iv, t0, t1)
                nx = 0 if du >= 0.0 else 1
                ny = 0 if dv >= 0.0 else 1
                nc = 0
                for qq in range(4):  # near corner, the two side children, far corner
                    if qq == 0:
                        c = ny * 2 + nx
                    elif qq == 1:
                        c = ny * 2 + (1 - nx)
                    elif qq == 2:
                        c = (1 - ny) * 2 + nx
                    else:
                        c = (1 - ny) * 2 + (1 - nx)
                    if not (m >> c) & 1:
                        continue
                    if c & 1:
                        a0, a1 = uh0, uh1
                    else:
                        a0, a1 = ul0, ul1
                    if c >> 1:
                        a0 = max(a0, vh0)
                        a1 = min(a1, vh1)
                    else:
                        a0 = max(a0, vl0)
                        a1 = min(a1, vl1)
                    if not (a0 <= a1):
                        continue
                    ct0[nc] = a0
                    ct1[nc] = a1
                    cid[nc] = c
                    nc += 1
                for j in range(1, nc):  # only the side children can be out of order
                    if ct0[j - 1] > ct0[j]:
                        ct0[j - 1], ct0[j] = ct0[j], ct0[j - 1]
                        ct1[j - 1], ct1[j] = ct1[j], ct1[j - 1]
                        cid[j - 1], cid[j] = cid[j], cid[j - 1]
                if lev == 1:
                    # the block's pixels are consecutive in the Morton order, pixel c at kb + c
                    kb = _spread(x0) | (_spread(y0) << 1)
                    for j in range(nc):
                        _prefetch(samp, 4 * (offs[kb + cid[j]] + layer))
                    for j in range(nc):
                        if ct0[j] >= best_t:
                            break
                        c = cid[j]
                        px = x0 + (c & 1)
                        py = y0 + (c >> 1)
                        n_steps += 1
                        k = kb + c
                        for s in range(offs[k] + layer, offs[k + 1]):
                            n_tests += 1
                            q = 4 * s
                            t = _patch_t(px, py, samp[q], samp[q + 1], samp[q + 2], samp[q + 3], pu, pv, pw, ou, ov, ow,
                                         du, dv, d0, d1, d2, h, lim, min_cos, self_eps, s0, s1, s2, sdn, st, t_lo,
                                         best_t)
                            if t < best_t:
                                best_t = t
                                best_s = s
                                best_a = a
                else:
                    fc = w >> 4
                    for j in range(nc - 1, 0, -1):  # reversed: the first child the ray enters pops first
                        c = cid[j]
                        stk_i[sp, 0] = fc + _rank(m, c)
                        stk_i[sp, 1] = lev - 1
                        stk_i[sp, 2] = x0 + (c & 1) * half
                        stk_i[sp, 3] = y0 + (c >> 1) * half
                        stk_i[sp, 4] = layer
                        stk_f[sp, 0] = ct0[j]
                        stk_f[sp, 1] = ct1[j]
                        sp += 1
                    if nc > 0:  # the first one is visited next without the round trip through the stack
                        c = cid[0]
                        node = fc + _rank(m, c)
                        lev -= 1
                        x0 += (c & 1) * half
                        y0 += (c >> 1) * half
                        t0 = ct0[0]
                        t1 = ct1[0]
                        held = True
        out_axis[r] = best_a
        out_sample[r] = best_s  # record index, mapped to the LDI's sample index by the caller
        out_t[r] = best_t if best_a >= 0 else np.inf
    work[ci, 0] = n_steps
    work[ci, 1] = n_tests


@nb.njit(cache=True, nogil=True, parallel=True)
def _trace_kernel(groups, o, d, tmin, tmax, selfinfo, perm, org, hs, res, offs_t, samp_t, use_tree,
                  layer_root, root_level, nodef, nodei, zr, uvr, margin, min_cos, self_eps, out_axis, out_sample, out_t,
                  work):
    # the ``groups`` threads take chunks from a shared counter (``engine.sched``): neighbouring
    # rays cost alike (a mirror sphere's rays are contiguous), and a core may be busy elsewhere
    nch = work.shape[0]
    counter = np.zeros(1, np.int64)
    for _ in nb.prange(groups):
        while True:
            ci = next_block(counter)
            if ci >= nch:
                break
            _trace_chunk(ci, o, d, tmin, tmax, selfinfo, perm, org, hs, res, offs_t, samp_t, use_tree,
                         layer_root, root_level, nodef, nodei, zr, uvr, margin, min_cos, self_eps, out_axis,
                         out_sample, out_t, work)


# ----------------------------------------------------------------------------- API


def _rays(origins, dirs, t_min, t_max) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    o, d = check_rays(origins, dirs)
    ln = np.linalg.norm(d, axis=1)
    if np.any(ln == 0.0):
        raise InvalidInputError("dirs must be non-zero vectors")
    d = np.ascontiguousarray(d / ln[:, None])
    n = o.shape[0]
    tlo = np.ascontiguousarray(np.broadcast_to(np.asarray(t_min, dtype=np.float64), (n,)))
    thi = np.ascontiguousarray(np.broadcast_to(np.asarray(t_max, dtype=np.float64), (n,)))
    if np.any(np.isnan(tlo)) or np.any(tlo < 0) or np.any(np.isinf(tlo)):
        raise InvalidInputError("t_min must be finite and >= 0")
    if np.any(np.isnan(thi)):
        raise InvalidInputError("t_max must not be NaN")
    return o, d, tlo.copy(), thi.copy()


def _check(ldc: LDC, accel: IBRTAccel) -> None:
    ns = np.array([ax.n_samples for ax in ldc.axes], dtype=np.int64)
    if not np.array_equal(ns, accel.n_samples):
        raise InvalidInputError(f"IBRT accel was built for an LDC with {accel.n_samples.tolist()} samples per axis, "
                                f"this LDC has {ns.tolist()}: rebuild it with build_accel(ldc)")


@nb.njit(cache=True, nogil=True)
def _self_info(d, nrm, h, out):
    """Per ray: the origin's unit normal, d . normal and the self distance (module docstring)."""
    for i in range(d.shape[0]):
        n0, n1, n2 = nrm[i, 0], nrm[i, 1], nrm[i, 2]
        ln = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        if ln > 0.0:
            n0, n1, n2 = n0 / ln, n1 / ln, n2 / ln
        else:
            n0 = n1 = n2 = 0.0
        dn = d[i, 0] * n0 + d[i, 1] * n1 + d[i, 2] * n2
        out[i, 0], out[i, 1], out[i, 2], out[i, 3] = n0, n1, n2, dn
        out[i, 4] = SELF_PIXELS * h / max(abs(dn), 0.2)


def sample_records(ax) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An LDC axis' samples as the trace kernel reads them: pixels in Morton order (the 2^l x
    2^l blocks of the quadtree are consecutive), each pixel's samples in layer order as in the
    LDI. Returns (offsets (size^2 + 1,) int64 indexed by the pixel's Morton code, size = the
    quadtree's side, records (n, 4) float64 = depth and the float32 geometric normal as
    float64 (exactly the values the patch test computes with), orig (n,) int64 the LDI sample
    index of each record). One 32-byte record per sample and neighbouring pixels close
    together: a patch test touches one cache line instead of two, a leaf block one or two."""
    f = ax.ldi.frame
    nu, nv = f.nu, f.nv
    size = 2
    while size < max(nu, nv):
        size *= 2
    offs = np.asarray(ax.ldi.offsets, dtype=np.int64)
    counts = np.diff(offs)
    pix = np.arange(nu * nv)
    code = _morton(pix % nu, pix // nu)
    cnt_m = np.zeros(size * size, dtype=np.int64)
    cnt_m[code] = counts
    offs_m = np.zeros(size * size + 1, dtype=np.int64)
    np.cumsum(cnt_m, out=offs_m[1:])
    order = pix[np.argsort(code, kind="stable")]  # pixels in Morton order
    # LDI sample index of every record: each pixel's run offs[k] .. offs[k + 1], pixels in that order
    run = np.repeat(offs[order] - offs_m[code[order]], counts[order])
    orig = np.arange(ax.n_samples, dtype=np.int64) + run
    rec = np.empty((ax.n_samples, 4))
    rec[:, 0] = np.asarray(ax.ldi.depth, dtype=np.float64)[orig]
    rec[:, 1:] = np.asarray(ax.geo_normal, dtype=np.float32)[orig]
    return offs_m, rec, orig


class TraceArrays(NamedTuple):
    """An LDC's frames and per-sample records as the trace kernel reads them (``trace_args``)."""

    perm: np.ndarray  #: (3, 3) int64 per axis the world component of u, v, w
    origin: np.ndarray  #: (3, 3) float64 per axis the frame's origin
    h: np.ndarray  #: (3,) float64 per axis the pixel size
    resolution: np.ndarray  #: (3, 2) int64 per axis nu, nv
    offsets: tuple  #: per axis (size^2 + 1,) int64 first record of each pixel, by Morton code
    records: tuple  #: per axis (n, 4) float64 depth and geometric normal per record
    sample: tuple  #: per axis (n,) int64 the LDI sample index of each record


def trace_args(ldc: LDC) -> TraceArrays:
    """The LDC's arrays as the trace kernel takes them (build once per LDC for ``trace_prepared``)."""
    perm, org, hs, res = _frame_arrays(ldc)
    parts = [sample_records(ax) for ax in ldc.axes]
    return TraceArrays(perm, org, hs, res, tuple(p[0] for p in parts), tuple(p[1] for p in parts),
                       tuple(p[2] for p in parts))


def trace_nbytes(args: TraceArrays, accel: IBRTAccel) -> int:
    """Memory of the traversal's structures for one LDC: the per-sample records of
    ``trace_args`` and the accel's packed node records once they are built (neither is
    stored; the accel's own arrays are ``accel.nbytes``)."""
    n = sum(a.nbytes for g in (args.offsets, args.records, args.sample) for a in g)
    if "node_records" in accel.__dict__:  # a cached_property, built on the first trace
        n += accel.node_records.nbytes
    return int(n)


def trace_prepared(ldc: LDC, args: TraceArrays, accel: IBRTAccel, o: np.ndarray, d: np.ndarray, *,
                   origin_normals: np.ndarray | None = None, self_eps: float = DEFAULT_SELF_EPS,
                   t_min: np.ndarray | None = None, t_max: np.ndarray | None = None,
                   use_tree: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray, int, int]:
    """``trace`` without the checks, for callers whose rays are already valid: o, d (n, 3)
    C-contiguous float64 with unit d, ``args = trace_args(ldc)``. Returns (axis (n,) int8,
    sample (n,) int64, t (n,) float64, n_steps, n_tests); no side or point (callers compute
    what they need in their own kernels)."""
    n = o.shape[0]
    selfinfo = np.zeros((n, 5))
    if origin_normals is not None and n:
        _self_info(d, np.ascontiguousarray(origin_normals, dtype=np.float64), float(ldc.h), selfinfo)
    tlo = np.zeros(n) if t_min is None else t_min
    thi = np.full(n, np.inf) if t_max is None else t_max
    out_axis = np.empty(n, dtype=np.int8)
    out_sample = np.empty(n, dtype=np.int64)
    out_t = np.empty(n)
    work = np.zeros(((n + _CHUNK - 1) // _CHUNK, 2), dtype=np.int64)
    if n:
        nodei = accel.node_records.reshape(-1)  # flat: 4 node / 4 s index without the strides
        _trace_kernel(max(1, nb.get_num_threads()), o, d, tlo, thi, selfinfo, args.perm, args.origin, args.h,
                      args.resolution, args.offsets, tuple(r.reshape(-1) for r in args.records), use_tree,
                      accel.layer_root, accel.root_level, nodei.view(np.float32), nodei, accel.zrange, accel.uvrange,
                      accel.margin, accel.min_cos, float(self_eps), out_axis, out_sample, out_t, work)
        # record index -> LDI sample index (in the kernel this load missed the cache once per ray,
        # 2.7 % of its profile; vectorised here the misses overlap)
        for a in range(3):
            sel = out_axis == a
            out_sample[sel] = args.sample[a][out_sample[sel]]
    return out_axis, out_sample, out_t, int(work[:, 0].sum()), int(work[:, 1].sum())


def _run(ldc: LDC, accel: IBRTAccel, origins, dirs, t_min, t_max, threads, self_eps, origin_normals,
         use_tree: bool) -> IBRTHits:
    _check(ldc, accel)
    if not (0.0 <= float(self_eps) < 1.0):
        raise InvalidInputError(f"self_eps must be in [0, 1) pixels, got {self_eps!r}")
    self_eps = float(self_eps)
    o, d, tlo, thi = _rays(origins, dirs, t_min, t_max)
    n = o.shape[0]
    nrm = None
    if origin_normals is not None:
        nrm = np.asarray(origin_normals, dtype=np.float64)
        if nrm.shape != (n, 3) or not np.all(np.isfinite(nrm)):
            raise InvalidInputError(f"origin_normals must be (n, 3) = {(n, 3)} finite, got {nrm.shape}")
    args = trace_args(ldc)
    prev = nb.get_num_threads()
    if threads is not None:
        if not (1 <= int(threads) <= nb.config.NUMBA_NUM_THREADS):
            raise InvalidInputError(f"threads must be in [1, {nb.config.NUMBA_NUM_THREADS}], got {threads!r}")
        nb.set_num_threads(int(threads))
    try:
        out_axis, out_sample, out_t, n_steps, n_tests = trace_prepared(
            ldc, args, accel, o, d, origin_normals=nrm, self_eps=self_eps, t_min=tlo, t_max=thi, use_tree=use_tree)
    finally:
        if threads is not None:
            nb.set_num_threads(prev)
    hit = out_axis >= 0
    side = np.zeros(n, dtype=np.int8)
    point = np.zeros((n, 3))
    if hit.any():
        for a in range(3):
            sel = np.flatnonzero(out_axis == a)
            if sel.size:
                ng = ldc.axes[a].geo_normal[out_sample[sel]].astype(np.float64)
                side[sel] = (np.einsum("ij,ij->i", ng, d[sel]) > 0.0).astype(np.int8)
        point[hit] = o[hit] + out_t[hit, None] * d[hit]
    return IBRTHits(hit=hit, axis=out_axis, sample=out_sample, side=side, t=out_t, point=point,
                    n_steps=n_steps, n_tests=n_tests)


def trace(ldc: LDC, accel: IBRTAccel, origins: np.ndarray, dirs: np.ndarray, *,
          t_min: np.ndarray | float = 0.0, t_max: np.ndarray | float = np.inf,
          threads: int | None = None, origin_normals: np.ndarray | None = None,
          self_eps: float = DEFAULT_SELF_EPS) -> IBRTHits:
    """First hit of each ray (origins, dirs (n, 3); dirs are normalised) against the LDC's
    samples, through the quadtrees of ``accel`` (``build_accel(ldc)``). Hits count when
    ``t_min < t < t_max`` (scalars or (n,) arrays). ``threads``: numba threads for this call
    (None: numba's current setting). Parallel over rays, releases the GIL.

    Rays leaving a surface need no offset: patches within ``self_eps`` pixels of the origin
    are never hit; ``origin_normals`` (n, 3), the surface normal at each origin, also skips
    the origin surface's neighbouring patches (module docstring)."""
    return _run(ldc, accel, origins, dirs, t_min, t_max, threads, self_eps, origin_normals, True)


def trace_linear(ldc: LDC, accel: IBRTAccel, origins: np.ndarray, dirs: np.ndarray, *,
                 t_min: np.ndarray | float = 0.0, t_max: np.ndarray | float = np.inf,
                 threads: int | None = None, origin_normals: np.ndarray | None = None,
                 self_eps: float = DEFAULT_SELF_EPS) -> IBRTHits:
    """Same as ``trace`` without the quadtrees (every crossed pixel, every layer): the
    baseline the acceleration is measured and tested against (uses only the accel's
    parameters and depth ranges)."""
    return _run(ldc, accel, origins, dirs, t_min, t_max, threads, self_eps, origin_normals, False)

