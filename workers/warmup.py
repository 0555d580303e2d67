"""Render worker warm-up: run every engine path of the render queue's jobs once, on tiny data.

numba compiles a kernel the first time it is called with a new type signature (``cache=True``
writes the result to numba's disk cache, ``NUMBA_CACHE_DIR``). With an empty cache -- a fresh
deployment, a new container image, a new CPU model -- the first LDC render of a render worker
compiles for about a minute and the first relight of each store kind for ~30 s, inside the
user's request. :func:`warm_up` moves that cost out of the requests: ``python -m workers.runner
--queue render`` starts ``python -m workers.warmup --publish <worker>`` in background processes
(:data:`LANES`: two on two or more cores) as it starts taking jobs; they fill numba's disk cache,
from which the worker's jobs load the kernels, and publish per-method readiness in Redis
(:func:`warm_up_published`, ``workers.warmup_readiness``). With a warm disk cache the warm-up
only loads the kernels (a few seconds).

What it runs -- the render queue's own job functions, not look-alikes, so the compiled
signatures are the ones the jobs need (same dtypes, array layouts, kernel variants, thread
settings):

- ``workers.jobs.render.render_job`` for ``reference`` (a 1-chunk image, its kernels split over
  the cores, and a 2-chunk image, two pipelines in threads, with mirror, glossy and indirect
  paths and the light-traced caustics of the rect light in the mirror: the same kernels, each
  compiled once), and for ``ldc``, ``ldc+llf``, ``ldc+ibrt:1``, ``ldc+ibrt:2`` from a
  bake with a light field, plus ``ldc`` from a bake without one (the highlight pass then takes
  other parameter types); every output encoder (preview PNG, EXRs, provenance PNG);
- the bake those renders read: the bake queue's part jobs (``bake_ldc_axis_job``,
  ``bake_llf_views_job``) at an LDC resolution of 8 and an LLF of 6 directions at 4 px, published
  as the bake jobs publish them and read back by the render job's ``load_bake`` (npz round trip);
- ``workers.jobs.datasets.relight_job`` on a synthetic illumination dataset baked
  (``engine.relighting.bake.bake_dataset``, stored as ``bake_job`` stores it) into every store the
  service can produce -- float16 / float32 x pixel-major / tiled, and low-rank -- each under a
  point, a directional, a rect and an environment light (interpolating kernel) and under a
  light exactly at a dataset light (the exact-hit kernel);
- ``workers.jobs.datasets.composite_job`` (two relights and ``engine.relighting.composite``);
- a walkthrough of the warm-up scene with a moving sphere: ``bake_walkthrough`` (the walkthrough
  bake job's engine call) and ``WalkthroughRenderer.render`` with every fill mode (the chunk job's),
  and frames path-traced without a bake (``PathTracedFrames``, the chunk job's for ``path_traced``).

The scene, the dataset and the images are made in code; everything is written to a scratch
object store in a temporary directory (RAM-backed when ``/dev/shm`` is writable) that is
deleted afterwards, and the job modules' store and caches are swapped for the warm-up and
restored (the warm-up process's own job modules; the worker's store sees no writes).

Each step reports its wall time and how many numba signatures appeared in the engine's
dispatchers, split into compiled (numba disk cache misses) and loaded from the disk cache.
``python -m workers.warmup`` runs it and prints the report (e.g. at image build time with
``NUMBA_CACHE_DIR`` set, to ship a populated cache; docs/service-design.md).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import hashlib
import json
import logging
import math
import os
import sys
import tempfile
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numba.core.dispatcher import Dispatcher

from api_schemas.datasets import CompositeRequest, DatasetBakeParams, RelightRequest
from api_schemas.scene import Scene
from api_schemas.service import BakeParams, RenderRequest
from engine import ENGINE_VERSION
from engine.imageio import encode_image
from engine.newviews.effects import analyze
from engine.relighting.bake import bake_dataset
from engine.relighting.dataset import IlluminationDataset
from engine.walkthrough.bake import WalkthroughRenderer, bake_walkthrough, walkthrough_preset
from engine.walkthrough.reconstruct import FILL_MODES
from producer.artifacts import put_scene, write_artifact
from producer.bakes import bake_key, part_key, plan_parts
from producer.datasets import bake_artifact_key, composite_artifact_key, relight_artifact_key, store_file
from producer.names import DATASET_BAKE_KIND
from producer.payloads import CompositeJobPayload, RelightJobPayload, RenderJobPayload
from producer.renders import render_artifact_key
from producer.store.local import LocalStore
from workers.jobs.bake import bake_ldc_axis_job, bake_ldc_indirect_job, bake_llf_views_job, bake_plan_doc
from workers.jobs.common import json_safe, load_stored_scene, set_worker_store
from workers.jobs.datasets import NPZ, baked_to_bytes, composite_job, relight_job, set_caches
from workers.jobs.render import render_job, set_renderer_cache
from workers.jobs.walkthrough import PathTracedFrames, engine_space
from workers.scene_loader import camera_params, load_animated_scene
from workers.warmup_steps import LANES, NEEDS, STEPS, lanes_for, needs_of

__all__ = [
    "LANES",
    "NEEDS",
    "STEPS",
    "WarmupReport",
    "WarmupStep",
    "compile_stats",
    "engine_dispatchers",
    "lanes_for",
    "main",
    "needs_of",
    "signature_counts",
    "warm_up",
]

log = logging.getLogger("workers.warmup")

# ------------------------------------------------------------------------------ numba bookkeeping


def engine_dispatchers() -> dict[str, Any]:
    """Every numba dispatcher of the imported engine modules by ``module.name``, each dispatcher once."""
    found: dict[str, Any] = {}
    seen: set[int] = set()
    for mod_name, mod in sorted(sys.modules.items()):
        if mod is None or not (mod_name == "engine" or mod_name.startswith("engine.")):
            continue
        for attr, value in sorted(vars(mod).items()):
            if isinstance(value, Dispatcher) and id(value) not in seen:
                seen.add(id(value))
                found[f"{mod_name}.{attr}"] = value
    return found


def signature_counts() -> dict[str, int]:
    """``len(dispatcher.signatures)`` of every engine dispatcher (compiled or loaded from disk)."""
    return {name: len(d.signatures) for name, d in engine_dispatchers().items()}


def compile_stats() -> tuple[int, int]:
    """(disk cache hits, disk cache misses = compilations) summed over the engine's dispatchers."""
    hits = misses = 0
    for d in engine_dispatchers().values():
        st = d.stats
        hits += sum(st.cache_hits.values())
        misses += sum(st.cache_misses.values())
    return hits, misses


class _Meter:
    """New signatures, compilations and disk cache loads between ``start()`` and ``stop()``."""

    def start(self) -> None:
        self._sigs = signature_counts()
        self._hits, self._misses = compile_stats()
        self._t0 = time.perf_counter()

    def stop(self) -> tuple[float, int, int, int, list[str]]:
        seconds = time.perf_counter() - self._t0
        after = signature_counts()
        hits, misses = compile_stats()
        grown = sorted(n for n, c in after.items() if c > self._sigs.get(n, 0))
        new = sum(c - self._sigs.get(n, 0) for n, c in after.items())
        return seconds, new, misses - self._misses, hits - self._hits, grown


# ------------------------------------------------------------------------------ report


@dataclass
class WarmupStep:
    """One warm-up step: wall time, numba signatures that appeared (``compiled`` of them were
    compiled, ``loaded`` loaded from numba's disk cache; callee kernels compiled inside a caller
    count too), the dispatchers that grew, and the error when the step failed."""

    name: str
    seconds: float = 0.0
    new_signatures: int = 0
    compiled: int = 0
    loaded: int = 0
    kernels: list[str] = field(default_factory=list)
    error: str | None = None

    @property
    def ok(self) -> bool:
        return self.error is None


@dataclass
class WarmupReport:
    steps: list[WarmupStep]
    seconds: float

    @property
    def ok(self) -> bool:
        return all(s.ok for s in self.steps)

    @property
    def compiled(self) -> int:
        return sum(s.compiled for s in self.steps)

    @property
    def loaded(self) -> int:
        return sum(s.loaded for s in self.steps)

    @property
    def new_signatures(self) -> int:
        return sum(s.new_signatures for s in self.steps)

    @property
    def failed(self) -> list[str]:
        return [s.name for s in self.steps if not s.ok]

    def step(self, name: str) -> WarmupStep:
        for s in self.steps:
            if s.name == name:
                return s
        raise KeyError(name)

    def summary(self) -> str:
        state = "ok" if self.ok else f"FAILED steps: {', '.join(self.failed)}"
        return (f"{self.seconds:.1f} s, {len(self.steps)} steps, {self.new_signatures} numba signatures "
                f"({self.compiled} compiled, {self.loaded} from the disk cache), {state}")

    def table(self) -> str:
        lines = [f"{'step':<28} {'seconds':>8} {'new sigs':>8} {'compiled':>8} {'loaded':>7}"]
        for s in self.steps:
            lines.append(f"{s.name:<28} {s.seconds:8.2f} {s.new_signatures:8d} {s.compiled:8d} {s.loaded:7d}"
                         + (f"  ERROR {s.error.splitlines()[0]}" if s.error else ""))
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        return {"seconds": self.seconds, "ok": self.ok, "compiled": self.compiled, "loaded": self.loaded,
                "new_signatures": self.new_signatures, "steps": [asdict(s) for s in self.steps]}


# ------------------------------------------------------------------------------ built-in data

WARMUP_SCENE: dict[str, Any] = {
    "name": "warm-up",
    "camera": {"type": "perspective", "eye": [0.0, 1.3, 3.4], "look_at": [0.0, 0.4, 0.0], "fov_y_deg": 45.0,
               "width": 24, "height": 24},
    "materials": [
        {"name": "diffuse", "kd": [0.6, 0.55, 0.5]},
        {"name": "glossy", "kd": [0.3, 0.3, 0.3], "ks": [0.3, 0.3, 0.3], "shininess": 40.0,
         "kg": [0.2, 0.2, 0.2], "gloss_exponent": 20.0},
        {"name": "highlight", "kd": [0.5, 0.2, 0.2], "ks": [0.3, 0.3, 0.3], "shininess": 30.0},
        {"name": "mirror", "kd": [0.05, 0.05, 0.05], "kr": [0.85, 0.85, 0.85]},
        {"name": "glow", "kd": [0.2, 0.2, 0.2], "emission": [1.5, 1.2, 0.8]},
    ],
    "objects": [
        {"type": "plane", "material": "glossy", "size": [3.0, 3.0]},
        {"type": "box", "material": "diffuse", "center": [-0.55, 0.3, 0.0], "size": [0.5, 0.6, 0.5]},
        {"type": "box", "material": "highlight", "center": [0.0, 0.15, 0.6], "size": [0.3, 0.3, 0.3]},
        {"type": "sphere", "material": "mirror", "center": [0.5, 0.35, -0.1], "radius": 0.35, "subdivisions": 1},
        {"type": "sphere", "material": "glow", "center": [0.0, 1.1, -0.8], "radius": 0.12, "subdivisions": 0},
    ],
    "lights": [
        {"type": "point", "position": [1.0, 2.0, 1.5], "intensity": [6.0, 6.0, 6.0]},
        {"type": "directional", "direction": [-0.3, -1.0, -0.4], "irradiance": [0.8, 0.8, 0.8]},
        {"type": "rect", "corner": [-0.4, 1.8, -0.4], "edge_u": [0.8, 0.0, 0.0], "edge_v": [0.0, 0.0, 0.8],
         "radiance": [1.5, 1.5, 1.5]},
    ],
    "ambient": [0.02, 0.02, 0.02],
    "background": [0.05, 0.06, 0.08],
}
"""The warm-up scene: a glossy floor, a diffuse and a highlight box, a mirror and an emitting
sphere, lit by a point, a directional and a rect light (every light kind of the scene format; the
glossy floor under the mirror and the rect light makes ``ldc+ibrt:k`` trace glossy lobes, the view's
``glossy_rays="auto"``)."""

WALKTHROUGH_SCENE: dict[str, Any] = {
    **WARMUP_SCENE,
    "objects": [*WARMUP_SCENE["objects"][:3], {**WARMUP_SCENE["objects"][3], "name": "ball"},
                *WARMUP_SCENE["objects"][4:]],
    "animation": {"start": 0.0, "end": 1.0,
                  "objects": {"ball": [{"time": 0.0, "transform": {"translate": [0.0, 0.0, 0.0]}},
                                       {"time": 1.0, "transform": {"translate": [-0.3, 0.0, 0.2]}}]}},
    "view_space": {"type": "path", "points": [[-0.3, 1.3, 3.4], [0.3, 1.3, 3.4]]},
}
"""The warm-up scene with its mirror sphere moving and a camera path: a walkthrough's scene."""

_BAKE = {"ldc_resolution": 8, "max_layers": 4, "area_light_samples": 4, "llf": "always", "llf_f": 1,
         "indirect": {"mode": "off"},
         "llf_resolution": 4, "llf_chunk": 6, "llf_params": {"glossy_samples": 2, "area_light_samples": 1}}
"""A tiny bake of the warm-up scene: LDC 8 px per axis, LLF of 6 directions at 4 px, one chunk."""

_RELIGHT_STORES: tuple[tuple[str, dict[str, Any], str], ...] = (
    ("float16-pixel_major", {"layout": "pixel_major", "half": True}, "float16"),
    ("float16-tiled", {"layout": "tiled", "half": True}, "float16"),
    ("float32-pixel_major", {"layout": "pixel_major", "half": False}, "float32"),
    ("float32-tiled", {"layout": "tiled", "half": False}, "float32"),
    ("lowrank", {"layout": "pixel_major", "half": False, "compress": 0.05}, "lowrank"),
)
"""(step suffix, dataset bake params, expected store) for every store ``bake_dataset`` produces."""


def synthetic_dataset(size: int = 24, n_lights: int = 24) -> Any:
    """A small illumination dataset made in code: a bumpy disc (a height field seen from above),
    Lambertian with an ambient floor (every value > 0, so float16 is chosen when asked for), lit
    by ``n_lights`` point lights on a sphere around it."""
    ys, xs = np.mgrid[0:size, 0:size]
    u = (xs + 0.5) / size * 2.0 - 1.0
    v = (ys + 0.5) / size * 2.0 - 1.0
    r2 = u * u + v * v
    mask = r2 < 0.95
    z = 0.25 * np.sqrt(np.clip(1.0 - r2, 0.0, None))
    pts = np.stack([u, -v, z], axis=2)
    nrm = np.stack([u * 0.5, -v * 0.5, np.ones_like(u)], axis=2)
    nrm /= np.linalg.norm(nrm, axis=2, keepdims=True)
    k = np.arange(n_lights) + 0.5
    polar = np.arccos(1.0 - k / n_lights)  # upper hemisphere, Fibonacci spiral
    azim = math.pi * (1.0 + math.sqrt(5.0)) * k
    dirs = np.stack([np.sin(polar) * np.cos(azim), np.sin(polar) * np.sin(azim), np.cos(polar)], axis=1)
    lights = 3.0 * dirs
    albedo = np.stack([0.7 - 0.2 * u * u, 0.5 + 0.1 * v, np.full_like(u, 0.4)], axis=2)
    images = np.empty((n_lights, size, size, 3), np.float32)
    for i, lp in enumerate(lights):
        off = lp - pts
        d2 = np.sum(off * off, axis=2)
        cos = np.clip(np.sum(nrm * off, axis=2) / np.sqrt(d2), 0.0, None)
        images[i] = (albedo * (0.1 + cos / d2)[:, :, None]).astype(np.float32)
    return IlluminationDataset(images, lights, np.full((n_lights, 3), 1.0), pts, mask=mask,
                               sphere_center=np.zeros(3))


def _dataset_id(name: str) -> str:
    return hashlib.sha256(f"ibr-warm-up:{name}".encode()).hexdigest()


# ------------------------------------------------------------------------------ scratch context


@contextlib.contextmanager
def _scratch_jobs(store: Any) -> Iterator[None]:
    """Point the render queue's job modules (and the bake part jobs) at ``store`` with fresh
    caches for the duration, then restore what they had. Only for a process that runs no job
    meanwhile (the runner warms up before the worker starts)."""

    saved_store = set_worker_store(store)
    saved_renderers = set_renderer_cache(None)
    saved_datasets = set_caches(None, None)
    try:
        yield
    finally:
        set_worker_store(saved_store)
        set_renderer_cache(saved_renderers)
        set_caches(*saved_datasets)


def _scratch_dir() -> str | None:
    shm = "/dev/shm"
    return shm if os.path.isdir(shm) and os.access(shm, os.W_OK | os.X_OK) else None


# ------------------------------------------------------------------------------ the steps


class _Run:
    """State shared by the steps (the scratch store, the stored scene, bakes and datasets)."""

    def __init__(self, store: Any):
        self.store = store
        self.scene_id = ""
        self.bake_params: Any = None
        self.no_llf_params: Any = None
        self.env_sha = ""
        self.plate_sha = ""
        self.mask_sha = ""
        self.datasets: dict[str, tuple[str, Any]] = {}  # step suffix -> (dataset id, bake params)
        self.dataset_size = 24
        self.background_id = _dataset_id("background")
        self.light_positions = np.zeros((0, 3))

    # --- helpers
    def render(self, **request: Any) -> dict[str, Any]:

        req = RenderRequest.model_validate({"scene_id": self.scene_id, **request})
        payload = RenderJobPayload(request=req, artifact_key=render_artifact_key(req))
        return render_job(payload.model_dump(mode="json"))

    def relight(self, suffix: str, lights: list[dict[str, Any]]) -> dict[str, Any]:

        did, params = self.datasets[suffix]
        req = RelightRequest.model_validate({"dataset_id": did, "lights": lights, "bake": params.model_dump()})
        return relight_job(RelightJobPayload(request=req, artifact_key=relight_artifact_key(req))
                           .model_dump(mode="json"))

    def image_file(self, name: str, pixels: np.ndarray) -> str:

        info = store_file(self.store, encode_image(name, pixels), max_pixels=1 << 20)
        return str(info["sha256"])

    # --- steps
    def scene(self) -> None:

        self.scene_id = put_scene(self.store, Scene.model_validate(WARMUP_SCENE), {}, owner=None).id

    def reference(self) -> None:
        # 24 x 24 = one wavefront chunk: each kernel's batch split over the cores
        self.render(params={"spp": 1, "max_depth": 2, "glossy_samples": 2, "area_light_samples": 4})

    def reference_pipelined(self) -> None:
        # 40 x 32 = two chunks: two pipelines in threads, each kernel's batch in one call; indirect paths too
        self.render(params={"spp": 1, "max_depth": 2, "glossy_samples": 2, "area_light_samples": 4,
                            "indirect_samples": 1, "indirect_bounces": 1},
                    camera={**WARMUP_SCENE["camera"], "width": 40, "height": 32})

    def ldc_bake(self) -> None:
        self.bake_params = BakeParams.model_validate(_BAKE)
        self._publish_bake(self.bake_params, with_llf=True)
        # the same LDC without a light field: ``ldc`` renders then use the no-gather parameters
        self.no_llf_params = BakeParams.model_validate({**_BAKE, "llf": "never"})
        self._publish_bake(self.no_llf_params, with_llf=False)

    def _publish_bake(self, params: Any, *, with_llf: bool) -> None:
        """Run the bake queue's part jobs into the scratch store and publish the bake manifest the
        merge job would (the plan and merge jobs need Redis; the render job reads only this)."""

        bkey = bake_key(self.scene_id, params)
        scene = load_stored_scene(self.store, self.scene_id).runtime
        plan_doc = bake_plan_doc(scene, params, analyze(scene))
        with_indirect = plan_doc["indirect"]["state"] == "planned"
        specs = [{**spec, "key": part_key(self.scene_id, bkey, spec)}
                 for spec in plan_parts(params, with_llf, with_indirect)]
        jobs = {"ldc_axis": bake_ldc_axis_job, "ldc_indirect": bake_ldc_indirect_job, "llf_views": bake_llf_views_job}
        for spec in specs:  # in plan order: an axis before its indirect chunks
            part = {k: v for k, v in spec.items() if k != "key"}
            payload = {"scene_id": self.scene_id, "bake_key": bkey, "params": params.model_dump(mode="json"),
                       "part": part, "part_key": spec["key"]}
            jobs[spec["kind"]](payload)
        if with_indirect:
            plan_doc["indirect"]["state"] = "baked"
        result = json.loads(json.dumps({"plan": plan_doc, "parts": specs}, default=str))
        write_artifact(self.store, bkey, "bake", {"scene": self.scene_id}, params.model_dump(mode="json"),
                       ENGINE_VERSION, {"plan.json": (json.dumps(plan_doc, sort_keys=True).encode(),
                                                      "application/json")}, result)

    def ldc_render(self, method: str, *, with_llf: bool) -> None:
        bake = self.bake_params if with_llf else self.no_llf_params
        self.render(method=method, bake=bake.model_dump(mode="json"))

    def relight_bake(self) -> None:
        """Bake the synthetic dataset into every store kind and publish each as ``bake_job`` does."""

        ds = synthetic_dataset(self.dataset_size)
        for suffix, kwargs, expected in _RELIGHT_STORES:
            bp = DatasetBakeParams.model_validate(kwargs)
            extra: dict[str, Any] = {"compress": bp.compress} if bp.compress is not None else {}
            baked = bake_dataset(ds, layout=bp.layout, half=bp.half, dedupe_tol_deg=bp.dedupe_tol_deg,
                                 max_face_radius_deg=bp.max_face_radius_deg, half_rel_floor=bp.half_rel_floor,
                                 **extra)
            got = "lowrank" if baked.lowrank is not None else str(baked.store.dtype)
            if got != expected:  # the synthetic data no longer selects this store: a coverage gap
                raise RuntimeError(f"relight store {suffix}: bake_dataset chose {got} "
                                   f"({baked.report.get('dtype_reason')}; {baked.report.get('compression_reason')})")
            blob = baked_to_bytes(baked)
            ids = [_dataset_id(suffix)] + ([self.background_id] if suffix == "float16-pixel_major" else [])
            for did in ids:  # the composite's background dataset: the same bake under another id
                write_artifact(self.store, bake_artifact_key(did, bp), DATASET_BAKE_KIND, {"dataset": did},
                               bp.model_dump(mode="json"), ENGINE_VERSION, {"baked.npz": (blob, NPZ)},
                               json_safe({"report": baked.report}))
            self.datasets[suffix] = (ids[0], bp)
        env = np.empty((8, 16, 3), np.float32)
        env[:] = np.linspace(0.2, 2.0, 16, dtype=np.float32)[None, :, None]
        env[:2] *= 3.0  # a brighter sky band
        self.env_sha = self.image_file("env.exr", env)
        self.light_positions = ds.light_positions

    def lights(self) -> list[dict[str, Any]]:
        return [{"type": "point", "position": [0.4, 0.5, 2.5], "intensity": [2.0, 2.0, 2.0]},
                {"type": "directional", "direction": [0.2, -0.3, -1.0], "irradiance": [0.5, 0.5, 0.5]},
                {"type": "rect", "corner": [-0.5, -0.5, 2.5], "edge_u": [1.0, 0.0, 0.0], "edge_v": [0.0, 1.0, 0.0],
                 "radiance": [0.3, 0.3, 0.3], "samples": 4},
                {"type": "environment", "image_sha256": self.env_sha, "n_lights": 8}]

    def relight_store(self, suffix: str) -> None:
        self.relight(suffix, self.lights())  # the interpolating kernel, every light kind
        exact = [float(x) for x in self.light_positions[0]]
        self.relight(suffix, [{"type": "point", "position": exact, "intensity": [1.0, 1.0, 1.0]}])  # exact-hit kernel

    def walkthrough(self) -> None:
        """A walkthrough of the animated warm-up scene: the bake (the bake queue's
        ``engine.walkthrough.bake.bake_walkthrough``, as ``walkthrough_bake_job`` calls it) and
        frames reconstructed as ``walkthrough_chunk_job`` does, with every fill mode, and path-traced."""

        scene = Scene.model_validate(WALKTHROUGH_SCENE)
        an = load_animated_scene(scene)
        params = walkthrough_preset("low", face_res=16, probe_res=8, indirect_samples=2, indirect_res_div=2,
                                    max_views=2, max_time_samples=2)
        bake = bake_walkthrough(an, engine_space(scene), params)
        renderer = WalkthroughRenderer(bake, an)
        cam = camera_params(scene.camera)
        for fill in FILL_MODES:
            renderer.render(cam, 0.5, fill=fill, strict=False)
        for noise in (0.2, 0.05):  # path-traced frames: a fixed path count, and a pilot sizing each pixel's
            PathTracedFrames(an, noise).render(cam, 0.5, 0)

    def composite(self) -> None:

        obj, bp = self.datasets["float16-pixel_major"]
        size = self.dataset_size
        plate = np.full((size, size, 3), 0.4, np.float32)
        mask = np.zeros((size, size, 1), np.float32)
        mask[size // 3: 2 * size // 3, size // 3: 2 * size // 3] = 1.0
        req = CompositeRequest.model_validate({
            "object_dataset_id": obj, "background_dataset_id": self.background_id,
            "plate_sha256": self.image_file("plate.exr", plate),
            "object_mask_sha256": self.image_file("mask.exr", mask), "lights": self.lights()[:2],
            "bake": bp.model_dump()})
        payload = CompositeJobPayload(request=req, artifact_key=composite_artifact_key(req))
        composite_job(payload.model_dump(mode="json"))


def _plan(run: _Run) -> list[tuple[str, Callable[[], None], tuple[str, ...]]]:
    """(step name, function, steps it needs) in order (``workers.warmup_steps``)."""
    fns: dict[str, Callable[[], None]] = {
        "scene": run.scene,
        "reference": run.reference,
        "reference-pipelined": run.reference_pipelined,
        "ldc-bake": run.ldc_bake,
        "ldc": functools.partial(run.ldc_render, "ldc", with_llf=True),
        "ldc-without-llf": functools.partial(run.ldc_render, "ldc", with_llf=False),
        **{m: functools.partial(run.ldc_render, m, with_llf=True) for m in ("ldc+llf", "ldc+ibrt:1", "ldc+ibrt:2")},
        "relight-bake": run.relight_bake,
        **{f"relight-{suffix}": functools.partial(run.relight_store, suffix) for suffix, _, _ in _RELIGHT_STORES},
        "composite": run.composite,
        "walkthrough": run.walkthrough,
    }
    return [(name, fns[name], NEEDS[name]) for name in STEPS]


def warm_up(*, logger: logging.Logger | None = None, on_start: Callable[[str], None] | None = None,
            on_end: Callable[[WarmupStep], None] | None = None, only: Sequence[str] | None = None) -> WarmupReport:
    """Run every step (module docstring), or those named in ``only`` (a lane: the steps they need
    must be in it); a failing step is recorded with its traceback's last line (and logged with the
    traceback) and the others still run (those that need it are skipped). Never raises for a step's
    failure: the caller decides what a failed report means. ``on_start(name)`` / ``on_end(step)``
    are told when each step starts and ends (readiness)."""
    lg = logger or log
    t_start = time.perf_counter()
    steps: list[WarmupStep] = []
    meter = _Meter()
    with tempfile.TemporaryDirectory(prefix="ibr-warmup-", dir=_scratch_dir()) as tmp:
        run = _Run(LocalStore(Path(tmp)))
        with _scratch_jobs(run.store):
            for name, fn, needs in _plan(run):
                if only is not None and name not in only:
                    continue
                step = WarmupStep(name)
                failed_needs = [n for n in needs if any(s.name == n and not s.ok for s in steps)]
                if failed_needs:
                    step.error = f"skipped: needs step {failed_needs[0]}, which failed"
                    steps.append(step)
                    if on_end is not None:
                        on_end(step)
                    continue
                if on_start is not None:
                    on_start(name)
                meter.start()
                try:
                    fn()
                except Exception as exc:  # noqa: BLE001 - recorded in the report, logged with the traceback
                    step.error = f"{type(exc).__name__}: {exc}"
                    lg.error("warm-up step %s failed:\n%s", name, traceback.format_exc())
                step.seconds, step.new_signatures, step.compiled, step.loaded, step.kernels = meter.stop()
                lg.info("warm-up step %-22s %6.2f s  %3d new numba signatures (%d compiled, %d from the disk cache)%s",
                        name, step.seconds, step.new_signatures, step.compiled, step.loaded,
                        "" if step.ok else f"  FAILED: {step.error}")
                steps.append(step)
                if on_end is not None:
                    on_end(step)
    return WarmupReport(steps, time.perf_counter() - t_start)


PUBLISH_INTERVAL_S = 1.0
"""Seconds between readiness updates in Redis while a published warm-up runs (the estimates count down)."""


def warm_up_published(worker: str, lane: int = 0, lanes: int = 1, *,
                      logger: logging.Logger | None = None) -> WarmupReport:
    """:func:`warm_up` of lane ``lane`` of ``lanes_for(lanes)``, publishing its kinds' readiness
    (``workers.warmup_readiness``) in Redis (``IBR_REDIS_URL``) as render worker ``worker``'s every
    :data:`PUBLISH_INTERVAL_S` and after each step. A Redis error is logged and the warm-up goes on
    (readiness is for display only)."""
    from producer.queue import redis_from_url  # deferred on purpose: only the published mode talks to Redis
    from producer.readiness import publish_readiness
    from producer.settings import Settings
    from workers.warmup_readiness import ReadinessTracker

    lg = logger or log
    redis = redis_from_url(Settings().effective_redis_url)
    steps = lanes_for(lanes)[lane]
    tracker = ReadinessTracker(steps, worker)
    stop = threading.Event()

    def publish() -> None:
        try:
            publish_readiness(redis, worker, tracker.document(), lane=lane)
        except Exception as exc:  # noqa: BLE001 - display only: the warm-up goes on
            lg.warning("warm-up readiness not published: %s", exc)

    def loop() -> None:
        while not stop.wait(PUBLISH_INTERVAL_S):
            publish()

    def step_ended(step: WarmupStep) -> None:
        tracker.finished(step.name, step.seconds, step.ok)
        publish()

    publish()
    ticker = threading.Thread(target=loop, name="ibr-warmup-readiness", daemon=True)
    ticker.start()
    try:
        report = warm_up(logger=lg, on_start=tracker.started, on_end=step_ended, only=steps)
    finally:
        stop.set()
        ticker.join(timeout=5)
        tracker.end()
        publish()
        redis.close()
    return report


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m workers.warmup [--json] [--publish WORKER] [--lanes N --lane I]``: warm up this
    process (and numba's disk cache) and print the report; exit status 1 when a step failed (e.g. an
    image build should stop). ``--publish``: the render worker's background warm-up
    (workers/runner.py). ``--lanes N --lane I``: only lane I's steps, so N processes fill a cache
    together (the test session does, tests/conftest.py)."""
    p = argparse.ArgumentParser(prog="python -m workers.warmup", description=main.__doc__)
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.add_argument("--publish", metavar="WORKER",
                   help="publish per-method readiness in Redis (IBR_REDIS_URL) as render worker WORKER's")
    p.add_argument("--lanes", type=int, default=1, help="the steps split for this many cores (lanes_for)")
    p.add_argument("--lane", type=int, default=0, help="the lane this process runs (with --lanes)")
    p.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    args = p.parse_args(argv)
    logging.basicConfig(level=args.log_level, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    lanes = lanes_for(args.lanes)
    if not 0 <= args.lane < len(lanes):
        p.error(f"--lane must be in 0..{len(lanes) - 1} for --lanes {args.lanes}")
    if args.publish:
        report = warm_up_published(args.publish, args.lane, args.lanes)
    else:
        report = warm_up(only=lanes[args.lane] if len(lanes) > 1 else None)
    print(json.dumps(report.to_dict(), indent=1) if args.json else f"{report.table()}\n{report.summary()}")
    return 0 if report.ok else 1


if __name__ == "__main__":
    sys.exit(main())
