"""engine.imageio fast paths: in-memory encoding (``encode_image``), lossless codec choice
(``compression=``) and the exact 8-bit sRGB code thresholds, each against the slow obvious path."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest

from engine import imageio
from engine.errors import InvalidInputError, NonFiniteOutputError
from engine.imageio import COMPRESSIONS, encode_image, read_image, tonemap_srgb, write_image


def _srgb8_scalar(x: float) -> int:
    """Code value written out once more with math.pow, independently of the module."""
    c = min(max(x, 0.0), 1.0)
    v = 12.92 * c if c <= 0.0031308 else 1.055 * math.pow(c, 1.0 / 2.4) - 0.055
    return int(math.floor(v * 255 + 0.5))


def _read_bytes(tmp_path: Path, name: str, data: bytes, **kw: object) -> tuple[np.ndarray, dict]:
    p = tmp_path / name
    p.write_bytes(data)
    return read_image(p, **kw)  # type: ignore[arg-type]


def _hostile_floats(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    """float32 samples over the whole range: signs, subnormals, huge values, exact zeros, -0.0."""
    x = (rng.standard_normal(shape) * np.exp2(rng.integers(-140, 120, shape))).astype(np.float32)
    flat = x.reshape(-1)
    flat[:7] = [0.0, -0.0, np.float32(1e-45), np.finfo(np.float32).max, -np.finfo(np.float32).max, 1.0, 65504.0]
    return x


# --------------------------------------------------------------------------------------------- exact sRGB


def test_srgb8_thresholds_are_exactly_the_code_boundaries() -> None:
    t = imageio._srgb8_thresholds()
    assert t.shape == (255,) and np.all(np.diff(t) > 0) and t[0] > 0 and t[-1] <= 1.0
    ref = np.rint(tonemap_srgb(t) * 255)
    below = np.rint(tonemap_srgb(np.nextafter(t, 0.0)) * 255)
    np.testing.assert_array_equal(ref, np.arange(1, 256))
    np.testing.assert_array_equal(below, np.arange(0, 255))


@pytest.mark.parametrize("exposure", [0.0, 1.0, -2.5, 0.37, 40.0, -64.0])
def test_fast_8bit_codes_equal_the_float64_reference(exposure: float) -> None:
    rng = np.random.default_rng(7)
    t = imageio._srgb8_thresholds() / 2.0**exposure
    edges = np.concatenate([t, np.nextafter(t, 0), np.nextafter(t, 2), [0.0, -0.0, 1.0, 5e-324, -1.0, 3.0]])
    px = np.concatenate([edges.astype(np.float32), rng.uniform(-0.2, 1.3, 200_000).astype(np.float32),
                         rng.exponential(0.01, 100_000).astype(np.float32), _hostile_floats(rng, (5000,))])
    for arr in (px.reshape(-1, 1, 1), px[: (px.size // 3) * 3].reshape(-1, 1, 3)):
        ref = np.rint(tonemap_srgb(arr, exposure) * 255).astype(np.uint8)
        got = imageio._srgb8_codes(arr, exposure)
        assert got.dtype == np.uint8
        np.testing.assert_array_equal(got, ref)
    # and the independent scalar formula agrees within one code value (float rounding only)
    sample = px[:20_000]
    got = imageio._srgb8_codes(sample.reshape(-1, 1, 1), exposure).ravel()
    scalar = np.array([_srgb8_scalar(float(x) * 2.0**exposure) for x in sample])
    assert int(np.max(np.abs(got.astype(int) - scalar))) <= 1


def test_written_png_codes_equal_the_reference_tonemap(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    px = rng.uniform(-0.1, 1.4, (33, 47, 3)).astype(np.float32)
    for exposure in (0.0, -1.25):
        write_image(tmp_path / "a.png", px, exposure_stops=exposure)
        inp = oiio.ImageInput.open(str(tmp_path / "a.png"))
        codes = inp.read_image(oiio.UINT8)
        inp.close()
        np.testing.assert_array_equal(codes, np.rint(tonemap_srgb(px, exposure) * 255).astype(np.uint8))


# ---------------------------------------------------------------------------------------- encode_image


@pytest.mark.parametrize("name,pixel_type", [("r.exr", None), ("r.exr", "half"), ("r.png", None), ("r.png", "uint16"),
                                              ("r.tif", None), ("r.jpg", None)])
def test_encode_image_gives_the_bytes_write_image_writes(tmp_path: Path, name: str, pixel_type: str | None) -> None:
    rng = np.random.default_rng(11)
    px = rng.uniform(0, 1.2, (20, 31, 3)).astype(np.float32)
    meta = {"camera": {"eye": [0.1, 2.0, 3.0]}, "scene_id": "s" * 64, "n": 3}
    write_image(tmp_path / name, px, pixel_type=pixel_type, metadata=meta)
    data = encode_image(name, px, pixel_type=pixel_type, metadata=meta)
    assert data == (tmp_path / name).read_bytes()
    assert encode_image(name, px, pixel_type=pixel_type, metadata=meta) == data  # deterministic


def test_encode_image_checks_like_write_image() -> None:
    bad = np.zeros((4, 4, 3), np.float32)
    bad[1, 2, 0] = np.nan
    with pytest.raises(NonFiniteOutputError, match="1 non-finite"):
        encode_image("x.exr", bad)
    with pytest.raises(InvalidInputError, match="float16 range"):
        encode_image("x.exr", np.full((2, 2), 1e6, np.float32), pixel_type="half")
    with pytest.raises(InvalidInputError, match="metadata key"):
        encode_image("x.png", np.zeros((2, 2), np.float32), metadata={"_x": 1})


@pytest.mark.parametrize("compression", COMPRESSIONS["openexr"])
@pytest.mark.parametrize("channels", [1, 3, 4])
def test_every_exr_codec_round_trips_float32_bit_exact(tmp_path: Path, compression: str, channels: int) -> None:
    px = _hostile_floats(np.random.default_rng(channels), (37, 53, channels))
    data = encode_image("r.exr", px, compression=compression, metadata={"aov": "depth"})
    back, meta = _read_bytes(tmp_path, f"r-{compression}.exr", data)
    assert meta == {"aov": "depth"}
    np.testing.assert_array_equal(back.view(np.uint32), px.view(np.uint32))  # bits, so -0.0 and subnormals too
    inp = oiio.ImageInput.open(str(tmp_path / f"r-{compression}.exr"))
    assert inp.spec().get_string_attribute("compression") == compression
    inp.close()


@pytest.mark.parametrize("compression", ["default", "fast"])
def test_png_codecs_store_the_same_codes(tmp_path: Path, compression: str) -> None:
    px = np.random.default_rng(5).uniform(0, 1, (40, 24, 3)).astype(np.float32)
    data = encode_image("p.png", px, compression=compression)
    back, _ = _read_bytes(tmp_path, "p.png", data, transfer="linear")
    np.testing.assert_array_equal(np.rint(back * 255).astype(np.uint8),
                                  np.rint(tonemap_srgb(px) * 255).astype(np.uint8))


def test_fast_png_is_smaller_work_not_different_pixels() -> None:
    px = np.random.default_rng(9).uniform(0, 1, (64, 64, 3)).astype(np.float32)
    assert encode_image("p.png", px, compression="fast") != encode_image("p.png", px)  # other zlib settings
    assert encode_image("p.png", px, compression="default") == encode_image("p.png", px)


@pytest.mark.parametrize("name,compression", [("x.exr", "dwaa"), ("x.exr", "b44"), ("x.png", "zip"),
                                              ("x.jpg", "fast"), ("x.hdr", "zip"), ("x.tif", "rle")])
def test_lossy_or_unknown_codecs_are_refused_with_the_choices(name: str, compression: str) -> None:
    with pytest.raises(InvalidInputError, match="compression .* is not available") as exc:
        encode_image(name, np.zeros((2, 2, 3), np.float32), compression=compression)
    allowed = COMPRESSIONS.get({"x.exr": "openexr", "x.png": "png", "x.tif": "tiff"}.get(name, ""), ())
    for choice in allowed:
        assert choice in str(exc.value)


# ---------------------------------------------------------------------------------------- decode_image


@pytest.mark.parametrize("name,pixel_type", [("r.exr", None), ("r.exr", "half"), ("r.png", None), ("r.png", "uint16"),
                                              ("r.tif", None), ("r.jpg", None)])
def test_decode_image_reads_bytes_like_read_image(tmp_path: Path, name: str, pixel_type: str | None) -> None:
    rng = np.random.default_rng(5)
    px = rng.uniform(0, 1.2, (9, 14, 3)).astype(np.float32)
    meta = {"camera": {"eye": [0.1, 2.0, 3.0]}, "n": 3}
    write_image(tmp_path / name, px, pixel_type=pixel_type, metadata=meta)
    data = (tmp_path / name).read_bytes()
    for transfer in ("auto", "linear"):
        want, want_meta = read_image(tmp_path / name, transfer=transfer)
        got, got_meta = imageio.decode_image(name, data, transfer=transfer)
        assert got.dtype == np.float32
        np.testing.assert_array_equal(got, want)
        assert got_meta == want_meta


def test_decode_image_errors_name_the_image_and_leave_no_scratch_file() -> None:
    before = set(imageio._scratch_dir().glob("ibr-decode-*"))
    with pytest.raises(imageio.ImageFormatError, match="radiance.exr") as err:
        imageio.decode_image("radiance.exr", b"not an image")
    assert "ibr-decode-" not in str(err.value)
    with pytest.raises(imageio.ImageFormatError, match="unsupported image extension"):
        imageio.decode_image("radiance.xyz", encode_image("r.exr", np.zeros((2, 2, 3), np.float32)))
    big = encode_image("r.exr", np.zeros((4, 5, 3), np.float32))
    with pytest.raises(imageio.ImageFormatError, match="max_pixels"):
        imageio.decode_image("big.exr", big, max_pixels=19)
    assert set(imageio._scratch_dir().glob("ibr-decode-*")) == before


@pytest.mark.parametrize("channels", [1, 3, 4])
@pytest.mark.parametrize("exposure", [0.0, -1.5, 2.0])
def test_encode_display_is_what_the_png_stores(tmp_path: Path, channels: int, exposure: float) -> None:
    rng = np.random.default_rng(9)
    px = rng.uniform(-0.1, 1.4, (7, 12, channels)).astype(np.float32)
    if channels == 4:
        px[..., 3] = rng.uniform(0, 1, (7, 12)) * (rng.uniform(size=(7, 12)) > 0.2)
        px[..., :3] *= px[..., 3:]
    codes = imageio.encode_display(px, exposure, 255)
    (tmp_path / "a.png").write_bytes(encode_image("a.png", px, exposure_stops=exposure))
    assert codes.dtype == np.float64 and codes.shape == px.shape
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # the stored (straight) samples
    inp = oiio.ImageInput.open(str(tmp_path / "a.png"), config)
    stored = inp.read_image(oiio.UINT8)
    inp.close()
    np.testing.assert_array_equal(codes.astype(np.uint8), np.asarray(stored).reshape(px.shape))




def test_imageio_and_metrics_import_without_numba() -> None:
    """The API process decodes and measures images with these modules and never loads numba; the
    compiled 8-bit loop is imported on first use only."""
    import subprocess
    import sys

    code = ("import sys, numpy as np, engine.imageio as io, engine.metrics\n"
            "assert 'numba' not in sys.modules\n"
            "data = io.encode_image('x.exr', np.ones((2, 3, 3), np.float32))\n"
            "io.decode_image('x.exr', data); engine.metrics.error_heatmap(np.ones((2, 3)), np.ones((2, 3)))\n"
            "assert 'numba' not in sys.modules, 'float output and metrics need no numba'\n"
            "io.encode_image('x.png', np.ones((2, 3, 3), np.float32))\n"
            "print('numba' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
    assert out.stdout.strip() == "True"  # the 8-bit PNG path loaded the kernel
