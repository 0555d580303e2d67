"""Bit-identity digests of the engine's images: proves that a restructuring changed no output.

Run from the repository root::

    python -m bench.image_digest --out run.json              # render everything, write the digests
    python -m bench.image_digest --compare base.json         # render, compare with a saved run

Renders a small, fixed set of outputs (48x40 to 96x80 pixels, fixed seeds, a fixed numba thread
count) with every renderer and light kind, and records a digest per output array: SHA-256 of the
array's bytes, with its dtype and shape. The JSON is ``{name: "dtype shape sha256"}``; the arrays
themselves go to an ``.npz`` beside it, so a comparison can say how large a difference is.

What is covered (section / names):

- ``reference``: the reference renderer on the sample scenes -- direct light only
  (``mirror_box``, one point sample per pixel and jittered), mirror and glossy reflections
  (``mirror_box``, ``teapot_glossy``), a rect light (``cornell_box``) with direct light and
  with path-traced indirect bounces, a point + rect light (``teapot_spheres``), a directional
  light (``mitsuba_directional_sphere``), an orthographic camera. Every AOV (radiance, depth,
  normal, object / material ids).
- ``ldc``: ``mirror_box``, ``teapot_glossy`` and ``teapot_spheres`` (ten and more layers, a
  rect light) -- the LDC bake at resolution 64 and the LLF
  bake (every baked array), then the LDC renderer with ``ldc``, ``ldc+llf`` and ``ldc+ibrt:2``,
  each hole fill (``ibrt``, ``raycast``, ``none``), from two views off the LDC axes, plus a
  2x2-supersampled render; every result array (radiance, depth, normal, ids, provenance,
  hole mask).
- ``relight``: a dataset generated from ``teapot_glossy`` (and the same lights without the
  teapot), baked four ways (tiled float16 = the default, pixel-major, float32, low-rank) and
  relit with a point, a directional, a rect and an environment light, a light exactly at a
  dataset light (the exact path) and a mix; the composite of the teapot into a plate.
- ``walkthrough``: a low-quality bake of ``cornell_animated`` (animated objects and light,
  path-traced indirect light, a path view space) and of ``static_room`` (a polygon view space,
  two rect lights), and two frames of each (at two times in the animation) with each fill mode.

Timing dicts, counters and reports are not digested (they are not images); every numeric
field of a result or bake dataclass is. Long sequences (the LLF's views) get one digest per
field over all items in order; short ones (the LDC's three axes) one per item.

A/B across revisions (e.g. a redesign against the commit before it)::

    git worktree add /tmp/wt-base REV                 # detached checkout of the old revision
    cp bench/image_digest.py /tmp/wt-base/bench/
    cd /tmp/wt-base && PYTHONPATH=$PWD python -m bench.image_digest --out /tmp/digest_base.json
    cd - && python -m bench.image_digest --compare /tmp/digest_base.json --out /tmp/digest_new.json

The engine modules are imported from a list of candidate locations (the layout before the engine
was split by technique, e.g. ``engine/ldc_render.py``, and after it), so this file runs unchanged
at either revision. ``--compare`` prints ``same`` / ``DIFF`` / ``missing`` per name (with the
largest absolute difference and the number of differing values when the baseline's .npz is
there) and exits 1 on any difference or missing name; names only in the new run are listed as
``new``. ``--only SECTION[,SECTION]`` renders part of the set (and compares only that part).
Every project module must come from the checkout the script is in (it stops otherwise): the
virtualenv's editable install points at another checkout, which would supply any module this
one lacks.

Two runs give the same digests, and so do 1 and 2 numba threads (``--threads``); the count is
fixed all the same. With numba's caches warm the whole set takes about 10 s on 2 cores; in a
fresh checkout compiling the kernels takes about 5 minutes more.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import importlib
import json
import math
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SECTIONS = ("reference", "ldc", "relight", "walkthrough")
SKIP_FIELDS = {"timings"}  # wall-clock times: never identical
SEQUENCE_ITEMS = 4  # sequences up to this long get a name per item, longer ones one name per field


# ----------------------------------------------------------------------------- engine, any layout

# Where each engine module may live, newest layout first: after the split by technique
# (engine/newviews, engine/relighting, engine/walkthrough), then possible finer splits, then the
# flat layout before it.
CANDIDATES = {
    "renderer": ("engine.newviews.renderer", "engine.ldc_render"),
    "ldc": ("engine.newviews.ldc", "engine.ldc"),
    "llf": ("engine.newviews.llf", "engine.llf"),
    "effects": ("engine.newviews.effects", "engine.effects"),
    "relight": ("engine.relighting.relight", "engine.relighting.lights", "engine.relighting.dataset",
                "engine.relighting.bake", "engine.relighting.kernel", "engine.relighting", "engine.relight"),
    "generate": ("engine.relighting.generate", "engine.relight_gen"),
    "composite": ("engine.relighting.composite", "engine.composite"),
    "walkthrough": ("engine.walkthrough.bake", "engine.walkthrough"),
    "reconstruct": ("engine.walkthrough.reconstruct",),
    "viewspace": ("engine.walkthrough.viewspace",),
}


def _in_checkout(module: str) -> bool:
    """Whether ``module`` is a file of this checkout. Asked before importing: the virtualenv's
    editable install maps the project's packages to another checkout, whose copy of a module this
    one lacks (``engine.newviews`` at a revision from before it existed) would otherwise be
    imported in its place."""
    path = ROOT.joinpath(*module.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def _import(module: str):
    """The module, or None when this checkout does not have it."""
    return importlib.import_module(module) if _in_checkout(module) else None


def check_origin() -> None:
    """Every project module loaded so far comes from this checkout."""
    stray = sorted(name for name, mod in list(sys.modules.items())
                   if name.split(".")[0] in ("engine", "workers", "api_schemas", "samples")
                   and getattr(mod, "__file__", None) and not Path(mod.__file__).resolve().is_relative_to(ROOT))
    if stray:
        raise SystemExit(f"modules from outside {ROOT}: {', '.join(stray)} (run with PYTHONPATH={ROOT})")


def engine(kind: str, *names: str):
    """The objects ``names`` from the first candidate module of ``kind`` that has each of them."""
    found = []
    for name in names:
        for module in CANDIDATES[kind]:
            mod = _import(module)
            if mod is not None and hasattr(mod, name):
                found.append(getattr(mod, name))
                break
        else:
            raise ImportError(f"{name} is in none of {', '.join(CANDIDATES[kind])}")
    return found[0] if len(names) == 1 else found


def configure_numba(threads: int) -> int:
    """The engine's numba configuration first (its threading layer must be set before the thread
    pool starts), then a fixed thread count."""
    if _import("engine._numba_setup") is None:
        importlib.import_module("engine")  # before the split, engine/__init__.py configured numba
    import numba

    threads = min(threads, numba.config.NUMBA_NUM_THREADS)
    numba.set_num_threads(threads)
    return threads


# ----------------------------------------------------------------------------- digests


def _leaves(obj, name: str) -> Iterator[tuple[str, np.ndarray]]:
    """(name, array) of every array and number in a result / bake object, depth first."""
    if obj is None or isinstance(obj, (str, bytes, dict)):
        return  # None, labels, and the dicts of timings, counts, reports and parameters
    if isinstance(obj, np.ndarray):
        yield name, obj
    elif isinstance(obj, (bool, int, float, np.generic)):
        yield name, np.asarray(obj)
    elif dataclasses.is_dataclass(obj):
        for f in dataclasses.fields(obj):
            if f.name not in SKIP_FIELDS:
                yield from _leaves(getattr(obj, f.name), f"{name}.{f.name}")
    elif isinstance(obj, (tuple, list)):
        if all(isinstance(x, (bool, int, float, np.generic)) for x in obj):
            yield name, np.asarray(obj)
        elif len(obj) <= SEQUENCE_ITEMS:
            for i, x in enumerate(obj):
                yield from _leaves(x, f"{name}[{i}]")
        else:
            for x in obj:  # repeated names: Digests.add hashes the items in order under one name
                yield from _leaves(x, f"{name}[*]")
    else:
        raise TypeError(f"{name}: don't know how to digest a {type(obj).__name__}")


class Digests:
    """The arrays of one run by name (a name may hold several arrays, hashed in order)."""

    def __init__(self) -> None:
        self.arrays: dict[str, list[np.ndarray]] = {}

    def add(self, name: str, obj) -> None:
        """Every array of ``obj`` (an array, or a result / bake object: its fields)."""
        if isinstance(obj, np.ndarray):
            self.arrays.setdefault(name, []).append(np.array(obj))
            return
        for leaf, a in _leaves(obj, name):
            self.arrays.setdefault(leaf, []).append(np.array(a))  # a copy: later code may reuse buffers

    def digest(self, name: str) -> str:
        arrays = self.arrays[name]
        h = hashlib.sha256()
        for a in arrays:
            h.update(f"{a.dtype.str}{a.shape}".encode())
            h.update(np.ascontiguousarray(a).tobytes())
        if len(arrays) == 1:
            return f"{arrays[0].dtype} {arrays[0].shape} {h.hexdigest()}"
        dtypes = {str(a.dtype) for a in arrays}
        return f"{dtypes.pop() if len(dtypes) == 1 else 'mixed'} {len(arrays)} arrays {h.hexdigest()}"

    def digests(self) -> dict[str, str]:
        return {name: self.digest(name) for name in self.arrays}

    def flat(self, name: str) -> np.ndarray:
        """One array per name for the .npz: the array, or the items raveled and concatenated."""
        arrays = self.arrays[name]
        if len(arrays) == 1:
            return arrays[0]
        if len({a.dtype for a in arrays}) > 1:
            arrays = [a.astype(np.float64) for a in arrays]
        return np.concatenate([a.ravel() for a in arrays])


def _npz_key(name: str) -> str:
    return name.replace("/", "|")  # a '/' would be a folder inside the zip


def write(path: Path, d: Digests, meta: dict) -> None:
    path.write_text(json.dumps(d.digests(), indent=1, sort_keys=True) + "\n")
    arrays = {_npz_key(n): d.flat(n) for n in d.arrays}
    arrays["__meta__"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez_compressed(path.with_suffix(".npz"), **arrays)


def _difference(a: np.ndarray, b: np.ndarray) -> str:
    if a.shape != b.shape:
        return f"shape {a.shape} -> {b.shape}"
    if a.dtype.kind in "biuf" and b.dtype.kind in "biuf" and a.size:
        x, y = a.astype(np.float64), b.astype(np.float64)
        both_nan = np.isnan(x) & np.isnan(y)
        differ = (x != y) & ~both_nan
        mx = float(np.max(np.where(differ, np.abs(x - y), 0.0)))
        kind = "" if a.dtype == b.dtype else f" ({a.dtype} -> {b.dtype})"
        return f"max|diff| {mx:.3g}, {int(differ.sum())} of {a.size} values differ{kind}"
    return f"{a.dtype} -> {b.dtype}"


def compare(base_path: Path, d: Digests, sections: tuple[str, ...]) -> int:
    """Print same / DIFF / missing per name of the baseline (in the sections run); 1 on any
    difference or missing name."""
    base = json.loads(base_path.read_text())
    npz_path = base_path.with_suffix(".npz")
    npz = np.load(npz_path) if npz_path.exists() else None
    now = d.digests()
    base = {n: v for n, v in base.items() if n.split("/", 1)[0] in sections}
    bad = 0
    for name in sorted(base):
        if name not in now:
            print(f"missing  {name}")
            bad += 1
        elif now[name] == base[name]:
            print(f"same     {name}")
        else:
            detail = base[name] + " -> " + now[name]
            if npz is not None and _npz_key(name) in npz.files:
                detail = _difference(npz[_npz_key(name)], d.flat(name))
            print(f"DIFF     {name}: {detail}")
            bad += 1
    for name in sorted(set(now) - set(base)):
        print(f"new      {name}")
    n_same = sum(1 for n in base if now.get(n) == base[n])
    print(f"{n_same} of {len(base)} same, {bad} differ or missing, {len(set(now) - set(base))} new "
          f"(against {base_path})")
    return 1 if bad else 0


# ----------------------------------------------------------------------------- scenes and views


def load_sample(name: str):
    """(runtime scene, the scene file's camera) of a sample scene."""
    from api_schemas import load_scene_file
    from samples import SAMPLES_DIR, sample_path
    from workers.scene_loader import directory_resolver, load_scene

    ls = load_scene(load_scene_file(sample_path(name)), directory_resolver(SAMPLES_DIR))
    return ls.runtime, ls.camera


def sized(cam, w: int, h: int):
    return dataclasses.replace(cam, width=w, height=h)


def orbit(cam, az_deg: float, el_deg: float, w: int, h: int):
    """The camera turned by ``az_deg`` about the look-at point's vertical and raised by ``el_deg``."""
    eye, at = np.asarray(cam.eye, float), np.asarray(cam.look_at, float)
    off = eye - at
    a, e = math.radians(az_deg), math.radians(el_deg)
    off = np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]]) @ off
    r, horiz = float(np.linalg.norm(off)), math.hypot(off[0], off[2])
    el = math.asin(off[1] / r) + e
    off = np.array([off[0] / horiz * math.cos(el), math.sin(el), off[2] / horiz * math.cos(el)]) * r
    return dataclasses.replace(cam, eye=tuple(float(x) for x in at + off), width=w, height=h)


# ----------------------------------------------------------------------------- sections


def run_reference(d: Digests) -> None:
    from engine.reference import ReferenceParams, ReferenceRenderer

    direct = ReferenceParams(spp=1, max_depth=0, area_light_samples=4, seed=3)
    cases = [
        # (scene, name, params, camera transform)
        ("mirror_box", "direct_point_sampled", ReferenceParams(spp=1, max_depth=0, pixel_jitter=False), None),
        ("mirror_box", "direct_jittered", ReferenceParams(spp=2, max_depth=0, seed=5), None),
        ("mirror_box", "reflections", ReferenceParams(spp=2, max_depth=4, glossy_samples=4, seed=1), None),
        ("mirror_box", "orthographic", ReferenceParams(spp=1, max_depth=2, glossy_samples=2),
         lambda c: dataclasses.replace(c, kind="orthographic", ortho_height=4.0)),
        ("teapot_glossy", "glossy", ReferenceParams(spp=1, max_depth=3, glossy_samples=6, seed=2), None),
        ("cornell_box", "rect_direct", direct, None),
        ("cornell_box", "path_traced", ReferenceParams(spp=1, max_depth=1, area_light_samples=4,
                                                       indirect_samples=4, indirect_bounces=2, seed=4), None),
        ("teapot_spheres", "point_and_rect", ReferenceParams(spp=1, max_depth=2, glossy_samples=2,
                                                             area_light_samples=4, seed=6), None),
        ("mitsuba_directional_sphere", "directional", direct, None),
    ]
    renderers: dict[str, tuple] = {}
    for scene, label, params, transform in cases:
        if scene not in renderers:
            sc, cam = load_sample(scene)
            renderers[scene] = (ReferenceRenderer(sc), cam)
        ren, cam = renderers[scene]
        cam = sized(cam, 96, 80)
        if transform is not None:
            cam = transform(cam)
        d.add(f"reference/{scene}/{label}", ren.render(cam, params))


LDC_RES = 64
LLF_F, LLF_RES = 2, 24  # 18 directions
LDC_METHODS = ("ldc", "ldc+llf", "ldc+ibrt:2")
LDC_FILLS = ("ibrt", "raycast", "none")
LDC_SCENES = ("mirror_box", "teapot_glossy", "teapot_spheres")


def run_ldc(d: Digests) -> None:
    from engine.raycast import EmbreeCaster
    from engine.reference import ReferenceParams

    renderer_cls = engine("renderer", "LDCViewRenderer")
    bake_ldc = engine("ldc", "bake_ldc")
    bake_llf = engine("llf", "bake_llf")
    analyze = engine("effects", "analyze")
    for scene in LDC_SCENES:
        sc, cam = load_sample(scene)
        caster = EmbreeCaster(sc)
        plan = analyze(sc)
        ldc = bake_ldc(sc, caster, LDC_RES, plan=plan)
        d.add(f"ldc/{scene}/bake_ldc", ldc)
        llf = None
        if plan.needs_llf:
            llf = bake_llf(sc, caster, LLF_F, LLF_RES, params=ReferenceParams(max_depth=2, glossy_samples=4))
            d.add(f"ldc/{scene}/bake_llf", llf)
        ren = renderer_cls(sc, ldc, llf, plan)
        views = {"view_a": orbit(cam, -23.0, 7.0, 96, 80), "view_b": orbit(cam, 31.0, -6.0, 96, 80)}
        for vname, view in views.items():
            for method in LDC_METHODS:
                if method != "ldc" and llf is None:
                    continue
                for fill in LDC_FILLS:
                    d.add(f"ldc/{scene}/{vname}/{method}/fill_{fill}", ren.render(view, method, fill=fill))
        d.add(f"ldc/{scene}/view_a/ldc+ibrt:1/supersample_2",
              ren.render(sized(views["view_a"], 48, 40), "ldc+ibrt:1", supersample=2))


def run_relight(d: Digests) -> None:
    from engine.reference import ReferenceParams

    LightPlacement, generate_dataset, scene_without_objects, object_mask = engine(
        "generate", "LightPlacement", "generate_dataset", "scene_without_objects", "object_mask")
    PointLight, DirectionalLight, RectLight, EnvironmentLight, bake_dataset, relight = engine(
        "relight", "PointLight", "DirectionalLight", "RectLight", "EnvironmentLight", "bake_dataset", "relight")
    composite, active_region_around = engine("composite", "composite", "active_region_around")

    sc, cam = load_sample("teapot_glossy")
    cam = sized(cam, 64, 56)
    params = ReferenceParams(spp=1, max_depth=2, glossy_samples=3, seed=0)
    ds = generate_dataset(sc, cam, LightPlacement(region="hemisphere", spacing_deg=20.0), params)  # 62 lights
    d.add("relight/dataset/teapot_glossy", ds)
    same_lights = LightPlacement.from_dict(ds.meta["resolved_placement"])
    ds_bg = generate_dataset(scene_without_objects(sc, ["teapot"]), cam, same_lights, params)
    d.add("relight/dataset/floor_only", ds_bg)

    bakes = {  # name: (expected layout, bake_dataset keywords)
        "tiled_f16": ("tiled", {}), "pixel_major": ("pixel_major", {"layout": "pixel_major"}),
        "tiled_f32": ("tiled", {"half": False}),
        "lowrank": ("lowrank", {"compress": 0.1}),  # 10 % relative RMS: about half the float16 store
    }
    baked = {}
    for bname, (layout, kw) in bakes.items():
        baked[bname] = bake_dataset(ds, **kw)
        if baked[bname].layout != layout:
            raise RuntimeError(f"relight bake {bname}: layout {baked[bname].layout}, expected {layout}")
        d.add(f"relight/bake/{bname}", baked[bname])

    c = np.asarray(ds.sphere_center, float)
    r = float(baked["tiled_f16"].sphere_radius)
    k = ds.light_positions.shape[0]
    env = np.random.default_rng(0).uniform(0.0, 1.0, (16, 32, 3))
    env[8:] = 0.0  # sky only
    point = PointLight(tuple(c + r * np.array([0.45, 0.75, 0.5])), r * r)
    directional = DirectionalLight((-0.3, -1.0, -0.4), (1.0, 0.9, 0.8))
    s = 0.4 * r
    rect = RectLight(tuple(c + np.array([-s / 2, 0.8 * r, -s / 2])), (s, 0.0, 0.0), (0.0, 0.0, s), (3.0, 3.0, 3.0),
                     samples=9, seed=1)
    lights = {"point": point, "point_near": PointLight(tuple(c + r * np.array([-0.2, 0.4, 0.25])), (0.2, 0.3, 0.4)),
              "directional": directional, "rect": rect,
              "environment": EnvironmentLight(env, n_lights=24),
              "at_dataset_light": PointLight(tuple(ds.light_positions[k // 2]), tuple(ds.intensities[k // 2])),
              "mix": [point, directional, rect]}
    for bname, b in baked.items():
        for lname, light in lights.items():
            d.add(f"relight/{bname}/{lname}", relight(b, light))
    d.add("relight/tiled_f16/point_serial_kernel", relight(baked["tiled_f16"], point, serial=True))

    b_bg = bake_dataset(ds_bg)
    obj, bg = relight(baked["tiled_f16"], point), relight(b_bg, point)
    plate = relight(b_bg, directional).image
    om = object_mask(sc, cam, ["teapot"])
    out, _ = composite(obj, bg, plate, om, active_region_around(om, 4))
    d.add("relight/composite/teapot_into_plate", out)


# per scene: two frames (eye inside the view space, look-at point, time)
WALKTHROUGH_FRAMES = {
    "cornell_animated": {"frame_a": ((224.0, 273.0, 45.0), (278.0, 150.0, 420.0), 0.7),
                         "frame_b": ((334.0, 273.0, 45.0), (278.0, 150.0, 420.0), 2.9)},
    "static_room": {"frame_a": ((2.0, 1.6, 1.5), (6.0, 1.3, 4.5), 0.0),
                    "frame_b": ((3.0, 1.6, 4.0), (7.5, 1.0, 1.5), 0.0)},
}


def run_walkthrough(d: Digests) -> None:
    from api_schemas import load_scene_file
    from engine.scene import CameraParams
    from samples import SAMPLES_DIR, sample_path
    from workers.scene_loader import directory_resolver, load_animated_scene

    bake_walkthrough, walkthrough_preset, renderer_cls = engine(
        "walkthrough", "bake_walkthrough", "walkthrough_preset", "WalkthroughRenderer")
    fill_modes = engine("reconstruct", "FILL_MODES")
    PathSpace, PolygonSpace = engine("viewspace", "PathSpace", "PolygonSpace")
    params = walkthrough_preset("low", face_res=64, probe_res=8, indirect_samples=2, indirect_res_div=2,
                                area_light_samples=4, max_views=3, max_time_samples=3)
    for scene_name, frames in WALKTHROUGH_FRAMES.items():
        scene = load_scene_file(sample_path(scene_name))
        an = load_animated_scene(scene, directory_resolver(SAMPLES_DIR))
        vs = scene.view_space
        if vs.type == "path":
            space = PathSpace(np.asarray(vs.points, np.float64), vs.radius)
        else:
            space = PolygonSpace(np.asarray(vs.vertices, np.float64), vs.eye_height)
        bake = bake_walkthrough(an, space, params)
        d.add(f"walkthrough/{scene_name}/bake", bake)
        wr = renderer_cls(bake, an)
        for fname, (eye, at, t) in frames.items():
            cam = CameraParams("perspective", eye, at, (0.0, 1.0, 0.0), 64, 48, fov_y_deg=60.0)
            for fill in fill_modes:
                d.add(f"walkthrough/{scene_name}/{fname}/fill_{fill}", wr.render(cam, t, fill=fill))


RUNS = {"reference": run_reference, "ldc": run_ldc, "relight": run_relight, "walkthrough": run_walkthrough}


# ----------------------------------------------------------------------------- main


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, help="write the digests (JSON) and the arrays (.npz beside it)")
    ap.add_argument("--compare", type=Path, help="compare with a saved run; exit 1 on any difference")
    ap.add_argument("--only", default=",".join(SECTIONS), help=f"sections to run, of {','.join(SECTIONS)}")
    ap.add_argument("--threads", type=int, default=2, help="numba threads (default 2)")
    args = ap.parse_args(argv)
    sections = tuple(s for s in args.only.split(",") if s)
    if set(sections) - set(SECTIONS):
        ap.error(f"unknown sections {sorted(set(sections) - set(SECTIONS))}")
    t_start = time.perf_counter()

    def log(msg: str) -> None:
        print(f"{time.perf_counter() - t_start:7.1f}s {msg}", file=sys.stderr, flush=True)

    threads = configure_numba(args.threads)
    check_origin()
    rev = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                         text=True).stdout.strip()
    dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no", "engine"],
                           capture_output=True, text=True).stdout.strip()
    log(f"engine at {rev}{' (engine modified)' if dirty else ''}, {threads} numba threads")
    d = Digests()
    for s in sections:
        t0 = time.perf_counter()
        before = len(d.arrays)
        RUNS[s](d)
        check_origin()
        log(f"{s}: {len(d.arrays) - before} digests in {time.perf_counter() - t0:.1f} s")
    meta = {"rev": rev, "engine_modified": bool(dirty), "threads": threads, "sections": sections,
            "seconds": round(time.perf_counter() - t_start, 1)}
    if args.out:
        write(args.out, d, meta)
        log(f"wrote {args.out} and {args.out.with_suffix('.npz')}")
    if args.compare:
        return compare(args.compare, d, sections)
    if not args.out:
        for name, dig in d.digests().items():
            print(f"{dig}  {name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
