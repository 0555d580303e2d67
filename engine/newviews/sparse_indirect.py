"""Indirect light traced on a coarser lattice of LDC samples and interpolated in between.

The indirect light reaching a diffuse surface varies slowly over it: it is an integral over the
whole hemisphere, so an occluder changes it over distances of the order of its own distance,
where direct light from a small source changes across a sharp shadow border. So the LDC can keep
its full resolution for the direct light, whose shadow borders need it, and path-trace the
indirect light only at every ``stride``-th LDI pixel in each direction (``IndirectParams.stride``):
a quarter of the samples at stride 2. Every other sample takes the bilinear interpolation of the
traced samples at the lattice pixels around it that lie on the same surface (same object and
material, geometric normals within ``SAME_SURFACE_COS``, within half an LDI pixel of its tangent plane;
the weights of missing ones are left out). A sample with no such neighbour (a thin object, a
border, a small part seen by one pixel) is traced itself, so no sample is left without indirect
light.

``traced_samples`` says which samples of an axis are traced; it depends on the axis alone, so
every job that traces a run of samples agrees on it. ``interpolate_untraced`` fills the others
once the traced ones are known.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from engine.newviews.ldi import LDI

SAME_SURFACE_COS = 0.9
"""Two samples of one object whose geometric normals are closer than this (cosine) and whose
points are within half an LDI pixel of one tangent plane are on the same surface: the neighbours
of this interpolation and of the view renderer's bilinear diffuse reconstruction."""


@nb.njit(cache=True, nogil=True)
def _lattice_neighbours(j, stride, nu, nv, pix, offsets, depth, gn, obj, mat, origin, u, v, w, h, idx, wgt):
    """The traced samples sample ``j`` interpolates between and their bilinear weights, written to
    ``idx`` / ``wgt`` (4 slots); returns how many. A sample on the lattice returns itself."""
    k = np.int64(pix[j])
    ci, cj = k % nu, k // nu
    rx, ry = ci % stride, cj % stride
    if rx == 0 and ry == 0:
        idx[0] = j
        wgt[0] = 1.0
        return 1
    g0, g1, g2 = np.float64(gn[j, 0]), np.float64(gn[j, 1]), np.float64(gn[j, 2])
    a, b, d = (ci + 0.5) * h, (cj + 0.5) * h, depth[j]
    p0 = origin[0] + a * u[0] + b * v[0] + d * w[0]
    p1 = origin[1] + a * u[1] + b * v[1] + d * w[1]
    p2 = origin[2] + a * u[2] + b * v[2] + d * w[2]
    tol = 0.5 * h
    fx, fy = rx / stride, ry / stride
    # on the lattice along an axis: one neighbour there (weight 1); off it: the two around
    n_x, n_y = 1 if rx == 0 else 2, 1 if ry == 0 else 2
    m = 0
    for cy in range(n_y):
        yj = cj - ry + cy * stride
        wy = 1.0 if n_y == 1 else (fy if cy == 1 else 1.0 - fy)
        if yj < 0 or yj >= nv:
            continue
        for cx in range(n_x):
            xi = ci - rx + cx * stride
            wx = 1.0 if n_x == 1 else (fx if cx == 1 else 1.0 - fx)
            if xi < 0 or xi >= nu:
                continue
            kk = yj * nu + xi
            aa, bb = (xi + 0.5) * h, (yj + 0.5) * h
            best = -1
            best_d = tol
            for q in range(offsets[kk], offsets[kk + 1]):
                if obj[q] != obj[j] or mat[q] != mat[j]:
                    continue
                if gn[q, 0] * g0 + gn[q, 1] * g1 + gn[q, 2] * g2 < SAME_SURFACE_COS:
                    continue
                dq = depth[q]
                e0 = origin[0] + aa * u[0] + bb * v[0] + dq * w[0] - p0
                e1 = origin[1] + aa * u[1] + bb * v[1] + dq * w[1] - p1
                e2 = origin[2] + aa * u[2] + bb * v[2] + dq * w[2] - p2
                dist = abs(e0 * g0 + e1 * g1 + e2 * g2)
                if dist < best_d:
                    best, best_d = q, dist
            if best >= 0:
                idx[m] = best
                wgt[m] = wx * wy
                m += 1
    return m


@nb.njit(cache=True, nogil=True)
def _traced_kernel(stride, nu, nv, pix, offsets, depth, gn, obj, mat, origin, u, v, w, h):
    n = pix.shape[0]
    out = np.zeros(n, np.bool_)
    idx = np.empty(4, np.int64)
    wgt = np.empty(4, np.float64)
    for j in range(n):
        m = _lattice_neighbours(j, stride, nu, nv, pix, offsets, depth, gn, obj, mat, origin, u, v, w, h, idx, wgt)
        out[j] = m == 0 or (m == 1 and idx[0] == j)
    return out


@nb.njit(cache=True, nogil=True)
def _interpolate_kernel(stride, nu, nv, pix, offsets, depth, gn, obj, mat, origin, u, v, w, h, traced, radiance):
    n = pix.shape[0]
    idx = np.empty(4, np.int64)
    wgt = np.empty(4, np.float64)
    for j in range(n):
        if traced[j]:
            continue
        m = _lattice_neighbours(j, stride, nu, nv, pix, offsets, depth, gn, obj, mat, origin, u, v, w, h, idx, wgt)
        wsum = 0.0
        for t in range(m):
            wsum += wgt[t]
        for s in range(2):
            for c in range(3):
                acc = 0.0
                for t in range(m):
                    acc += wgt[t] * radiance[idx[t], s, c]
                radiance[j, s, c] = acc / wsum


def _axis_args(ldi: LDI, geo_normal: np.ndarray, obj: np.ndarray, mat: np.ndarray) -> tuple:
    f = ldi.frame
    c = np.ascontiguousarray
    return (int(f.nu), int(f.nv), ldi.sample_pixels().astype(np.int64), c(ldi.offsets, np.int64),
            c(ldi.depth, np.float64), c(geo_normal, np.float32), c(obj, np.int32), c(mat, np.int32),
            c(f.origin, np.float64), c(f.u, np.float64), c(f.v, np.float64), c(f.w, np.float64), float(f.h))


def traced_samples(ldi: LDI, geo_normal: np.ndarray, obj: np.ndarray, mat: np.ndarray, stride: int) -> np.ndarray:
    """(n,) bool: the samples of an LDC axis whose indirect light is path-traced at ``stride``
    (module docstring); every sample at stride 1."""
    if stride == 1:
        return np.ones(ldi.n_samples, np.bool_)
    return _traced_kernel(int(stride), *_axis_args(ldi, geo_normal, obj, mat))


def interpolate_untraced(ldi: LDI, geo_normal: np.ndarray, obj: np.ndarray, mat: np.ndarray, stride: int,
                         traced: np.ndarray, radiance: np.ndarray) -> np.ndarray:
    """``radiance`` (n, 2, 3) of an axis's samples, known where ``traced``, with every other sample
    set to the interpolation of its traced neighbours (a new array)."""
    out = np.array(radiance, dtype=np.float32, copy=True)
    if stride > 1:
        _interpolate_kernel(int(stride), *_axis_args(ldi, geo_normal, obj, mat), np.ascontiguousarray(traced), out)
    return out
