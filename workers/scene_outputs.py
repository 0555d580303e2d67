"""What a scene leaves in the store besides its document, and removing it with the scene.

A scene's LDC bakes (``bakes/<scene>/<key>.json`` records, see :mod:`workers.bakes`), its
walkthroughs (``walkthroughs/<key>.json``, indexed per scene under
``walkthroughs-by-scene/<scene>/<key>``) and their walkthrough bakes are derived from the scene
alone: once the scene is gone nobody can request them again, so ``DELETE /v1/scenes/{id}``
removes them with it (the last owner's delete). Single renders stay in the content-addressed
artifact cache (they are small, and a re-upload of the same scene reuses them).

The delete is all-or-nothing with respect to running work: when any job of the scene or of one
of its bakes or walkthroughs is queued or running, :class:`SceneOutputsInUse` is raised before
anything is removed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from redis import Redis
from rq.job import Job
from rq.serializers import JSONSerializer

from workers.bakes import delete_bake, list_bakes
from workers.queues import ids_in_active_jobs
from workers.walkthroughs import (
    bake_job_id as walkthrough_bake_job_id,
)
from workers.walkthroughs import (
    delete_walkthrough,
    read_request,
    walkthrough_bake_key,
)

if TYPE_CHECKING:
    from api_schemas.service import BakeParams
    from workers.store import ObjectStore

__all__ = ["SceneOutputs", "SceneOutputsInUse", "delete_scene_outputs", "scene_outputs", "walkthrough_index_key"]


class SceneOutputsInUse(RuntimeError):
    """A job of the scene, of one of its bakes or of one of its walkthroughs is queued or running (HTTP 409)."""


def walkthrough_index_key(scene_id: str, wkey: str) -> str:
    """Marker object listing walkthrough ``wkey`` under its scene (written when it is requested)."""
    return f"walkthroughs-by-scene/{scene_id}/{wkey}"


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
        wbakes[walkthrough_bake_key(scene_id, req.bake)] = None
    out.walkthrough_bakes = list(wbakes)
    return out


def delete_scene_outputs(redis: Redis, store: ObjectStore, scene_id: str) -> SceneOutputs:
    """Remove every LDC bake, walkthrough and walkthrough bake of ``scene_id``; returns what was removed.

    Raises :class:`SceneOutputsInUse` (nothing removed) while a job that uses the scene or one of
    those outputs is queued or running."""
    from workers.artifacts import delete_artifact

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
        job = Job.fetch_many([walkthrough_bake_job_id(bkey)], connection=redis, serializer=JSONSerializer)[0]
        if job is not None:
            job.delete(remove_from_queue=True)
    for k in store.list(f"walkthroughs-by-scene/{scene_id}/"):  # markers of walkthroughs deleted earlier
        store.delete(k)
    return outs
