"""Compositing a relit object into a plate: rules against a per-pixel reference,
the near-black guard, and a generated object + background pair against ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from engine.errors import InvalidInputError
from engine.reference import ReferenceParams
from engine.relighting.bake import bake_dataset
from engine.relighting.composite import active_region_around, composite, composite_ratio
from engine.relighting.generate import (
    LightPlacement,
    generate_dataset,
    object_mask,
    render_ground_truth,
    scene_without_objects,
)
from engine.relighting.lights import PointLight
from engine.relighting.relight import relight
from engine.scene import CameraParams
from tests.engine.scenes import mat, quad, scene, sphere_mesh

REF = ReferenceParams(spp=1, max_depth=0, seed=0)
CAM = CameraParams("perspective", (0, 3.0, 3.0), (0, 0.3, 0), (0, 1, 0), 32, 32, fov_y_deg=40)


def naive_composite(i_obj, i_bg, plate, om, act, eps=1e-3, eps_abs=1e-8, max_ratio=8.0):
    """Per-pixel loops: the documented rule written out."""
    h, w, _ = plate.shape
    act = act & ~om
    mean = [np.mean([i_bg[y, x, c] for y in range(h) for x in range(w) if act[y, x]]) for c in range(3)]
    out = plate.astype(np.float64).copy()
    for y in range(h):
        for x in range(w):
            if om[y, x]:
                out[y, x] = i_obj[y, x]
            elif act[y, x]:
                for c in range(3):
                    e = max(eps * mean[c], eps_abs)
                    r = (float(i_obj[y, x, c]) + e) / (float(i_bg[y, x, c]) + e)
                    out[y, x, c] = plate[y, x, c] * min(max(r, 0.0), max_ratio)
    return out


def test_rules_match_per_pixel_reference():
    rng = np.random.default_rng(3)
    h, w = 12, 15
    i_bg = rng.uniform(0.0, 1.0, (h, w, 3)).astype(np.float32)
    i_bg[2:5, 3:7] = 0.0  # black background patch
    i_obj = (i_bg * rng.uniform(0.0, 1.5, (h, w, 3))).astype(np.float32)  # shadows (< 1) and brightening (> 1)
    i_obj[3, 4] = 0.7  # lit object next to a black background: clamped
    plate = rng.uniform(0.1, 1.0, (h, w, 3)).astype(np.float32)
    om = np.zeros((h, w), bool)
    om[6:9, 6:10] = True
    act = active_region_around(om, 4) | (np.arange(w)[None, :] < 8) & (np.arange(h)[:, None] < 6)
    out, st = composite(i_obj, i_bg, plate, om, act)
    ref = naive_composite(i_obj, i_bg, plate, om, act)
    assert np.allclose(out, ref, rtol=1e-6, atol=1e-7)
    assert np.array_equal(out[om], i_obj[om])
    keep = ~om & ~act
    assert np.array_equal(out[keep], plate[keep])
    assert st["n_object"] == om.sum() and st["n_active"] == (act & ~om).sum() and st["n_unchanged"] == keep.sum()
    assert st["n_clamped"] >= 1 and st["ratio_max"] == 8.0 and st["n_guarded"] >= 12
    assert st["n_darkened"] > 0 and st["n_brightened"] > 0


def test_near_black_background_never_blows_up():
    h, w = 8, 8
    i_bg = np.zeros((h, w, 3), np.float32)
    i_bg[:, :4] = 1e-30  # denormal-small
    i_obj = np.zeros((h, w, 3), np.float32)
    i_obj[:4] = 5.0  # the object lights a black floor
    plate = np.full((h, w, 3), 0.5, np.float32)
    act = np.ones((h, w), bool)
    out, st = composite(i_obj, i_bg, plate, np.zeros((h, w), bool), act)
    assert np.all(np.isfinite(out))
    r, _ = composite_ratio(i_obj, i_bg, act)
    assert np.all(r <= 8.0) and np.all(r >= 0)
    assert np.all(r[4:] == 1.0)  # 0/0: the plate is kept
    assert np.all(r[:4] == 8.0) and st["n_clamped"] == 32  # x/0: clamped
    assert st["n_guarded"] == 64 and st["eps"] == [1e-8] * 3
    assert np.allclose(out[:4], 4.0) and np.allclose(out[4:], 0.5)
    # all-zero inputs everywhere: the plate comes back unchanged
    z = np.zeros((h, w, 3), np.float32)
    out, _ = composite(z, z, plate, np.zeros((h, w), bool), act)
    assert np.array_equal(out, plate)


def test_pixels_without_data_keep_the_plate():
    """A RelightResult's outside-coverage / singular pixels never enter the ratio."""
    from engine.relighting.relight import RelightResult

    h, w = 6, 7
    i_obj = np.full((h, w, 3), 0.25, np.float32)
    i_bg = np.full((h, w, 3), 0.5, np.float32)
    outside = np.zeros((h, w), bool)
    outside[1, 2] = True
    singular = np.zeros((h, w), bool)
    singular[4, 5] = True
    res = RelightResult(image=i_obj, outside_mask=outside, n_outside=1, singular_mask=singular, n_singular=1,
                        timings={})
    plate = np.full((h, w, 3), 0.8, np.float32)
    om = np.zeros((h, w), bool)
    om[0, 0] = True
    out, st = composite(res, i_bg, plate, om, np.ones((h, w), bool))
    assert st["n_no_data"] == 2 and st["n_active"] == h * w - 1
    assert np.array_equal(out[1, 2], plate[1, 2]) and np.array_equal(out[4, 5], plate[4, 5])
    assert np.allclose(out[2, 2], 0.4, rtol=1e-3)  # 0.8 x 0.25 / 0.5
    assert np.array_equal(out[0, 0], i_obj[0, 0])


def test_validation_names_the_field():
    a = np.zeros((4, 5, 3), np.float32)
    m = np.zeros((4, 5), bool)
    with pytest.raises(InvalidInputError, match="background_relit: size 6x4 differs"):
        composite(a, np.zeros((4, 6, 3)), a, m, m)
    with pytest.raises(InvalidInputError, match="plate: expected an"):
        composite(a, a, np.zeros((4, 5)), m, m)
    with pytest.raises(InvalidInputError, match="object_mask: shape"):
        composite(a, a, a, np.zeros((5, 4), bool), m)
    with pytest.raises(InvalidInputError, match="active_region: shape"):
        composite(a, a, a, m, np.zeros(3, bool))
    with pytest.raises(InvalidInputError, match="plate: contains NaN"):
        composite(a, a, np.full((4, 5, 3), np.nan), m, m)
    with pytest.raises(InvalidInputError, match="max_ratio"):
        composite(a, a, a, m, m, max_ratio=0.5)
    with pytest.raises(InvalidInputError, match="margin_px"):
        active_region_around(m, -1)


@pytest.fixture(scope="module")
def pair():
    """Object dataset (ball on a floor) and background dataset (the floor alone), same lights."""
    parts = [(sphere_mesh((0, 0.5, 0), 0.5, subdivisions=3), mat(name="ball", kd=(0.6, 0.6, 0.6))),
             (quad((0, 0, 0), 3.0), mat(name="floor", kd=(0.5, 0.4, 0.3)))]
    sc = scene(parts)
    ds_obj = generate_dataset(sc, CAM, LightPlacement(region="hemisphere", spacing_deg=10.0), REF)
    bg = scene_without_objects(sc, ["o0"])
    same = LightPlacement.from_dict(ds_obj.meta["resolved_placement"])  # the same lights for the background
    ds_bg = generate_dataset(bg, CAM, same, REF)
    assert np.array_equal(ds_bg.light_positions, ds_obj.light_positions)
    return sc, bg, bake_dataset(ds_obj), bake_dataset(ds_bg), object_mask(sc, CAM, ["o0"])


def test_generated_shadow_darkens_like_ground_truth(pair):
    sc, bg, b_obj, b_bg, om = pair
    c = b_obj.sphere_center
    light = PointLight(tuple(c + [1.2, 2.5, 0.8]), 12.0)
    r_obj, r_bg = relight(b_obj, light), relight(b_bg, light)
    gt_full = render_ground_truth(sc, CAM, light, REF)
    plate = render_ground_truth(bg, CAM, light, REF)  # the plate: the background under the same light
    act = active_region_around(om, 12)
    has_bg = np.zeros(act.size, bool)
    has_bg[b_bg.pixel_index] = True
    act &= has_bg.reshape(act.shape)  # the floor (pixels past its edge have no surface)
    out, st = composite(r_obj, r_bg, plate, om, act)
    assert st["n_no_data"] == 0 and st["n_clamped"] == 0
    assert np.array_equal(out[om], r_obj.image[om])
    assert np.array_equal(out[~om & ~act], plate[~om & ~act])
    # the ground-truth ratio: the full scene over the background alone
    r_gt = gt_full[..., 1] / np.maximum(plate[..., 1], 1e-12)
    shadow = act & (r_gt < 0.3)
    lit = act & (r_gt > 0.95)
    assert shadow.sum() >= 10 and lit.sum() >= 10
    r, _ = composite_ratio(r_obj, r_bg, act)
    assert r[shadow, 1].mean() < 0.35 and out[shadow, 1].mean() < 0.4 * plate[shadow, 1].mean()
    assert np.abs(r[lit, 1] - 1.0).mean() < 0.03
    # R follows the ground-truth ratio (interpolation error only at the shadow's edge)
    dr = np.abs(r[act, 1] - r_gt[act])
    assert dr.mean() < 0.05 and np.median(dr) < 0.01
    # and the composite matches the ground-truth render of the full scene in the active region
    err = np.abs(out[act] - gt_full[act]).mean() / gt_full[act].mean()
    assert err < 0.05, err
