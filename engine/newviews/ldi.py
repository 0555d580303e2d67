"""Layered depth images (LDI) with a parallel projection, stored flat (CSR).

Frame: pixel (i, j) (i along ``u``, j along ``v``) has its centre at
``origin + (i + 0.5) h u + (j + 0.5) h v`` on the reference plane; its ray travels
along ``w = u x v``. Pixel index ``k = j * nu + i``.

Storage: ``offsets`` (nu*nv + 1,) int64, pixel k owns samples ``offsets[k]:offsets[k+1]``
sorted front to back. ``depth`` is float64, the distance along ``w`` from the reference
plane (docs/hard-cases.md #6: we keep float64 instead of a float32 offset from a per-LDI reference,
8 bytes per sample buys exact layer separation at any placement, e.g. 1e-3 apart at 1e4).
``prim`` int32 triangle id, ``u``, ``v`` float32 barycentrics (Embree computes them in
float32; the sample point is rebuilt in float64 from the frame and the depth).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from engine.errors import InvalidInputError
from engine.raycast import RayCaster, all_hits

# bytes per sample in an LDI (depth 8 + prim 4 + u 4 + v 4)
LDI_SAMPLE_BYTES = 20
DEFAULT_MAX_BYTES = 1 << 31  # 2 GiB worst case per LDI unless the caller says otherwise
MAX_LAYERS_LIMIT = 4096


@dataclass(frozen=True)
class LDIFrame:
    """Parallel-projection frame: reference-plane origin (float64), unit axes u, v and
    projection direction w (right-handed, w = u x v), pixel size h, resolution (nu, nv)."""

    origin: np.ndarray
    u: np.ndarray
    v: np.ndarray
    w: np.ndarray
    h: float
    nu: int
    nv: int

    def __post_init__(self) -> None:
        for name in ("origin", "u", "v", "w"):
            a = np.asarray(getattr(self, name), dtype=np.float64)
            if a.shape != (3,) or not np.all(np.isfinite(a)):
                raise InvalidInputError(f"LDIFrame.{name} must be 3 finite numbers")
            object.__setattr__(self, name, a)
        if not (np.isfinite(self.h) and self.h > 0):
            raise InvalidInputError("LDIFrame.h (pixel size) must be > 0")
        if self.nu < 1 or self.nv < 1:
            raise InvalidInputError("LDIFrame resolution must be >= 1 x 1")
        if abs(np.dot(np.cross(self.u, self.v), self.w) - 1.0) > 1e-9:
            raise InvalidInputError("LDIFrame axes must be orthonormal and right-handed (w = u x v)")

    @property
    def n_pixels(self) -> int:
        return self.nu * self.nv

    def pixel_origins(self) -> np.ndarray:
        """(nu*nv, 3) float64 ray origins (pixel centres on the reference plane), row-major in v."""
        j, i = np.mgrid[0:self.nv, 0:self.nu]
        a = (i.ravel() + 0.5) * self.h
        b = (j.ravel() + 0.5) * self.h
        return self.origin[None] + a[:, None] * self.u[None] + b[:, None] * self.v[None]

    def to_dict(self) -> dict:
        return {"origin": self.origin.tolist(), "u": self.u.tolist(), "v": self.v.tolist(),
                "w": self.w.tolist(), "h": self.h, "nu": self.nu, "nv": self.nv}


@dataclass(frozen=True)
class LDI:
    """A layered depth image: frame + CSR samples (see module docstring)."""

    frame: LDIFrame
    offsets: np.ndarray
    depth: np.ndarray
    prim: np.ndarray
    u: np.ndarray
    v: np.ndarray
    truncated: np.ndarray  # (nu*nv,) bool: pixels whose ray had more than max_layers crossings

    @property
    def n_samples(self) -> int:
        return int(self.depth.shape[0])

    def counts(self) -> np.ndarray:
        return np.diff(self.offsets)

    @property
    def n_truncated(self) -> int:
        return int(self.truncated.sum())

    def layer(self, i: int) -> np.ndarray:
        """(nv, nu) depth of layer i (the i-th hit of each pixel), NaN where the pixel has fewer."""
        c = self.counts()
        out = np.full(self.frame.n_pixels, np.nan)
        has = c > i
        out[has] = self.depth[self.offsets[:-1][has] + i]
        return out.reshape(self.frame.nv, self.frame.nu)

    def sample_pixels(self) -> np.ndarray:
        """(n_samples,) int64 pixel index of every sample."""
        return np.repeat(np.arange(self.frame.n_pixels, dtype=np.int64), self.counts())

    def points(self) -> np.ndarray:
        """(n_samples, 3) float64 world positions of the samples."""
        f = self.frame
        k = self.sample_pixels()
        a = (k % f.nu + 0.5) * f.h
        b = (k // f.nu + 0.5) * f.h
        return f.origin[None] + a[:, None] * f.u[None] + b[:, None] * f.v[None] + self.depth[:, None] * f.w[None]

    @property
    def nbytes(self) -> int:
        return int(self.offsets.nbytes + self.depth.nbytes + self.prim.nbytes + self.u.nbytes + self.v.nbytes
                   + self.truncated.nbytes)

    def to_arrays(self, prefix: str = "") -> dict[str, np.ndarray]:
        """Plain arrays (frame + CSR) for storage, e.g. ``np.savez``; no pickled objects."""
        f = self.frame
        return {prefix + "frame_origin": f.origin, prefix + "frame_u": f.u, prefix + "frame_v": f.v,
                prefix + "frame_w": f.w, prefix + "frame_h": np.float64(f.h),
                prefix + "frame_res": np.array([f.nu, f.nv], np.int64),
                prefix + "offsets": self.offsets, prefix + "depth": self.depth, prefix + "prim": self.prim,
                prefix + "u": self.u, prefix + "v": self.v, prefix + "truncated": self.truncated}

    @classmethod
    def from_arrays(cls, d, prefix: str = "") -> LDI:
        """Inverse of ``to_arrays``; checks shapes and CSR consistency (InvalidInputError)."""
        try:
            nu, nv = (int(x) for x in np.asarray(d[prefix + "frame_res"]).reshape(2))
            frame = LDIFrame(origin=np.asarray(d[prefix + "frame_origin"]), u=np.asarray(d[prefix + "frame_u"]),
                             v=np.asarray(d[prefix + "frame_v"]), w=np.asarray(d[prefix + "frame_w"]),
                             h=float(np.asarray(d[prefix + "frame_h"])), nu=nu, nv=nv)
            offsets = np.ascontiguousarray(d[prefix + "offsets"], dtype=np.int64)
            depth = np.ascontiguousarray(d[prefix + "depth"], dtype=np.float64)
            prim = np.ascontiguousarray(d[prefix + "prim"], dtype=np.int32)
            u = np.ascontiguousarray(d[prefix + "u"], dtype=np.float32)
            v = np.ascontiguousarray(d[prefix + "v"], dtype=np.float32)
            truncated = np.ascontiguousarray(d[prefix + "truncated"], dtype=np.bool_)
        except KeyError as e:
            raise InvalidInputError(f"stored LDI lacks array {e.args[0]!r}") from None
        n = depth.shape[0]
        if (offsets.shape != (frame.n_pixels + 1,) or offsets[0] != 0 or offsets[-1] != n
                or np.any(np.diff(offsets) < 0) or prim.shape != (n,) or u.shape != (n,) or v.shape != (n,)
                or truncated.shape != (frame.n_pixels,)):
            raise InvalidInputError("stored LDI arrays are inconsistent (shapes or offsets)")
        return cls(frame=frame, offsets=offsets, depth=depth, prim=prim, u=u, v=v, truncated=truncated)


def estimate_ldi_bytes(n_pixels: int, max_layers: int, sample_bytes: int = LDI_SAMPLE_BYTES) -> int:
    """Worst-case bytes of an LDI (every pixel full to max_layers), including the per-pixel arrays.

    ``all_hits`` holds about the same again while casting, so peak use is about twice this.
    """
    return int(n_pixels) * (9 + int(max_layers) * int(sample_bytes)) + 8


def build_ldi(caster: RayCaster, frame: LDIFrame, max_layers: int = 64,
              max_bytes: int = DEFAULT_MAX_BYTES) -> LDI:
    """Cast one ray per pixel centre along ``w`` and keep every surface crossing (front and
    back faces). The frame's reference plane must lie in front of the scene (depth >= 0).

    Refuses (InvalidInputError) when the worst-case size exceeds ``max_bytes``; pixels with
    more than ``max_layers`` crossings keep their nearest ``max_layers`` and are flagged.
    """
    if not (1 <= max_layers <= MAX_LAYERS_LIMIT):
        raise InvalidInputError(f"max_layers must be in [1, {MAX_LAYERS_LIMIT}], got {max_layers}")
    est = estimate_ldi_bytes(frame.n_pixels, max_layers)
    if est > max_bytes:
        raise InvalidInputError(f"LDI of {frame.nu}x{frame.nv} pixels x {max_layers} layers needs up to "
                                f"{est / 2**20:.1f} MiB, over the limit of {max_bytes / 2**20:.1f} MiB; "
                                "lower the resolution or max_layers")
    o = frame.pixel_origins()
    d = np.broadcast_to(frame.w, o.shape)
    ah = all_hits(caster, o, d, max_hits=max_layers)
    return LDI(frame=frame, offsets=ah.offsets, depth=np.ascontiguousarray(ah.t, dtype=np.float64),
               prim=np.ascontiguousarray(ah.prim, dtype=np.int32),
               u=np.ascontiguousarray(ah.u, dtype=np.float32), v=np.ascontiguousarray(ah.v, dtype=np.float32),
               truncated=np.ascontiguousarray(ah.truncated))


# axis a: (u, v) so that u x v = +e_a
_AXIS_UV = {0: (1, 2), 1: (2, 0), 2: (0, 1)}


def axis_frame(lo: np.ndarray, hi: np.ndarray, axis: int, h: float, pad_pixels: float = 1.0) -> LDIFrame:
    """Frame looking along +e_axis covering the box [lo, hi] padded by ``pad_pixels`` pixels
    on each side; the reference plane sits ``pad_pixels * h`` in front of the box."""
    if axis not in (0, 1, 2):
        raise InvalidInputError(f"axis must be 0, 1 or 2, got {axis!r}")
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    ia, ib = _AXIS_UV[axis]
    eye = np.eye(3)
    pad = pad_pixels * h
    origin = np.zeros(3)
    origin[ia] = lo[ia] - pad
    origin[ib] = lo[ib] - pad
    origin[axis] = lo[axis] - pad
    nu = max(1, int(np.ceil((hi[ia] - lo[ia] + 2 * pad) / h)))
    nv = max(1, int(np.ceil((hi[ib] - lo[ib] + 2 * pad) / h)))
    return LDIFrame(origin=origin, u=eye[ia], v=eye[ib], w=eye[axis], h=float(h), nu=nu, nv=nv)
