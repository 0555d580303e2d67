"""Tests for engine.imageio: round trips per format, refusals, hostile files (docs/hard-cases.md #9, #13, #16)."""

from __future__ import annotations

import json
import math
import struct
import time

import numpy as np
import OpenImageIO as oiio
import pytest

from engine import imageio
from engine.errors import ImageFormatError, InvalidInputError, NonFiniteOutputError
from engine.imageio import image_info, read_image, srgb_decode, srgb_encode, write_image


def _srgb_encode_scalar(x: float) -> float:
    """IEC 61966-2-1 written out once more, independently of the module."""
    if x <= 0.0031308:
        return 12.92 * x
    return 1.055 * math.pow(x, 1.0 / 2.4) - 0.055


def _raw_oiio_write(path, pixels: np.ndarray, typedesc) -> None:
    """Write with OIIO directly, bypassing write_image's checks (to plant bad files)."""
    h, w, c = pixels.shape
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(w, h, c, typedesc))
    assert out.write_image(pixels)
    out.close()


def _header_attrs(path) -> dict:
    inp = oiio.ImageInput.open(str(path))
    try:
        return {a.name: a.value for a in inp.spec().extra_attribs}
    finally:
        inp.close()


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


# ---------------------------------------------------------------------------------------------
# sRGB helpers


def test_srgb_encode_matches_scalar_definition_and_known_values():
    xs = np.concatenate([np.linspace(-0.05, 1.5, 997), [0.0031308, 0.0031307, 0.0031309, 1.0]])
    got = srgb_encode(xs)
    for x, g in zip(xs, got, strict=True):
        assert g == pytest.approx(_srgb_encode_scalar(float(x)), rel=1e-13, abs=1e-15)
    assert srgb_encode(np.array(1.0)) == pytest.approx(1.0, abs=1e-15)
    assert srgb_encode(np.array(0.5)) == pytest.approx(0.7353569830524495, rel=1e-12)
    assert srgb_encode(np.array(0.0031308)) == pytest.approx(0.040449936, rel=1e-9)


def test_srgb_decode_inverts_encode_on_both_segments():
    xs = np.concatenate([np.linspace(-0.01, 0.004, 301), np.geomspace(1e-6, 4.0, 700)])
    np.testing.assert_allclose(srgb_decode(srgb_encode(xs)), xs, rtol=1e-12, atol=1e-15)
    vs = np.linspace(0.0, 1.0, 1001)
    np.testing.assert_allclose(srgb_encode(srgb_decode(vs)), vs, rtol=1e-12, atol=1e-15)
    # decode of the curve's knee and of 1.0
    assert srgb_decode(np.array(0.04045)) == pytest.approx(0.04045 / 12.92, rel=1e-12)
    assert srgb_decode(np.array(1.0)) == pytest.approx(1.0, rel=1e-12)


def test_srgb_helpers_keep_float32_dtype():
    x = np.linspace(0, 1, 5, dtype=np.float32)
    assert srgb_encode(x).dtype == np.float32
    assert srgb_decode(x).dtype == np.float32
    assert srgb_encode(np.arange(3)).dtype == np.float64


# ---------------------------------------------------------------------------------------------
# EXR


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_exr_float_roundtrip_is_bit_exact_including_extremes(tmp_path, rng, channels):
    px = rng.uniform(-2.0, 50.0, size=(9, 13, channels)).astype(np.float32)
    px[0, 0, 0] = 1e6
    px[0, 1, 0] = 1e-8
    px[0, 2, 0] = -1e-8
    px[0, 3, 0] = 3.4e38
    path = tmp_path / "img.exr"
    write_image(path, px)
    got, meta = read_image(path)
    assert got.dtype == np.float32 and got.shape == px.shape
    assert np.array_equal(got, px)
    assert got[0, 0, 0] == np.float32(1e6) and got[0, 1, 0] == np.float32(1e-8)
    assert meta == {}
    info = image_info(path)
    assert info["pixel_type"] == "float" and info["format"] == "openexr"
    assert _header_attrs(path)["compression"] == "zip"


def test_exr_2d_input_becomes_single_channel(tmp_path, rng):
    px = rng.random((4, 6)).astype(np.float32)
    write_image(tmp_path / "y.exr", px)
    got, _ = read_image(tmp_path / "y.exr")
    assert got.shape == (4, 6, 1)
    assert np.array_equal(got[..., 0], px)


def test_exr_float64_input_is_stored_as_nearest_float32(tmp_path, rng):
    px = rng.random((3, 3, 3)) * 1e3
    write_image(tmp_path / "d.exr", px)
    got, _ = read_image(tmp_path / "d.exr")
    assert np.array_equal(got, px.astype(np.float32))


def test_exr_half_roundtrip_within_float16_precision(tmp_path, rng):
    px = np.exp(rng.uniform(np.log(1e-3), np.log(6e4), size=(8, 8, 3))).astype(np.float32)
    px[0, 0] = [65504.0, 1e-8, 1e-6]
    path = tmp_path / "h.exr"
    write_image(path, px, pixel_type="half")
    got, _ = read_image(path)
    assert image_info(path)["pixel_type"] == "half"
    # exactly what float16 round-to-nearest gives ...
    assert np.array_equal(got, px.astype(np.float16).astype(np.float32))
    # ... which is within half precision for normal values
    normal = px >= 6.2e-5
    np.testing.assert_allclose(got[normal], px[normal], rtol=1e-3)
    # documented: the max is exact, 1e-8 is below the smallest float16 subnormal (2**-24) and
    # becomes 0, 1e-6 survives as a subnormal (abs error <= 2**-25)
    assert got[0, 0, 0] == 65504.0
    assert got[0, 0, 1] == 0.0
    assert got[0, 0, 2] > 0 and abs(got[0, 0, 2] - 1e-6) <= 2.0**-25


@pytest.mark.parametrize("name", ["o.exr", "o.tif"])
@pytest.mark.parametrize("value", [65505.0, 70000.0, -1e6])
def test_half_overflow_raises_instead_of_inf(tmp_path, name, value):
    px = np.ones((2, 2, 3), np.float32)
    px[1, 1, 2] = value
    with pytest.raises(InvalidInputError, match='float16.*pixel_type="float"'):
        write_image(tmp_path / name, px, pixel_type="half")
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------------------------
# HDR (RGBE)


def test_hdr_roundtrip_within_rgbe_precision(tmp_path, rng):
    # RGBE shares one exponent per pixel: precision is relative to the pixel's largest channel.
    base = np.exp(rng.uniform(np.log(1e-3), np.log(1e5), size=(10, 12, 1)))
    px = (base * rng.uniform(0.2, 1.0, size=(10, 12, 3))).astype(np.float32)
    path = tmp_path / "r.hdr"
    write_image(path, px)
    got, meta = read_image(path)
    assert got.shape == px.shape and meta == {}
    err = np.abs(got - px) / px.max(axis=2, keepdims=True)
    assert err.max() < 0.01
    assert image_info(path)["format"] == "hdr"


def test_hdr_grey_is_replicated_and_negatives_alpha_metadata_refused(tmp_path):
    grey = np.full((2, 3), 0.5, np.float32)
    write_image(tmp_path / "g.hdr", grey)
    got, _ = read_image(tmp_path / "g.hdr")
    assert got.shape == (2, 3, 3)
    np.testing.assert_allclose(got, 0.5, rtol=0.01)
    with pytest.raises(InvalidInputError, match="negative"):
        write_image(tmp_path / "n.hdr", -np.ones((2, 2, 3), np.float32))
    with pytest.raises(InvalidInputError, match="4-channel"):
        write_image(tmp_path / "a.hdr", np.ones((2, 2, 4), np.float32))
    with pytest.raises(InvalidInputError, match="metadata"):
        write_image(tmp_path / "m.hdr", np.ones((2, 2, 3), np.float32), metadata={"a": 1})


# ---------------------------------------------------------------------------------------------
# PNG / JPEG (display-referred)


def test_png8_stores_exact_srgb_code_values_and_roundtrips(tmp_path, rng):
    px = rng.random((16, 16, 3)).astype(np.float32)
    px[0, 0] = [0.0, 0.0031308, 1.0]
    path = tmp_path / "p.png"
    write_image(path, px)
    assert image_info(path)["pixel_type"] == "uint8"

    codes, _ = read_image(path, transfer="linear")  # raw code values / 255
    expected = np.empty_like(px, dtype=np.float64)
    for idx in np.ndindex(px.shape):
        expected[idx] = round(_srgb_encode_scalar(float(px[idx])) * 255) / 255
    np.testing.assert_allclose(codes, expected, atol=1e-7)

    got, _ = read_image(path)  # auto: sRGB-decoded
    assert got.dtype == np.float32
    np.testing.assert_allclose(
        srgb_encode(got.astype(np.float64)), srgb_encode(px.astype(np.float64)), atol=0.5 / 255 + 1e-6
    )
    np.testing.assert_allclose(got, srgb_decode(expected), atol=1e-6)


def test_png_exposure_and_clipping(tmp_path):
    px = np.array([[[0.25, 0.125, 0.5], [4.0, -1.0, 0.0]]], np.float32)
    path = tmp_path / "e.png"
    write_image(path, px, exposure_stops=2.0)  # x4: 1.0, 0.5, 2.0 -> clip; 16 -> 1, -4 -> 0
    codes, _ = read_image(path, transfer="linear")
    expected = [[[1.0, round(_srgb_encode_scalar(0.5) * 255) / 255, 1.0], [1.0, 0.0, 0.0]]]
    np.testing.assert_allclose(codes, expected, atol=1e-7)

    write_image(path, px, exposure_stops=-1.0)  # 0.25 -> 0.125
    got, _ = read_image(path)
    assert got[0, 0, 0] == pytest.approx(0.125, rel=0.02)
    assert got[0, 1, 0] == pytest.approx(1.0)  # 4.0 * 0.5 = 2 -> clipped


def test_png16_roundtrip(tmp_path, rng):
    px = rng.random((5, 6, 3)).astype(np.float32)
    path = tmp_path / "p16.png"
    write_image(path, px, pixel_type="uint16")
    assert image_info(path)["pixel_type"] == "uint16"
    got, _ = read_image(path)
    np.testing.assert_allclose(
        srgb_encode(got.astype(np.float64)), srgb_encode(px.astype(np.float64)), atol=0.5 / 65535 + 1e-7
    )


def test_png_rgba_premultiplied_roundtrip(tmp_path):
    # associated alpha in memory, straight alpha in the PNG
    color = np.array([[[0.8, 0.2, 0.05], [0.5, 0.5, 0.5], [0.3, 0.6, 0.9]]])
    alpha = np.array([[[1.0], [0.5], [0.0]]])
    px = np.concatenate([color * alpha, alpha], axis=2).astype(np.float32)
    path = tmp_path / "rgba.png"
    write_image(path, px, pixel_type="uint16")
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    inp = oiio.ImageInput.open(str(path), config)
    raw = inp.read_image(0, 0, 0, 4, oiio.FLOAT)
    inp.close()
    # stored colour is un-premultiplied: the half-transparent grey is encoded as 0.5, not 0.25
    assert raw[0, 1, 0] == pytest.approx(_srgb_encode_scalar(0.5), abs=1e-4)
    assert raw[0, 1, 3] == pytest.approx(0.5, abs=1e-4)
    got, _ = read_image(path)
    np.testing.assert_allclose(got, px, atol=2e-4)
    assert np.all(got[0, 2] == 0.0)


def test_png_grey(tmp_path):
    px = np.linspace(0, 1, 12, dtype=np.float32).reshape(3, 4)
    write_image(tmp_path / "g.png", px)
    got, _ = read_image(tmp_path / "g.png")
    assert got.shape == (3, 4, 1)
    np.testing.assert_allclose(
        srgb_encode(got[..., 0].astype(np.float64)), srgb_encode(px.astype(np.float64)), atol=0.5 / 255 + 1e-6
    )


def test_read_transfer_options(tmp_path):
    px = np.array([[[0.2, 0.5, 0.9]]], np.float32)
    path = tmp_path / "t.png"
    write_image(path, px)
    codes, _ = read_image(path, transfer="linear")
    srgb, _ = read_image(path, transfer="srgb")
    auto, _ = read_image(path)
    g22, _ = read_image(path, transfer="gamma2.2")
    assert np.array_equal(srgb, auto)
    np.testing.assert_allclose(srgb, srgb_decode(codes.astype(np.float64)), rtol=1e-6)
    np.testing.assert_allclose(g22, codes.astype(np.float64) ** 2.2, rtol=1e-6)
    with pytest.raises(InvalidInputError, match="transfer"):
        read_image(path, transfer="rec2020")


def test_jpeg_roundtrip_is_close_and_alpha_refused(tmp_path):
    yy, xx = np.mgrid[0:32, 0:32] / 31.0
    px = srgb_decode(np.stack([xx, yy, 0.5 * np.ones_like(xx)], axis=2)).astype(np.float32)
    path = tmp_path / "j.jpg"
    write_image(path, px)
    got, _ = read_image(path)
    err = np.abs(srgb_encode(got.astype(np.float64)) - srgb_encode(px.astype(np.float64)))
    assert err.mean() < 0.01 and err.max() < 0.06
    with pytest.raises(InvalidInputError, match="4-channel"):
        write_image(tmp_path / "a.jpg", np.ones((2, 2, 4), np.float32))


# ---------------------------------------------------------------------------------------------
# TIFF


@pytest.mark.parametrize("suffix", [".tif", ".tiff"])
def test_tiff_float_roundtrip_exact(tmp_path, rng, suffix):
    px = rng.uniform(-1, 1e4, size=(7, 5, 3)).astype(np.float32)
    px[0, 0] = [1e6, 1e-8, 0.0]
    path = tmp_path / f"f{suffix}"
    write_image(path, px)
    got, _ = read_image(path)
    assert np.array_equal(got, px)
    assert image_info(path)["format"] == "tiff"


def test_tiff_half_and_uint16(tmp_path, rng):
    px = rng.random((4, 4, 3)).astype(np.float32)
    write_image(tmp_path / "h.tif", px * 100, pixel_type="half")
    assert image_info(tmp_path / "h.tif")["pixel_type"] == "half"
    got, _ = read_image(tmp_path / "h.tif")
    assert np.array_equal(got, (px * 100).astype(np.float16).astype(np.float32))

    write_image(tmp_path / "u.tif", px * 4, pixel_type="uint16", exposure_stops=-2.0)
    assert image_info(tmp_path / "u.tif")["pixel_type"] == "uint16"
    got, _ = read_image(tmp_path / "u.tif")  # auto: integer TIFF is sRGB-encoded
    np.testing.assert_allclose(got, px, atol=1e-4)


# ---------------------------------------------------------------------------------------------
# Metadata


METADATA = {
    "camera": {"position": [1.5, -2.0, 3.25], "fov_deg": 45.0, "look_at": [0, 0, 0], "up": [0, 1, 0]},
    "scene_hash": "sha256:0f3c9a",
    "technique": "ldc",
    "samples": 16,
    "exposure": 0.1,
    "tiny": 1e-300,
    "flags": [True, False, None],
    "preview": False,
    "note": "grüße ✓",
    "looks_like_json": "[not json",
}


@pytest.mark.parametrize("name", ["m.exr", "m.png", "m.tif", "m.jpg"])
def test_metadata_roundtrip(tmp_path, name):
    px = np.full((3, 4, 3), 0.25, np.float32)
    path = tmp_path / name
    write_image(path, px, metadata=METADATA)
    _, meta = read_image(path)
    assert meta == METADATA
    for key, value in METADATA.items():  # types survive, not just equality (True == 1)
        assert type(meta[key]) is type(value)


@pytest.mark.parametrize("name", ["a.exr", "a.png"])
def test_metadata_header_layout(tmp_path, name):
    path = tmp_path / name
    write_image(path, np.zeros((2, 2, 3), np.float32), metadata={"camera": {"b": 1, "a": [1, 2]}, "s": "x"})
    attrs = _header_attrs(path)
    assert attrs["ibr:camera"] == '{"a":[1,2],"b":1}'  # canonical JSON: sorted, compact
    assert attrs["ibr:s"] == "x"
    assert json.loads(attrs["ibr:_json_keys"]) == ["camera"]
    assert "DateTime" not in attrs


def test_metadata_without_manifest_decodes_only_obvious_json(tmp_path):
    # a file written by another tool: no ibr:_json_keys
    path = tmp_path / "ext.exr"
    spec = oiio.ImageSpec(2, 2, 3, oiio.FLOAT)
    spec.attribute("ibr:cam", '{"f":2}')
    spec.attribute("ibr:n", 7)
    spec.attribute("ibr:s", "42")
    out = oiio.ImageOutput.create(str(path))
    out.open(str(path), spec)
    out.write_image(np.zeros((2, 2, 3), np.float32))
    out.close()
    _, meta = read_image(path)
    assert meta == {"cam": {"f": 2}, "n": 7, "s": "42"}


@pytest.mark.parametrize(
    "metadata",
    [
        {"_hidden": 1},
        {"a:b": 1},
        {"": 1},
        {"k" * 65: 1},
        {"nan": float("nan")},
        {"obj": object()},
        {"arr": np.zeros(3)},
        {3: "x"},
    ],
)
def test_bad_metadata_refused(tmp_path, metadata):
    with pytest.raises(InvalidInputError):
        write_image(tmp_path / "b.exr", np.zeros((2, 2, 3), np.float32), metadata=metadata)
    assert list(tmp_path.iterdir()) == []


def test_numpy_scalar_metadata_accepted(tmp_path):
    write_image(
        tmp_path / "n.exr", np.zeros((1, 1, 3), np.float32), metadata={"x": np.float32(1.5), "i": np.int64(3)}
    )
    assert read_image(tmp_path / "n.exr")[1] == {"x": 1.5, "i": 3}


# ---------------------------------------------------------------------------------------------
# Refusals on write, atomicity


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_input_refused_with_count(tmp_path, bad):
    px = np.ones((4, 4, 3), np.float32)
    px[0, 0, 0] = bad
    px[3, 2, 1] = bad
    px[1, 1, 2] = bad
    with pytest.raises(NonFiniteOutputError, match=r"\b3 non-finite"):
        write_image(tmp_path / "x.exr", px)
    assert list(tmp_path.iterdir()) == []


def test_failed_write_keeps_previous_file_and_leaves_no_temp(tmp_path):
    path = tmp_path / "keep.exr"
    good = np.full((2, 2, 3), 0.5, np.float32)
    write_image(path, good)
    before = path.read_bytes()
    with pytest.raises(NonFiniteOutputError):
        write_image(path, np.full((2, 2, 3), np.nan, np.float32))
    with pytest.raises(InvalidInputError):
        write_image(path, good * 1e6, pixel_type="half")
    assert path.read_bytes() == before
    write_image(path, good * 2)  # overwrite works
    assert np.array_equal(read_image(path)[0], good * 2)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.exr"]


def test_write_is_deterministic(tmp_path, rng):
    px = rng.random((8, 8, 3)).astype(np.float32)
    for name in ("a.exr", "a.tif", "a.png"):
        write_image(tmp_path / name, px, metadata={"k": 1})
        first = (tmp_path / name).read_bytes()
        write_image(tmp_path / name, px, metadata={"k": 1})
        assert (tmp_path / name).read_bytes() == first


def test_write_argument_errors(tmp_path):
    px = np.zeros((2, 2, 3), np.float32)
    with pytest.raises(ImageFormatError, match="unsupported image extension"):
        write_image(tmp_path / "x.bmp", px)
    with pytest.raises(ImageFormatError):
        write_image(tmp_path / "noext", px)
    with pytest.raises(InvalidInputError, match="pixel_type"):
        write_image(tmp_path / "x.png", px, pixel_type="float")
    with pytest.raises(InvalidInputError, match="pixel_type"):
        write_image(tmp_path / "x.exr", px, pixel_type="uint8")
    with pytest.raises(InvalidInputError, match="exposure"):
        write_image(tmp_path / "x.exr", px, exposure_stops=1.0)
    with pytest.raises(InvalidInputError, match="float dtype"):
        write_image(tmp_path / "x.png", np.zeros((2, 2, 3), np.uint8))
    with pytest.raises(InvalidInputError, match="shape|c in"):
        write_image(tmp_path / "x.exr", np.zeros((2, 2, 2), np.float32))
    with pytest.raises(InvalidInputError):
        write_image(tmp_path / "x.exr", np.zeros((2, 2, 3, 1), np.float32))
    with pytest.raises(FileNotFoundError):
        write_image(tmp_path / "missing_dir" / "x.exr", px)
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------------------------
# Hostile and broken files (docs/hard-cases.md #16)


def test_truncated_exr_raises_quickly(tmp_path, rng):
    path = tmp_path / "t.exr"
    write_image(path, rng.random((256, 256, 3)).astype(np.float32))
    data = path.read_bytes()
    for cut, name in ((len(data) // 2, "half.exr"), (100, "header.exr")):
        bad = tmp_path / name
        bad.write_bytes(data[:cut])
        t0 = time.perf_counter()
        with pytest.raises(ImageFormatError) as exc:
            read_image(bad)
        assert time.perf_counter() - t0 < 2.0
        assert str(bad) in str(exc.value)


def test_truncated_png_raises(tmp_path, rng):
    path = tmp_path / "t.png"
    write_image(path, rng.random((64, 64, 3)).astype(np.float32))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ImageFormatError, match="t.png"):
        read_image(path)


def test_declared_size_checked_before_reading_pixels(tmp_path, rng, monkeypatch):
    path = tmp_path / "small.exr"
    write_image(path, rng.random((20, 30, 3)).astype(np.float32))
    assert read_image(path, max_pixels=600)[0].shape == (20, 30, 3)  # boundary: exactly allowed

    def must_not_run(*args, **kwargs):
        raise AssertionError("pixels were read before the size check")

    monkeypatch.setattr(imageio, "_read_pixels", must_not_run)
    with pytest.raises(ImageFormatError, match="max_pixels=599"):
        read_image(path, max_pixels=599)


def test_header_claiming_huge_image_fails_fast_without_allocating(tmp_path, monkeypatch):
    def must_not_run(*args, **kwargs):
        raise AssertionError("pixels were read")

    monkeypatch.setattr(imageio, "_read_pixels", must_not_run)
    # A 49-byte binary PPM whose header claims 9000 x 9000 (81 M pixels > the 64 M default).
    # OIIO opens it, so it is this module's header check that refuses it.
    ppm = tmp_path / "claims_81M.ppm"
    ppm.write_bytes(b"P6\n9000 9000\n255\n" + bytes(30))
    t0 = time.perf_counter()
    with pytest.raises(ImageFormatError, match="9000x9000.*max_pixels"):
        read_image(ppm)
    assert time.perf_counter() - t0 < 2.0

    # 100k x 100k: as PPM and as a real EXR header with patched data/display windows.
    ppm_huge = tmp_path / "claims_100k.ppm"
    ppm_huge.write_bytes(b"P6\n100000 100000\n255\n" + bytes(30))
    exr = tmp_path / "claims_100k.exr"
    write_image(exr, np.zeros((2, 2, 3), np.float32))
    header = bytearray(exr.read_bytes())
    for attr in (b"dataWindow\x00box2i\x00", b"displayWindow\x00box2i\x00"):
        at = header.index(attr) + len(attr)
        assert struct.unpack_from("<i", header, at)[0] == 16  # attribute size: 4 int32
        struct.pack_into("<4i", header, at + 4, 0, 0, 99_999, 99_999)
    exr.write_bytes(bytes(header))
    for path in (ppm_huge, exr):
        t0 = time.perf_counter()
        with pytest.raises(ImageFormatError, match=path.name):
            read_image(path)
        assert time.perf_counter() - t0 < 2.0


def test_unreadable_files_raise_image_format_error(tmp_path):
    missing = tmp_path / "nope.exr"
    with pytest.raises(ImageFormatError, match="nope.exr"):
        read_image(missing)
    with pytest.raises(ImageFormatError, match="nope.exr"):
        image_info(missing)
    junk = tmp_path / "junk.png"
    junk.write_bytes(b"this is not a png file at all")
    with pytest.raises(ImageFormatError, match="junk.png"):
        read_image(junk)
    unknown = tmp_path / "data.xyz"
    unknown.write_bytes(b"\x00\x01\x02\x03" * 10)
    with pytest.raises(ImageFormatError, match="data.xyz"):
        read_image(unknown)


def test_file_holding_nan_is_refused_on_read(tmp_path):
    px = np.ones((3, 3, 3), np.float32)
    px[1, 1, 1] = np.nan
    px[2, 2, 0] = np.inf
    path = tmp_path / "nan.exr"
    _raw_oiio_write(path, px, oiio.FLOAT)
    with pytest.raises(ImageFormatError, match="2 non-finite"):
        read_image(path)


def test_read_argument_errors(tmp_path):
    path = tmp_path / "a.exr"
    write_image(path, np.zeros((2, 2, 3), np.float32))
    for bad in (0, -1, 1.5, True):
        with pytest.raises(InvalidInputError, match="max_pixels"):
            read_image(path, max_pixels=bad)


def test_image_info_reads_header_only(tmp_path, monkeypatch):
    path = tmp_path / "i.exr"
    write_image(path, np.zeros((5, 7, 4), np.float32), pixel_type="half")
    monkeypatch.setattr(imageio, "_read_pixels", lambda *a, **k: pytest.fail("pixels read"))
    info = image_info(path)
    assert info == {
        "width": 7,
        "height": 5,
        "channels": 4,
        "format": "openexr",
        "pixel_type": "half",
        "channel_names": ["R", "G", "B", "A"],
    }
