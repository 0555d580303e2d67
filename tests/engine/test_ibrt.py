"""Image-based ray tracing through the LDC (engine/ibrt.py) against Embree and slow references."""

from __future__ import annotations

import numpy as np
import pytest

from api_schemas import load_scene_file
from engine.errors import InvalidInputError
from engine.ibrt import IBRTAccel, build_accel, trace, trace_linear
from engine.ldc import bake_ldc
from engine.raycast import EmbreeCaster
from samples import SAMPLES_DIR, sample_path
from workers.scene_loader import directory_resolver, load_scene


def _sample_scene(name):
    return load_scene(load_scene_file(sample_path(name)), directory_resolver(SAMPLES_DIR)).runtime


@pytest.fixture(scope="module", params=["mirror_box", "teapot_spheres"])
def baked(request):
    sc = _sample_scene(request.param)
    caster = EmbreeCaster(sc)
    ldc = bake_ldc(sc, caster, 128)
    return request.param, sc, caster, ldc, build_accel(ldc)


def _random_rays(sc, n, seed):
    rng = np.random.default_rng(seed)
    lo, hi = sc.bounds
    o = lo + rng.random((n, 3)) * (hi - lo)
    d = rng.normal(size=(n, 3))
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def _hit_objects(ldc, hits):
    out = np.full(hits.hit.shape[0], -1, dtype=np.int64)
    for a in range(3):
        s = hits.axis == a
        out[s] = ldc.axes[a].object[hits.sample[s]]
    return out


def test_same_first_hit_as_embree(baked):
    name, sc, caster, ldc, acc = baked
    o, d = _random_rays(sc, 4000, 1)
    ib = trace(ldc, acc, o, d)
    e = caster.intersect(o, d)
    ehit = e.prim >= 0
    eobj = np.where(ehit, sc.tri_object[np.maximum(e.prim, 0)], -1)
    both = ib.hit & ehit
    same = (_hit_objects(ldc, ib) == eobj)[both].mean()
    assert same >= 0.97, same
    assert (ib.hit == ehit).mean() >= 0.97


def test_quadtree_gives_the_same_hits_as_linear_march(baked):
    name, sc, caster, ldc, acc = baked
    o, d = _random_rays(sc, 3000, 2)
    a = trace(ldc, acc, o, d)
    b = trace_linear(ldc, acc, o, d)
    assert np.array_equal(a.hit, b.hit)
    assert np.allclose(a.t[a.hit], b.t[b.hit], rtol=1e-9, atol=1e-12)
    assert a.n_steps < b.n_steps


def test_accel_roundtrip_and_mismatch(baked):
    name, sc, caster, ldc, acc = baked
    acc2 = IBRTAccel.from_arrays(acc.to_arrays())
    assert acc2.nbytes == acc.nbytes
    o, d = _random_rays(sc, 200, 3)
    h1 = trace(ldc, acc, o, d)
    h2 = trace(ldc, acc2, o, d)
    assert np.array_equal(h1.sample, h2.sample)
    other = bake_ldc(sc, caster, 64)
    with pytest.raises(InvalidInputError):
        trace(other, acc, o, d)
