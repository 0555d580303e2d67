"""``producer.costs`` against what the engine and the jobs really do: triangles after tessellation against
the built scene, mesh file counts against the loader, the mirrored engine constants, the API's bake
estimate against the plan job's (on the built scene), the light count against the placement."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from api_schemas.datasets import GenerateRequest
from api_schemas.scene import Scene
from api_schemas.service import BakeParams, RenderRequest
from producer import costs
from producer.settings import Settings

REPO = Path(__file__).resolve().parents[2]


def _scene(objects: list[dict[str, Any]], lights: int = 1) -> Scene:
    return Scene.model_validate({
        "camera": {"type": "perspective", "eye": [0, 1, 6], "look_at": [0, 0, 0], "fov_y_deg": 45.0,
                   "width": 64, "height": 48},
        "materials": [{"name": "m", "kd": [0.5, 0.5, 0.5]}, {"name": "black", "kd": [0, 0, 0], "kr": [0.9, 0.9, 0.9]}],
        "lights": [{"type": "point", "position": [0, 3, 0.1 * i], "intensity": [1, 1, 1]} for i in range(lights)],
        "objects": objects,
    })


ALL_PRIMITIVES = [
    {"type": "sphere", "radius": 0.5, "subdivisions": 3, "material": "m", "center": [1, 0, 0]},
    {"type": "sphere", "radius": 0.3, "subdivisions": 0, "material": "m", "transform": {"scale": [2, 1, 1]}},
    {"type": "box", "size": [1, 2, 0.5], "material": "m", "transform": {"rotate_deg": [0, 30, 0],
                                                                       "translate": [0, 0, -1]}},
    {"type": "cylinder", "radius": 0.2, "height": 1, "segments": 17, "material": "m", "center": [-1, 0, 0]},
    {"type": "cylinder", "radius": 0.2, "height": 1, "segments": 9, "capped": False, "material": "m"},
    {"type": "plane", "size": [4, 4], "segments": 5, "material": "m", "center": [0, -1, 0]},
    {"type": "disk", "radius": 0.4, "segments": 23, "material": "m", "center": [0, 1.5, 0]},
    {"type": "mesh", "vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], "faces": [[0, 1, 2], [1, 3, 2]],
     "material": "m"},
]


def test_triangles_after_tessellation_are_the_built_scenes() -> None:
    from workers.scene_loader import load_scene

    for obj in ALL_PRIMITIVES:
        scene = _scene([obj])
        assert costs.scene_triangles(scene) == load_scene(scene).runtime.n_triangles, obj
    scene = _scene(ALL_PRIMITIVES)
    assert costs.scene_triangles(scene) == load_scene(scene).runtime.n_triangles


def test_ten_thousand_spheres_at_subdivision_8_count_without_building() -> None:
    obj = {"type": "sphere", "radius": 0.1, "subdivisions": 8, "material": "m"}
    scene = _scene([{**obj, "center": [0.3 * (i % 100), 0, 0.3 * (i // 100)]} for i in range(10_000)])
    assert costs.scene_triangles(scene) == 10_000 * 20 * 4 ** 8 == 13_107_200_000
    assert costs.scene_cost(costs.scene_triangles(scene)).peak_bytes > 6 << 40  # ~7 TiB: never build it


def test_mesh_file_counts_are_the_loaders() -> None:
    from engine.geometry.meshio import load_mesh_bytes

    files = [REPO / "samples/meshes/teapot.ply", *sorted((REPO / "samples/meshes/cbox").glob("*.obj"))[:3],
             *sorted((REPO / "samples/meshes/mitsuba_ref").glob("*.obj"))]
    assert len(files) >= 4
    for path in files:
        data = path.read_bytes()
        mesh, _ = load_mesh_bytes(data, file_type=path.suffix.lstrip("."), source=path.name)
        assert costs.mesh_triangles(path.name, data) == mesh.faces.shape[0], path.name
    # binary STL: the header's count; glTF: the index accessors
    stl = b"\0" * 80 + (3).to_bytes(4, "little") + b"\0" * 150
    assert costs.mesh_triangles("a.stl", stl) == 3
    gltf = {"meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
            "accessors": [{"count": 4}, {"count": 6}]}
    assert costs.mesh_triangles("a.gltf", json.dumps(gltf).encode()) == 2
    assert costs.mesh_triangles("a.ply", b"not a ply") == 0


def test_mirrored_engine_constants_agree() -> None:
    from engine.newviews.indirect import MAX_RAYS_PER_BATCH
    from engine.newviews.ldc import LDC_ATTR_BYTES
    from engine.newviews.ldi import LDI_SAMPLE_BYTES
    from engine.newviews.llf import LLF_SAMPLE_BYTES
    from engine.quality import CALIBRATION_SPP
    from engine.reference import ReferenceParams
    from workers.jobs.bake import (
        CAUSTIC_BYTES_PER_PHOTON,
        CAUSTIC_CPU_S_PER_PHOTON,
        INDIRECT_RAY_BYTES,
        PATHS_RATE_BOUNCES,
    )
    from workers.jobs.calibrate import LDC_REPEATS

    assert (costs.MAX_RAYS_PER_BATCH, costs.LDC_ATTR_BYTES, costs.LDI_SAMPLE_BYTES, costs.LLF_SAMPLE_BYTES) == (
        MAX_RAYS_PER_BATCH, LDC_ATTR_BYTES, LDI_SAMPLE_BYTES, LLF_SAMPLE_BYTES)
    assert (costs.INDIRECT_RAY_BYTES, costs.PATHS_RATE_BOUNCES) == (INDIRECT_RAY_BYTES, PATHS_RATE_BOUNCES)
    assert (costs.CAUSTIC_CPU_S_PER_PHOTON, costs.CAUSTIC_BYTES_PER_PHOTON) == (CAUSTIC_CPU_S_PER_PHOTON,
                                                                               CAUSTIC_BYTES_PER_PHOTON)
    assert costs.REFERENCE_CHUNK_PIXELS == ReferenceParams().chunk_pixels
    assert costs.CALIBRATION_SPP_TOTAL == sum(CALIBRATION_SPP) and costs.CALIBRATION_LDC_RUNS == LDC_REPEATS


def _sample(name: str) -> Scene:
    doc = json.loads((REPO / name).read_text())
    return Scene.model_validate(doc.get("scene", doc))


BAKE_SCENES = ["samples/scenes/mirror_box.json", "samples/scenes/static_room.json", "examples/scenes/spheres.json",
               "examples/walkthrough/room.json"]


@pytest.mark.parametrize("name", BAKE_SCENES)
def test_the_apis_bake_estimate_is_the_plan_jobs(name: str) -> None:
    """The API estimates from the document what the plan job estimates on the built scene: the LDC axis
    memory within 10 %, the expected samples and the indirect CPU time within a factor 1.6."""
    from engine.newviews.effects import analyze
    from workers.jobs.bake import bake_estimates, bake_plan_doc
    from workers.scene_loader import load_scene

    scene = _sample(name)
    params = BakeParams(ldc_resolution=128)
    runtime = load_scene(scene).runtime
    plan_doc = bake_plan_doc(runtime, params, analyze(runtime))
    plan = bake_estimates(runtime, params, plan_doc)
    api = costs.bake_cost(scene, params, costs.scene_triangles(scene), Settings().bake_paths_per_s)
    axis_ratio = api.detail["ldc_axis_bytes_max"] / max(plan["ldc_axis_bytes_max"])
    assert 0.9 <= axis_ratio <= 1.1, (axis_ratio, api.detail, plan)
    if plan_doc["indirect"]["state"] == "planned":
        samples_ratio = api.detail["ldc_samples_expected"] / sum(plan["ldc_samples_expected"])
        cpu_ratio = api.detail["indirect_cpu_s"] / plan["indirect_cpu_s"]
        assert 1 / 1.6 <= cpu_ratio <= 1.6, (name, samples_ratio, cpu_ratio, api.detail, plan)


@pytest.mark.parametrize(("region", "spacing"), [("upper_front_quarter", 10.0), ("hemisphere", 15.0),
                                                 ("sphere", 20.0), ("upper_front_quarter", 5.0)])
def test_the_light_count_is_the_placements(region: str, spacing: float) -> None:
    from engine.relighting.generate import LightPlacement

    req = GenerateRequest.model_validate({"scene_id": "0" * 64, "max_lights": 4096,
                                          "placement": {"region": region, "spacing_deg": spacing}})
    placed = len(LightPlacement(**req.placement.model_dump(exclude_none=True)).directions(None))
    assert 0.7 <= costs.light_count(req) / placed <= 1.4, (costs.light_count(req), placed)


def test_limits_name_the_estimate_the_limit_and_the_setting() -> None:
    settings = Settings(max_render_bytes=1 << 30, max_render_cpu_s=10)
    scene = _scene(ALL_PRIMITIVES)
    limits = costs.Limits.for_job(settings, "render")
    big = costs.render_cost(RenderRequest(scene_id="0" * 64), 7000, 7000, costs.scene_triangles(scene))
    with pytest.raises(costs.CostOverLimit) as err:
        costs.check(big, limits, "camera.height", "render a smaller image")
    assert "IBR_MAX_RENDER_BYTES = 1073741824" in err.value.message and "1.00 GiB" in err.value.message
    assert costs.size_text(big.peak_bytes) in err.value.message and err.value.field == "camera.height"
    cheap_rays = {"spp": 16, "glossy_samples": 1, "area_light_samples": 1}
    slow = costs.render_cost(RenderRequest(scene_id="0" * 64, params=cheap_rays), 1024, 1024)
    assert slow.peak_bytes < 1 << 30 and slow.cpu_s > 10
    with pytest.raises(costs.CostOverLimit, match="IBR_MAX_RENDER_CPU_S = 10"):
        costs.check(slow, limits, "params.spp", "fewer samples")
    tris = costs.Cost("x", triangles=settings.max_scene_triangles + 1)
    with pytest.raises(costs.CostOverLimit) as err:
        costs.check(tris, limits, "scene_id", "")
    assert err.value.type == "scene_too_large" and "IBR_MAX_SCENE_TRIANGLES" in err.value.message


def test_a_stride_prices_only_the_traced_share_of_the_indirect_pass() -> None:
    scene = _sample("samples/scenes/static_room.json")
    tri = costs.scene_triangles(scene)
    one, two = (costs.bake_cost(scene, BakeParams(ldc_resolution=128, indirect={"stride": s}), tri, 4.0e5)
                for s in (1, 2))
    assert two.detail["indirect_cpu_s"] == pytest.approx(one.detail["indirect_cpu_s"] / 4, rel=0.01)


def test_light_traced_caustics_are_priced_where_a_reference_render_traces_them() -> None:
    """A pinhole view of a scene with a rect light and a mirror, with indirect paths, prices
    ``light_paths`` light paths per sample; an orthographic view, a scene without mirror / glossy
    materials or without a rect light, direct light only, and ``light_paths`` 0 price none."""
    rect = {"type": "rect", "corner": [-0.5, 2.9, -0.5], "edge_u": [1, 0, 0], "edge_v": [0, 0, 1],
            "radiance": [5, 5, 5]}
    objects = [{"type": "sphere", "radius": 0.5, "material": "black"},
               {"type": "plane", "size": [4, 4], "material": "m", "center": [0, -1, 0]}]
    caustic = Scene.model_validate({**_scene(objects).model_dump(mode="json"), "lights": [rect]})
    diffuse = Scene.model_validate({**caustic.model_dump(mode="json"),
                                    "materials": [{"name": "m", "kd": [0.5] * 3}, {"name": "black", "kd": [0.1] * 3}]})
    no_rect = _scene(objects)
    ortho = {"type": "orthographic", "eye": [0, 1, 6], "look_at": [0, 0, 0], "ortho_height": 4.0, "width": 64,
             "height": 48}
    assert costs.scene_light_traced(caustic, caustic.camera)
    assert not costs.scene_light_traced(diffuse, diffuse.camera)
    assert not costs.scene_light_traced(no_rect, no_rect.camera)
    assert not costs.scene_light_traced(caustic, Scene.model_validate(
        {**caustic.model_dump(mode="json"), "camera": ortho}).camera)

    def cpu(light_paths: float, indirect: int, traced: bool = True) -> float:
        params = {"spp": 4, "indirect_samples": indirect, "light_paths": light_paths}
        req = RenderRequest(scene_id="0" * 64, params=params)
        return costs.render_cost(req, 256, 256, 1000, light_traced=traced).cpu_s

    base = cpu(0.0, 4)
    assert cpu(1.0, 4, traced=False) == base and cpu(1.0, 0) == cpu(0.0, 0)
    one, four = cpu(1.0, 4) - base, cpu(4.0, 4) - base
    assert one == pytest.approx(256 * 256 * 4 * costs.REFERENCE_CPU_S_PER_LIGHT_PATH, rel=1e-9)
    assert four == pytest.approx(4 * one, rel=1e-9)
    req = RenderRequest(scene_id="0" * 64, params={"spp": 4, "indirect_samples": 4, "light_paths": 2})
    assert "2 light paths per sample" in costs.render_cost(req, 64, 64, light_traced=True).kind
