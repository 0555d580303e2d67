"""What every job body shares: progress and cancellation, loading a stored scene, JSON-safe results,
the worker's object store, the state of the job a missing input was expected from, integer codes
as PNG.

Job bodies (``render``, ``bake``, ``datasets``, ``walkthrough``) import from here, never from each
other's helpers.
"""

from __future__ import annotations

import json
import logging
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import OpenImageIO as oiio
from rq import get_current_job
from rq.job import Job

from producer.artifacts import blob_reader, get_scene
from producer.calibrations import record_served
from producer.queue import fetch_job
from producer.settings import open_settings_store
from producer.status import cancel_key, job_public
from producer.store import NotFound, ObjectStore
from workers.scene_loader import LoadedScene, load_scene, load_scene_at

__all__ = [
    "LOAD_END",
    "RENDER_END",
    "JobCanceled",
    "ProgressReporter",
    "SceneNotFound",
    "codes_png",
    "dependency_note",
    "fold_served",
    "json_safe",
    "load_stored_scene",
    "set_worker_store",
    "worker_store",
]

# Share of a render job's progress bar per stage (loading and writing are short next to rendering).
LOAD_END = 0.05
RENDER_END = 0.95

_store: ObjectStore | None = None

log = logging.getLogger("workers.jobs")


class JobCanceled(Exception):
    """Raised from the progress callback when the job's cancellation was requested."""


class SceneNotFound(LookupError):
    """The payload names a scene the store does not hold."""


def dependency_note(job_id: str, label: str = "its job") -> str:
    """`` (<label> <id> is <state>[: <error>])`` for the job a missing input was expected from, read
    through the running job's connection; ``""`` outside a job or when that job is not known."""
    job = get_current_job()
    if job is None:
        return ""
    dep = fetch_job(job.connection, job_id)
    if dep is None:
        return ""
    pub = job_public(dep)
    return f" ({label} {pub.id} is {pub.state}{': ' + pub.error if pub.error else ''})"


def codes_png(path: Path, codes: Any, attributes: Mapping[str, str | int] | None = None) -> bytes:
    """Exact integer codes in an 8-bit single-channel PNG written to ``path`` (OpenImageIO, no sRGB
    encoding), with ``attributes`` set on its spec in order; returns the file's bytes."""
    arr = np.ascontiguousarray(codes, dtype=np.uint8)
    out = oiio.ImageOutput.create(str(path))
    if out is None:
        raise RuntimeError(f"OpenImageIO cannot write PNG: {oiio.geterror()}")
    spec = oiio.ImageSpec(arr.shape[1], arr.shape[0], 1, "uint8")
    for name, value in (attributes or {}).items():
        spec.attribute(name, value)
    if not out.open(str(path), spec) or not out.write_image(arr[:, :, None]):
        err = out.geterror()
        out.close()
        raise RuntimeError(f"writing {path.name} failed: {err}")
    out.close()
    return path.read_bytes()


def worker_store() -> ObjectStore:
    """This process's object store (from its settings, never from a payload), opened once."""
    global _store
    if _store is None:
        _store = open_settings_store()
    return _store


def set_worker_store(store: ObjectStore | None) -> ObjectStore | None:
    """Replace this process's object store (None: open it from the settings on next use); returns
    the previous one (the warm-up runs the jobs against a scratch store, then puts it back)."""
    global _store
    previous, _store = _store, store
    return previous


def load_stored_scene(store: ObjectStore, scene_id: str, time: float | None = None) -> LoadedScene:
    """A stored scene and its meshes, loaded for the engine: as stored, or with ``time`` at that moment
    of its animation (``workers.scene_loader.load_scene_at``). :class:`SceneNotFound` when absent."""
    try:
        scene, mesh_shas, _ = get_scene(store, scene_id)
    except NotFound as exc:
        raise SceneNotFound(f"scene {scene_id} is not in the store") from exc
    if time is not None:
        return load_scene_at(scene, time, blob_reader(store, mesh_shas))
    return load_scene(scene, blob_reader(store, mesh_shas))


def json_safe(value: Any) -> Any:
    """Plain JSON types only (numpy scalars and tuples come out of engine reports)."""
    return json.loads(json.dumps(value, default=lambda o: o.item() if hasattr(o, "item") else str(o)))


class ProgressReporter:
    """``progress(fraction, stage)`` for the engine: writes ``job.meta["progress"]`` (fraction,
    stage, eta_s from the elapsed time) at most every ``min_interval`` seconds and raises
    :class:`JobCanceled` when the job's cancel flag is set or RQ marked it canceled.

    Without a current RQ job (direct calls, tests) it only keeps the numbers.
    """

    def __init__(self, job: Job | None, min_interval: float = 0.25):
        self.job = job
        self.min_interval = min_interval
        self.t0 = time.monotonic()
        self._last_save = -1e9
        self._last_check = -1e9
        self.fraction = 0.0
        self.stage = "starting"

    def __call__(self, fraction: float, stage: str) -> None:
        self.report(LOAD_END + (RENDER_END - LOAD_END) * fraction, stage)

    def report(self, fraction: float, stage: str, force: bool = False, check: bool = True) -> None:
        self.fraction = min(1.0, max(0.0, float(fraction)))
        self.stage = stage
        now = time.monotonic()
        if self.job is None:
            return
        if check and (force or now - self._last_check >= self.min_interval):
            self._last_check = now
            self.check_canceled()
        if force or now - self._last_save >= self.min_interval:
            self._last_save = now
            self._save(now)

    def _save(self, now: float) -> None:
        assert self.job is not None
        elapsed = now - self.t0
        eta = elapsed * (1.0 - self.fraction) / self.fraction if self.fraction > 1e-6 else None
        self.job.meta["progress"] = {"fraction": round(self.fraction, 4), "stage": self.stage,
                                     "eta_s": None if eta is None else round(eta, 2)}
        self.job.save_meta()  # type: ignore[no-untyped-call]

    def check_canceled(self) -> None:
        job = self.job
        if job is None:
            return
        with job.connection.pipeline(transaction=False) as p:
            p.exists(cancel_key(job.id))
            p.hget(job.key, "status")
            flag, status = p.execute()
        if flag or status in (b"canceled", "canceled"):
            job.meta["cancel_requested"] = True
            job.meta["progress"] = {"fraction": round(self.fraction, 4), "stage": "canceled", "eta_s": None}
            job.save_meta()  # type: ignore[no-untyped-call]
            raise JobCanceled(f"job {job.id} was canceled on request")


def fold_served(store: ObjectStore, scene_id: str, contract: Mapping[str, Any], *, achieved_ms: float | None = None,
                measured_error: float | None = None) -> None:
    """``producer.calibrations.record_served`` after a job's result is stored: a failure to fold the
    observation is logged, not raised (the result is published already; a lost observation only
    slows the correction)."""
    try:
        record_served(store, scene_id, dict(contract), achieved_ms=achieved_ms, measured_error=measured_error)
    except Exception:  # noqa: BLE001 - see the docstring
        log.warning("could not fold a served measurement into scene %s's contract corrections", scene_id,
                    exc_info=True)
