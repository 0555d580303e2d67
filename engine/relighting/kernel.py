"""The relight kernel: a baked dataset under new lights, per pixel (paper eq. 1).

Owns the numba code that runs on every relight:

- the intrinsics it needs beyond numba: float16 bits -> float32 (:data:`half_f16c` by F16C,
  :data:`half_int` by integer operations, :data:`HOST_F16C` picks one), cache-line prefetch, a
  16-pixel RGB output run written with non-temporal stores, the store fence, 512-bit vectors;
- the store accessors (``_fetch``, ``_run``, ``_run_value``, ...), overloaded per store kind
  (tiled / pixel-major, float16 / float32, low-rank factors);
- :func:`relight_kernel` (its parameters are documented one by one there) and :func:`exact_kernel`
  (lights exactly at dataset lights: the stored images, scaled): Python functions that run the
  serial ``nogil`` kernels ``_relight_group`` and ``_exact_chunks`` on the threads of
  ``engine.sched`` (each compiled once per store kind, no ``prange``), and :func:`zero_pixels`.

The kernels do no validation: ``engine.relighting.relight.relight`` checks and prepares every
argument. The kernel's design (passes A, B2, B3, the float32 geometry and its error bound) is
in ``docs/relighting.md`` "Kernel".
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from llvmlite import binding as llvm_binding
from llvmlite import ir
from numba.core import cgutils
from numba.core import types as nbtypes
from numba.extending import intrinsic, overload

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.relighting.bake import CHUNK, TILE, TILE_SHIFT
from engine.relighting.grid import CONE_EPS, locate
from engine.sched import next_block, run_on_threads, run_pieces_parallel

_MAX_PASSES = 4  # triangles per chunk and light in the SIMD pass B (the rest: scalar pass B3)
_F32_BAND = 512.0  # the float32 cone test's border, in units of its error bound's 2^-24 N |s| (see the kernel)
_F32_WELL = 0.81  # the float32 geometry's points: |P - c| <= 0.9 R (nearer the sphere: the float64 test)
_F32_LIGHT_RANGE = 2.0 ** 20  # the float32 geometry's lights: within 2^20 sphere radii of the centre
_SIMD_MIN_ROWS = 32  # fewer rows left than this: the scalar pass B3 is cheaper than another SIMD pass
_UNIT = 8  # consecutive chunks one scratch group runs in a row (neighbouring 16 x 16 blocks: output rows,
#            points and pixel indices stay in the same pages and prefetch streams)


def _make_half(hardware: bool):
    @intrinsic
    def half(typingctx, bits):
        """float16 bits (uint16) -> float32, exact for zero, subnormal and normal values (the bake
        never stores Inf or NaN). numba has no CPU float16 type. ``hardware``: LLVM's half -> float
        extension (one F16C ``vcvtph2ps``); otherwise 32-bit integer operations (sign, exponent
        rebias 15 -> 127, mantissa widened 10 -> 23 bits; subnormals as mantissa x 2^-24). Both are
        vectorisable, unlike the 256 KiB lookup table used before."""
        if bits != nbtypes.uint16:
            return None

        def codegen(context, builder, sig, args):
            i32, f32 = ir.IntType(32), ir.FloatType()
            if hardware:
                return builder.fpext(builder.bitcast(args[0], ir.HalfType()), f32)
            x = builder.zext(args[0], i32)
            sign = builder.shl(builder.and_(x, ir.Constant(i32, 0x8000)), ir.Constant(i32, 16))
            em = builder.and_(x, ir.Constant(i32, 0x7FFF))  # exponent and mantissa
            normal = builder.add(builder.shl(em, ir.Constant(i32, 13)), ir.Constant(i32, 112 << 23))
            sub = builder.bitcast(builder.fmul(builder.uitofp(em, f32), ir.Constant(f32, 2.0 ** -24)), i32)
            mag = builder.select(builder.icmp_unsigned(">=", em, ir.Constant(i32, 0x400)), normal, sub)
            return builder.bitcast(builder.or_(mag, sign), f32)
        return nbtypes.float32(nbtypes.uint16), codegen
    return half


half_int = _make_half(False)  # float16 bits -> float32 by integer operations (any host)
half_f16c = _make_half(True)  # float16 bits -> float32 by F16C (hosts with HOST_F16C only)
# numba compiles for the host CPU: with F16C the hardware conversion (without it LLVM would call a
# runtime helper the JIT may not provide, so the integer version is used)
HOST_F16C = "+f16c" in llvm_binding.get_host_cpu_features().flatten().split(",")
_half = half_f16c if HOST_F16C else half_int


def _make_prefetch(rw: int):
    @intrinsic
    def prefetch(typingctx, arr, idx):
        """Hint the cache line holding arr[idx] (1-D array) into L1; never faults (an index past the
        end is harmless), no effect on results."""
        if not (isinstance(arr, nbtypes.Array) and arr.ndim == 1 and isinstance(idx, nbtypes.Integer)):
            return None

        def codegen(context, builder, sig, args):
            aryty = sig.args[0]
            ary = context.make_array(aryty)(context, builder, args[0])
            ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [args[1]], wraparound=False)
            i8p, i32 = ir.IntType(8).as_pointer(), ir.IntType(32)
            fn = cgutils.get_or_insert_function(builder.module, ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32]),
                                                "llvm.prefetch.p0")
            builder.call(fn, [builder.bitcast(ptr, i8p), ir.Constant(i32, rw), ir.Constant(i32, 3),
                              ir.Constant(i32, 1)])
            return context.get_dummy_value()
        return nbtypes.none(arr, idx), codegen
    return prefetch


@intrinsic
def _store_run48(typingctx, out, q, a0, a1, a2, r0):
    """out[q + 3 k + c] = (a0, a1, a2)[c][r0 + k] for k < 16: one 16-pixel RGB output run built from three
    float32 channel rows by vector shuffles. When &out[q] is 64-byte aligned the three cache lines are
    written with non-temporal stores (the frame is far larger than the caches: no read-for-ownership of
    lines that are overwritten whole, no eviction of the store runs); otherwise ordinary stores."""
    arr1 = (isinstance(out, nbtypes.Array) and out.ndim == 1 and out.dtype == nbtypes.float32)
    if not (arr1 and all(isinstance(a, nbtypes.Array) and a.ndim == 1 and a.dtype == nbtypes.float32
                         for a in (a0, a1, a2)) and isinstance(q, nbtypes.Integer)
            and isinstance(r0, nbtypes.Integer)):
        return None

    def codegen(context, builder, sig, args):
        f32 = ir.FloatType()
        i32, i64 = ir.IntType(32), ir.IntType(64)
        v16 = ir.VectorType(f32, 16)

        def ptr(k, idx):
            aryty = sig.args[k]
            ary = context.make_array(aryty)(context, builder, args[k])
            idx = context.cast(builder, idx, sig.args[1 if k == 0 else 5], nbtypes.intp)
            return cgutils.get_item_pointer(context, builder, aryty, ary, [idx], wraparound=False)

        dst = ptr(0, args[1])
        rows = [builder.load(builder.bitcast(ptr(k, args[5]), v16.as_pointer()), align=4) for k in (2, 3, 4)]
        ab = builder.shuffle_vector(rows[0], rows[1], ir.Constant(ir.VectorType(i32, 32), list(range(32))))
        cc = builder.shuffle_vector(rows[2], rows[2], ir.Constant(ir.VectorType(i32, 32), list(range(16)) * 2))
        mask = [(k // 3) + 16 * (k % 3) for k in range(48)]
        il = builder.shuffle_vector(ab, cc, ir.Constant(ir.VectorType(i32, 48), mask))
        parts = [builder.shuffle_vector(il, il, ir.Constant(ir.VectorType(i32, 16), list(range(16 * j, 16 * j + 16))))
                 for j in range(3)]
        aligned = builder.icmp_unsigned("==", builder.and_(builder.ptrtoint(dst, i64), ir.Constant(i64, 63)),
                                        ir.Constant(i64, 0))
        base = builder.bitcast(dst, v16.as_pointer())
        with builder.if_else(aligned) as (nt, plain):
            with nt:
                for j in range(3):
                    st = builder.store(parts[j], builder.gep(base, [ir.Constant(i32, j)]), align=64)
                    st.set_metadata("nontemporal", builder.module.add_metadata([ir.Constant(i32, 1)]))
            with plain:
                for j in range(3):
                    builder.store(parts[j], builder.gep(base, [ir.Constant(i32, j)]), align=4)
        return context.get_dummy_value()
    return nbtypes.none(out, q, a0, a1, a2, r0), codegen


@intrinsic
def _fence(typingctx):
    """Order the non-temporal stores before the kernel returns (a full fence: mfence on x86)."""
    def codegen(context, builder, sig, args):
        builder.fence("seq_cst")
        return context.get_dummy_value()
    return nbtypes.none(), codegen


_prefetch = _make_prefetch(0)  # for reading


@intrinsic
def _wide_vectors(typingctx):
    """Let LLVM's vectorisers use 512-bit vectors in the calling function (on AVX-512 hosts LLVM prefers
    256-bit ones by default; elsewhere the attribute changes nothing): the function attribute
    ``"prefer-vector-width"="512"``, which llvmlite's attribute set does not list (added as text)."""
    def codegen(context, builder, sig, args):
        set.add(builder.function.attributes, '"prefer-vector-width"="512"')
        return context.get_dummy_value()
    return nbtypes.none(), codegen


@nb.njit(cache=True, nogil=True)
def _lr_dot(u, b, u0, b0, r):
    """One value of a low-rank store: the dot product of a pixel-channel row and a light row."""
    s = np.float32(0.0)
    for j in range(r):
        s += u[u0 + j] * b[b0 + j]
    return s


def _fetch(store, i, k, c):  # pragma: no cover - replaced by the overload in numba code
    raise NotImplementedError


@overload(_fetch, inline="always")
def _fetch_impl(store, i, k, c):
    """Value (float32, stored scale) of store row i, kept light k, channel c, for every store kind."""
    if isinstance(store, nbtypes.BaseTuple):  # low-rank factors (u, b, u_off, b_off, rank)
        def lowrank(store, i, k, c):
            u, b, u_off, b_off, rank = store
            t = i >> TILE_SHIFT
            r = rank[t]
            return _lr_dot(u, b, u_off[t] + ((i & (TILE - 1)) * 3 + c) * r, b_off[t] + k * r, r)
        return lowrank
    if store.ndim == 4:  # tiled: (tile, light, row in tile, channel)
        if store.dtype == nbtypes.uint16:
            return lambda store, i, k, c: _half(store[i >> TILE_SHIFT, k, i & (TILE - 1), c])
        return lambda store, i, k, c: store[i >> TILE_SHIFT, k, i & (TILE - 1), c]
    if store.dtype == nbtypes.uint16:
        return lambda store, i, k, c: _half(store[i, k, c])
    return lambda store, i, k, c: store[i, k, c]


def _flat(store):  # pragma: no cover - replaced by the overload in numba code
    raise NotImplementedError


@overload(_flat, inline="always")
def _flat_impl(store):
    """A tiled store as one flat array (hoisted out of the loops: reshape calls into the runtime)."""
    if not isinstance(store, nbtypes.BaseTuple) and store.ndim == 4:
        return lambda store: store.reshape(-1)
    return lambda store: np.zeros(1, np.float32)


def _run(flat, store, tile, k):  # pragma: no cover - replaced by the overload in numba code
    raise NotImplementedError


@overload(_run, inline="always")
def _run_impl(flat, store, tile, k):
    """The TILE x 3 values of light k in a tile, as a contiguous 1-D view (tiled store): row r,
    channel c is run[3 r + c], strides the loop vectoriser sees as constants."""
    if not isinstance(store, nbtypes.BaseTuple) and store.ndim == 4:
        def run(flat, store, tile, k):
            o = (tile * store.shape[1] + k) * (TILE * 3)
            return flat[o:o + TILE * 3]
        return run
    return lambda flat, store, tile, k: flat


def _run_value(run, store, i, r, k, c):  # pragma: no cover - replaced by the overload in numba code
    raise NotImplementedError


@overload(_run_value, inline="always")
def _run_value_impl(run, store, i, r, k, c):
    """_fetch(store, i, k, c) for row r of the chunk, through its light run when the store is tiled."""
    if not isinstance(store, nbtypes.BaseTuple) and store.ndim == 4:
        if store.dtype == nbtypes.uint16:
            return lambda run, store, i, r, k, c: _half(run[3 * r + c])
        return lambda run, store, i, r, k, c: run[3 * r + c]
    return lambda run, store, i, r, k, c: _fetch(store, i, k, c)


def _simd_store(store):  # pragma: no cover - replaced by the overload in numba code
    raise NotImplementedError


@overload(_simd_store, inline="always")
def _simd_store_impl(store):
    """True for a tiled float16/float32 store: its light runs are contiguous per tile, so pass B2
    (all rows against the chunk's triangle) reads them as vectors."""
    simd = not isinstance(store, nbtypes.BaseTuple) and store.ndim == 4
    return lambda store: simd


def _prefetch_runs(flat, store, tile, ka, kb, kc):  # pragma: no cover - replaced by the overload
    raise NotImplementedError


@overload(_prefetch_runs, inline="always")
def _prefetch_runs_impl(flat, store, tile, ka, kb, kc):
    """Prefetch three lights' runs of a tile (tiled store; nothing for the other kinds)."""
    if not isinstance(store, nbtypes.BaseTuple) and store.ndim == 4:
        step = 512 // store.dtype.bitwidth  # elements per 64-byte cache line

        def pf(flat, store, tile, ka, kb, kc):
            base = tile * store.shape[1]
            for k in (ka, kb, kc):
                o = (base + k) * (TILE * 3)
                for e in range(0, TILE * 3, step):
                    _prefetch(flat, o + e)
        return pf
    return lambda flat, store, tile, ka, kb, kc: None



@nb.njit(cache=True, nogil=True, inline="always")
def _f32(x):
    return np.float32(x)


@nb.njit(cache=True, nogil=True, inline="always")
def _sphere_point(kd, distant_ds, lx, ly, lz, nx, ny, nz, ox, oy, oz, r2):
    """Scalar pass A for one row and light in the kernel frame (origin = sphere centre): (d2, den, sx,
    sy, sz) with d2 = |l - P|^2 (inf for directional lights), den the irradiance denominator (the
    light's contribution is its intensity / den; den < 0 = an area sample facing away) and s a
    positive multiple of the direction from the centre to the sphere point (the cone test and the
    normalised weights do not depend on its length). The SIMD loops of pass A are the same
    operations per row."""
    if kd == 1:
        if distant_ds:
            return math.inf, 1.0, lx, ly, lz
        b = ox * lx + oy * ly + oz * lz
        cc = ox * ox + oy * oy + oz * oz - r2
        e = b * b - cc
        t = math.sqrt(e if e > 0.0 else 0.0) - b
        return math.inf, 1.0, ox + t * lx, oy + t * ly, oz + t * lz
    dx, dy, dz = lx - ox, ly - oy, lz - oz
    d2 = dx * dx + dy * dy + dz * dz
    den = d2
    if kd >= 2:
        c = -(dx * nx + dy * ny + dz * nz) / math.sqrt(d2)
        if kd == 3:
            c = abs(c)
        den = d2 / c if c > 0.0 else -1.0
    if distant_ds:
        return d2, den, dx, dy, dz
    b = ox * dx + oy * dy + oz * dz
    cc = ox * ox + oy * oy + oz * oz - r2
    e = b * b - cc * d2
    t = math.sqrt(e if e > 0.0 else 0.0) - b
    return d2, den, d2 * ox + t * dx, d2 * oy + t * dy, d2 * oz + t * dz


def relight_kernel(kpts, points64, origin, store, lpos32, inv_int, distant_ds, radius, fscale, tris, inv,
                   grid_n, grid_start, grid_items, kinds, lp, lint, lnorm, min_dist2, near2, pix, runs, run_pix, out,
                   outside, singular, touched, flagged, serial=None):
    """Per store row (pixel): sum over lights of interpolated normalised response x irradiance.

    Kernel frame: every position is relative to ``origin`` (the sphere centre; for a distant dataset the
    centre of the points' bounding box). M = the expanded lights (``lights.expand_lights``), K = the kept
    dataset lights, n = the store rows, T = the triangles. Parameters, in order:

    - kpts (n_chunks, 3, CHUNK) float32: the surface points in the kernel frame, one contiguous row per
      axis and chunk, zero padded (``KernelGeometry.points``).
    - points64 (n, 3) float64: the baked points (world frame), for the rows whose light is within
      ``near2`` of the float32 point: whether the light is closer than ``min_dist2`` (singular) is
      decided, and the row computed, in float64 from the exact point.
    - origin (3,) float64: the kernel frame's origin in the world frame.
    - store: (n, K, 3) or tiled (n_tiles, K, TILE, 3), float32 or float16 bits (uint16), or the low-rank
      factors' tuple (``BakedDataset.kernel_store``).
    - lpos32 (K, 3) float32: the dataset lights' positions in the kernel frame (directions for a
      distant dataset).
    - inv_int (K, 3) float64: 1 / (dataset light intensity x store scale), per channel.
    - distant_ds: the dataset's lights are distant (directions, no sphere).
    - radius: the light sphere's radius (1 for a distant dataset).
    - fscale: the power of two that brings ``radius`` into [1, 2) (the float32 geometry's frame).
    - tris (T, 3) int64, inv (T, 3, 3) float64: the triangles' kept-light indices and the inverse
      matrices of their vertex directions (``BakedDataset.triangles``, ``tri_inverse``).
    - grid_n, grid_start, grid_items: the cube-map grid (``grid.build_grid``).
    - kinds (M,) int64: light kind (``lights.K_POINT``, ``K_DIRECTIONAL``, ``K_ORIENTED``,
      ``K_TWO_SIDED``).
    - lp (M, 3) float64: light position (kernel frame), or unit direction toward a directional light.
    - lint (M, 3) float64: intensity (point, oriented) or irradiance (directional).
    - lnorm (M, 3) float64: emitter normal (oriented and two-sided samples).
    - min_dist2: squared ``min_light_distance``: a light this near a point contributes 0 (singular).
    - near2: squared distance under which the float64 point is used (``min_light_distance`` + 4 x the
      float32 points' rounding bound, squared).
    - pix (n,) int32/int64: flat pixel of each store row; runs (ceil(n / 16),) uint8 and run_pix:
      the 16-row groups that are 16 consecutive pixels and their first pixel (``KernelGeometry``).
    - out (h*w, 3) float32: written at ``pix[i]`` only.
    - outside, singular (h*w,) bool: zeroed by the caller, set at ``pix[i]`` where true.
    - touched (T,) uint8: set to 1 for every triangle whose three lights were read (racing writes all
      store 1).
    - flagged (1,) uint8: set to 1 when any outside or singular flag was set (so the caller counts the
      masks only then).
    - serial: one thread (``engine.sched.threads_for``; None: every numba thread from the main thread).

    The parameters stay positional on purpose: bundled in five NamedTuples (rows, dataset, grid, lights,
    output) the images were bit-identical but every call cost ~85 us more (a per-call cost: numba's dispatcher
    types tuple arguments more slowly than arrays), 8 % of a one-light relight of 250k pixels (paired A/B).

    Fixed chunks of CHUNK consecutive rows (one tile of the tiled store; the same chunks for any
    thread count and schedule, so results do not depend on them). One scratch group per thread
    (``_relight_group``, the only compiled code: run on the threads of ``engine.sched.run_on_threads``)
    takes units of _UNIT consecutive chunks from a shared counter (``engine.sched.next_block``: a thread
    that loses its core for a while takes fewer units instead of the other waiting for it).
    Light by light:
    - pass A (SIMD): every row's sphere direction s (a positive multiple of the sphere point: one
      sqrt, no division), |l - P|^2 and the irradiance denominator;
    - pass B1: the chunk's triangle = the one the first usable row falls in (cube-map search);
    - pass B2 (SIMD across rows, in simple loops the vectoriser takes): every row's cone test against
      that triangle, its weights times the squared distances to the three vertex lights times the
      irradiance factor (one division per row), the three lights' runs of the tile decoded, and the
      accumulation of the rows the triangle contains (most rows: a 16 x 16 block sees a light in
      nearly one direction);
    - pass B3 (scalar): the other rows, previous-row triangle first, then the cube-map search; the
      same operations per row as B2 (a tiled and a pixel-major store give the same image).
    While a chunk is processed, the next chunk's points (after the first light's pass A) and its runs of
    the current triangle's lights are prefetched.
    """
    counter = np.zeros(1, np.int64)
    run_on_threads(lambda: _relight_group(counter, kpts, points64, origin, store, lpos32, inv_int, distant_ds, radius,
                                          fscale, tris, inv, grid_n, grid_start, grid_items, kinds, lp, lint, lnorm,
                                          min_dist2, near2, pix, runs, run_pix, out, outside, singular, touched,
                                          flagged), serial)


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _relight_group(counter, kpts, points64, origin, store, lpos32, inv_int, distant_ds, radius, fscale, tris, inv,
                   grid_n, grid_start, grid_items, kinds, lp, lint, lnorm, min_dist2, near2, pix, runs, run_pix, out,
                   outside, singular, touched, flagged):
    """One scratch group of :func:`relight_kernel` (its units taken from ``counter``; parameters as
    documented there), serial and ``nogil``: each thread of the call runs one."""
    _wide_vectors()
    n = points64.shape[0]
    m = kinds.shape[0]
    gx0, gy0, gz0 = origin[0], origin[1], origin[2]
    r2 = radius * radius
    n_chunks = (n + CHUNK - 1) // CHUNK
    n_units = (n_chunks + _UNIT - 1) // _UNIT
    flat = _flat(store)
    kflat = kpts.reshape(-1)
    oflat = out.reshape(-1)
    simd = _simd_store(store)
    sx = np.empty(CHUNK)
    sy = np.empty(CHUNK)
    sz = np.empty(CHUNK)
    den = np.empty(CHUNK)
    d2s = np.empty(CHUNK)
    acc0 = np.empty(CHUNK, np.float32)
    acc1 = np.empty(CHUNK, np.float32)
    acc2 = np.empty(CHUNK, np.float32)
    out_f = np.empty(CHUNK, np.bool_)
    sing_f = np.empty(CHUNK, np.bool_)
    todo = np.empty(CHUNK, np.bool_)
    hit = np.empty(CHUNK, np.bool_)
    wa = np.empty(CHUNK)
    wb = np.empty(CHUNK)
    wc = np.empty(CHUNK)
    fa32 = np.empty(CHUNK, np.float32)
    fb32 = np.empty(CHUNK, np.float32)
    fc32 = np.empty(CHUNK, np.float32)
    sx32 = np.empty(CHUNK, np.float32)
    sy32 = np.empty(CHUNK, np.float32)
    sz32 = np.empty(CHUNK, np.float32)
    d2s32 = np.empty(CHUNK, np.float32)
    bet32 = np.empty(CHUNK, np.float32)
    bord = np.zeros(CHUNK, np.bool_)
    bordw = bord.view(np.uint64)
    # float32 pass A: a light nearer than this (squared, float32) to a row's point sends the row to pass B3,
    # which decides with the float64 d2 against near2 (the float32 d2 is within 2^-20 of it; the 1e-12
    # radii floor keeps the float32 geometry away from underflow)
    rsc = radius * fscale
    nh32 = _f32(max(near2 * fscale * fscale * (1.0 + 2.0 ** -12), 1e-12 * rsc * rsc))
    va = np.empty((3, CHUNK), np.float32)
    vb = np.empty((3, CHUNK), np.float32)
    vc = np.empty((3, CHUNK), np.float32)
    out_f[:] = False
    sing_f[:] = False
    # units of _UNIT consecutive chunks from the shared counter (engine.sched); the next unit is taken when
    # the current one's last chunk starts, so that chunk can prefetch its successor's points and runs
    unit = next_block(counter)
    unit_next = n_units
    ci = unit * _UNIT - 1
    while True:
        ci += 1
        if ci >= min((unit + 1) * _UNIT, n_chunks):
            unit = unit_next
            ci = unit * _UNIT
        if unit >= n_units:
            break
        i0 = ci * CHUNK
        nc = min(n, i0 + CHUNK) - i0
        # the group's next chunk: the next of this unit, else the first of the unit it takes now
        cn = ci + 1
        if cn >= min((unit + 1) * _UNIT, n_chunks):
            unit_next = next_block(counter)
            cn = unit_next * _UNIT
        n0 = cn * CHUNK
        ncn = min(n, n0 + CHUNK) - n0 if cn < n_chunks else 0
        # the chunk's points: three contiguous float32 rows
        qx = kflat[3 * i0:3 * i0 + CHUNK]
        qy = kflat[3 * i0 + CHUNK:3 * i0 + 2 * CHUNK]
        qz = kflat[3 * i0 + 2 * CHUNK:3 * i0 + 3 * CHUNK]
        for r in range(CHUNK):
            acc0[r] = np.float32(0.0)
            acc1[r] = np.float32(0.0)
            acc2[r] = np.float32(0.0)
        flags = False
        for j in range(m):
            kd = kinds[j]
            lx, ly, lz = lp[j, 0], lp[j, 1], lp[j, 2]
            nx, ny, nz = lnorm[j, 0], lnorm[j, 1], lnorm[j, 2]
            # the float32 geometry (one point light of a tiled store, the common case; the light within
            # 2^20 sphere radii: no float32 overflow or underflow in the scaled frame): pass A and the
            # cone test in float32, rows whose test is within its error bound re-tested in float64
            f32 = (simd and kd == 0 and not distant_ds
                   and max(abs(lx), max(abs(ly), abs(lz))) <= _F32_LIGHT_RANGE * radius)
            # ---- pass A: sphere direction, squared distance and irradiance denominator of every row
            if f32:
                # in the frame scaled by fscale (a power of two: exact) the radius is in [1, 2); the light
                # position as float32 hi + lo, so d = l - P is accurate to float32 rounding of d itself
                lsx, lsy, lsz = lx * fscale, ly * fscale, lz * fscale
                lxh, lyh, lzh = _f32(lsx), _f32(lsy), _f32(lsz)
                lxl, lyl, lzl = _f32(lsx - lxh), _f32(lsy - lyh), _f32(lsz - lzh)
                fs32 = _f32(fscale)
                rs2 = _f32(rsc * rsc)
                well = _f32(_F32_WELL * rsc * rsc)
                for r in range(CHUNK):
                    ox, oy, oz = qx[r] * fs32, qy[r] * fs32, qz[r] * fs32
                    dx, dy, dz = (lxh - ox) + lxl, (lyh - oy) + lyl, (lzh - oz) + lzl
                    d2 = dx * dx + dy * dy + dz * dz
                    b = ox * dx + oy * dy + oz * dz
                    oo = ox * ox + oy * oy + oz * oz
                    e = b * b - (oo - rs2) * d2
                    t = math.sqrt(e if e > np.float32(0.0) else np.float32(0.0)) - b
                    sx32[r] = d2 * ox + t * dx
                    sy32[r] = d2 * oy + t * dy
                    sz32[r] = d2 * oz + t * dz
                    d2s32[r] = d2
                    # the cone test's error bound is proportional to d2 for points well inside the sphere;
                    # the others always take the float64 test
                    bet32[r] = d2 if oo <= well else np.float32(np.inf)
                n_todo = 0  # (a separate loop: an integer count in pass A halves its vector width)
                for r in range(CHUNK):
                    u = (r < nc) & (d2s32[r] > nh32)
                    todo[r] = u
                    n_todo += u
            elif kd == 1:
                for r in range(CHUNK):
                    den[r] = 1.0
                    d2s[r] = math.inf
                if distant_ds:
                    for r in range(CHUNK):
                        sx[r], sy[r], sz[r] = lx, ly, lz
                else:
                    for r in range(CHUNK):
                        ox, oy, oz = np.float64(qx[r]), np.float64(qy[r]), np.float64(qz[r])
                        b = ox * lx + oy * ly + oz * lz
                        cc = ox * ox + oy * oy + oz * oz - r2
                        e = b * b - cc
                        t = math.sqrt(e if e > 0.0 else 0.0) - b
                        sx[r] = ox + t * lx
                        sy[r] = oy + t * ly
                        sz[r] = oz + t * lz
            elif kd == 0 and not distant_ds:  # the common case, branch-free
                for r in range(CHUNK):
                    ox, oy, oz = np.float64(qx[r]), np.float64(qy[r]), np.float64(qz[r])
                    dx, dy, dz = lx - ox, ly - oy, lz - oz
                    d2 = dx * dx + dy * dy + dz * dz
                    d2s[r] = d2
                    den[r] = d2
                    b = ox * dx + oy * dy + oz * dz
                    cc = ox * ox + oy * oy + oz * oz - r2
                    e = b * b - cc * d2
                    t = math.sqrt(e if e > 0.0 else 0.0) - b
                    sx[r] = d2 * ox + t * dx
                    sy[r] = d2 * oy + t * dy
                    sz[r] = d2 * oz + t * dz
            else:
                for r in range(nc):
                    d2s[r], den[r], sx[r], sy[r], sz[r] = _sphere_point(
                        kd, distant_ds, lx, ly, lz, nx, ny, nz, np.float64(qx[r]), np.float64(qy[r]),
                        np.float64(qz[r]), r2)
            if j == 0 and ncn > 0:
                # the next chunk's points, after this chunk's pass A rather than at its start (right after the
                # previous chunk's 48 non-temporal output lines, which hold the fill buffers the prefetches
                # wait for): bench A/B one point light 1.02-1.06x, bit-identical
                for e in range(0, 3 * CHUNK, 16):
                    _prefetch(kflat, 3 * n0 + e)
            # the light's largest channel goes into the float64 factor (so the float32 weights are
            # in the range of the result, for any distance), the channel ratios into the constants
            lmax = max(lint[j, 0], max(lint[j, 1], lint[j, 2]))
            lmax = lmax if lmax > 0.0 else 1.0
            l0, l1, l2 = lint[j, 0] / lmax, lint[j, 1] / lmax, lint[j, 2] / lmax
            # rows to do: usable (not within near2 of the light, not an area sample facing away) and
            # not yet accumulated; the unusable rows (rare) go to pass B3
            if not f32:
                n_todo = 0
                for r in range(CHUNK):
                    u = (r < nc) & (d2s[r] > near2) & (den[r] > 0.0)
                    todo[r] = u
                    n_todo += u
            n_rest = nc - n_todo  # unusable rows
            # ---- pass B (SIMD, tiled stores; pixel-major and low-rank rows are gathers either way:
            # all rows go to B3): a triangle = the one the first row to do falls in (cube-map search),
            # tested against every row of the chunk; then the next one, while >= _SIMD_MIN_ROWS rows
            # are left (a 16 x 16 block mostly needs one or two triangles)
            for _ in range(_MAX_PASSES if simd else 0):
                t0 = -1
                for r in range(nc):
                    if todo[r]:
                        if f32:  # the float64 direction (as the float64 kernel locates it)
                            _, _, x, y, z = _sphere_point(kd, distant_ds, lx, ly, lz, nx, ny, nz, np.float64(qx[r]),
                                                          np.float64(qy[r]), np.float64(qz[r]), r2)
                        else:
                            x, y, z = sx[r], sy[r], sz[r]
                        t0, w0, w1, w2 = locate(x, y, z, inv, grid_n, grid_start, grid_items)
                        break
                if t0 < 0:  # outside coverage: pass B3 marks it
                    break
                touched[t0] = 1
                m00, m01, m02 = inv[t0, 0, 0], inv[t0, 0, 1], inv[t0, 0, 2]
                m10, m11, m12 = inv[t0, 1, 0], inv[t0, 1, 1], inv[t0, 1, 2]
                m20, m21, m22 = inv[t0, 2, 0], inv[t0, 2, 1], inv[t0, 2, 2]
                ka, kb, kc = tris[t0, 0], tris[t0, 1], tris[t0, 2]
                if ncn > 0:  # neighbouring blocks mostly see the same triangle
                    _prefetch_runs(flat, store, cn, ka, kb, kc)
                ax, ay, az = lpos32[ka, 0], lpos32[ka, 1], lpos32[ka, 2]
                bx, by, bz = lpos32[kb, 0], lpos32[kb, 1], lpos32[kb, 2]
                cx, cy, cz = lpos32[kc, 0], lpos32[kc, 1], lpos32[kc, 2]
                ia0, ia1, ia2 = _f32(inv_int[ka, 0] * l0), _f32(inv_int[ka, 1] * l1), _f32(inv_int[ka, 2] * l2)
                ib0, ib1, ib2 = _f32(inv_int[kb, 0] * l0), _f32(inv_int[kb, 1] * l1), _f32(inv_int[kb, 2] * l2)
                ic0, ic1, ic2 = _f32(inv_int[kc, 0] * l0), _f32(inv_int[kc, 1] * l1), _f32(inv_int[kc, 2] * l2)
                if f32:
                    # the cone test in float32: a row is inside t0 for sure when every cone coordinate is
                    # >= the bound of its float32 error, outside when one is below -bound, else on the
                    # border (re-tested below). Bound: |a32 - a64| <= 175 u N |s| (u = 2^-24, N the largest
                    # row sum of |inv[t0]|, |s| <= 3.42 d2 R in the scaled frame, points with |o|^2 <=
                    # _F32_WELL R^2), used with a factor ~3 margin
                    n00, n01, n02 = _f32(m00), _f32(m01), _f32(m02)
                    n10, n11, n12 = _f32(m10), _f32(m11), _f32(m12)
                    n20, n21, n22 = _f32(m20), _f32(m21), _f32(m22)
                    nrm = max(abs(m00) + abs(m01) + abs(m02), max(abs(m10) + abs(m11) + abs(m12),
                                                                  abs(m20) + abs(m21) + abs(m22)))
                    cb = _f32(_F32_BAND * 2.0 ** -24 * nrm * rsc)
                    lm32 = _f32(lmax * fscale * fscale)
                    for r in range(CHUNK):
                        x, y, z = sx32[r], sy32[r], sz32[r]
                        a0 = n00 * x + n01 * y + n02 * z
                        a1 = n10 * x + n11 * y + n12 * z
                        a2 = n20 * x + n21 * y + n22 * z
                        mn = min(a0, min(a1, a2))
                        bb = cb * bet32[r]
                        tr = todo[r]
                        sure = mn >= bb
                        hit[r] = sure & tr
                        bd = (mn >= -bb) & (not sure) & tr
                        bord[r] = bd
                        a0 = max(a0, np.float32(0.0))
                        a1 = max(a1, np.float32(0.0))
                        a2 = max(a2, np.float32(0.0))
                        g = lm32 / ((a0 + a1 + a2) * d2s32[r])
                        px, py, pz = qx[r], qy[r], qz[r]
                        ex, ey, ez = ax - px, ay - py, az - pz
                        fa32[r] = (a0 * g) * (ex * ex + ey * ey + ez * ez)
                        ex, ey, ez = bx - px, by - py, bz - pz
                        fb32[r] = (a1 * g) * (ex * ex + ey * ey + ez * ez)
                        ex, ey, ez = cx - px, cy - py, cz - pz
                        fc32[r] = (a2 * g) * (ex * ex + ey * ey + ez * ez)
                    # the rows within the float32 test's error bound: _locate's float64 test and float64
                    # weights, exactly as the float64 pass below computes them
                    for w in range(CHUNK // 8):  # 8 flags a word: the border rows are rare
                        if bordw[w] == 0:
                            continue
                        for r in range(8 * w, 8 * w + 8):
                            if not bord[r]:
                                continue
                            _, dn, x, y, z = _sphere_point(kd, distant_ds, lx, ly, lz, nx, ny, nz, np.float64(qx[r]),
                                                           np.float64(qy[r]), np.float64(qz[r]), r2)
                            a0 = m00 * x + m01 * y + m02 * z
                            a1 = m10 * x + m11 * y + m12 * z
                            a2 = m20 * x + m21 * y + m22 * z
                            s = a0 + a1 + a2
                            if s > 0.0 and min(a0, min(a1, a2)) >= -CONE_EPS * s:
                                hit[r] = True
                                a0 = max(a0, 0.0)
                                a1 = max(a1, 0.0)
                                a2 = max(a2, 0.0)
                                g = lmax / ((a0 + a1 + a2) * dn)
                                px, py, pz = qx[r], qy[r], qz[r]
                                ex, ey, ez = ax - px, ay - py, az - pz
                                fa32[r] = _f32(a0 * g) * (ex * ex + ey * ey + ez * ez)
                                ex, ey, ez = bx - px, by - py, bz - pz
                                fb32[r] = _f32(a1 * g) * (ex * ex + ey * ey + ez * ez)
                                ex, ey, ez = cx - px, cy - py, cz - pz
                                fc32[r] = _f32(a2 * g) * (ex * ex + ey * ey + ez * ez)
                            bord[r] = False
                else:
                    # _locate's test against t0, weights x irradiance factor ...
                    for r in range(CHUNK):
                        x, y, z = sx[r], sy[r], sz[r]
                        a0 = m00 * x + m01 * y + m02 * z
                        a1 = m10 * x + m11 * y + m12 * z
                        a2 = m20 * x + m21 * y + m22 * z
                        s = a0 + a1 + a2
                        hit[r] = (s > 0.0) & (min(a0, min(a1, a2)) >= -CONE_EPS * s) & todo[r]
                        a0 = max(a0, 0.0)
                        a1 = max(a1, 0.0)
                        a2 = max(a2, 0.0)
                        g = lmax / ((a0 + a1 + a2) * den[r])  # rows outside t0: unused (masked)
                        wa[r], wb[r], wc[r] = a0 * g, a1 * g, a2 * g
                # ... times the squared distances to the three vertex lights (float32: relative
                # rounding 2^-24 per operation, the positions are scene-sized) ...
                if f32:
                    pass
                elif distant_ds:
                    for r in range(CHUNK):
                        fa32[r], fb32[r], fc32[r] = wa[r], wb[r], wc[r]
                else:
                    for r in range(CHUNK):
                        px, py, pz = qx[r], qy[r], qz[r]
                        ex, ey, ez = ax - px, ay - py, az - pz
                        fa32[r] = _f32(wa[r]) * (ex * ex + ey * ey + ez * ez)
                        ex, ey, ez = bx - px, by - py, bz - pz
                        fb32[r] = _f32(wb[r]) * (ex * ex + ey * ey + ez * ez)
                        ex, ey, ez = cx - px, cy - py, cz - pz
                        fc32[r] = _f32(wc[r]) * (ex * ex + ey * ey + ez * ez)
                # ... the three lights' values of the rows ...
                run_a, run_b = _run(flat, store, ci, ka), _run(flat, store, ci, kb)
                run_c = _run(flat, store, ci, kc)
                for r in range(CHUNK):
                    i = i0 + r
                    va[0, r] = _run_value(run_a, store, i, r, ka, 0)
                    va[1, r] = _run_value(run_a, store, i, r, ka, 1)
                    va[2, r] = _run_value(run_a, store, i, r, ka, 2)
                    vb[0, r] = _run_value(run_b, store, i, r, kb, 0)
                    vb[1, r] = _run_value(run_b, store, i, r, kb, 1)
                    vb[2, r] = _run_value(run_b, store, i, r, kb, 2)
                    vc[0, r] = _run_value(run_c, store, i, r, kc, 0)
                    vc[1, r] = _run_value(run_c, store, i, r, kc, 1)
                    vc[2, r] = _run_value(run_c, store, i, r, kc, 2)
                # ... and the accumulation of the rows t0 contains (a select, not a branch; float32:
                # the values are float16 or float32, the weights' rounding is 2^-24)
                for r in range(CHUNK):
                    ua, ub, uc = fa32[r], fb32[r], fc32[r]
                    v0 = ua * ia0 * va[0, r] + ub * ib0 * vb[0, r] + uc * ic0 * vc[0, r]
                    v1 = ua * ia1 * va[1, r] + ub * ib1 * vb[1, r] + uc * ic1 * vc[1, r]
                    v2 = ua * ia2 * va[2, r] + ub * ib2 * vb[2, r] + uc * ic2 * vc[2, r]
                    ok = hit[r]
                    c0, c1, c2 = acc0[r], acc1[r], acc2[r]
                    acc0[r] = c0 + v0 if ok else c0
                    acc1[r] = c1 + v1 if ok else c1
                    acc2[r] = c2 + v2 if ok else c2
                # the rows still to do: how many, and their range
                n_todo = 0
                for r in range(CHUNK):
                    t = todo[r] > hit[r]  # still to do: not hit by this triangle
                    todo[r] = t
                    n_todo += t
                if n_todo < _SIMD_MIN_ROWS:
                    break
            # ---- pass B3 (scalar): the rows t0 does not contain. The current triangle's search
            # matrix, vertex lights, their positions and 1/intensity live in locals.
            last = -1
            ka = kb = kc = 0
            m00 = m01 = m02 = m10 = m11 = m12 = m20 = m21 = m22 = 0.0
            ax = ay = az = bx = by = bz = cx = cy = cz = np.float32(0.0)
            ia0 = ia1 = ia2 = ib0 = ib1 = ib2 = ic0 = ic1 = ic2 = np.float32(0.0)
            if n_todo + n_rest == 0:
                continue
            for r in range(nc):
                i = i0 + r
                px, py, pz = np.float64(qx[r]), np.float64(qy[r]), np.float64(qz[r])
                if f32:
                    if not todo[r] and d2s32[r] > nh32:  # accumulated in pass B
                        continue
                    d2, dn, x, y, z = _sphere_point(kd, distant_ds, lx, ly, lz, nx, ny, nz, px, py, pz, r2)
                else:
                    if not todo[r] and d2s[r] > near2 and den[r] > 0.0:  # accumulated in pass B
                        continue
                    d2, dn, x, y, z = d2s[r], den[r], sx[r], sy[r], sz[r]
                if d2 <= near2:  # the light is at the float32 point's rounding scale: exact point
                    px, py, pz = points64[i, 0] - gx0, points64[i, 1] - gy0, points64[i, 2] - gz0
                    d2, dn, x, y, z = _sphere_point(kd, distant_ds, lx, ly, lz, nx, ny, nz, px, py, pz, r2)
                    if d2 <= min_dist2:  # <=: a cutoff of 0 still catches d = 0
                        sing_f[r] = True
                        flags = True
                        continue
                if dn <= 0.0:  # area-light sample facing away
                    continue
                tri = -1
                if last >= 0:  # the previous such row's triangle first (_locate's test)
                    a0 = m00 * x + m01 * y + m02 * z
                    a1 = m10 * x + m11 * y + m12 * z
                    a2 = m20 * x + m21 * y + m22 * z
                    s = a0 + a1 + a2
                    if s > 0.0 and min(a0, min(a1, a2)) >= -CONE_EPS * s:
                        tri = last
                if tri < 0:
                    tri, w0, w1, w2 = locate(x, y, z, inv, grid_n, grid_start, grid_items)
                    if tri < 0:
                        out_f[r] = True
                        flags = True
                        continue
                if tri != last:
                    touched[tri] = 1
                    last = tri
                    m00, m01, m02 = inv[tri, 0, 0], inv[tri, 0, 1], inv[tri, 0, 2]
                    m10, m11, m12 = inv[tri, 1, 0], inv[tri, 1, 1], inv[tri, 1, 2]
                    m20, m21, m22 = inv[tri, 2, 0], inv[tri, 2, 1], inv[tri, 2, 2]
                    ka, kb, kc = tris[tri, 0], tris[tri, 1], tris[tri, 2]
                    ax, ay, az = lpos32[ka, 0], lpos32[ka, 1], lpos32[ka, 2]
                    bx, by, bz = lpos32[kb, 0], lpos32[kb, 1], lpos32[kb, 2]
                    cx, cy, cz = lpos32[kc, 0], lpos32[kc, 1], lpos32[kc, 2]
                    ia0, ia1, ia2 = _f32(inv_int[ka, 0] * l0), _f32(inv_int[ka, 1] * l1), _f32(inv_int[ka, 2] * l2)
                    ib0, ib1, ib2 = _f32(inv_int[kb, 0] * l0), _f32(inv_int[kb, 1] * l1), _f32(inv_int[kb, 2] * l2)
                    ic0, ic1, ic2 = _f32(inv_int[kc, 0] * l0), _f32(inv_int[kc, 1] * l1), _f32(inv_int[kc, 2] * l2)
                # the weights exactly as pass B2 computes them
                a0 = m00 * x + m01 * y + m02 * z
                a1 = m10 * x + m11 * y + m12 * z
                a2 = m20 * x + m21 * y + m22 * z
                a0 = max(a0, 0.0)
                a1 = max(a1, 0.0)
                a2 = max(a2, 0.0)
                g = lmax / ((a0 + a1 + a2) * dn)
                ua, ub, uc = _f32(a0 * g), _f32(a1 * g), _f32(a2 * g)  # float32 from here, as in pass B
                if not distant_ds:
                    p32x, p32y, p32z = _f32(px), _f32(py), _f32(pz)
                    ex, ey, ez = ax - p32x, ay - p32y, az - p32z
                    ua = ua * (ex * ex + ey * ey + ez * ez)
                    ex, ey, ez = bx - p32x, by - p32y, bz - p32z
                    ub = ub * (ex * ex + ey * ey + ez * ez)
                    ex, ey, ez = cx - p32x, cy - p32y, cz - p32z
                    uc = uc * (ex * ex + ey * ey + ez * ez)
                v0 = (ua * ia0 * _fetch(store, i, ka, 0)
                      + ub * ib0 * _fetch(store, i, kb, 0)
                      + uc * ic0 * _fetch(store, i, kc, 0))
                v1 = (ua * ia1 * _fetch(store, i, ka, 1)
                      + ub * ib1 * _fetch(store, i, kb, 1)
                      + uc * ic1 * _fetch(store, i, kc, 1))
                v2 = (ua * ia2 * _fetch(store, i, ka, 2)
                      + ub * ib2 * _fetch(store, i, kb, 2)
                      + uc * ic2 * _fetch(store, i, kc, 2))
                acc0[r] += v0
                acc1[r] += v1
                acc2[r] += v2
        for r0 in range(0, nc, 16):
            if runs[(i0 + r0) >> 4]:  # 16 rows = 16 consecutive pixels (a block row): 48 floats
                _store_run48(oflat, 3 * run_pix[(i0 + r0) >> 4], acc0, acc1, acc2, r0)
            else:
                for r in range(r0, min(nc, r0 + 16)):
                    q = 3 * pix[i0 + r]
                    oflat[q] = acc0[r]
                    oflat[q + 1] = acc1[r]
                    oflat[q + 2] = acc2[r]
        if flags:  # outside / singular flags (rare); the arrays arrive zeroed
            flagged[0] = 1
            for r in range(nc):
                if out_f[r]:
                    outside[pix[i0 + r]] = True
                if sing_f[r]:
                    singular[pix[i0 + r]] = True
                out_f[r] = False
                sing_f[r] = False
    # once per group, not per chunk: the non-temporal stores drain while the next chunks compute (a fence
    # per chunk waited for every chunk's 3 KiB to reach memory: 7.5 % of the serial kernel's samples)
    _fence()


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _exact_chunks(store, pix, ks, scales, ratios, out, c0, c1):
    """Chunks c0 .. c1 - 1 of :func:`exact_kernel`."""
    n = pix.size
    for ci in range(c0, c1):
        for i in range(ci * CHUNK, min(n, (ci + 1) * CHUNK)):
            q = pix[i]
            for c in range(3):
                acc = np.float32(0.0)
                for j in range(ks.size):
                    v = _fetch(store, i, ks[j], c)
                    if scales[j] != 1.0:
                        v = v / scales[j]
                    r = ratios[j, c]
                    acc += v if r == 1.0 else v * r
                out[q, c] = acc


_EXACT_MIN_CHUNKS = 8  # 2048 rows x lights x 3 channels per piece at least


def exact_kernel(store, pix, ks, scales, ratios, out, serial=None):
    """out[pix[i]] = sum_j (stored value of light ks[j] / scales[j]) x ratios[j], in float32; a ratio
    of exactly 1 adds the value unscaled (so one light at its own intensity is the stored image).
    Chunks of CHUNK rows split over the threads (``engine.sched.run_pieces_parallel``; ``serial`` as
    there)."""
    n_chunks = (pix.size + CHUNK - 1) // CHUNK
    run_pieces_parallel(lambda c0, c1: _exact_chunks(store, pix, ks, scales, ratios, out, c0, c1), n_chunks,
                        _EXACT_MIN_CHUNKS, serial)


@nb.njit(cache=True, nogil=True)
def zero_pixels(img, pixels):
    """img[pixels] = 0 for an (h*w, 3) image."""
    for i in range(pixels.size):
        q = pixels[i]
        img[q, 0] = 0.0
        img[q, 1] = 0.0
        img[q, 2] = 0.0

