"""Effect analysis: what the scene needs, and that skipping the rest changes nothing."""

from __future__ import annotations

import json

import numpy as np
import trimesh

from engine.newviews.effects import analyze, plan_from_dict
from engine.newviews.ldc import bake_ldc
from engine.newviews.warp import warp_ldc
from engine.raycast import EmbreeCaster
from engine.scene import CameraParams
from tests.engine.scenes import from_trimesh, mat, quad, scene, sphere_mesh

PT = dict(type="point", position=(2.0, 3.0, 2.5), intensity=(5.0, 5.0, 5.0))
PT2 = dict(type="point", position=(-3.0, 1.0, 1.0), intensity=(2.0, 3.0, 4.0))
DIR = dict(type="directional", direction=(0.3, -1.0, -0.2), irradiance=(1.0, 0.9, 0.8))


def test_material_kinds_and_passes():
    sc = scene([(sphere_mesh((0, 0, 0), 0.5, 1), mat("d")),
                (sphere_mesh((2, 0, 0), 0.5, 1), mat("h", ks=(0.3, 0.3, 0.3), shininess=20.0)),
                (sphere_mesh((4, 0, 0), 0.5, 1), mat("g", kg=(0.2, 0.2, 0.2), gloss_exponent=50.0)),
                (sphere_mesh((6, 0, 0), 0.5, 1), mat("m", kr=(0.9, 0.9, 0.9)))], [PT])
    plan = analyze(sc)
    assert plan.material_kinds == ("diffuse", "highlight", "glossy", "mirror")
    assert plan.needs_view_pass and plan.needs_llf
    assert plan.occludable_lights == (True,)  # four objects: may shadow each other
    assert plan.closed_objects == (True, True, True, True)
    assert not plan.animated
    json.dumps(plan.to_dict())
    assert plan_from_dict(json.loads(json.dumps(plan.to_dict()))) == plan

    only_hl = scene([(sphere_mesh(), mat("h", ks=(0.3, 0.3, 0.3), shininess=20.0))], [PT])
    p2 = analyze(only_hl)
    assert p2.needs_view_pass and not p2.needs_llf
    diffuse = scene([(sphere_mesh(), mat("d"))], [PT], ambient=(0.1, 0.1, 0.1))
    p3 = analyze(diffuse)
    assert not p3.needs_view_pass and not p3.needs_llf and p3.has_ambient and not p3.has_emission


def test_occluders():
    # a single convex closed object, lights outside: nothing can shadow anything
    p = analyze(scene([(sphere_mesh(), mat("d"))], [PT, DIR]))
    assert p.convex_single_object and p.occludable_lights == (False, False) and not p.any_occludable
    # a light inside it can be blocked (from the outer side it can't reach anything, but stay conservative)
    p = analyze(scene([(sphere_mesh(), mat("d"))], [dict(type="point", position=(0, 0, 0), intensity=(1, 1, 1))]))
    assert p.occludable_lights == (True,)
    # non-convex closed object
    torus = from_trimesh(trimesh.creation.torus(1.0, 0.3, major_sections=16, minor_sections=8))
    p = analyze(scene([(torus, mat("d"))], [PT]))
    assert p.closed_objects == (True,) and not p.convex_single_object and p.occludable_lights == (True,)
    # an open surface is not closed; two objects are occluders
    p = analyze(scene([(quad((0, 0, 0), 1.0), mat("d")), (sphere_mesh((0, 1, 0), 0.3, 1), mat("d"))], [PT]))
    assert p.closed_objects == (False, True) and p.occludable_lights == (True,)
    # inverted winding (normals inward) is not "closed and outward"
    inv = from_trimesh(trimesh.creation.icosphere(1))
    inv = type(inv)(inv.vertices, np.ascontiguousarray(inv.faces[:, ::-1]), -inv.normals)
    assert analyze(scene([(inv, mat("d"))], [PT])).closed_objects == (False,)


def test_no_occluders_no_bits_same_image():
    sc = scene([(sphere_mesh((0.1, 0.2, 0.0), 1.0, subdivisions=3), mat("d", kd=(0.6, 0.5, 0.4)))],
               [PT, PT2, DIR, dict(type="rect", corner=(-1, 3, -1), edge_u=(2, 0, 0), edge_v=(0, 0, 2),
                                   radiance=(1, 1, 1))])
    plan = analyze(sc)
    assert not plan.any_occludable
    caster = EmbreeCaster(sc)
    lean = bake_ldc(sc, caster, 48, plan=plan)
    full = bake_ldc(sc, caster, 48, plan=plan, lights_visibility="force")
    assert lean.visibility_words == 0 and all(a.visibility.size == 0 for a in lean.axes)
    assert all(a.timings["shadow_rays"] == 0 for a in lean.axes)
    assert full.visibility_words == 1 and all(a.timings["shadow_rays"] > 0 for a in full.axes)
    # the outer side: the analytic bits equal the traced ones (light in front => visible)
    for a in full.axes:
        assert np.array_equal(a.diffuse[:, 0], lean.axes[a.axis].diffuse[:, 0])
    for cam in (CameraParams("perspective", (3.0, 2.0, 4.0), (0, 0, 0), (0, 1, 0), 96, 80, 40.0),
                CameraParams("orthographic", (0, 0, 5.0), (0, 0, 0), (0, 1, 0), 64, 64, ortho_height=2.6)):
        w1 = warp_ldc(lean, cam)
        w2 = warp_ldc(full, cam)
        assert np.array_equal(w1.radiance, w2.radiance)
        assert np.array_equal(w1.object_id, w2.object_id)
        assert (w1.object_id >= 0).sum() > 0.1 * cam.width * cam.height
