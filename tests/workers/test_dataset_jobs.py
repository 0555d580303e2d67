"""The dataset job functions called directly (no RQ): payload checks, the baked-dataset
serialisation round trip, geometry from a pinhole depth map and from a stored scene, and bad
datasets failing the bake with the engine's message."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from api_schemas.datasets import DatasetBakeParams, DatasetManifest, RelightRequest
from producer.datasets import bake_artifact_key, commit_dataset, relight_artifact_key, store_file
from producer.payloads import DatasetBakeJobPayload, InvalidPayload, RelightJobPayload
from producer.store import ObjectStore, open_store
from tests.service.api.test_datasets import write_bytes
from workers.jobs import datasets as jobs
from workers.jobs.common import set_worker_store

H, W = 12, 16


@pytest.fixture
def store(tmp_path: Path) -> Iterator[ObjectStore]:
    s = open_store(str(tmp_path / "store"))
    previous = set_worker_store(s)
    jobs.baked_cache().clear()
    yield s
    set_worker_store(previous)


def _lambert_dataset(store: ObjectStore, camera: dict[str, Any], geometry: dict[str, Any], pts: np.ndarray,
                     lights: np.ndarray, files: dict[str, bytes] | None = None) -> str:
    """A Lambertian surface (normal +z, albedo 0.5) lit by point lights, stored as float EXRs."""
    files = dict(files or {})
    images = []
    for i, lp in enumerate(lights):
        d = lp - pts
        dist2 = np.sum(d * d, axis=2)
        cos = np.clip(d[:, :, 2] / np.sqrt(dist2), 0, None)
        img = np.repeat((0.5 / np.pi * cos * 10.0 / dist2)[:, :, None], 3, axis=2).astype(np.float32)
        name = f"img{i}.exr"
        files[name] = write_bytes(img, ".exr", "float")
        images.append({"file": name, "position": [float(x) for x in lp], "intensity": 10.0})
    shas = {n: str(store_file(store, b, max_pixels=10**6)["sha256"]) for n, b in files.items()}
    for img in images:
        img["sha256"] = shas[img["file"]]
    if "file" in geometry:
        geometry = {**geometry, "sha256": shas[geometry["file"]]}
    manifest = DatasetManifest.model_validate({"images": images, "transfer": "linear", "camera": camera,
                                               "geometry": geometry})
    return commit_dataset(store, manifest, None)[0].id


def _grid_lights(n: int = 5) -> np.ndarray:
    th, ph = np.meshgrid(np.radians(np.linspace(10, 70, n)), np.radians(np.linspace(0, 360, 2 * n, endpoint=False)))
    d = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=-1).reshape(-1, 3)
    return np.vstack([[0.0, 0.0, 1.0], d]) * 18.0


def test_pinhole_depth_dataset_bakes_and_relights(store: ObjectStore) -> None:
    fx = fy = 20.0
    cx, cy = W / 2, H / 2
    z = 10.0
    # camera at (0, 0, 10) looking down -z: world_from_camera flips y and z (OpenCV frame)
    pose = [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, z], [0, 0, 0, 1]]
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    pts = np.stack([(xs - cx) / fx * z, -(ys - cy) / fy * z, np.zeros_like(xs)], axis=-1)
    depth = np.full((H, W), z, np.float32)
    cam = {"type": "pinhole", "fx": fx, "fy": fy, "cx": cx, "cy": cy, "width": W, "height": H,
           "world_from_camera": pose}
    did = _lambert_dataset(store, cam, {"type": "depth", "file": "depth.exr", "depth_kind": "z"}, pts,
                           _grid_lights(), {"depth.exr": write_bytes(depth, ".exr", "float")})
    ds = jobs.load_illumination_dataset(store, did)
    assert np.allclose(ds.points, pts, atol=1e-9) and ds.mask is not None and ds.mask.all()
    params = DatasetBakeParams(half=False)
    key = bake_artifact_key(did, params)
    res = jobs.bake_job(DatasetBakeJobPayload(dataset_id=did, params=params, artifact_key=key).model_dump(mode="json"))
    assert res["artifact_key"] == key and res["counts"]["n_lights"] == 51
    payload = DatasetBakeJobPayload(dataset_id=did, params=params, artifact_key=key).model_dump(mode="json")
    again = jobs.bake_job(payload)
    assert again["report"] == res["report"]  # the stored result, no second bake
    # a light between dataset lights: close to the analytic Lambertian value
    req = RelightRequest.model_validate({"dataset_id": did, "bake": {"half": False},
                                         "lights": [{"type": "point", "position": [1.0, 0.5, 17.0],
                                                     "intensity": [10, 10, 10]}]})
    out = jobs.relight_job(RelightJobPayload(request=req, artifact_key=relight_artifact_key(req))
                           .model_dump(mode="json"))
    assert out["counts"]["n_outside"] == 0 and out["exact"] is False


def test_baked_bytes_round_trip_relights_identically(store: ObjectStore) -> None:
    from engine.relighting.bake import bake_dataset
    from engine.relighting.lights import PointLight
    from engine.relighting.relight import relight

    cam = {"type": "orthographic", "eye": [0, 0, 10], "look_at": [0, 0, 0], "ortho_height": float(H),
           "width": W, "height": H}
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    pts = np.stack([xs - W / 2, H / 2 - ys, np.zeros_like(xs)], axis=-1)
    depth = np.full((H, W), 10.0, np.float32)
    did = _lambert_dataset(store, cam, {"type": "depth", "file": "d.exr"}, pts, _grid_lights(),
                           {"d.exr": write_bytes(depth, ".exr", "float")})
    ds = jobs.load_illumination_dataset(store, did)
    assert np.allclose(ds.points, pts)
    light = [PointLight((0.7, -0.4, 16.5), (3.0, 3.0, 3.0))]
    layouts = []
    for kw in ({"layout": "pixel_major"}, {"layout": "tiled"}, {"half": False}, {"compress": 0.05}):
        baked = bake_dataset(ds, **kw)
        back = jobs.baked_from_bytes(jobs.baked_to_bytes(baked), baked.report)
        a, b = relight(baked, light), relight(back, light)
        assert np.array_equal(a.image, b.image) and a.n_outside == b.n_outside, kw
        assert back.layout == baked.layout and back.nbytes == baked.nbytes
        layouts.append(baked.layout)
    assert "lowrank" in layouts, layouts  # Lambertian images are low rank per tile: the compressed store is used


def test_scene_geometry_is_ray_cast(store: ObjectStore) -> None:
    from api_schemas.scene import Scene
    from engine.relighting.dataset import points_from_depth
    from engine.relighting.generate import surface_aovs
    from producer.artifacts import put_scene
    from tests.service.api.conftest import small_scene
    from workers.scene_loader import camera_params, load_scene

    doc = small_scene()
    scene = Scene.model_validate(doc)
    sid = put_scene(store, scene, {}, None).id
    loaded = load_scene(scene)
    cam = camera_params(scene.camera)
    depth, _ = surface_aovs(loaded.runtime, cam)
    pts, valid = points_from_depth(depth, cam, depth_kind="distance")
    lights = _grid_lights() + np.array([0.0, 0.5, 0.0])
    did = _lambert_dataset(store, doc["camera"], {"type": "scene", "scene_id": sid},
                           np.where(valid[:, :, None], pts, 0.0), lights)
    ds = jobs.load_illumination_dataset(store, did)
    assert ds.mask is not None and np.array_equal(ds.mask, valid)
    assert np.allclose(ds.points[valid], pts[valid], rtol=0, atol=1e-5)


def test_bad_payloads_and_bad_datasets_fail_clearly(store: ObjectStore) -> None:
    with pytest.raises(InvalidPayload, match="dataset_id"):
        jobs.bake_job({"v": 1, "params": {}, "artifact_key": "0" * 64})
    cam = {"type": "orthographic", "eye": [0, 0, 10], "look_at": [0, 0, 0], "ortho_height": float(H),
           "width": W, "height": H}
    ys, xs = np.mgrid[0:H, 0:W] + 0.5
    pts = np.stack([xs - W / 2, H / 2 - ys, np.zeros_like(xs)], axis=-1)
    ring = np.array([[20 * np.cos(a), 20 * np.sin(a), 3.0] for a in np.linspace(0, 2 * np.pi, 6, endpoint=False)])
    did = _lambert_dataset(store, cam, {"type": "depth", "file": "d.exr"}, pts, ring,
                           {"d.exr": write_bytes(np.full((H, W), 10.0, np.float32), ".exr", "float")})
    params = DatasetBakeParams()
    with pytest.raises(InvalidPayload, match="does not match"):
        bad_key = DatasetBakeJobPayload(dataset_id=did, params=params, artifact_key="1" * 64)
        jobs.bake_job(bad_key.model_dump(mode="json"))
    from engine.errors import InvalidInputError

    # six lights on one circle: the bake refuses it with the engine's message, nothing is stored
    with pytest.raises(InvalidInputError, match="coplanar"):
        jobs.bake_job(DatasetBakeJobPayload(dataset_id=did, params=params, artifact_key=bake_artifact_key(did, params))
                      .model_dump(mode="json"))
    assert not store.list("artifacts/")
