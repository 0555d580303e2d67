"""Image file I/O for the engine, through OpenImageIO only.

In memory an image is linear radiance: ``(h, w, c) float32`` with ``c`` in 1, 3, 4 (grey, RGB,
RGBA with *associated* / premultiplied alpha, the EXR convention). Files are either

- scene-referred, stored linear: ``.exr`` (float or half, lossless compression: ZIP by default,
  ``compression=`` picks ``zips``, ``rle``, ``piz`` or ``none``), ``.hdr``
  (Radiance RGBE, ~1 % precision, RGB only, no negatives) and ``.tif``/``.tiff`` with float or
  half samples;
- display-referred, stored sRGB-encoded after an explicit exposure: ``.png`` (8 or 16 bit),
  ``.jpg``/``.jpeg`` (8 bit) and ``.tif``/``.tiff`` with ``uint16`` samples. Encoding is
  ``srgb_encode(clip(x * 2**exposure_stops, 0, 1))`` rounded to the integer grid; alpha is stored
  unassociated (straight) and linear, as PNG requires. ``read_image`` undoes the encoding (not the
  exposure or the clipping, which are lossy by design).

Rules (``docs/algorithms.md`` "Shared conventions", docs/hard-cases.md #9, #13, #16):

- NaN/Inf are never written (:class:`NonFiniteOutputError`) and never returned
  (:class:`ImageFormatError`).
- Half precision never overflows silently: finite values with ``|x| > 65504`` raise
  :class:`InvalidInputError` (use ``pixel_type="float"``). Underflow is *not* an error: half has
  no values below its smallest subnormal ``2**-24 ~ 5.96e-8``, so e.g. ``1e-8`` is stored as 0
  and ``1e-6`` keeps about 4 significant bits. Keep float (the default) where that matters.
- The resolution a file declares is checked against ``max_pixels`` from the header, before a
  single pixel is read or allocated, so a malicious header costs nothing.
- Every write is atomic (temporary file in the same directory, fsync, ``os.replace``): a reader
  never sees a half-written image and a crash leaves the old file intact.
- Output is byte-deterministic: the ``DateTime`` stamp OpenImageIO would add is suppressed, so
  the same pixels, metadata and compression give the same file (useful for content-addressed caches).
- :func:`encode_image` returns the bytes :func:`write_image` would write (same checks, same bytes),
  for callers that ship them elsewhere (an object store): it encodes in a RAM-backed scratch file
  when there is one and skips the fsyncs, since no file is kept. :func:`decode_image` reads such
  bytes back like :func:`read_image`.
- No numba at import: the API process reads images and computes metrics with this module. The
  compiled loop of the 8-bit encode (``engine/_srgb8_kernel.py``) is imported on first use.
- 8-bit display encoding goes through exact code-value thresholds (one table look-up and one
  comparison per sample), bit-identical to ``rint(tonemap_srgb(x) * 255)`` in float64.

Metadata: callers put what is needed to reproduce an image in ``metadata`` -- the camera
(``{"camera": {...}}``), the scene hash, the technique and its render parameters, the exposure
used for a PNG. Each entry is stored as the header attribute ``ibr:<key>``; ``str`` values
verbatim, every other value (int, float, bool, None, dict, list) as canonical JSON
(``sort_keys=True``, separators ``(",", ":")``, ASCII), so numbers survive exactly (an EXR float
attribute would keep only 32 bits). The attribute ``ibr:_json_keys`` lists the JSON-encoded keys
so they decode back to the same Python types. Keys are 1-64 characters from ``[A-Za-z0-9_.-]``,
not starting with ``_``. TIFF and JPEG cannot hold arbitrary named attributes, so there the whole
dict goes into ``ImageDescription`` as canonical JSON ``{"ibr": {...}}``; RGBE (``.hdr``) cannot
store metadata at all and refuses it rather than dropping it.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import secrets
import tempfile
import threading
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import OpenImageIO as oiio

from engine.errors import ImageFormatError, InvalidInputError, NonFiniteOutputError

__all__ = [
    "COMPRESSIONS",
    "DEFAULT_MAX_PIXELS",
    "HALF_MAX",
    "SUPPORTED_EXTENSIONS",
    "decode_image",
    "encode_display",
    "encode_image",
    "image_info",
    "read_image",
    "srgb_decode",
    "srgb_encode",
    "tonemap_srgb",
    "write_image",
]

HALF_MAX = 65504.0
"""Largest finite float16 value."""

DEFAULT_MAX_PIXELS = 64_000_000

_TRANSFERS = ("auto", "srgb", "linear", "gamma2.2")
_META_PREFIX = "ibr:"
_JSON_KEYS_ATTR = "ibr:_json_keys"
_KEY_RE = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,63}")
_INTEGER_TYPES = {"uint8", "int8", "uint16", "int16", "uint", "int", "uint32", "int32"}


@dataclass(frozen=True)
class _Format:
    oiio_name: str
    pixel_types: tuple[str, ...]  # first one is the default
    metadata: str  # "attributes" | "description" | "none"
    channels: tuple[int, ...]


_FORMATS: dict[str, _Format] = {
    ".exr": _Format("openexr", ("float", "half"), "attributes", (1, 3, 4)),
    ".hdr": _Format("hdr", ("rgbe", "float"), "none", (1, 3)),
    ".png": _Format("png", ("uint8", "uint16"), "attributes", (1, 3, 4)),
    ".jpg": _Format("jpeg", ("uint8",), "description", (1, 3)),
    ".jpeg": _Format("jpeg", ("uint8",), "description", (1, 3)),
    ".tif": _Format("tiff", ("float", "half", "uint16"), "description", (1, 3, 4)),
    ".tiff": _Format("tiff", ("float", "half", "uint16"), "description", (1, 3, 4)),
}
SUPPORTED_EXTENSIONS = tuple(_FORMATS)

COMPRESSIONS: dict[str, tuple[str, ...]] = {
    "openexr": ("zip", "zips", "rle", "piz", "none"),
    "tiff": ("zip", "lzw", "none"),
    "png": ("default", "fast"),
}
"""Lossless ``compression`` choices per OpenImageIO format (the first is the default); other
formats take none. EXR: ``zip`` (zlib, 16 scanlines per block; the smallest files here),
``zips`` (1 scanline), ``rle`` (cheap, wins only on flat images such as ids), ``piz`` (wavelet),
``none`` (fastest, largest). PNG: ``default`` is libpng's (zlib level 6, adaptive row filters);
``fast`` is zlib level 1 with the 'sub' row filter (about 3-4x faster, files 10-40 % larger)."""
_PNG_FAST = {"png:compressionLevel": 1, "png:filter": 16}

_OIIO_TYPES = {
    "float": oiio.FLOAT,
    "half": oiio.HALF,
    "rgbe": oiio.FLOAT,  # the HDR writer does the RGBE packing
    "uint8": oiio.UINT8,
    "uint16": oiio.UINT16,
}


# ----------------------------------------------------------------------------------------------
# Transfer functions


def srgb_encode(linear: Any) -> np.ndarray:
    """Exact piecewise sRGB OETF (IEC 61966-2-1), element-wise.

    ``12.92 x`` for ``x <= 0.0031308``, else ``1.055 x**(1/2.4) - 0.055``. No clipping: the
    linear segment extends to negative values and the power segment above 1, so
    :func:`srgb_decode` inverts it on all reals. Float inputs keep their dtype (computed in
    float64), anything else returns float64.
    """
    x = np.asarray(linear)
    out_dtype = x.dtype if x.dtype.kind == "f" else np.dtype(np.float64)
    x64 = x.astype(np.float64, copy=False)
    power = 1.055 * np.power(np.maximum(x64, 0.0031308), 1.0 / 2.4) - 0.055
    return np.where(x64 <= 0.0031308, 12.92 * x64, power).astype(out_dtype, copy=False)


def srgb_decode(encoded: Any) -> np.ndarray:
    """Exact inverse of :func:`srgb_encode` (the sRGB EOTF), element-wise.

    ``v / 12.92`` for ``v <= 0.04045``, else ``((v + 0.055) / 1.055)**2.4``.
    """
    v = np.asarray(encoded)
    out_dtype = v.dtype if v.dtype.kind == "f" else np.dtype(np.float64)
    v64 = v.astype(np.float64, copy=False)
    power = np.power((np.maximum(v64, 0.04045) + 0.055) / 1.055, 2.4)
    return np.where(v64 <= 0.04045, v64 / 12.92, power).astype(out_dtype, copy=False)


def tonemap_srgb(linear: Any, exposure_stops: float = 0.0) -> np.ndarray:
    """Display transform of the PNG/JPEG path: ``srgb_encode(clip(x * 2**exposure_stops, 0, 1))``.

    Returns float64 values in [0, 1] (not quantised). :mod:`engine.metrics` uses it for PSNR so
    that the metric sees exactly what a written PNG shows.
    """
    _check_exposure(exposure_stops)
    x = np.asarray(linear, dtype=np.float64)
    return srgb_encode(np.clip(x * (2.0**exposure_stops), 0.0, 1.0))


def _gamma22_decode(v: np.ndarray) -> np.ndarray:
    return np.power(np.maximum(v, 0.0), 2.2)


# ----------------------------------------------------------------------------------------------
# Writing


def write_image(
    path: str | os.PathLike[str],
    pixels: Any,
    *,
    pixel_type: str | None = None,
    exposure_stops: float = 0.0,
    metadata: Mapping[str, Any] | None = None,
    compression: str | None = None,
) -> None:
    """Write ``pixels`` to ``path`` atomically; the format comes from the extension.

    Args:
        path: destination; its directory must exist. Extensions: ``.exr .hdr .png .jpg .jpeg
            .tif .tiff`` (anything else raises :class:`ImageFormatError`).
        pixels: ``(h, w, c)`` with ``c`` in 1, 3, 4, or ``(h, w)``; a float dtype, linear
            radiance, alpha (``c == 4``) associated. Must be finite.
        pixel_type: sample type on disk; ``None`` picks the format's default.
            ``.exr``: ``"float"`` (default) or ``"half"``; ``.hdr``: ``"rgbe"`` (``"float"`` is
            accepted as an alias); ``.png``: ``"uint8"`` (default) or ``"uint16"``; ``.jpg``:
            ``"uint8"``; ``.tif``: ``"float"`` (default), ``"half"`` (both linear) or
            ``"uint16"`` (sRGB-encoded, like PNG).
        exposure_stops: scale ``2**exposure_stops`` applied before clipping and sRGB encoding
            for the integer (display) outputs. Linear outputs store radiance unchanged, so a
            non-zero exposure there raises :class:`InvalidInputError` instead of being ignored.
        metadata: ``str -> str | int | float | bool | None | dict | list``, stored under
            ``ibr:<key>`` (see the module docstring). Put the camera, scene hash and render
            parameters here.
        compression: lossless codec, one of :data:`COMPRESSIONS` for the format (``None``: its
            default, ``zip`` for EXR and TIFF, libpng's default for PNG).

    Raises:
        ImageFormatError: unknown extension.
        InvalidInputError: bad shape/dtype/pixel_type/metadata/compression, half overflow (``|x| > 65504``),
            values outside float32 range, negative values or alpha for RGBE, alpha for JPEG,
            metadata for RGBE.
        NonFiniteOutputError: ``pixels`` holds NaN or Inf (the message gives the count).
        OSError: the directory does not exist or the file system refused the write.
    """
    path = Path(path)
    fmt, spec, data = _prepare(path, pixels, pixel_type, exposure_stops, metadata, compression)
    _write_atomic(path, fmt, spec, data)


def encode_image(
    name: str | os.PathLike[str],
    pixels: Any,
    *,
    pixel_type: str | None = None,
    exposure_stops: float = 0.0,
    metadata: Mapping[str, Any] | None = None,
    compression: str | None = None,
) -> bytes:
    """The bytes :func:`write_image` would write to a file called ``name``, without keeping a file.

    ``name`` only picks the format (its extension) and names the image in errors; arguments,
    checks and errors are those of :func:`write_image`, and the bytes are identical. OpenImageIO
    writes files only, so the image goes through a scratch file (in ``/dev/shm`` when writable,
    else the temp directory) that is read back and removed; without fsync, as it is not kept.
    Safe to call from several threads at once (OpenImageIO releases the GIL while encoding).
    """
    path = Path(name)
    fmt, spec, data = _prepare(path, pixels, pixel_type, exposure_stops, metadata, compression)
    scratch = _scratch_dir() / f"ibr-encode-{secrets.token_hex(8)}{path.suffix.lower()}"
    try:
        out = oiio.ImageOutput.create(fmt.oiio_name)
        if out is None:
            raise ImageFormatError(f"cannot encode {path}: {oiio.geterror()}")
        try:
            if not out.open(str(scratch), spec) or not out.write_image(data):
                raise OSError(f"cannot encode {path}: {out.geterror()}")
        finally:
            closed = out.close()
        if not closed:
            raise OSError(f"cannot encode {path}: {out.geterror()}")
        return scratch.read_bytes()
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(scratch)


_SCRATCH: Path | None = None


def _scratch_dir() -> Path:
    global _SCRATCH
    if _SCRATCH is None:
        shm = Path("/dev/shm")
        _SCRATCH = shm if shm.is_dir() and os.access(shm, os.W_OK | os.X_OK) else Path(tempfile.gettempdir())
    return _SCRATCH


def _prepare(
    path: Path,
    pixels: Any,
    pixel_type: str | None,
    exposure_stops: float,
    metadata: Mapping[str, Any] | None,
    compression: str | None,
) -> tuple[_Format, oiio.ImageSpec, np.ndarray]:
    """Validate and convert: the format, the OpenImageIO spec and the samples to write."""
    fmt = _format_for(path)
    ptype = _resolve_pixel_type(path, fmt, pixel_type)
    _check_exposure(exposure_stops)
    codec = _resolve_compression(path, fmt, compression)
    px = _as_hwc(pixels, "pixels")

    n_bad = int(px.size - np.count_nonzero(np.isfinite(px)))
    if n_bad:
        raise NonFiniteOutputError(
            f"refusing to write {path}: pixels hold {n_bad} non-finite value(s) (NaN/Inf) out of {px.size}"
        )
    h, w, c = px.shape
    if c not in fmt.channels:
        raise InvalidInputError(
            f"{path.suffix} cannot store {c}-channel images (supported: {fmt.channels}); use .exr for RGBA"
        )
    display = ptype in ("uint8", "uint16")
    if not display and exposure_stops != 0.0:
        raise InvalidInputError(
            f"exposure_stops={exposure_stops} only applies to display-referred (integer) outputs; "
            f"{path.suffix} with pixel_type={ptype!r} stores linear radiance, scale it yourself"
        )

    attrs = _encode_metadata(metadata, fmt, path)
    if display:
        if ptype == "uint8" and c in (1, 3):
            data = _srgb8_codes(px, exposure_stops)
        else:
            data = encode_display(px, exposure_stops, 255 if ptype == "uint8" else 65535)
            data = data.astype(np.uint8 if ptype == "uint8" else np.uint16)
        attrs["oiio:ColorSpace"] = "sRGB"
        if c == 4:
            attrs["oiio:UnassociatedAlpha"] = 1
    elif ptype == "half":
        too_big = int(np.count_nonzero(np.abs(px) > HALF_MAX))
        if too_big:
            raise InvalidInputError(
                f"{too_big} value(s) exceed the float16 range (|x| > {HALF_MAX:g}, max "
                f"{float(np.max(np.abs(px))):.6g}) and would become Inf in a half image; "
                'write with pixel_type="float"'
            )
        data = px.astype(np.float16)
    else:  # float or rgbe: float32 samples
        data = px.astype(np.float32)
        n_over = int(data.size - np.count_nonzero(np.isfinite(data)))
        if n_over:
            raise InvalidInputError(f"{n_over} value(s) exceed the float32 range")
        if ptype == "rgbe":
            n_neg = int(np.count_nonzero(data < 0))
            if n_neg:
                raise InvalidInputError(f"RGBE (.hdr) cannot store negative values ({n_neg} found); use .exr")
            if c == 1:
                data = np.repeat(data, 3, axis=2)  # RGBE is RGB only; grey becomes R = G = B
    if fmt.oiio_name in ("openexr", "tiff"):
        attrs["compression"] = codec
    elif codec == "fast":
        attrs.update(_PNG_FAST)
    if fmt.oiio_name == "tiff" and ptype == "half":
        attrs["tiff:half"] = 1  # otherwise OIIO widens half TIFF samples to float

    spec = oiio.ImageSpec(w, h, data.shape[2], _OIIO_TYPES[ptype])
    spec.attribute("DateTime", "")  # suppress the time stamp: byte-deterministic files
    for name, value in attrs.items():
        spec.attribute(name, value)
    return fmt, spec, np.ascontiguousarray(data)


def _resolve_compression(path: Path, fmt: _Format, compression: str | None) -> str | None:
    allowed = COMPRESSIONS.get(fmt.oiio_name, ())
    if compression is None:
        return allowed[0] if allowed else None
    if compression not in allowed:
        choices = f"one of {allowed}" if allowed else "None (the format has no compression choice)"
        raise InvalidInputError(f"compression {compression!r} is not available for {path.suffix}; use {choices}")
    return compression


def encode_display(px: np.ndarray, exposure_stops: float = 0.0, levels: int = 255) -> np.ndarray:
    """The display encoding of the integer outputs as code values: ``(h, w, c)`` linear pixels with
    associated alpha (``c == 4``) -> ``rint(levels * tonemap_srgb(colour, exposure_stops))`` as
    float64, alpha straight (colour un-premultiplied; fully transparent pixels carry no colour) and
    linear. ``levels`` 255 gives the samples of an 8-bit PNG (:func:`write_image` writes the same
    codes through a faster exact path), 65535 those of a 16-bit one. No input checks: finite
    pixels, as :func:`write_image` requires."""
    x = px.astype(np.float64)
    c = x.shape[2]
    color = x[..., :3] if c == 4 else x
    if c == 4:
        alpha = np.clip(x[..., 3:4], 0.0, 1.0)
        # PNG stores straight alpha: un-premultiply; fully transparent pixels carry no colour.
        safe = np.where(alpha > 0, alpha, 1.0)
        color = np.where(alpha > 0, color / safe, 0.0)
    encoded = tonemap_srgb(color, exposure_stops)
    if c == 4:
        encoded = np.concatenate([encoded, alpha], axis=2)
    return np.rint(encoded * levels)


# Exact 8-bit sRGB codes by thresholds. The reference is ``rint(srgb_encode(c) * 255)`` in float64
# for c = clip(x * 2**exposure, 0, 1); it is non-decreasing in c, so code k starts at a threshold t_k
# (the smallest float64 with code >= k), found once by bisection over the bit patterns of [0, 1]
# (non-negative doubles order like their bits). A sample's top 20 bits (sign, exponent, 8 mantissa
# bits) pick a bucket holding at most one threshold: code = base[bucket] + (c >= threshold[bucket]).
_BUCKET_SHIFT = np.uint64(44)
_SRGB8: tuple[np.ndarray, np.ndarray] | None = None
_SRGB8_LOCK = threading.Lock()


def _reference_srgb8(c: np.ndarray) -> np.ndarray:
    """Code values of clipped linear values c in [0, 1], computed as the float64 reference path does."""
    return np.rint(srgb_encode(c) * 255)


def _srgb8_thresholds() -> np.ndarray:
    """t_1 .. t_255 (float64): the smallest c in [0, 1] with reference code >= k."""
    k = np.arange(1, 256, dtype=np.float64)
    lo = np.zeros(255, np.int64)  # code(bits 0 = 0.0) = 0 < k
    hi = np.full(255, np.float64(1.0).view(np.int64), np.int64)  # code(1.0) = 255 >= k
    while np.any(hi - lo > 1):
        mid = lo + (hi - lo) // 2
        up = _reference_srgb8(mid.view(np.float64)) >= k
        hi = np.where(up, mid, hi)
        lo = np.where(up, lo, mid)
    return hi.view(np.float64)


def _srgb8_tables() -> tuple[np.ndarray, np.ndarray]:
    global _SRGB8
    with _SRGB8_LOCK:
        if _SRGB8 is None:
            t = _srgb8_thresholds()
            n = int(np.float64(1.0).view(np.uint64) >> _BUCKET_SHIFT) + 1
            starts = (np.arange(n, dtype=np.uint64) << _BUCKET_SHIFT).view(np.float64)
            base = _reference_srgb8(starts).astype(np.uint8)
            thresh = np.full(n, np.inf)
            buckets = (t.view(np.uint64) >> _BUCKET_SHIFT).astype(np.int64)
            inside = t > starts[buckets]  # a threshold at a bucket's start is already in its base
            if len(np.unique(buckets[inside])) != int(np.count_nonzero(inside)):
                raise AssertionError("two sRGB code thresholds share a bucket; lower _BUCKET_SHIFT")
            thresh[buckets[inside]] = t[inside]
            _SRGB8 = (base, thresh)
    return _SRGB8


def _srgb8_codes(px: np.ndarray, exposure_stops: float) -> np.ndarray:
    """uint8 codes of grey/RGB linear pixels, bit-identical to ``encode_display(px, e, 255)``
    (finite input: callers refuse NaN/Inf first). One pass of ``engine._srgb8_kernel``: the same
    float64 operations as the NumPy form it replaced, ~4x faster at 512x512 (the render preview)."""
    # Deferred on purpose: the compiled loop needs numba, which importing this module must not load
    # (the API process reads images and computes metrics, and never encodes 8-bit ones).
    from engine._srgb8_kernel import srgb8_kernel

    base, thresh = _srgb8_tables()
    flat = np.ascontiguousarray(px).reshape(-1)
    if flat.dtype not in (np.float32, np.float64):  # float16 / longdouble: to float64 as before
        flat = flat.astype(np.float64)
    out = np.empty(flat.size, np.uint8)
    scale = 2.0**exposure_stops if exposure_stops != 0.0 else 1.0  # x * 1.0 == x: the same bits
    srgb8_kernel(flat, np.float64(scale), base, thresh, np.int64(_BUCKET_SHIFT), out)
    return out.reshape(px.shape)


def _write_atomic(path: Path, fmt: _Format, spec: oiio.ImageSpec, data: np.ndarray) -> None:
    directory = path.parent
    if not directory.is_dir():
        raise FileNotFoundError(f"cannot write {path}: directory {directory} does not exist")
    # A random hidden name in the same directory (same file system, so os.replace is atomic).
    # OIIO creates the file itself, so the process umask applies as for any other file.
    tmp = directory / f".{path.name}.{secrets.token_hex(8)}.tmp"
    try:
        out = oiio.ImageOutput.create(fmt.oiio_name)
        if out is None:
            raise ImageFormatError(f"cannot write {path}: {oiio.geterror()}")
        try:
            if not out.open(str(tmp), spec):
                raise OSError(f"cannot write {path}: {out.geterror()}")
            if not out.write_image(data):
                raise OSError(f"cannot write {path}: {out.geterror()}")
        finally:
            closed = out.close()
        if not closed:
            raise OSError(f"cannot write {path}: {out.geterror()}")
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    # Make the rename itself durable; not possible everywhere (e.g. Windows), hence best effort.
    with contextlib.suppress(OSError):
        dfd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)


# ----------------------------------------------------------------------------------------------
# Reading


def read_image(
    path: str | os.PathLike[str],
    *,
    max_pixels: int = DEFAULT_MAX_PIXELS,
    transfer: str = "auto",
) -> tuple[np.ndarray, dict[str, Any]]:
    """Read an image as ``(h, w, c) float32`` linear pixels plus its ``ibr:`` metadata.

    Args:
        path: any format OpenImageIO reads (first subimage, full-resolution MIP level).
        max_pixels: upper bound on ``width * height`` as declared by the header, checked before
            any pixel is read; larger files raise :class:`ImageFormatError`. Files whose
            ``width * height * channels`` exceeds ``4 * max_pixels`` are refused likewise.
        transfer: how sample values are linearised. ``"auto"``: integer files (8/16 bit) are
            decoded with the transfer their header declares -- sRGB unless it says linear or
            gamma 2.2 -- and float files are taken as linear. ``"srgb"``, ``"linear"``,
            ``"gamma2.2"`` force that curve on any file. Alpha is never transfer-decoded.
            Straight (unassociated) alpha, as in PNG, is premultiplied after decoding.

    Returns:
        ``(pixels, metadata)``: pixels ``(h, w, c) float32``; metadata maps ``<key>`` of every
        ``ibr:<key>`` attribute to its value, JSON-encoded values decoded back (see the module
        docstring); ``{}`` when the file has none.

    Raises:
        ImageFormatError: missing, unreadable, truncated or corrupt file, unsupported format,
            resolution over ``max_pixels``, deep or volume image, NaN/Inf samples. The message
            names the path and the reason reported by OpenImageIO.
        InvalidInputError: bad ``transfer`` or ``max_pixels``.
    """
    if transfer not in _TRANSFERS:
        raise InvalidInputError(f"transfer must be one of {_TRANSFERS}, got {transfer!r}")
    if isinstance(max_pixels, bool) or not isinstance(max_pixels, int) or max_pixels < 1:
        raise InvalidInputError(f"max_pixels must be a positive int, got {max_pixels!r}")
    path = Path(path)
    inp = _open(path)
    try:
        spec = inp.spec()
        _check_declared_size(path, spec, max_pixels)
        pixels = _read_pixels(inp, spec, path)
        metadata = _decode_metadata(spec)
    finally:
        inp.close()

    n_bad = int(pixels.size - np.count_nonzero(np.isfinite(pixels)))
    if n_bad:
        raise ImageFormatError(f"{path}: file holds {n_bad} non-finite sample(s) (NaN/Inf)")

    alpha_ch = spec.alpha_channel if 0 <= spec.alpha_channel < pixels.shape[2] else -1
    color = [i for i in range(pixels.shape[2]) if i != alpha_ch]
    curve = _resolve_transfer(transfer, spec)
    if curve != "linear":
        decode = srgb_decode if curve == "srgb" else _gamma22_decode
        pixels[..., color] = decode(pixels[..., color].astype(np.float64)).astype(np.float32)
    if alpha_ch >= 0 and spec.get_int_attribute("oiio:UnassociatedAlpha", 0):
        pixels[..., color] *= pixels[..., alpha_ch : alpha_ch + 1]
    return pixels, metadata


def decode_image(
    name: str | os.PathLike[str],
    data: bytes,
    *,
    max_pixels: int = DEFAULT_MAX_PIXELS,
    transfer: str = "auto",
) -> tuple[np.ndarray, dict[str, Any]]:
    """:func:`read_image` of an encoded image held in memory (a blob from an object store), the
    counterpart of :func:`encode_image`.

    ``name`` picks the format (its extension, one of :data:`SUPPORTED_EXTENSIONS`) and names the
    image in errors; arguments, checks, errors and results are those of :func:`read_image`.
    OpenImageIO reads files only, so the bytes go through a scratch file (in ``/dev/shm`` when
    writable) that is removed again.
    """
    path = Path(name)
    _format_for(path)
    scratch = _scratch_dir() / f"ibr-decode-{secrets.token_hex(8)}{path.suffix.lower()}"
    try:
        scratch.write_bytes(data)
        return read_image(scratch, max_pixels=max_pixels, transfer=transfer)
    except ImageFormatError as exc:
        raise ImageFormatError(str(exc).replace(str(scratch), str(path))) from None
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(scratch)


def image_info(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Header facts without reading pixels.

    Returns ``{"width", "height", "channels", "format", "pixel_type", "channel_names"}``:
    ``format`` is OpenImageIO's format name (``"openexr"``, ``"png"``, ``"hdr"``, ...),
    ``pixel_type`` the sample type (``"float"``, ``"half"``, ``"uint8"``, ``"uint16"``; RGBE
    files report ``"float"``). Raises :class:`ImageFormatError` like :func:`read_image`.
    """
    path = Path(path)
    inp = _open(path)
    try:
        spec = inp.spec()
        return {
            "width": int(spec.width),
            "height": int(spec.height),
            "channels": int(spec.nchannels),
            "format": inp.format_name(),
            "pixel_type": str(spec.format),
            "channel_names": list(spec.channelnames),
        }
    finally:
        inp.close()


def _open(path: Path) -> oiio.ImageInput:
    config = oiio.ImageSpec()
    # Hand back the stored values; un/premultiplication is done here, in linear space.
    config.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(str(path), config)
    if inp is None:
        raise ImageFormatError(f"cannot read image {path}: {oiio.geterror() or 'unknown error'}")
    return inp


def _check_declared_size(path: Path, spec: oiio.ImageSpec, max_pixels: int) -> None:
    w, h, d, c = int(spec.width), int(spec.height), int(spec.depth), int(spec.nchannels)
    if w < 1 or h < 1 or c < 1:
        raise ImageFormatError(f"{path}: header declares an empty image ({w}x{h}, {c} channels)")
    if d != 1 or spec.deep:
        raise ImageFormatError(f"{path}: volume and deep images are not supported")
    if w * h > max_pixels:
        raise ImageFormatError(
            f"{path}: header declares {w}x{h} = {w * h} pixels, more than max_pixels={max_pixels}"
        )
    if w * h * c > 4 * max_pixels:
        raise ImageFormatError(
            f"{path}: header declares {w}x{h} pixels x {c} channels, "
            f"more than 4 * max_pixels={max_pixels} samples"
        )


def _read_pixels(inp: oiio.ImageInput, spec: oiio.ImageSpec, path: Path) -> np.ndarray:
    data = inp.read_image(0, 0, 0, spec.nchannels, oiio.FLOAT)
    if data is None or inp.has_error:
        raise ImageFormatError(
            f"{path}: cannot read pixels (truncated or corrupt?): {inp.geterror() or 'unknown error'}"
        )
    return np.array(data, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)


def _resolve_transfer(transfer: str, spec: oiio.ImageSpec) -> str:
    if transfer != "auto":
        return transfer
    if str(spec.format) not in _INTEGER_TYPES:
        return "linear"
    colorspace = spec.get_string_attribute("oiio:ColorSpace", "").lower()
    if "lin" in colorspace:
        return "linear"
    if "g22" in colorspace or "gamma2.2" in colorspace:
        return "gamma2.2"
    return "srgb"


# ----------------------------------------------------------------------------------------------
# Helpers


def _format_for(path: Path) -> _Format:
    fmt = _FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise ImageFormatError(
            f"{path}: unsupported image extension {path.suffix!r}; "
            f"supported: {', '.join(SUPPORTED_EXTENSIONS)}"
        )
    return fmt


def _resolve_pixel_type(path: Path, fmt: _Format, pixel_type: str | None) -> str:
    if pixel_type is None:
        return fmt.pixel_types[0]
    if pixel_type not in fmt.pixel_types:
        raise InvalidInputError(
            f"pixel_type {pixel_type!r} is not available for {path.suffix}; choose one of {fmt.pixel_types}"
        )
    return "rgbe" if fmt.oiio_name == "hdr" else pixel_type


def _check_exposure(exposure_stops: float) -> None:
    if isinstance(exposure_stops, bool) or not isinstance(exposure_stops, (int, float)):
        raise InvalidInputError(f"exposure_stops must be a number, got {exposure_stops!r}")
    if not math.isfinite(exposure_stops) or abs(exposure_stops) > 64:
        raise InvalidInputError(f"exposure_stops must be finite and within +-64, got {exposure_stops}")


def _as_hwc(pixels: Any, name: str) -> np.ndarray:
    px = np.asarray(pixels)
    if px.dtype.kind != "f":
        raise InvalidInputError(
            f"{name} must have a float dtype (linear radiance), got {px.dtype}; "
            "convert integer code values with srgb_decode first"
        )
    if px.ndim == 2:
        px = px[:, :, None]
    if px.ndim != 3 or px.shape[2] not in (1, 3, 4) or px.shape[0] < 1 or px.shape[1] < 1:
        raise InvalidInputError(f"{name} must be (h, w) or (h, w, c) with c in 1, 3, 4; got {px.shape}")
    return px


def _canonical_json(value: Any) -> str:
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)


def _plain(value: Any) -> Any:
    """numpy scalars -> Python scalars, so np.float32(1.5) is accepted like 1.5."""
    return value.item() if isinstance(value, np.generic) else value


def _encode_metadata(metadata: Mapping[str, Any] | None, fmt: _Format, path: Path) -> dict[str, Any]:
    if not metadata:
        return {}
    if not isinstance(metadata, Mapping):
        raise InvalidInputError(f"metadata must be a dict, got {type(metadata).__name__}")
    if fmt.metadata == "none":
        raise InvalidInputError(f"{path.suffix} cannot store metadata; write .exr, .png or .tif")
    stored: dict[str, str] = {}
    json_keys: list[str] = []
    for key, raw in metadata.items():
        if not isinstance(key, str) or not _KEY_RE.fullmatch(key):
            raise InvalidInputError(
                f"metadata key {key!r} must be 1-64 characters from [A-Za-z0-9_.-], not starting with '_'"
            )
        value = _plain(raw)
        if isinstance(value, str):
            stored[key] = value
            continue
        if isinstance(value, np.ndarray):
            raise InvalidInputError(f"metadata[{key!r}] is an array; pass value.tolist()")
        try:
            stored[key] = _canonical_json(value)
        except (TypeError, ValueError) as exc:
            raise InvalidInputError(f"metadata[{key!r}] is not JSON-serialisable: {exc}") from exc
        json_keys.append(key)

    if fmt.metadata == "description":
        everything = {k: (json.loads(stored[k]) if k in json_keys else stored[k]) for k in stored}
        return {"ImageDescription": _canonical_json({"ibr": everything})}
    attrs: dict[str, Any] = {_META_PREFIX + k: v for k, v in stored.items()}
    if json_keys:
        attrs[_JSON_KEYS_ATTR] = _canonical_json(sorted(json_keys))
    return attrs


def _decode_metadata(spec: oiio.ImageSpec) -> dict[str, Any]:
    attrs = {a.name: a.value for a in spec.extra_attribs}
    json_keys: set[str] | None = None
    manifest = attrs.get(_JSON_KEYS_ATTR)
    if isinstance(manifest, str):
        with contextlib.suppress(ValueError):
            loaded = json.loads(manifest)
            if isinstance(loaded, list):
                json_keys = {k for k in loaded if isinstance(k, str)}

    out: dict[str, Any] = {}
    for name, value in attrs.items():
        if not name.startswith(_META_PREFIX) or name == _JSON_KEYS_ATTR:
            continue
        key = name[len(_META_PREFIX) :]
        # Without a manifest (a file written by another tool) decode only what is clearly JSON.
        is_json = key in json_keys if json_keys is not None else str(value)[:1] in ("{", "[")
        if isinstance(value, str) and is_json:
            with contextlib.suppress(ValueError):
                value = json.loads(value)
        elif isinstance(value, tuple):
            value = list(value)
        out[key] = value

    desc = attrs.get("ImageDescription")
    if isinstance(desc, str) and desc.startswith('{"ibr":'):
        with contextlib.suppress(ValueError):
            packed = json.loads(desc)
            if isinstance(packed, dict) and isinstance(packed.get("ibr"), dict):
                for key, value in packed["ibr"].items():
                    out.setdefault(key, value)
    return out
