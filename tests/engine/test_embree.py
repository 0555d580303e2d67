"""engine/embree.py: Embree traced from numba kernels, against the brute-force float64 caster."""

from __future__ import annotations

import gc
import threading

import numpy as np
import pytest

from engine import embree
from engine.errors import EngineError
from engine.raycast import ReferenceCaster
from tests.engine.scenes import mat, quad, scene, sphere_mesh


def _scene_and_rays(n: int, seed: int):
    parts = [(sphere_mesh(subdivisions=2, jitter=0.05, seed=3), mat()), (quad((0, -1.5, 0), 5.0), mat("floor"))]
    sc = scene(parts)
    rng = np.random.default_rng(seed)
    o = rng.uniform(-2.0, 2.0, (n, 3))
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return sc, o, d


@pytest.mark.parametrize("serial", [True, False])
def test_first_hits_match_the_brute_force_caster(serial):
    sc, o, d = _scene_and_rays(3001, 1)  # not a multiple of the packet width
    es = embree.build_scene(sc.tri_local32)
    o32 = (o - sc.center).astype(np.float32)
    prim, u, v, t = embree.intersect(es, o32, d.astype(np.float32), serial=serial)
    ref = ReferenceCaster(sc).intersect(o32.astype(np.float64) + sc.center, d.astype(np.float32).astype(np.float64))
    assert (prim >= 0).sum() > 1000 and (prim < 0).sum() > 100  # both hits and misses are exercised
    np.testing.assert_array_equal(prim, ref.prim)
    hit = prim >= 0
    np.testing.assert_allclose(t[hit], ref.t[hit], rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(u[hit], ref.u[hit], atol=1e-4)
    np.testing.assert_allclose(v[hit], ref.v[hit], atol=1e-4)
    assert np.all(np.isinf(t[~hit])) and np.all(u[~hit] == 0) and np.all(v[~hit] == 0)


@pytest.mark.parametrize("serial", [True, False])
def test_occlusion_is_a_hit_closer_than_tmax(serial):
    sc, o, d = _scene_and_rays(2999, 2)
    es = embree.build_scene(sc.tri_local32)
    o32 = (o - sc.center).astype(np.float32)
    d32 = d.astype(np.float32)
    _, _, _, t = embree.intersect(es, o32, d32)
    tmax = np.random.default_rng(3).uniform(0.1, 4.0, o.shape[0]).astype(np.float32)
    occ = embree.occluded(es, o32, d32, tmax, serial=serial)
    clear = np.abs(t - tmax) > 1e-4 * np.maximum(1.0, tmax)  # no hit within rounding of tmax
    np.testing.assert_array_equal(occ[clear], (t < tmax)[clear])
    assert occ.any() and (~occ).any()


def test_pipeline_threads_and_the_main_thread_agree():
    """Serial kernels in several Python threads at once (the renderer's pipelines) give the
    parallel kernel's answers."""
    sc, o, d = _scene_and_rays(20000, 4)
    es = embree.build_scene(sc.tri_local32)
    o32 = (o - sc.center).astype(np.float32)
    d32 = d.astype(np.float32)
    want = embree.intersect(es, o32, d32)[0]
    got: dict[int, np.ndarray] = {}

    def run(k: int) -> None:
        got[k] = embree.intersect(es, o32[k::4], d32[k::4])[0]  # None: serial off the main thread

    threads = [threading.Thread(target=run, args=(k,)) for k in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    for k in range(4):
        np.testing.assert_array_equal(got[k], want[k::4])


def test_empty_batches_and_bad_meshes():
    sc, _, _ = _scene_and_rays(1, 5)
    es = embree.build_scene(sc.tri_local32)
    z = np.zeros((0, 3), np.float32)
    assert embree.intersect(es, z, z)[0].shape == (0,)
    assert embree.occluded(es, z, z, np.zeros(0, np.float32)).shape == (0,)
    with pytest.raises(EngineError, match="triangles"):
        embree.build_scene(np.zeros((0, 3, 3), np.float32))


def test_scenes_are_released_when_unreferenced():
    sc, o, d = _scene_and_rays(100, 6)
    es = embree.build_scene(sc.tri_local32)
    embree.intersect(es, (o - sc.center).astype(np.float32), d.astype(np.float32))
    release = es.release
    assert release.alive
    del es
    gc.collect()
    assert not release.alive  # rtcReleaseScene ran: Embree frees the BVH and buffers
