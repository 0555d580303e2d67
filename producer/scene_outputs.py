"""What a scene leaves in the store besides its document, and removing it with the scene.

A scene's LDC bakes (``bakes/<scene>/<key>.json`` records, see :mod:`producer.bakes`), its
walkthroughs (``walkthroughs/<key>.json``, indexed per scene under
``walkthroughs-by-scene/<scene>/<key>``) and their walkthrough bakes are derived from the scene
alone: once the scene is gone nobody can request them again, so ``DELETE /v1/scenes/{id}``
removes them with it (the last owner's delete), and with them the scene's calibrations for quality
contracts (``calibrations/<scene>/``). Single renders stay in the content-addressed
artifact cache (they are small, and a re-upload of the same scene reuses them).

The delete is all-or-nothing with respect to running work: when any job of the scene or of one
of its bakes or walkthroughs is queued or running, :class:`SceneOutputsInUse` is raised before
anything is removed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from redis import Redis

from api_schemas.service import BakeParams
from producer.artifacts import delete_artifact
from producer.bakes import delete_bake, list_bakes
from producer.errors import SceneOutputsInUse
from producer.names import walkthrough_bake_job_id
from producer.queue import fetch_job
from producer.status import ids_in_active_jobs
from producer.store import ObjectStore
from producer.walkthroughs import delete_walkthrough, frames_bake_key, read_request, walkthrough_index_key

__all__ = ["SceneOutputs", "delete_scene_outputs", "scene_outputs"]


@dataclass
class SceneOutputs:
    ldc_bakes: list[tuple[str, BakeParams]] = field(default_factory=list)
    walkthroughs: list[str] = field(default_factory=list)
    walkthrough_bakes: list[str] = field(default_factory=list)

    def keys(self) -> set[str]:
        return {k for k, _ in self.ldc_bakes} | set(self.walkthroughs) | set(self.walkthrough_bakes)


def scene_outputs(store: ObjectStore, scene_id: str) -> SceneOutputs:
    """The bakes and walkthroughs requested for ``scene_id`` that are still stored."""
    out = SceneOutputs(ldc_bakes=list_bakes(store, scene_id))
    wbakes: dict[str, None] = {}
    for k in store.list(f"walkthroughs-by-scene/{scene_id}/"):
        wkey = k.rsplit("/", 1)[-1]
        req = read_request(store, wkey)
        if req is None or req.scene_id != scene_id:
            continue
        out.walkthroughs.append(wkey)
        bkey = frames_bake_key(req)
        if bkey is not None:  # path-traced frames have none
            wbakes[bkey] = None
    out.walkthrough_bakes = list(wbakes)
    return out


def delete_scene_outputs(redis: Redis, store: ObjectStore, scene_id: str) -> SceneOutputs:
    """Remove every LDC bake, walkthrough and walkthrough bake of ``scene_id``; returns what was removed.

    Raises :class:`SceneOutputsInUse` (nothing removed) while a job that uses the scene or one of
    those outputs is queued or running."""
    outs = scene_outputs(store, scene_id)
    busy = ids_in_active_jobs(redis, ("scene_id", "scene", "walkthrough_key", "bake_key", "artifact_key")) & (
        outs.keys() | {scene_id})
    if busy:
        what = "the scene" if scene_id in busy else f"its bake or walkthrough {sorted(busy)[0]}"
        raise SceneOutputsInUse(f"scene {scene_id} is used by a queued or running job (for {what}); "
                                "cancel it or wait")
    for key, params in outs.ldc_bakes:
        delete_bake(redis, store, scene_id, key, params)
    for wkey in outs.walkthroughs:
        delete_walkthrough(redis, store, wkey)
        store.delete(walkthrough_index_key(scene_id, wkey))
    for bkey in outs.walkthrough_bakes:
        delete_artifact(store, bkey)
        job = fetch_job(redis, walkthrough_bake_job_id(bkey))
        if job is not None:
            job.delete(remove_from_queue=True)
    for k in store.list(f"walkthroughs-by-scene/{scene_id}/"):  # markers of walkthroughs deleted earlier
        store.delete(k)
    for k in store.list(f"calibrations/{scene_id}/"):  # quality-contract models (producer.calibrations)
        store.delete(k)
    return outs
