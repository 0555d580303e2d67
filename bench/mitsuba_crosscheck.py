"""Cross-check of the reference renderer against Mitsuba 3 (``direct`` and ``path``).

Run ``python -m bench.mitsuba_crosscheck`` (full size, about half an hour on 2 cores); it writes
``docs/accuracy-reference.md`` and the images under ``docs/img/crosscheck/``. The test
``tests/engine/test_mitsuba_crosscheck.py`` runs the same comparisons at small resolution.

Scenes (loaded into both renderers):

- ``cornell_box``: ``samples/scenes/cornell_box.json`` for us, Mitsuba's own
  ``../shared/data/cornell-box-mitsuba/cbox-rgb.xml`` for Mitsuba (its luminaire is an area
  emitter; ours is a rect light at the same place plus an emissive, non-lighting luminaire).
- ``spheres_box``: a sphere, a rotated box and a back wall on a floor, lit by a point light and a
  rect light (built here as a schema ``Scene``; converted by ``bench.mitsuba_bridge``).
- ``directional_sphere``: ``samples/scenes/mitsuba_directional_sphere.json`` against Mitsuba's
  stored 32k-spp ``direct`` reference image (``direct``) and against Mitsuba's own test scene
  file rendered with ``path`` (``path``).
- ``cornell_mirror_glossy``: ``samples/scenes/cornell_mirror_glossy.json`` (the Cornell box with a
  mirror sphere and a glossy tall box; converted by ``bench.mitsuba_bridge``, the glossy material
  by its ``ibr_phong`` plugin, rendered in ``llvm_ad_rgb``), ``path`` only: light reaches the walls
  through the mirror and the glossy lobe (caustic paths). ``direct`` is left out: Mitsuba's
  ``direct`` stops after one bounce, our direct-only renders follow mirror chains to
  ``max_depth``.

Error numbers are ``engine.metrics.compare`` with Mitsuba as the reference, over the pixels
whose centre ray hits geometry in our render (``object_id >= 0``), minus the pixels that see an
emissive surface or a rect light, or touch one (3 x 3 neighbourhood) -- see :func:`comparison_mask`
for why.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from api_schemas.scene import load_scene_file, load_scene_json
from bench import mitsuba_bridge as mb
from engine.error_region import emissive_objects, region_around, sees_rect_light
from engine.metrics import ErrorReport, compare, error_heatmap, lrms, luminance
from engine.reference import ReferenceParams, ReferenceRenderer
from engine.scene import CameraParams, RuntimeScene
from workers.scene_loader import directory_resolver, load_scene

SCENES = ("cornell_box", "spheres_box", "directional_sphere", "cornell_mirror_glossy")
KINDS = ("direct", "path")
# the mirror / glossy box is checked with path only (see the module docstring)
KINDS_OF = {"cornell_mirror_glossy": ("path",)}
BOUNCES = 4  # our indirect_bounces; Mitsuba path max_depth = 6, the Cornell box file's default
# the mirror / glossy scene: our mirror / glossy segments along a camera chain do not count against
# indirect_bounces (Mitsuba counts every segment), so paths seen in the mirror may be one or two
# segment longer than Mitsuba's; with 6 bounces (max_depth 8) that segment carries well under the
# noise (in this box every further bounce adds about half of the one before; measured in
# docs/accuracy-reference.md)
MIRROR_BOUNCES = 6
MIRROR_DEPTH = 8

# the acceptance thresholds (LRMS against Mitsuba), per kind, and stricter per scene
THRESHOLD = {"direct": 0.01, "path": 0.03}
SCENE_THRESHOLD = {("cornell_mirror_glossy", "path"): 0.015}


def threshold(scene: str, kind: str) -> float:
    return SCENE_THRESHOLD.get((scene, kind), THRESHOLD[kind])

DOC = mb.REPO_ROOT / "docs" / "accuracy-reference.md"
IMG_DIR = mb.REPO_ROOT / "docs" / "img" / "crosscheck"


@dataclass(frozen=True)
class Budget:
    """Image size and sample counts of one run.

    res: image side in pixels (``directional_sphere`` always uses its reference's 48 x 48).
    ours_spp / ours_area: our antialiasing samples and rect-light samples (g x g grid) for
    ``direct``; ours_path_spp / ours_path_area / ours_paths: the same and the indirect paths per
    pixel for ``path`` (the camera hit's direct light is estimated with spp x area samples
    there too, so spp must stay high); mi_direct_spp / mi_path_spp: Mitsuba samples per pixel
    (``multijitter`` sampler: use squares).
    """

    res: int
    ours_spp: int
    ours_area: int
    ours_path_spp: int
    ours_path_area: int
    ours_paths: int
    mi_direct_spp: int
    mi_path_spp: int

    def ours_params(self, kind: str, seed: int = 0, max_depth: int = 0, bounces: int = BOUNCES) -> ReferenceParams:
        if kind == "direct":
            return ReferenceParams(spp=self.ours_spp, max_depth=max_depth, area_light_samples=self.ours_area,
                                   indirect_samples=0, seed=seed, chunk_pixels=4096)
        # chunk_pixels bounds a wavefront to chunk x spp x ceil(paths / spp) rays
        chunk = max(64, (1 << 21) // (self.ours_path_spp * max(1, -(-self.ours_paths // self.ours_path_spp))))
        return ReferenceParams(spp=self.ours_path_spp, max_depth=max_depth, area_light_samples=self.ours_path_area,
                               indirect_samples=self.ours_paths, indirect_bounces=bounces, seed=seed,
                               chunk_pixels=chunk)

    def mi_spp(self, kind: str) -> int:
        return self.mi_direct_spp if kind == "direct" else self.mi_path_spp


FULL = Budget(res=256, ours_spp=256, ours_area=16, ours_path_spp=256, ours_path_area=4, ours_paths=2048,
              mi_direct_spp=4096, mi_path_spp=4096)
# Caustics through the mirror sphere (and the glossy box) are found by unidirectional paths in
# both renderers: a rare, bright event, about 3 x the per-path noise of the diffuse box. LRMS is a
# per-pixel RMS, so the check runs at a low resolution with 32 x the paths per pixel instead.
SCENE_BUDGET = {
    "cornell_mirror_glossy": Budget(res=24, ours_spp=256, ours_area=16, ours_path_spp=256, ours_path_area=4,
                                    ours_paths=65536, mi_direct_spp=4096, mi_path_spp=262144),
}


# ============================================================================ scenes


SPHERES_BOX = {
    "schema_version": 1,
    "name": "crosscheck_spheres_box",
    "camera": {"type": "perspective", "eye": [0.6, 1.9, 5.6], "look_at": [0.0, 0.7, 0.0],
               "up": [0, 1, 0], "fov_y_deg": 40.0, "width": 256, "height": 256},
    "materials": [
        {"name": "floor", "kd": [0.7, 0.7, 0.68]},
        {"name": "wall", "kd": [0.55, 0.6, 0.5]},
        {"name": "red", "kd": [0.75, 0.2, 0.12]},
        {"name": "blue", "kd": [0.15, 0.35, 0.7]},
    ],
    "objects": [
        {"type": "plane", "name": "floor", "material": "floor", "size": [7.0, 7.0]},
        {"type": "plane", "name": "back_wall", "material": "wall", "size": [7.0, 3.4],
         "transform": {"rotate_deg": [90.0, 0.0, 0.0], "translate": [0.0, 1.7, -2.0]}},
        # asymmetric on purpose: red sphere on the left, taller blue box on the right
        {"type": "sphere", "name": "ball", "material": "red", "center": [-0.9, 0.6, 0.2],
         "radius": 0.6, "subdivisions": 5},
        {"type": "box", "name": "block", "material": "blue", "size": [0.8, 1.3, 0.8],
         "transform": {"rotate_deg": [0.0, 30.0, 0.0], "translate": [0.9, 0.65, -0.4]}},
    ],
    "lights": [
        {"type": "point", "name": "key", "position": [2.2, 3.0, 2.0], "intensity": [20.0, 19.0, 17.0]},
        # above everything and out of the camera's view, facing down (cross(u, v) = -y)
        {"type": "rect", "name": "sky", "corner": [-1.8, 3.6, -0.6], "edge_u": [1.2, 0.0, 0.0],
         "edge_v": [0.0, 0.0, 1.0], "radiance": [6.0, 6.4, 7.2]},
    ],
}


@dataclass
class Prepared:
    """One scene, ready in both renderers."""

    name: str
    title: str
    runtime: RuntimeScene
    camera: CameraParams
    mi_scene: object
    mi_sensor: object
    direct_reference: np.ndarray | None = None  # a stored Mitsuba image replaces the direct render
    notes: list[str] = field(default_factory=list)
    kinds: tuple[str, ...] = KINDS
    variant: str = mb.MITSUBA_VARIANT  # the Mitsuba variant mi_scene was loaded in
    max_depth: int = 0  # our mirror / glossy chain depth (0: the scene has no such lobes)
    bounces: int = BOUNCES  # our indirect_bounces for path (Mitsuba max_depth = bounces + 2)


def _sample(name: str):
    import samples

    return load_scene(load_scene_file(samples.sample_path(name)), directory_resolver(samples.SAMPLES_DIR))


def prepare(name: str, res: int, workdir: str | Path) -> Prepared:
    """Load scene ``name`` into both renderers at ``res`` x ``res`` (meshes for Mitsuba go to
    ``workdir``, which must live as long as the scene is rendered)."""
    if name == "cornell_box":
        ls = _sample("cornell_box")
        cam = replace(ls.camera, width=res, height=res)
        scene = mb.load_cornell_box(res)
        return Prepared(name, "Cornell box (Mitsuba's cbox-rgb.xml vs samples/scenes/cornell_box.json)",
                        ls.runtime, cam, scene, mb.resampled_sensor(scene))
    if name == "spheres_box":
        ls = load_scene(load_scene_json(json.dumps(SPHERES_BOX)))
        cam = replace(ls.camera, width=res, height=res)
        scene = mb.runtime_to_mitsuba(ls.runtime, cam, workdir, sampler="multijitter")
        return Prepared(name, "Sphere + box + wall on a floor, point + rect light (converted by the bridge)",
                        ls.runtime, cam, scene, scene.sensors()[0])
    if name == "directional_sphere":
        ls = _sample("mitsuba_directional_sphere")
        scene = mb.load_directional_sphere()
        ref = mb.read_directional_reference()
        if ref.shape[:2] != (ls.camera.height, ls.camera.width):
            raise ValueError(f"reference is {ref.shape}, camera {ls.camera}")
        return Prepared(name, "Floating sphere under a directional light (Mitsuba test scene, 48 x 48)",
                        ls.runtime, ls.camera, scene, mb.resampled_sensor(scene), direct_reference=ref)
    if name == "cornell_mirror_glossy":
        ls = _sample("cornell_mirror_glossy")
        cam = replace(ls.camera, width=res, height=res)
        scene = mb.runtime_to_mitsuba(ls.runtime, cam, workdir, sampler="multijitter", variant=mb.LLVM_VARIANT)
        return Prepared(name, "Cornell box with a mirror sphere and a glossy box (converted by the bridge)",
                        ls.runtime, cam, scene, scene.sensors()[0], kinds=KINDS_OF[name], variant=mb.LLVM_VARIANT,
                        max_depth=MIRROR_DEPTH, bounces=MIRROR_BOUNCES)
    raise KeyError(f"unknown cross-check scene {name!r}; known: {', '.join(SCENES)}")


def mirrored_emitters(runtime: RuntimeScene, camera: CameraParams, max_depth: int, spp: int = 64) -> np.ndarray:
    """(h, w) bool: some of the pixel's ``spp`` samples see an emitter (a rect light or an emissive
    surface) through mirrors (``kr``, up to ``max_depth`` reflections):
    ``ReferenceRenderer.emitters_in_mirrors`` with more samples than the engine's region takes. A
    mirror sphere shows the light as a tiny image ~100 x brighter than the room."""
    return ReferenceRenderer(runtime).emitters_in_mirrors(camera, max_depth, spp)


def comparison_mask(runtime: RuntimeScene, object_id: np.ndarray,
                    light_pixels: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Pixels compared: covered in our render (centre ray hits geometry), minus every pixel
    whose 3 x 3 neighbourhood sees an emissive material or (``light_pixels``, from
    :func:`sees_rect_light`, or an emitter seen through a mirror: :func:`mirrored_emitters`) a
    light. Returns (mask, pixels excluded). Why the emitter pixels go: ``engine/error_region.py``
    (the Cornell box luminaire is ~100 x brighter than anything it lights; excluding it makes the
    check stricter, not looser)."""
    covered = object_id >= 0
    sees_emitter = covered & emissive_objects(runtime)[np.clip(object_id, 0, None)]
    if light_pixels is not None:
        sees_emitter |= light_pixels
    mask = region_around(covered, sees_emitter)
    return mask, int(np.count_nonzero(covered & ~mask))


@dataclass
class Result:
    scene: str
    kind: str
    ours: np.ndarray
    ref: np.ndarray
    mask: np.ndarray
    excluded: int
    report: ErrorReport
    ours_seconds: float
    mi_seconds: float | None
    ours_settings: str
    mi_settings: str
    lrms_covered: float  # over every covered pixel, emitter pixels included (for the record)
    mean_bias: float  # mean(Y_ours) / mean(Y_ref) - 1 over the mask: a systematic offset shows here


    @property
    def threshold(self) -> float:
        return threshold(self.scene, self.kind)

    @property
    def passed(self) -> bool:
        return self.report.lrms < self.threshold


def run(prep: Prepared, kind: str, budget: Budget, seed: int = 0,
        renderer: ReferenceRenderer | None = None) -> Result:
    """Render ``prep`` with both renderers (``kind`` = direct | path) and compare."""
    renderer = renderer or ReferenceRenderer(prep.runtime)
    params = budget.ours_params(kind, seed, prep.max_depth, prep.bounces)
    t0 = time.perf_counter()
    out = renderer.render(prep.camera, params)
    t_ours = time.perf_counter() - t0
    if kind == "path":
        ours_settings = (f"spp {params.spp}, rect {params.area_light_samples}, "
                         f"{params.indirect_samples} paths x {params.indirect_bounces} bounces")
        if params.max_depth:
            ours_settings += f", max_depth {params.max_depth}, glossy {params.glossy_samples}"
    else:
        ours_settings = f"spp {params.spp}, rect {params.area_light_samples}"
    if kind == "direct" and prep.direct_reference is not None:
        ref, t_mi, mi_settings = prep.direct_reference, None, "stored reference (32k spp, independent)"
    else:
        spp = budget.mi_spp(kind)
        mr = mb.render(prep.mi_scene, kind, prep.bounces, spp=spp, seed=seed, sensor=prep.mi_sensor,
                       variant=prep.variant)
        ref, t_mi = mr.radiance, mr.seconds
        depth = f", max_depth {mr.integrator['max_depth']}" if kind == "path" else ""
        mi_settings = f"{kind}{depth}, spp {spp}, multijitter, {prep.variant}"
    if ref.shape != out.radiance.shape:
        raise ValueError(f"{prep.name}: Mitsuba image {ref.shape} vs ours {out.radiance.shape}")
    light_px = sees_rect_light(prep.runtime, prep.camera, out.depth)
    if prep.max_depth:
        light_px |= mirrored_emitters(prep.runtime, prep.camera, prep.max_depth)
    mask, excluded = comparison_mask(prep.runtime, out.object_id, light_px)
    rep = compare(out.radiance, ref, mask)
    lr_cov = lrms(out.radiance, ref, out.object_id >= 0)
    bias = float(luminance(out.radiance)[mask].mean() / luminance(ref)[mask].mean() - 1.0)
    return Result(prep.name, kind, out.radiance, ref, mask, excluded, rep, t_ours, t_mi,
                  ours_settings, mi_settings, lr_cov, bias)


# ============================================================================ report


def side_by_side(res: Result, upscale: int = 1) -> np.ndarray:
    """[ours | Mitsuba | error heatmap] as a linear image for ``write_image`` (exposure baked in:
    the 99th percentile of the reference luminance maps to 0.8; the heatmap is yellow at an
    error of 5 % of the mean reference luminance, black outside the mask)."""
    y = luminance(res.ref)[res.mask]
    k = 0.8 / max(float(np.percentile(y, 99)), 1e-12)
    heat = error_heatmap(res.ours, res.ref, mask=res.mask, scale=0.05 * float(y.mean()))
    gap = np.ones((res.ours.shape[0], 2, 3), dtype=np.float32)
    img = np.concatenate([res.ours * k, gap, res.ref * k, gap, heat], axis=1)
    img = np.clip(img, 0.0, 1.0).astype(np.float32)
    if upscale > 1:
        img = np.repeat(np.repeat(img, upscale, axis=0), upscale, axis=1)
    return img


def _fmt_time(t: float | None) -> str:
    return "--" if t is None else f"{t:.1f}"


def _load() -> str:
    try:
        return ", ".join(f"{x:.1f}" for x in os.getloadavg())
    except OSError:
        return "unknown"


def _git_rev() -> str:
    """Short HEAD, plus a note when the code this run imported differs from it."""
    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(mb.REPO_ROOT), *args], capture_output=True, text=True,
                              check=True).stdout.strip()

    try:
        rev = git("rev-parse", "--short", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no", "--", "engine", "workers", "api_schemas",
                    "samples", "bench")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return f"{rev} (with uncommitted changes)" if dirty else rev


def table_rows(results: list[Result]) -> tuple[list[str], list[str]]:
    """The results table's rows and the sample-count table's rows (markdown)."""
    rows = []
    for r in results:
        rep = r.report
        rmse = ", ".join(f"{x:.2e}" for x in rep.rmse)
        rows.append(
            f"| {r.scene} | {r.kind} | **{100 * rep.lrms:.2f} %** | {100 * r.threshold:g} % | "
            f"{'yes' if r.passed else '**NO**'} | {rmse} | {rep.psnr:.1f} | "
            f"{100 * rep.fraction_over_5pct:.2f} % | {rep.n_pixels} ({r.excluded} excl.) | "
            f"{_fmt_time(r.ours_seconds)} | {_fmt_time(r.mi_seconds)} | {100 * r.mean_bias:+.3f} % | "
            f"{100 * r.lrms_covered:.2f} % |")
    settings = [f"| {r.scene} | {r.kind} | {r.ours_settings} | {r.mi_settings} |" for r in results]
    return rows, settings


def write_doc(results: list[Result], extras: list[str], budget: Budget, total_seconds: float,
              rev: str) -> None:
    import mitsuba as mi_mod

    rows, settings = table_rows(results)
    imgs = "\n".join(f"![{r.scene} {r.kind}](img/crosscheck/{r.scene}_{r.kind}.png)\n\n"
                     f"*{r.scene}, {r.kind}: ours | Mitsuba | |error| (yellow = 5 % of mean luminance)*\n"
                     for r in results)
    text = f"""# Reference renderer vs Mitsuba 3

The reference renderer (`engine/reference.py`) is the yardstick of every image-based
technique in this project, so it is itself checked against an independent renderer,
Mitsuba {mi_mod.__version__} (`{mb.MITSUBA_VARIANT}`), on scenes both
can express: diffuse ones, and a Cornell box with a mirror sphere and a glossy box. This page is
written by `python -m bench.mitsuba_crosscheck`; the same comparisons run at small resolution
in `tests/engine/test_mitsuba_crosscheck.py` (part of `make test`).

Acceptance: direct lighting within **LRMS 1 %** of Mitsuba's `direct`
integrator, and with the indirect term on, within **LRMS 3 %** of Mitsuba's `path`; on the
Cornell box with a mirror sphere and a glossy box, where light also reaches the walls through the
mirror and the glossy lobe (caustic paths), within **LRMS 1.5 %** of `path`.

## Results (full size)

Image {budget.res} x {budget.res} (the directional sphere: 48 x 48, its reference's size; the mirror / glossy
box: {SCENE_BUDGET["cornell_mirror_glossy"].res} x {SCENE_BUDGET["cornell_mirror_glossy"].res}, see Scenes).
LRMS, RMSE (R, G, B), PSNR of the tone-mapped images and the fraction of pixels whose
luminance error exceeds 5 % of the mean are `engine.metrics.compare(ours, mitsuba, mask)`.
Times are wall-clock seconds on this machine (2 cores), Mitsuba multi-threaded. "mean" is
`mean(Y_ours) / mean(Y_mitsuba) - 1` over the compared pixels: a convention error (a factor
of pi, a wrong light unit, a wrong reflectance) shows there, noise hardly does. "all px" is
LRMS over every covered pixel, the excluded emitter pixels included (see below why it is not
the criterion; it is dominated by the luminaire's outline).

| scene | kind | LRMS | limit | pass | RMSE R, G, B | PSNR dB | > 5 % | pixels | ours s | Mitsuba s | mean | all px |
|---|---|---|---|---|---|---|---|---|---|---|---|---|
{chr(10).join(rows)}

Sample counts:

| scene | integrator | ours | Mitsuba |
|---|---|---|---|
{chr(10).join(settings)}

{chr(10).join(extras)}

Run: commit `{rev}` at the start, {platform.machine()}, Python {platform.python_version()},
total {total_seconds / 60:.1f} min, load average {_load()} at the end (a machine shared with
other jobs makes the times longer, never the errors larger).

## Scenes

- **cornell_box**: we load `samples/scenes/cornell_box.json`; Mitsuba loads its own
  `../shared/data/cornell-box-mitsuba/cbox-rgb.xml` unchanged (only the integrator is swapped
  and the sampler of a copy of its sensor, see below), so the JSON translation (meshes, RGB
  reflectances, light, camera) is checked together with the renderer. Mitsuba's light is the
  luminaire mesh as an area emitter; ours is the rect light at the same place (emitting down)
  plus the luminaire with an emission that is seen but lights nothing.
- **spheres_box**: built in `bench/mitsuba_crosscheck.py` (`SPHERES_BOX`): an icosphere, a box
  rotated 30 degrees and a back wall on a floor, a point light and a rect light. Converted to
  Mitsuba by `bench/mitsuba_bridge.py`: our exact world-space triangles and corner normals as
  PLY meshes, `diffuse` BSDFs, `point` emitter, the rect light as a `rectangle` with a
  one-sided `area` emitter and a black BSDF (it sits above everything and outside the view, so
  that it being a real surface in Mitsuba changes nothing). It is asymmetric on purpose: the
  test checks that the mirrored Mitsuba image is far worse than the unmirrored one.
- **directional_sphere**: `samples/scenes/mitsuba_directional_sphere.json` (meshes copied to
  `samples/meshes/mitsuba_ref/`) against Mitsuba's stored reference
  `../shared/data/mitsuba-ref-directional-sphere/refs/test_directional_ref_rgb.exr`, the
  32,000-spp mean of the `direct` integrator (3 channels R, G, B: the `moment` integrator's
  second moments are in the separate `_var` file). For `path` there is no stored image, so
  Mitsuba renders its own test scene file with `path`.
- **cornell_mirror_glossy**: `samples/scenes/cornell_mirror_glossy.json`, the Cornell box (same
  meshes, reflectances and light as `cornell_box`) with a mirror sphere (`kr` 0.9) in place of the
  short box and a glossy tall box (`kd` + `kg` 0.4, exponent 60), converted by the bridge: the
  mirror becomes a `conductor` (`material = "none"`, `specular_reflectance = kr`), the glossy
  material the bridge's `ibr_phong` plugin (a Python BSDF with exactly our
  `kd / pi + kg (g + 2) / (2 pi) cos^g` lobe, checked against a quadrature in the test), rendered
  in `llvm_ad_rgb`. The light is a rect light seen directly (no emissive luminaire) with a black
  housing 0.4 mm behind it, so that diffuse rays find the same black behind the light in both
  renderers (for Mitsuba the light is a black rectangle itself). Checked with `path` only:
  Mitsuba's `direct` stops after one bounce, our direct-only renders follow mirror chains.
  Rendered at 24 x 24 with 65536 paths per pixel (Mitsuba 262144 spp): the caustics are rare,
  bright path events for both unidirectional path tracers, about 3 x the per-path noise of the
  diffuse box, and LRMS, a per-pixel RMS, needs many paths per pixel, not many pixels.

## Conventions found on the way

- **Mitsuba's default fov is not 45 degrees.** The floating-sphere sensor sets no `fov`, so
  Mitsuba derives it from its default 50 mm focal length on a film with the 35 mm diagonal:
  `x_fov = 2 atan(sqrt(36^2 + 24^2) / sqrt(2) / 100) = 34.0221` degrees on the 48 x 48 film
  (square, so it is also our vertical `fov_y_deg`). With 45 degrees the LRMS was 67 %.
- **Orientation**: Mitsuba's `look_at` frame points camera +x to the image's left and flips
  the film x back, so image column 0 lies toward `cross(up, forward)`, as ours; `mi.render`
  returns rows top to bottom. A mirrored image gives LRMS of tens of percent (tested).
- **fov axis**: ours is vertical; the bridge sets `fov_axis = "y"`. The Cornell box file uses
  `fov_axis = "smaller"`, which is the vertical one for a square film.
- **Depth**: our `indirect_bounces = B` (next-event estimation at the camera hit and at B
  path vertices) is Mitsuba `path` with `max_depth = B + 2`; here B = {BOUNCES} (max_depth 6,
  the Cornell box file's default).
- **Sampler**: Mitsuba's scene files use the `independent` sampler. The comparison renders
  through a copy of each file's sensor (same fov, frame, film, box filter) with Mitsuba's
  `multijitter` sampler: both are unbiased, but at equal time the stratified one has about
  3 x less noise on pixel edges and penumbrae, and noise is what limits these numbers.
- **Emitter pixels are excluded** (the `excl.` column: pixels seeing the Cornell box
  luminaire or next to one). The luminaire is about 100 x brighter than the surfaces it lights:
  its pixels would inflate `mean(Y_ref)`, the LRMS denominator, making the check laxer, and its
  outline pixels carry a coverage fraction times that radiance, whose anti-aliasing noise alone
  exceeds 1 % LRMS at any affordable sample count. Its radiance is the same constant in both
  files. No other pixels are excluded (the directional sphere's far edge, the "horizon", needs
  no special treatment: both renderers box-filter partial pixels identically). Uncovered pixels
  (centre ray misses all geometry) are outside the mask, as the error metric specifies (`docs/algorithms.md`).
- **Lights seen directly or in a mirror are excluded the same way**: pixels whose centre ray meets
  a rect light, and pixels any of whose 64 samples sees an emitter through mirrors (a render of
  ours with only the mirror lobes and emission left), with their 3 x 3 neighbourhoods. The mirror
  sphere shows the light as a tiny image 100 x brighter than the room: at 12 x 12 one such pixel
  alone was 8.7 % LRMS of anti-aliasing noise. The light's radiance is a constant both renderers
  take from the same number, checked on its own (emission-only renders agree to 0.3 %).

## What limits the numbers

Both renderers agree in the mean (the "mean" column); what is left is Monte Carlo noise,
which LRMS (a per-pixel RMS) does not average away. For `direct`, our noise comes from stratified
anti-aliasing on silhouettes and from the g x g jittered rect-light grid in penumbrae; for
`path`, from the indirect paths. The noise floor of each number can be read from the heatmaps:
speckle without structure. A convention error shows as structure instead (a shifted silhouette,
a whole wall off by a constant factor).

For **cornell_mirror_glossy** the remaining difference is noise too (the mean agrees within
0.2 %; before camera, mirror and glossy rays saw rect lights, engine 0.3.0 at commit `d72a196`,
our render of this box was 8.9 % darker over the compared pixels: the ceiling 22 %, the glossy
box 27 %, the floor and walls 5-7 %, at 32 x 32 with 8192 paths per pixel), but noise of a
harder kind: light that reaches a wall through the mirror sphere is found
only by a diffuse path that happens to hit the sphere and then the light's small, bright image in
it, in both renderers (neither can sample a light through a mirror), and light through the glossy
box is found by our paths only by BSDF sampling, where Mitsuba also samples the light (MIS), so
our per-path noise there is higher. Remaining systematic differences, each well under the noise:
along camera chains our mirror and glossy segments do not count against `indirect_bounces`, so a
surface seen in the sphere or the glossy box gets one segment more than Mitsuba's `max_depth`
(Mitsuba's mean over the compared pixels grows 1.3 % from max_depth 6 to 7 and 1.3 % more from 7
to 10, so with B = 6, max_depth 8, one segment more adds roughly 0.4 %, and only on the pixels
that see the sphere or the box); and Mitsuba's
rectangle light is a black, opaque surface where ours passes diffuse rays (the housing makes
both see black there).

## Images

{imgs}
## Reproduce

```
python -m bench.mitsuba_crosscheck            # full size, writes this page and docs/img/crosscheck/
python -m pytest tests/engine/test_mitsuba_crosscheck.py   # small resolution, < 3 min
```

Mitsuba is a dev dependency (`pip install -e '.[dev]'`); the scalar `{mb.MITSUBA_VARIANT}` variant needs no
LLVM; the mirror / glossy box is rendered in `llvm_ad_rgb`, which needs Debian's `libllvm19`
(`apt-get install libllvm19`; `bench/mitsuba_bridge.py` finds it, or set `DRJIT_LIBLLVM_PATH`).
The shared data folder is found at `../shared/data` beside the repository, or at
`$IBR_SHARED_DATA`.
"""
    DOC.write_text(text)


def main(argv: list[str] | None = None) -> int:
    from engine.imageio import write_image

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--res", type=int, default=FULL.res)
    ap.add_argument("--scale", type=float, default=1.0, help="multiply every sample count (quick runs)")
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--no-doc", action="store_true", help="print the numbers only")
    args = ap.parse_args(argv)

    def sc(n: int, lo: int = 1) -> int:
        return max(lo, int(round(n * args.scale)))

    def scaled(b: Budget, res: int) -> Budget:
        return replace(b, res=res, ours_spp=sc(b.ours_spp), ours_path_spp=sc(b.ours_path_spp),
                       ours_paths=sc(b.ours_paths), mi_direct_spp=sc(b.mi_direct_spp), mi_path_spp=sc(b.mi_path_spp))

    budget = scaled(FULL, args.res)
    budgets = {name: scaled(b, b.res if args.res == FULL.res else args.res) for name, b in SCENE_BUDGET.items()}
    t_start = time.perf_counter()
    rev = _git_rev()  # the code imported now is the code measured
    results: list[Result] = []
    extras: list[str] = []
    if not args.no_doc:
        IMG_DIR.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as td:
        for name in args.scenes.split(","):
            b = budgets.get(name, budget)
            prep = prepare(name, b.res, td)
            renderer = ReferenceRenderer(prep.runtime)
            for kind in prep.kinds:
                r = run(prep, kind, b, renderer=renderer)
                results.append(r)
                print(f"{name:20s} {kind:6s} LRMS {100 * r.report.lrms:6.3f} %  mean {100 * r.mean_bias:+.3f} %  "
                      f"(limit {100 * r.threshold:.1f} %)  fraction>5% {100 * r.report.fraction_over_5pct:.2f} %"
                      f"  ours {r.ours_seconds:.1f} s  mitsuba {_fmt_time(r.mi_seconds)} s", flush=True)
                if not args.no_doc:
                    up = max(1, 256 // r.ours.shape[0])
                    write_image(IMG_DIR / f"{name}_{kind}.png", side_by_side(r, up))
            if prep.direct_reference is not None:
                # does this machine's Mitsuba reproduce the stored reference?
                mr = mb.render(prep.mi_scene, "direct", spp=budget.mi_direct_spp, sensor=prep.mi_sensor)
                direct = next(r for r in results if r.scene == name and r.kind == "direct")
                lr = compare(mr.radiance, prep.direct_reference, direct.mask).lrms
                line = (f"Sanity check: Mitsuba {mb.mitsuba().__version__} `direct` on this machine "
                        f"({budget.mi_direct_spp} spp, multijitter, {mr.seconds:.1f} s) vs the stored "
                        f"reference of `{name}`: LRMS {100 * lr:.2f} %.")
                extras.append(line)
                print(line, flush=True)
    total = time.perf_counter() - t_start
    if args.no_doc:
        rows, settings = table_rows(results)
        print("\n".join(rows + [""] + settings))
        print(f"commit {rev}, total {total / 60:.1f} min, load average {_load()}", flush=True)
    else:
        write_doc(results, extras, budget, total, rev)
        print(f"wrote {DOC.relative_to(mb.REPO_ROOT)} and {IMG_DIR.relative_to(mb.REPO_ROOT)}/", flush=True)
    failed = [r for r in results if not r.passed]
    for r in failed:
        print(f"FAILED: {r.scene} {r.kind}: LRMS {100 * r.report.lrms:.3f} % >= {100 * r.threshold:.1f} %")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

