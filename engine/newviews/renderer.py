"""Render a new view from a baked LDC (+ LLF): the first paper's rendering (docs/algorithms.md part A).

``LDCViewRenderer(scene, ldc, llf, plan).render(camera, method, ibrt_generations=k)``:

1. **Warp** (``engine/newviews/warp.py``): every LDC sample into the camera with a depth test; holes
   flagged (uncovered pixels and far surfaces seen through cracks).
2. **Hole filling**: ``fill="ibrt"`` (default) traces one image-based ray per hole pixel from
   the eye through the LDC (``engine/newviews/ibrt.py``); a hit shows that sample's diffuse radiance,
   a miss the background. ``fill="raycast"`` (the interim fill) casts Embree rays against
   the scene's triangles instead and shades the hits with the bake's diffuse model (it
   needs the triangles; the image-based fill needs only the bake). ``fill="none"`` leaves
   holes as background. **Silhouette rays** (``silhouette_rays=True``, the default; off with
   ``fill="none"``): covered pixels at a visibility edge of the warped image (a 4-neighbour
   shows another object, nothing, the same object more than ``silhouette_rel_depth``
   deeper or nearer, or the other side of a sheet) get the same eye ray as the holes. There
   the splats' footprints, which reach up to about a sample spacing past a silhouette,
   decided what the pixel shows; the ray decides by the pixel centre, and then the **mesh
   test** (``silhouette_mesh_test=True``) by the triangles of the candidates (the ray's hit,
   the warp's 3x3 winners) that the pixel ray really crosses (mirror_box, 256x256, LDC 512:
   pixels showing another object than the point-sampled reference 450-620 -> 11-34 per view,
   LRMS 0.060 -> 0.033, ~10 % more render time; ``docs/ldc.md``). Their provenance is 2 like
   the holes'; counts ``silhouette_rays``, ``silhouette_changed`` (pixels whose object
   changed) and ``silhouette_mesh_hits``.
2b. **Diffuse reconstruction** (``diffuse_filter="bilinear"``, the default): a pixel's
   view-independent radiance is interpolated bilinearly between the samples of its LDI's 2 x 2
   pixels around the point where the pixel ray meets the shown sample's tangent plane, among
   the samples on the same surface (same object, normals within ``SAME_SURFACE_COS``, within half
   a sample spacing of the plane); missing neighbours (a crease, a border, another object)
   drop out of the weights. A sample stands for a cell of its LDI; read whole
   (``diffuse_filter="nearest"``) it turns smooth shading into steps at the sample spacing and
   each sample's noise into a blotch, both beating against the camera's pixels. Timed as
   ``diffuse``; count ``diffuse_interpolated``.
3. **View-dependent pass**, only on the visible pixels whose material needs it (the effect
   plan; ``force_all_passes=True`` runs every pass of the method on every covered pixel,
   for the test that skipping changes nothing): Phong highlights gated by the LDC's
   visibility bits (``engine/newviews/view_pass.py``), then reflections:

   - ``ldc``: no reflections (warp + holes + highlights: everything the LDC alone holds);
   - ``ldc+llf``: light-field gather for mirror (3-direction cone) and glossy (lobe) terms;
   - ``ldc+ibrt`` with ``ibrt_generations`` = k: the mirror term (kr) is traced through the
     LDC for k generations (at each hit: the sample's diffuse radiance + its highlights
     toward the ray + its glossy gather + kr x the next generation), the last generation
     ending in the mirror-cone gather at its hit; a ray that meets a rect light first shows
     it. The glossy term is gathered, or traced with ``glossy_rays`` (``_mirrors``; by
     default where a glossy surface may see a rect light in a mirror). k = 0 is ``ldc+llf``.
     Rays that leave the LDC see the background.

The radiance of a pixel is the sample's view-independent radiance (direct diffuse with
shadows + ambient + emission, from the bake) + highlights + reflections.

Provenance per pixel: 0 background, 1 warped, 2 hole-filled, 3 reflections gathered,
4 reflections traced (the later stages overwrite the earlier ones).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numba as nb
import numpy as np

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)
from engine.errors import InvalidInputError, NonFiniteOutputError
from engine.geometry.adjacency import locate_on_mesh, triangle_neighbours
from engine.methods import (
    ANTIALIAS_MODES,
    GLOSSY_FILTER,
    GLOSSY_RAYS,
    IBRT_GENERATIONS,
    LDC_IBRT,
    MethodSpec,
    allowed_forms,
    auto_glossy_rays,
)
from engine.methods import parse_method as parse_wire_method
from engine.newviews.effects import EffectPlan, analyze, plan_from_dict
from engine.newviews.ldc import LDC, shade_samples, surface_attributes
from engine.newviews.llf import LLF
from engine.newviews.sparse_indirect import SAME_SURFACE_COS
from engine.newviews.view_pass import (
    GatherParams,
    gather_params,
    gather_point,
    gather_scratch,
    highlight_params,
    highlight_point_u,
)
from engine.newviews.warp import WarpResult, warp_ldc
from engine.path_vertex import _lobe_dir, _rect_light_t
from engine.raycast import RayCaster, make_caster
from engine.sampler import sample_2d, sample_key
from engine.scene import CameraParams, RuntimeScene
from engine.sched import next_block
from engine.shading import mirror_direction

PROV_NONE = 0
PROV_WARPED = 1
PROV_FILLED = 2
PROV_GATHERED = 3
PROV_TRACED = 4

FILLS = ("ibrt", "raycast", "none")
ANTIALIAS = ANTIALIAS_MODES  #: where ``supersample`` > 1 traces sub-pixel rays (``engine.methods``)
EDGE_CONTRAST = 0.05  #: ``antialias="edges"``: the luminance step (relative) that makes an edge pixel
SAME_FACE_COS = 0.9  #: ``antialias="edges"``: a sample is on the crossed face if its normal is this close


@dataclass
class LDCRenderResult:
    """radiance (h, w, 3) float32 linear; depth (h, w) float32 distance along the pixel ray (0
    where empty); normal (h, w, 3) float32 shading normal facing the camera; object_id,
    material_id (h, w) int32 (-1 where empty); provenance (h, w) uint8 (module docstring);
    hole_mask (h, w) bool (holes found by the warp, before filling); timings (seconds per
    stage), counts (work done), plan (which passes ran and why)."""

    radiance: np.ndarray
    depth: np.ndarray
    normal: np.ndarray
    object_id: np.ndarray
    material_id: np.ndarray
    provenance: np.ndarray
    hole_mask: np.ndarray
    timings: dict[str, float] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    plan: dict = field(default_factory=dict)


def method_spec(method: str, ibrt_generations: int = 0) -> MethodSpec:
    """The registry's (``engine.methods``) spec of an LDC method: a wire string ("ldc+ibrt:k"
    carries k) or "ldc+ibrt" with ``ibrt_generations`` (checked for every method). The renderer
    reads what a method does from the spec (``gathers``, ``ibrt_generations``), never from the string."""
    k = IBRT_GENERATIONS.check(ibrt_generations, "ibrt_generations")
    spec = LDC_IBRT.spec(k) if method == LDC_IBRT.name else parse_wire_method(method)
    if not spec.needs_bake:
        raise InvalidInputError(f"the LDC renderer renders {allowed_forms(needs_bake=True)}, got {method!r}")
    return spec


def parse_method(method: str, ibrt_generations: int = 0) -> tuple[str, int]:
    """("ldc" | "ldc+llf" | "ldc+ibrt", k) of an LDC method (``method_spec``)."""
    spec = method_spec(method, ibrt_generations)
    return spec.name, spec.ibrt_generations


# ----------------------------------------------------------------------------- kernel parameters
# The fused kernels take their arrays in named bundles (NamedTuples: numba passes a bundle like
# its fields one by one and reads a field by name). A kernel takes a bundle's fields out ONCE per
# thread, outside its pixel loop: a field read inside the loop of an inlined helper may cost an
# atomic reference count per pixel on arrays both threads share.


class KernelCamera(NamedTuple):
    """The camera as the kernels take it (``kernel_camera``): one basis per render, and the
    numbers ``_pixel_ray`` turns a flat pixel index into its eye ray with."""

    ortho: bool  #: orthographic (else perspective)
    eye: np.ndarray  #: (3,) float64 eye position
    right: np.ndarray  #: (3,) float64 image x axis
    up: np.ndarray  #: (3,) float64 image y axis
    forward: np.ndarray  #: (3,) float64 viewing direction
    width: int  #: pixels
    height: int  #: pixels
    tan_half_fov: float  #: tan(fov_y / 2) (perspective)
    aspect: float  #: width / height
    half_ortho_height: float  #: half the image height in world units (orthographic)
    pixel_angle: float  #: a pixel's size per unit distance (perspective): 2 tan(fov_y / 2) / height
    ortho_pixel: float  #: a pixel's size in world units (orthographic)


def kernel_camera(camera: CameraParams) -> KernelCamera:
    """``camera`` as the kernels take it."""
    right, up, fwd = camera.basis()
    th = float(np.tan(np.radians(camera.fov_y_deg) * 0.5))
    px_size = 2.0 * math.tan(math.radians(camera.fov_y_deg) * 0.5) / camera.height
    return KernelCamera(camera.kind == "orthographic", np.asarray(camera.eye, np.float64), right, up, fwd,
                        int(camera.width), int(camera.height), th, camera.width / camera.height,
                        0.5 * camera.ortho_height, px_size, camera.ortho_height / camera.height)


class AxisArrays(NamedTuple):
    """One LDC axis as the fused kernels read it (``_ldc_axes``): its LDI frame and, per sample,
    the bake's records."""

    origin: np.ndarray  #: (3,) float64 the frame's origin
    u: np.ndarray  #: (3,) float64 the frame's pixel axis u
    v: np.ndarray  #: (3,) float64 the frame's pixel axis v
    w: np.ndarray  #: (3,) float64 the frame's depth axis
    h: float  #: pixel size
    nu: int  #: pixels per row
    sample_pixel: np.ndarray  #: (n,) int32 LDI pixel of every sample
    depth: np.ndarray  #: (n,) float64 depth along w
    geo_normal: np.ndarray  #: (n, 3) float32 geometric normal
    normal: np.ndarray  #: (n, 3) float32 shading normal
    material: np.ndarray  #: (n,) int32 material index
    object: np.ndarray  #: (n,) int32 object index
    diffuse: np.ndarray  #: (n, 2, 3) float32 view-independent radiance per side
    visibility: np.ndarray  #: (2 n, W) uint64 light-visibility words, row 2 s + side
    prim: np.ndarray  #: (n,) int32 triangle the sample lies on
    offsets: np.ndarray  #: (nu nv + 1,) int64 the LDI's CSR: pixel k owns samples offsets[k] .. offsets[k + 1] - 1


class PixelSamples(NamedTuple):
    """Per flat camera pixel, the LDC sample it shows (the warp's, or a fill ray's hit)."""

    axis: np.ndarray  #: (h w,) int8 LDC axis (-1: none)
    index: np.ndarray  #: (h w,) int64 sample index on that axis
    side: np.ndarray  #: (h w,) int8 side of the sample facing the camera (0: along the normal)


class SurfaceMesh(NamedTuple):
    """The triangles a sample's point is refined onto (``_refine_point``)."""

    tri_p: np.ndarray  #: (nt, 3, 3) float64 vertex positions
    tri_n: np.ndarray  #: (nt, 3, 3) float64 vertex normals
    tri_ng: np.ndarray  #: (nt, 3) float64 geometric normals
    neighbours: np.ndarray  #: (nt, 3) int32 edge neighbours for the walk ((0, 3): no walk)
    ldc_h: float  #: the LDC's pixel size (the move limits are multiples of it)


class RaycastRecords(NamedTuple):
    """The surface records of the pixels the raycast fill shaded (no LDC sample behind them)."""

    row: np.ndarray  #: (h w,) int64 flat pixel -> record row (-1: none); (0,) when there are none
    p: np.ndarray  #: (n, 3) float64 points
    ng: np.ndarray  #: (n, 3) float64 geometric normals (facing the camera)
    ns: np.ndarray  #: (n, 3) float64 shading normals (facing the camera)
    mat: np.ndarray  #: (n,) int32 materials
    bits: np.ndarray  #: (n, W) uint64 light-visibility words


class ViewPassSwitches(NamedTuple):
    """What the view pass does, per material and per render."""

    hl_mat: np.ndarray  #: (n_materials,) bool materials with highlights
    rf_mat: np.ndarray  #: (n_materials,) bool materials with reflections (mirror or glossy)
    gathered_mat: np.ndarray  #: (n_materials,) bool materials the gather does anything for
    want_hl: bool  #: the method's highlights run (the plan or ``force`` says so)
    want_rf: bool  #: the method's reflections run
    force: bool  #: every pass on every covered pixel (adds exact zeros)
    mirror: bool  #: the gather includes the mirror cone (not traced)
    trace: bool  #: write each reflecting pixel's mirror ray (``MirrorRays``)
    glossy: bool  #: write each glossy pixel's surface (``GlossySurfaces``): its lobe is traced, not gathered
    refine: bool  #: refine each sample's point onto its triangle at the pixel ray


class ViewPassImage(NamedTuple):
    """The flat image buffers the view pass adds to (row = flat pixel; ``lookups``: row = position in pix)."""

    radiance: np.ndarray  #: (h w, 3) float64
    normal: np.ndarray  #: (h w, 3) float32 shading normal used
    prov: np.ndarray  #: (h w,) uint8 provenance (module docstring)
    lookups: np.ndarray  #: (n_pix,) int64 LLF lookups per view-pass pixel


class MirrorRays(NamedTuple):
    """Mirror rays leaving surface points (row = the ray's slot; rows with ``live`` False are unused)."""

    o: np.ndarray  #: (n, 3) float64 origins
    d: np.ndarray  #: (n, 3) float64 unit directions
    ng: np.ndarray  #: (n, 3) float64 geometric normals at the origins
    thr: np.ndarray  #: (n, 3) float64 throughput (product of the kr met)
    live: np.ndarray  #: (n,) bool the slot holds a ray


def mirror_rays(n: int) -> MirrorRays:
    """n empty ray slots (none live)."""
    return MirrorRays(np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3)), np.zeros(n, np.bool_))


class GlossySurfaces(NamedTuple):
    """The surface points whose glossy lobe is traced (``glossy_rays``; row = the view pass's pixel,
    rows with ``live`` False are unused)."""

    p: np.ndarray  #: (n, 3) float64 points
    ng: np.ndarray  #: (n, 3) float64 geometric normals (facing the viewer)
    ns: np.ndarray  #: (n, 3) float64 shading normals (facing the viewer)
    wo: np.ndarray  #: (n, 3) float64 unit directions toward the viewer
    mat: np.ndarray  #: (n,) int32 materials
    live: np.ndarray  #: (n,) bool the row holds a surface


def glossy_surfaces(n: int) -> GlossySurfaces:
    """n empty rows (none live)."""
    return GlossySurfaces(np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3)),
                          np.zeros(n, np.int32), np.zeros(n, np.bool_))


class RayHits(NamedTuple):
    """Where image-based rays hit the LDC (``engine.newviews.ibrt.trace_prepared``)."""

    axis: np.ndarray  #: (n,) int8 LDC axis of the hit sample (-1: a miss)
    sample: np.ndarray  #: (n,) int64 the sample on that axis
    t: np.ndarray  #: (n,) float64 distance along the ray


class TracedRays(NamedTuple):
    """One generation of mirror rays, each adding to the pixel of its ``owner``."""

    o: np.ndarray  #: (n, 3) float64 origins
    d: np.ndarray  #: (n, 3) float64 unit directions
    owner: np.ndarray  #: (n,) int64 row of the accumulator the ray adds to (distinct within a generation)
    thr: np.ndarray  #: (n, 3) float64 throughput


class Generation(NamedTuple):
    """What one generation of ``_shade_hits`` does at its hits."""

    last: bool  #: the last generation: its gather includes the mirror cone, no ray continues
    has_llf: bool  #: there is a light field to gather from
    gather_mat: np.ndarray  #: (n_materials,) bool the gather does anything (glossy; mirrors on the last)
    force: bool  #: every term at every hit (adds exact zeros)
    background: np.ndarray  #: (3,) float64 radiance of a miss
    emitters: bool  #: the rays see the rect lights (the nearest of a light and the LDC's hit counts)


# ----------------------------------------------------------------------------- fused per-pixel kernels
# The three LDC axes travel as three bundles (``ax0``, ``ax1``, ``ax2``) and each part of a launch
# is a call with one of them, not a tuple of axes indexed by the axis at run time: numba does that
# only at the price of reference counting per access (measured: several times the work itself).


@nb.njit(cache=True, nogil=True, inline="always")
def _sample_point(org, fu, fv, fw, h, nu, k, dep):
    """World position of a sample in LDI pixel k at depth ``dep`` of an axis whose frame
    (origin, u, v, w) is given as 3-tuples (scalars only: an inlined function's array
    arguments are increfed and decrefed per call)."""
    aa = (k % nu + 0.5) * h
    bb = (k // nu + 0.5) * h
    return (org[0] + aa * fu[0] + bb * fv[0] + dep * fw[0],
            org[1] + aa * fu[1] + bb * fv[1] + dep * fw[1],
            org[2] + aa * fu[2] + bb * fv[2] + dep * fw[2])


@nb.njit(cache=True, nogil=True)
def _sample_normals(a0, a1, a2, b0, b1, b2, sd):
    """Geometric (a) and shading normal (b) of a sample flipped to side sd (the shading normal
    falls back to the geometric one when it is on the other side); scalars in and out."""
    sg = 1.0 if sd == 0 else -1.0
    g0, g1, g2 = sg * a0, sg * a1, sg * a2
    n0, n1, n2 = sg * b0, sg * b1, sg * b2
    if n0 * g0 + n1 * g1 + n2 * g2 <= 0.0:
        n0, n1, n2 = g0, g1, g2
    return g0, g1, g2, n0, n1, n2


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _interp_normal(t, bw, bu, bv, tri_n, tri_ng, g0, g1, g2):
    """Triangle t's vertex normals at barycentrics (bw, bu, bv), normalised and flipped to the
    side the sample was seen from (g), falling back to g when it points the other way; ok False
    when the interpolated normal vanishes. A plain function (LLVM inlines it): inlined by numba
    its two array arguments were increfed and decrefed per call."""
    m0 = bw * tri_n[t, 0, 0] + bu * tri_n[t, 1, 0] + bv * tri_n[t, 2, 0]
    m1 = bw * tri_n[t, 0, 1] + bu * tri_n[t, 1, 1] + bv * tri_n[t, 2, 1]
    m2 = bw * tri_n[t, 0, 2] + bu * tri_n[t, 1, 2] + bv * tri_n[t, 2, 2]
    ln = math.sqrt(m0 * m0 + m1 * m1 + m2 * m2)
    if not ln > 1e-12:
        return False, g0, g1, g2
    sg = 1.0 if g0 * tri_ng[t, 0] + g1 * tri_ng[t, 1] + g2 * tri_ng[t, 2] >= 0.0 else -1.0
    m0, m1, m2 = sg * m0 / ln, sg * m1 / ln, sg * m2 / ln
    if m0 * g0 + m1 * g1 + m2 * g2 <= 0.0:
        m0, m1, m2 = g0, g1, g2
    return True, m0, m1, m2


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _refine_point(ox, oy, oz, dx, dy, dz, t, mesh, max_move, px, py, pz, g0, g1, g2, n0, n1, n2):
    """The pixel ray o + t d meets the surface of the sample's triangle t of ``mesh`` (a
    ``SurfaceMesh``): move p there (when within max_move) and interpolate the shading normal,
    flipped like g. With the mesh's edge neighbours (``engine.geometry.adjacency``; (0, 3): none) the walk first
    crosses edges to the triangle the ray crosses (up to 8 steps); where it ends inside a
    triangle that triangle's barycentrics are used, otherwise (a border, a silhouette, too many
    steps) triangle t's, clamped to [-0.25, 1.25] (mild extrapolation across its edges).
    Returns (p, ns), unchanged when the ray misses the plane or the crossing is too far."""
    tri_p, tri_n, tri_ng, nbr = mesh.tri_p, mesh.tri_n, mesh.tri_ng, mesh.neighbours
    if nbr.shape[0] > 0:
        ok, t2, s2, bw, bu, bv = locate_on_mesh(ox, oy, oz, dx, dy, dz, t, tri_p, tri_ng, nbr, 8)
        if ok and min(bw, min(bu, bv)) >= -1e-6:
            qx, qy, qz = ox + s2 * dx, oy + s2 * dy, oz + s2 * dz
            ex, ey, ez = qx - px, qy - py, qz - pz
            if ex * ex + ey * ey + ez * ez <= max_move * max_move:
                ok, m0, m1, m2 = _interp_normal(t2, max(bw, 0.0), max(bu, 0.0), max(bv, 0.0), tri_n, tri_ng, g0,
                                                g1, g2)
                if ok:
                    return qx, qy, qz, m0, m1, m2
    den = dx * g0 + dy * g1 + dz * g2
    if abs(den) < 1e-9:
        return px, py, pz, n0, n1, n2
    ax, ay, az = tri_p[t, 0, 0], tri_p[t, 0, 1], tri_p[t, 0, 2]
    tt = ((ax - ox) * g0 + (ay - oy) * g1 + (az - oz) * g2) / den
    if not tt > 0.0:
        return px, py, pz, n0, n1, n2
    qx, qy, qz = ox + tt * dx, oy + tt * dy, oz + tt * dz
    ex, ey, ez = qx - px, qy - py, qz - pz
    if not (ex * ex + ey * ey + ez * ez <= max_move * max_move):
        return px, py, pz, n0, n1, n2
    e1x, e1y, e1z = tri_p[t, 1, 0] - ax, tri_p[t, 1, 1] - ay, tri_p[t, 1, 2] - az
    e2x, e2y, e2z = tri_p[t, 2, 0] - ax, tri_p[t, 2, 1] - ay, tri_p[t, 2, 2] - az
    vx, vy, vz = qx - ax, qy - ay, qz - az
    d00 = e1x * e1x + e1y * e1y + e1z * e1z
    d01 = e1x * e2x + e1y * e2y + e1z * e2z
    d11 = e2x * e2x + e2y * e2y + e2z * e2z
    d20 = vx * e1x + vy * e1y + vz * e1z
    d21 = vx * e2x + vy * e2y + vz * e2z
    dd = d00 * d11 - d01 * d01
    if not dd > 0.0:
        return px, py, pz, n0, n1, n2
    bu = min(max((d11 * d20 - d01 * d21) / dd, -0.25), 1.25)
    bv = min(max((d00 * d21 - d01 * d20) / dd, -0.25), 1.25)
    bw = min(max(1.0 - bu - bv, -0.25), 1.25)
    ok, m0, m1, m2 = _interp_normal(t, bw, bu, bv, tri_n, tri_ng, g0, g1, g2)
    if not ok:
        return px, py, pz, n0, n1, n2
    return qx, qy, qz, m0, m1, m2


DIFFUSE_FILTERS = ("bilinear", "nearest")
"""How a pixel's view-independent radiance is read from the LDC (``LDCViewRenderer._smooth_diffuse``)."""


@nb.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _bilinear_diffuse(r, i, sd, ray, frm, h, nu, spix, depth, geo, obj_a, diff, offsets, radiance):
    """The diffuse radiance of frame row ``r`` (eye ray ``ray`` = (ox, oy, oz, dx, dy, dz),
    showing sample ``i``, side ``sd``, of an LDC axis: its frame ``frm`` = (origin, u, v, w),
    pixel size ``h``, ``nu`` pixels per row, and the ``AxisArrays`` fields named alike),
    interpolated bilinearly between the samples of the LDI's 2 x 2 pixels around where the pixel
    ray meets the sample's tangent plane, among those on the same surface (object, normal
    within ``SAME_SURFACE_COS``, within half a pixel of the plane); the weights of missing
    neighbours are left out (a crease, a border, another object). Written to ``radiance[r]``;
    False (nothing written: the sample's own value stays) when the ray runs along the plane or
    meets it more than a pixel and a half from the sample."""
    nv = (offsets.shape[0] - 1) // nu
    k = np.int64(spix[i])
    ci, cj = k % nu, k // nu
    o0, o1, o2, u0, u1, u2, v0, v1, v2, w0, w1, w2 = frm
    a, b, dep = (ci + 0.5) * h, (cj + 0.5) * h, depth[i]
    p0 = o0 + a * u0 + b * v0 + dep * w0
    p1 = o1 + a * u1 + b * v1 + dep * w1
    p2 = o2 + a * u2 + b * v2 + dep * w2
    g0, g1, g2 = np.float64(geo[i, 0]), np.float64(geo[i, 1]), np.float64(geo[i, 2])
    ox, oy, oz, dx, dy, dz = ray
    den = dx * g0 + dy * g1 + dz * g2
    if abs(den) < 1e-6:
        return False
    t = ((p0 - ox) * g0 + (p1 - oy) * g1 + (p2 - oz) * g2) / den
    q0, q1, q2 = ox + t * dx - o0, oy + t * dy - o1, oz + t * dz - o2
    fx = (q0 * u0 + q1 * u1 + q2 * u2) / h - 0.5
    fy = (q0 * v0 + q1 * v1 + q2 * v2) / h - 0.5
    if not (abs(fx - ci) <= 1.5 and abs(fy - cj) <= 1.5):
        return False
    x0, y0 = math.floor(fx), math.floor(fy)
    tx, ty = fx - x0, fy - y0
    tol = 0.5 * h
    obj = obj_a[i]
    acc0 = acc1 = acc2 = 0.0
    wsum = 0.0
    for cy in range(2):
        yj = np.int64(y0) + cy
        wy = ty if cy == 1 else 1.0 - ty
        if yj < 0 or yj >= nv or wy <= 0.0:
            continue
        for cx in range(2):
            xi = np.int64(x0) + cx
            wx = tx if cx == 1 else 1.0 - tx
            if xi < 0 or xi >= nu or wx <= 0.0:
                continue
            kk = yj * nu + xi
            a, b = (xi + 0.5) * h, (yj + 0.5) * h
            best = -1
            best_d = tol
            for j in range(offsets[kk], offsets[kk + 1]):
                if obj_a[j] != obj:
                    continue
                if geo[j, 0] * g0 + geo[j, 1] * g1 + geo[j, 2] * g2 < SAME_SURFACE_COS:
                    continue
                dj = depth[j]
                e0 = o0 + a * u0 + b * v0 + dj * w0 - p0
                e1 = o1 + a * u1 + b * v1 + dj * w1 - p1
                e2 = o2 + a * u2 + b * v2 + dj * w2 - p2
                dist = abs(e0 * g0 + e1 * g1 + e2 * g2)
                if dist < best_d:
                    best, best_d = j, dist
            if best >= 0:
                wgt = wx * wy
                acc0 += wgt * diff[best, sd, 0]
                acc1 += wgt * diff[best, sd, 1]
                acc2 += wgt * diff[best, sd, 2]
                wsum += wgt
    if wsum < 1e-3:
        return False
    radiance[r, 0] = acc0 / wsum
    radiance[r, 1] = acc1 / wsum
    radiance[r, 2] = acc2 / wsum
    return True


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _bilinear_diffuse_block(lo, hi, axis, ax, pix, cam_pix, samples, cam, radiance):
    """``_bilinear_diffuse`` for the rows ``pix[lo:hi]`` whose sample is on LDC axis ``axis``
    (``AxisArrays`` ``ax``). One call per block and axis, the bundles unpacked once and the
    per-pixel function inlined into this loop: called per pixel with the bundles, it paid
    atomic reference counts on their arrays at every call (1.3-1.6x the time); inlined into
    the kernel's per-axis branches, it was compiled three times (+11 s of cold compile)."""
    # everything a pixel reads, taken out of the bundles once (``_view_pass_group``)
    s_axis, s_idx, s_side = samples.axis, samples.index, samples.side
    frm = (ax.origin[0], ax.origin[1], ax.origin[2], ax.u[0], ax.u[1], ax.u[2], ax.v[0], ax.v[1], ax.v[2],
           ax.w[0], ax.w[1], ax.w[2])
    h, nu = ax.h, ax.nu
    spix, depth, geo, obj_a, diff, offsets = ax.sample_pixel, ax.depth, ax.geo_normal, ax.object, ax.diffuse, ax.offsets
    c = 0
    for q in range(lo, hi):
        r = pix[q]
        if s_axis[r] != axis:
            continue
        if _bilinear_diffuse(r, s_idx[r], s_side[r], _pixel_ray(cam_pix[q], cam), frm, h, nu, spix, depth, geo, obj_a,
                             diff, offsets, radiance):
            c += 1
    return c


@nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _bilinear_diffuse_kernel(pix, cam_pix, samples, cam, ax0, ax1, ax2, radiance):
    """``_bilinear_diffuse`` for every frame row of ``pix`` (camera pixel ``cam_pix``: see
    ``_view_pass_group``) that shows an LDC sample (``samples``); the others keep their
    radiance. Returns how many pixels were interpolated."""
    n = pix.shape[0]
    blocks = (n + 1023) // 1024
    done = np.zeros(blocks, np.int64)
    for blk in nb.prange(blocks):
        lo, hi = blk * 1024, min(n, blk * 1024 + 1024)
        # the axis as a run-time int64 (one compiled block function, not one per literal)
        done[blk] = (_bilinear_diffuse_block(lo, hi, np.int64(0), ax0, pix, cam_pix, samples, cam, radiance) +
                     _bilinear_diffuse_block(lo, hi, np.int64(1), ax1, pix, cam_pix, samples, cam, radiance) +
                     _bilinear_diffuse_block(lo, hi, np.int64(2), ax2, pix, cam_pix, samples, cam, radiance))
    return done.sum()


@nb.njit(cache=True, nogil=True)
def _select_view_pass(obj_id, mat_id, hl_mat, rf_mat, want_hl, want_rf, force):
    """The covered pixels the view pass runs on (row-major) and how many get highlights and
    reflections."""
    n = obj_id.shape[0]
    out = np.empty(n, np.int64)
    m = 0
    n_hl = 0
    n_rf = 0
    for i in range(n):
        if obj_id[i] < 0:
            continue
        mt = mat_id[i]
        hl = want_hl and (force or hl_mat[mt])
        rf = want_rf and (force or rf_mat[mt])
        if hl or rf:
            out[m] = i
            m += 1
            n_hl += hl
            n_rf += rf
    return out[:m], n_hl, n_rf


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _view_pass_group(counter, axis, ax, pix, cam_pix, samples, rc, cam, mesh, sw, hp, gp, out, rays, gs):
    """One parallel group of ``_view_pass_kernel``: the whole view-dependent pass of the camera
    pixels ``pix`` whose sample is on LDC axis ``axis`` (-1: the raycast fill's records), in one
    pass: surface record, refinement onto the sample's triangle, direction to the eye,
    highlights and the light-field gather, added to the image. The threads take blocks of 64
    pixels from ``counter`` (``engine.sched``: mirror and glossy pixels cluster in the image,
    and a core may be busy).

    counter: (1,) int64 this part's block counter, shared by the threads.
    axis: the LDC axis whose pixels this call shades (0, 1, 2), or -1 for the raycast fill's.
    ax: that axis' ``AxisArrays`` (axis -1: any axis', unused).
    pix: (n_pix,) int64 the view pass's pixels: rows of the frame's arrays (row-major).
    cam_pix: (n_pix,) int64 the camera pixel of each (its eye ray, its highlight samples): ``pix``
        itself, or in a compact frame (``LDCViewRenderer._subpixel_frame``) the sub-pixel's.
    samples: ``PixelSamples``, the sample each pixel shows.
    rc: ``RaycastRecords`` of the raycast fill's pixels.
    cam: ``KernelCamera``.
    mesh: ``SurfaceMesh`` for the refinement.
    sw: ``ViewPassSwitches``.
    hp, gp: ``HighlightParams``, ``GatherParams`` (``engine.newviews.view_pass``).
    out: ``ViewPassImage``, added to.
    rays: ``MirrorRays`` written with ``sw.trace`` (row = position in pix).
    gs: ``GlossySurfaces`` written with ``sw.glossy`` (row = position in pix).
    """
    # Everything a pixel reads is taken out of the bundles here, once per thread: inlined helpers
    # given a bundle would unpack it per pixel (``highlight_point_u``).
    ortho, eye, fwd, px_size, ortho_px = cam.ortho, cam.eye, cam.forward, cam.pixel_angle, cam.ortho_pixel
    s_axis, s_idx, s_side = samples.axis, samples.index, samples.side
    spix, depth, geo, nrm, mat_a, prim = ax.sample_pixel, ax.depth, ax.geo_normal, ax.normal, ax.material, ax.prim
    h, nu = ax.h, ax.nu
    hl_mat, rf_mat, gathered_mat = sw.hl_mat, sw.rf_mat, sw.gathered_mat
    want_hl, want_rf, force, mirror, trace, refine = sw.want_hl, sw.want_rf, sw.force, sw.mirror, sw.trace, sw.refine
    glossy = sw.glossy
    gs_p, gs_ng, gs_ns, gs_wo, gs_mat, gs_live = gs.p, gs.ng, gs.ns, gs.wo, gs.mat, gs.live
    rc_row, rc_p, rc_ng, rc_ns, rc_mat = rc.row, rc.p, rc.ng, rc.ns, rc.mat
    radiance, normal, prov, lookups = out.radiance, out.normal, out.prov, out.lookups
    ray_o, ray_d, ray_ng, ray_thr, ray_live = rays.o, rays.d, rays.ng, rays.thr, rays.live
    ks, shin, spec_cut, stream = hp.ks, hp.shininess, hp.spec_cut, hp.stream
    kg, gexp, gloss_cut = hp.kg, hp.gloss_exponent, hp.gloss_cut
    pt_pos, pt_int, dir_dir, dir_irr = hp.point_position, hp.point_intensity, hp.dir_direction, hp.dir_irradiance
    rc_, ru, rv, r_n, r_area = hp.rect_corner, hp.rect_edge_u, hp.rect_edge_v, hp.rect_normal, hp.rect_area
    rL, r2s, r_g, center, extent = hp.rect_radiance, hp.rect_two_sided, hp.rect_grid, hp.center, hp.extent
    kr = gp.kr
    cand, best_c, pt = gather_scratch(gp.directions.shape[0])
    bits = ax.visibility if axis >= 0 else rc.bits
    org_t = (ax.origin[0], ax.origin[1], ax.origin[2])
    fu_t = (ax.u[0], ax.u[1], ax.u[2])
    fv_t = (ax.v[0], ax.v[1], ax.v[2])
    fw_t = (ax.w[0], ax.w[1], ax.w[2])
    n = pix.shape[0]
    nblk = (n + 63) // 64
    while True:
        blk = next_block(counter)
        if blk >= nblk:
            break
        for i in range(blk * 64, min(n, blk * 64 + 64)):
            r = pix[i]
            if s_axis[r] != axis:
                continue
            if axis >= 0:
                s = s_idx[r]
                sd = s_side[r]
                px, py, pz = _sample_point(org_t, fu_t, fv_t, fw_t, h, nu, np.int64(spix[s]), depth[s])
                g0, g1, g2, n0, n1, n2 = _sample_normals(geo[s, 0], geo[s, 1], geo[s, 2], nrm[s, 0], nrm[s, 1],
                                                         nrm[s, 2], sd)
                m = mat_a[s]
                brow = 2 * s + sd
                if refine:
                    ox, oy, oz, dx, dy, dz = _pixel_ray(cam_pix[i], cam)
                    if ortho:
                        reach = ortho_px
                    else:
                        ex, ey, ez = px - ox, py - oy, pz - oz
                        reach = px_size * math.sqrt(ex * ex + ey * ey + ez * ez)
                    lim = 2.0 * (mesh.ldc_h + reach)
                    px, py, pz, n0, n1, n2 = _refine_point(ox, oy, oz, dx, dy, dz, prim[s], mesh, lim, px, py, pz,
                                                           g0, g1, g2, n0, n1, n2)
            else:  # a pixel of the raycast fill
                j = rc_row[r]
                px, py, pz = rc_p[j, 0], rc_p[j, 1], rc_p[j, 2]
                g0, g1, g2 = rc_ng[j, 0], rc_ng[j, 1], rc_ng[j, 2]
                n0, n1, n2 = rc_ns[j, 0], rc_ns[j, 1], rc_ns[j, 2]
                m = rc_mat[j]
                brow = j
            if ortho:
                wo0, wo1, wo2 = -fwd[0], -fwd[1], -fwd[2]
            else:
                wo0, wo1, wo2 = eye[0] - px, eye[1] - py, eye[2] - pz
                ln = math.sqrt(wo0 * wo0 + wo1 * wo1 + wo2 * wo2)
                if not ln > 0.0:
                    ln = 1.0
                wo0 /= ln
                wo1 /= ln
                wo2 /= ln
            normal[r, 0], normal[r, 1], normal[r, 2] = n0, n1, n2
            pt[0], pt[1], pt[2], pt[3], pt[4], pt[5] = px, py, pz, g0, g1, g2
            pt[6], pt[7], pt[8], pt[9], pt[10], pt[11] = n0, n1, n2, wo0, wo1, wo2
            if want_hl and (force or hl_mat[m]):
                h0, h1, h2 = highlight_point_u(cam_pix[i], pt, m, bits, brow, force, ks, shin, spec_cut, kg, gexp,
                                               gloss_cut, pt_pos, pt_int, dir_dir, dir_irr, rc_, ru, rv, r_n, r_area,
                                               rL, r2s, r_g, stream, center, extent)
                radiance[r, 0] += h0
                radiance[r, 1] += h1
                radiance[r, 2] += h2
            if want_rf and (force or rf_mat[m]):
                # gathered_mat: the materials gather_point does anything for (a traced mirror's gather
                # is zero); the call passes ~20 arrays on the stack, so it is skipped where it would
                # return zeros (see _shade_group)
                if force or gathered_mat[m]:
                    f0, f1, f2, u = gather_point(pt, m, mirror, True, force, cand, best_c, gp)
                    radiance[r, 0] += f0
                    radiance[r, 1] += f1
                    radiance[r, 2] += f2
                    lookups[i] = u
                if gathered_mat[m]:
                    prov[r] = 3
                if glossy and (force or kg[m, 0] > 0.0 or kg[m, 1] > 0.0 or kg[m, 2] > 0.0):
                    gs_live[i] = True
                    gs_p[i, 0], gs_p[i, 1], gs_p[i, 2] = px, py, pz
                    gs_ng[i, 0], gs_ng[i, 1], gs_ng[i, 2] = g0, g1, g2
                    gs_ns[i, 0], gs_ns[i, 1], gs_ns[i, 2] = n0, n1, n2
                    gs_wo[i, 0], gs_wo[i, 1], gs_wo[i, 2] = wo0, wo1, wo2
                    gs_mat[i] = m
                if trace:
                    d0, d1, d2 = mirror_direction(n0, n1, n2, wo0, wo1, wo2)
                    live = force or ((kr[m, 0] > 0.0 or kr[m, 1] > 0.0 or kr[m, 2] > 0.0) and
                                     g0 * d0 + g1 * d1 + g2 * d2 > 0.0)
                    ray_live[i] = live
                    if live:
                        ray_o[i, 0], ray_o[i, 1], ray_o[i, 2] = px, py, pz
                        ray_d[i, 0], ray_d[i, 1], ray_d[i, 2] = d0, d1, d2
                        ray_ng[i, 0], ray_ng[i, 1], ray_ng[i, 2] = g0, g1, g2
                        ray_thr[i, 0], ray_thr[i, 1], ray_thr[i, 2] = kr[m, 0], kr[m, 1], kr[m, 2]


@nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _view_pass_kernel(groups, pix, cam_pix, samples, rc, cam, mesh, sw, hp, gp, out, rays, gs, ax0, ax1, ax2):
    """The view-dependent pass of every pixel in ``pix`` in ONE parallel launch: the pixels whose
    sample is on LDC axis 0, 1, 2 (``AxisArrays`` ``ax0``, ``ax1``, ``ax2``) and, when ``rc`` has
    records, those of the raycast fill (axis -1). Each part has its own block counter and a thread
    done with one goes on to the next (the parts are disjoint pixels), so there is one launch and
    one tail instead of one per axis (a numba workqueue launch costs 0.1-0.3 ms here).
    ``groups``: parallel groups (one per numba thread); the other parameters are
    ``_view_pass_group``'s."""
    counters = np.zeros(4, np.int64)
    c_0 = counters[0:1]
    c_1 = counters[1:2]
    c_2 = counters[2:3]
    c_r = counters[3:4]
    with_rc = rc.row.shape[0] > 0
    # the axis as a run-time int64, not a literal: numba would compile the group once per literal value
    # (four copies of the largest LDC kernel, three quarters of its cold compile; docs/performance.md)
    for _ in nb.prange(groups):
        _view_pass_group(c_0, np.int64(0), ax0, pix, cam_pix, samples, rc, cam, mesh, sw, hp, gp, out, rays, gs)
        _view_pass_group(c_1, np.int64(1), ax1, pix, cam_pix, samples, rc, cam, mesh, sw, hp, gp, out, rays, gs)
        _view_pass_group(c_2, np.int64(2), ax2, pix, cam_pix, samples, rc, cam, mesh, sw, hp, gp, out, rays, gs)
        if with_rc:  # the raycast fill's pixels (no LDC sample; axis 0's arrays are placeholders)
            _view_pass_group(c_r, np.int64(-1), ax0, pix, cam_pix, samples, rc, cam, mesh, sw, hp, gp, out, rays, gs)


@nb.njit(cache=True, nogil=True)
def _clear_pixels(pix, bg, radiance, depth, normal, obj_id, mat_id, prov, s_axis, s_idx):
    """Pixels ``pix`` show the background and no sample (before a ray's answer replaces them)."""
    for i in range(pix.shape[0]):
        r = pix[i]
        for c in range(3):
            radiance[r, c] = bg[c]
            normal[r, c] = 0.0
        depth[r] = 0.0
        obj_id[r] = -1
        mat_id[r] = -1
        prov[r] = 0
        s_axis[r] = -1
        s_idx[r] = -1


@nb.njit(cache=True, nogil=True, parallel=True)
def _to_f32_count_nonfinite(radiance, depth, out):
    """out (n, 3) float32 = radiance (n, 3) float64; returns how many radiance or depth values
    are not finite."""
    n = radiance.shape[0]
    nblk = (n + 4095) // 4096
    bad = 0
    for b in nb.prange(nblk):
        for i in range(b * 4096, min(n, b * 4096 + 4096)):
            for c in range(3):
                v = radiance[i, c]
                out[i, c] = v
                if not np.isfinite(v):
                    bad += 1
            if not np.isfinite(depth[i]):
                bad += 1
    return bad


@nb.njit(cache=True, nogil=True, inline="always")
def _pixel_ray(r, cam):
    """The eye ray (o, d) through the centre of flat pixel r of ``cam`` (a ``KernelCamera``;
    ``engine.camera.camera_rays``' arithmetic, operation for operation: the same float64 rays)."""
    ortho, eye, right, up, fwd = cam.ortho, cam.eye, cam.right, cam.up, cam.forward
    W, H, th, aspect, hh = cam.width, cam.height, cam.tan_half_fov, cam.aspect, cam.half_ortho_height
    sx = 2.0 * (r % W + 0.5) / W - 1.0
    sy = 1.0 - 2.0 * (r // W + 0.5) / H
    if ortho:
        a = sx * hh * aspect
        b = sy * hh
        return (eye[0] + a * right[0] + b * up[0], eye[1] + a * right[1] + b * up[1],
                eye[2] + a * right[2] + b * up[2], fwd[0], fwd[1], fwd[2])
    a = sx * th * aspect
    b = sy * th
    dx = fwd[0] + a * right[0] + b * up[0]
    dy = fwd[1] + a * right[1] + b * up[1]
    dz = fwd[2] + a * right[2] + b * up[2]
    ln = math.sqrt(dx * dx + dy * dy + dz * dz)
    return eye[0], eye[1], eye[2], dx / ln, dy / ln, dz / ln


@nb.njit(cache=True, nogil=True, parallel=True)
def _pixel_rays(pix, cam):
    """(o, d), each (n, 3) float64: the eye rays of the flat pixels ``pix`` (``_pixel_ray``)."""
    n = pix.shape[0]
    o = np.empty((n, 3))
    d = np.empty((n, 3))
    for i in nb.prange(n):
        o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2] = _pixel_ray(pix[i], cam)
    return o, d


@nb.njit(cache=True, nogil=True, parallel=True)
def _rays_meet_box(pix, cam, lo, hi):
    """(n,) bool: the eye ray of flat pixel ``pix[i]`` meets the box [lo, hi] at t >= 0 (slab
    test; an axis the ray is parallel to is skipped, like the NaN-ignoring numpy version)."""
    n = pix.shape[0]
    keep = np.empty(n, np.bool_)
    for i in nb.prange(n):
        ox, oy, oz, dx, dy, dz = _pixel_ray(pix[i], cam)
        tn = -np.inf
        tf = np.inf
        for a in range(3):
            oa = ox if a == 0 else (oy if a == 1 else oz)
            da = dx if a == 0 else (dy if a == 1 else dz)
            inv = 1.0 / da if da != 0.0 else math.copysign(np.inf, da)
            t0 = (lo[a] - oa) * inv
            t1 = (hi[a] - oa) * inv
            if t0 != t0 or t1 != t1:
                continue
            tn = max(tn, min(t0, t1))
            tf = min(tf, max(t0, t1))
        keep[i] = tf >= max(tn, 0.0)
    return keep


_RAY_TILE = 16  # mirror rays are traced in 16 x 16 pixel tiles (see _tile_order)
_GLOSSY_STREAM = 23  # sampler stream of the glossy lobe rays: sample_key(seed, _GLOSSY_STREAM)
_GLOSSY_CHUNK_RAYS = 1 << 16  # glossy lobe rays traced at once (~10 MiB of ray and hit arrays)
_GLOSSY_FILTER_DEFAULT = int(GLOSSY_FILTER.default or 0)
_GLOSSY_FILTER_COS = 0.95  # the glossy filter's same-surface tests: normals within ~18 degrees,
_GLOSSY_FILTER_DEPTH = 0.05  # depths within 5 %


@nb.njit(cache=True, nogil=True)
def _tile_order(pix, W, T):
    """The permutation that puts the flat pixels ``pix`` of a W-wide image in T x T tiles, tile
    rows top to bottom, tiles left to right, each tile's pixels in their given order (row-major,
    or a compact frame's: ``_Frame.pixels``): a counting sort. Neighbouring mirror rays then
    traverse the same quadtree nodes and samples one after the other, so the image-based tracer
    finds them in its caches (mirror stage 1.04-1.09x against row-major order, mirror_box
    512x512 LDC 128; each ray's result is independent of the order). The view pass itself stays
    row-major (measured slightly faster)."""
    n = pix.shape[0]
    tw = (W + T - 1) // T
    key = np.empty(n, np.int64)
    kmax = 0
    for i in range(n):
        k = (pix[i] // W // T) * tw + (pix[i] % W) // T
        key[i] = k
        kmax = max(kmax, k)
    start = np.zeros(kmax + 2, np.int64)
    for i in range(n):
        start[key[i] + 1] += 1
    for k in range(kmax + 1):
        start[k + 1] += start[k]
    out = np.empty(n, np.int64)
    for i in range(n):
        k = key[i]
        out[start[k]] = i
        start[k] += 1
    return out


@nb.njit(cache=True, nogil=True, parallel=True)
def _near_covered(covered, r):
    """(H, W) bool: a covered pixel within the (2r+1) x (2r+1) square around each pixel (a
    binary dilation; outside the image counts as uncovered)."""
    H, W = covered.shape
    row = np.zeros((H, W), np.bool_)
    for y in nb.prange(H):
        c = 0  # covered pixels in row y's window [x - r, x + r]
        for x in range(min(r, W)):
            c += covered[y, x]
        for x in range(W):
            if x + r < W:
                c += covered[y, x + r]
            if x - r - 1 >= 0:
                c -= covered[y, x - r - 1]
            row[y, x] = c > 0
    out = np.zeros((H, W), np.bool_)
    for y in nb.prange(H):
        for yy in range(max(0, y - r), min(H, y + r + 1)):
            for x in range(W):
                out[y, x] |= row[yy, x]
    return out


@nb.njit(cache=True, nogil=True, parallel=True)
def _silhouette_pixels(obj_id, depth, side, is_hole, h, w, rel_jump):
    """Covered pixels (row-major, not already holes) at a visibility edge of the warped image: a
    4-neighbour shows another object or nothing, the same object at a depth more than
    ``rel_jump`` (relative) away (a fold: a handle over the body), or the other side of a sheet
    (``side``: the inside of a rim next to its outside). There the splats' footprints, not the
    pixel centre, decided what the pixel shows."""
    flag = np.zeros(h * w, np.bool_)
    for y in nb.prange(h):
        for x in range(w):
            i = y * w + x
            o = obj_id[i]
            if o < 0 or is_hole[i]:
                continue
            lim = rel_jump * depth[i]
            edge = False
            for k in range(4):
                if k == 0:
                    if x == 0:
                        continue
                    j = i - 1
                elif k == 1:
                    if x == w - 1:
                        continue
                    j = i + 1
                elif k == 2:
                    if y == 0:
                        continue
                    j = i - w
                else:
                    if y == h - 1:
                        continue
                    j = i + w
                if obj_id[j] != o or abs(depth[j] - depth[i]) > lim or side[j] != side[i]:
                    edge = True
                    break
            flag[i] = edge
    return np.flatnonzero(flag)


@nb.njit(cache=True, nogil=True)
def _mean_luminance(radiance, obj_id, bg):
    """The mean Rec.709 luminance of the covered pixels of ``radiance`` (h, w, 3) float32 (of
    the background when none is covered)."""
    H, W = obj_id.shape
    acc = 0.0
    n = 0
    for y in range(H):
        for x in range(W):
            if obj_id[y, x] >= 0:
                acc += 0.2126 * radiance[y, x, 0] + 0.7152 * radiance[y, x, 1] + 0.0722 * radiance[y, x, 2]
                n += 1
    if n == 0:
        return 0.2126 * bg[0] + 0.7152 * bg[1] + 0.0722 * bg[2]
    return acc / n


@nb.njit(cache=True, nogil=True, parallel=True)
def _edge_pixels(obj_id, depth, radiance, rel_jump, contrast, y_mean):
    """(h w,) bool: the pixels of a one-sample image at an edge, the ones ``antialias="edges"``
    supersamples: a pixel of its 3 x 3 neighbourhood shows another object (or nothing), the
    same object at a depth more than ``rel_jump`` (relative) away, or a luminance differing by
    more than ``contrast`` x max(the two luminances, ``y_mean``) (a shadow's edge, a highlight's,
    a texture's; below ``y_mean`` the step is measured against the image's mean luminance, as
    the LRMS measures errors)."""
    H, W = obj_id.shape
    lum = np.empty((H, W))
    for y in nb.prange(H):
        for x in range(W):
            lum[y, x] = 0.2126 * radiance[y, x, 0] + 0.7152 * radiance[y, x, 1] + 0.0722 * radiance[y, x, 2]
    flag = np.zeros(H * W, np.bool_)
    for y in nb.prange(H):
        for x in range(W):
            o = obj_id[y, x]
            d = depth[y, x]
            yl = lum[y, x]
            edge = False
            for yy in range(max(0, y - 1), min(H, y + 2)):
                for xx in range(max(0, x - 1), min(W, x + 2)):
                    if obj_id[yy, xx] != o:
                        edge = True
                    elif o >= 0 and abs(depth[yy, xx] - d) > rel_jump * min(d, depth[yy, xx]):
                        edge = True
                    else:
                        yn = lum[yy, xx]
                        if abs(yn - yl) > contrast * max(yn, yl, y_mean):
                            edge = True
                    if edge:
                        break
                if edge:
                    break
            flag[y * W + x] = edge
    return flag


@nb.njit(cache=True, nogil=True, parallel=True, error_model="numpy")
def _subpixel_samples(pix, n_sub, o, d, s_axis, s_idx, W, H, ax0, ax1, ax2, tri_p, tri_ng, tri_obj, nbr, tol, face_cos):
    """The LDC sample each sub-pixel ray shows (rays o, d: rows i n_sub .. (i + 1) n_sub - 1 are
    the sub-pixels of flat pixel ``pix[i]`` of the W x H one-sample image), from the samples of
    that pixel's 3 x 3 neighbourhood (``s_axis``, ``s_idx``: the one-sample render's, after its
    fill): each one's triangle is walked along the ray (``locate_on_mesh``, as in the
    silhouette mesh test); the nearest crossing decides the surface, and of the candidates on
    that surface (the same object, crossed within ``tol``) the one whose sample point lies
    nearest the crossing gives the radiance (the sample whose splat a finer warp would most
    likely show there: across a shadow's edge the sub-pixels pick different samples),
    preferring the samples whose geometric normal is within ``face_cos`` of the crossed
    triangle's (the same face: at a box's edge the nearest sample may lie on the other face,
    lit differently). The candidates, their points and normals are gathered once per pixel,
    each distinct triangle walked once per sub-pixel. Returns (axis (n,) int8, -1 where the ray
    crosses no candidate; sample (n,) int64; t (n,) float64)."""
    n = o.shape[0]
    out_a = np.full(n, -1, np.int8)
    out_s = np.full(n, -1, np.int64)
    out_t = np.full(n, np.inf)
    n_pix = pix.shape[0]
    nblk = (n_pix + 3) // 4
    for b in nb.prange(nblk):
        ca = np.empty(9, np.int64)  # candidate k: its axis (-1: none), sample, object, point, normal
        cs = np.empty(9, np.int64)
        cu = np.empty(9, np.int64)  # the candidate's triangle, as an index into ut
        cq = np.empty((9, 3))
        cg = np.empty((9, 3))
        ut = np.empty(9, np.int64)  # the distinct triangles
        uok = np.empty(9, np.bool_)  # per distinct triangle, this sub-pixel's walk: crossed, where, at t
        ut2 = np.empty(9, np.int64)
        us2 = np.empty(9)
        ct = np.empty(9)
        co = np.empty(9, np.int64)
        good = np.empty(9, np.bool_)
        for p in range(b * 4, min(n_pix, b * 4 + 4)):
            r = pix[p]
            x = r % W
            y = r // W
            nu = 0
            for k in range(9):
                ca[k] = -1
                xx = x + k % 3 - 1
                yy = y + k // 3 - 1
                if xx < 0 or yy < 0 or xx >= W or yy >= H:
                    continue
                j = yy * W + xx
                a = s_axis[j]
                sm = s_idx[j]
                if a < 0:
                    continue
                # one branch per axis, not ``ax = ax0 if ... else ...``: selecting the bundle pays
                # reference counts on its arrays (placing the sub-pixels measured 1.2x slower)
                if a == 0:
                    t = ax0.prim[sm]
                    qx, qy, qz = _axis_sample_point(ax0, sm)
                    g0, g1, g2 = ax0.geo_normal[sm, 0], ax0.geo_normal[sm, 1], ax0.geo_normal[sm, 2]
                elif a == 1:
                    t = ax1.prim[sm]
                    qx, qy, qz = _axis_sample_point(ax1, sm)
                    g0, g1, g2 = ax1.geo_normal[sm, 0], ax1.geo_normal[sm, 1], ax1.geo_normal[sm, 2]
                else:
                    t = ax2.prim[sm]
                    qx, qy, qz = _axis_sample_point(ax2, sm)
                    g0, g1, g2 = ax2.geo_normal[sm, 0], ax2.geo_normal[sm, 1], ax2.geo_normal[sm, 2]
                ca[k] = a
                cs[k] = sm
                cq[k, 0], cq[k, 1], cq[k, 2] = qx, qy, qz
                cg[k, 0], cg[k, 1], cg[k, 2] = g0, g1, g2
                u = -1
                for q in range(nu):
                    if ut[q] == t:
                        u = q
                        break
                if u < 0:
                    u = nu
                    ut[nu] = t
                    nu += 1
                cu[k] = u
            for i in range(p * n_sub, (p + 1) * n_sub):
                ox, oy, oz, dx, dy, dz = o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2]
                for u in range(nu):
                    ok, t2, s2, bw, bu, bv = locate_on_mesh(ox, oy, oz, dx, dy, dz, ut[u], tri_p, tri_ng, nbr, 8)
                    uok[u] = ok and min(bw, min(bu, bv)) >= -1e-6 and s2 > 0.0
                    ut2[u] = t2
                    us2[u] = s2
                best_t = np.inf
                best_o = -1
                for k in range(9):
                    good[k] = ca[k] >= 0 and uok[cu[k]]
                    if good[k]:
                        ct[k] = us2[cu[k]]
                        co[k] = tri_obj[ut2[cu[k]]]
                        if ct[k] < best_t:
                            best_t = ct[k]
                            best_o = co[k]
                if best_t == np.inf:
                    continue
                tb = -1
                for k in range(9):
                    if good[k] and ct[k] == best_t:
                        tb = ut2[cu[k]]
                        break
                px, py, pz = ox + best_t * dx, oy + best_t * dy, oz + best_t * dz
                pick = -1
                for same_face in (True, False):
                    best_d = np.inf
                    for k in range(9):
                        if not good[k] or co[k] != best_o or ct[k] > best_t + tol:
                            continue
                        if same_face and abs(cg[k, 0] * tri_ng[tb, 0] + cg[k, 1] * tri_ng[tb, 1] +
                                             cg[k, 2] * tri_ng[tb, 2]) < face_cos:
                            continue
                        dd = (cq[k, 0] - px) ** 2 + (cq[k, 1] - py) ** 2 + (cq[k, 2] - pz) ** 2
                        if dd < best_d:
                            best_d = dd
                            pick = k
                    if pick >= 0:
                        break
                out_a[i] = ca[pick]
                out_s[i] = cs[pick]
                out_t[i] = best_t
    return out_a, out_s, out_t


@nb.njit(cache=True, nogil=True, inline="always")
def _axis_sample_point(ax, s):
    """The point of sample ``s`` of LDC axis ``ax`` (``AxisArrays``; ``_sample_point``)."""
    return _sample_point((ax.origin[0], ax.origin[1], ax.origin[2]), (ax.u[0], ax.u[1], ax.u[2]),
                         (ax.v[0], ax.v[1], ax.v[2]), (ax.w[0], ax.w[1], ax.w[2]), ax.h, ax.nu,
                         np.int64(ax.sample_pixel[s]), ax.depth[s])


@nb.njit(cache=True, nogil=True, parallel=True)
def _fill_subpixels(hit_axis, hit_sample, hit_t, d, bg, ax0, ax1, ax2, radiance, depth, normal, obj_id, mat_id, prov,
                    s_axis, s_idx, s_side):
    """Row i of a compact frame of sub-pixels (``_subpixel_frame``) shows its hit sample as
    ``_fill_from_hits`` shows a hole's (the sample's diffuse radiance, distance, shading normal,
    ids; provenance 2), or the background as ``_clear_pixels`` leaves a pixel (``hit_axis``
    -1); one parallel pass over the three axes."""
    for r in nb.prange(hit_axis.shape[0]):
        a = hit_axis[r]
        if a < 0:
            for c in range(3):
                radiance[r, c] = bg[c]
                normal[r, c] = 0.0
            depth[r] = 0.0
            obj_id[r] = -1
            mat_id[r] = -1
            prov[r] = 0
            s_axis[r] = -1
            s_idx[r] = -1
            s_side[r] = 0
            continue
        ax = ax0 if a == 0 else (ax1 if a == 1 else ax2)
        geo, nrm, diff = ax.geo_normal, ax.normal, ax.diffuse
        sm = hit_sample[r]
        sd = 1 if geo[sm, 0] * d[r, 0] + geo[sm, 1] * d[r, 1] + geo[sm, 2] * d[r, 2] > 0.0 else 0
        _, _, _, n0, n1, n2 = _sample_normals(geo[sm, 0], geo[sm, 1], geo[sm, 2], nrm[sm, 0], nrm[sm, 1], nrm[sm, 2],
                                              sd)
        radiance[r, 0], radiance[r, 1], radiance[r, 2] = diff[sm, sd, 0], diff[sm, sd, 1], diff[sm, sd, 2]
        depth[r] = hit_t[r]
        normal[r, 0], normal[r, 1], normal[r, 2] = n0, n1, n2
        obj_id[r] = ax.object[sm]
        mat_id[r] = ax.material[sm]
        prov[r] = 2
        s_axis[r] = a
        s_idx[r] = sm
        s_side[r] = sd


@nb.njit(cache=True, nogil=True, parallel=True)
def _box_filter_pixels(pix, fine, n_sub, out):
    """out[pix[i]] (float32) = the mean of rows i n_sub .. (i + 1) n_sub - 1 of ``fine`` (n, 3)
    float64: pixel ``pix[i]``'s sub-pixels in a compact frame (``_subpixel_frame``), each
    rounded to float32 first (uniform supersampling's arithmetic: the float32 image of the fine
    frame, averaged in float64). Returns how many sub-pixel values are not finite."""
    n = pix.shape[0]
    bad = 0
    for i in nb.prange(n):
        p = pix[i]
        for c in range(3):
            acc = 0.0
            for k in range(i * n_sub, (i + 1) * n_sub):
                v = fine[k, c]
                if not np.isfinite(v):
                    bad += 1
                acc += np.float64(np.float32(v))
            out[p, c] = acc / n_sub
    return bad


@nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _silhouette_mesh_test(pix, o, d, h_axis, h_sample, h_t, s_axis, s_idx, W, H, prim0, prim1, prim2, tri_p, tri_ng,
                          tri_obj, nbr, tol):
    """Silhouette pixels ``pix`` (eye rays o, d; image-based hits h_*, updated in place): the
    candidates are the warp's winners of the 3x3 neighbourhood (one side of a silhouette shows
    the surface the other side's splats overreached) and the ray's own hit where one is given
    (h_axis >= 0; the renderer runs this test BEFORE tracing: only the pixels it leaves at -1
    take an image-based ray). Each candidate's
    triangle is walked along the ray (``locate_on_mesh``); the nearest crossing - the ray
    really crosses that mesh there - decides the surface, at the crossing's distance. Of the
    candidates on that surface (the same object, crossed within ``tol`` of it) the sample that gives the
    radiance is the pixel's own warp winner if it is one, else the ray's hit, else the first
    (the nearer a sample is to the pixel, the less its baked shading, shadow edges included,
    differs from the pixel's). Where no candidate is crossed the image-based answer stays.
    Returns how many pixels took a mesh-tested hit."""
    n = pix.shape[0]
    nblk = (n + 63) // 64
    acc = np.zeros(nblk, np.int64)
    for b in nb.prange(nblk):  # blocks of 64 pixels: the scratch is allocated once per block
        acc[b] = _silhouette_mesh_block(b * 64, min(n, b * 64 + 64), pix, o, d, h_axis, h_sample, h_t, s_axis, s_idx,
                                        W, H, prim0, prim1, prim2, tri_p, tri_ng, tri_obj, nbr, tol)
    return acc.sum()


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _silhouette_mesh_block(i0, i1, pix, o, d, h_axis, h_sample, h_t, s_axis, s_idx, W, H, prim0, prim1, prim2, tri_p,
                           tri_ng, tri_obj, nbr, tol):
    """Pixels i0 <= i < i1 of ``_silhouette_mesh_test``; returns how many took a mesh-tested hit."""
    ca = np.empty(10, np.int64)
    cs = np.empty(10, np.int64)
    ct = np.empty(10)
    co = np.empty(10, np.int64)
    wt = np.empty(10, np.int64)  # per candidate: start triangle of its walk (-1: none), the walk's result
    wok = np.empty(10, np.bool_)
    wt2 = np.empty(10, np.int64)
    ws2 = np.empty(10)
    n_acc = 0
    for i in range(i0, i1):
        r = pix[i]
        x = r % W
        y = r // W
        ct[:] = np.inf
        best_t = np.inf
        best_o = -1
        for k in range(10):
            ca[k] = -1
            wt[k] = -1
            if k == 9:
                a = h_axis[i]
                sm = h_sample[i]
            else:
                xx = x + k % 3 - 1
                yy = y + k // 3 - 1
                if xx < 0 or yy < 0 or xx >= W or yy >= H:
                    continue
                j = yy * W + xx
                a = s_axis[j]
                sm = s_idx[j]
            if a < 0:
                continue
            t = prim0[sm] if a == 0 else (prim1[sm] if a == 1 else prim2[sm])
            # the walk is a function of (ray, start triangle): neighbours splatted from one sample or
            # triangle (most of the 3x3 at LDC resolutions below the image's) share its result
            kk = -1
            for q in range(k):
                if wt[q] == t:
                    kk = q
                    break
            if kk >= 0:
                good = wok[kk]
                t2 = wt2[kk]
                s2 = ws2[kk]
            else:
                ok, t2, s2, bw, bu, bv = locate_on_mesh(o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2], t, tri_p,
                                                        tri_ng, nbr, 8)
                good = ok and min(bw, min(bu, bv)) >= -1e-6 and s2 > 0.0
            wt[k] = t
            wok[k] = good
            wt2[k] = t2
            ws2[k] = s2
            if good:
                ca[k] = a
                cs[k] = sm
                ct[k] = s2
                co[k] = tri_obj[t2]
                if s2 < best_t:
                    best_t = s2
                    best_o = co[k]
        if best_t == np.inf:
            continue
        pick = -1
        for k in (4, 9, 0, 1, 2, 3, 5, 6, 7, 8):  # own winner, the ray's hit, the neighbours
            if ca[k] >= 0 and co[k] == best_o and ct[k] <= best_t + tol:
                pick = k
                break
        h_axis[i] = ca[pick]
        h_sample[i] = cs[pick]
        h_t[i] = best_t
        n_acc += 1
    return n_acc


@nb.njit(cache=True, nogil=True)
def _fill_from_hits(axis, holes, hit_axis, hit_sample, hit_t, d, geo, nrm, mat_a, obj_a, diff, radiance, depth,
                    normal, obj_id, mat_id, prov, s_axis, s_idx, s_side):
    """Hole pixels whose eye ray hit LDC axis ``axis`` show the hit sample's diffuse radiance,
    distance, shading normal and ids (provenance 2). Serial: a few thousand pixels take less
    than a parallel launch costs (0.1-0.3 ms with numba's workqueue layer here)."""
    for i in range(holes.shape[0]):
        if hit_axis[i] != axis:
            continue
        r = holes[i]
        s = hit_sample[i]
        sd = 1 if geo[s, 0] * d[i, 0] + geo[s, 1] * d[i, 1] + geo[s, 2] * d[i, 2] > 0.0 else 0
        _, _, _, n0, n1, n2 = _sample_normals(geo[s, 0], geo[s, 1], geo[s, 2], nrm[s, 0], nrm[s, 1], nrm[s, 2], sd)
        radiance[r, 0], radiance[r, 1], radiance[r, 2] = diff[s, sd, 0], diff[s, sd, 1], diff[s, sd, 2]
        depth[r] = hit_t[i]
        normal[r, 0], normal[r, 1], normal[r, 2] = n0, n1, n2
        obj_id[r] = obj_a[s]
        mat_id[r] = mat_a[s]
        prov[r] = 2
        s_axis[r] = axis
        s_idx[r] = s
        s_side[r] = sd


@nb.njit(cache=True, nogil=True, error_model="numpy")
def _shade_group(counter, axis, ax, hits, rays, gen, hp, gp, mesh, acc, lookups, nxt):
    """One parallel group of ``_shade_hits``, one axis: the rays that hit LDC axis ``axis`` (or, with
    axis -1, missed everything). With edge neighbours in ``mesh`` each hit is refined like a
    camera pixel: onto the triangle the ray crosses, with its interpolated normal.

    counter: (1,) int64 this part's block counter, shared by the threads.
    axis: the LDC axis whose hits this call shades (0, 1, 2), or -1 for the misses.
    ax: that axis' ``AxisArrays`` (axis -1: any axis', unused).
    hits: ``RayHits`` of ``rays``.
    rays: ``TracedRays``, this generation's.
    gen: ``Generation``.
    hp, gp: ``HighlightParams``, ``GatherParams`` (``engine.newviews.view_pass``).
    mesh: ``SurfaceMesh`` for the refinement.
    acc: (n_owners, 3) float64 radiance accumulated per owner.
    lookups: (n,) int64 LLF lookups per ray.
    nxt: ``MirrorRays``, the next generation's rays (row = this ray's; ``live``: it continues).
    """
    # taken out of the bundles once per thread (see ``_view_pass_group``)
    hit_axis, hit_sample, hit_t = hits.axis, hits.sample, hits.t
    o, d, owner, thr = rays.o, rays.d, rays.owner, rays.thr
    geo, nrm, mat_a, diff, vis2, prim = ax.geo_normal, ax.normal, ax.material, ax.diffuse, ax.visibility, ax.prim
    last, has_llf, gather_mat, force, bg = gen.last, gen.has_llf, gen.gather_mat, gen.force, gen.background
    emitters = gen.emitters
    cont, n_o, n_d, n_ng, n_thr = nxt.live, nxt.o, nxt.d, nxt.ng, nxt.thr
    refine = mesh.neighbours.shape[0] > 0
    max_move = 3.0 * mesh.ldc_h
    ks, shin, spec_cut, stream = hp.ks, hp.shininess, hp.spec_cut, hp.stream
    kg, gexp, gloss_cut = hp.kg, hp.gloss_exponent, hp.gloss_cut
    pt_pos, pt_int, dir_dir, dir_irr = hp.point_position, hp.point_intensity, hp.dir_direction, hp.dir_irradiance
    rc, ru, rv, r_n, r_area = hp.rect_corner, hp.rect_edge_u, hp.rect_edge_v, hp.rect_normal, hp.rect_area
    rL, r2s, r_g, center, extent = hp.rect_radiance, hp.rect_two_sided, hp.rect_grid, hp.center, hp.extent
    kr = gp.kr
    cand, best_c, pt = gather_scratch(gp.directions.shape[0])
    n = o.shape[0]
    nblk = (n + 63) // 64
    while True:
        blk = next_block(counter)
        if blk >= nblk:
            break
        for i in range(blk * 64, min(n, blk * 64 + 64)):
            if hit_axis[i] != axis:
                continue
            q = owner[i]
            if emitters:  # the nearest rect light in front of the LDC's hit (or of nothing) is what the ray sees
                tl = np.inf
                lq = -1
                for j in range(r_area.shape[0]):
                    tj = _rect_light_t(o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2], rc[j, 0], rc[j, 1],
                                       rc[j, 2], ru[j, 0], ru[j, 1], ru[j, 2], rv[j, 0], rv[j, 1], rv[j, 2], r_n[j, 0],
                                       r_n[j, 1], r_n[j, 2], r_area[j], r2s[j])
                    if tj < tl:
                        tl = tj
                        lq = j
                if lq >= 0 and (axis < 0 or tl < hit_t[i]):
                    for c in range(3):
                        acc[q, c] += thr[i, c] * rL[lq, c]
                    continue
            if axis < 0:
                for c in range(3):
                    acc[q, c] += thr[i, c] * bg[c]
                continue
            s = hit_sample[i]
            d0, d1, d2 = d[i, 0], d[i, 1], d[i, 2]
            t = hit_t[i]
            px, py, pz = o[i, 0] + t * d0, o[i, 1] + t * d1, o[i, 2] + t * d2
            sd = 1 if geo[s, 0] * d0 + geo[s, 1] * d1 + geo[s, 2] * d2 > 0.0 else 0
            g0, g1, g2, n0, n1, n2 = _sample_normals(geo[s, 0], geo[s, 1], geo[s, 2], nrm[s, 0], nrm[s, 1], nrm[s, 2],
                                                     sd)
            if refine:
                px, py, pz, n0, n1, n2 = _refine_point(o[i, 0], o[i, 1], o[i, 2], d0, d1, d2, prim[s], mesh, max_move,
                                                       px, py, pz, g0, g1, g2, n0, n1, n2)
            m = mat_a[s]
            wo0, wo1, wo2 = -d0, -d1, -d2
            pt[0], pt[1], pt[2], pt[3], pt[4], pt[5] = px, py, pz, g0, g1, g2
            pt[6], pt[7], pt[8], pt[9], pt[10], pt[11] = n0, n1, n2, wo0, wo1, wo2
            h0, h1, h2 = highlight_point_u(i, pt, m, vis2, 2 * s + sd, force, ks, shin, spec_cut, kg, gexp, gloss_cut,
                                           pt_pos, pt_int, dir_dir, dir_irr, rc, ru, rv, r_n, r_area, rL, r2s, r_g,
                                           stream, center, extent)
            l0 = diff[s, sd, 0] + h0
            l1 = diff[s, sd, 1] + h1
            l2 = diff[s, sd, 2] + h2
            # gather_mat: the materials gather_point does anything for in this generation (glossy; mirrors
            # on the last, the cone's, generation): the call is not inlined and passes ~20 arrays on the
            # stack (~160 pushes), 57 % of this kernel's samples on mirror_box when it ran for every hit
            if has_llf and (force or gather_mat[m]):
                f0, f1, f2, u = gather_point(pt, m, last, True, force, cand, best_c, gp)
                l0 += f0
                l1 += f1
                l2 += f2
                lookups[i] = u
            acc[q, 0] += thr[i, 0] * l0
            acc[q, 1] += thr[i, 1] * l1
            acc[q, 2] += thr[i, 2] * l2
            if last:
                continue
            e0, e1, e2 = mirror_direction(n0, n1, n2, wo0, wo1, wo2)
            go = force or ((kr[m, 0] > 0.0 or kr[m, 1] > 0.0 or kr[m, 2] > 0.0) and g0 * e0 + g1 * e1 + g2 * e2 > 0.0)
            cont[i] = go
            if go:
                n_o[i, 0], n_o[i, 1], n_o[i, 2] = px, py, pz
                n_d[i, 0], n_d[i, 1], n_d[i, 2] = e0, e1, e2
                n_ng[i, 0], n_ng[i, 1], n_ng[i, 2] = g0, g1, g2
                for c3 in range(3):
                    n_thr[i, c3] = thr[i, c3] * kr[m, c3]


@nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _shade_hits(groups, hits, rays, gen, hp, gp, mesh, acc, lookups, nxt, ax0, ax1, ax2):
    """One generation of traced mirror rays (``_shade_group``'s parameters): at each hit the
    sample's diffuse radiance + its highlights toward the ray + its glossy gather (+ the mirror
    cone on the ``last`` generation) times the ray's throughput into ``acc[owner]``; a miss adds
    the background; with ``gen.emitters`` a rect light nearer than the hit adds its radiance
    instead (and the ray ends). Hits on mirrors continue (``nxt``: the next generation's rays). The misses
    (axis -1) and the hits on each LDC axis (``AxisArrays`` ``ax0``, ``ax1``, ``ax2``) in ONE
    call: each Python -> numba call pays ~150 us of argument typing for bundles this size, and
    one call per axis was ~1 % of a render. Each axis has its own block counter; a thread done
    with one axis goes on to the next (the axes' rays are disjoint). ``groups``: parallel groups
    (one per numba thread)."""
    counters = np.zeros(4, np.int64)
    c_m = counters[0:1]
    c_0 = counters[1:2]
    c_1 = counters[2:3]
    c_2 = counters[3:4]
    for _ in nb.prange(groups):
        # run-time axes: one compilation of the group, not one per literal (see _view_pass_kernel)
        _shade_group(c_m, np.int64(-1), ax0, hits, rays, gen, hp, gp, mesh, acc, lookups, nxt)
        _shade_group(c_0, np.int64(0), ax0, hits, rays, gen, hp, gp, mesh, acc, lookups, nxt)
        _shade_group(c_1, np.int64(1), ax1, hits, rays, gen, hp, gp, mesh, acc, lookups, nxt)
        _shade_group(c_2, np.int64(2), ax2, hits, rays, gen, hp, gp, mesh, acc, lookups, nxt)


@nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _glossy_lobe_rays(rows, gs, cam_pix, kg, gexp, n_rays, key, o, d, ng, thr, live):
    """``n_rays`` rays per glossy surface ``gs`` row in ``rows`` (ray ``j n_rays + k`` of row
    ``rows[j]``): directions from the cos^g lobe around the mirror direction of ``gs.wo`` about
    ``gs.ns`` (the reference renderer's lobe sampling: ``engine.path_vertex._lobe_direction``), the
    2-D points ``sample_2d(key, cam_pix[row], k)`` (one stratified set per pixel), throughput
    ``kg (g + 2) / (g + 1) cos_i / n_rays``: the reference's glossy estimator, averaged. A
    direction below the shading or the geometric surface gets throughput 0 and ``live`` False."""
    p, gng, ns, wo, mat = gs.p, gs.ng, gs.ns, gs.wo, gs.mat
    for j in nb.prange(rows.shape[0]):
        i = rows[j]
        m = mat[i]
        n0, n1, n2 = ns[i, 0], ns[i, 1], ns[i, 2]
        e0, e1, e2 = mirror_direction(n0, n1, n2, wo[i, 0], wo[i, 1], wo[i, 2])
        ge = gexp[m]
        for k in range(n_rays):
            r = j * n_rays + k
            u0, u1 = sample_2d(key, cam_pix[i], k)
            cos_a = math.exp(math.log(max(u0, 1e-300)) / (ge + 1.0))
            x0, x1, x2 = _lobe_dir(e0, e1, e2, cos_a, 2.0 * math.pi * u1)
            lx = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
            x0 /= lx
            x1 /= lx
            x2 /= lx
            cos_i = n0 * x0 + n1 * x1 + n2 * x2
            up = gng[i, 0] * x0 + gng[i, 1] * x1 + gng[i, 2] * x2
            f = (ge + 2.0) / (ge + 1.0) * cos_i / n_rays if (cos_i > 0.0 and up > 0.0) else 0.0
            o[r, 0], o[r, 1], o[r, 2] = p[i, 0], p[i, 1], p[i, 2]
            d[r, 0], d[r, 1], d[r, 2] = x0, x1, x2
            ng[r, 0], ng[r, 1], ng[r, 2] = gng[i, 0], gng[i, 1], gng[i, 2]
            for c3 in range(3):
                thr[r, c3] = kg[m, c3] * f
            live[r] = thr[r, 0] > 0.0 or thr[r, 1] > 0.0 or thr[r, 2] > 0.0


@nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def _filter_glossy(has, term, normal, depth, mat, w, h, radius, min_cos, rel_depth, out):
    """The traced glossy term of each pixel that has one (``has``), averaged over the pixels within
    ``radius`` (a square window) that have one too and lie on the same surface: the same material,
    shading normals within ``min_cos``, depths within ``rel_depth`` of the pixel's. A glossy lobe's
    reflection changes slowly across a surface next to the noise of a few rays per pixel (module
    docstring of ``_mirrors``); the surface tests keep the filter off other objects and creases."""
    for y in nb.prange(h):
        for x in range(w):
            i = y * w + x
            if not has[i]:
                continue
            s0 = s1 = s2 = 0.0
            cnt = 0
            m = mat[i]
            n0, n1, n2 = normal[i, 0], normal[i, 1], normal[i, 2]
            di = depth[i]
            for yy in range(max(0, y - radius), min(h, y + radius + 1)):
                for xx in range(max(0, x - radius), min(w, x + radius + 1)):
                    j = yy * w + xx
                    if not has[j] or mat[j] != m:
                        continue
                    if n0 * normal[j, 0] + n1 * normal[j, 1] + n2 * normal[j, 2] < min_cos:
                        continue
                    if abs(depth[j] - di) > rel_depth * di:
                        continue
                    s0 += term[j, 0]
                    s1 += term[j, 1]
                    s2 += term[j, 2]
                    cnt += 1
            if cnt == 0:  # a degenerate normal fails even its own test: the pixel's term unfiltered
                out[i, 0], out[i, 1], out[i, 2] = term[i, 0], term[i, 1], term[i, 2]
            else:
                out[i, 0], out[i, 1], out[i, 2] = s0 / cnt, s1 / cnt, s2 / cnt


class _Glossy(NamedTuple):
    """How a render traces glossy lobes: rays per pixel (0: gathered), the filter's radius and why."""

    rays: int
    filter: int
    why: str


def _ldc_axes(ldc: LDC) -> tuple[AxisArrays, AxisArrays, AxisArrays]:
    """Per LDC axis the arrays the fused kernels take (``AxisArrays``)."""
    out = []
    c = np.ascontiguousarray
    for ax in ldc.axes:
        f = ax.ldi.frame
        vis = c(ax.visibility, dtype=np.uint64)
        out.append(AxisArrays(c(f.origin, np.float64), c(f.u, np.float64), c(f.v, np.float64), c(f.w, np.float64),
                              float(f.h), int(f.nu), ax.ldi.sample_pixels().astype(np.int32),
                              c(ax.ldi.depth, np.float64), c(ax.geo_normal, np.float32), c(ax.normal, np.float32),
                              c(ax.material, np.int32), c(ax.object, np.int32), c(ax.diffuse, np.float32),
                              vis.reshape(vis.shape[0] * 2, vis.shape[2]), c(ax.ldi.prim, np.int32),
                              c(ax.ldi.offsets, np.int64)))
    return out[0], out[1], out[2]


def _no_gather_params(scene: RuntimeScene) -> GatherParams:
    """``gather_params`` of an empty light field (typed like a real one; never gathered from)."""
    mt = scene.materials
    z3 = np.zeros((0, 3))
    return GatherParams(mt.kr, mt.kg, mt.gloss_exponent, n_c=1.0, cone_directions=3, f=1,
                        table=np.full((3, 3, 2), -1, np.int64), directions=z3, pk_offsets=np.zeros(1, np.int64),
                        pk_depth=np.zeros(0), pk_radiance=np.zeros((0, 3), np.float32), pk_origin=z3, pk_u=z3,
                        pk_v=z3, pk_w=z3, pk_h=np.zeros(0), resolution=1,
                        background=np.asarray(scene.background, np.float64).reshape(3),
                        cone_offsets=np.zeros(10, np.int64), cone_index=np.zeros(0, np.int64),
                        cone_xyz=np.zeros((3, 0)))


def _no_raycast_records(visibility_words: int) -> RaycastRecords:
    """``RaycastRecords`` of no pixels (typed like real ones)."""
    z3 = np.zeros((0, 3))
    return RaycastRecords(np.zeros(0, np.int64), z3, z3, z3, np.zeros(0, np.int32),
                          np.zeros((0, visibility_words), np.uint64))


@dataclass
class _Frame:
    """One render in progress: the camera, the warp's images as flat views (this render's own,
    updated in place by the later stages: row = flat pixel y * w + x) and the bookkeeping the
    result reports."""

    camera: CameraParams
    cam: KernelCamera  #: the camera as the kernels take it (one basis per render)
    warp: WarpResult
    radiance: np.ndarray  #: (h w, 3) float64
    depth: np.ndarray  #: (h w,) float32
    normal: np.ndarray  #: (h w, 3) float32
    obj_id: np.ndarray  #: (h w,) int32
    mat_id: np.ndarray  #: (h w,) int32
    prov: np.ndarray  #: (h w,) uint8
    samples: PixelSamples
    progress: Callable[[float, str], None] | None
    #: None: row = flat camera pixel; a compact frame (``LDCViewRenderer._subpixel_frame``):
    #: (n,) int64 the camera pixel of each row
    pixels: np.ndarray | None = None
    #: an image frame's traced glossy term, filtered (``_mirrors``): (h w, 3) float64, and which rows hold one
    glossy: np.ndarray | None = None
    glossy_has: np.ndarray | None = None
    timings: dict[str, float] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    passes: dict[str, dict] = field(default_factory=dict)

    @property
    def width(self) -> int:
        return self.camera.width

    @property
    def height(self) -> int:
        return self.camera.height

    def camera_pixels(self, rows: np.ndarray) -> np.ndarray:
        """The camera pixel of each of the frame's ``rows``."""
        return rows if self.pixels is None else self.pixels[rows]

    def report(self, frac: float, stage: str) -> None:
        if self.progress is not None:
            self.progress(frac, stage)


@dataclass
class _FillRays:
    """The pixels that take their own eye ray: ``pix`` = the hole pixels (the first ``n_holes``)
    then the silhouette pixels, whose warped objects were ``sil_obj``."""

    pix: np.ndarray
    n_holes: int
    n_silhouette: int
    sil_obj: np.ndarray


@dataclass
class _ViewPassOut:
    """What the view pass leaves for the mirror stage: its pixels, how many reflect, their
    mirror rays (``rays.live`` rows; none unless mirrors are traced) and the surfaces whose glossy
    lobe is traced (``glossy.live`` rows; none unless ``glossy_rays``)."""

    pix: np.ndarray
    n_reflect: int
    rays: MirrorRays
    glossy: GlossySurfaces


class LDCViewRenderer:
    """Holds the scene's tables, the LDC, the LLF (None when the plan needs none) and, built
    lazily on first use, the IBRT acceleration structure. Reusable across renders (cache it
    per worker); ``render`` is not meant to run in two threads at once (numba's workqueue
    layer), a lock serialises it."""

    def __init__(self, scene: RuntimeScene, ldc: LDC, llf: LLF | None, plan: EffectPlan | dict | None = None, *,
                 caster: RayCaster | None = None, area_light_samples: int = 16, seed: int = 0,
                 warp_options: dict | None = None, hole_search_px: int | None = 3, refine_surface: bool = True,
                 refine_walk: bool = True, silhouette_mesh_test: bool = True, silhouette_rays: bool = True,
                 silhouette_rel_depth: float = 0.1, diffuse_filter: str = "bilinear"):
        if not isinstance(ldc, LDC):
            raise InvalidInputError("LDCViewRenderer needs an LDC")
        if ldc.n_lights != scene.lights.count:
            raise InvalidInputError(f"the LDC was baked for {ldc.n_lights} lights, the scene has {scene.lights.count}")
        self.scene = scene
        self.ldc = ldc
        self.llf = llf
        # the plan: given, or the one stored with the LDC bake, or analysed now
        if plan is None:
            plan = plan_from_dict(ldc.plan) if ldc.plan else analyze(scene)
        elif isinstance(plan, dict):
            plan = plan_from_dict(plan)
        self.plan = plan
        self._caster = caster
        self.area_light_samples = int(area_light_samples)
        self.seed = int(seed)
        if hole_search_px is not None and not (isinstance(hole_search_px, int) and 0 <= hole_search_px <= 64):
            raise InvalidInputError("hole_search_px must be None or an integer in [0, 64]")
        self.hole_search_px = hole_search_px
        self.refine_surface = bool(refine_surface)
        self.refine_walk = bool(refine_walk)
        self.silhouette_mesh_test = bool(silhouette_mesh_test)
        # edge neighbours for the walks to the triangle a ray crosses (refinement, silhouette test)
        walk = self.refine_surface and self.refine_walk
        self._nbr = triangle_neighbours(scene.tri_p) if (walk or self.silhouette_mesh_test) \
            else np.zeros((0, 3), np.int32)
        self._nbr_refine = self._nbr if walk else np.zeros((0, 3), np.int32)
        self._tri_obj = np.ascontiguousarray(scene.tri_object, np.int64)
        self.silhouette_rays = bool(silhouette_rays)
        if not (isinstance(silhouette_rel_depth, (int, float)) and 0.0 < float(silhouette_rel_depth) <= 10.0):
            raise InvalidInputError("silhouette_rel_depth must be a number in (0, 10]")
        self.silhouette_rel_depth = float(silhouette_rel_depth)
        if diffuse_filter not in DIFFUSE_FILTERS:
            raise InvalidInputError(f"diffuse_filter must be one of {list(DIFFUSE_FILTERS)}, got {diffuse_filter!r}")
        self.diffuse_filter = diffuse_filter
        self.warp_options = dict(warp_options or {})
        bad = set(self.warp_options) - {"min_cos", "max_footprint", "footprint_scale", "hole_rel_depth",
                                         "hole_neighbors"}
        if bad:
            raise InvalidInputError(f"unknown warp options {sorted(bad)}")
        self._accel = None
        self._trace_args = None
        self._lock = threading.Lock()
        # kernel tables built once per renderer (the LDC, LLF and scene are immutable)
        self._axes = _ldc_axes(ldc)
        self._mesh = SurfaceMesh(scene.tri_p, scene.tri_n, scene.tri_ng, self._nbr_refine, float(ldc.h))
        self._bounds = scene.bounds
        self._hp = highlight_params(scene, self.area_light_samples, self.seed)
        self._gp = gather_params(scene, llf) if llf is not None else _no_gather_params(scene)
        mt = scene.materials
        self._has_ks = (np.any(mt.ks > 0, axis=1) & (mt.shininess > 0))
        self._has_kr = np.any(mt.kr > 0, axis=1)
        self._has_kg = np.any(mt.kg > 0, axis=1)
        # materials the highlight kernel shades: Phong highlights, and the glossy lobe's reflection of
        # the rect lights (the light field holds surfaces, never a light)
        self._has_hl = self._has_ks | (self._has_kg & (scene.lights.n_rect > 0))
        # glossy_rays="auto": trace the lobes only where one may see a rect light in a mirror, the one
        # thing the light field cannot hold (it stores surfaces, never a light)
        used = np.unique(scene.tri_material) if scene.tri_material.size else np.zeros(0, np.int64)
        glossy, mirror, rect = bool(self._has_kg[used].any()), bool(self._has_kr[used].any()), scene.lights.n_rect > 0
        self.auto_glossy_rays = auto_glossy_rays(glossy, mirror, rect)
        self._auto_glossy_why = (
            "glossy surfaces may see rect lights in mirrors" if self.auto_glossy_rays else
            "no glossy surface" if not glossy else "no mirror" if not mirror else "no rect light")

    # ------------------------------------------------------------------ resources
    @property
    def accel(self):
        if self._accel is None:
            from engine.newviews.ibrt import build_accel

            self._accel = build_accel(self.ldc)
        return self._accel

    @property
    def caster(self) -> RayCaster:
        if self._caster is None:
            self._caster = make_caster(self.scene, "embree")
        return self._caster

    @property
    def nbytes(self) -> int:
        n = self.ldc.nbytes + (self.llf.nbytes if self.llf is not None else 0)
        if self._accel is not None:
            n += self._accel.nbytes
            if self._trace_args is not None:
                from engine.newviews.ibrt import trace_nbytes

                n += trace_nbytes(self._trace_args, self._accel)
        return int(n)

    # ------------------------------------------------------------------ helpers
    def _hole_rays(self, cam: KernelCamera, w: WarpResult) -> np.ndarray:
        """The hole pixels worth a ray: covered pixels flagged as holes (a far surface seen
        through a crack), and uncovered pixels within ``hole_search_px`` of a covered one whose
        ray meets the scene's bounds. An uncovered pixel farther from every splat is background:
        any LDC sample its ray could meet would have been splatted within about a pixel of it
        (the image-based ray tracer finds nothing the warp doesn't have). ``None``: every hole."""
        hm = w.hole_mask
        if self.hole_search_px is not None:
            covered = w.sample_axis >= 0
            r = self.hole_search_px
            near = _near_covered(covered, r) if r else covered
            hm = hm & near
        pix = np.flatnonzero(hm.reshape(-1))
        if self.hole_search_px is None or not pix.size:
            return pix
        lo, hi = self._bounds
        pad = float(self.ldc.h)
        keep = _rays_meet_box(pix, cam, np.asarray(lo, np.float64) - pad,
                              np.asarray(hi, np.float64) + pad)
        return pix[keep]

    # ------------------------------------------------------------------ render
    def render(self, camera: CameraParams, method: str, *, ibrt_generations: int = 0,
               progress: Callable[[float, str], None] | None = None, force_all_passes: bool = False,
               fill: str = "ibrt", supersample: int = 1, antialias: str = "uniform",
               edge_contrast: float = EDGE_CONTRAST, glossy_rays: int | str = "auto",
               glossy_filter: int = _GLOSSY_FILTER_DEFAULT) -> LDCRenderResult:
        """Render ``camera`` with ``method`` ("ldc", "ldc+llf", "ldc+ibrt" (+ ``ibrt_generations``
        0..8) or "ldc+ibrt:k"); see the module docstring. ``supersample`` s (1..4) renders s x s
        samples per pixel on a regular grid and box-filters the radiance (antialiasing).
        ``antialias="uniform"``: every pixel (s^2 the work); depth, normal, ids and provenance
        are those of the sample nearest the pixel centre, counts are summed. ``antialias="edges"``:
        only the pixels at an edge of the one-sample image (``_edge_pixels``: another object,
        a depth jump, or a luminance step of more than ``edge_contrast`` in the 3 x 3
        neighbourhood) get the s x s samples, on the sub-pixel rays of uniform supersampling
        but without a second warp (``_render_edges``); every other pixel, and every pixel's
        depth, normal, ids and provenance, is the one-sample render's, bit for bit.
        ``glossy_rays`` n (``ldc+ibrt:k`` with k >= 1 only; 0: the light field's gather; "auto", the
        default: ``GLOSSY_RAYS_AUTO`` where a glossy surface may see a rect light in a mirror,
        ``auto_glossy_rays``, else 0) traces n
        image-based rays of each glossy pixel's lobe instead of gathering it from the light field
        (``_mirrors``): a glossy surface then shows what its lobe sees through mirrors, lights
        included, at the price of n rays per glossy pixel. Their noise is filtered over the
        neighbouring pixels of the same surface within ``glossy_filter`` pixels (0..8; 0: none;
        ``_filter_glossy``). A supersampled pixel's sub-pixels share its n rays
        (``_glossy_rays_per_subpixel``); at the edges (``antialias="edges"``) a sub-pixel on the
        surface its pixel shows takes the pixel's filtered term. Raises
        InvalidInputError for a bad method / fill / supersample / antialias / glossy_rays or when
        the method needs an LLF the bake doesn't have."""
        spec = method_spec(method, ibrt_generations)
        if fill not in FILLS:
            raise InvalidInputError(f"fill must be one of {list(FILLS)}, got {fill!r}")
        if not isinstance(supersample, (int, np.integer)) or isinstance(supersample, bool) or \
                not (1 <= supersample <= 4):
            raise InvalidInputError(f"supersample must be an integer in [1, 4], got {supersample!r}")
        if antialias not in ANTIALIAS:
            raise InvalidInputError(f"antialias must be one of {list(ANTIALIAS)}, got {antialias!r}")
        if not isinstance(edge_contrast, (int, float)) or isinstance(edge_contrast, bool) or \
                not (0.0 < float(edge_contrast) <= 1.0):
            raise InvalidInputError(f"edge_contrast must be a number in (0, 1], got {edge_contrast!r}")
        gf = int(GLOSSY_FILTER.check(glossy_filter, "glossy_filter"))
        if isinstance(glossy_rays, str) and glossy_rays == "auto":
            g = self.auto_glossy_rays if spec.ibrt_generations >= 1 else 0
            why = f"auto: {self._auto_glossy_why}" if spec.ibrt_generations >= 1 else "auto: the method traces no rays"
        else:
            g = int(GLOSSY_RAYS.check(glossy_rays, "glossy_rays"))
            if g and spec.ibrt_generations < 1:
                raise InvalidInputError(f"glossy_rays traces image-based rays: it needs method 'ldc+ibrt:k' with "
                                        f"k >= 1, got {spec.wire!r}")
            why = "requested"
        glossy = _Glossy(g, gf, why)
        with self._lock:
            if supersample == 1:
                return self._render(camera, spec, progress, bool(force_all_passes), fill, glossy)
            s = int(supersample)
            if antialias == "edges":
                return self._render_edges(camera, spec, progress, bool(force_all_passes), fill, s,
                                          float(edge_contrast), glossy)
            big = replace(camera, width=camera.width * s, height=camera.height * s)
            r = self._render(big, spec, progress, bool(force_all_passes), fill,
                             _Glossy(_glossy_rays_per_subpixel(g, s), gf * s, why))
            H, W = camera.height, camera.width
            rad = r.radiance.astype(np.float64).reshape(H, s, W, s, 3).mean(axis=(1, 3)).astype(np.float32)
            c = s // 2

            def pick(a: np.ndarray) -> np.ndarray:
                return np.ascontiguousarray(a[c::s, c::s])

            r.plan["supersample"] = s
            r.plan["antialias"] = "uniform"
            r.counts["supersample"] = s
            return LDCRenderResult(radiance=rad, depth=pick(r.depth), normal=pick(r.normal),
                                   object_id=pick(r.object_id), material_id=pick(r.material_id),
                                   provenance=pick(r.provenance),
                                   hole_mask=r.hole_mask.reshape(H, s, W, s).any(axis=(1, 3)),
                                   timings=r.timings, counts=r.counts, plan=r.plan)

    def _render(self, camera, spec: MethodSpec, progress, force, fill,
                glossy: _Glossy) -> LDCRenderResult:
        """One render (``render``'s arguments, checked): the stages of the module docstring in
        order, each timed under its name in ``timings``."""
        return self._render_frame(camera, spec, progress, force, fill, glossy)[1]

    def _render_frame(self, camera, spec: MethodSpec, progress, force, fill,
                      glossy: _Glossy) -> tuple[_Frame, LDCRenderResult]:
        """``_render``, with the frame it ran on."""
        t_start = time.perf_counter()
        fr = self._warp(camera, progress)
        rc = self._fill(fr, fill)
        self._smooth_diffuse(fr, None)
        vp = self._view_pass(fr, spec, force, rc, glossy.rays)
        self._mirrors(fr, vp, spec, force, glossy)
        return fr, self._result(fr, spec, fill, force, t_start)

    def _render_edges(self, camera: CameraParams, spec: MethodSpec, progress, force: bool, fill: str, s: int,
                      contrast: float, glossy: _Glossy) -> LDCRenderResult:
        """``render(..., supersample=s, antialias="edges")``: the one-sample render, its edge
        pixels (``_edge_pixels``), then s x s sub-pixel rays in each edge pixel: the very rays
        of uniform supersampling (``camera`` at s times the width and height). No second warp:
        a sub-pixel shows the sample ``_subpixel_samples`` picks from the one-sample render's
        3 x 3 neighbourhood (the crossed surface, the nearest sample on it), or where the ray
        crosses none of them the image-based ray's hit (or the background); then the view pass
        and the mirror rays run on those sub-pixels as on any pixel (``_view_pass``,
        ``_mirrors``; a sub-pixel's highlight samples are uniform supersampling's), and each
        edge pixel's radiance is the box filter of its sub-pixels. Timings: the one-sample
        render's stages plus ``edges`` (detection), ``edge_rays`` (picking the sub-pixels'
        samples), ``edge_diffuse``, ``edge_surfaces``, ``edge_ibrt`` and ``total``."""
        t_start = time.perf_counter()

        def part(lo: float, hi: float):
            return None if progress is None else (lambda f, st: progress(lo + (hi - lo) * f, st))

        fr1, r1 = self._render_frame(camera, spec, part(0.0, 0.6), force, fill, glossy)
        H, W = camera.height, camera.width
        t0 = time.perf_counter()
        bg = np.asarray(self.ldc.background, np.float64)
        edge = _edge_pixels(r1.object_id, r1.depth, r1.radiance, self.silhouette_rel_depth, contrast,
                            _mean_luminance(r1.radiance, r1.object_id, bg))
        pix = np.flatnonzero(edge)
        timings = dict(r1.timings)
        timings["edges"] = time.perf_counter() - t0
        counts = dict(r1.counts)
        counts["supersample"] = s
        counts["edge_pixels"] = int(pix.size)
        rad = r1.radiance
        if pix.size:
            t0 = time.perf_counter()
            big = replace(camera, width=W * s, height=H * s)
            fr = self._subpixel_frame(fr1, big, pix, s, counts)
            timings["edge_rays"] = time.perf_counter() - t0
            self._smooth_diffuse(fr, np.flatnonzero(fr.obj_id >= 0))
            timings["edge_diffuse"] = fr.timings["diffuse"]
            g_sub = _Glossy(_glossy_rays_per_subpixel(glossy.rays, s), 0, glossy.why)
            vp = self._view_pass(fr, spec, force, None, g_sub.rays)
            self._mirrors(fr, vp, spec, force, g_sub, inherit=(fr1, pix, s))
            timings["edge_surfaces"] = fr.timings["surfaces"]
            timings["edge_ibrt"] = fr.timings["ibrt"]
            for k in ("view_pass_pixels", "traced_rays", "gather_lookups", "glossy_rays"):
                counts["edge_" + k] = int(fr.counts.get(k, 0))
            rad = r1.radiance.copy()
            if _box_filter_pixels(pix, fr.radiance, s * s, rad.reshape(-1, 3)):
                raise NonFiniteOutputError("LDC render produced non-finite values")
        timings["total"] = time.perf_counter() - t_start
        plan = dict(r1.plan)
        plan["supersample"] = s
        plan["antialias"] = "edges"
        plan["edge_contrast"] = contrast
        if progress is not None:
            progress(1.0, "done")
        return LDCRenderResult(radiance=rad, depth=r1.depth, normal=r1.normal, object_id=r1.object_id,
                               material_id=r1.material_id, provenance=r1.provenance, hole_mask=r1.hole_mask,
                               timings=timings, counts=counts, plan=plan)

    def _subpixel_frame(self, fr1: _Frame, big: CameraParams, pix: np.ndarray, s: int, counts: dict) -> _Frame:
        """A compact frame of the s x s sub-pixels of the one-sample frame's pixels ``pix``
        (``_render_edges``): row i s^2 + a s + b is sub-pixel (a, b) of ``pix[i]``, i.e. pixel
        (y s + a, x s + b) of the s-times finer camera ``big`` (``_Frame.pixels``: the kernels
        trace that pixel's ray). Each shows its sample (``_subpixel_samples``, else an
        image-based ray's hit, whatever the ``fill``: the sub-pixels are no holes of a warp), or
        the background. Compact, because the edge pixels are a few per cent of the image: a
        frame of all of ``big``'s pixels (16x the image at 4 x 4) cost more to allocate and
        fault in than its sub-pixels cost to render (docs/accuracy/gi.md)."""
        W = fr1.width
        a = np.arange(s)
        y, x = pix // W, pix % W
        q = (((y[:, None, None] * s + a[None, :, None]) * (W * s)) + (x[:, None, None] * s + a[None, None, :]))
        q = q.reshape(-1)
        n = q.size
        cam = kernel_camera(big)
        o, d = _pixel_rays(q, cam)
        ax0, ax1, ax2 = self._axes
        h_axis, h_sample, h_t = _subpixel_samples(pix, s * s, o, d, fr1.samples.axis, fr1.samples.index, W, fr1.height,
                                                  ax0, ax1, ax2, self.scene.tri_p, self.scene.tri_ng, self._tri_obj,
                                                  self._nbr, 2.0 * float(self.ldc.h), SAME_FACE_COS)
        ray = np.flatnonzero(h_axis < 0)
        counts["edge_subpixels"] = int(n)
        counts["edge_ibrt_rays"] = int(ray.size)
        if ray.size:
            r_axis, r_sample, r_t, _, _ = self._trace(o[ray], d[ray])
            h_axis[ray], h_sample[ray], h_t[ray] = r_axis, r_sample, r_t
        fr = _Frame(camera=big, cam=cam, warp=fr1.warp, radiance=np.empty((n, 3)), depth=np.empty(n, np.float32),
                    normal=np.empty((n, 3), np.float32), obj_id=np.empty(n, np.int32), mat_id=np.empty(n, np.int32),
                    prov=np.empty(n, np.uint8),
                    samples=PixelSamples(np.empty(n, np.int8), np.empty(n, np.int64), np.empty(n, np.int8)),
                    progress=None, pixels=q)
        sm = fr.samples
        _fill_subpixels(h_axis, h_sample, h_t, d, np.asarray(self.ldc.background, np.float64), ax0, ax1, ax2,
                        fr.radiance, fr.depth, fr.normal, fr.obj_id, fr.mat_id, fr.prov, sm.axis, sm.index, sm.side)
        return fr

    def _warp(self, camera: CameraParams, progress) -> _Frame:
        """Stage 1, timed as "warp" and "holes": every LDC sample splatted into the camera with a
        depth test, holes flagged (``warp_ldc``). Returns the render's frame: the warp's images,
        which the later stages update in place."""
        w = warp_ldc(self.ldc, camera, fill="none", radiance_dtype=np.float64, **self.warp_options)
        fr = _Frame(camera=camera, cam=kernel_camera(camera), warp=w, radiance=w.radiance.reshape(-1, 3),
                    depth=w.depth.reshape(-1), normal=w.normal.reshape(-1, 3), obj_id=w.object_id.reshape(-1),
                    mat_id=w.material_id.reshape(-1), prov=w.provenance.reshape(-1),
                    samples=PixelSamples(w.sample_axis.reshape(-1), w.sample_index.reshape(-1),
                                         w.sample_side.reshape(-1)), progress=progress)
        fr.timings["warp"] = w.timings["splat"] + w.timings["resolve"]
        fr.timings["holes"] = w.timings["holes"]
        fr.passes["warp"] = {"ran": True, "why": "always: the LDC's view-independent radiance"}
        fr.counts["warped_pixels"] = int((fr.prov == PROV_WARPED).sum())
        fr.counts["hole_pixels"] = w.n_holes
        fr.report(0.3, "warp")
        return fr

    def _smooth_diffuse(self, fr: _Frame, pix: np.ndarray | None) -> None:
        """Stage 2b, timed as "diffuse": with ``diffuse_filter="bilinear"``, the view-independent
        radiance of every pixel of ``pix`` (None: all) that shows an LDC sample is interpolated
        between that surface's samples around the pixel's point (``_bilinear_diffuse``) instead
        of being the nearest sample's. A sample's value stands for a cell of the LDI; taken whole,
        it turns smooth shading into steps at the sample spacing and every sample's own noise
        into a blotch, which beat against the camera's pixels (module docstring, *Diffuse
        reconstruction*)."""
        t0 = time.perf_counter()
        n = 0
        if self.diffuse_filter == "bilinear":
            if pix is None:
                pix = np.arange(fr.height * fr.width, dtype=np.int64)
            ax0, ax1, ax2 = self._axes
            n = int(_bilinear_diffuse_kernel(pix, fr.camera_pixels(pix), fr.samples, fr.cam, ax0, ax1, ax2,
                                             fr.radiance))
        fr.timings["diffuse"] = time.perf_counter() - t0
        fr.counts["diffuse_interpolated"] = n

    def _fill(self, fr: _Frame, fill: str) -> RaycastRecords | None:
        """Stage 2, timed as "fill": the hole pixels worth a ray and the silhouette pixels take
        their own eye ray (``_fill_rays``), through the LDC (``fill="ibrt"``: ``_ibrt_fill``) or
        against the triangles (``"raycast"``: ``_raycast_fill``). Returns the raycast fill's
        surface records (those pixels have no LDC sample), None without them."""
        t0 = time.perf_counter()
        fr_rays = self._fill_rays(fr, fill)
        holes, n_holes = fr_rays.pix, fr_rays.n_holes
        filled = 0
        rc = None
        if fill != "none" and holes.size:
            o, d = _pixel_rays(holes, fr.cam)
            if fill == "ibrt":
                filled = self._ibrt_fill(fr, fr_rays, o, d)
            else:
                # the warp's (covered) value is replaced by the ray's answer
                self._clear(fr, holes)
                rc = self._raycast_fill(fr, o, d, holes)
                filled = int(np.count_nonzero(fr.prov[holes[:n_holes]] == PROV_FILLED))
        fr.timings["fill"] = time.perf_counter() - t0
        counts = fr.counts
        counts["filled_pixels"] = filled
        # hole rays that met nothing: background the warp could not tell from a hole (most of
        # ``hole_pixels`` is uncovered background next to silhouettes; Embree agrees, docs/ldc.md)
        counts["hole_ray_misses"] = int(n_holes - filled) if fill != "none" else 0
        # silhouette pixels whose own ray showed another object (or nothing) than the splats did
        sil = holes[n_holes:]
        counts["silhouette_changed"] = int(np.count_nonzero(fr.obj_id[sil] != fr_rays.sil_obj)) if sil.size else 0
        fr.passes["fill"] = {"ran": bool(fill != "none" and holes.size), "how": fill,
                             "why": (f"{n_holes} hole pixels, {sil.size} silhouette pixels" if holes.size
                                     else "no holes, no silhouettes")}
        fr.report(0.5, "fill")
        return rc

    def _fill_rays(self, fr: _Frame, fill: str) -> _FillRays:
        """The pixels that take an eye ray in the fill: the hole pixels worth one (``_hole_rays``)
        and, with ``silhouette_rays`` (and a fill), the covered pixels at visibility edges of
        the warped image (module docstring)."""
        holes = self._hole_rays(fr.cam, fr.warp)
        fr.counts["hole_rays"] = int(holes.size)
        n_holes = int(holes.size)
        sil = np.zeros(0, np.int64)
        sil_obj = np.zeros(0, np.int32)
        if self.silhouette_rays and fill != "none":
            is_hole = np.zeros(fr.height * fr.width, np.bool_)
            is_hole[holes] = True
            sil = _silhouette_pixels(fr.obj_id, fr.depth, fr.samples.side, is_hole, fr.height, fr.width,
                                     self.silhouette_rel_depth)
            sil_obj = fr.obj_id[sil].copy()
            holes = np.concatenate([holes, sil])
        fr.counts["silhouette_rays"] = int(sil.size)
        return _FillRays(holes, n_holes, int(sil.size), sil_obj)

    def _ibrt_fill(self, fr: _Frame, rays: _FillRays, o: np.ndarray, d: np.ndarray) -> int:
        """The image-based fill of ``rays.pix`` (eye rays o, d): the silhouette pixels' mesh test
        first, then one image-based ray per hole pixel and per silhouette pixel the test left
        open; every such pixel then shows the ray's hit sample, or the background. Returns how
        many hole pixels a ray filled."""
        holes, n_holes = rays.pix, rays.n_holes
        counts = fr.counts
        counts["silhouette_mesh_hits"] = 0
        if rays.n_silhouette and self.silhouette_mesh_test:
            # Silhouette pixels: the mesh test decides first, from the triangles of the warp's
            # 3x3 winners the pixel ray crosses (docs/ldc.md); only the pixels where the ray
            # crosses none of them take an image-based ray (whose answer is within a cell of
            # the silhouette anyway). Hole pixels always take one.
            h_axis = np.full(holes.size, -1, np.int8)
            h_sample = np.full(holes.size, -1, np.int64)
            h_t = np.full(holes.size, np.inf)
            sl = slice(n_holes, None)
            ax0, ax1, ax2 = self._axes
            counts["silhouette_mesh_hits"] = int(_silhouette_mesh_test(
                holes[sl], o[sl], d[sl], h_axis[sl], h_sample[sl], h_t[sl], fr.samples.axis, fr.samples.index,
                fr.width, fr.height, ax0.prim, ax1.prim, ax2.prim, self.scene.tri_p, self.scene.tri_ng,
                self._tri_obj, self._nbr, 2.0 * float(self.ldc.h)))
            ray = np.concatenate([np.arange(n_holes), n_holes + np.flatnonzero(h_axis[sl] < 0)])
            r_axis, r_sample, r_t, n_steps, _ = self._trace(o[ray], d[ray])
            h_axis[ray], h_sample[ray], h_t[ray] = r_axis, r_sample, r_t
            counts["fill_ibrt_rays"] = int(ray.size)
        else:
            h_axis, h_sample, h_t, n_steps, _ = self._trace(o, d)
            counts["fill_ibrt_rays"] = int(holes.size)
        counts["fill_ibrt_steps"] = n_steps
        # the warp's (covered) value is replaced by the ray's answer: a sample, or the background
        self._clear(fr, holes)
        s = fr.samples
        for a, ax in enumerate(self._axes):
            _fill_from_hits(a, holes, h_axis, h_sample, h_t, d, ax.geo_normal, ax.normal, ax.material, ax.object,
                            ax.diffuse, fr.radiance, fr.depth, fr.normal, fr.obj_id, fr.mat_id, fr.prov, s.axis,
                            s.index, s.side)
        return int(np.count_nonzero(h_axis[:n_holes] >= 0))

    def _clear(self, fr: _Frame, pix: np.ndarray) -> None:
        """Pixels ``pix`` show the background and no sample (before a ray's answer replaces them)."""
        _clear_pixels(pix, np.asarray(self.ldc.background, np.float64), fr.radiance, fr.depth, fr.normal, fr.obj_id,
                      fr.mat_id, fr.prov, fr.samples.axis, fr.samples.index)

    def _raycast_fill(self, fr: _Frame, o, d, holes) -> RaycastRecords | None:
        """Interim fill: Embree rays against the triangles, shaded with the bake's diffuse model.
        Returns the surface records of the pixels it shaded (None: it shaded none)."""
        sc, ldc = self.scene, self.ldc
        caster = self.caster
        hit = caster.intersect(o, d)
        ok = hit.prim >= 0
        pix = holes[ok]
        if not pix.size:
            return None
        p, ng, ns = surface_attributes(sc, hit.prim[ok], hit.u[ok], hit.v[ok])
        mat = sc.tri_material[hit.prim[ok]].astype(np.int32)
        occl = np.asarray(ldc.plan.get("occludable_lights", [True] * sc.lights.count), dtype=np.bool_)
        store = ldc.visibility_words > 0
        rad, vis, _ = shade_samples(sc, caster, p, ng, ns, mat, occl, store_bits=store,
                                    area_light_samples=self.area_light_samples, seed=self.seed, stream_id=3)
        side = (np.einsum("ij,ij->i", ng, d[ok]) >= 0).astype(np.int64)
        r = np.arange(side.shape[0])
        sg = np.where(side == 0, 1.0, -1.0)[:, None]
        g = ng * sg
        n = ns * sg
        n = np.where((np.einsum("ij,ij->i", n, g) > 0)[:, None], n, g)
        fr.radiance[pix] = rad[r, side]
        fr.depth[pix] = hit.t[ok]
        fr.normal[pix] = n
        fr.obj_id[pix] = sc.tri_object[hit.prim[ok]]
        fr.mat_id[pix] = mat
        fr.prov[pix] = PROV_FILLED
        bits = vis[r, side] if store else np.zeros((pix.size, 0), np.uint64)
        if bits.shape[1] != ldc.visibility_words:
            bits = np.zeros((pix.size, ldc.visibility_words), np.uint64)
        row = np.full(fr.height * fr.width, -1, np.int64)
        row[pix] = np.arange(pix.size)
        c = np.ascontiguousarray
        return RaycastRecords(row, c(p, np.float64), c(g, np.float64), c(n, np.float64), c(mat, np.int32),
                              c(bits, np.uint64))

    def _view_pass(self, fr: _Frame, spec: MethodSpec, force: bool, rc: RaycastRecords | None,
                   glossy_rays: int) -> _ViewPassOut:
        """Stage 3, timed as "surfaces" ("highlights" and "gather" are 0: one fused kernel does
        them): on the covered pixels whose material needs it (the effect plan, or every one
        with ``force``), the surface record, its refinement, the highlights and the light-field
        gather (``_view_pass_kernel``); with ``ldc+ibrt:k`` (k >= 1) the mirror rays instead of
        the mirror cone, and with ``glossy_rays`` the glossy surfaces instead of the glossy gather."""
        t0 = time.perf_counter()
        counts, passes = fr.counts, fr.passes
        want_vp = force or self.plan.needs_view_pass
        reflect = spec.gathers
        refl_mat = self._has_kr | self._has_kg
        want_rf = want_vp and reflect
        if want_rf and self.llf is None:
            covered = fr.obj_id >= 0
            if force or np.any(covered & refl_mat[np.where(covered, fr.mat_id, 0)]):
                if force and not self.plan.needs_llf:
                    want_rf = False
                    passes["gather_note"] = {"why": "forced, but there is no LLF to gather from"}
                else:
                    raise InvalidInputError(f"method {spec.wire!r} needs the bake's LLF (the scene has glossy or "
                                            "mirror materials) but this bake has none; use method 'ldc' or rebake "
                                            "with an LLF")
        vp_pix, n_hl, n_rf = _select_view_pass(fr.obj_id, fr.mat_id, self._has_hl, refl_mat, bool(want_vp),
                                               bool(want_rf), force)
        counts["view_pass_pixels"] = int(vp_pix.size)
        counts["highlight_pixels"] = int(n_hl)
        counts["reflection_pixels"] = int(n_rf)
        why_vp = self._why_view_pass(force)
        trace_mirror = spec.ibrt_generations > 0
        nv = vp_pix.size
        lookups = np.zeros(nv, np.int64)
        rays = mirror_rays(nv if (trace_mirror and n_rf) else 0)
        trace_glossy = bool(glossy_rays) and trace_mirror and bool(n_rf)
        gsurf = glossy_surfaces(nv if trace_glossy else 0)
        if nv:
            gathered = self._has_kg if trace_mirror else refl_mat
            if trace_glossy:
                gathered = np.zeros_like(gathered)
            sw = ViewPassSwitches(hl_mat=self._has_hl, rf_mat=refl_mat, gathered_mat=gathered, want_hl=bool(want_vp),
                                  want_rf=bool(want_rf), force=force, mirror=not trace_mirror,
                                  trace=rays.live.size > 0, glossy=gsurf.live.size > 0, refine=self.refine_surface)
            _view_pass_kernel(_groups(), vp_pix, fr.camera_pixels(vp_pix), fr.samples,
                              rc if rc is not None else _no_raycast_records(self.ldc.visibility_words), fr.cam,
                              self._mesh, sw, self._hp, self._gp,
                              ViewPassImage(fr.radiance, fr.normal, fr.prov, lookups), rays, gsurf, *self._axes)
        fr.timings["surfaces"] = time.perf_counter() - t0
        fr.timings["highlights"] = 0.0
        fr.timings["gather"] = 0.0
        passes["highlights"] = {"ran": bool(n_hl), "why": why_vp, "pixels": int(n_hl)}
        fr.report(0.6, "highlights")
        counts["gather_lookups"] = int(lookups.sum())
        # provenance is at most PROV_FILLED before this pass: the gathered ones were set by the kernel
        counts["gather_pixels"] = int(np.count_nonzero(fr.prov[vp_pix] == PROV_GATHERED)) if n_rf else 0
        passes["gather"] = {"ran": bool(n_rf) and not trace_glossy,
                            "what": ("glossy lobe" if trace_mirror else "mirror cone + glossy lobe"),
                            "why": ("method 'ldc' has no reflections" if not reflect else
                                    "the glossy lobe is traced (glossy_rays)" if trace_glossy else why_vp)}
        fr.report(0.75, "gather")
        return _ViewPassOut(vp_pix, int(n_rf), rays, gsurf)

    def _mirrors(self, fr: _Frame, vp: _ViewPassOut, spec: MethodSpec, force: bool, glossy: _Glossy,
                 inherit: tuple[_Frame, np.ndarray, int] | None = None) -> None:
        """Stage 4, timed as "ibrt": with ``ldc+ibrt:k`` (k >= 1) the view pass's mirror rays,
        traced through the LDC for k generations (``_trace_rays``) in 16 x 16 pixel tiles
        (``_tile_order``; the view pass's pixels are row-major); with ``glossy.rays`` n, n rays
        of each glossy pixel's lobe (``_glossy_lobe_rays``), traced for k + 1 generations: the
        lobe's own ray, then k mirror bounces. A ray of the lobe that meets a rect light straight
        away adds nothing (the highlights shade the lobe's reflection of the rect lights); one
        that meets it after a mirror does (the glossy reflection of a light seen in a mirror).
        In an image frame the traced glossy term is then filtered (``_filter_glossy``, radius
        ``glossy.filter``); in the compact frame of an edge render (``inherit``: the one-sample
        frame, its edge pixels, s) a sub-pixel on the glossy surface its pixel shows takes the
        pixel's filtered term instead of tracing."""
        k = spec.ibrt_generations
        trace_mirror = k > 0
        rays = vp.rays
        t0 = time.perf_counter()
        fr.counts["traced_rays"] = 0
        fr.counts["ibrt_steps"] = 0
        fr.counts["glossy_rays"] = 0
        if rays.live.size:
            live = np.flatnonzero(rays.live)
            live = live[_tile_order(fr.camera_pixels(vp.pix[live]), fr.width, _RAY_TILE)]
            traced = vp.pix[live]
            acc = self._trace_rays(rays.o[live], rays.d[live], rays.ng[live], rays.thr[live], k, 1, fr.counts, force)
            fr.radiance[traced] += acc
            fr.prov[traced[self._has_kr[fr.mat_id[traced]]]] = PROV_TRACED
        gs = vp.glossy
        if gs.live.size:
            rows = np.flatnonzero(gs.live)
            fr.prov[vp.pix[rows]] = PROV_TRACED
            if inherit is not None:
                fr1, parent_pix, ss = inherit
                if fr1.glossy is not None and fr1.glossy_has is not None:
                    sub = vp.pix[rows]
                    par = parent_pix[sub // (ss * ss)]
                    same = (fr1.glossy_has[par] & (fr1.obj_id[par] == fr.obj_id[sub])
                            & (fr1.mat_id[par] == fr.mat_id[sub]))
                    fr.radiance[sub[same]] += fr1.glossy[par[same]]
                    fr.counts["glossy_inherited"] = int(same.sum())
                    rows = rows[~same]
            term = self._trace_glossy(fr, vp, rows, k, glossy.rays, force)
            frows = vp.pix[rows]
            if fr.pixels is None and rows.size:  # an image frame: the term per pixel, filtered, kept for the edges
                has = np.zeros(fr.radiance.shape[0], np.bool_)
                has[frows] = True
                img = np.zeros_like(fr.radiance)
                img[frows] = term
                if glossy.filter > 0:
                    out = np.zeros_like(img)
                    _filter_glossy(has, img, fr.normal, fr.depth, fr.mat_id, fr.width, fr.height, glossy.filter,
                                   _GLOSSY_FILTER_COS, _GLOSSY_FILTER_DEPTH, out)
                    img = out
                fr.radiance[frows] += img[frows]
                fr.glossy, fr.glossy_has = img, has
            else:
                fr.radiance[frows] += term
        fr.timings["ibrt"] = time.perf_counter() - t0
        why_vp = self._why_view_pass(force)
        fr.passes["ibrt"] = {"ran": bool(trace_mirror and vp.n_reflect), "generations": k,
                             "glossy_rays": int(glossy.rays) if gs.live.size else 0,
                             "glossy_filter": int(glossy.filter) if gs.live.size else 0,
                             "glossy_why": glossy.why,
                             "why": ("method is not ldc+ibrt:k with k >= 1" if not trace_mirror else why_vp)}
        fr.report(0.95, "ibrt")

    def _why_view_pass(self, force: bool) -> str:
        return ("forced on every covered pixel" if force else
                ("the plan has non-diffuse materials" if self.plan.needs_view_pass
                 else "skipped: every material is diffuse"))

    def _result(self, fr: _Frame, spec: MethodSpec, fill: str, force: bool, t_start: float) -> LDCRenderResult:
        """The frame as an ``LDCRenderResult`` (float32 radiance, checked finite) with the plan that ran."""
        H, W = fr.height, fr.width
        out = np.empty((H, W, 3), np.float32)
        if _to_f32_count_nonfinite(fr.radiance, fr.depth, out.reshape(-1, 3)):
            raise NonFiniteOutputError("LDC render produced non-finite values")
        fr.timings["total"] = time.perf_counter() - t_start
        nondiffuse = self._has_ks | self._has_kr | self._has_kg
        plan = {"method": spec.wire, "ibrt_generations": spec.ibrt_generations, "fill": fill,
                "refine_surface": self.refine_surface, "refine_walk": self.refine_surface and self.refine_walk,
                "silhouette_rays": self.silhouette_rays and fill != "none",
                "silhouette_mesh_test": self.silhouette_mesh_test and self.silhouette_rays and fill == "ibrt",
                "force_all_passes": force, "passes": fr.passes, "effects": self.plan.to_dict(),
                "indirect": self.ldc.plan.get("indirect", {"state": "off", "reason": "baked without indirect light"}),
                "non_diffuse_materials": [int(i) for i in np.flatnonzero(nondiffuse)]}
        fr.report(1.0, "done")
        return LDCRenderResult(radiance=out, depth=fr.depth.reshape(H, W).astype(np.float32, copy=False),
                               normal=fr.normal.reshape(H, W, 3).astype(np.float32, copy=False),
                               object_id=fr.obj_id.reshape(H, W).astype(np.int32, copy=False),
                               material_id=fr.mat_id.reshape(H, W).astype(np.int32, copy=False),
                               provenance=fr.prov.reshape(H, W).astype(np.uint8, copy=False),
                               hole_mask=fr.warp.hole_mask, timings=fr.timings, counts=fr.counts, plan=plan)

    def _trace(self, o: np.ndarray, d: np.ndarray, origin_normals: np.ndarray | None = None):
        """(axis, sample, t, n_steps, n_tests) of rays o + t d (d unit) through the LDC."""
        from engine.newviews.ibrt import trace_args, trace_prepared

        if self._trace_args is None:
            self._trace_args = trace_args(self.ldc)
        return trace_prepared(self.ldc, self._trace_args, self.accel, np.ascontiguousarray(o, np.float64),
                              np.ascontiguousarray(d, np.float64), origin_normals=origin_normals)

    def _trace_glossy(self, fr: _Frame, vp: _ViewPassOut, rows: np.ndarray, k: int, n_rays: int,
                      force: bool) -> np.ndarray:
        """The traced glossy term (len(rows), 3) of the view pass's glossy surfaces ``rows``: n_rays
        lobe rays each (``_glossy_lobe_rays``), traced for k + 1 generations, the rect lights seen
        from the second on, summed per surface in ray order (the same term for any chunking)."""
        term = np.zeros((rows.size, 3))
        if not rows.size:
            return term
        order = _tile_order(fr.camera_pixels(vp.pix[rows]), fr.width, _RAY_TILE)
        cam_pix = fr.camera_pixels(vp.pix)
        key = sample_key(self.seed, _GLOSSY_STREAM)
        step = max(1, _GLOSSY_CHUNK_RAYS // n_rays)  # bounded memory: the rays of a chunk of pixels at a time
        for lo in range(0, rows.size, step):
            part = order[lo:lo + step]
            n = part.size * n_rays
            o, d, ng, thr = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3))
            live = np.empty(n, np.bool_)
            _glossy_lobe_rays(rows[part], vp.glossy, cam_pix, self._hp.kg, self._hp.gloss_exponent, n_rays, key,
                              o, d, ng, thr, live)
            keep = np.flatnonzero(live)
            fr.counts["glossy_rays"] += int(keep.size)
            acc = np.zeros((n, 3))
            acc[keep] = self._trace_rays(o[keep], d[keep], ng[keep], thr[keep], k + 1, 2, fr.counts, force)
            term[part] = acc.reshape(part.size, n_rays, 3).sum(axis=1)  # a pixel's rays are consecutive
        return term

    def _trace_rays(self, o, d, ng_o, thr, k, emitters_from, counts, force) -> np.ndarray:
        """The radiance (n, 3) each of n image-based rays brings (origins o, unit directions d,
        surface normals ng_o at the origins, throughput thr) over k generations: the rays, then
        the mirror rays of their hits, the last generation ending in the mirror-cone gather at its
        hit (module docstring). Rays of generation ``emitters_from`` and later see the rect lights."""
        bg = np.asarray(self.ldc.background, np.float64)
        owner = np.arange(o.shape[0])
        acc = np.zeros((o.shape[0], 3))
        for gen in range(1, k + 1):
            n = owner.size
            if not n:
                break
            h_axis, h_sample, h_t, n_steps, _ = self._trace(o, d, ng_o)  # leaves the surface it starts on
            counts["traced_rays"] += int(n)
            counts["ibrt_steps"] += n_steps
            last = gen == k
            lookups = np.zeros(n, np.int64)
            m = 0 if last else n  # the last generation writes no next rays (only ``live``, all False)
            nxt = MirrorRays(np.empty((m, 3)), np.empty((m, 3)), np.empty((m, 3)), np.empty((m, 3)),
                             np.zeros(n, np.bool_))
            gather_mat = (self._has_kg | self._has_kr) if last else self._has_kg
            _shade_hits(_groups(), RayHits(h_axis, h_sample, h_t), TracedRays(o, d, owner, thr),
                        Generation(last, self.llf is not None, gather_mat, force, bg, gen >= emitters_from),
                        self._hp, self._gp, self._mesh, acc, lookups, nxt, *self._axes)
            counts["gather_lookups"] += int(lookups.sum())
            if last:
                break
            go = np.flatnonzero(nxt.live)
            owner = owner[go]
            o, d, ng_o, thr = nxt.o[go], nxt.d[go], nxt.ng[go], nxt.thr[go]
        return acc


def _glossy_rays_per_subpixel(glossy_rays: int, s: int) -> int:
    """The glossy lobe rays each of a pixel's s x s sub-pixels traces: ``glossy_rays`` per pixel
    shared among them (at least one each), so supersampling antialiases a glossy pixel without
    multiplying its rays."""
    return 0 if not glossy_rays else max(1, -(-glossy_rays // (s * s)))


def _groups() -> int:
    """Parallel groups for the fused kernels: one per numba thread."""
    return max(1, int(nb.get_num_threads()))


__all__ = ["ANTIALIAS", "EDGE_CONTRAST", "FILLS", "LDCRenderResult", "LDCViewRenderer", "PROV_FILLED",
           "PROV_GATHERED", "PROV_NONE", "PROV_TRACED", "PROV_WARPED", "method_spec", "parse_method"]
