"""3D warp of a layered depth cube into a camera (the first rendering stage of the LDC method).

Every sample of the three LDIs is rebuilt in float64 (frame origin + pixel centre + depth
along w; docs/hard-cases.md #6), projected into the camera (``engine/camera.py`` conventions) and
splatted with a z-buffer (distance along the pixel ray, like the reference's depth):

- **Footprint.** A sample stands for an ``h x h`` cell of its LDI's reference plane. Its
  surface patch is spanned by ``e_u = h (u - (n.u / n.w) w)`` and ``e_v`` (the cell lifted
  onto the tangent plane, n the geometric normal); both are projected through the camera's
  Jacobian at the sample, and the sample covers every pixel whose centre lies in the
  axis-aligned box of half-size ``0.5 (|a| + |b|)`` around its projection (plus always the
  nearest pixel). Half-sizes are capped at ``max_footprint`` (16) pixels (close-ups: beyond it
  the image is under-sampled anyway and the hole detector takes over).
- **Grazing samples are dropped.** A sample whose LDI direction makes ``|n_g . w| <
  min_cos`` (0.5) with the surface is left to the other two LDIs: every normal has a
  component >= 1/sqrt(3) = 0.577 along some axis, so one LDI always keeps it; this stops
  edge-on surfaces (thin walls, a wall parallel to an axis) from smearing.
- **Sides.** Surfaces are two-sided like the reference; the side facing the eye picks the
  sample's ``diffuse[:, side]``. Samples within the depth slack count as one surface only
  when the same side faces the eye (else the nearer wins: a sheet seen from behind just
  under one seen from the front, as the teapot's lid under its rim, showed through as dark
  speckle, LRMS 0.201 -> 0.179 on teapot_glossy at 256x256). Back faces of CLOSED objects (the inner side; effect plan
  ``closed_objects``) are culled.
- **Holes.** A pixel is a hole when no sample covers it, or when at least ``hole_neighbors``
  (6) of its 8 neighbours are covered and nearer than ``(1 - hole_rel_depth)`` (0.95) times
  its depth: a far surface showing through a crack in a near one. (Six, because a pixel
  just outside a concave corner of a silhouette legitimately has five nearer neighbours.)
  Uncovered background pixels are holes too: the warp cannot tell "nothing there" from "not
  sampled"; ``fill="raycast"`` resolves them.
- **Filling.** ``fill="none"``: holes keep the background and are flagged. ``fill="raycast"``
  casts Embree rays from the eye for the hole pixels, shaded with the same diffuse model as
  the bake: a check against the scene's triangles, not the paper's image-based ray tracing
  through the LDC (``fill="ibrt"``, the renderer's default), and it needs the caster.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numba as nb
import numpy as np

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.camera import camera_rays
from engine.errors import InvalidInputError, NonFiniteOutputError
from engine.newviews.ldc import LDC, shade_samples, surface_attributes
from engine.raycast import RayCaster
from engine.scene import CameraParams
from engine.sched import next_block

PROV_NONE = 0
PROV_WARPED = 1
PROV_FILLED = 2


@dataclass
class WarpResult:
    """radiance (h, w, 3) float32 view-independent (diffuse) radiance; depth (h, w) float32
    distance along the pixel ray (0 where empty); normal (h, w, 3) float32 shading normal
    facing the camera; material_id / object_id (h, w) int32 (-1 where empty); sample_axis
    (h, w) int8 and sample_index (h, w) int64: the LDC sample shown (-1: none / ray-filled);
    sample_side (h, w) int8; hole_mask (h, w) bool (before filling); provenance (h, w) uint8
    (0 background, 1 warped, 2 hole-filled)."""

    radiance: np.ndarray
    depth: np.ndarray
    normal: np.ndarray
    material_id: np.ndarray
    object_id: np.ndarray
    sample_axis: np.ndarray
    sample_index: np.ndarray
    sample_side: np.ndarray
    hole_mask: np.ndarray
    provenance: np.ndarray
    n_holes: int
    n_filled: int = 0
    timings: dict[str, float] = field(default_factory=dict)


@nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _project(origin, fu, fv, fw, h, nu, offsets, depth, ng, obj, closed,
             ortho, eye, right, up, fwd, W, H, th, hh, min_cos, max_fp, fp_scale,
             out_f, out_side, out_box, groups):
    """Per sample (in parallel): projected position, footprint half-sizes, distance, depth
    slack and visible side into out_f (n, 4) = (px, py, dist, tol); out_box (n, 4) int32
    the footprint's pixel rows and columns (y0, y1, x0, x1), clipped to the image; y0 > y1 for a
    sample that is not splatted (dropped, or its footprint off the image's rows)."""
    aspect = W / H
    npix = offsets.shape[0] - 1
    nblk = (npix + 63) // 64
    counter = np.zeros(1, np.int64)
    for _ in nb.prange(groups):  # blocks of 64 LDI pixels from a shared counter (samples cluster: engine.sched)
        while True:
            blk = next_block(counter)
            if blk >= nblk:
                break
            for k in range(blk * 64, min(npix, blk * 64 + 64)):
                s0 = offsets[k]
                s1 = offsets[k + 1]
                if s0 == s1:
                    continue
                a = (k % nu + 0.5) * h
                b = (k // nu + 0.5) * h
                bx = origin[0] + a * fu[0] + b * fv[0]
                by = origin[1] + a * fu[1] + b * fv[1]
                bz = origin[2] + a * fu[2] + b * fv[2]
                for s in range(s0, s1):
                    out_box[s, 0] = 1
                    out_box[s, 1] = 0
                    n0, n1, n2 = ng[s, 0], ng[s, 1], ng[s, 2]
                    nw = n0 * fw[0] + n1 * fw[1] + n2 * fw[2]
                    if abs(nw) < min_cos:
                        continue
                    px_ = bx + depth[s] * fw[0]
                    py_ = by + depth[s] * fw[1]
                    pz_ = bz + depth[s] * fw[2]
                    rx, ry, rz = px_ - eye[0], py_ - eye[1], pz_ - eye[2]
                    xc = rx * right[0] + ry * right[1] + rz * right[2]
                    yc = rx * up[0] + ry * up[1] + rz * up[2]
                    zc = rx * fwd[0] + ry * fwd[1] + rz * fwd[2]
                    if ortho:
                        if zc < 0.0:
                            continue
                        vd = n0 * fwd[0] + n1 * fwd[1] + n2 * fwd[2]
                        dist = zc
                    else:
                        dist = math.sqrt(rx * rx + ry * ry + rz * rz)
                        if zc <= 1e-12 * dist or dist == 0.0:
                            continue
                        vd = n0 * rx + n1 * ry + n2 * rz
                    if vd == 0.0:
                        continue
                    # depth slack within which two samples count as the same surface: about one
                    # LDC cell along the surface at this slope to the view ray
                    cosv = abs(vd) / (dist if not ortho else 1.0)
                    tol = 1.5 * h / max(cosv, 0.25)
                    side = 0 if vd < 0.0 else 1
                    if side == 1 and closed[obj[s]]:
                        continue  # inner side of a closed object: back face
                    # projection and Jacobian (pixels per world unit) at the sample
                    if ortho:
                        kx = W / (2.0 * hh * aspect)
                        ky = H / (2.0 * hh)
                        pxf = (xc * kx / W * 2.0 + 1.0) * 0.5 * W
                        pyf = (1.0 - yc * ky / H * 2.0) * 0.5 * H
                    else:
                        kx = W / (2.0 * th * aspect)
                        ky = H / (2.0 * th)
                        pxf = (xc / zc * kx / W * 2.0 + 1.0) * 0.5 * W
                        pyf = (1.0 - yc / zc * ky / H * 2.0) * 0.5 * H
                    if not (abs(pxf) < 1e9 and abs(pyf) < 1e9):
                        continue
                    # tangent edges of the cell
                    cu = (n0 * fu[0] + n1 * fu[1] + n2 * fu[2]) / nw
                    cv = (n0 * fv[0] + n1 * fv[1] + n2 * fv[2]) / nw
                    ex = 0.0
                    ey = 0.0
                    for e in range(2):
                        if e == 0:
                            dx = h * (fu[0] - cu * fw[0])
                            dy = h * (fu[1] - cu * fw[1])
                            dz = h * (fu[2] - cu * fw[2])
                        else:
                            dx = h * (fv[0] - cv * fw[0])
                            dy = h * (fv[1] - cv * fw[1])
                            dz = h * (fv[2] - cv * fw[2])
                        ex_ = dx * right[0] + dy * right[1] + dz * right[2]
                        ey_ = dx * up[0] + dy * up[1] + dz * up[2]
                        ez_ = dx * fwd[0] + dy * fwd[1] + dz * fwd[2]
                        if ortho:
                            ex += abs(kx * ex_)
                            ey += abs(ky * ey_)
                        else:
                            ex += abs(kx * (ex_ / zc - xc * ez_ / (zc * zc)))
                            ey += abs(ky * (ey_ / zc - yc * ez_ / (zc * zc)))
                    ex = 0.5 * ex * fp_scale
                    ey = 0.5 * ey * fp_scale
                    if not (ex <= max_fp):
                        ex = max_fp
                    if not (ey <= max_fp):
                        ey = max_fp
                    out_f[s, 0] = pxf
                    out_f[s, 1] = pyf
                    out_f[s, 2] = dist
                    out_f[s, 3] = tol
                    out_side[s] = side
                    iy = int(math.floor(pyf))
                    ix = int(math.floor(pxf))
                    y0 = max(min(int(math.ceil(pyf - ey - 0.5)), iy), 0)
                    y1 = min(max(int(math.floor(pyf + ey - 0.5)), iy), H - 1)
                    x0 = max(min(int(math.ceil(pxf - ex - 0.5)), ix), 0)
                    x1 = min(max(int(math.floor(pxf + ex - 0.5)), ix), W - 1)
                    if y0 <= y1 and x0 <= x1:  # else no pixel: stays "not splatted"
                        out_box[s, 0] = y0
                        out_box[s, 1] = y1
                        out_box[s, 2] = x0
                        out_box[s, 3] = x1


@nb.njit(cache=True, parallel=True, nogil=True)
def _write(axis_id, out_f, out_side, out_box, W, H, zb, bands):
    """Z-buffer writes in CSR order, ``bands`` threads each owning the image's 8-row stripes
    ``g, g + bands, ...`` (interleaved: the bottom of a view - a floor close by - has far more
    writes than the top): each thread applies every sample to its own rows only, so each
    pixel sees the samples in CSR order whatever the band count (the serial pass's image, bit
    for bit)."""
    for g in nb.prange(bands):
        _write_rows(axis_id, out_f, out_side, out_box, W, H, zb, g, bands)


@nb.njit(cache=True, nogil=True)
def _write_rows(axis_id, out_f, out_side, out_box, W, H, zb, g, bands):
    """The z-buffer writes of the image rows in stripes g, g + bands, ... (8 rows each; 0, 1:
    the serial pass). ``zb`` (H, W, 3) float64 per pixel: distance, the winner's offset from
    the pixel centre, and its code ``8 sample + 2 axis + side`` (-8: none), one cache line
    per pixel instead of five arrays (see ``_init_buffers``). The footprints' pixel boxes come
    from ``_project`` (16 bytes per sample: a thread skips the samples outside its stripes
    without reading their records; measured 1.6 -> 1.3 ms per half of an axis). The boxes replace the
    footprint half-sizes in the records: ``out_f`` keeps only what the pixel loop reads."""
    for s in range(out_box.shape[0]):
        y0 = np.int64(out_box[s, 0])
        y1 = np.int64(out_box[s, 1])
        if y0 > y1:
            continue
        # this thread's first stripe at or after y0's (one integer division per sample, none per row)
        k = (y0 >> 3) + (g - (y0 >> 3)) % bands
        if (k << 3) > y1:
            continue  # the whole footprint is in other threads' stripes
        pxf = out_f[s, 0]
        pyf = out_f[s, 1]
        dist = out_f[s, 2]
        tol = out_f[s, 3]
        side = out_side[s]
        x0 = np.int64(out_box[s, 2])
        x1 = np.int64(out_box[s, 3])
        while (k << 3) <= y1:
            ya = max(y0, k << 3)
            yb = min(y1, (k << 3) + 7)
            k += bands
            for y in range(ya, yb + 1):
                for x in range(x0, x1 + 1):
                    ddx = x + 0.5 - pxf
                    ddy = y + 0.5 - pyf
                    off = math.sqrt(ddx * ddx + ddy * ddy)
                    z = zb[y, x, 0]
                    b = zb[y, x, 1]
                    # same surface (within tol, same side): the better-centred sample wins; a tie
                    # within 0.05 px (layers of one LDI pixel, up to parallax) goes to the nearer.
                    # Opposite sides are never one surface: a sample seen from behind next to one
                    # seen from the front is another sheet (a lid under a rim, the inner wall of a
                    # thin part), so the plain depth test orders them
                    if side == (np.int64(zb[y, x, 2]) & 1):
                        win = dist <= z + tol and (off < b - 0.05 or (off <= b + 0.05 and dist < z))
                    else:
                        win = dist < z
                    if dist < z - tol or win:
                        zb[y, x, 0] = dist
                        zb[y, x, 1] = off
                        zb[y, x, 2] = np.float64(8 * s + 2 * axis_id + side)


@nb.njit(cache=True, parallel=True, nogil=True)
def _detect_holes(zb, rel, need, out, groups):
    H, W = zb.shape[0], zb.shape[1]
    counter = np.zeros(1, np.int64)
    for _ in nb.prange(groups):  # rows from a shared counter: the image's halves differ in work (engine.sched)
        while True:
            y = next_block(counter)
            if y >= H:
                break
            for x in range(W):
                d = zb[y, x, 0]
                if not d < np.inf:
                    out[y, x] = True
                    continue
                lim = d * (1.0 - rel)
                c = 0
                for dy in range(-1, 2):
                    for dx in range(-1, 2):
                        if dx == 0 and dy == 0:
                            continue
                        yy = y + dy
                        xx = x + dx
                        if 0 <= yy < H and 0 <= xx < W and zb[yy, xx, 0] < lim:
                            c += 1
                out[y, x] = c >= need



@nb.njit(cache=True, parallel=True, nogil=True)
def _init_buffers(zb, groups):
    """The z-buffer empty: distance and offset inf, no sample (code -8: sample -1, side 0; sample
    indices up to 2^50 are exact in the float64 code)."""
    H, W = zb.shape[0], zb.shape[1]
    counter = np.zeros(1, np.int64)
    for _ in nb.prange(groups):  # rows from a shared counter: the image's halves differ in work (engine.sched)
        while True:
            y = next_block(counter)
            if y >= H:
                break
            for x in range(W):
                zb[y, x, 0] = np.inf
                zb[y, x, 1] = np.inf
                zb[y, x, 2] = -8.0


@nb.njit(cache=True, nogil=True)
def _resolve_pixel(y, x, i, s, diffuse, nrm, material, obj, radiance, normal, mat_id, obj_id):
    sign = 1.0 if s == 0 else -1.0
    for c in range(3):
        radiance[y, x, c] = diffuse[i, s, c]
        normal[y, x, c] = sign * nrm[i, c]
    mat_id[y, x] = material[i]
    obj_id[y, x] = obj[i]


@nb.njit(cache=True, parallel=True, nogil=True)
def _resolve(zb, win_axis, win_idx, win_side, bg, diff0, nrm0, mat0, obj0, diff1, nrm1, mat1, obj1, diff2, nrm2,
             mat2, obj2, radiance, depth, normal, mat_id, obj_id, prov, groups):
    """Every pixel in one pass: the winner (axis, sample, side) decoded from the z-buffer, its
    attributes, or the background (depth 0, ids -1, provenance 0) where nothing won. Returns
    the number of non-finite values written."""
    H, W = win_axis.shape
    bad = 0
    counter = np.zeros(1, np.int64)
    for _ in nb.prange(groups):  # rows from a shared counter: the image's halves differ in work (engine.sched)
        while True:
            y = next_block(counter)
            if y >= H:
                break
            for x in range(W):
                code = np.int64(zb[y, x, 2])
                if code < 0:
                    win_axis[y, x] = -1
                    win_idx[y, x] = -1
                    win_side[y, x] = 0
                    for c in range(3):
                        radiance[y, x, c] = bg[c]
                        normal[y, x, c] = 0.0
                    depth[y, x] = 0.0
                    mat_id[y, x] = -1
                    obj_id[y, x] = -1
                    prov[y, x] = 0
                    continue
                i = code >> 3
                a = (code >> 1) & 3
                s = code & 1
                win_axis[y, x] = a
                win_idx[y, x] = i
                win_side[y, x] = s
                if a == 0:
                    _resolve_pixel(y, x, i, s, diff0, nrm0, mat0, obj0, radiance, normal, mat_id, obj_id)
                elif a == 1:
                    _resolve_pixel(y, x, i, s, diff1, nrm1, mat1, obj1, radiance, normal, mat_id, obj_id)
                else:
                    _resolve_pixel(y, x, i, s, diff2, nrm2, mat2, obj2, radiance, normal, mat_id, obj_id)
                depth[y, x] = zb[y, x, 0]
                prov[y, x] = 1
                if not (np.isfinite(radiance[y, x, 0]) and np.isfinite(radiance[y, x, 1])
                        and np.isfinite(radiance[y, x, 2]) and np.isfinite(depth[y, x])):
                    bad += 1
    return bad


def warp_ldc(ldc: LDC, camera: CameraParams, *, fill: str = "none", caster: RayCaster | None = None,
             min_cos: float = 0.5, max_footprint: float = 16.0, footprint_scale: float = 1.0,
             hole_rel_depth: float = 0.05, hole_neighbors: int = 6, area_light_samples: int = 16,
             seed: int = 0, radiance_dtype=np.float32) -> WarpResult:
    """Warp every LDC sample into ``camera`` with a depth test; detect (and optionally fill) holes.
    ``radiance_dtype`` float64 gives the renderer its working precision directly (the values
    are the same: the LDC's float32 radiance). Timed stages: "splat" (``_splat``), "holes",
    "resolve" (each pixel's winner's records), "fill" (``_raycast_fill``)."""
    _check_options(fill, caster, min_cos, max_footprint, footprint_scale, hole_rel_depth, hole_neighbors)
    t_start = time.perf_counter()
    W, H = camera.width, camera.height
    zb = np.empty((H, W, 3))  # distance, offset, winner code per pixel (_write_rows)
    win_axis = np.empty((H, W), np.int8)
    win_idx = np.empty((H, W), np.int64)
    win_side = np.empty((H, W), np.int8)
    bands = max(1, int(nb.get_num_threads()))  # z-buffer stripes and row groups: one per numba thread
    _init_buffers(zb, bands)
    t_splat = _splat(ldc, camera, zb, bands, min_cos, max_footprint, footprint_scale)
    t0 = time.perf_counter()
    holes = np.zeros((H, W), np.bool_)
    _detect_holes(zb, hole_rel_depth, hole_neighbors, holes, bands)
    t_holes = time.perf_counter() - t0
    t0 = time.perf_counter()
    if np.dtype(radiance_dtype) not in (np.float32, np.float64):
        raise InvalidInputError("radiance_dtype must be float32 or float64")
    radiance = np.empty((H, W, 3), radiance_dtype)
    depth = np.empty((H, W), np.float32)
    normal = np.empty((H, W, 3), np.float32)
    mat_id = np.empty((H, W), np.int32)
    obj_id = np.empty((H, W), np.int32)
    prov = np.empty((H, W), np.uint8)
    if [ax.axis for ax in ldc.axes] != [0, 1, 2]:
        raise InvalidInputError("the LDC's axes must be x, y, z in that order")
    a0, a1, a2 = ldc.axes
    n_bad = _resolve(zb, win_axis, win_idx, win_side, ldc.background.astype(np.float32), a0.diffuse, a0.normal,
                     a0.material, a0.object, a1.diffuse, a1.normal, a1.material, a1.object, a2.diffuse, a2.normal,
                     a2.material, a2.object, radiance, depth, normal, mat_id, obj_id, prov, bands)
    t_resolve = time.perf_counter() - t0
    out = WarpResult(radiance=radiance, depth=depth, normal=normal, material_id=mat_id, object_id=obj_id,
                     sample_axis=win_axis, sample_index=win_idx, sample_side=win_side, hole_mask=holes,
                     provenance=prov, n_holes=int(holes.sum()))
    t_fill = 0.0
    if fill == "raycast" and out.n_holes:
        t0 = time.perf_counter()
        out.n_filled = _raycast_fill(ldc, camera, caster, out, area_light_samples, seed)
        t_fill = time.perf_counter() - t0
    if n_bad or (out.n_filled and (not np.all(np.isfinite(radiance)) or not np.all(np.isfinite(depth)))):
        raise NonFiniteOutputError("LDC warp produced non-finite values")
    out.timings = {"splat": t_splat, "holes": t_holes, "resolve": t_resolve, "fill": t_fill,
                   "total": time.perf_counter() - t_start}
    return out


def _check_options(fill, caster, min_cos, max_footprint, footprint_scale, hole_rel_depth, hole_neighbors) -> None:
    if fill not in ("none", "raycast"):
        raise InvalidInputError(f"fill must be 'none' or 'raycast', got {fill!r}")
    if fill == "raycast" and caster is None:
        raise InvalidInputError("fill='raycast' needs the scene's caster")
    if not (0.0 <= min_cos < 1.0 / math.sqrt(3.0)):
        raise InvalidInputError("min_cos must be in [0, 1/sqrt(3)) so every surface keeps one LDI")
    if not (0.0 < max_footprint <= 64.0) or not (0.0 < footprint_scale <= 4.0):
        raise InvalidInputError("max_footprint must be in (0, 64] and footprint_scale in (0, 4]")
    if not (0.0 < hole_rel_depth < 1.0) or not (1 <= hole_neighbors <= 8):
        raise InvalidInputError("hole_rel_depth must be in (0, 1) and hole_neighbors in [1, 8]")


def _splat(ldc: LDC, camera: CameraParams, zb: np.ndarray, bands: int, min_cos: float, max_footprint: float,
           footprint_scale: float) -> float:
    """Every sample of the three LDIs projected (``_project``) and written into the z-buffer
    ``zb`` (``_write``), axis by axis. Returns the seconds the projection and writing took."""
    W, H = camera.width, camera.height
    right, up, fwd = camera.basis()
    eye = np.asarray(camera.eye, dtype=np.float64)
    ortho = camera.kind == "orthographic"
    th = math.tan(math.radians(camera.fov_y_deg) * 0.5)
    hh = 0.5 * camera.ortho_height
    n_obj = max([len(ldc.closed_objects)] + [int(a.object.max(initial=-1)) + 1 for a in ldc.axes])
    closed = np.zeros(max(n_obj, 1), dtype=np.bool_)
    closed[:len(ldc.closed_objects)] = ldc.closed_objects
    t0 = time.perf_counter()
    for ax in ldc.axes:
        f = ax.ldi.frame
        n = ax.n_samples
        out_f = np.empty((n, 4))
        out_side = np.empty(n, np.int8)
        out_box = np.empty((n, 4), np.int32)
        _project(f.origin, f.u, f.v, f.w, f.h, f.nu, ax.ldi.offsets, ax.ldi.depth, ax.geo_normal, ax.object, closed,
                 ortho, eye, right, up, fwd, W, H, th, hh, min_cos, max_footprint, footprint_scale,
                 out_f, out_side, out_box, bands)
        _write(ax.axis, out_f, out_side, out_box, W, H, zb, bands)
    return time.perf_counter() - t0


def _raycast_fill(ldc: LDC, camera: CameraParams, caster: RayCaster, w: WarpResult, area_light_samples: int,
                  seed: int) -> int:
    """``fill="raycast"``: an Embree ray from the eye per hole pixel of ``w`` (updated in place);
    a hit is shaded with the bake's diffuse model, a miss shows the background. Returns the
    number of pixels filled."""
    radiance, depth, normal, mat_id, obj_id, prov = (w.radiance, w.depth, w.normal, w.material_id, w.object_id,
                                                     w.provenance)
    win_axis, win_idx = w.sample_axis, w.sample_index
    ys, xs = np.nonzero(w.hole_mask)
    o, d = camera_rays(camera, xs + 0.5, ys + 0.5)
    hit = caster.intersect(o, d)
    ok = hit.prim >= 0
    # misses: background, no sample
    miss = ~ok
    radiance[ys[miss], xs[miss]] = ldc.background.astype(radiance.dtype)
    depth[ys[miss], xs[miss]] = 0.0
    normal[ys[miss], xs[miss]] = 0.0
    mat_id[ys[miss], xs[miss]] = -1
    obj_id[ys[miss], xs[miss]] = -1
    prov[ys[miss], xs[miss]] = PROV_NONE
    win_axis[ys[miss], xs[miss]] = -1
    win_idx[ys[miss], xs[miss]] = -1
    if not ok.any():
        return 0
    sc = caster.scene
    yh, xh = ys[ok], xs[ok]
    p, ng, ns = surface_attributes(sc, hit.prim[ok], hit.u[ok], hit.v[ok])
    mat = sc.tri_material[hit.prim[ok]].astype(np.int32)
    occl = np.asarray(ldc.plan.get("occludable_lights", [True] * sc.lights.count), dtype=np.bool_)
    rad, _, _ = shade_samples(sc, caster, p, ng, ns, mat, occl, store_bits=False,
                              area_light_samples=area_light_samples, seed=seed, stream_id=3)
    side = (np.einsum("ij,ij->i", ng, d[ok]) >= 0).astype(np.int64)
    radiance[yh, xh] = rad[np.arange(side.shape[0]), side]
    depth[yh, xh] = hit.t[ok].astype(np.float32)
    normal[yh, xh] = (ns * np.where(side == 0, 1.0, -1.0)[:, None]).astype(np.float32)
    mat_id[yh, xh] = mat
    obj_id[yh, xh] = sc.tri_object[hit.prim[ok]]
    prov[yh, xh] = PROV_FILLED
    win_axis[yh, xh] = -1
    win_idx[yh, xh] = -1
    return int(ok.sum())
