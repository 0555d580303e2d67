"""Low-rank compression of the baked store: the reported error is the
measured one, the kernel reads the factors correctly, compression is used only when it pays."""

from __future__ import annotations

import numpy as np
import pytest

from engine.errors import InvalidInputError
from engine.reference import ReferenceParams
from engine.relighting.bake import bake_dataset
from engine.relighting.compress import block_order
from engine.relighting.dataset import IlluminationDataset
from engine.relighting.generate import LightPlacement, generate_dataset
from engine.relighting.lights import DirectionalLight, PointLight
from engine.relighting.relight import relight
from engine.scene import CameraParams
from tests.engine.scenes import mat, quad, scene, sphere_mesh

CAM = CameraParams("perspective", (0, 3.0, 3.0), (0, 0.3, 0), (0, 1, 0), 40, 40, fov_y_deg=40)


@pytest.fixture(scope="module")
def ds():
    """A glossy ball casting a shadow on a floor, 254 lights on the upper hemisphere."""
    parts = [(sphere_mesh((0, 0.5, 0), 0.5, subdivisions=3), mat(name="ball", kd=(0.5, 0.5, 0.6),
                                                                 ks=(0.4, 0.4, 0.4), shininess=40.0)),
             (quad((0, 0, 0), 3.0), mat(name="floor", kd=(0.5, 0.4, 0.3)))]
    return generate_dataset(scene(parts), CAM, LightPlacement(region="hemisphere", spacing_deg=10.0),
                            ReferenceParams(spp=1, max_depth=0))


@pytest.fixture(scope="module")
def plain(ds):
    return bake_dataset(ds, half=False)


def _rel_rms(a, b):
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return float(np.sqrt(np.sum((a - b) ** 2) / np.sum(b ** 2)))


def _novel(ds):
    c = ds.sphere_center
    return [PointLight(tuple(c + [1.0, 2.5, 1.0]), 20.0), PointLight(tuple(c + [-10.0, 30.0, 12.0]), 900.0),
            DirectionalLight((0.3, -1.0, 0.2), 1.0)]


@pytest.mark.parametrize("tol", [0.1, 0.02])
def test_reported_error_is_the_measured_error(ds, plain, tol):
    b = bake_dataset(ds, compress=tol)
    cr = b.report["compression_report"]
    assert b.layout == "lowrank" and b.report["compression"] == "svd_per_tile"
    assert cr["rel_rms_error"] <= tol and cr["worst_tile_rel_rms"] <= tol * (1 + 1e-9)
    assert cr["bytes"] == b.lowrank.nbytes < cr["uncompressed_store_bytes"] == plain.store.nbytes // 2  # float16
    assert 1 <= cr["rank_mean"] <= cr["rank_max"] <= len(b.light_positions)
    # relighting at every dataset light (the exact path) against the uncompressed float32 store:
    # the stack's relative RMS error is exactly what the report says
    got, want = [], []
    for k in range(len(b.light_positions)):
        rc = relight(b, PointLight(tuple(b.light_positions[k]), tuple(b.intensities[k])))
        rp = relight(plain, PointLight(tuple(plain.light_positions[k]), tuple(plain.intensities[k])))
        assert rc.exact and rp.exact
        got.append(rc.image[ds.mask])
        want.append(rp.image[ds.mask])
    measured = _rel_rms(got, want)
    assert measured == pytest.approx(cr["rel_rms_error"], rel=1e-4)
    max_abs = float(np.max(np.abs(np.asarray(got, np.float64) - np.asarray(want, np.float64))))
    assert max_abs == pytest.approx(cr["max_abs_error"], rel=1e-3)
    # novel (interpolated) lights: the relit error stays within the requested error
    for light in _novel(ds):
        assert _rel_rms(relight(b, light).image, relight(plain, light).image) <= tol


def test_kernel_reads_the_factors(ds, plain):
    """Relighting the compressed store == relighting an uncompressed store of the reconstructed images."""
    b = bake_dataset(ds, compress=0.05)
    k = len(b.light_positions)
    h, w = ds.shape
    rec = np.zeros((k, h * w, 3), np.float32)
    for j in range(k):
        rec[j, b.pixel_index] = b.light_values(j)
    ds_rec = IlluminationDataset(rec.reshape(k, h, w, 3), b.light_positions, b.intensities, ds.points, ds.mask,
                                 sphere_center=ds.sphere_center)
    b_rec = bake_dataset(ds_rec, half=False)
    for light in _novel(ds):
        a, r = relight(b, light), relight(b_rec, light)
        assert np.allclose(a.image, r.image, rtol=2e-5, atol=1e-7)
        assert np.array_equal(a.outside_mask, r.outside_mask)
    ser = relight(b, _novel(ds)[0], serial=True).image
    assert np.allclose(ser, relight(b, _novel(ds)[0]).image, rtol=1e-6, atol=1e-8)


def test_block_order_and_pixel_mapping():
    m = np.zeros((20, 37), bool)
    m[3:19, 2:35] = True
    m[7, 10] = False
    p = block_order(m)
    assert np.array_equal(np.sort(p), np.nonzero(m.ravel())[0])
    ys, xs = p // 37, p % 37
    blk = (ys // 16) * 3 + xs // 16
    assert np.all(np.diff(blk) >= 0)  # blocks in order, each block's pixels contiguous


def test_compression_only_when_it_meets_the_request_and_pays(ds, plain):
    # an error below float32 precision cannot be met: the plain store is built, bit-exact as without
    b = bake_dataset(ds, compress=1e-9, half=False)
    assert b.lowrank is None and b.layout == "tiled" and b.report["compression"] == "none"
    assert "exceeds the requested" in b.report["compression_reason"]
    assert b.report["compression_report"]["rel_rms_error"] > 1e-9
    light = _novel(ds)[0]
    assert np.array_equal(relight(b, light).image, relight(plain, light).image)
    assert np.array_equal(b.store, plain.store)
    # a tight error that needs nearly full rank is larger than the float16 store: not used
    b = bake_dataset(ds, compress=1e-4)
    assert b.lowrank is None and "not smaller than the float16 store" in b.report["compression_reason"]
    assert bake_dataset(ds).report["compression_reason"] == "not requested"
    for bad in (0, 1.0, -0.1, "0.1", float("nan")):
        with pytest.raises(InvalidInputError, match="compress must be a relative RMS error in"):
            bake_dataset(ds, compress=bad)
