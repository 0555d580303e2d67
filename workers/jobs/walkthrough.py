"""Walkthrough jobs (see ``producer/walkthroughs.py`` for the split and the keys).

- :func:`walkthrough_bake_job` (``bake`` queue): loads the stored scene, chooses base viewpoints
  and time samples and renders the base range images (``engine.walkthrough.bake``), publishes
  ``bake.npz``;
- :func:`walkthrough_chunk_job` (``render`` queue): reconstructs frames ``start..stop-1`` (or
  path-traces them, ``WalkthroughRequest.path_traced``: ``engine.walkthrough.ground_truth``) and
  publishes them as EXR (linear), PNG (sRGB preview) and provenance PNG (8-bit codes);
- :func:`walkthrough_video_job` (``render`` queue): encodes every frame's PNG into ``video.mp4``
  (H.264, yuv420p, ffmpeg from ``imageio-ffmpeg``) and publishes the walkthrough manifest; a
  walkthrough planned from a quality contract then folds its frames' times into the calibration's
  time corrections.

Every job validates its payload, recomputes its artifact key (a mismatch fails the job at once),
returns early when its artifact already exists (jobs are at-least-once, artifacts written once),
reports progress and honours cancellation through :class:`workers.jobs.render.ProgressReporter`.
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import imageio_ffmpeg
import numpy as np
import OpenImageIO as oiio
from pydantic import ValidationError
from rq import get_current_job

from api_schemas.common import FrozenModel
from api_schemas.scene import BoxViewSpace, PathViewSpace, Scene
from api_schemas.walkthrough import WalkthroughRequest, WalkthroughSettings
from engine import ENGINE_VERSION
from engine.imageio import write_image
from engine.newviews.effects import analyze
from engine.reference import ReferenceRenderer
from engine.scene import CameraParams
from engine.walkthrough.animation import AnimatedScene
from engine.walkthrough.bake import WalkthroughBake, WalkthroughRenderer, bake_walkthrough, walkthrough_preset
from engine.walkthrough.ground_truth import path_traced_frame
from engine.walkthrough.viewspace import BoxSpace, PathSpace, PolygonSpace, ViewSpace
from producer.artifacts import blob_reader, get_scene, read_blob, read_manifest, write_artifact
from producer.names import walkthrough_bake_job_id, walkthrough_chunk_job_id
from producer.payloads import (
    InvalidPayload,
    WalkthroughBakeJobPayload,
    WalkthroughChunkJobPayload,
    WalkthroughVideoJobPayload,
    describe_validation_error,
)
from producer.store import ObjectStore
from producer.walkthrough_calibrations import read_contract, record_served_walkthrough
from producer.walkthroughs import (
    chunk_key,
    chunks,
    frames_bake_key,
    read_request,
    walkthrough_bake_key,
    walkthrough_inputs,
    walkthrough_key,
)
from workers.jobs.common import ProgressReporter, codes_png, dependency_note, log, worker_store
from workers.scene_loader import camera_params, load_animated_scene

__all__ = ["PathTracedFrames", "WalkthroughUnavailable", "engine_space", "load_stored_bake", "load_walkthrough_scene",
           "make_walkthrough_bake", "walkthrough_bake_job", "walkthrough_chunk_job", "walkthrough_video_job"]

EXR = "image/x-exr"
PNG = "image/png"
MP4 = "video/mp4"
PROVENANCE_CODES = {0: "hole", 1: "reprojected", 2: "foreground", 3: "background-fill", 4: "traced", 5: "sky"}
_TRACED, _SKY = 4, 5


class PathTracedFrames:
    """Renders walkthrough frames by path tracing (no bake): ``render(cam, time, frame)`` returns
    ``(radiance, provenance, stats)``, the provenance ``traced`` where a surface is seen and ``sky``
    elsewhere. One reference renderer (scene and BVH) per animation time, the last few kept. The
    indirect bounces are the default preset's, so the frames show the light the bases do."""

    def __init__(self, an: AnimatedScene, noise: float, seed: int = 0, bounces: int | None = None,
                 max_ms: float | None = None):
        self.an, self.noise, self.seed, self.max_ms = an, float(noise), int(seed), max_ms
        self.bounces = walkthrough_preset("medium").indirect_bounces if bounces is None else int(bounces)
        self._renderers: dict[float, tuple[ReferenceRenderer, str]] = {}

    def renderer(self, t: float) -> tuple[ReferenceRenderer, str]:
        """The reference renderer of the scene at time ``t``, and why its surfaces cannot receive
        indirect light ("" when they can: ``engine.newviews.effects.analyze``, per time, since
        lights and objects move)."""
        key = float(self.an.start) if self.an.is_static else float(t)
        got = self._renderers.get(key)
        if got is None:
            if len(self._renderers) >= 4:
                self._renderers.pop(next(iter(self._renderers)))
            rr = ReferenceRenderer(self.an.scene_at(key))
            got = self._renderers[key] = (rr, analyze(rr.scene).indirect_skip)
        return got

    def render(self, cam: CameraParams, t: float, frame: int) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
        rr, skip = self.renderer(t)
        img, covered, st = path_traced_frame(rr, cam, frame, self.seed, self.noise, self.bounces, skip,
                                             max_ms=self.max_ms)
        return img, np.where(covered, _TRACED, _SKY).astype(np.uint8), st

    def frame(self, cam: CameraParams, t: float, frame: int) -> _ChunkFrame:
        """Frame ``frame`` as the chunk job publishes it."""
        t0 = time.perf_counter()
        radiance, provenance, st = self.render(cam, t, frame)
        ms = 1e3 * (time.perf_counter() - t0)
        counts = {PROVENANCE_CODES[c]: int((provenance == c).sum()) for c in (_TRACED, _SKY)}
        return _ChunkFrame(radiance, provenance, ms, counts, {"path_noise": self.noise, "seed": self.seed},
                           st["rel_stderr_median"], str(st["indirect_skip"]), st["estimated_error"],
                           int(st["paths_mean"]))


@dataclass
class _ChunkFrame:
    """A frame as the chunk job publishes it: its pixels, provenance codes, render time, provenance
    counts, the metadata written into its images, and for a path-traced frame what it reached (its
    pixels' median relative standard error, its estimated LRMS, the paths per pixel its pilot sized)
    and why it traced no indirect light, if it did not."""

    radiance: np.ndarray
    provenance: np.ndarray
    ms: float
    counts: dict[str, int]
    meta: dict[str, Any]
    rel_stderr_median: float | None = None
    indirect_skip: str = ""
    estimated_error: float | None = None
    paths: int | None = None


@dataclass
class _BakedFrames:
    """Frames reconstructed from a walkthrough bake with a hole fill, as the chunk job publishes them."""

    renderer: WalkthroughRenderer
    fill: str
    bake_key: str

    def frame(self, cam: CameraParams, t: float, frame: int) -> _ChunkFrame:
        fr = self.renderer.render(cam, t, fill=self.fill, strict=False)  # the API checked eyes and times
        return _ChunkFrame(fr.radiance, fr.provenance, 1e3 * fr.timings["total"], dict(fr.counts),
                           {"fill": self.fill, "bake_key": self.bake_key})


class WalkthroughUnavailable(RuntimeError):
    """A walkthrough's bake or chunk is missing: the message names it and its job's state."""


_bakes: dict[str, WalkthroughBake] = {}
_scenes: dict[str, AnimatedScene] = {}


def _validate(model: type[FrozenModel], payload: dict[str, Any], what: str) -> Any:
    try:
        return model.model_validate(payload)
    except ValidationError as exc:
        raise InvalidPayload(f"invalid {what} payload: {describe_validation_error(exc)}") from None


def engine_space(scene: Scene) -> ViewSpace:
    """The engine view space of a schema scene (the API checked that it has one)."""
    vs = scene.view_space
    if vs is None:
        raise InvalidPayload("the scene has no view_space")
    if isinstance(vs, PathViewSpace):
        return PathSpace(np.asarray(vs.points, np.float64), vs.radius)
    if isinstance(vs, BoxViewSpace):
        return BoxSpace(np.asarray(vs.min, np.float64), np.asarray(vs.max, np.float64))
    return PolygonSpace(np.asarray(vs.vertices, np.float64), vs.eye_height)


def load_walkthrough_scene(store: ObjectStore, scene_id: str) -> tuple[Scene, AnimatedScene]:
    scene, mesh_shas, _ = get_scene(store, scene_id)
    an = _scenes.get(scene_id)
    if an is None:
        an = load_animated_scene(scene, blob_reader(store, mesh_shas))
        if len(_scenes) >= 4:
            _scenes.pop(next(iter(_scenes)))
        _scenes[scene_id] = an
    return scene, an


def walkthrough_bake_job(payload: dict[str, Any]) -> dict[str, Any]:
    """Decompose the view space and time interval, render the base images, publish ``bake.npz``."""
    t_start = time.perf_counter()
    p: WalkthroughBakeJobPayload = _validate(WalkthroughBakeJobPayload, payload, "walkthrough bake")
    if walkthrough_bake_key(p.scene_id, p.settings) != p.bake_key:
        raise InvalidPayload("bake_key does not match scene_id and settings")
    store = worker_store()
    existing = read_manifest(store, p.bake_key)
    if existing is not None:
        return {"artifact_key": p.bake_key, **existing.result}
    progress = ProgressReporter(get_current_job())
    progress.report(0.0, "loading scene", force=True)
    _, result = make_walkthrough_bake(store, p.scene_id, p.bake_key, p.settings, progress)
    result["timings"]["job_total"] = time.perf_counter() - t_start
    progress.report(1.0, "done", force=True, check=False)
    return {"artifact_key": p.bake_key, **result}


def make_walkthrough_bake(store: ObjectStore, scene_id: str, bkey: str, settings: WalkthroughSettings,
                          progress: Callable[[float, str], None]) -> tuple[WalkthroughBake, dict[str, Any]]:
    """Bake the scene for ``settings`` and publish the bake as artifact ``bkey`` (the walkthrough
    bake job's work; the walkthrough calibration bakes the presets it measures the same way).
    Returns the bake and the artifact's result (its ``timings.total`` is the bake's wall time)."""
    t_start = time.perf_counter()
    scene, an = load_walkthrough_scene(store, scene_id)
    params = walkthrough_preset(settings.quality, **settings.overrides())
    bake = bake_walkthrough(an, engine_space(scene), params, progress=progress)
    progress(0.95, "writing")  # a ProgressReporter raises here when the job was canceled
    with tempfile.TemporaryDirectory(prefix="ibr-wt-") as tmp:
        path = Path(tmp) / "bake.npz"
        bake.save(path)
        data = path.read_bytes()
    result = {"views": bake.views.tolist(), "direct_times": bake.direct_times.tolist(),
              "indirect_times": bake.indirect_times.tolist(), "face_res": bake.res,
              "indirect": {k: v for k, v in bake.indirect_stats.items() if k != "cubes"},
              "timings": {**bake.timings, "job_total": time.perf_counter() - t_start}}
    write_artifact(store, bkey, "walkthrough-bake", {"scene": scene_id}, settings.model_dump(mode="json"),
                   ENGINE_VERSION, {"bake.npz": (data, "application/octet-stream")}, result)
    return bake, result


def _stored_request(wkey: str) -> tuple[ObjectStore, WalkthroughRequest]:
    """The worker's store and the request stored for walkthrough ``wkey`` (InvalidPayload when none)."""
    store = worker_store()
    req = read_request(store, wkey)
    if req is None:
        raise InvalidPayload(f"walkthrough {wkey} has no stored request")
    return store, req


def load_stored_bake(store: ObjectStore, bkey: str) -> WalkthroughBake:
    """The stored walkthrough bake ``bkey`` (the last one loaded is kept in the process)."""
    b = _bakes.get(bkey)
    if b is not None:
        return b
    if read_manifest(store, bkey) is None:
        why = dependency_note(walkthrough_bake_job_id(bkey))
        raise WalkthroughUnavailable(f"walkthrough bake {bkey} is not available{why}")
    _bakes.clear()  # one bake per worker process (they can be GBs): drop the old one first
    with tempfile.TemporaryDirectory(prefix="ibr-wt-") as tmp:
        path = Path(tmp) / "bake.npz"
        path.write_bytes(read_blob(store, bkey, "bake.npz"))
        b = WalkthroughBake.load(path)
    _bakes[bkey] = b
    return b


def walkthrough_chunk_job(payload: dict[str, Any]) -> dict[str, Any]:
    """Reconstruct frames ``start..stop-1`` of a walkthrough and publish them."""
    t_start = time.perf_counter()
    p: WalkthroughChunkJobPayload = _validate(WalkthroughChunkJobPayload, payload, "walkthrough chunk")
    store, req = _stored_request(p.walkthrough_key)
    if (chunk_key(p.walkthrough_key, p.index, p.start, p.stop) != p.chunk_key
            or walkthrough_key(req) != p.walkthrough_key or (p.start, p.stop) not in chunks(req)
            or frames_bake_key(req) != p.bake_key):
        raise InvalidPayload("chunk payload does not match its walkthrough request")
    existing = read_manifest(store, p.chunk_key)
    if existing is not None:
        return {"artifact_key": p.chunk_key, **existing.result}
    progress = ProgressReporter(get_current_job())
    source: PathTracedFrames | _BakedFrames
    if req.path_traced is not None:
        progress.report(0.0, "loading the scene", force=True)
        source = PathTracedFrames(load_walkthrough_scene(store, req.scene_id)[1], req.path_traced.noise,
                                  req.path_traced.seed, max_ms=req.path_traced.max_ms)
    else:
        assert p.bake_key is not None
        progress.report(0.0, "loading bake", force=True)
        bake = load_stored_bake(store, p.bake_key)
        an = load_walkthrough_scene(store, req.scene_id)[1] if req.fill == "trace" else None
        source = _BakedFrames(WalkthroughRenderer(bake, an), req.fill, p.bake_key)
    noise: list[float] = []
    estimated: list[float] = []
    paths: list[int] = []
    skipped = ""  # why the path-traced frames traced no indirect light, when they did not
    blobs: dict[str, tuple[bytes, str]] = {}
    frame_ms: list[float] = []
    counts: dict[str, int] = {}
    with tempfile.TemporaryDirectory(prefix="ibr-wt-") as tmpdir:
        tmp = Path(tmpdir)
        n = p.stop - p.start
        for j, i in enumerate(range(p.start, p.stop)):
            f = req.frames[i]
            cam = camera_params(f.camera)
            fr = source.frame(cam, f.time, i)
            frame_ms.append(fr.ms)
            for k, v in fr.counts.items():
                counts[k] = counts.get(k, 0) + v
            if fr.rel_stderr_median is not None:
                noise.append(float(fr.rel_stderr_median))
                estimated.append(float(fr.estimated_error or 0.0))
                paths.append(int(fr.paths or 0))
            skipped = skipped or fr.indirect_skip
            meta = {"frame": i, "time": f.time, "camera": cam.to_dict(), **fr.meta, "engine_version": ENGINE_VERSION}
            for name, ctype in ((f"frame_{i:05d}.exr", EXR), (f"frame_{i:05d}.png", PNG)):
                path = tmp / name
                write_image(path, fr.radiance, metadata=meta)
                blobs[name] = (path.read_bytes(), ctype)
            blobs[f"provenance_{i:05d}.png"] = (codes_png(tmp / f"provenance_{i:05d}.png", fr.provenance), PNG)
            progress.report(0.05 + 0.9 * (j + 1) / n, f"frame {i}")
    progress.check_canceled()
    result: dict[str, Any] = {"frames": [p.start, p.stop], "frame_ms": frame_ms, "provenance": counts,
                              "provenance_codes": {str(k): v for k, v in PROVENANCE_CODES.items()},
                              "timings": {"job_total": time.perf_counter() - t_start}}
    if noise:  # what the path-traced frames reached: per frame, the pixels' median relative standard
        # error, the frame's estimated LRMS and the paths per pixel its pilot sized
        result.update(rel_stderr_median=noise, estimated_error=estimated, paths_per_pixel=paths)
        if skipped:
            result["indirect"] = {"state": "skipped", "reason": skipped}
    write_artifact(store, p.chunk_key, "walkthrough-chunk", {"walkthrough": p.walkthrough_key},
                   {"index": p.index, "start": p.start, "stop": p.stop}, ENGINE_VERSION, blobs, result)
    progress.report(1.0, "done", force=True, check=False)
    return {"artifact_key": p.chunk_key, **result}


def _fold_served(store: ObjectStore, scene_id: str, wkey: str, chunk_keys: list[str]) -> None:
    """A walkthrough planned from a quality contract: fold its frames' times into the calibration's
    corrections (``producer.walkthrough_calibrations.record_served_walkthrough``). Logged, not raised,
    when it fails: the walkthrough is published already, and a lost observation only slows the
    correction."""
    try:
        contract = read_contract(store, wkey)
        if contract is None:
            return
        chunk_ms = []
        for ck in chunk_keys:
            m = read_manifest(store, ck)
            chunk_ms.append([float(x) for x in (m.result.get("frame_ms") or [])] if m is not None else [])
        record_served_walkthrough(store, scene_id, contract, chunk_ms)
    except Exception:  # noqa: BLE001 - see the docstring
        log.warning("could not fold walkthrough %s's frame times into its calibration's corrections", wkey,
                    exc_info=True)


def walkthrough_video_job(payload: dict[str, Any]) -> dict[str, Any]:
    """Check every chunk, encode ``video.mp4`` and publish the walkthrough."""
    t_start = time.perf_counter()
    p: WalkthroughVideoJobPayload = _validate(WalkthroughVideoJobPayload, payload, "walkthrough video")
    store, req = _stored_request(p.walkthrough_key)
    if walkthrough_key(req) != p.walkthrough_key or frames_bake_key(req) != p.bake_key:
        raise InvalidPayload("video payload does not match its walkthrough request")
    existing = read_manifest(store, p.walkthrough_key)
    if existing is not None:
        return {"artifact_key": p.walkthrough_key, **existing.result}
    progress = ProgressReporter(get_current_job())
    keys = []
    for i, (a, b) in enumerate(chunks(req)):
        ck = chunk_key(p.walkthrough_key, i, a, b)
        if read_manifest(store, ck) is None:
            why = dependency_note(walkthrough_chunk_job_id(ck), "job")
            raise WalkthroughUnavailable(f"frames {a}..{b - 1} are missing{why}")
        keys.append(ck)
    w, h = req.frames[0].camera.width, req.frames[0].camera.height
    with tempfile.TemporaryDirectory(prefix="ibr-wt-") as tmpdir:
        tmp = Path(tmpdir)
        out = tmp / "video.mp4"
        writer = imageio_ffmpeg.write_frames(str(out), (w, h), fps=req.fps, codec="libx264", pix_fmt_in="rgb24",
                                             pix_fmt_out="yuv420p", macro_block_size=2, quality=7,
                                             ffmpeg_log_level="error")
        writer.send(None)
        try:
            for ck, (a, b) in zip(keys, chunks(req), strict=True):
                for i in range(a, b):
                    png = tmp / "f.png"
                    png.write_bytes(read_blob(store, ck, f"frame_{i:05d}.png"))
                    inp = oiio.ImageInput.open(str(png))
                    if inp is None:
                        raise RuntimeError(f"cannot read frame {i}: {oiio.geterror()}")
                    px = np.asarray(inp.read_image(0, 0, 0, 3, "uint8"))
                    inp.close()
                    writer.send(np.ascontiguousarray(px.reshape(h, w, 3)).tobytes())
                    progress.report(0.9 * (i + 1) / len(req.frames), f"encoding frame {i}")
        finally:
            writer.close()
        data = out.read_bytes()
    progress.check_canceled()
    result = {"chunks": keys, "frames": len(req.frames), "fps": req.fps, "width": w, "height": h,
              "timings": {"job_total": time.perf_counter() - t_start}}
    inputs, params = walkthrough_inputs(req)
    write_artifact(store, p.walkthrough_key, "walkthrough", inputs, params, ENGINE_VERSION, {"video.mp4": (data, MP4)},
                   result)
    _fold_served(store, req.scene_id, p.walkthrough_key, keys)
    progress.report(1.0, "done", force=True, check=False)
    return {"artifact_key": p.walkthrough_key, **result}
