"""Frame reconstruction: reproject base range images into a new camera (Radiance ``pinterp``).

For a camera and a time, the ``n_bases`` base viewpoints nearest to the eye are reprojected:
every cube-map pixel with a hit becomes the world point ``eye_b + depth * dir`` (float64),
is projected into the camera and depth-tested against the other samples of the frame:

- **depth test with tolerance**: per output pixel, the nearest fragment distance ``z_min``
  wins; every fragment with ``z <= z_min (1 + depth_tol)`` is averaged (the same surface seen
  from several bases or several base pixels), weighted by ``1 / (1 - cos a + 1e-12)`` where
  ``a`` is the angle between the base ray and the new ray to the same point: base rays closest
  in direction dominate, and at a base viewpoint the base image is reproduced.
- **radiance at time t**: per base pixel, ``direct`` is interpolated linearly between the two
  bracketing direct time samples and ``indirect`` between the two bracketing indirect time
  samples; depth and object ids come from the direct time sample nearest to ``t``. At a time
  sample this is exactly that sample's image.
- rays that left the scene (depth 0) are projected as directions (points at infinity) and
  show the scene background where no surface lands (``provenance`` SKY).

Fill modes (``fill``):

- ``none``: every base pixel lands on at most one output pixel; empty pixels keep the
  background colour (provenance HOLE).
- ``foreground``: base pixels are also drawn as small parallelograms (two triangles) to their
  right / lower neighbours on the same cube face when all four lie on the same object with
  depths within a factor ``quad_depth_ratio`` (1.6) of each other (same surface: never bridging a depth
  discontinuity), with depth and radiance interpolated; closes the cracks of magnification.
  Quads larger than ``max_footprint`` pixels are skipped.
- ``background``: like ``none``, then every empty pixel copies the farther (by depth) of the
  nearest filled pixels left / right in its row and up / down in its column (repeated for
  holes whose whole row and column were empty).
- ``both``: foreground, then background.
- ``trace``: foreground, then the remaining holes are ray traced with the reference renderer
  (``ReferenceRenderer.shade_hits`` on the scene at time t: one ray per pixel).

Everything is deterministic. The splat runs in horizontal bands, one per thread: each band
walks all projected samples and rasterises only its own rows, so no atomics are needed.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numba as nb
import numpy as np

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.errors import InvalidInputError, NonFiniteOutputError
from engine.scene import CameraParams
from engine.walkthrough.range_images import _BASIS

__all__ = [
    "FILL_MODES",
    "PROV_BACKGROUND_FILL",
    "PROV_FOREGROUND",
    "PROV_HOLE",
    "PROV_REPROJECTED",
    "PROV_SKY",
    "PROV_TRACED",
    "FrameResult",
    "reproject",
]

FILL_MODES = ("none", "foreground", "background", "both", "trace")

PROV_HOLE = 0  # nothing landed; background colour
PROV_REPROJECTED = 1  # at least one base pixel landed here
PROV_FOREGROUND = 2  # covered only by foreground-fill parallelograms
PROV_BACKGROUND_FILL = 3  # copied from a neighbour by the background fill
PROV_TRACED = 4  # ray traced
PROV_SKY = 5  # only rays that left the scene: background radiance


@dataclass
class FrameResult:
    """radiance (h, w, 3) float32; depth (h, w) float32 distance along the pixel ray (0: none);
    object_id (h, w) int32 (-1: none); provenance (h, w) uint8 (PROV_*); timings in seconds;
    bases: indices of the base views used; counts of provenance classes."""

    radiance: np.ndarray
    depth: np.ndarray
    object_id: np.ndarray
    provenance: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)
    bases: list[int] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=dict)


# ---------------------------------------------------------------------------- kernels


@nb.njit(cache=True, inline="always", error_model="numpy")
def _radiance(v, f, r, c, k, td0, td1, a_d, ti0, ti1, a_i, direct, indirect):
    d = direct[v, td0, f, r, c, k]
    if a_d != 0.0:
        d = (1.0 - a_d) * d + a_d * direct[v, td1, f, r, c, k]
    i = indirect[v, ti0, f, r, c, k]
    if a_i != 0.0:
        i = (1.0 - a_i) * i + a_i * indirect[v, ti1, f, r, c, k]
    return d + i


@nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _project(views, tg, td0, td1, a_d, ti0, ti1, a_i, direct, indirect, eyes, depth, oid, basis, res, ortho, ceye,
             right, up, fwd, W, H, sx_scale, sy_scale, margin, face_on, px_out, py_out, z_out, cos_out, rad_out,
             state_out, oid_out):
    """Project every base pixel of the selected bases. state: 0 invalid, 1 surface, 2 sky
    (direction only). px/py are continuous pixel coordinates (samples farther than ``margin`` pixels
    outside the frame are invalid), z the distance along the new ray (perspective) or along the view
    axis (orthographic), cos_out holds 1 - cos(angle between the base ray and the new ray). Faces with
    ``face_on[b, f]`` False are skipped (all their samples invalid)."""
    inv = 1.0 / res
    nrows = views.shape[0] * 6 * res
    for row in nb.prange(nrows):  # one cube row per iteration: no integer division per sample
        b = row // (6 * res)
        rem = row - b * 6 * res
        f = rem // res
        r = rem - f * res
        v = views[b]
        g = tg[b]
        sy = 1.0 - (r + 0.5) * 2.0 * inv
        if not face_on[b, f]:  # culled: nothing of this face can reach the frame
            for c in range(res):
                state_out[row * res + c] = 0
            continue
        for c in range(res):
            s = row * res + c
            sx = (c + 0.5) * 2.0 * inv - 1.0
            dx = basis[f, 2, 0] + sx * basis[f, 0, 0] + sy * basis[f, 1, 0]
            dy = basis[f, 2, 1] + sx * basis[f, 0, 1] + sy * basis[f, 1, 1]
            dz = basis[f, 2, 2] + sx * basis[f, 0, 2] + sy * basis[f, 1, 2]
            ln = math.sqrt(dx * dx + dy * dy + dz * dz)
            dx /= ln
            dy /= ln
            dz /= ln
            dep = depth[v, g, f, r, c]
            state_out[s] = 0
            oid_out[s] = oid[v, g, f, r, c]
            if dep > 0.0:
                qx = eyes[v, 0] + dx * dep - ceye[0]
                qy = eyes[v, 1] + dy * dep - ceye[1]
                qz = eyes[v, 2] + dz * dep - ceye[2]
                kind = 1
            else:
                if ortho:
                    continue
                qx, qy, qz = dx, dy, dz
                kind = 2
            xc = qx * right[0] + qy * right[1] + qz * right[2]
            yc = qx * up[0] + qy * up[1] + qz * up[2]
            zc = qx * fwd[0] + qy * fwd[1] + qz * fwd[2]
            if ortho:
                if zc <= 0.0:
                    continue
                u = xc / sx_scale
                w = yc / sy_scale
                dist = zc
                cosv = 1.0 - (dx * fwd[0] + dy * fwd[1] + dz * fwd[2])
            else:
                dist = math.sqrt(qx * qx + qy * qy + qz * qz)
                if zc <= 1e-12 * dist or dist == 0.0:
                    continue
                u = xc / (zc * sx_scale)
                w = yc / (zc * sy_scale)
                # 1 - cos(angle) from the chord between the unit rays: accurate for tiny angles
                ex, ey, ez = dx - qx / dist, dy - qy / dist, dz - qz / dist
                cosv = 0.5 * (ex * ex + ey * ey + ez * ez)
            pxf = (u + 1.0) * 0.5 * W
            pyf = (1.0 - w) * 0.5 * H
            # farther than max_fp outside the frame: neither the point nor a quad it starts can land
            if not (-margin <= pxf <= W + margin and -margin <= pyf <= H + margin):
                continue
            px_out[s] = pxf
            py_out[s] = pyf
            z_out[s] = dist if kind == 1 else np.inf
            cos_out[s] = cosv
            for k in range(3):  # radiance at time t, once per sample (the splat reads it per fragment)
                rad_out[s, k] = _radiance(v, f, r, c, k, td0[b], td1[b], a_d[b], ti0[b], ti1[b], a_i[b], direct,
                                          indirect)
            state_out[s] = kind


@nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _quad_flags(views, tg, res, depth, oid, state, quad_ratio, qok):
    """qok[s] = 1 when base pixel s and its right, lower-right and lower neighbours (same face) are
    all projected surface samples of one object with depths within a factor ``quad_ratio``."""
    nrows = views.shape[0] * 6 * res
    for row in nb.prange(nrows):
        b = row // (6 * res)
        rem = row - b * 6 * res
        f = rem // res
        r = rem - f * res
        v = views[b]
        g = tg[b]
        for c in range(res):
            s = row * res + c
            qok[s] = 0
            if c + 1 >= res or r + 1 >= res:
                continue
            if state[s] != 1 or state[s + 1] != 1 or state[s + res] != 1 or state[s + res + 1] != 1:
                continue
            o0 = oid[v, g, f, r, c]
            if oid[v, g, f, r, c + 1] != o0 or oid[v, g, f, r + 1, c + 1] != o0 or oid[v, g, f, r + 1, c] != o0:
                continue
            d0 = depth[v, g, f, r, c]
            d1 = depth[v, g, f, r, c + 1]
            d2 = depth[v, g, f, r + 1, c + 1]
            d3 = depth[v, g, f, r + 1, c]
            if max(max(d0, d1), max(d2, d3)) > min(min(d0, d1), min(d2, d3)) * quad_ratio:
                continue
            qok[s] = 1


@nb.njit(cache=True, error_model="numpy")
def _edge(ax, ay, bx, by, px, py):
    return (bx - ax) * (py - ay) - (by - ay) * (px - ax)


@nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _splat(live, res, W, H, px, py, z, cosw, rad, state, soid, qok, quads, max_fp, depth_tol, nbands,
           acc, wsum, zbuf, zoid, flags, acc_sky, wsky):
    """Depth-tested, tolerance-averaged splat of points (and foreground quads), band by band."""
    n = live.shape[0]
    for band in nb.prange(nbands):
        y0 = band * H // nbands
        y1 = (band + 1) * H // nbands
        for phase in range(2):
            for j in range(n):
                s = live[j]
                st = state[s]
                pys = py[s]
                if pys < y0 - max_fp - 1.0 or pys >= y1 + max_fp + 1.0:
                    continue  # neither the point nor a quad it starts can reach this band
                # ---- the point sample
                ix = int(math.floor(px[s]))
                iy = int(math.floor(pys))
                if 0 <= ix < W and y0 <= iy < y1:
                    q = iy * W + ix
                    if phase == 0:
                        if st == 1 and z[s] < zbuf[q]:
                            zbuf[q] = z[s]
                            zoid[q] = soid[s]
                        flags[q] |= 1 if st == 1 else 4
                    elif st == 1 and z[s] <= zbuf[q] * (1.0 + depth_tol):
                        w = 1.0 / (cosw[s] + 1e-12)
                        for k in range(3):
                            acc[q, k] += w * rad[s, k]
                        wsum[q] += w
                    elif st == 2 and zbuf[q] == np.inf:
                        for k in range(3):
                            acc_sky[q, k] += rad[s, k]
                        wsky[q] += 1.0
                # ---- the foreground quad to the right / lower neighbours
                if not quads or qok[s] == 0:
                    continue
                s1 = s + 1
                s2 = s + res + 1
                s3 = s + res
                o0 = soid[s]
                xmin = min(min(px[s], px[s1]), min(px[s2], px[s3]))
                xmax = max(max(px[s], px[s1]), max(px[s2], px[s3]))
                ymin = min(min(py[s], py[s1]), min(py[s2], py[s3]))
                ymax = max(max(py[s], py[s1]), max(py[s2], py[s3]))
                if xmax - xmin > max_fp or ymax - ymin > max_fp:
                    continue
                cx0 = max(int(math.ceil(xmin - 0.5)), 0)
                cx1 = min(int(math.floor(xmax - 0.5)), W - 1)
                cy0 = max(int(math.ceil(ymin - 0.5)), y0)
                cy1 = min(int(math.floor(ymax - 0.5)), y1 - 1)
                if cx0 > cx1 or cy0 > cy1:
                    continue
                # two triangles: (s, s1, s2) and (s, s2, s3)
                for tri in range(2):
                    ia = s
                    ib = s1 if tri == 0 else s2
                    ic = s2 if tri == 0 else s3
                    ax, ay = px[ia], py[ia]
                    bx, by = px[ib], py[ib]
                    cx, cy = px[ic], py[ic]
                    area = _edge(ax, ay, bx, by, cx, cy)
                    if area == 0.0:
                        continue
                    inv_area = 1.0 / area
                    for yy in range(cy0, cy1 + 1):
                        fy = yy + 0.5
                        for xx in range(cx0, cx1 + 1):
                            fx = xx + 0.5
                            wa = _edge(bx, by, cx, cy, fx, fy) * inv_area
                            wb = _edge(cx, cy, ax, ay, fx, fy) * inv_area
                            wc = 1.0 - wa - wb
                            if wa < -1e-9 or wb < -1e-9 or wc < -1e-9:
                                continue
                            zz = wa * z[ia] + wb * z[ib] + wc * z[ic]
                            q = yy * W + xx
                            if phase == 0:
                                if zz < zbuf[q]:
                                    zbuf[q] = zz
                                    zoid[q] = o0
                                flags[q] |= 2
                            elif zz <= zbuf[q] * (1.0 + depth_tol):
                                cw = wa * cosw[ia] + wb * cosw[ib] + wc * cosw[ic]
                                w = 1.0 / (cw + 1e-12)
                                for k in range(3):
                                    acc[q, k] += w * (wa * rad[ia, k] + wb * rad[ib, k] + wc * rad[ic, k])
                                wsum[q] += w


@nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _resolve(acc, wsum, zbuf, zoid, flags, acc_sky, wsky, background, out, dep, ids, prov):
    for q in nb.prange(wsum.shape[0]):
        if wsum[q] > 0.0:
            for k in range(3):
                out[q, k] = acc[q, k] / wsum[q]
            dep[q] = zbuf[q]
            ids[q] = zoid[q]
            prov[q] = PROV_REPROJECTED if flags[q] & 1 else PROV_FOREGROUND
        else:
            dep[q] = 0.0
            ids[q] = -1
            if wsky[q] > 0.0:  # only rays that left the scene: their (antialiased) radiance
                for k in range(3):
                    out[q, k] = acc_sky[q, k] / wsky[q]
                prov[q] = PROV_SKY
            else:
                for k in range(3):
                    out[q, k] = background[k]
                prov[q] = PROV_HOLE


@nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _background_fill(out, dep, ids, prov, W, H):
    """Each HOLE pixel copies the farther of the nearest filled pixels along its row and its
    column (sky counts as infinitely far). Linear time: nearest filled pixels by sweeps."""
    n = W * H
    left = np.empty(n, np.int64)
    right = np.empty(n, np.int64)
    upn = np.empty(n, np.int64)
    down = np.empty(n, np.int64)
    for y in nb.prange(H):
        last = -1
        for x in range(W):
            q = y * W + x
            if prov[q] != PROV_HOLE:
                last = q
            left[q] = last
        last = -1
        for x in range(W - 1, -1, -1):
            q = y * W + x
            if prov[q] != PROV_HOLE:
                last = q
            right[q] = last
    for x in nb.prange(W):
        last = -1
        for y in range(H):
            q = y * W + x
            if prov[q] != PROV_HOLE:
                last = q
            upn[q] = last
        last = -1
        for y in range(H - 1, -1, -1):
            q = y * W + x
            if prov[q] != PROV_HOLE:
                last = q
            down[q] = last
    src = np.full(n, -1, np.int64)
    for q in nb.prange(n):
        if prov[q] != PROV_HOLE:
            continue
        best = -1
        bz = -1.0
        for j in (left[q], right[q], upn[q], down[q]):
            if j >= 0:
                zj = np.inf if prov[j] == PROV_SKY else dep[j]
                if zj > bz:
                    best, bz = j, zj
        src[q] = best
    for q in nb.prange(n):
        j = src[q]
        if j >= 0:
            for k in range(3):
                out[q, k] = out[j, k]
            dep[q] = dep[j]
            ids[q] = ids[j]
            prov[q] = PROV_BACKGROUND_FILL


@nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _background_fill_sparse(out, dep, ids, prov, W, H, holes):
    """``_background_fill`` for a few holes: scan from each hole to its nearest filled pixels
    (same result, cost proportional to the hole runs instead of the image)."""
    src = np.full(holes.shape[0], -1, np.int64)
    for h in nb.prange(holes.shape[0]):
        q = holes[h]
        y = q // W
        x = q - y * W
        best = -1
        bz = -1.0
        for dx, dy in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            xx = x + dx
            yy = y + dy
            while 0 <= xx < W and 0 <= yy < H and prov[yy * W + xx] == PROV_HOLE:
                xx += dx
                yy += dy
            if 0 <= xx < W and 0 <= yy < H:
                j = yy * W + xx
                zj = np.inf if prov[j] == PROV_SKY else dep[j]
                if zj > bz:
                    best, bz = j, zj
        src[h] = best
    # serial on purpose: a second prange over the same range would be fused with the first by
    # numba, and the scans would then see holes already filled by other iterations
    for h in range(holes.shape[0]):
        j = src[h]
        if j >= 0:
            q = holes[h]
            for k in range(3):
                out[q, k] = out[j, k]
            dep[q] = dep[j]
            ids[q] = ids[j]
            prov[q] = PROV_BACKGROUND_FILL


# ---------------------------------------------------------------------------- driver


@nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _clear(acc, wsum, zbuf, zoid, flags, acc_sky, wsky):
    for q in nb.prange(wsum.shape[0]):
        for k in range(3):
            acc[q, k] = 0.0
            acc_sky[q, k] = 0.0
        wsum[q] = 0.0
        wsky[q] = 0.0
        zbuf[q] = np.inf
        zoid[q] = -1
        flags[q] = 0


class _Buffers:
    """Scratch arrays reused between frames of the same size (allocation is a visible share of
    a 512 x 512 frame's budget)."""

    def __init__(self) -> None:
        self.key: tuple[int, ...] = ()

    def get(self, n_samples: int, npix: int) -> _Buffers:
        key = (n_samples, npix)
        if key != self.key:
            self.px = np.empty(n_samples, np.float32)
            self.py = np.empty(n_samples, np.float32)
            self.z = np.empty(n_samples, np.float32)
            self.cos = np.empty(n_samples, np.float32)
            self.rad = np.empty((n_samples, 3), np.float32)
            self.soid = np.empty(n_samples, np.int32)
            self.qok = np.empty(n_samples, np.uint8)
            self.state = np.empty(n_samples, np.uint8)
            self.acc = np.empty((npix, 3))
            self.wsum = np.empty(npix)
            self.zbuf = np.empty(npix)
            self.zoid = np.empty(npix, np.int32)
            self.flags = np.empty(npix, np.uint8)
            self.acc_sky = np.empty((npix, 3))
            self.wsky = np.empty(npix)
            self.key = key
        _clear(self.acc, self.wsum, self.zbuf, self.zoid, self.flags, self.acc_sky, self.wsky)
        return self


def _visible_faces(camera: CameraParams, eyes: np.ndarray, depth: np.ndarray, vb: np.ndarray, tg: np.ndarray,
                   sx: float, sy: float, margin: float) -> np.ndarray:
    """(nb, 6) bool: cube faces whose samples may reach the frame (conservative). A face's hit
    points lie in the pyramid of apex ``eye_b`` spanned by the face's corner rays out to its
    largest depth along the face axis; a face is culled when all five pyramid vertices are
    outside one plane of the camera frustum (widened by ``margin`` pixels). Faces with rays that
    leave the scene (points at infinity) and orthographic cameras are never culled."""
    nbases = vb.shape[0]
    on = np.ones((nbases, 6), dtype=np.bool_)
    if camera.kind != "perspective":
        return on
    right, up, fwd = camera.basis()
    ceye = np.asarray(camera.eye, np.float64)
    gx = sx * (1.0 + 2.0 * margin / camera.width) + 1e-9
    gy = sy * (1.0 + 2.0 * margin / camera.height) + 1e-9
    for i in range(nbases):
        dface = depth[vb[i], tg[i]]  # (6, R, R)
        dmax = dface.reshape(6, -1).max(axis=1)
        sky = (dface.reshape(6, -1) <= 0).any(axis=1)
        e = eyes[vb[i]]
        for f in range(6):
            if sky[f]:
                continue
            rgt, upv, fw = _BASIS[f, 0], _BASIS[f, 1], _BASIS[f, 2]
            verts = [e] + [e + (fw + a * rgt + b * upv) * float(dmax[f]) for a in (-1.0, 1.0) for b in (-1.0, 1.0)]
            q = np.asarray(verts) - ceye
            xc, yc, zc = q @ right, q @ up, q @ fwd
            planes = (-zc, xc - gx * zc, -xc - gx * zc, yc - gy * zc, -yc - gy * zc)  # > 0: outside
            if any(bool(np.all(pl > 0)) for pl in planes):
                on[i, f] = False
    return on


def reproject(camera: CameraParams, eyes: np.ndarray, depth: np.ndarray, object_id: np.ndarray,
              direct: np.ndarray, indirect: np.ndarray, views: list[int], geometry_time: list[int],
              direct_times: list[tuple[int, int, float]], indirect_times: list[tuple[int, int, float]],
              *, background: np.ndarray, fill: str = "both", depth_tol: float = 0.02,
              quad_depth_ratio: float = 1.6, max_footprint: float = 32.0,
              buffers: _Buffers | None = None) -> FrameResult:
    """Reproject bases ``views`` into ``camera`` (the core of ``WalkthroughRenderer.render``).

    eyes (V, 3) float64; depth (V, Td, 6, R, R) float32; object_id (V, Td, 6, R, R) int32;
    direct (V, Td, 6, R, R, 3) float32; indirect (V, Ti, 6, R, R, 3) float32.
    geometry_time[b]: direct time index giving base b's depth / ids; direct_times[b] =
    (i0, i1, a): radiance (1 - a) direct[:, i0] + a direct[:, i1], same for indirect_times.
    ``fill`` "trace" is handled by the caller (it needs the scene): here it acts as foreground.
    """
    if fill not in FILL_MODES:
        raise InvalidInputError(f"fill must be one of {', '.join(FILL_MODES)}; got {fill!r}")
    if not views:
        raise InvalidInputError("no base views to reproject")
    if not (0.0 <= depth_tol < 1.0):
        raise InvalidInputError(f"depth_tol must be in [0, 1), got {depth_tol}")
    t0 = time.perf_counter()
    res = int(depth.shape[-1])
    W, H = camera.width, camera.height
    right, up, fwd = camera.basis()
    ortho = camera.kind == "orthographic"
    if ortho:
        sy = 0.5 * camera.ortho_height
    else:
        sy = math.tan(math.radians(camera.fov_y_deg) * 0.5)
    sx = sy * W / H
    vb = np.asarray(views, np.int64)
    tg = np.asarray(geometry_time, np.int64)
    td0 = np.asarray([d[0] for d in direct_times], np.int64)
    td1 = np.asarray([d[1] for d in direct_times], np.int64)
    ad = np.asarray([d[2] for d in direct_times], np.float64)
    ti0 = np.asarray([d[0] for d in indirect_times], np.int64)
    ti1 = np.asarray([d[1] for d in indirect_times], np.int64)
    ai = np.asarray([d[2] for d in indirect_times], np.float64)
    n = len(views) * 6 * res * res
    buf = (buffers or _Buffers()).get(n, W * H)
    timings: dict[str, float] = {"setup": time.perf_counter() - t0}
    t1 = time.perf_counter()
    margin = float(max_footprint) + 1.0
    face_on = _visible_faces(camera, eyes, depth, vb, tg, sx, sy, margin)
    _project(vb, tg, td0, td1, ad, ti0, ti1, ai, direct, indirect, eyes, depth, object_id, _BASIS, res, ortho,
             np.asarray(camera.eye, np.float64), right, up, fwd, W, H, sx, sy, margin, face_on,
             buf.px, buf.py, buf.z, buf.cos, buf.rad, buf.state, buf.soid)
    quads = fill in ("foreground", "both", "trace")
    if quads:
        _quad_flags(vb, tg, res, depth, object_id, buf.state, float(quad_depth_ratio), buf.qok)
    live = np.flatnonzero(buf.state)
    timings["project"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    nbands = max(1, min(H, 2 * nb.get_num_threads()))
    _splat(live, res, W, H, buf.px, buf.py, buf.z, buf.cos, buf.rad, buf.state, buf.soid, buf.qok, quads,
           float(max_footprint), float(depth_tol), nbands, buf.acc, buf.wsum, buf.zbuf, buf.zoid, buf.flags,
           buf.acc_sky, buf.wsky)
    timings["splat"] = time.perf_counter() - t1
    t1 = time.perf_counter()
    out = np.empty((W * H, 3), np.float32)
    dep = np.empty(W * H, np.float32)
    ids = np.empty(W * H, np.int32)
    prov = np.empty(W * H, np.uint8)
    _resolve(buf.acc, buf.wsum, buf.zbuf, buf.zoid, buf.flags, buf.acc_sky, buf.wsky,
             np.asarray(background, np.float64), out, dep, ids,
             prov)
    if fill in ("background", "both"):
        # a hole whose whole row and column are empty is reached by a second pass
        holes = np.flatnonzero(prov == PROV_HOLE)
        for _ in range(8):
            if holes.size == 0:
                break
            if holes.size * 20 < prov.size:  # few holes: scan from each
                _background_fill_sparse(out, dep, ids, prov, W, H, holes)
            else:
                _background_fill(out, dep, ids, prov, W, H)
            left = np.flatnonzero(prov == PROV_HOLE)
            if left.size == holes.size:
                break
            holes = left
    timings["fill"] = time.perf_counter() - t1
    if not np.all(np.isfinite(out)):
        raise NonFiniteOutputError("reconstruction produced non-finite values")
    timings["total"] = time.perf_counter() - t0
    return FrameResult(out.reshape(H, W, 3), dep.reshape(H, W), ids.reshape(H, W), prov.reshape(H, W), timings,
                       list(views))
