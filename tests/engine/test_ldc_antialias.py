"""Edge antialiasing of the LDC renderer (``render(..., supersample=s, antialias="edges")``):
the pixels it refines come close to uniform supersampling's radiance, every other pixel keeps
the one-sample render's bit for bit, and a hard edge's error against a jittered reference
drops to uniform supersampling's."""

from __future__ import annotations

import numpy as np
import pytest

from engine.errors import InvalidInputError
from engine.metrics import lrms
from engine.newviews.effects import analyze
from engine.newviews.ldc import bake_ldc
from engine.newviews.llf import bake_llf
from engine.newviews.renderer import EDGE_CONTRAST, LDCViewRenderer
from engine.raycast import EmbreeCaster
from engine.reference import ReferenceParams, render_reference
from engine.scene import CameraParams
from tests.engine.scenes import mat, quad, scene
from tests.engine.test_ldc_render import LLF_PARAMS, _shiny_scene

CAM = CameraParams("perspective", (2.0, 1.5, 3.5), (0.0, 0.0, 0.0), (0, 1, 0), 40, 32, 45.0)


def _edges_slow(r, rel_depth: float, contrast: float) -> np.ndarray:
    """The edge pixels of a one-sample render, written out plainly (the renderer's criterion:
    a 3 x 3 neighbour with another object, a relative depth jump, or a luminance step)."""
    ids, dep = r.object_id, r.depth.astype(np.float64)
    y = r.radiance.astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722])
    cov = ids >= 0
    y_mean = y[cov].mean()
    H, W = ids.shape
    out = np.zeros((H, W), bool)
    for py in range(H):
        for px in range(W):
            for qy in range(max(0, py - 1), min(H, py + 2)):
                for qx in range(max(0, px - 1), min(W, px + 2)):
                    if ids[qy, qx] != ids[py, px]:
                        out[py, px] = True
                    elif ids[py, px] >= 0 and abs(dep[qy, qx] - dep[py, px]) > rel_depth * min(dep[qy, qx],
                                                                                                dep[py, px]):
                        out[py, px] = True
                    elif abs(y[qy, qx] - y[py, px]) > contrast * max(y[qy, qx], y[py, px], y_mean):
                        out[py, px] = True
    return out


@pytest.fixture(scope="module")
def shiny():
    """The renderer of test_ldc_render's shiny scene at a coarser LDC (48: samples about as far
    apart as this camera's pixels) and LLF."""
    sc = _shiny_scene()
    caster = EmbreeCaster(sc)
    return LDCViewRenderer(sc, bake_ldc(sc, caster, 48), bake_llf(sc, caster, 2, 16, params=LLF_PARAMS))


@pytest.mark.parametrize("method", ["ldc", "ldc+llf", "ldc+ibrt:1"])
def test_edges_reproduce_uniform_supersampling_and_keep_the_rest(shiny, method):
    r = shiny
    one = r.render(CAM, method)
    edge = _edges_slow(one, r.silhouette_rel_depth, EDGE_CONTRAST)
    assert 0.05 < edge.mean() < 0.7  # the test scene has edges and an interior
    for s in (2, 3):
        uni = r.render(CAM, method, supersample=s)
        ada = r.render(CAM, method, supersample=s, antialias="edges")
        assert ada.counts["edge_pixels"] == int(edge.sum())
        assert ada.counts["edge_subpixels"] == s * s * int(edge.sum())
        assert ada.plan["antialias"] == "edges" and ada.plan["supersample"] == s
        # the refined pixels come close to uniform supersampling's radiance: the same sub-pixel
        # rays, but each shows the nearest sample on the surface it crosses instead of the
        # winner of a finer warp (measured: LRMS 0.03-0.05 against uniform on these pixels,
        # the one-sample render's 0.15-0.30)
        e_ada, e_one = lrms(ada.radiance[edge], uni.radiance[edge]), lrms(one.radiance[edge], uni.radiance[edge])
        print(f"{method} ss{s}: LRMS against uniform on the edge pixels: edges {e_ada:.4f}, one sample {e_one:.4f}")
        assert e_ada < 0.4 * e_one
        # every other pixel, and every AOV, is the one-sample render's, bit for bit
        assert np.array_equal(ada.radiance[~edge], one.radiance[~edge])
        for k in ("depth", "normal", "object_id", "material_id", "provenance", "hole_mask"):
            assert np.array_equal(getattr(ada, k), getattr(one, k)), k
    # supersample=1 is the one-sample render whatever the mode
    assert np.array_equal(r.render(CAM, method, antialias="edges").radiance, one.radiance)


def test_antialias_arguments_are_checked(shiny):
    for kw in ({"antialias": "adaptive"}, {"antialias": None}, {"edge_contrast": 0.0}, {"edge_contrast": 1.5},
               {"edge_contrast": True}, {"edge_contrast": "0.1"}):
        with pytest.raises(InvalidInputError, match=next(iter(kw))):
            shiny.render(CAM, "ldc", supersample=2, **kw)


def test_edges_lower_the_error_of_a_hard_edge():
    """A bright square in front of a dark wall, lit by a point light that casts the square's
    shadow on the wall: silhouettes and a shadow edge, nothing else. Against the reference's
    box-filtered image (64 jittered samples per pixel) the edge mode at 4 x 4 is about as good
    as uniform 4 x 4 supersampling and much better than one sample per pixel."""
    sc = scene([(quad((0.0, 0.0, -1.0), 4.0, normal_axis=2), mat("wall", kd=(0.3, 0.3, 0.3))),
                (quad((0.1, 0.05, 0.0), 1.2, normal_axis=2), mat("square", kd=(0.9, 0.8, 0.7)))],
               [dict(type="point", position=(0.8, 0.9, 3.0), intensity=(6.0, 6.0, 6.0))],
               ambient=(0.01, 0.01, 0.01), background=(0.0, 0.0, 0.0))
    caster = EmbreeCaster(sc)
    plan = analyze(sc)
    ldc = bake_ldc(sc, caster, 64, plan=plan)
    r = LDCViewRenderer(sc, ldc, None, plan)
    cam = CameraParams("perspective", (0.7, 0.5, 3.0), (0.0, 0.0, -0.5), (0.1, 1.0, 0.0), 48, 48, 45.0)
    ref = render_reference(sc, cam, ReferenceParams(spp=64, max_depth=0, seed=3))
    m = ref.object_id >= 0
    e1 = lrms(r.render(cam, "ldc").radiance, ref.radiance, m)
    e_uni = lrms(r.render(cam, "ldc", supersample=4).radiance, ref.radiance, m)
    ada = r.render(cam, "ldc", supersample=4, antialias="edges")
    e_ada = lrms(ada.radiance, ref.radiance, m)
    print(f"LRMS ss1 {e1:.4f}, uniform ss4 {e_uni:.4f}, edges ss4 {e_ada:.4f}, "
          f"edge pixels {ada.counts['edge_pixels']} of {48 * 48}")
    assert ada.counts["edge_pixels"] < 0.35 * 48 * 48
    assert e_ada < 0.6 * e1
    assert e_ada < 1.15 * e_uni


def test_edges_progress_and_plan(shiny):
    seen = []
    res = shiny.render(CAM, "ldc+ibrt:1", supersample=2, antialias="edges", progress=lambda f, s: seen.append(f))
    assert seen == sorted(seen) and seen[-1] == 1.0
    assert res.plan["antialias"] == "edges" and res.plan["edge_contrast"] == 0.05
    assert res.counts["edge_subpixels"] == 4 * res.counts["edge_pixels"] > 0
    assert shiny.render(CAM, "ldc", supersample=2).plan["antialias"] == "uniform"


@pytest.mark.parametrize("fill", ["ibrt", "raycast", "none"])
def test_edges_with_other_fills_and_an_orthographic_camera(shiny, fill):
    cam = CameraParams("orthographic", (2.0, 1.5, 3.5), (0.0, 0.0, 0.0), (0, 1, 0), 36, 30, ortho_height=3.0)
    one = shiny.render(cam, "ldc+llf", fill=fill)
    ada = shiny.render(cam, "ldc+llf", fill=fill, supersample=2, antialias="edges")
    edge = _edges_slow(one, shiny.silhouette_rel_depth, EDGE_CONTRAST)
    assert ada.counts["edge_pixels"] == int(edge.sum()) > 0
    assert np.array_equal(ada.radiance[~edge], one.radiance[~edge])
    assert np.all(np.isfinite(ada.radiance))
    uni = shiny.render(cam, "ldc+llf", fill=fill, supersample=2)
    # closer to uniform supersampling than the one-sample image; with the other fills not as
    # close as with the default: the sub-pixels that cross none of their candidates take an
    # image-based ray whatever the fill, where uniform supersampling casts Embree's rays
    # (raycast) or shows the finer warp's cracks as background (none)
    e_ada, e_one = lrms(ada.radiance[edge], uni.radiance[edge]), lrms(one.radiance[edge], uni.radiance[edge])
    print(f"fill {fill}: LRMS against uniform on the edge pixels: edges {e_ada:.4f}, one sample {e_one:.4f}")
    assert e_ada < (0.4 if fill == "ibrt" else 0.9) * e_one
