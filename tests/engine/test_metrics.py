"""Tests for engine.metrics against slow, obvious per-pixel loops (docs/algorithms.md "Shared
conventions", error metric)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from engine import metrics
from engine.errors import InvalidInputError
from engine.imageio import read_image, srgb_decode, srgb_encode, write_image
from engine.metrics import (
    ErrorReport,
    compare,
    error_heatmap,
    error_heatmap_display,
    fraction_over,
    lrms,
    luminance,
    psnr_tonemapped,
    rmse_per_channel,
)

# ---------------------------------------------------------------------------------------------
# Naive references: explicit loops, Python floats, nothing shared with the module.


def _naive_y(img, i, j):
    p = img[i, j]
    if np.ndim(p) == 0:
        return float(p)
    if len(p) == 1:
        return float(p[0])
    return 0.2126 * float(p[0]) + 0.7152 * float(p[1]) + 0.0722 * float(p[2])


def _pixels(shape, mask):
    h, w = shape[:2]
    return [(i, j) for i in range(h) for j in range(w) if mask is None or mask[i, j]]


def _naive_lrms(test, ref, mask=None):
    pix = _pixels(ref.shape, mask)
    sq = sum((_naive_y(test, i, j) - _naive_y(ref, i, j)) ** 2 for i, j in pix)
    mean = sum(_naive_y(ref, i, j) for i, j in pix) / len(pix)
    return math.sqrt(sq / len(pix)) / mean


def _naive_rmse(test, ref, mask=None):
    pix = _pixels(ref.shape, mask)
    out = []
    for ch in range(ref.shape[2]):
        sq = sum((float(test[i, j, ch]) - float(ref[i, j, ch])) ** 2 for i, j in pix)
        out.append(math.sqrt(sq / len(pix)))
    return out


def _naive_tonemap(x, stops):
    v = min(max(x * 2.0**stops, 0.0), 1.0)
    return 12.92 * v if v <= 0.0031308 else 1.055 * v ** (1 / 2.4) - 0.055


def _naive_psnr(test, ref, stops=0.0, mask=None):
    pix = _pixels(ref.shape, mask)
    nch = min(ref.shape[2], 3)
    sq = 0.0
    for i, j in pix:
        for ch in range(nch):
            d = _naive_tonemap(float(test[i, j, ch]), stops) - _naive_tonemap(float(ref[i, j, ch]), stops)
            sq += d * d
    mse = sq / (len(pix) * nch)
    return math.inf if mse == 0 else 10 * math.log10(1.0 / mse)


def _naive_fraction_over(test, ref, thr, mask=None):
    pix = _pixels(ref.shape, mask)
    mean = sum(_naive_y(ref, i, j) for i, j in pix) / len(pix)
    over = sum(1 for i, j in pix if abs(_naive_y(test, i, j) - _naive_y(ref, i, j)) > thr * mean)
    return over / len(pix)


@pytest.fixture
def pair():
    rng = np.random.default_rng(7)
    ref = rng.uniform(0.05, 2.0, size=(6, 5, 3))
    test = ref * rng.uniform(0.85, 1.15, size=ref.shape) + rng.normal(0, 0.02, size=ref.shape)
    mask = rng.random((6, 5)) > 0.3
    mask[0, 0] = True
    return test, ref, mask


# ---------------------------------------------------------------------------------------------
# luminance


def test_luminance_weights_and_passthrough():
    img = np.zeros((1, 3, 3))
    img[0, 0, 0] = img[0, 1, 1] = img[0, 2, 2] = 1.0
    np.testing.assert_allclose(luminance(img)[0], [0.2126, 0.7152, 0.0722], rtol=1e-15)
    rng = np.random.default_rng(0)
    rgb = rng.random((4, 3, 3))
    y = luminance(rgb)
    assert y.shape == (4, 3) and y.dtype == np.float64
    for i in range(4):
        for j in range(3):
            assert y[i, j] == pytest.approx(_naive_y(rgb, i, j), rel=1e-14)
    grey = rng.random((4, 3)).astype(np.float32)
    assert np.array_equal(luminance(grey), grey.astype(np.float64))
    assert np.array_equal(luminance(grey[..., None]), grey.astype(np.float64))
    rgba = np.concatenate([rgb, np.full((4, 3, 1), 123.0)], axis=2)
    np.testing.assert_allclose(luminance(rgba), y, rtol=1e-15)  # alpha ignored


# ---------------------------------------------------------------------------------------------
# the metrics against the loops


@pytest.mark.parametrize("use_mask", [False, True])
def test_metrics_match_naive_loops(pair, use_mask):
    test, ref, mask = pair
    m = mask if use_mask else None
    assert lrms(test, ref, m) == pytest.approx(_naive_lrms(test, ref, m), rel=1e-12)
    np.testing.assert_allclose(rmse_per_channel(test, ref, m), _naive_rmse(test, ref, m), rtol=1e-12)
    for stops in (0.0, -1.0, 1.5):
        got = psnr_tonemapped(test, ref, exposure_stops=stops, mask=m)
        assert got == pytest.approx(_naive_psnr(test, ref, stops, m), rel=1e-12)
    for thr in (0.0, 0.05, 0.2):
        assert fraction_over(test, ref, thr, m) == _naive_fraction_over(test, ref, thr, m)
    # the fixture is built so that the 5 % fraction is strictly between 0 and 1
    assert 0.0 < fraction_over(test, ref, mask=m) < 1.0


def test_metrics_on_single_channel_and_float32(pair):
    test, ref, mask = pair
    t1, r1 = test[..., 1], ref[..., 1]
    assert lrms(t1, r1, mask) == pytest.approx(_naive_lrms(t1[..., None], r1[..., None], mask), rel=1e-12)
    assert rmse_per_channel(t1, r1).shape == (1,)
    # float32 input is accumulated in float64: same as converting first
    t32, r32 = test.astype(np.float32), ref.astype(np.float32)
    assert lrms(t32, r32) == lrms(t32.astype(np.float64), r32.astype(np.float64))


def test_rgba_psnr_ignores_alpha_rmse_reports_it(pair):
    test, ref, _ = pair
    a_t = np.concatenate([test, np.zeros(test.shape[:2] + (1,))], axis=2)
    a_r = np.concatenate([ref, np.ones(ref.shape[:2] + (1,))], axis=2)
    assert psnr_tonemapped(a_t, a_r) == pytest.approx(psnr_tonemapped(test, ref), rel=1e-14)
    assert lrms(a_t, a_r) == pytest.approx(lrms(test, ref), rel=1e-14)
    assert rmse_per_channel(a_t, a_r)[3] == pytest.approx(1.0)


def test_hand_computed_two_pixel_case():
    ref = np.array([[[1.0, 1.0, 1.0], [3.0, 3.0, 3.0]]])  # Y = 1 and 3, mean 2
    test = np.array([[[1.0, 1.0, 1.0], [3.2, 3.2, 3.2]]])  # dY = 0 and 0.2
    assert lrms(test, ref) == pytest.approx(math.sqrt(0.2**2 / 2) / 2.0, rel=1e-12)
    np.testing.assert_allclose(rmse_per_channel(test, ref), [math.sqrt(0.02)] * 3, rtol=1e-12)
    # 0.2 > 0.05 * 2 -> one of two pixels over
    assert fraction_over(test, ref) == 0.5
    # strictly greater, checked with exactly representable grey values: |dY| = 0.25 = 0.125 * 2
    assert fraction_over(np.array([[1.0, 3.25]]), np.array([[1.0, 3.0]]), threshold=0.125) == 0.0
    assert fraction_over(np.array([[1.0, 3.25]]), np.array([[1.0, 3.0]]), threshold=0.124) == 0.5
    # both saturate at exposure 0 -> identical tone-mapped images
    assert psnr_tonemapped(test, ref) == math.inf
    assert math.isfinite(psnr_tonemapped(test, ref, exposure_stops=-2.0))


def test_identical_images():
    rng = np.random.default_rng(3)
    img = rng.random((5, 4, 3))
    assert lrms(img, img) == 0.0
    assert psnr_tonemapped(img, img) == math.inf
    assert fraction_over(img, img) == 0.0
    assert np.array_equal(rmse_per_channel(img, img), np.zeros(3))
    report = compare(img, img.copy())
    assert report.lrms == 0.0 and report.psnr == math.inf and report.n_pixels == 20


def test_masked_pixels_are_ignored(pair):
    test, ref, mask = pair
    t2, r2 = test.copy(), ref.copy()
    t2[~mask] = 1e9
    r2[~mask] = 40.0
    assert lrms(t2, r2, mask) == lrms(test, ref, mask)
    assert np.array_equal(rmse_per_channel(t2, r2, mask), rmse_per_channel(test, ref, mask))
    assert psnr_tonemapped(t2, r2, mask=mask) == psnr_tonemapped(test, ref, mask=mask)
    assert fraction_over(t2, r2, mask=mask) == fraction_over(test, ref, mask=mask)
    assert compare(t2, r2, mask) == compare(test, ref, mask)
    # and they do matter without the mask
    assert lrms(t2, r2) != lrms(test, ref, mask)


def test_black_reference_decisions():
    ref = np.zeros((2, 2, 3))
    assert lrms(ref, ref) == 0.0
    test = ref.copy()
    test[0, 0] = 0.1
    assert lrms(test, ref) == math.inf
    assert fraction_over(test, ref) == 0.25  # any non-zero error counts
    heat = error_heatmap(test, ref)
    np.testing.assert_allclose(srgb_encode(heat[0, 0].astype(np.float64)), metrics._VIRIDIS[-1], atol=1e-5)
    np.testing.assert_allclose(srgb_encode(heat[1, 1].astype(np.float64)), metrics._VIRIDIS[0], atol=1e-5)
    assert compare(test, ref).to_dict()["lrms"] == "inf"


def test_negative_reference_mean_refused():
    ref = -np.ones((2, 2, 3))
    with pytest.raises(InvalidInputError, match="negative"):
        lrms(ref * 0.5, ref)


# ---------------------------------------------------------------------------------------------
# validation


@pytest.mark.parametrize(
    "func", [lrms, rmse_per_channel, psnr_tonemapped, fraction_over, error_heatmap, compare]
)
def test_validation(func):
    a = np.ones((3, 4, 3))
    with pytest.raises(InvalidInputError, match="same shape"):
        func(a, np.ones((4, 3, 3)))
    with pytest.raises(InvalidInputError, match="same shape"):
        func(a, np.ones((3, 4, 1)))
    with pytest.raises(InvalidInputError, match="mask selects no pixels"):
        func(a, a, mask=np.zeros((3, 4), bool))
    with pytest.raises(InvalidInputError, match="mask must have shape"):
        func(a, a, mask=np.ones((4, 3), bool))
    with pytest.raises(InvalidInputError, match="bool"):
        func(a, a, mask=np.ones((3, 4), np.uint8))
    bad = a.copy()
    bad[1, 1, 1] = np.nan
    bad[2, 2, 2] = np.inf
    with pytest.raises(InvalidInputError, match="2 non-finite"):
        func(bad, a)
    with pytest.raises(InvalidInputError, match="non-finite"):
        func(a, bad)
    with pytest.raises(InvalidInputError, match="c in 1, 3, 4"):
        func(np.ones((3, 4, 2)), np.ones((3, 4, 2)))
    with pytest.raises(InvalidInputError):
        func(np.ones(5), np.ones(5))
    with pytest.raises(InvalidInputError, match="numeric"):
        func(np.full((3, 4, 3), "x"), a)


def test_threshold_and_scale_validation():
    a = np.ones((2, 2, 3))
    with pytest.raises(InvalidInputError):
        fraction_over(a, a, threshold=-0.1)
    with pytest.raises(InvalidInputError):
        fraction_over(a, a, threshold=float("nan"))
    for scale in (0.0, -1.0, float("inf")):
        with pytest.raises(InvalidInputError):
            error_heatmap(a, a, scale=scale)
    with pytest.raises(InvalidInputError):
        psnr_tonemapped(a, a, exposure_stops=float("nan"))


# ---------------------------------------------------------------------------------------------
# heat map


def test_heatmap_shape_range_mask_and_values(pair):
    test, ref, mask = pair
    heat = error_heatmap(test, ref, mask=mask)
    assert heat.shape == (6, 5, 3) and heat.dtype == np.float32
    assert heat.min() >= 0.0 and heat.max() <= 1.0
    assert np.all(heat[~mask] == 0.0)
    assert np.all(heat[mask].max(axis=1) > 0.0)  # viridis is never black

    # explicit check of a pixel against the loop-level definition
    pix = _pixels(ref.shape, mask)
    mean = sum(_naive_y(ref, i, j) for i, j in pix) / len(pix)
    table = metrics._VIRIDIS
    for i, j in pix:
        v = min(abs(_naive_y(test, i, j) - _naive_y(ref, i, j)) / mean, 1.0)
        k = min(int(v * 16), 15)
        f = v * 16 - k
        expected = [(1 - f) * table[k][ch] + f * table[k + 1][ch] for ch in range(3)]
        np.testing.assert_allclose(srgb_encode(heat[i, j].astype(np.float64)), expected, atol=1e-5)


def test_heatmap_scale_and_ordering():
    ref = np.ones((1, 6, 3))
    test = ref + np.array([0.0, 0.01, 0.05, 0.1, 0.5, 2.0])[None, :, None]
    heat = error_heatmap(test, ref, scale=0.1)
    encoded = srgb_encode(heat.astype(np.float64))
    np.testing.assert_allclose(encoded[0, 0], metrics._VIRIDIS[0], atol=1e-5)
    for j in (3, 4, 5):  # error >= scale saturates at the top colour
        np.testing.assert_allclose(encoded[0, j], metrics._VIRIDIS[-1], atol=1e-5)
    # perceptual ordering: luminance of the displayed colour increases with the error
    y = luminance(encoded)[0]
    assert np.all(np.diff(y[:4]) > 0)


def test_heatmap_written_as_png_shows_the_palette(tmp_path):
    ref = np.ones((1, 17, 3))
    test = ref + np.linspace(0.0, 1.0, 17)[None, :, None]
    heat = error_heatmap(test, ref)
    write_image(tmp_path / "heat.png", heat)
    codes, _ = read_image(tmp_path / "heat.png", transfer="linear")
    np.testing.assert_allclose(codes[0], np.rint(metrics._VIRIDIS * 255) / 255, atol=1.01 / 255)
    np.testing.assert_allclose(srgb_decode(codes[0].astype(np.float64)), heat[0], atol=0.01)


def test_heatmap_display_values_are_the_palette(pair):
    test, ref, mask = pair
    disp = error_heatmap_display(test, ref, mask=mask)
    assert disp.shape == (6, 5, 3) and disp.dtype == np.float64
    assert np.all(disp[~mask] == 0.0) and disp.min() >= 0.0 and disp.max() <= 1.0
    # the linear heatmap is exactly their decoding; the display values are the viridis colours
    np.testing.assert_array_equal(error_heatmap(test, ref, mask=mask), srgb_decode(disp).astype(np.float32))
    ends = error_heatmap_display(np.ones((1, 2, 3)) + [[[0.0], [5.0]]], np.ones((1, 2, 3)))
    np.testing.assert_array_equal(ends[0], metrics._VIRIDIS[[0, -1]])
    with pytest.raises(InvalidInputError):
        error_heatmap_display(test, ref, scale=0.0)


def test_viridis_table_is_perceptually_ordered():
    y = luminance(metrics._VIRIDIS[None].astype(np.float64))[0]
    assert np.all(np.diff(y) > 0)


# ---------------------------------------------------------------------------------------------
# compare / ErrorReport


def test_compare_matches_individual_metrics_and_is_json_safe(pair):
    test, ref, mask = pair
    report = compare(test, ref, mask, exposure_stops=-1.0)
    assert isinstance(report, ErrorReport)
    assert report.lrms == pytest.approx(lrms(test, ref, mask), rel=1e-15)
    assert report.rmse == tuple(rmse_per_channel(test, ref, mask))
    assert all(type(x) is float for x in report.rmse)
    assert report.psnr == pytest.approx(psnr_tonemapped(test, ref, exposure_stops=-1.0, mask=mask), rel=1e-15)
    assert report.fraction_over_5pct == fraction_over(test, ref, 0.05, mask)
    assert report.n_pixels == int(mask.sum())
    with pytest.raises(AttributeError):
        report.lrms = 0.0  # frozen

    d = report.to_dict()
    assert json.loads(json.dumps(d, allow_nan=False)) == d
    assert d["n_pixels"] == report.n_pixels and d["rmse"] == list(report.rmse)

    same = compare(ref, ref).to_dict()
    assert same["psnr"] == "inf" and same["lrms"] == 0.0
    json.dumps(same, allow_nan=False)
    assert float(same["psnr"]) == math.inf
