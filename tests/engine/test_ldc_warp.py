"""LDC bake and 3D warp: reference agreement, docs/hard-cases.md #4 and #11, holes on mirror_box, many-light bits."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.ndimage import binary_erosion

from engine.errors import InvalidInputError
from engine.metrics import lrms
from engine.newviews.ldc import bake_ldc, bake_ldc_axis, estimate_ldc_bytes, ldc_pixel_size, merge_ldc
from engine.newviews.warp import PROV_FILLED, warp_ldc
from engine.raycast import OFFSET_EXTENT, OFFSET_REL, SHADOW_SHORTEN, EmbreeCaster
from engine.reference import ReferenceParams, render_reference
from engine.scene import CameraParams
from tests.engine.scenes import degenerate_cameras, from_trimesh, mat, quad, sample_scene, scene, sphere_mesh

LIGHTS = [dict(type="point", position=(1.5, 2.5, 2.0), intensity=(4.0, 4.0, 4.0)),
          dict(type="point", position=(-2.0, 1.5, 1.0), intensity=(1.0, 2.0, 3.0)),
          dict(type="directional", direction=(0.2, -1.0, -0.5), irradiance=(0.5, 0.4, 0.3))]


def _box(extents, center, smooth=False):
    return from_trimesh(trimesh.creation.box(extents=extents).apply_translation(center), smooth=smooth)


def _diffuse_scene(lights=LIGHTS):
    return scene([(quad((0, -0.5, 0), 3.0, normal_axis=1), mat("floor", kd=(0.6, 0.6, 0.55))),
                  (_box((0.8, 0.8, 0.8), (0.6, -0.1, -0.2)), mat("box", kd=(0.7, 0.2, 0.2))),
                  (sphere_mesh((-0.6, 0.0, 0.3), 0.5, subdivisions=3), mat("ball", kd=(0.2, 0.3, 0.7)))],
                 lights, ambient=(0.02, 0.02, 0.02))


def _warp(ldc, camera, **options):
    """``warp_ldc`` with float64 radiance, as the renderer calls it (``LDCViewRenderer``): its kernels'
    compiled specialization, which the render warm-up caches (the values are the same as float32's)."""
    return warp_ldc(ldc, camera, radiance_dtype=np.float64, **options)


@pytest.fixture(scope="module")
def mirror_box():
    return sample_scene("mirror_box").runtime


def test_axis_view_reproduces_reference_visibility_and_diffuse():
    sc = _diffuse_scene()
    caster = EmbreeCaster(sc)
    ldc = bake_ldc(sc, caster, 96)
    # orthographic camera looking along -z, one camera pixel per LDC pixel
    cam = CameraParams("orthographic", (0.0, 0.0, 10.0), (0.0, 0.0, 0.0), (0, 1, 0), 96, 96,
                       ortho_height=96 * ldc.h)
    w = _warp(ldc, cam)
    ref = render_reference(sc, cam, ReferenceParams(spp=1, max_depth=0), backend="embree")
    cov = ref.object_id >= 0
    agree = (w.object_id == ref.object_id)[cov].mean()
    assert agree >= 0.98, agree
    assert (w.material_id == ref.material_id)[cov].mean() >= 0.98
    same = cov & (w.object_id == ref.object_id)
    inner = np.zeros_like(same)
    for o in range(3):
        inner |= binary_erosion(ref.object_id == o) & same
    # Residual: the LDC shades its own sample point, the reference (spp=1) a jittered point in
    # the pixel, up to a pixel apart: on the sphere's limb and at shadow edges that is a large
    # difference, so silhouette pixels are left out (measured: 0.18 with them, 0.023 without;
    # against a 16-spp reference 0.005 without)
    err1 = lrms(w.radiance, ref.radiance, inner)
    assert err1 < 0.05, err1
    ref16 = render_reference(sc, cam, ReferenceParams(spp=16, max_depth=0))
    err16 = lrms(w.radiance, ref16.radiance, inner)
    assert err16 < 0.015, err16
    assert np.all(np.isfinite(w.radiance))
    assert np.all(w.hole_mask[cov] == (w.object_id[cov] < 0))  # every covered pixel warped or flagged


def test_parallel_surfaces_and_thin_wall_hard_case_4():
    res = 64
    wall_t = 0.2 * 3.0 / res  # thinner than the LDC pixel (scene extent 3)
    sc = scene([(quad((0, 0, -1.0), 3.0, normal_axis=2), mat("back", kd=(0.5, 0.5, 0.5))),
                (_box((1.5, 1.0, wall_t), (0.0, 0.0, 0.0)), mat("wall", kd=(0.8, 0.3, 0.1)))],
               LIGHTS[:1] + LIGHTS[2:])
    caster = EmbreeCaster(sc)
    ldc = bake_ldc(sc, caster, res)
    assert ldc.h > wall_t
    # the wall's big faces (normal +-z) are parallel to x and y: only the z LDI samples them
    for ax in ldc.axes:
        big = (ax.object == 1) & (np.abs(ax.geo_normal[:, 2]) > 0.99)
        assert big.any() == (ax.axis == 2)
    assert (ldc.axes[2].object == 0).sum() > 0 and (ldc.axes[0].object == 0).sum() == 0
    for eye in ((1.2, 0.7, 3.0), (-2.0, -0.4, 2.0), (-0.4, 1.5, 1.5)):
        cam = CameraParams("perspective", eye, (0, 0, -0.2), (0, 1, 0), 128, 128, 50.0)
        w = _warp(ldc, cam)
        ref = render_reference(sc, cam, ReferenceParams(spp=1, max_depth=0))
        wall = ref.object_id == 1
        assert wall.sum() > 500
        assert not (w.hole_mask & wall).any()
        assert (w.object_id == ref.object_id)[ref.object_id >= 0].mean() >= 0.97


def test_mirror_box_holes_below_two_percent(mirror_box):
    sc = mirror_box
    caster = EmbreeCaster(sc)
    ldc = bake_ldc(sc, caster, 256)
    cam = CameraParams("perspective", (1.3, 2.0, 4.6), (0.1, 0.5, -0.3), (0, 1, 0), 256, 256, 45.0)
    w = _warp(ldc, cam)
    ref = render_reference(sc, cam, ReferenceParams(spp=1, max_depth=0))
    cov = ref.object_id >= 0
    frac = (w.hole_mask & cov).sum() / cov.sum()
    print(f"mirror_box hole fraction among covered pixels: {frac:.5f} "
          f"(all flagged incl. background: {w.n_holes / w.hole_mask.size:.4f})")
    assert frac < 0.02
    assert (w.object_id == ref.object_id)[cov].mean() >= 0.98
    wf = _warp(ldc, cam, fill="raycast", caster=caster)
    assert wf.n_holes == w.n_holes
    assert not ((wf.object_id < 0) & cov).any()
    assert np.all(wf.provenance[wf.provenance == PROV_FILLED] == PROV_FILLED)


def test_degenerate_cameras_hard_case_11():
    sc = _diffuse_scene()
    caster = EmbreeCaster(sc)
    ldc = bake_ldc(sc, caster, 48)
    cams = degenerate_cameras(ldc.axes[2].ldi.frame.origin, 40, 30)
    for cam in cams:
        for fill in ("none", "raycast"):
            w = _warp(ldc, cam, fill=fill, caster=caster)
            assert np.all(np.isfinite(w.radiance)) and np.all(np.isfinite(w.depth))
            assert np.all(np.isfinite(w.normal))
            assert w.radiance.shape == (cam.height, cam.width, 3)
    # along -x with fill: matches reference visibility almost everywhere
    cam = CameraParams("perspective", (5.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0, 1, 0), 96, 72, 45.0)
    w = _warp(ldc, cam, fill="raycast", caster=caster)
    ref = render_reference(sc, cam, ReferenceParams(spp=1, max_depth=0))
    assert (w.object_id == ref.object_id).mean() >= 0.95


def test_visibility_bits_with_70_lights():
    rng = np.random.default_rng(3)
    pos = np.column_stack([rng.uniform(-2, 2, 70), rng.uniform(-0.4, 2.5, 70), rng.uniform(-2, 2, 70)])
    lights = [dict(type="point", position=tuple(p), intensity=(0.1, 0.1, 0.1)) for p in pos]
    sc = _diffuse_scene(lights)
    caster = EmbreeCaster(sc)
    part = bake_ldc_axis(sc, caster, 1, 12)
    vis = part.visibility
    assert vis.shape == (part.n_samples, 2, 2) and vis.dtype == np.uint64
    # brute force: one occlusion query per (sample, light) through the public API
    from engine.newviews.ldc import surface_attributes

    p, ng, _ = surface_attributes(sc, part.ldi.prim, part.ldi.u, part.ldi.v)
    mag = OFFSET_REL * (np.abs(p - sc.center).max(axis=1) + OFFSET_EXTENT * sc.extent)
    n_set = 0
    for li in range(70):
        to = pos[li][None] - p
        side = (np.einsum("ij,ij->i", ng, to) < 0).astype(int)
        g = np.where(side[:, None] == 0, ng, -ng)
        o = p + mag[:, None] * g
        d = pos[li][None] - o
        dist = np.linalg.norm(d, axis=1)
        d /= dist[:, None]
        front = np.einsum("ij,ij->i", g, d) > 0
        tmax = dist * (1 - SHADOW_SHORTEN) - mag
        occ = caster.occluded(o, d, tmax)
        want = front & ~occ & (tmax > 0)
        bit = (vis[np.arange(p.shape[0]), side, li // 64] >> np.uint64(li % 64)) & np.uint64(1)
        other = (vis[np.arange(p.shape[0]), 1 - side, li // 64] >> np.uint64(li % 64)) & np.uint64(1)
        assert np.array_equal(bit.astype(bool), want), li
        assert not other.any()
        n_set += int(want.sum())
    assert 0 < n_set < 70 * p.shape[0]  # some lights are blocked, some visible


def test_split_bake_merge_and_limits():
    sc = _diffuse_scene()
    caster = EmbreeCaster(sc)
    parts = [bake_ldc_axis(sc, caster, a, 32) for a in (2, 0, 1)]
    ldc = merge_ldc(sc, parts, 32)
    whole = bake_ldc(sc, caster, 32)
    for a, b in zip(ldc.axes, whole.axes, strict=True):
        assert a.axis == b.axis
        assert np.array_equal(a.ldi.depth, b.ldi.depth) and np.array_equal(a.diffuse, b.diffuse)
    assert ldc.h == pytest.approx(ldc_pixel_size(sc, 32))
    with pytest.raises(InvalidInputError):
        merge_ldc(sc, parts[:2], 32)
    with pytest.raises(InvalidInputError):
        merge_ldc(sc, parts, 64)
    with pytest.raises(InvalidInputError):
        bake_ldc(sc, caster, 0)
    est = estimate_ldc_bytes(sc, 32)
    with pytest.raises(InvalidInputError, match="MiB"):
        bake_ldc(sc, caster, 32, max_bytes=est // 2)
    with pytest.raises(InvalidInputError):
        _warp(ldc, CameraParams("perspective", (0, 0, 5), (0, 0, 0), (0, 1, 0), 8, 8), fill="raycast")


def test_cracks_are_detected_and_filled():
    # a coarse LDC seen close up with tiny splats: the back wall shows through gaps in the front quad
    sc = scene([(quad((0, 0, -1.0), 3.0, normal_axis=2), mat("back", kd=(0.5, 0.5, 0.5))),
                (quad((0, 0, 0.0), 1.0, normal_axis=2), mat("front", kd=(0.8, 0.3, 0.1)))], LIGHTS[2:])
    caster = EmbreeCaster(sc)
    ldc = bake_ldc(sc, caster, 16)
    cam = CameraParams("perspective", (0.05, 0.02, 1.5), (0.0, 0.0, 0.0), (0, 1, 0), 96, 96, 30.0)
    ref = render_reference(sc, cam, ReferenceParams(spp=1, max_depth=0))
    front = ref.object_id == 1
    inner = binary_erosion(front, iterations=2)
    # splats capped just below the sample spacing (~24 px here): one-pixel cracks
    w = _warp(ldc, cam, max_footprint=11.0)
    through = inner & (w.object_id == 0)
    assert through.sum() > 100  # the cracks exist
    # and nearly all are flagged (missed: where two cracks cross, too few nearer neighbours)
    assert (w.hole_mask & through).sum() >= 0.85 * through.sum()
    wf = _warp(ldc, cam, max_footprint=11.0, fill="raycast", caster=caster)
    assert wf.n_filled > 0 and (wf.object_id[through & w.hole_mask] == 1).all()
    # with the default footprint cap there are no cracks at all
    wn = _warp(ldc, cam)
    assert not (wn.hole_mask & front).any() and (wn.object_id[inner] == 1).all()


def test_close_layers_far_away_warp_hard_case_6():
    base = np.array([1e4, 1e4, 1e4])
    sc = scene([(quad(base, 1.0, normal_axis=2), mat("back", kd=(0.2, 0.2, 0.2))),
                (quad(base + [0, 0, 1e-3], 1.0, normal_axis=2), mat("front", kd=(0.9, 0.1, 0.1)))], LIGHTS[2:])
    ldc = bake_ldc(sc, EmbreeCaster(sc), 32)
    assert all(np.all(np.diff(a.ldi.depth.reshape(-1, 2), axis=1) > 5e-4) for a in ldc.axes if a.n_samples)
    for cam in (CameraParams("orthographic", tuple(base + [0, 0, 10.0]), tuple(base), (0, 1, 0), 48, 48,
                             ortho_height=1.2),
                CameraParams("perspective", tuple(base + [0.1, 0.05, 3.0]), tuple(base), (0, 1, 0), 48, 48, 30.0)):
        w = _warp(ldc, cam)
        ref = render_reference(sc, cam, ReferenceParams(spp=1, max_depth=0))
        cov = ref.object_id >= 0
        assert np.all(ref.object_id[cov] == 1)
        assert (w.object_id[cov] == 1).mean() >= 0.98
        assert not (w.object_id == 0).any()


def test_rect_light_and_no_lights_perspective():
    rect = dict(type="rect", corner=(-1.0, 2.0, -1.0), edge_u=(2.0, 0, 0), edge_v=(0, 0, 2.0), radiance=(2.0, 2.0, 2.0))
    sc = _diffuse_scene([rect])
    caster = EmbreeCaster(sc)
    ldc = bake_ldc(sc, caster, 96, area_light_samples=64)
    cam = CameraParams("perspective", (2.0, 2.5, 3.5), (0.0, -0.2, 0.0), (0, 1, 0), 96, 96, 45.0)
    w = _warp(ldc, cam)
    ref = render_reference(sc, cam, ReferenceParams(spp=16, max_depth=0, area_light_samples=64))
    same = (w.object_id == ref.object_id) & (ref.object_id >= 0)
    inner = np.zeros_like(same)
    for o in range(3):
        inner |= binary_erosion(ref.object_id == o) & same
    # per pixel the LDC's shading point is up to an LDC pixel from the reference's pixel centre:
    # the median error is small, the LRMS (measured 0.054) is carried by box edges (the other
    # face of the same object), the sphere's curvature and penumbrae
    rel = np.abs(w.radiance - ref.radiance).sum(2) / (ref.radiance.sum(2) + 1e-6)
    assert np.median(rel[inner & (ref.object_id == 0)]) < 0.01
    assert np.median(rel[inner]) < 0.02
    assert lrms(w.radiance, ref.radiance, inner) < 0.08
    # no lights at all: ambient only, no bits, no shadow rays
    sc0 = _diffuse_scene([])
    l0 = bake_ldc(sc0, EmbreeCaster(sc0), 16)
    assert l0.visibility_words == 0 and all(a.timings["shadow_rays"] == 0 for a in l0.axes)
    w0 = _warp(l0, cam)
    assert np.allclose(w0.radiance[w0.material_id == 0], 0.02 * np.array([0.6, 0.6, 0.55]), rtol=1e-5)


def test_parallel_zbuffer_writes_equal_the_serial_pass(mirror_box):
    """The z-buffer writes run in image bands, one per numba thread; every pixel still sees the
    samples in CSR order, so 2 and 3 bands give the serial pass's images bit for bit."""
    import numba as nb

    from engine.newviews import warp as warp_mod

    sc = mirror_box
    ldc = bake_ldc(sc, EmbreeCaster(sc), 128)
    cam = CameraParams("perspective", (1.3, 2.0, 4.6), (0.1, 0.5, -0.3), (0, 1, 0), 97, 83, 45.0)
    ax = ldc.axes[0]
    n = ax.n_samples
    f = ax.ldi.frame
    out_f, out_side, out_box = np.empty((n, 4)), np.empty(n, np.int8), np.empty((n, 4), np.int32)
    right, up, fwd = cam.basis()
    closed = np.zeros(64, np.bool_)
    warp_mod._project(f.origin, f.u, f.v, f.w, f.h, f.nu, ax.ldi.offsets, ax.ldi.depth, ax.geo_normal, ax.object,
                      closed, False, np.asarray(cam.eye, np.float64), right, up, fwd, cam.width, cam.height,
                      np.tan(np.radians(cam.fov_y_deg) / 2), 0.5, 0.5, 16.0, 1.0, out_f, out_side, out_box, 2)
    assert (out_box[:, 0] <= out_box[:, 1]).sum() > 1000
    results = []
    for bands in (1, 2, 3):
        zb = np.empty((83, 97, 3))
        warp_mod._init_buffers(zb, 2)
        if bands == 1:
            warp_mod._write_rows(0, out_f, out_side, out_box, 97, 83, zb, 0, 1)  # the serial pass
        else:
            warp_mod._write(0, out_f, out_side, out_box, 97, 83, zb, bands)
        results.append(zb)
    assert np.isfinite(results[0][..., 0]).sum() > 1000
    for zb in results[1:]:
        assert np.array_equal(results[0], zb)
    # the whole warp under 1 and 2 numba threads
    before = nb.get_num_threads()
    try:
        nb.set_num_threads(1)
        w1 = _warp(ldc, cam)
        nb.set_num_threads(min(2, nb.config.NUMBA_NUM_THREADS))
        w2 = _warp(ldc, cam)
    finally:
        nb.set_num_threads(before)
    for key in ("radiance", "depth", "normal", "object_id", "sample_index", "hole_mask"):
        assert np.array_equal(getattr(w1, key), getattr(w2, key)), key
