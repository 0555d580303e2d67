"""A reference render of an animated scene at an animation time (``RenderRequest.time``): the render
job publishes the image of ``AnimatedScene.scene_at(time)``, which differs from another moment where an
object moves; without a time the job renders the scene as stored, under the key it always had."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from api_schemas.scene import Scene
from api_schemas.service import RenderRequest
from engine.errors import InvalidInputError
from engine.imageio import decode_image
from engine.reference import ReferenceParams, ReferenceRenderer
from producer.artifacts import mesh_paths, put_scene, read_blob, read_manifest
from producer.payloads import RenderJobPayload
from producer.renders import render_artifact_key
from producer.settings import reset_settings_cache
from producer.store import ObjectStore, open_store
from workers.jobs import render
from workers.jobs.common import set_worker_store
from workers.scene_loader import directory_resolver, load_animated_scene, load_scene, load_scene_at

SAMPLES = Path(__file__).resolve().parents[2] / "samples"
SAMPLE = SAMPLES / "scenes" / "cornell_animated.json"
W = H = 24
MESHES = directory_resolver(SAMPLES)


def _scene() -> Scene:
    doc = json.loads(SAMPLE.read_text())
    # from outside the open front, looking down at the floor where the ball and the cube move
    doc["camera"] = {**doc["camera"], "eye": [278, 273, -200], "look_at": [250, 60, 150], "fov_y_deg": 50,
                     "width": W, "height": H}
    return Scene.model_validate(doc)


@pytest.fixture
def stored(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Iterator[tuple[ObjectStore, str]]:
    monkeypatch.setenv("IBR_STORE_URL", str(tmp_path))
    reset_settings_cache()
    previous_store = set_worker_store(None)
    previous_cache = render.set_renderer_cache(None)
    try:
        store = open_store(str(tmp_path))
        meshes = {p: MESHES(p)[0] for p in mesh_paths(_scene())}
        yield store, put_scene(store, _scene(), meshes, owner=None).id
    finally:
        render.set_renderer_cache(previous_cache)
        set_worker_store(previous_store)
        reset_settings_cache()


def _job(store: ObjectStore, sid: str, time: float | None) -> tuple[str, dict[str, np.ndarray]]:
    req = RenderRequest(scene_id=sid, params={"spp": 1}, time=time)
    key = render_artifact_key(req)
    render.render_job(RenderJobPayload(request=req, artifact_key=key).model_dump(mode="json"))
    assert read_manifest(store, key) is not None
    images = {name: decode_image(f"{name}.exr", read_blob(store, key, f"{name}.exr"))[0]
              for name in ("radiance", "object_id")}
    return key, images


def _direct(runtime: object) -> np.ndarray:
    out = ReferenceRenderer(runtime).render(load_scene(_scene(), MESHES).camera, ReferenceParams(spp=1))  # type: ignore[arg-type]
    return np.asarray(out.radiance, dtype=np.float32)


def test_a_render_at_a_time_is_the_scene_at_that_time(stored: tuple[ObjectStore, str]) -> None:
    store, sid = stored
    key_2, at_2 = _job(store, sid, 2.0)
    key_0, at_0 = _job(store, sid, 0.0)
    assert key_2 != key_0
    animated = load_animated_scene(_scene(), MESHES)
    # the artifact holds exactly the image of scene_at(t) rendered directly
    np.testing.assert_array_equal(at_2["radiance"][..., :3], _direct(animated.scene_at(2.0)))
    np.testing.assert_array_equal(at_0["radiance"][..., :3], _direct(animated.scene_at(0.0)))
    # the ball moves between t = 0 and t = 2 (the cube turns, the lamp moves): other pixels see other objects
    ball = animated.object_names.index("ball")
    assert 0 < np.count_nonzero(at_0["object_id"] == ball) < np.count_nonzero(at_2["object_id"] == ball)
    assert np.count_nonzero(at_2["object_id"] != at_0["object_id"]) > 10
    assert float(np.abs(at_2["radiance"] - at_0["radiance"]).mean()) > 1e-3
    manifest = read_manifest(store, key_2)
    assert manifest is not None and manifest.params["time"] == 2.0


def test_without_a_time_the_scene_renders_as_stored_under_its_old_key(stored: tuple[ObjectStore, str]) -> None:
    store, sid = stored
    req = RenderRequest(scene_id=sid, params={"spp": 1})
    assert "time" not in req.model_dump(mode="json")  # the artifact key's params: as before the field existed
    key, as_stored = _job(store, sid, None)
    assert key == render_artifact_key(req)
    np.testing.assert_array_equal(as_stored["radiance"][..., :3], _direct(load_scene(_scene(), MESHES).runtime))


def test_a_time_outside_the_animation_is_refused_naming_the_interval() -> None:
    with pytest.raises(InvalidInputError, match=r"time: 5 is outside the animation interval \[0, 4\]"):
        load_scene_at(_scene(), 5.0, MESHES)
    static = _scene().model_copy(update={"animation": None})
    with pytest.raises(InvalidInputError, match="time: the scene has no animation"):
        load_scene_at(static, 0.0, MESHES)
