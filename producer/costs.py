"""What a job will cost, estimated from its request before it is queued: triangles after tessellation,
peak memory and CPU time. The API refuses a request whose estimate is over a configured limit
(:class:`CostOverLimit`, 422 naming the estimate and the limit) instead of letting a worker swell or
run into its timeout. Numba-free: the API imports it.

Every estimate is a :class:`Cost`. Memory is the growth of the worker's peak RSS while it runs the job
(the scene it builds included); CPU time is seconds of one core. The constants are measured on this
project's 2-core machine (docs/limits.md: how, with the commands that measure them again):

- scenes: a built scene (tessellation, the runtime scene's arrays, Embree's BVH) grew a worker's peak
  RSS by 480-540 bytes per triangle and took 3.6-3.8 CPU us per triangle (82 k to 5.2 M triangles of
  icospheres, ``tests/workers/queue/scene_build_rss.py``);
- renders: ``REFERENCE_*`` / ``LDC_*`` below (``tests/workers/queue/render_rss.py``);
- scene bakes: the plan job's own model (``workers/jobs/bake.py``), here from the scene document
  instead of the built scene (projected areas from object surface areas, the grid from analytic
  bounds), so the API can refuse before the plan job builds anything;
- the rest (dataset generation is reference renders, relights and composites hold image stacks,
  walkthrough bakes their base images, calibrations reference and LDC renders of small probes) is
  sized from the arrays the job holds and the render models above.

The estimates are refusal thresholds, not accounting: memory carries ``MARGIN``.
"""

from __future__ import annotations

import json
import math
import re
import struct
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import PurePosixPath
from typing import Any

import numpy as np

from api_schemas.datasets import CompositeRequest, DatasetBakeParams, GenerateRequest, RelightRequest
from api_schemas.scene import (
    BoxObject,
    CylinderObject,
    DiskObject,
    InlineMeshObject,
    MeshFileObject,
    PlaneObject,
    Scene,
    SceneObject,
    SphereObject,
)
from api_schemas.service import BakeParams, CalibrationParams, RenderRequest, method_needs_bake
from api_schemas.walkthrough import WalkthroughRequest
from engine.methods import auto_glossy_rays, parse_method
from engine.newviews.indirect_sampling import expected_paths_per_side
from engine.walkthrough.path_settings import path_traced_settings

__all__ = [
    "FIXED_BYTES",
    "GLOSSY_RAY_CPU_S",
    "INDIRECT_RAY_BYTES",
    "LDC_ATTR_BYTES",
    "LDC_BYTES_PER_PIXEL",
    "LDC_CPU_S_PER_PIXEL",
    "LDI_SAMPLE_BYTES",
    "LLF_SAMPLE_BYTES",
    "MARGIN",
    "MAX_RAYS_PER_BATCH",
    "REFERENCE_BYTES_PER_AREA_RAY",
    "REFERENCE_BYTES_PER_CHUNK_SAMPLE",
    "REFERENCE_BYTES_PER_GLOSSY_RAY",
    "REFERENCE_BYTES_PER_PIXEL",
    "REFERENCE_CHUNK_PIXELS",
    "REFERENCE_CPU_S_PER_AREA_RAY",
    "REFERENCE_CPU_S_PER_GLOSSY_RAY",
    "REFERENCE_CPU_S_PER_LIGHT_PATH",
    "REFERENCE_CPU_S_PER_SAMPLE",
    "SCENE_BYTES_PER_TRIANGLE",
    "SCENE_CPU_S_PER_TRIANGLE",
    "WORKER_KEPT_BYTES",
    "Cost",
    "CostOverLimit",
    "Limits",
    "bake_cost",
    "batch_cost",
    "calibration_cost",
    "check",
    "composite_cost",
    "dataset_bake_cost",
    "generate_cost",
    "mesh_triangles",
    "object_triangles",
    "reference_chunk_pixels",
    "relight_cost",
    "render_cost",
    "scene_auto_glossy_rays",
    "scene_bounds",
    "scene_cost",
    "scene_light_traced",
    "scene_triangles",
    "stored_scene",
    "stored_scene_triangles",
    "remember_mesh_triangles",
    "walkthrough_costs",
]

# --------------------------------------------------------------------------- constants (docs/limits.md)

SCENE_BYTES_PER_TRIANGLE = 560
"""Peak RSS growth of building a scene, per triangle (measured 480-540)."""
SCENE_CPU_S_PER_TRIANGLE = 4.0e-6
"""CPU seconds of building a scene, per triangle (measured 3.6-3.8 us)."""

REFERENCE_BYTES_PER_PIXEL = 240
"""Reference render, image-sized buffers (float64 radiance accumulator, normals, depth, ids, the copies
the encoders write): 235 bytes per pixel measured (512 x 512 -> 1024 x 1024 at 4 spp)."""
REFERENCE_BYTES_PER_CHUNK_SAMPLE = 930
"""Reference render: every sample's rays of a wavefront chunk (two chunks in flight), per chunk pixel
and sample; plus ``REFERENCE_BYTES_PER_GLOSSY_RAY`` per glossy (and indirect) sample and
``REFERENCE_BYTES_PER_AREA_RAY`` per area-light sample beyond the first (512 x 512, spp 4 / 16,
glossy 1 / 8, area 1 / 16: 106 MiB to 656 MiB). A render at 1 spp needs about what 2 spp predict."""
REFERENCE_BYTES_PER_GLOSSY_RAY = 440
REFERENCE_BYTES_PER_AREA_RAY = 135
REFERENCE_CHUNK_PIXELS = 16384
"""``engine.reference.ReferenceParams.chunk_pixels``: pixels per wavefront chunk."""
REFERENCE_CPU_S_PER_SAMPLE = 0.5e-6
"""Reference render: CPU seconds per pixel sample besides its glossy and area-light rays (camera ray,
first hit, shading, accumulation). Fitted with the two below on 512 x 512 renders of the warm-up scene:
spp 4 glossy 1 area 1: 0.85 us per sample; spp 2 glossy 8 area 1: 2.15 us; spp 4 glossy 16 area 16: 9.7 us."""
REFERENCE_CPU_S_PER_GLOSSY_RAY = 0.2e-6
"""Reference render: CPU seconds per glossy sample of a pixel sample (indirect samples count as one
per bounce; not measured separately)."""
REFERENCE_CPU_S_PER_AREA_RAY = 0.4e-6
"""Reference render: CPU seconds per area-light sample of a pixel sample (a shadow ray and its MIS)."""
REFERENCE_CPU_S_PER_LIGHT_PATH = 0.6e-6
"""Reference render of a scene with caustics (``engine.light_tracing``, ``params.light_paths`` light paths per
pixel sample): CPU seconds per light path. Measured 0.30 us of wall time per path on two cores (1 M and 4 M
paths of up to 3 bounces, the mirror / glossy Cornell box at 256 x 256): at one light path per sample 3 %
of a render with glossy chains and an indirect path per sample, 44 % of the CPU time of one with a single
path and light sample per sample (``bench.noise_sources``)."""
LDC_BYTES_PER_PIXEL = 180
"""The LDC methods render the whole view at once (warp, candidate lists, provenance): ``ldc+llf``
grew 74-90 bytes per pixel (1024 x 1024, 2048 x 2048); about twice that for ``ldc+ibrt:k``'s retracing."""
LDC_CPU_S_PER_PIXEL = 0.6e-6
"""LDC methods: CPU seconds per pixel (0.42-0.46 us measured at 1024 x 1024 for ``ldc``, ``ldc+llf``
and ``ldc+ibrt:1`` on the warm-up scene; a third more for busier scenes)."""
GLOSSY_RAY_CPU_S = 2.0e-6
"""LDC views with ``view.glossy_rays`` n: CPU seconds per traced glossy-lobe ray and generation (each
ray's image-based trace and the shading of its hit); priced as if every pixel were glossy, an upper
bound (the rays are traced in chunks, so their memory is bounded and not priced)."""
FIXED_BYTES = 32 << 20
"""Per-job overhead that does not scale with the image (kernels' scratch, encoder state)."""
MARGIN = 1.25
"""Memory estimates are multiplied by this: a refusal threshold, not an accounting."""
WORKER_KEPT_BYTES = 256 << 20
"""Freed memory a worker keeps mapped for its next job (``Settings.malloc_keep_mib``'s default,
``engine.memory``): a job's peak RSS can hold up to this much memory its own earlier stages freed. In a
real render worker a 1024 x 1024 reference render grew the RSS by 958-1090 MiB, where the same render in
a bare process grew it by 914 MiB (``tests/service/api/test_worker_rss_at_limit.py``)."""

# Mirrors of engine constants (the API must not import the engine's numba modules; a test checks they agree).
LDI_SAMPLE_BYTES = 20
"""``engine.newviews.ldi.LDI_SAMPLE_BYTES``."""
LDC_ATTR_BYTES = 57
"""``engine.newviews.ldc.LDC_ATTR_BYTES``."""
LLF_SAMPLE_BYTES = 32
"""``engine.newviews.llf.LLF_SAMPLE_BYTES``."""
MAX_RAYS_PER_BATCH = 1 << 20
"""``engine.newviews.indirect.MAX_RAYS_PER_BATCH``."""
INDIRECT_RAY_BYTES = 576
"""``workers.jobs.bake.INDIRECT_RAY_BYTES``: working memory per path of an indirect batch."""
PATHS_RATE_BOUNCES = 3
"""``workers.jobs.bake.PATHS_RATE_BOUNCES``: ``Settings.bake_paths_per_s`` is measured at this many bounces."""
IMAGE_BYTES_PER_PIXEL = 12
"""A float32 RGB image."""
CAUSTIC_CPU_S_PER_PHOTON = 1.0e-6
"""``workers.jobs.bake.CAUSTIC_CPU_S_PER_PHOTON``: an indirect chunk job's caustic photon map."""
CAUSTIC_BYTES_PER_PHOTON = 400
"""``workers.jobs.bake.CAUSTIC_BYTES_PER_PHOTON``."""
WALKTHROUGH_CPU_S_PER_BASE_PIXEL = 4.0e-6
"""A walkthrough bake's base range images: CPU per base pixel (first hits, shading and indirect
paths at the preset's samples; sized from the LDC bake's per-sample cost, not measured separately)."""
WALKTHROUGH_CPU_S_PER_PATH = 1.0e-6
"""A path-traced walkthrough frame: CPU per indirect path, times the paths a pixel is expected to
trace (``engine.walkthrough.path_settings``; the reference traces ~1.25 M paths of 3 bounces a
second on one core, docs/accuracy/reference-vs-mitsuba.md)."""
DATASET_BAKE_BYTES_PER_VALUE = 4 + 4
"""A dataset bake holds the float32 stack and its baked copy (float16 or low-rank factors, at most
float32)."""
RELIGHT_CPU_S_PER_VALUE = 2.0e-9
"""A relight: one multiply-add per pixel, channel and expanded light (numba, vectorised)."""


# --------------------------------------------------------------------------- the cost and its limits


@dataclass(frozen=True)
class Cost:
    """The estimate of one job (or of the jobs of one request, with ``jobs`` > 1)."""

    kind: str
    """What runs: ``reference render``, ``scene bake``, ``dataset generation``, ..."""
    triangles: int = 0
    """Triangles after tessellation of the scene the job builds (0: no scene)."""
    peak_bytes: int = 0
    """Growth of the worker's peak RSS while the largest of the jobs runs (scene included)."""
    cpu_s: float = 0.0
    """CPU seconds of the largest job."""
    total_cpu_s: float = 0.0
    """CPU seconds of every job of the request together."""
    jobs: int = 1
    detail: dict[str, Any] = field(default_factory=dict)
    """The parts the estimate adds up (JSON types), for messages and the job's metadata."""

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.kind, "triangles": self.triangles, "peak_bytes": self.peak_bytes,
                "cpu_s": round(self.cpu_s, 3), "total_cpu_s": round(self.total_cpu_s, 3), "jobs": self.jobs,
                "detail": self.detail}


@dataclass(frozen=True)
class Limits:
    """What one job may cost on this server (``Settings``: ``max_scene_triangles``, ``max_render_bytes``
    or ``max_bake_part_bytes``, ``max_render_cpu_s`` or ``max_bake_job_cpu_s``, ``max_bake_cpu_s`` for the
    jobs of one request together)."""

    triangles: int
    peak_bytes: int
    cpu_s: float
    total_cpu_s: float
    names: tuple[str, str, str, str] = ("IBR_MAX_SCENE_TRIANGLES", "IBR_MAX_RENDER_BYTES", "IBR_MAX_RENDER_CPU_S",
                                        "IBR_MAX_BAKE_CPU_S")

    @classmethod
    def for_job(cls, settings: Any, queue: str, bake_part: bool = False) -> Limits:
        """The limits of a job on the ``render`` or the ``bake`` queue (``settings``: ``Settings``): memory
        ``max_render_bytes`` (``max_bake_part_bytes`` for the parts of a scene bake, which it splits
        into jobs of that size), CPU ``max_render_cpu_s`` or ``max_bake_job_cpu_s`` by queue."""
        mem, mem_name = ((settings.max_bake_part_bytes, "IBR_MAX_BAKE_PART_BYTES") if bake_part
                         else (settings.max_render_bytes, "IBR_MAX_RENDER_BYTES"))
        cpu, cpu_name = ((settings.max_render_cpu_s, "IBR_MAX_RENDER_CPU_S") if queue == "render"
                         else (settings.max_bake_job_cpu_s, "IBR_MAX_BAKE_JOB_CPU_S"))
        return cls(settings.max_scene_triangles, mem, cpu, settings.max_bake_cpu_s,
                   ("IBR_MAX_SCENE_TRIANGLES", mem_name, cpu_name, "IBR_MAX_BAKE_CPU_S"))


class CostOverLimit(ValueError):
    """A request whose estimate is over a limit: the API answers 422 with ``field`` and ``message``."""

    def __init__(self, field: str, message: str, cost: Cost, limit: str, type_: str = "over_limit"):
        super().__init__(message)
        self.type = type_
        self.field = field
        self.message = message
        self.cost = cost
        self.limit = limit


def size_text(n: float) -> str:
    """``1.50 GiB`` / ``12 MiB``."""
    return f"{n / (1 << 30):.2f} GiB" if n >= 1 << 30 else f"{n / (1 << 20):.0f} MiB"


def duration_text(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def check(cost: Cost, limits: Limits, field: str, lower: str, type_: str = "over_limit") -> Cost:
    """``cost`` when every part is within ``limits``, else :class:`CostOverLimit` naming the estimate, the
    limit and (``lower``) what the request can lower; ``type_`` is the error type the API reports
    (``scene_too_large`` for the triangles)."""
    tri_name, bytes_name, cpu_name, total_name = limits.names
    if cost.triangles > limits.triangles:
        raise CostOverLimit(field, f"the scene has {cost.triangles:,} triangles after tessellation, over this "
                                   f"server's limit of {limits.triangles:,} ({tri_name}); use fewer objects or "
                                   f"fewer subdivisions / segments", cost, tri_name, "scene_too_large")
    problem: tuple[str, str] | None = None
    if cost.peak_bytes > limits.peak_bytes:
        problem = (f"a {cost.kind} needs an estimated {size_text(cost.peak_bytes)} of memory, over this server's "
                   f"limit of {size_text(limits.peak_bytes)} ({bytes_name} = {limits.peak_bytes})", bytes_name)
    elif cost.cpu_s > limits.cpu_s:
        problem = (f"a {cost.kind} needs an estimated {duration_text(cost.cpu_s)} of CPU time, over this server's "
                   f"limit of {duration_text(limits.cpu_s)} per job ({cpu_name} = {limits.cpu_s:g})", cpu_name)
    elif cost.total_cpu_s > limits.total_cpu_s:
        problem = (f"a {cost.kind} needs an estimated {duration_text(cost.total_cpu_s)} of CPU time in {cost.jobs} "
                   f"jobs, over this server's limit of {duration_text(limits.total_cpu_s)} ({total_name} = "
                   f"{limits.total_cpu_s:g})", total_name)
    if problem is not None:
        raise CostOverLimit(field, f"{problem[0]}; {lower}", cost, problem[1], type_)
    return cost


# --------------------------------------------------------------------------- scenes

_ICOSAHEDRON_FACES = 20


def object_triangles(obj: SceneObject, mesh_counts: Mapping[str, int] | None = None) -> int:
    """Triangles of one scene object after tessellation (``engine.geometry.primitives``); a mesh file's from
    ``mesh_counts`` (by path; 0 when absent)."""
    if isinstance(obj, SphereObject):
        return int(_ICOSAHEDRON_FACES * 4 ** obj.subdivisions)
    if isinstance(obj, BoxObject):
        return 12
    if isinstance(obj, CylinderObject):
        return 2 * obj.segments + (2 * obj.segments if obj.capped else 0)
    if isinstance(obj, PlaneObject):
        return 2 * obj.segments * obj.segments
    if isinstance(obj, DiskObject):
        return obj.segments
    if isinstance(obj, InlineMeshObject):
        return len(obj.faces)
    if isinstance(obj, MeshFileObject):
        return int((mesh_counts or {}).get(obj.path, 0))
    raise TypeError(f"unknown scene object {type(obj).__name__}")


def scene_triangles(scene: Scene, mesh_counts: Mapping[str, int] | None = None) -> int:
    """Triangles of the whole scene after tessellation, counted from the document: never builds anything."""
    return sum(object_triangles(obj, mesh_counts) for obj in scene.objects)


_PLY_FACE = re.compile(rb"^element[ \t]+face[ \t]+(\d+)", re.MULTILINE)


def mesh_triangles(path: str, data: bytes) -> int:
    """Triangles a mesh file holds, read from its header or by counting face records (no geometry is
    decoded): PLY's face count, binary STL's count, OBJ's ``f`` lines (an n-gon is n - 2 triangles),
    glTF / GLB's index (or position) accessor counts / 3. Polygons in a PLY count as one triangle each
    (the header has no sizes). 0 when the file is not readable as its type (the upload's own checks
    name that)."""
    ext = PurePosixPath(path).suffix.lower().lstrip(".")
    try:
        if ext == "ply":
            head = data[: 1 << 16]
            m = _PLY_FACE.search(head)
            return int(m.group(1)) if m else 0
        if ext == "stl":
            if data[:5].lower() == b"solid" and b"facet" in data[:4096]:
                return data.count(b"facet normal")
            return int(struct.unpack_from("<I", data, 80)[0]) if len(data) >= 84 else 0
        if ext == "obj":
            total = 0
            for line in data.splitlines():
                if line[:2] in (b"f ", b"f\t"):
                    total += max(1, len(line.split()) - 3)
            return total
        if ext in ("gltf", "glb"):
            return _gltf_triangles(data, binary=ext == "glb")
    except (ValueError, struct.error, UnicodeDecodeError, KeyError, TypeError, IndexError):
        return 0
    return 0


def _gltf_triangles(data: bytes, binary: bool) -> int:
    if binary:
        if len(data) < 20:
            return 0
        length = struct.unpack_from("<I", data, 12)[0]
        doc = json.loads(data[20:20 + length])
    else:
        doc = json.loads(data)
    accessors = doc.get("accessors", [])
    total = 0
    for mesh in doc.get("meshes", []):
        for prim in mesh.get("primitives", []):
            if prim.get("mode", 4) != 4:
                continue
            idx = prim.get("indices")
            acc = accessors[idx] if idx is not None else accessors[prim["attributes"]["POSITION"]]
            total += int(acc.get("count", 0)) // 3
    return total


_MESH_COUNTS: dict[str, int] = {}
"""Triangles of mesh blobs by sha256 (content-addressed: a count never changes), so a job request reads
a scene's mesh files at most once per process."""
_MESH_COUNTS_MAX = 65536


def remember_mesh_triangles(sha: str, triangles: int) -> None:
    if len(_MESH_COUNTS) >= _MESH_COUNTS_MAX:
        _MESH_COUNTS.clear()
    _MESH_COUNTS[sha] = int(triangles)


def stored_scene_triangles(scene: Scene, mesh_shas: Mapping[str, str], read_blob: Callable[[str], bytes]) -> int:
    """Triangles of a stored scene: its primitives from the document, its mesh files from their headers
    (``read_blob(sha)`` reads a blob the first time this process sees it)."""
    counts: dict[str, int] = {}
    for path, sha in mesh_shas.items():
        if sha not in _MESH_COUNTS:
            remember_mesh_triangles(sha, mesh_triangles(path, read_blob(sha)))
        counts[path] = _MESH_COUNTS[sha]
    return scene_triangles(scene, counts)


def stored_scene(store: Any, scene_id: str) -> tuple[Scene, int]:
    """A stored scene and its triangles after tessellation (``producer.store.NotFound`` when absent)."""
    from producer.artifacts import blob_key, get_scene

    scene, shas, _ = get_scene(store, scene_id)
    return scene, stored_scene_triangles(scene, shas, lambda sha: store.get_bytes(blob_key(sha)))


def _object_box(obj: SceneObject) -> tuple[np.ndarray, np.ndarray] | None:
    """Local-space bounds of an object, None for a mesh file (not read here)."""
    c = np.asarray(obj.center if not isinstance(obj, (InlineMeshObject, MeshFileObject)) else (0.0, 0.0, 0.0))
    if isinstance(obj, SphereObject):
        return c - obj.radius, c + obj.radius
    if isinstance(obj, BoxObject):
        half = 0.5 * np.asarray(obj.size)
        return c - half, c + half
    if isinstance(obj, CylinderObject):
        half = np.array([obj.radius, 0.5 * obj.height, obj.radius])
        return c - half, c + half
    if isinstance(obj, PlaneObject):
        half = np.array([0.5 * obj.size[0], 0.0, 0.5 * obj.size[1]])
        return c - half, c + half
    if isinstance(obj, DiskObject):
        half = np.array([obj.radius, 0.0, obj.radius])
        return c - half, c + half
    if isinstance(obj, InlineMeshObject):
        v = np.asarray(obj.vertices, dtype=np.float64)
        return v.min(axis=0), v.max(axis=0)
    return None


def _world_box(obj: SceneObject) -> tuple[np.ndarray, np.ndarray] | None:
    box = _object_box(obj)
    if box is None:
        return None
    lo, hi = box
    corners = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    world = corners @ np.asarray(obj.transform.to_matrix(), dtype=np.float64).T
    return world[:, :3].min(axis=0), world[:, :3].max(axis=0)


def scene_bounds(scene: Scene) -> tuple[np.ndarray, np.ndarray] | None:
    """World bounds of the scene's objects from the document (each object's box, transformed); None when
    the scene has a mesh file (its vertices are not read here)."""
    boxes = [_world_box(obj) for obj in scene.objects]
    if any(b is None for b in boxes) or not boxes:
        return None
    lo = np.min([b[0] for b in boxes if b is not None], axis=0)
    hi = np.max([b[1] for b in boxes if b is not None], axis=0)
    return lo, hi


def _surface_area(obj: SceneObject) -> float:
    """World surface area of an object (scaled by the transform's mean area factor); 0 for a mesh file."""
    if isinstance(obj, SphereObject):
        local = 4.0 * math.pi * obj.radius ** 2
    elif isinstance(obj, BoxObject):
        x, y, z = obj.size
        local = 2.0 * (x * y + y * z + z * x)
    elif isinstance(obj, CylinderObject):
        local = 2.0 * math.pi * obj.radius * obj.height + (2.0 * math.pi * obj.radius ** 2 if obj.capped else 0.0)
    elif isinstance(obj, PlaneObject):
        local = obj.size[0] * obj.size[1]
    elif isinstance(obj, DiskObject):
        local = math.pi * obj.radius ** 2
    elif isinstance(obj, InlineMeshObject):
        v = np.asarray(obj.vertices, dtype=np.float64)
        f = np.asarray(obj.faces, dtype=np.int64)
        local = float(0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum())
    else:
        return 0.0
    m = np.asarray(obj.transform.to_matrix(), dtype=np.float64)[:3, :3]
    return float(local * abs(float(np.linalg.det(m))) ** (2.0 / 3.0))


def scene_cost(triangles: int) -> Cost:
    """Building a scene of ``triangles`` (every job that renders or bakes one does, once per worker)."""
    return Cost("scene build", triangles, int(MARGIN * SCENE_BYTES_PER_TRIANGLE * triangles),
                SCENE_CPU_S_PER_TRIANGLE * triangles, SCENE_CPU_S_PER_TRIANGLE * triangles)


def _plus_scene(kind: str, triangles: int, body_bytes: float, body_cpu_s: float, jobs: int = 1,
                total_cpu_s: float | None = None, **detail: Any) -> Cost:
    s = scene_cost(triangles)
    peak = int(MARGIN * (body_bytes + FIXED_BYTES)) + s.peak_bytes + WORKER_KEPT_BYTES
    cpu = body_cpu_s + s.cpu_s
    total = (total_cpu_s if total_cpu_s is not None else body_cpu_s * jobs) + s.cpu_s * jobs
    return Cost(kind, triangles, peak, cpu, total, jobs,
                {"scene_bytes": s.peak_bytes, "kept_bytes": WORKER_KEPT_BYTES, "scene_cpu_s": round(s.cpu_s, 3),
                 **detail})


# --------------------------------------------------------------------------- renders


def reference_chunk_pixels(pixels: int) -> int:
    """Pixels per wavefront chunk of a reference render of ``pixels`` (``engine.reference``: an eighth of
    the image, at least 1024 and at most ``REFERENCE_CHUNK_PIXELS``); its rays for every sample are traced
    at once."""
    return min(pixels, REFERENCE_CHUNK_PIXELS, max(1024, -(-pixels // 8)))


def _reference_bytes(p: Any, pixels: int) -> float:
    chunk = reference_chunk_pixels(pixels)
    per_sample = (REFERENCE_BYTES_PER_CHUNK_SAMPLE
                  + REFERENCE_BYTES_PER_GLOSSY_RAY * (p.glossy_samples - 1 + p.indirect_samples)
                  + REFERENCE_BYTES_PER_AREA_RAY * (p.area_light_samples - 1))
    in_flight = 0.5 if chunk >= pixels else 1.0  # the constants hold two chunks in flight; one chunk: one
    return float(REFERENCE_BYTES_PER_PIXEL * pixels + in_flight * chunk * max(p.spp, 2) * per_sample)


def _light_paths_priced(p: Any, light_traced: bool) -> float:
    """Light paths per pixel sample a reference render with ``p`` traces where the scene is
    ``light_traced``: its ``light_paths`` when it traces indirect paths, else none."""
    return float(getattr(p, "light_paths", 0.0)) if light_traced and getattr(p, "indirect_samples", 0) > 0 else 0.0


def _reference_cpu_s(p: Any, pixels: int, light_traced: bool = False) -> float:
    glossy = p.glossy_samples + getattr(p, "indirect_samples", 0) * getattr(p, "indirect_bounces", 1)
    light = _light_paths_priced(p, light_traced)
    return float(pixels * p.spp * (REFERENCE_CPU_S_PER_SAMPLE + REFERENCE_CPU_S_PER_GLOSSY_RAY * glossy
                                   + REFERENCE_CPU_S_PER_AREA_RAY * p.area_light_samples
                                   + REFERENCE_CPU_S_PER_LIGHT_PATH * light))


def render_cost(req: RenderRequest, width: int, height: int, triangles: int = 0, auto_glossy_rays: int = 0,
                light_traced: bool = False) -> Cost:
    """A render job of ``req`` at ``width`` x ``height`` (the request's camera, or the scene's) of a scene
    of ``triangles``, in a worker (``WORKER_KEPT_BYTES`` included); ``auto_glossy_rays``: what
    ``view.glossy_rays="auto"`` means for the scene (``scene_auto_glossy_rays``); ``light_traced``: a
    reference render light-traces caustics there (``scene_light_traced``). The memory's image part is
    ``estimate_render_bytes`` (light paths are traced in batches of bounded size, not priced)."""
    pixels = width * height
    if method_needs_bake(req.method):
        # supersampling renders s x s sub-pixels: in every pixel (uniform) or, at most, in every pixel at an edge
        s = req.view.supersample
        body, cpu = float(LDC_BYTES_PER_PIXEL * pixels * s * s), LDC_CPU_S_PER_PIXEL * pixels * s * s
        where = "edge pixel" if req.view.antialias == "edges" else "pixel"
        spp = f" at {s} x {s} samples per {where}" if s > 1 else ""
        k = parse_method(req.method).ibrt_generations or 0
        rays = auto_glossy_rays if req.view.glossy_rays == "auto" else req.view.glossy_rays
        if rays and k:
            cpu += GLOSSY_RAY_CPU_S * pixels * rays * (k + 1)  # a pixel's rays are shared by its sub-pixels
            spp += f", {rays} glossy rays per glossy pixel"
    else:
        body, cpu = _reference_bytes(req.params, pixels), _reference_cpu_s(req.params, pixels, light_traced)
        spp = f" at {req.params.spp} spp"
        if (light := _light_paths_priced(req.params, light_traced)) > 0:
            spp += f", {light:g} light paths per sample"
    return _plus_scene(f"{req.method} render of {width} x {height}{spp}", triangles, body, cpu,
                       render_bytes=int(MARGIN * (body + FIXED_BYTES)))


def scene_auto_glossy_rays(scene: Scene) -> int:
    """The glossy lobe rays ``view.glossy_rays="auto"`` traces per glossy pixel in ``scene``
    (``engine.methods.auto_glossy_rays`` of its declared materials and lights; the renderer asks it of
    the materials its triangles use), for pricing."""
    return auto_glossy_rays(any(max(m.kg) > 0 for m in scene.materials), any(max(m.kr) > 0 for m in scene.materials),
                            any(getattr(li, "type", "") == "rect" for li in scene.lights))


def _scene_has_caustics(scene: Scene) -> bool:
    """Can light reach a diffuse surface through a mirror or a glossy lobe (``engine.caustics.has_caustics``:
    a rect light and a mirror or glossy material)? Declared materials stand for the triangles' (an unused
    mirror material prices caustics the engine will not trace: an over-estimate)."""
    return (any(max(m.kr) > 0 or max(m.kg) > 0 for m in scene.materials)
            and any(getattr(li, "type", "") == "rect" for li in scene.lights))


def scene_light_traced(scene: Scene, camera: Any) -> bool:
    """Could a reference render of ``scene`` through ``camera`` light-trace caustics
    (``engine.light_tracing.applies``: a pinhole camera and a scene with caustics; the render's own
    parameters decide the rest), for pricing."""
    return getattr(camera, "type", "perspective") == "perspective" and _scene_has_caustics(scene)


def estimate_render_bytes(req: RenderRequest, width: int, height: int) -> int:
    """Estimated growth of a process's peak memory while it renders ``req`` at ``width`` x ``height`` of a
    scene it holds already, without a worker's kept memory (the image part of :func:`render_cost`)."""
    return int(render_cost(req, width, height).detail["render_bytes"])


def batch_cost(costs: Iterable[Cost]) -> Cost:
    """A batch of renders: its largest job's memory and time, the sum of their times."""
    items = list(costs)
    if not items:
        return Cost("batch", jobs=0)
    big = max(items, key=lambda c: c.peak_bytes)
    return Cost(f"batch of {len(items)} renders", max(c.triangles for c in items), big.peak_bytes,
                max(c.cpu_s for c in items), sum(c.total_cpu_s for c in items), len(items),
                {"largest": big.kind})


# --------------------------------------------------------------------------- scene bakes


def _ldi_bytes(pixels: int, max_layers: int, sample_bytes: int) -> int:
    return pixels * (9 + max_layers * sample_bytes) + 8


def expected_paths(params: BakeParams) -> float:
    """Expected indirect paths per LDC sample side, over all sides: a traced side takes the fixed
    sampler's count or stops between ``min_paths`` and ``max_paths``
    (``engine.newviews.indirect_sampling``), and at ``stride`` s about one side in s^2 is traced (the
    others are interpolated, ``engine/newviews/sparse_indirect.py``)."""
    ip = params.indirect
    return expected_paths_per_side(ip.sampling, ip.noise, ip.min_paths, ip.max_paths, ip.round_paths) / ip.stride ** 2


def _has_caustics(scene: Scene, params: BakeParams) -> bool:
    """Will the indirect pass build a caustic photon map (``engine.caustics.has_caustics``: a rect light
    and a mirror or glossy material, with ``caustics`` = ``photons``)?"""
    return params.indirect.caustics == "photons" and _scene_has_caustics(scene)


def _axis_grids(scene: Scene, resolution: int) -> list[int]:
    """Pixels of the LDC's three axis grids (``engine.newviews.ldi.axis_frame``, one pixel of padding);
    without bounds (a mesh file) every axis at the cube's ``(resolution + 2)^2``."""
    bounds = scene_bounds(scene)
    if bounds is None:
        return [(resolution + 2) ** 2] * 3
    ext = np.maximum(bounds[1] - bounds[0], 0.0)
    h = float(ext.max()) / resolution if ext.max() > 0 else 1.0
    n = [max(1, math.ceil(e / h + 2)) for e in ext]
    return [n[1] * n[2], n[0] * n[2], n[0] * n[1]]


def bake_cost(scene: Scene, params: BakeParams, triangles: int, paths_per_s: float) -> Cost:
    """A scene bake (plan, LDC axis parts, indirect chunks, LLF chunks, merge): its largest job's memory
    and CPU time, and the whole bake's CPU time (dominated by the indirect pass), as the plan job
    estimates them (``workers/jobs/bake.py``), from the document: expected LDC samples from each object's
    surface area (a surface seen along the three axes crosses ``1.25 area / h^2`` rays of the grids
    together, between an axis-aligned box's 1 and a random orientation's 1.5), every light's visibility
    word counted, the grid from the objects' analytic bounds."""
    res, layers = params.ldc_resolution, params.max_layers
    words = (len(scene.lights) + 63) // 64
    grids = _axis_grids(scene, res)
    axis_bytes = [_ldi_bytes(g, layers, LDI_SAMPLE_BYTES + LDC_ATTR_BYTES + 16 * words) for g in grids]
    bounds = scene_bounds(scene)
    ext = float(np.max(bounds[1] - bounds[0])) if bounds is not None else 0.0
    detail: dict[str, Any] = {"ldc_axis_bytes_max": max(axis_bytes)}
    if ext > 0 and params.indirect.mode != "off":
        h = ext / res
        kd = {m.name: max(m.kd) > 0 for m in scene.materials}
        area = sum(_surface_area(obj) for obj in scene.objects if kd.get(obj.material, True))
        cap = sum(grids) * layers
        samples = min(cap, 1.25 * area / (h * h))
    elif params.indirect.mode != "off":  # a mesh file: no area from the document; the grid's layers at 2 deep
        samples = sum(grids) * min(layers, 2)
    else:
        samples = 0.0
    rate = paths_per_s * (PATHS_RATE_BOUNCES + 1) / (params.indirect.bounces + 1)
    sides = 2.0 * samples
    photons = params.indirect.caustic_photons if samples and _has_caustics(scene, params) else 0
    caustic_cpu = 3 * params.indirect.chunks * photons * CAUSTIC_CPU_S_PER_PHOTON
    indirect_cpu = sides * expected_paths(params) / rate + caustic_cpu
    chunk_paths = min(MAX_RAYS_PER_BATCH, math.ceil(sides / 3 / params.indirect.chunks) * params.indirect.round_paths)
    chunk_bytes = (max(axis_bytes) + max(chunk_paths * INDIRECT_RAY_BYTES, photons * CAUSTIC_BYTES_PER_PHOTON)
                   if samples else 0)
    n_dir = 4 * params.llf_f ** 2 + 2
    llf_bytes = min(params.llf_chunk, n_dir) * _ldi_bytes(params.llf_resolution ** 2, layers, LLF_SAMPLE_BYTES)
    part = max(max(axis_bytes), chunk_bytes, llf_bytes if params.llf != "never" else 0)
    jobs = 3 + (3 * params.indirect.chunks if samples else 0) + 2
    detail.update({"ldc_samples_expected": int(samples), "indirect_cpu_s": round(indirect_cpu, 1),
                   "caustic_map_cpu_s": round(caustic_cpu, 1),
                   "indirect_chunk_bytes_max": chunk_bytes, "llf_chunk_bytes_max": llf_bytes})
    s = scene_cost(triangles)
    per_job_cpu = indirect_cpu / max(1, 3 * params.indirect.chunks) + s.cpu_s
    return Cost("scene bake", triangles, part + s.peak_bytes, per_job_cpu, indirect_cpu + jobs * s.cpu_s, jobs,
                {"scene_bytes": s.peak_bytes, **detail})


# --------------------------------------------------------------------------- calibrations


CALIBRATION_SPP_TOTAL = 1 + 4 + 16
"""``engine.quality.CALIBRATION_SPP`` summed: the reference sample counts a calibration renders per probe."""
CALIBRATION_LDC_RUNS = 3
"""Timed runs of each LDC method per probe and size (``workers.jobs.calibrate.LDC_REPEATS``)."""


def calibration_cost(scene: Scene, params: CalibrationParams, triangles: int, has_mirrors: bool = True) -> Cost:
    """A calibration job (``workers/jobs/calibrate.py``): per probe view the ground truth at ``truth_spp``,
    the reference at 1, 4 and 16 spp and adaptively (up to ``truth_spp``), every LDC method at ``size``
    and ``size x time_scale``, each timed a few times."""
    from api_schemas.service import ReferenceRenderParams

    cam = scene.camera
    scale = params.size / max(cam.width, cam.height)
    w, h = max(1, round(cam.width * scale)), max(1, round(cam.height * scale))
    pixels = w * h
    truth = ReferenceRenderParams(spp=params.truth_spp)
    one = ReferenceRenderParams(spp=1)
    big = pixels * params.time_scale ** 2
    ldc_methods = 2 + (len(params.ibrt_ks) if has_mirrors else 0)
    ref_cpu = (2 * params.truth_spp + CALIBRATION_SPP_TOTAL) * _reference_cpu_s(one, pixels)
    cpu = params.probes * (ref_cpu + CALIBRATION_LDC_RUNS * ldc_methods * LDC_CPU_S_PER_PIXEL * (pixels + big))
    body = max(_reference_bytes(truth, pixels), LDC_BYTES_PER_PIXEL * big)
    return _plus_scene(f"calibration ({params.probes} probes of {w} x {h}, truth at {params.truth_spp} spp)",
                       triangles, body, cpu)


# --------------------------------------------------------------------------- datasets


def generate_cost(req: GenerateRequest, width: int, height: int, triangles: int, n_lights: int) -> Cost:
    """A dataset generation job: ``n_lights`` reference renders (one per light) plus the ground truths, the
    stack of float32 images kept until they are encoded."""
    pixels = width * height
    n = n_lights + len(req.ground_truth)
    body = _reference_bytes(req.params, pixels) + n * pixels * IMAGE_BYTES_PER_PIXEL
    cpu = n * _reference_cpu_s(req.params, pixels)
    return _plus_scene(f"dataset generation of {n} images of {width} x {height}", triangles, body, cpu,
                       images=n)


_REGION_SR = {"sphere": 4.0 * math.pi, "hemisphere": 2.0 * math.pi, "upper_front_quarter": math.pi}


def light_count(req: GenerateRequest) -> int:
    """Lights the placement puts in a generated dataset: its region's solid angle over the spacing's
    (``engine.relighting.generate`` places them; this count is within ~20 % of its grids), at most
    ``max_lights``."""
    spacing = math.radians(req.placement.spacing_deg)
    return max(3, min(req.max_lights, math.ceil(_REGION_SR[req.placement.region] / (spacing * spacing))))


def dataset_bake_cost(n_images: int, width: int, height: int, params: DatasetBakeParams) -> Cost:
    """A dataset bake: the decoded float32 stack and the baked copy."""
    values = n_images * width * height * 3
    body = values * DATASET_BAKE_BYTES_PER_VALUE * (2 if params.compress is not None else 1)
    cpu = values * RELIGHT_CPU_S_PER_VALUE * (50 if params.compress is not None else 5)
    return _plus_scene(f"dataset bake of {n_images} images of {width} x {height}", 0, body, cpu)


def _expanded_lights(lights: Iterable[Any]) -> int:
    total = 0
    for light in lights:
        total += int(getattr(light, "samples", None) or getattr(light, "n_lights", None) or 1)
    return total


def relight_cost(req: RelightRequest, n_images: int, width: int, height: int) -> Cost:
    """A relight: the baked stack (float16 or factors) held warm, the weights per image, the output."""
    pixels = width * height
    body = n_images * pixels * 3 * (2 if req.bake.half else 4) + 4 * pixels * IMAGE_BYTES_PER_PIXEL
    cpu = n_images * pixels * 3 * RELIGHT_CPU_S_PER_VALUE + _expanded_lights(req.lights) * n_images * 1e-6
    return _plus_scene(f"relight of {width} x {height}", 0, body, cpu)


def composite_cost(req: CompositeRequest, n_images: int, width: int, height: int) -> Cost:
    """A composite: two relights (object and background datasets) and the plate, mask and blend images."""
    one = relight_cost(RelightRequest(dataset_id="0" * 64, lights=req.lights, bake=req.bake), n_images, width, height)
    pixels = width * height
    body = 2 * (one.peak_bytes / MARGIN - FIXED_BYTES) + 6 * pixels * IMAGE_BYTES_PER_PIXEL
    return _plus_scene(f"composite of {width} x {height}", 0, body, 2 * one.cpu_s)


# --------------------------------------------------------------------------- walkthroughs


def walkthrough_costs(req: WalkthroughRequest, triangles: int,
                      frame_pixels: Callable[[Any], int] | None = None) -> tuple[Cost, Cost]:
    """``(bake, frames)``: the walkthrough bake (its base range images at their upper bound; nothing
    but the scene for path-traced frames) and the largest frame-chunk job (``chunk_frames`` LDC-like
    frames, or path-traced ones)."""
    pixels = [f.camera.width * f.camera.height if frame_pixels is None else frame_pixels(f) for f in req.frames]
    chunk = req.chunk_frames
    worst = max(sum(pixels[a:a + chunk]) for a in range(0, len(pixels), chunk))
    n_chunks = -(-len(pixels) // chunk)
    if req.path_traced is not None:
        per_px = WALKTHROUGH_CPU_S_PER_PATH * path_traced_settings(req.path_traced.noise).expected_paths
        frames = _plus_scene(f"path-traced walkthrough frame chunk of {min(chunk, len(pixels))} frames", triangles,
                             (REFERENCE_BYTES_PER_PIXEL + IMAGE_BYTES_PER_PIXEL) * max(pixels), per_px * worst,
                             n_chunks, per_px * sum(pixels))
        return scene_cost(triangles), frames
    base = req.bake.upper_bound_bytes()
    base_pixels = base // 32  # BYTES_PER_BASE_PIXEL
    bake = _plus_scene("walkthrough bake", triangles, base, base_pixels * WALKTHROUGH_CPU_S_PER_BASE_PIXEL,
                       base_bytes=base)
    frames = _plus_scene(f"walkthrough frame chunk of {min(chunk, len(pixels))} frames", triangles,
                         base + LDC_BYTES_PER_PIXEL * max(pixels), LDC_CPU_S_PER_PIXEL * worst, n_chunks,
                         LDC_CPU_S_PER_PIXEL * sum(pixels))
    return bake, frames
