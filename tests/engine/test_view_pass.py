"""View-dependent pass: highlights gated by the LDC bits vs the reference's direct light,
light-field gather vs a naive lookup, constant environments, huge exponents (docs/hard-cases.md #8)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from engine.newviews.ldc import bake_ldc, surface_attributes
from engine.newviews.llf import bake_llf
from engine.newviews.view_pass import (
    GLOSSY_LOG_CUT,
    gather_incoming,
    gather_reflections,
    highlights,
    lookup_direction,
    mirror_cone_exponent,
)
from engine.raycast import EmbreeCaster
from engine.reference import ReferenceParams, ReferenceRenderer
from tests.engine.scenes import from_trimesh, mat, quad, scene, sphere_mesh

C = np.array([0.3, 0.5, 0.7])
LIGHTS = [dict(type="point", position=(1.5, 2.5, 2.0), intensity=(4.0, 4.0, 4.0)),
          dict(type="point", position=(-2.0, 1.5, 1.0), intensity=(1.0, 2.0, 3.0)),
          dict(type="directional", direction=(0.2, -1.0, -0.5), irradiance=(0.5, 0.4, 0.3))]


def _inside_out_sphere(radius):
    m = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    m.faces = m.faces[:, ::-1]
    m.vertex_normals  # noqa: B018 (recomputed from the flipped winding)
    return from_trimesh(m)


@pytest.fixture(scope="module")
def env():
    """Two quads (mirror, glossy) in the plane y = 0 inside a sphere of constant emission C."""
    sc = scene([(_inside_out_sphere(2.0), mat("env", kd=(0, 0, 0), emission=tuple(C))),
                (quad((-0.5, 0.0, 0.0), 0.8, normal_axis=1), mat("mirror", kd=(0, 0, 0), kr=(0.6, 0.6, 0.6))),
                (quad((0.5, 0.0, 0.0), 0.8, normal_axis=1), mat("gloss", kd=(0, 0, 0), kg=(0.5, 0.5, 0.5),
                                                               gloss_exponent=40.0))], [])
    caster = EmbreeCaster(sc)
    llf = bake_llf(sc, caster, 4, 48, params=ReferenceParams(max_depth=0))
    return sc, llf


def _points_on_quads(n, rng):
    x = np.concatenate([rng.uniform(-0.85, -0.15, n), rng.uniform(0.15, 0.85, n)])
    z = rng.uniform(-0.35, 0.35, 2 * n)
    p = np.column_stack([x, np.zeros(2 * n), z])
    mat_ = np.concatenate([np.full(n, 1), np.full(n, 2)]).astype(np.int32)
    return p, mat_


def test_gather_of_constant_environment_returns_the_constant(env):
    # free points inside an empty emissive sphere: any direction, mirror cone and lobes of any width
    empty = scene([(_inside_out_sphere(2.0), mat("env", kd=(0, 0, 0), emission=tuple(C)))], [])
    llf0 = bake_llf(empty, EmbreeCaster(empty), 4, 32, params=ReferenceParams(max_depth=0))
    rng = np.random.default_rng(0)
    p = rng.uniform(-0.8, 0.8, (500, 3))
    d = rng.normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for e in (0.0, 1.0, 40.0, 1e4, 1e6):
        for ng in (d, -d):
            g = gather_incoming(llf0, p, ng, d, exponent=e)
            assert np.all(np.abs(g / C - 1) < 1e-5), (e, np.abs(g / C - 1).max())
    sc, llf = env
    # points on the mirror quad, seen from above: kr * C
    p, m = _points_on_quads(200, rng)
    eye = np.array([0.3, 1.5, 1.2])
    wo = eye - p
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    up = np.tile([0.0, 1.0, 0.0], (p.shape[0], 1))
    out, n_look = gather_reflections(sc, llf, p, up, up, wo, m)
    assert n_look >= 3 * 200
    assert np.allclose(out[m == 1], 0.6 * C, rtol=1e-5)


def test_glossy_gather_matches_a_naive_sum(env):
    sc, llf = env
    rng = np.random.default_rng(1)
    p, m = _points_on_quads(60, rng)
    sel = m == 2
    p, m = p[sel], m[sel]
    eye = np.array([-0.4, 1.0, 1.5])
    wo = eye - p
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    up = np.tile([0.0, 1.0, 0.0], (p.shape[0], 1))
    n_c = mirror_cone_exponent(llf)
    dirs = llf.directions
    for g in (3.0, 40.0):  # a lobe the 66 directions resolve (g < n_c = 7.4), and a narrower one
        gsc = scene([(_inside_out_sphere(2.0), mat("env", kd=(0, 0, 0), emission=tuple(C))),
                     (quad((-0.5, 0.0, 0.0), 0.8, normal_axis=1), mat("mirror", kd=(0, 0, 0), kr=(0.6, 0.6, 0.6))),
                     (quad((0.5, 0.0, 0.0), 0.8, normal_axis=1), mat("gloss", kd=(0, 0, 0), kg=(0.5, 0.5, 0.5),
                                                                    gloss_exponent=g))], [])
        out, _ = gather_reflections(gsc, llf, p, up, up, wo, m)
        ge = min(g, n_c)
        for i in range(p.shape[0]):
            wr = 2 * wo[i] @ up[i] * up[i] - wo[i]
            c = dirs @ wr
            lw = ge * np.log(np.clip(c, 1e-300, None)) - ge * math.log(c.max())
            w = np.where((c > 0) & (lw >= -GLOSSY_LOG_CUT), np.exp(lw), 0.0)
            if g <= n_c:
                cos_i = np.clip(dirs[:, 1], 0, None)
                want = 0.5 * (g + 2) / (g + 1) * (w * cos_i).sum() / w.sum() * C
            else:
                want = 0.5 * max(wr[1], 0.0) * C  # cone average of a constant
            assert np.allclose(out[i], want, rtol=1e-9), (g, i)
            # close to the reference's expectation kg (g+2)/(g+1) E[cos_i] ~ kg cos(theta_r) (g large)
            if g > n_c:
                assert abs(out[i, 0] / (0.5 * C[0]) - wr[1]) < 1e-6


def _naive_lookup(llf, j, p, n, bg):
    """Slow obvious version of the LLF lookup (paper 4.2 + the tangent-plane start)."""
    v = llf.views[j]
    fr = v.ldi.frame
    rel = p - fr.origin
    a = rel @ fr.u / fr.h - 0.5
    b = rel @ fr.v / fr.h - 0.5
    zp = rel @ fr.w
    i0, j0 = math.floor(a), math.floor(b)
    total = np.zeros(3)
    for di in (0, 1):
        for dj in (0, 1):
            ii, jj = i0 + di, j0 + dj
            wgt = (a - i0 if di else 1 - (a - i0)) * (b - j0 if dj else 1 - (b - j0))
            val = np.asarray(bg, float)
            if 0 <= ii < fr.nu and 0 <= jj < fr.nv:
                off = 0.0
                nw = n @ fr.w
                if nw > 1e-3:
                    off = float(np.clip(-fr.h * ((ii - a) * (n @ fr.u) + (jj - b) * (n @ fr.v)) / nw,
                                        -3 * fr.h, 3 * fr.h))
                k = jj * fr.nu + ii
                for s in range(v.ldi.offsets[k], v.ldi.offsets[k + 1]):
                    if v.ldi.depth[s] > zp + off + 0.05 * fr.h:
                        val = v.radiance[s].astype(float)
                        break
            total += wgt * val
    return total


def test_lookup_kernel_matches_naive_lookup():
    sc = scene([(quad((0, -0.5, 0), 3.0, normal_axis=1), mat("floor", kd=(0.6, 0.6, 0.55))),
                (sphere_mesh((0.2, 0.1, 0.0), 0.5, 2), mat("ball", kd=(0.2, 0.3, 0.7))),
                (quad((0, 0.5, -1.0), 1.5, normal_axis=2), mat("wall", kd=(0.7, 0.2, 0.2)))], LIGHTS,
               background=(0.1, 0.2, 0.3))
    caster = EmbreeCaster(sc)
    llf = bake_llf(sc, caster, 2, 24, params=ReferenceParams(max_depth=0))
    rng = np.random.default_rng(2)
    hits = caster.intersect(rng.uniform(-1, 1, (300, 3)) + [0, 2.5, 1.5],
                            np.tile([0.05, -0.9, -0.4], (300, 1)) / np.linalg.norm([0.05, -0.9, -0.4]))
    ok = hits.prim >= 0
    p, ng, _ = surface_attributes(sc, hits.prim[ok], hits.u[ok], hits.v[ok])
    assert p.shape[0] > 200
    for j in rng.choice(llf.n_directions, 6, replace=False):
        got = lookup_direction(llf, int(j), p, ng, sc.background)
        want = np.array([_naive_lookup(llf, int(j), p[i], ng[i], sc.background) for i in range(p.shape[0])])
        assert np.allclose(got, want, rtol=1e-9, atol=1e-12)
        assert np.any(np.abs(got - sc.background).sum(1) > 1e-3)  # not only background
    # the mirror cone: the 3 directions nearest to d, weights cos^n_c normalised
    n_c = mirror_cone_exponent(llf)
    d = rng.normal(size=(40, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    got = gather_incoming(llf, p[:40], ng[:40], d, background=sc.background)
    for i in range(40):
        c = llf.directions @ d[i]
        near = np.argsort(-c)[:3]
        w = c[near] ** n_c
        look = [_naive_lookup(llf, int(j), p[i], ng[i], sc.background) for j in near]
        assert np.allclose(got[i], (w[:, None] * np.array(look)).sum(0) / w.sum(), rtol=1e-9, atol=1e-12)


def test_diffuse_plus_highlights_equals_reference_direct_light():
    hl = mat("hl", kd=(0.4, 0.3, 0.2), ks=(0.5, 0.5, 0.5), shininess=30.0)
    sc = scene([(quad((0, -0.5, 0), 3.0, normal_axis=1), hl),
                (sphere_mesh((-0.4, 0.1, 0.2), 0.5, 3), hl),
                (from_trimesh(trimesh.creation.box(extents=(0.6, 0.6, 0.6)).apply_translation((0.7, -0.2, -0.3)),
                              smooth=False), hl)], LIGHTS, ambient=(0.02, 0.02, 0.02))
    caster = EmbreeCaster(sc)
    ldc = bake_ldc(sc, caster, 48)
    assert ldc.visibility_words == 1
    ren = ReferenceRenderer(sc, caster)
    n_total = n_bad = 0
    for ax in ldc.axes:
        p, ng, ns = surface_attributes(sc, ax.ldi.prim, ax.ldi.u, ax.ldi.v)
        for eye in (np.array([2.0, 2.0, 3.0]), np.array([-2.5, 1.0, -1.5])):
            wo = eye - p
            wo /= np.linalg.norm(wo, axis=1, keepdims=True)
            side = (np.einsum("ij,ij->i", ng, wo) < 0).astype(np.int64)
            sg = np.where(side == 0, 1.0, -1.0)[:, None]
            g, s = ng * sg, ns * sg
            s = np.where((np.einsum("ij,ij->i", s, g) > 0)[:, None], s, g)
            bits = ax.visibility[np.arange(p.shape[0]), side]
            spec = highlights(sc, p, g, s, wo, ax.material, bits)
            ours = ax.diffuse[np.arange(p.shape[0]), side] + spec
            ref = ren.shade_hits(ax.ldi.prim, ax.ldi.u, ax.ldi.v, -wo, ReferenceParams(max_depth=0))
            close = np.isclose(ours, ref, rtol=1e-5, atol=1e-7).all(axis=1)
            n_total += p.shape[0]
            n_bad += int((~close).sum())
            assert spec.max() > 0.05  # highlights do show
    # shadow rays from float32 barycentric points: a handful can flip exactly on a shadow boundary
    assert n_bad <= 1e-3 * n_total, (n_bad, n_total)


@pytest.mark.parametrize("g", [1.0, 20.0, 200.0])
def test_glossy_lobe_reflects_rect_lights_as_a_highlight(g):
    """The light field holds surfaces, never a light, so the glossy lobe's reflection of a rect
    light is shaded per view with the highlights: it must be the reference's, the quadrature of the
    lobe over the light (tests/engine/test_reference_caustics.py checks the reference against the
    same quadrature). A glossy lobe does not see point or directional lights (nor does the
    reference's: no ray meets them)."""
    from tests.engine.test_reference_caustics import _down_light, _glossy_quadrature

    le, size, h, rho = 2.0, 2.0, 1.0, 0.8
    glossy = mat("f", kd=(0, 0, 0), kg=(rho,) * 3, gloss_exponent=g)
    up = np.array([[0.0, 1.0, 0.0]])
    m = np.zeros(1, np.int32)
    sc = scene([(quad((0, 0, 0), 40.0), glossy)], [_down_light(size, h, le)])
    got = highlights(sc, np.zeros((1, 3)), up, up, up, m, area_light_samples=4096)
    assert got[0, 0] == pytest.approx(rho * _glossy_quadrature(g, size, h, le), rel=0.01)
    only_points = scene([(quad((0, 0, 0), 40.0), glossy)], LIGHTS)
    assert np.all(highlights(only_points, np.zeros((1, 3)), up, up, up, m) == 0.0)


def test_huge_exponents_stay_finite_hard_case_8(env):
    sc0, llf = env
    rng = np.random.default_rng(3)
    for e in (1e4, 1e6):
        sc = scene([(_inside_out_sphere(2.0), mat("env", kd=(0, 0, 0), emission=tuple(C))),
                    (quad((0.5, 0.0, 0.0), 0.8, normal_axis=1), mat("g", kd=(0.2, 0.2, 0.2), ks=(0.5, 0.5, 0.5),
                                                                   shininess=e, kg=(0.5, 0.5, 0.5),
                                                                   gloss_exponent=e))],
                   [dict(type="point", position=(0.5, 1.0, 0.0), intensity=(1.0, 1.0, 1.0))])
        p, _ = _points_on_quads(100, rng)
        p = p[100:]
        m = np.full(p.shape[0], 1, np.int32)
        up = np.tile([0.0, 1.0, 0.0], (p.shape[0], 1))
        wo = np.array([0.0, 1.0, 0.0]) + rng.normal(scale=1e-3, size=p.shape)
        wo /= np.linalg.norm(wo, axis=1, keepdims=True)
        out, _ = gather_reflections(sc, llf, p, up, up, wo, m)
        assert np.all(np.isfinite(out)) and np.all(out > 0)
        # lobe weights normalised: at most kg (g+2)/(g+1) C
        assert np.all(out <= 0.5 * (e + 2) / (e + 1) * C * (1 + 1e-9))
        spec = highlights(sc, p, up, up, wo, m)
        assert np.all(np.isfinite(spec)) and np.all(spec >= 0)
        # straight below the light, looking straight down: the peak (s+2)/(2pi) I / d^2 is reached
        exact = highlights(sc, np.array([[0.5, 0.0, 0.0]]), up[:1], up[:1], up[:1], m[:1])
        assert exact[0, 0] == pytest.approx(0.5 * (e + 2) / (2 * np.pi) * 1.0 / 1.0, rel=1e-3)


@pytest.mark.parametrize("f", [1, 4, 8, 13])
def test_cone_tables_list_the_candidates_of_every_lattice_cell(f):
    """The cone gather's per-cell candidate table holds, for any direction, exactly the list
    (same directions, same order) ``candidate_directions`` builds for it at radius 3."""
    from engine.newviews.llf import (
        candidate_directions,
        direction_to_lattice,
        lattice_index_table,
        octahedron_directions,
    )
    from engine.newviews.view_pass import _cone_tables

    table, dirs = lattice_index_table(f), octahedron_directions(f)
    off, idx, xyz = _cone_tables(f, table, dirs, 3)
    rng = np.random.default_rng(f)
    d = rng.normal(size=(3000, 3))
    d = np.vstack([d / np.linalg.norm(d, axis=1, keepdims=True), dirs, -dirs, np.eye(3), -np.eye(3)])
    out = np.empty(len(dirs) + 200, np.int64)
    for v in d:
        n = candidate_directions(v[0], v[1], v[2], f, 3, table, out)
        a, b, _ = direction_to_lattice(v[0], v[1], v[2], f)
        cell = (int(np.floor(a)) + f) * (2 * f + 1) + int(np.floor(b)) + f
        assert np.array_equal(idx[off[cell]:off[cell + 1]], out[:n])
    assert np.array_equal(xyz.T, dirs[idx])
