"""Compositing a relit object into a background plate (the relighting paper's section 3.3;
docs/algorithms.md part B).

Inputs, all registered to the same fixed camera: the object dataset relit under the new lights
(``I_obj``: the object *and* its surroundings, e.g. the floor it stands on, with its shadows and
interreflections), the background dataset (same lights, object removed) relit under the same new
lights (``I_bg``), a background plate (the photograph or frame to composite into), the object
mask and an active region (the surroundings the object influences). Output per pixel:

- object pixels (``object_mask``): ``I_obj`` (the relit object itself);
- active-region pixels (not object): ``plate x R`` with ``R = I_obj / I_bg`` per channel: the
  object's shadow has R < 1 (darkens the plate), its interreflections R > 1 (brighten it);
- every other pixel: the plate, unchanged.

Guard where the background is near black (a 0/0 or x/0 ratio): per channel c,

    eps_c = max(eps x mean(I_bg[active, c]), eps_abs)
    R = clip((I_obj + eps_c) / (I_bg + eps_c), 0, max_ratio)

i.e. both images are lifted by a floor that is tiny next to the region's typical background
level (default 1e-3 of its mean: ordinary pixels change by < 0.1 %), so R -> 1 where both are
black (the plate is kept), R stays finite where only the background is black, and R is clamped to
``max_ratio`` (default 8) where the object would light a black background. Pixels where either
relit image has no data (outside the dataset's light coverage, or a singular light) keep the plate
(R = 1). The counts of guarded, clamped and no-data pixels are in the stats.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import binary_dilation

from engine.errors import InvalidInputError


def _image(name: str, a, shape=None) -> tuple[np.ndarray, np.ndarray | None]:
    """(image float32 (h, w, 3), no-data mask or None) from an array or a RelightResult."""
    nodata = None
    if hasattr(a, "image") and hasattr(a, "outside_mask"):
        nodata = np.asarray(a.outside_mask, bool) | np.asarray(a.singular_mask, bool)
        a = a.image
    try:
        img = np.asarray(a, dtype=np.float32)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name}: not a numeric image") from None
    if img.ndim != 3 or img.shape[2] != 3:
        raise InvalidInputError(f"{name}: expected an (h, w, 3) image, got shape {img.shape}")
    if shape is not None and img.shape[:2] != shape:
        raise InvalidInputError(f"{name}: size {img.shape[1]}x{img.shape[0]} differs from object_relit's "
                                f"{shape[1]}x{shape[0]}")
    if not np.all(np.isfinite(img)):
        raise InvalidInputError(f"{name}: contains NaN/Inf")
    return img, nodata


def _mask(name: str, m, shape) -> np.ndarray:
    a = np.asarray(m)
    if a.shape != shape:
        raise InvalidInputError(f"{name}: shape {a.shape} differs from the image size {shape}")
    return a.astype(bool)


def active_region_around(object_mask, margin_px: int) -> np.ndarray:
    """The object mask dilated by ``margin_px`` pixels (8-connected), minus the object."""
    m = np.asarray(object_mask, bool)
    if m.ndim != 2:
        raise InvalidInputError("object_mask: expected an (h, w) mask")
    if not (isinstance(margin_px, (int, np.integer)) and 0 <= margin_px <= 4096):
        raise InvalidInputError(f"margin_px must be an integer in [0, 4096], got {margin_px!r}")
    if margin_px == 0:
        return np.zeros_like(m)
    return binary_dilation(m, structure=np.ones((3, 3), bool), iterations=int(margin_px)) & ~m


def composite_ratio(object_relit, background_relit, active_region, *, eps: float = 1e-3, eps_abs: float = 1e-8,
                    max_ratio: float = 8.0) -> tuple[np.ndarray, dict]:
    """R (h, w, 3) float32 (1 outside the active region) and its stats; the guard is in the module
    docstring. ``object_relit`` / ``background_relit``: (h, w, 3) images or RelightResults."""
    if not (np.isfinite(eps) and eps > 0) or not (np.isfinite(eps_abs) and eps_abs > 0):
        raise InvalidInputError("eps and eps_abs must be finite and > 0")
    if not (np.isfinite(max_ratio) and max_ratio >= 1):
        raise InvalidInputError("max_ratio must be finite and >= 1")
    i_obj, nd_obj = _image("object_relit", object_relit)
    shape = i_obj.shape[:2]
    i_bg, nd_bg = _image("background_relit", background_relit, shape)
    act = _mask("active_region", active_region, shape)
    if nd_obj is not None:
        act_nodata = act & nd_obj
    else:
        act_nodata = np.zeros(shape, bool)
    if nd_bg is not None:
        act_nodata |= act & nd_bg
    use = act & ~act_nodata
    ratio = np.ones(shape + (3,), np.float32)
    stats: dict = dict(n_active=int(act.sum()), n_no_data=int(act_nodata.sum()), max_ratio=float(max_ratio))
    if not np.any(use):
        stats.update(eps=[float(eps_abs)] * 3, n_guarded=0, n_clamped=0, ratio_min=1.0, ratio_max=1.0,
                     ratio_mean=1.0, n_darkened=0, n_brightened=0)
        return ratio, stats
    o = i_obj[use].astype(np.float64)
    b = i_bg[use].astype(np.float64)
    e = np.maximum(eps * b.mean(axis=0), eps_abs)  # per channel
    r = (o + e) / (b + e)
    clamped = r > max_ratio
    r = np.clip(r, 0.0, max_ratio)
    ratio[use] = r.astype(np.float32)
    lum = r @ np.array([0.2126, 0.7152, 0.0722])
    stats.update(eps=[float(x) for x in e], n_guarded=int(np.any(b < e, axis=1).sum()),
                 n_clamped=int(np.any(clamped, axis=1).sum()), ratio_min=float(r.min()), ratio_max=float(r.max()),
                 ratio_mean=float(r.mean()), n_darkened=int((lum < 0.99).sum()), n_brightened=int((lum > 1.01).sum()))
    return ratio, stats


def composite(object_relit, background_relit, plate, object_mask, active_region, *, eps: float = 1e-3,
              eps_abs: float = 1e-8, max_ratio: float = 8.0) -> tuple[np.ndarray, dict]:
    """The composite (h, w, 3) float32 and its stats (counts, ratio range, the eps used).

    object_relit: the object dataset relit (image or RelightResult); background_relit: the
    background dataset (same lights, object removed) relit under the same lights; plate: the
    background image to composite into; object_mask, active_region: (h, w) bool (an object pixel
    is never treated as active). Rules and the near-black guard: module docstring.
    """
    i_obj, nd_obj = _image("object_relit", object_relit)
    shape = i_obj.shape[:2]
    pl, _ = _image("plate", plate, shape)
    om = _mask("object_mask", object_mask, shape)
    act = _mask("active_region", active_region, shape) & ~om
    ratio, stats = composite_ratio(object_relit, background_relit, act, eps=eps, eps_abs=eps_abs,
                                   max_ratio=max_ratio)
    out = pl.copy()
    out[act] = pl[act] * ratio[act]
    out[om] = i_obj[om]
    stats.update(n_object=int(om.sum()), n_unchanged=int((~om & ~act).sum()),
                 n_object_no_data=int((om & nd_obj).sum()) if nd_obj is not None else 0)
    return out, stats


__all__ = ["active_region_around", "composite", "composite_ratio"]
