"""Error metrics between a test image and a reference, as ``docs/algorithms.md`` defines them
("Shared conventions", error metric).

``LRMS = RMS(Y_test - Y_ref) / mean(Y_ref)`` on Rec.709 luminance
``Y = 0.2126 R + 0.7152 G + 0.0722 B``, over the pixels covered in the reference (``mask``), plus
RMSE per channel, PSNR of the tone-mapped images and the fraction of pixels whose luminance error
exceeds 5 % of the mean reference luminance.

Inputs are linear images ``(h, w)`` or ``(h, w, c)`` with ``c`` in 1, 3, 4, any float or integer
dtype, finite; ``test`` and ``ref`` must have the same shape. For ``c == 4`` the fourth channel is
alpha: luminance and PSNR use the colour channels only, ``rmse_per_channel`` reports all four.
``mask`` is an optional ``(h, w)`` bool array, True where the reference covers the pixel; it must
select at least one pixel. Everything is accumulated in float64. Bad input raises
:class:`~engine.errors.InvalidInputError`.

Zero or negative reference luminance (decisions, since the formula divides by ``mean(Y_ref)``):

- ``mean(Y_ref) == 0`` (a black reference): :func:`lrms` is ``0.0`` when the luminances are
  identical and ``inf`` otherwise; :func:`fraction_over` counts the pixels with any non-zero
  luminance error (the threshold ``threshold * 0`` is 0); :func:`error_heatmap` without a
  ``scale`` shows differing pixels at the top of the colour map and equal pixels at the bottom.
- ``mean(Y_ref) < 0`` is not radiance: :class:`InvalidInputError`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from engine.errors import InvalidInputError
from engine.imageio import srgb_decode, tonemap_srgb

__all__ = [
    "REC709_WEIGHTS",
    "ErrorReport",
    "compare",
    "error_heatmap",
    "error_heatmap_display",
    "fraction_over",
    "lrms",
    "luminance",
    "psnr_tonemapped",
    "rmse_per_channel",
]

REC709_WEIGHTS = (0.2126, 0.7152, 0.0722)

# Viridis sampled at 17 evenly spaced points (perceptually ordered, readable in grey scale and by
# colour-blind viewers); linear interpolation between them is visually indistinguishable from the
# 256-entry table and avoids a matplotlib dependency.
_VIRIDIS = np.array(
    [
        (0.2670, 0.0049, 0.3294),
        (0.2823, 0.0950, 0.4173),
        (0.2788, 0.1755, 0.4834),
        (0.2590, 0.2515, 0.5247),
        (0.2297, 0.3224, 0.5457),
        (0.1994, 0.3876, 0.5546),
        (0.1727, 0.4488, 0.5579),
        (0.1490, 0.5081, 0.5573),
        (0.1276, 0.5669, 0.5506),
        (0.1206, 0.6258, 0.5335),
        (0.1579, 0.6838, 0.5017),
        (0.2461, 0.7389, 0.4520),
        (0.3692, 0.7889, 0.3829),
        (0.5160, 0.8312, 0.2943),
        (0.6785, 0.8637, 0.1895),
        (0.8456, 0.8873, 0.0997),
        (0.9932, 0.9062, 0.1439),
    ],
    dtype=np.float64,
)


# ----------------------------------------------------------------------------------------------
# Validation


def _as_image(img: Any, name: str) -> np.ndarray:
    """Validated float64 ``(h, w, c)`` view of an image."""
    arr = np.asarray(img)
    if arr.dtype.kind not in "fiu":
        raise InvalidInputError(f"{name} must be a numeric array, got dtype {arr.dtype}")
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3 or arr.shape[2] not in (1, 3, 4) or arr.shape[0] < 1 or arr.shape[1] < 1:
        raise InvalidInputError(
            f"{name} must be (h, w) or (h, w, c) with c in 1, 3, 4 and h, w >= 1; got shape {np.shape(img)}"
        )
    arr = arr.astype(np.float64, copy=False)
    n_bad = int(arr.size - np.count_nonzero(np.isfinite(arr)))
    if n_bad:
        raise InvalidInputError(f"{name} holds {n_bad} non-finite value(s) (NaN/Inf)")
    return arr


def _prepare(test: Any, ref: Any, mask: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validated ``(test, ref, mask)``: float64 ``(h, w, c)`` pair and ``(h, w)`` bool mask."""
    t = _as_image(test, "test")
    r = _as_image(ref, "ref")
    if t.shape != r.shape:
        raise InvalidInputError(
            f"test and ref must have the same shape, got {np.shape(test)} and {np.shape(ref)}"
        )
    h, w = r.shape[:2]
    if mask is None:
        m = np.ones((h, w), dtype=bool)
    else:
        m = np.asarray(mask)
        if m.dtype != np.bool_:
            raise InvalidInputError(f"mask must be a bool array, got dtype {m.dtype}")
        if m.shape != (h, w):
            raise InvalidInputError(f"mask must have shape {(h, w)}, got {m.shape}")
    if not m.any():
        raise InvalidInputError("mask selects no pixels; the metric is undefined")
    return t, r, m


def _luminance64(img: np.ndarray) -> np.ndarray:
    """(h, w, c) float64 -> (h, w) float64 luminance; c == 1 is the value itself."""
    if img.shape[2] == 1:
        return img[..., 0]
    wr, wg, wb = REC709_WEIGHTS
    return wr * img[..., 0] + wg * img[..., 1] + wb * img[..., 2]


def _mean_ref_luminance(y_ref: np.ndarray) -> float:
    mean = float(np.mean(y_ref))
    if mean < 0.0:
        raise InvalidInputError(f"mean reference luminance is negative ({mean:g}); not radiance")
    return mean


def _check_threshold(value: float, name: str, *, positive: bool) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise InvalidInputError(f"{name} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v) or v < 0.0 or (positive and v == 0.0):
        raise InvalidInputError(f"{name} must be finite and {'> 0' if positive else '>= 0'}, got {value}")
    return v


# ----------------------------------------------------------------------------------------------
# Metrics


def luminance(img: Any) -> np.ndarray:
    """Rec.709 luminance ``0.2126 R + 0.7152 G + 0.0722 B`` as ``(h, w) float64``.

    ``(h, w)`` and ``(h, w, 1)`` inputs are luminance already and come back unchanged (as
    float64); for ``(h, w, 4)`` the alpha channel is ignored.
    """
    return _luminance64(_as_image(img, "img"))


def lrms(test: Any, ref: Any, mask: Any = None) -> float:
    """Relative RMS luminance error ``RMS(Y_test - Y_ref) / mean(Y_ref)`` over ``mask``.

    Both the RMS and the mean are taken over the masked pixels. A black reference
    (``mean(Y_ref) == 0``) gives 0.0 for identical luminance and ``inf`` otherwise.
    """
    t, r, m = _prepare(test, ref, mask)
    return _lrms(_luminance64(t)[m], _luminance64(r)[m])


def _lrms(y_test: np.ndarray, y_ref: np.ndarray) -> float:
    mean = _mean_ref_luminance(y_ref)
    rms = math.sqrt(float(np.mean(np.square(y_test - y_ref))))
    if mean == 0.0:
        return 0.0 if rms == 0.0 else math.inf
    return rms / mean


def rmse_per_channel(test: Any, ref: Any, mask: Any = None) -> np.ndarray:
    """Root-mean-square error of each channel over ``mask``: ``(c,) float64`` (c = 1 for 2-D input)."""
    t, r, m = _prepare(test, ref, mask)
    return _rmse(t[m], r[m])


def _rmse(t: np.ndarray, r: np.ndarray) -> np.ndarray:
    return np.sqrt(np.mean(np.square(t - r), axis=0))


def psnr_tonemapped(test: Any, ref: Any, *, exposure_stops: float = 0.0, mask: Any = None) -> float:
    """PSNR in dB of the tone-mapped images, peak 1.0: ``10 log10(1 / MSE)``.

    Both images go through the PNG display transform of :func:`engine.imageio.write_image`
    (``srgb_encode(clip(x * 2**exposure_stops, 0, 1))``, without 8-bit quantisation); the MSE is
    over the masked pixels and the colour channels (alpha excluded). Identical tone-mapped images
    give ``inf``.
    """
    t, r, m = _prepare(test, ref, mask)
    return _psnr(_colour(t)[m], _colour(r)[m], exposure_stops)


def _colour(img: np.ndarray) -> np.ndarray:
    return img[..., :3] if img.shape[2] == 4 else img


def _psnr(t: np.ndarray, r: np.ndarray, exposure_stops: float) -> float:
    mse = float(np.mean(np.square(tonemap_srgb(t, exposure_stops) - tonemap_srgb(r, exposure_stops))))
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


def fraction_over(test: Any, ref: Any, threshold: float = 0.05, mask: Any = None) -> float:
    """Fraction of masked pixels with ``|Y_test - Y_ref| > threshold * mean(Y_ref)``.

    ``mean`` is over the masked reference pixels; the comparison is strict. With a black
    reference every pixel with a non-zero luminance error counts.
    """
    thr = _check_threshold(threshold, "threshold", positive=False)
    t, r, m = _prepare(test, ref, mask)
    return _fraction_over(_luminance64(t)[m], _luminance64(r)[m], thr)


def _fraction_over(y_test: np.ndarray, y_ref: np.ndarray, threshold: float) -> float:
    limit = threshold * _mean_ref_luminance(y_ref)
    return float(np.count_nonzero(np.abs(y_test - y_ref) > limit)) / y_ref.size


def error_heatmap(test: Any, ref: Any, *, scale: float | None = None, mask: Any = None) -> np.ndarray:
    """False-colour map of the luminance error, ``(h, w, 3) float32`` in [0, 1].

    Per pixel ``v = |Y_test - Y_ref| / s`` with ``s = scale`` if given, else ``mean(Y_ref)``
    over the mask (so ``v`` is the relative error LRMS is built from); ``v`` is clipped to [0, 1]
    and mapped through viridis (dark violet = 0, yellow >= 1). Pixels outside ``mask`` are black
    (0, 0, 0), which viridis never produces.

    The palette is defined on display (sRGB-encoded) values; the returned array is its linear
    decoding, like every image in the engine, so ``write_image("err.png", heatmap)`` (exposure
    0) stores exactly the viridis colours. :func:`error_heatmap_display` gives the display values.
    """
    heat: np.ndarray = srgb_decode(error_heatmap_display(test, ref, scale=scale, mask=mask)).astype(np.float32)
    return heat


def error_heatmap_display(test: Any, ref: Any, *, scale: float | None = None, mask: Any = None) -> np.ndarray:
    """:func:`error_heatmap` as display (sRGB-encoded) values, ``(h, w, 3) float64`` in [0, 1]: the
    viridis colours themselves, for a caller that encodes them directly (``rint(255 x)`` is the
    8-bit colour)."""
    s = None if scale is None else _check_threshold(scale, "scale", positive=True)
    t, r, m = _prepare(test, ref, mask)
    y_t, y_r = _luminance64(t), _luminance64(r)
    diff = np.abs(y_t - y_r)
    if s is None:
        s = _mean_ref_luminance(y_r[m])
    v = (diff > 0).astype(np.float64) if s == 0.0 else np.clip(diff / s, 0.0, 1.0)
    pos = v * (len(_VIRIDIS) - 1)
    lo = np.minimum(np.floor(pos).astype(np.intp), len(_VIRIDIS) - 2)
    frac = (pos - lo)[..., None]
    rgb: np.ndarray = _VIRIDIS[lo] * (1.0 - frac) + _VIRIDIS[lo + 1] * frac
    rgb[~m] = 0.0
    return rgb


# ----------------------------------------------------------------------------------------------
# Report


@dataclass(frozen=True)
class ErrorReport:
    """All error numbers for one test/reference pair.

    Fields: ``lrms`` (may be ``inf`` for a black reference), ``rmse`` (one per channel),
    ``psnr`` in dB (``inf`` for identical tone-mapped images), ``fraction_over_5pct`` and
    ``n_pixels`` (pixels inside the mask).
    """

    lrms: float
    rmse: tuple[float, ...]
    psnr: float
    fraction_over_5pct: float
    n_pixels: int

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe dict: infinite values become the string ``"inf"``.

        ``json.dumps`` would otherwise write the non-standard token ``Infinity``; pydantic and
        ``float("inf")`` both parse ``"inf"`` back. NaN cannot occur (inputs are validated).
        """

        def safe(x: float) -> float | str:
            return x if math.isfinite(x) else ("inf" if x > 0 else "-inf")

        return {
            "lrms": safe(self.lrms),
            "rmse": [safe(x) for x in self.rmse],
            "psnr": safe(self.psnr),
            "fraction_over_5pct": self.fraction_over_5pct,
            "n_pixels": self.n_pixels,
        }


def compare(test: Any, ref: Any, mask: Any = None, *, exposure_stops: float = 0.0) -> ErrorReport:
    """Every metric of this module in one pass (inputs validated once)."""
    t, r, m = _prepare(test, ref, mask)
    y_t, y_r = _luminance64(t)[m], _luminance64(r)[m]
    return ErrorReport(
        lrms=_lrms(y_t, y_r),
        rmse=tuple(float(x) for x in _rmse(t[m], r[m])),
        psnr=_psnr(_colour(t)[m], _colour(r)[m], exposure_stops),
        fraction_over_5pct=_fraction_over(y_t, y_r, 0.05),
        n_pixels=int(np.count_nonzero(m)),
    )
