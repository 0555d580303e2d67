"""The ``ibr`` client commands: they talk to the API at ``--api`` / ``IBR_API_URL`` (default
http://127.0.0.1:8000, key from ``IBR_API_KEY``) and import no engine code, so the ``ibr-client``
distribution (clients/python/) installs them without numba, Embree or OpenImageIO.

``ibr scenes add|list|show|delete``, ``ibr calibrate`` (per-scene calibration for quality
contracts: ``ibr render --quality-error 0.05`` or ``--quality-ms 100`` instead of a method),
``ibr render`` (request a render, follow it with a progress bar, fetch the image; ``--method
ldc+llf`` renders from the scene's bake), ``ibr bake`` (bake a scene, ``--wait`` follows its
parts), ``ibr bakes list|show|delete``, ``ibr fetch``, ``ibr jobs list|show|cancel``, ``ibr batch``;
illumination datasets: ``ibr datasets upload|list|show|delete|generate|bake``, ``ibr relight``,
``ibr composite``; walkthroughs: ``ibr walkthrough`` (request, follow with a progress bar, fetch the
MP4 / frames; ``--quality-error`` / ``--quality-ms`` let the planner pick the bake preset and the fill
after ``ibr calibrate-walkthroughs``), ``ibr walkthroughs show|fetch|delete``. Local, no service:
``ibr schema``, ``ibr samples``. The service's ``ibr`` (service/cli.py) is this app plus the commands that run the
service or the engine in their own process.

Exit codes: 0 ok, 2 bad input (with a message naming the field or file), 3 the
service could not be reached or failed the request, 4 the job failed.
"""

from __future__ import annotations

import json
import re
import sys
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from functools import partial
from pathlib import Path
from typing import Annotated, Any, Literal, NoReturn, TypeVar, cast, get_args

import httpx
import pydantic
import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

from api_schemas import format_validation_error, load_scene_file, scene_json_schema
from api_schemas.datasets import DatasetManifest, FileUploadPublic, RelightPublic
from api_schemas.scene import MeshFileObject, Scene, SceneFileTooLargeError
from api_schemas.service import ArtifactManifest, BakePublic, JobPublic
from api_schemas.walkthrough import (
    DEFAULT_PATH_NOISES,
    WalkthroughCalibrationParams,
    WalkthroughCalibrationPublic,
    WalkthroughContractPublic,
    WalkthroughPublic,
)
from ibr_client.client import ApiError, Client, InvalidId, JobFailed, read_dataset_dir, with_sha256s
from samples import SAMPLES_DIR, sample_names, sample_path

T = TypeVar("T")

app = typer.Typer(add_completion=False, no_args_is_help=True, help="ibr-service: image-based rendering")


def say(msg: str) -> None:
    """A message for the user: stderr (stdout carries only results, so ``X=$(ibr ...)`` captures them)."""
    typer.echo(msg, err=True)


def fail(msg: str, code: int = 2) -> NoReturn:
    typer.echo(f"error: {msg}", err=True)
    raise typer.Exit(code)


def load_scene_arg(scene_arg: str) -> tuple[Scene, Path]:
    """A scene file path or the name of a sample scene -> (Scene, base directory)."""
    path = Path(scene_arg)
    if not path.exists() and scene_arg in sample_names():
        path = sample_path(scene_arg)
    if not path.is_file():
        fail(f"{scene_arg}: no such scene file or sample (samples: {', '.join(sample_names())})")
    try:
        scene = load_scene_file(path)
    except pydantic.ValidationError as exc:
        lines = [f"  {e['field']}: {e['message']}" for e in format_validation_error(exc)]
        fail(f"{path}: invalid scene\n" + "\n".join(lines))
    except (SceneFileTooLargeError, ValueError, OSError) as exc:
        fail(f"{path}: {exc}")
    base = path.parent.parent if path.parent.resolve() == (SAMPLES_DIR / "scenes").resolve() else path.parent
    return scene, base


@app.command()
def schema(output: Annotated[Path | None, typer.Option("-o", "--output")] = None) -> None:
    """Print (or write) the scene JSON Schema."""
    text = json.dumps(scene_json_schema(), indent=2, sort_keys=True) + "\n"
    if output is None:
        sys.stdout.write(text)
    else:
        output.write_text(text)


@app.command()
def samples() -> None:
    """List the sample scenes shipped with the service."""
    for n in sample_names():
        typer.echo(f"{n}\t{sample_path(n)}")


DEFAULT_API = "http://127.0.0.1:8000"
ApiOpt = Annotated[str, typer.Option("--api", envvar="IBR_API_URL", help="API base URL")]
KeyOpt = Annotated[str | None, typer.Option("--api-key", envvar="IBR_API_KEY", help="API key (Bearer)")]


# ============================================================================ client commands

scenes_app = typer.Typer(help="Scenes stored in the service", no_args_is_help=True)
jobs_app = typer.Typer(help="Jobs in the queues", no_args_is_help=True)
app.add_typer(scenes_app, name="scenes")
app.add_typer(jobs_app, name="jobs")
bakes_app = typer.Typer(help="Bakes (LDC + LLF) of stored scenes", no_args_is_help=True)
app.add_typer(bakes_app, name="bakes")


def fail_code(msg: str, code: int) -> int:
    typer.echo(f"error: {msg}", err=True)
    return code


def _client(api_url: str, api_key: str | None) -> Client:
    return Client(api_url, api_key=api_key)


def _call(fn: Callable[[], T]) -> T:
    """Run a client call; map API and connection errors to exit codes 2 / 3."""
    try:
        return fn()
    except ApiError as exc:
        _api_fail(exc)
    except InvalidId as exc:
        fail(str(exc))
    except httpx.InvalidURL as exc:
        fail(f"invalid URL: {exc}")
    except httpx.HTTPError as exc:
        fail(f"cannot reach the API: {exc}", code=3)


def _api_fail(exc: ApiError) -> NoReturn:
    """Exit for an API error: 4 when a job failed or was canceled, 2 for bad input (4xx), else 3."""
    if isinstance(exc, JobFailed):
        fail(str(exc), code=4)
    fail(str(exc), code=2 if 400 <= exc.status < 500 and exc.status not in (401, 403, 429) else 3)


def _scene_doc(scene_arg: str) -> tuple[dict[str, Any], dict[str, Path]]:
    """Scene JSON (validated locally first) and its mesh files, from a path or sample name."""
    sc, base = load_scene_arg(scene_arg)
    doc = sc.model_dump(mode="json", exclude_defaults=False)
    meshes = {o.path: base / o.path for o in sc.objects if isinstance(o, MeshFileObject)}
    for rel, p in meshes.items():
        if not p.is_file():
            fail(f"mesh file {rel} not found next to the scene ({p})")
    return doc, meshes


_IMPORT_SUFFIXES = {".gltf": "gltf", ".glb": "glb", ".obj": "obj"}


@scenes_app.command("add")
def scenes_add(scene: Annotated[str, typer.Argument(help="Scene JSON file or sample name, or a glTF 2.0 "
                                                         "(.gltf with its buffers, .glb) or OBJ (+ MTL) file "
                                                         "to import")],
               width: Annotated[int | None, typer.Option(help="Imports: image width of the camera")] = None,
               height: Annotated[int | None, typer.Option(help="Imports: image height of the camera")] = None,
               name: Annotated[str | None, typer.Option(help="Imports: the scene's name")] = None,
               api_url: ApiOpt = DEFAULT_API, api_key: KeyOpt = None) -> None:
    """Upload a scene (and its mesh files), or import a glTF / GLB / OBJ file (with the buffers and MTL
    files it names, read from beside it); prints the scene id. What an import left out or approximated
    is printed on stderr."""
    fmt = _IMPORT_SUFFIXES.get(Path(scene).suffix.lower())
    if fmt is None:
        if width is not None or height is not None or name is not None:
            fail("--width, --height and --name apply to imported files (.gltf, .glb, .obj) only")
        doc, meshes = _scene_doc(scene)
        with _client(api_url, api_key) as c:
            pub = _call(lambda: c.create_scene(doc, meshes or None))
        typer.echo(pub.id)
        return
    from producer.scene_import import companions

    path = Path(scene)
    if not path.is_file():
        fail(f"{scene}: no such file")
    data = path.read_bytes()
    files: dict[str, Path] = {}
    for rel in companions(fmt, data):
        p = path.parent / rel
        if not p.is_file():
            fail(f"{path.name} names {rel!r}, which is not beside it ({p})")
        files[rel] = p
    with _client(api_url, api_key) as c:
        kind = cast(Literal["gltf", "glb", "obj"], fmt)
        imp = _call(lambda: c.import_scene(kind, path, files, width=width, height=height, name=name))
    for w in imp.import_warnings:
        places = ", ".join(w.where) + (f", ... ({w.count} in all)" if w.count > len(w.where) else "")
        say(f"import: {w.feature}: {w.message} [{places}]")
    typer.echo(imp.id)


@scenes_app.command("list")
def scenes_list(api_url: ApiOpt = DEFAULT_API, api_key: KeyOpt = None) -> None:
    """List stored scenes."""
    with _client(api_url, api_key) as c:
        for s in _call(lambda: list(c.iter_scenes())):
            typer.echo(f"{s.id}  {s.name}  objects={s.n_objects} lights={s.n_lights}")


@scenes_app.command("show")
def scenes_show(scene_id: str, api_url: ApiOpt = DEFAULT_API, api_key: KeyOpt = None) -> None:
    """Show one scene as JSON."""
    with _client(api_url, api_key) as c:
        typer.echo(_call(lambda: c.get_scene(scene_id)).model_dump_json(indent=2))


@scenes_app.command("delete")
def scenes_delete(scene_id: str, api_url: ApiOpt = DEFAULT_API, api_key: KeyOpt = None) -> None:
    """Delete a scene (refused while a job uses it)."""
    with _client(api_url, api_key) as c:
        _call(lambda: c.delete_scene(scene_id))


def _bake_choice(ldc_resolution: int | None, llf_f: int | None, indirect_noise: float | None) -> dict[str, Any]:
    """The bake an LDC render or a calibration names (the service's defaults for what is not given):
    the same options pick the same bake as ``ibr bake`` with them."""
    bake: dict[str, Any] = {k: v for k, v in {"ldc_resolution": ldc_resolution, "llf_f": llf_f}.items()
                            if v is not None}
    if indirect_noise is not None:
        bake["indirect"] = {"noise": indirect_noise}
    return bake


def render_and_fetch(api_url: str, api_key: str | None, scene_id: str, params: dict[str, Any],
                     output: Path | None, fmt: str, wait: bool, camera: dict[str, Any] | None = None,
                     method: str | None = "reference", bake: dict[str, Any] | None = None,
                     missing_bake: str | None = None, max_error: float | None = None,
                     max_ms: float | None = None, best_effort: bool = False, verify: bool = False,
                     at_time: float | None = None, view: dict[str, Any] | None = None) -> None:
    with _client(api_url, api_key) as c:
        r = _call(lambda: c.render(scene_id, camera=camera, params=params or None, wait=2.0 if wait else 0.0,
                                   method=method, bake=bake or None,
                                   missing_bake="bake" if missing_bake == "bake" else None,
                                   max_error=max_error, max_ms=max_ms, best_effort=best_effort, verify=verify,
                                   time=at_time, view=view or None))
        typer.echo(f"artifact {r.artifact_key} ({r.status})", err=True)
        if r.contract is not None:
            typer.echo(_contract_line(r.contract), err=True)
            if r.contract.verification is not None:
                typer.echo(f"verification: job {r.contract.verification['job_id']} "
                           f"({r.contract.verification['state']}; its result has measured_error)", err=True)
        if r.bake is not None:
            typer.echo(f"waiting for bake {r.bake.key} ({r.bake.state}; follow it with "
                       f"'ibr bake {scene_id} --wait')", err=True)
        if r.artifact is None and not wait:
            if r.job is not None:
                typer.echo(r.job.id)
            return
        if r.artifact is None:
            with _bar("render") as update:
                show = _job_progress(update)
                manifest = _call(lambda: c.wait_render(r, on_progress=show))  # a failed job: JobFailed, exit 4
        else:
            manifest = r.artifact
        if manifest.result.get("timings"):
            t = manifest.result["timings"]
            typer.echo("timings: " + ", ".join(f"{k}={v:.3f}s" for k, v in t.items()
                                               if isinstance(v, int | float)), err=True)
        adaptive = manifest.result.get("adaptive")
        if isinstance(adaptive, dict):
            typer.echo(_adaptive_line(adaptive), err=True)
        achieved = (manifest.result.get("timings") or {}).get("render_wall")
        if r.contract is not None and isinstance(achieved, int | float):
            est = (manifest.result.get("contract") or {}).get("estimated_error", r.contract.estimated_error)
            est_s = "" if est is None else (f", estimated LRMS {est:.4f} (by the "
                                            f"{r.contract.estimated_error_source or 'calibration'})")
            typer.echo(f"achieved: {achieved * 1000:.1f} ms (predicted {r.contract.predicted_ms:.1f} ms){est_s}",
                       err=True)
        counts = manifest.result.get("counts") or {}
        if "hole_pixels" in counts:
            typer.echo(f"hole pixels: {counts['hole_pixels']}, provenance: {counts.get('provenance')}", err=True)
        if output is not None:
            data = _call(lambda: c.download(manifest.key, "exr" if fmt == "exr" else "png"))
            output.parent.mkdir(parents=True, exist_ok=True)
            output.write_bytes(data)
            typer.echo(str(output))


def _adaptive_line(a: dict[str, Any]) -> str:
    """One line on how a progressive reference render ended (the result's ``adaptive``)."""
    target = a.get("max_error")
    met = "" if target is None else f" (target {target * 100:g} % {'met' if a.get('target_met') else 'NOT met'})"
    return (f"estimated error {a['estimated_error'] * 100:.2f} %{met}, stopped by {a['stop_reason']} after "
            f"{a['passes']} passes, spp mean {a['spp_mean']:.1f} min {a['spp_min']} max {a['spp_max']} "
            f"(cap {a['spp_cap']}), {a['elapsed_ms']:.0f} ms")


def _contract_line(con: Any) -> str:
    """One line saying what a quality contract got."""
    if con.params and con.params.get("max_error") is not None:
        setting = f"{con.method} adaptive (told {con.params['max_error']:.4g}, cap {con.params['spp']} spp)"
    else:
        setting = con.method + (f" at {con.params['spp']} spp" if con.params else "")
    if con.view and con.view.get("supersample", 1) > 1:
        s = con.view["supersample"]
        setting += f", {s} x {s} samples per {'' if con.view.get('antialias') == 'uniform' else 'edge '}pixel"
    met = "meets the contract" if con.met else f"DOES NOT meet {', '.join(con.unmet)}: {con.reason}"
    bake = {"waited": ", after its bake", "best_available_now": ", the best available now (bake missing)"}.get(
        con.bake, "")
    return (f"plan: {setting} ({con.rule}{bake}); predicted LRMS {con.predicted_error:.4f}, "
            f"{con.predicted_ms:.1f} ms; {met}")


@app.command()
def render(
    scene: Annotated[str, typer.Argument(help="Scene id, scene JSON file, or sample name (uploaded first)")],
    output: Annotated[Path | None, typer.Option("-o", "--output", help="Save the image (.png or .exr)")] = None,
    spp: Annotated[int | None, typer.Option(help="Antialiasing samples per pixel")] = None,
    indirect: Annotated[int | None, typer.Option(help="Indirect paths per pixel")] = None,
    bounces: Annotated[int | None, typer.Option(help="Bounces per indirect path")] = None,
    seed: Annotated[int | None, typer.Option(help="Random seed")] = None,
    max_error: Annotated[float | None, typer.Option(
        help="Reference: render progressively until the estimated LRMS against the converged image is at most "
             "this, in (0, 1) (--spp is then the cap per pixel)")] = None,
    max_ms: Annotated[float | None, typer.Option(
        help="Reference: render progressively, stopping after this many milliseconds of render time")] = None,
    light_paths: Annotated[float | None, typer.Option(
        help="Reference: light paths per camera sample for caustics seen on diffuse surfaces (light through "
             "mirrors / glossy surfaces), in [0, 64]; 0: camera paths alone (default 1)")] = None,
    method: Annotated[str | None, typer.Option(help="reference (default), ldc, ldc+llf or ldc+ibrt:k (k = 0..8)")
                      ] = None,
    ldc_resolution: Annotated[int | None, typer.Option(help="LDC methods: the bake's LDC resolution")] = None,
    llf_f: Annotated[int | None, typer.Option(help="LDC methods: the bake's LLF subdivision f")] = None,
    indirect_noise: Annotated[float | None, typer.Option(
        help="LDC methods: the bake's noise target for indirect light, relative per sample (default 0.02)")] = None,
    bake_missing: Annotated[bool, typer.Option("--bake-missing/--fail-missing",
                                               help="LDC methods: bake first when the bake is missing")] = False,
    supersample: Annotated[int | None, typer.Option(
        help="LDC methods: s x s samples per pixel, box-filtered (1..4; default 1)")] = None,
    antialias: Annotated[str | None, typer.Option(
        help="LDC methods: where --supersample applies: edges (default: pixels at an edge of the one-sample "
             "image) or uniform (every pixel)")] = None,
    glossy_rays: Annotated[int | None, typer.Option(
        help="--method ldc+ibrt:k (k >= 1): trace this many rays through each glossy pixel's lobe instead of "
             "gathering it from the light field (0..256; shows lights seen in mirrors)")] = None,
    quality_error: Annotated[float | None, typer.Option(
        help="Quality contract: largest LRMS against the converged image, in (0, 1); the planner picks the "
             "method (needs 'ibr calibrate' of the scene first)")] = None,
    quality_ms: Annotated[float | None, typer.Option(
        help="Quality contract: largest render time in the worker, in ms; the planner picks the method")] = None,
    best_effort: Annotated[bool, typer.Option(
        "--best-effort/--strict", help="Quality contract no setting meets: render the closest (marked) "
                                       "instead of failing")] = False,
    verify: Annotated[bool, typer.Option(
        "--verify", help="Quality contract: also measure the image against a converged reference of the view "
                         "(a follow-up job, at your cost)")] = False,
    at_time: Annotated[float | None, typer.Option(
        "--time", help="Animated scene: render it at this animation time, inside [animation.start, animation.end] "
                       "(--method reference only)")] = None,
    wait: Annotated[bool, typer.Option("--wait/--no-wait", help="Follow the job with a progress bar")] = True,
    api_url: ApiOpt = DEFAULT_API,
    api_key: KeyOpt = None,
) -> None:
    """Request a render from the service, follow it with a progress bar and fetch the image."""
    params = {k: v for k, v in {"spp": spp, "indirect_samples": indirect, "indirect_bounces": bounces,
                                "seed": seed, "max_error": max_error, "max_ms": max_ms,
                                "light_paths": light_paths}.items() if v is not None}
    bake = _bake_choice(ldc_resolution, llf_f, indirect_noise)
    contract = quality_error is not None or quality_ms is not None
    if contract and (method is not None or params):
        fail("--quality-error/--quality-ms let the planner choose the method: leave out --method and "
             "--spp/--indirect/--bounces/--seed/--max-error/--max-ms/--light-paths")
    if verify and not contract:
        fail("--verify measures a quality contract's render: give --quality-error and / or --quality-ms")
    if best_effort and not contract:
        fail("--best-effort applies to a quality contract: give --quality-error and / or --quality-ms")
    if method is None and not contract:
        method = "reference"
    if at_time is not None and (contract or method not in (None, "reference")):
        fail("--time renders an animated scene at that moment with --method reference; the LDC methods and "
             "--quality-error/--quality-ms work from the bake of the scene as stored")
    if method not in (None, "reference") and params:
        fail("--spp/--indirect/--bounces/--seed/--max-error/--max-ms/--light-paths apply to --method reference; "
             "LDC methods use the bake's settings")
    view = {k: v for k, v in {"supersample": supersample, "antialias": antialias,
                              "glossy_rays": glossy_rays}.items() if v is not None}
    if view and (contract or method in (None, "reference")):
        fail("--supersample/--antialias/--glossy-rays set how an LDC method (--method ldc, ldc+llf or ldc+ibrt:k) "
             "renders; "
             "--method reference takes --spp, and --quality-error/--quality-ms plan the method")
    if re.fullmatch(r"[0-9a-f]{64}", scene):
        scene_id = scene
    else:
        doc, meshes = _scene_doc(scene)
        with _client(api_url, api_key) as c:
            scene_id = _call(lambda: c.create_scene(doc, meshes or None)).id
    fmt = "exr" if output is not None and output.suffix.lower() == ".exr" else "png"
    if output is not None and output.suffix.lower() not in (".png", ".exr"):
        fail(f"{output}: the service delivers .png or .exr")
    render_and_fetch(api_url, api_key, scene_id, params, output, fmt, wait, method=method, bake=bake,
                     missing_bake="bake" if bake_missing else None, max_error=quality_error, max_ms=quality_ms,
                     best_effort=best_effort, verify=verify, at_time=at_time, view=view)


@app.command()
def calibrate(
    scene: Annotated[str, typer.Argument(help="Scene id, scene JSON file, or sample name (uploaded first)")],
    ldc_resolution: Annotated[int | None, typer.Option(help="The bake's LDC resolution")] = None,
    llf_f: Annotated[int | None, typer.Option(help="The bake's LLF subdivision f")] = None,
    indirect_noise: Annotated[float | None, typer.Option(
        help="The bake's noise target for indirect light, relative per sample (default 0.02)")] = None,
    probes: Annotated[int | None, typer.Option(help="Probe views (1..8)")] = None,
    size: Annotated[int | None, typer.Option(help="Probe images' longest side, pixels")] = None,
    truth_spp: Annotated[int | None, typer.Option(help="Ground truth samples per pixel")] = None,
    bake_missing: Annotated[bool, typer.Option("--bake-missing/--fail-missing",
                                               help="Bake first when the bake is missing")] = False,
    wait: Annotated[bool, typer.Option("--wait/--no-wait", help="Follow the calibration")] = True,
    api_url: ApiOpt = DEFAULT_API,
    api_key: KeyOpt = None,
) -> None:
    """Calibrate a scene's render settings for quality contracts (render --quality-error / --quality-ms)."""
    bake = _bake_choice(ldc_resolution, llf_f, indirect_noise)
    params = {k: v for k, v in {"probes": probes, "size": size, "truth_spp": truth_spp}.items() if v is not None}
    scene_id = _scene_id_of(scene, api_url, api_key)
    with _client(api_url, api_key) as c:
        cal = _call(lambda: c.calibrate(scene_id, bake, params, missing_bake="bake" if bake_missing else None))
        typer.echo(f"calibration {cal.key} ({'cached' if cal.cached else cal.state})", err=True)
        if wait and cal.state != "finished":
            with _bar("calibrate") as update:
                def show(p: Any) -> None:
                    if p.job is not None:
                        update(p.job.progress.fraction, p.job.progress.stage or p.state)

                cal = _call(lambda: c.wait_calibration(cal, on_progress=show))
        if cal.model is not None:
            m = cal.model
            typer.echo(f"cost: {m['cost_s']:.1f} s; reference: LRMS {m['reference']['error']:.3f} at 1 spp "
                       f"(falls as spp^-{m['reference'].get('exponent', 0.5):.2f})", err=True)
            for name, fit in m["methods"].items():
                if name not in m["excluded"]:
                    typer.echo(f"{name}: LRMS {fit['error']:.4f}, {fit['b_ms']:.1f} ms + "
                               f"{fit['c_ms'] * 1e6:.1f} ms per Mpixel", err=True)
            for name, why in m["excluded"].items():
                typer.echo(f"{name}: excluded ({why})", err=True)
    typer.echo(cal.bake_key)


def _scene_id_of(scene: str, api_url: str, api_key: str | None) -> str:
    """A scene id as given, or the id of a scene file / sample uploaded first."""
    if re.fullmatch(r"[0-9a-f]{64}", scene):
        return scene
    doc, meshes = _scene_doc(scene)
    with _client(api_url, api_key) as c:
        return _call(lambda: c.create_scene(doc, meshes or None)).id


@app.command()
def bake(
    scene: Annotated[str, typer.Argument(help="Scene id, scene JSON file, or sample name (uploaded first)")],
    ldc_resolution: Annotated[int | None, typer.Option(help="LDC pixels along the scene's longest side")] = None,
    max_layers: Annotated[int | None, typer.Option(help="Surface crossings kept per LDC pixel")] = None,
    llf: Annotated[str | None, typer.Option(help="auto (effect analysis decides), always or never")] = None,
    llf_f: Annotated[int | None, typer.Option(help="LLF directions: 4 f^2 + 2")] = None,
    llf_resolution: Annotated[int | None, typer.Option(help="LLF view resolution")] = None,
    llf_chunk: Annotated[int | None, typer.Option(help="LLF directions per bake job")] = None,
    indirect: Annotated[str | None, typer.Option(help="Indirect light: auto (when it can arrive) or off")] = None,
    noise: Annotated[float | None, typer.Option(
        "--noise", "--indirect-noise", help="Indirect light: noise level (sizes the paths per sample side)")] = None,
    sampling: Annotated[str | None, typer.Option(
        "--sampling", help="Indirect light: fixed (one path count for every sample, sized from the noise) or "
                           "adaptive (a pilot per sample sizes its own)")] = None,
    max_paths: Annotated[int | None, typer.Option(help="Indirect light: most paths per sample side")] = None,
    bounces: Annotated[int | None, typer.Option(help="Indirect light: diffuse bounces per path")] = None,
    caustics: Annotated[str | None, typer.Option(
        "--caustics", help="Indirect light through mirrors / glossy surfaces: photons (a caustic photon map) or "
                           "paths (the paths alone)")] = None,
    indirect_chunks: Annotated[int | None, typer.Option(help="Indirect light: jobs per LDC axis")] = None,
    wait: Annotated[bool, typer.Option("--wait/--no-wait", help="Follow the bake's parts with a progress bar")] = False,
    api_url: ApiOpt = DEFAULT_API,
    api_key: KeyOpt = None,
) -> None:
    """Bake a scene's layered depth cube (+ light field when needed) for the LDC render methods; prints the key."""
    params: dict[str, Any] = {k: v for k, v in {"ldc_resolution": ldc_resolution, "max_layers": max_layers, "llf": llf,
                                "llf_f": llf_f, "llf_resolution": llf_resolution,
                                "llf_chunk": llf_chunk}.items() if v is not None}
    ind = {k: v for k, v in {"mode": indirect, "sampling": sampling, "noise": noise, "max_paths": max_paths,
                             "bounces": bounces, "caustics": caustics,
                             "chunks": indirect_chunks}.items() if v is not None}
    if ind:
        params["indirect"] = ind
    scene_id = _scene_id_of(scene, api_url, api_key)
    with _client(api_url, api_key) as c:
        b = _call(lambda: c.bake(scene_id, params))
        typer.echo(f"bake {b.key} ({'cached' if b.cached else b.state})", err=True)
        if wait and b.state != "finished":
            with _bar("bake") as update:
                def show(p: BakePublic) -> None:
                    update(p.progress.fraction, p.progress.stage or p.state)

                b = _call(lambda: c.wait_bake(b, on_progress=show))  # a failed bake: JobFailed, exit 4
        if b.plan is not None:
            typer.echo(f"plan: light field {'yes' if b.plan.get('bake_llf') else 'no'} ({b.plan.get('reason')}); "
                       f"parts: {', '.join(p.name for p in b.parts)}", err=True)
            gi = b.plan.get("indirect") or {}
            summary = gi.get("summary") or {}
            noise_txt = (f", noise p95 {summary['rel_stderr_p95_of_chunks'] * 100:.2f} % (target "
                         f"{summary['noise_target'] * 100:.2f} %), {summary['paths_mean']:.0f} paths per side"
                         if "rel_stderr_p95_of_chunks" in summary else "")
            typer.echo(f"indirect light: {gi.get('state')} ({gi.get('reason')}){noise_txt}", err=True)
        if b.artifact is not None and b.artifact.result.get("sizes"):
            typer.echo(f"sizes: {b.artifact.result['sizes']}", err=True)
    typer.echo(b.key)


@bakes_app.command("list")
def bakes_list(scene_id: str, api_url: ApiOpt = DEFAULT_API, api_key: KeyOpt = None) -> None:
    """List a scene's bakes with their state and progress."""
    with _client(api_url, api_key) as c:
        res = _call(lambda: c.list_bakes(scene_id))
    for b in res.items:
        typer.echo(f"{b.key}  {b.state:<9} {b.progress.fraction * 100:5.1f}%  ldc={b.params.ldc_resolution} "
                   f"llf={'yes' if b.plan and b.plan.get('bake_llf') else 'no'} parts={len(b.parts)}")


@bakes_app.command("show")
def bakes_show(scene_id: str, key: str, api_url: ApiOpt = DEFAULT_API, api_key: KeyOpt = None) -> None:
    """Show one bake (parts, plan, progress) as JSON."""
    with _client(api_url, api_key) as c:
        typer.echo(_call(lambda: c.get_bake(scene_id, key)).model_dump_json(indent=2))


@bakes_app.command("delete")
def bakes_delete(scene_id: str, key: str, api_url: ApiOpt = DEFAULT_API, api_key: KeyOpt = None) -> None:
    """Delete a bake and its parts (refused while its jobs run)."""
    with _client(api_url, api_key) as c:
        _call(lambda: c.delete_bake(scene_id, key))


@app.command()
def fetch(key: Annotated[str, typer.Argument(help="Artifact key")],
          output: Annotated[Path, typer.Option("-o", "--output", help=".png or .exr")],
          api_url: ApiOpt = DEFAULT_API, api_key: KeyOpt = None) -> None:
    """Download a rendered image."""
    if output.suffix.lower() not in (".png", ".exr"):
        fail(f"{output}: the service delivers .png or .exr")
    with _client(api_url, api_key) as c:
        data = _call(lambda: c.download(key, "exr" if output.suffix.lower() == ".exr" else "png"))
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_bytes(data)
    typer.echo(str(output))


@jobs_app.command("list")
def jobs_list(api_url: ApiOpt = DEFAULT_API, api_key: KeyOpt = None) -> None:
    """List jobs with their state and progress."""
    with _client(api_url, api_key) as c:
        res = _call(c.jobs)
    for j in res.items:
        typer.echo(f"{j.id}  {j.kind:<6} {j.state:<9} {j.progress.fraction * 100:5.1f}%  {j.error or ''}")


@jobs_app.command("show")
def jobs_show(job_id: str, api_url: ApiOpt = DEFAULT_API, api_key: KeyOpt = None) -> None:
    """Show one job as JSON."""
    with _client(api_url, api_key) as c:
        typer.echo(_call(lambda: c.job(job_id)).model_dump_json(indent=2))


@jobs_app.command("cancel")
def jobs_cancel(job_id: str, api_url: ApiOpt = DEFAULT_API, api_key: KeyOpt = None) -> None:
    """Cancel a queued or running job."""
    with _client(api_url, api_key) as c:
        typer.echo(_call(lambda: c.cancel(job_id)).state)


@app.command()
def batch(
    scenes: Annotated[list[str], typer.Argument(help="Scene JSON files (with their mesh files) or sample names")],
    render_them: Annotated[bool, typer.Option("--render/--no-render", help="Also request a render of each")] = True,
    spp: Annotated[int | None, typer.Option(help="Antialiasing samples per pixel for the renders")] = None,
    follow: Annotated[bool, typer.Option(help="Follow the batch until every job ended")] = False,
    api_url: ApiOpt = DEFAULT_API,
    api_key: KeyOpt = None,
) -> None:
    """Submit many scenes (and renders of them) in one call; prints the batch id.

    The scenes and their mesh files go in one batch; the renders follow in a second one that names
    the stored scenes by id. Every scene is validated locally before anything is sent."""
    loaded = [_scene_doc(s) for s in scenes]
    with _client(api_url, api_key) as c:
        b = _call(lambda: c.batch(scenes=[doc for doc, _ in loaded], meshes=[meshes for _, meshes in loaded]))
        if render_them:
            params = {"spp": spp} if spp else {}
            renders: list[Mapping[str, Any]] = [{"scene_id": sid, "params": params} for sid in b.scene_ids]
            b = _call(lambda: c.batch(renders=renders))
        typer.echo(b.id)
        batch_id = b.id
        while follow:
            b = _call(lambda: c.get_batch(batch_id))
            say(f"  {b.progress.fraction * 100:5.1f}%  {b.counts}")
            if not any(b.counts.get(k, 0) for k in ("queued", "started")):
                unfinished = {k: b.counts[k] for k in ("failed", "canceled", "lost") if b.counts.get(k)}
                if unfinished:  # exit 4 like a single render's failed job
                    fail(f"batch {batch_id}: renders without an image: {unfinished}", code=4)
                break
            time.sleep(1.0)


# ------------------------------------------------------------------------------ progress bars


@contextmanager
def _bar(label: str) -> Iterator[Callable[[float, str], None]]:
    """A transient progress bar on stderr (stdout carries only results): ``update(fraction, description)``."""
    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.percentage:>5.1f}%"),
                  TimeRemainingColumn(), transient=True, console=Console(stderr=True)) as bar:
        task = bar.add_task(label, total=1.0)

        def update(fraction: float, description: str) -> None:
            bar.update(task, completed=fraction, description=description or label)

        yield update


def _job_progress(update: Callable[[float, str], None]) -> Callable[[JobPublic], None]:
    def show(j: JobPublic) -> None:
        update(j.progress.fraction, j.progress.stage or j.state)

    return show


def _write(output: Path, data: bytes) -> None:
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_bytes(data)
    typer.echo(str(output))


def _report(manifest: ArtifactManifest) -> None:
    """Counts and timings of a result on stderr."""
    res = manifest.result
    if isinstance(res.get("counts"), dict):
        typer.echo("counts: " + ", ".join(f"{k}={v}" for k, v in res["counts"].items()
                                          if isinstance(v, int | float)), err=True)
    if "exact" in res:
        typer.echo(f"exact: {res['exact']}", err=True)
    if isinstance(res.get("timings"), dict):
        typer.echo("timings: " + ", ".join(f"{k}={v:.3f}s" for k, v in res["timings"].items()
                                           if isinstance(v, int | float)), err=True)


# ------------------------------------------------------------------------------ illumination datasets

datasets_app = typer.Typer(help="Illumination datasets (upload, generate from a scene, bake)", no_args_is_help=True)
app.add_typer(datasets_app, name="datasets")
WaitOpt = Annotated[bool, typer.Option("--wait/--no-wait", help="Follow the job with a progress bar")]


def _dataset_bake_params(layout: str | None, half: bool | None, compress: float | None,
                         max_face_radius: float | None) -> dict[str, Any]:
    return {k: v for k, v in {"layout": layout, "half": half, "compress": compress,
                              "max_face_radius_deg": max_face_radius}.items() if v is not None}


BakeLayoutOpt = Annotated[str | None, typer.Option("--layout", help="Bake layout: pixel_major or tiled")]
HalfOpt = Annotated[bool | None, typer.Option("--half/--no-half", help="Bake: float16 where safe (default) or float32")]
CompressOpt = Annotated[float | None, typer.Option(help="Bake: low-rank store at this relative RMS error (0..1)")]
FaceRadiusOpt = Annotated[float | None, typer.Option("--max-face-radius",
                                                     help="Bake: coverage rule, largest triangle circumradius (deg)")]


@datasets_app.command("upload")
def datasets_upload(
    path: Annotated[Path, typer.Argument(help="Manifest JSON file, or a directory holding manifest.json; the "
                                              "files it names are read next to it")],
    resumable: Annotated[bool, typer.Option("--resumable/--multipart",
                                            help="Send the manifest, PUT only the files the server lacks, commit "
                                                 "(default); or everything in one multipart request")] = True,
    api_url: ApiOpt = DEFAULT_API,
    api_key: KeyOpt = None,
) -> None:
    """Upload an illumination dataset (validated locally first); prints the dataset id."""
    try:
        manifest, files = read_dataset_dir(path)
    except ValueError as exc:
        fail(str(exc))
    try:
        full = with_sha256s(manifest, files)
        DatasetManifest.model_validate(full)
    except ValueError as exc:
        if isinstance(exc, pydantic.ValidationError):
            lines = [f"  manifest.{e['field']}: {e['message']}" for e in format_validation_error(exc)]
            fail(f"{path}: invalid dataset manifest\n" + "\n".join(lines))
        fail(f"{path}: {exc}")
    with _client(api_url, api_key) as c:
        if not resumable:
            ds = _call(lambda: c.upload_dataset(manifest, files))
        else:
            with _bar("upload") as update:
                def show(done: int, total: int, name: str) -> None:
                    update(done / max(total, 1), f"upload {name}")

                ds = _call(lambda: c.upload_dataset_resumable(manifest, files, on_progress=show))
    typer.echo(f"dataset {ds.name}: {ds.n_images} images {ds.width}x{ds.height}, "
               f"{'distant' if ds.distant else 'point'} lights, {ds.total_bytes} bytes", err=True)
    typer.echo(ds.id)


@datasets_app.command("list")
def datasets_list(api_url: ApiOpt = DEFAULT_API, api_key: KeyOpt = None) -> None:
    """List stored datasets."""
    with _client(api_url, api_key) as c:
        items = _call(lambda: list(c.iter_datasets()))
    for d in items:
        typer.echo(f"{d.id}  {d.name}  images={d.n_images} {d.width}x{d.height} "
                   f"{'distant' if d.distant else 'point'} {d.source.get('kind', 'upload')}")


@datasets_app.command("show")
def datasets_show(dataset_id: str, api_url: ApiOpt = DEFAULT_API, api_key: KeyOpt = None) -> None:
    """Show one dataset (canonical manifest with every file's sha256) as JSON."""
    with _client(api_url, api_key) as c:
        typer.echo(_call(lambda: c.get_dataset(dataset_id)).model_dump_json(indent=2))


@datasets_app.command("delete")
def datasets_delete(dataset_id: str, api_url: ApiOpt = DEFAULT_API, api_key: KeyOpt = None) -> None:
    """Delete a dataset (refused while a job uses it)."""
    with _client(api_url, api_key) as c:
        _call(lambda: c.delete_dataset(dataset_id))


@datasets_app.command("generate")
def datasets_generate(
    scene: Annotated[str, typer.Argument(help="Scene id, scene JSON file, or sample name (uploaded first)")],
    region: Annotated[str | None, typer.Option(help="sphere, hemisphere or upper_front_quarter")] = None,
    layout: Annotated[str | None, typer.Option(help="grid or geodesic")] = None,
    spacing: Annotated[float | None, typer.Option(help="Light spacing in degrees (0.5..90)")] = None,
    radius: Annotated[float | None, typer.Option(help="Light sphere radius (default: automatic)")] = None,
    center: Annotated[str | None, typer.Option(help="Light sphere centre X,Y,Z (default: centroid of the "
                                                    "visible surface)")] = None,
    params: Annotated[str | None, typer.Option(help="Reference render params as JSON, e.g. "
                                                    "'{\"spp\": 4, \"max_depth\": 2}'")] = None,
    max_lights: Annotated[int | None, typer.Option(help="Refuse placements with more lights")] = None,
    spp: Annotated[int | None, typer.Option(help="Antialiasing samples per pixel of each image")] = None,
    width: Annotated[int | None, typer.Option(help="Override the camera width")] = None,
    height: Annotated[int | None, typer.Option(help="Override the camera height")] = None,
    wait: WaitOpt = True,
    api_url: ApiOpt = DEFAULT_API,
    api_key: KeyOpt = None,
) -> None:
    """Generate a dataset by rendering a scene under point lights over a sphere; prints the dataset id
    (with --no-wait: the generation job id)."""
    placement: dict[str, Any] = {k: v for k, v in {"region": region, "layout": layout, "spacing_deg": spacing,
                                                   "radius": radius}.items() if v is not None}
    if center is not None:
        placement["center"] = _floats(center, (3,), "--center")
    render_params: dict[str, Any] = {}
    if params is not None:
        try:
            render_params = json.loads(params)
        except ValueError as exc:
            fail(f"--params: not valid JSON: {exc}")
        if not isinstance(render_params, dict):
            fail("--params: must be a JSON object")
    if spp is not None:
        render_params["spp"] = spp
    scene_id = _scene_id_of(scene, api_url, api_key)
    with _client(api_url, api_key) as c:
        camera: dict[str, Any] | None = None
        if width is not None or height is not None:  # the scene's own camera, resized
            doc = _call(lambda: c.get_scene_document(scene_id)) if _is_id(scene) else _scene_doc(scene)[0]
            camera = dict(doc["camera"])
            camera.update({k: v for k, v in {"width": width, "height": height}.items() if v is not None})
        g = _call(lambda: c.generate_dataset(scene_id, placement=placement or None,
                                             params=render_params or None, camera=camera,
                                             max_lights=max_lights, wait=2.0 if wait else 0.0))
        typer.echo(f"generation {g.artifact_key} ({g.status})", err=True)
        if g.dataset_id is None and not wait:
            typer.echo(g.job.id if g.job is not None else g.artifact_key)
            return
        with _bar("generate") as update:
            did = _call(lambda: c.wait_generation(g, on_progress=_job_progress(update)))
    typer.echo(did)


@datasets_app.command("bake")
def datasets_bake(
    dataset_id: str,
    layout: BakeLayoutOpt = None,
    half: HalfOpt = None,
    compress: CompressOpt = None,
    max_face_radius: FaceRadiusOpt = None,
    wait: WaitOpt = True,
    api_url: ApiOpt = DEFAULT_API,
    api_key: KeyOpt = None,
) -> None:
    """Bake a dataset for relighting (triangulate the lights, reorganise the images); prints the bake key."""
    params = _dataset_bake_params(layout, half, compress, max_face_radius)
    with _client(api_url, api_key) as c:
        b = _call(lambda: c.bake_dataset(dataset_id, params, wait=2.0 if wait else 0.0))
        typer.echo(f"bake {b.artifact_key} ({b.status})", err=True)
        if wait and b.artifact is None:
            with _bar("bake") as update:
                b = _call(lambda: c.wait_dataset_bake(b, params, on_progress=_job_progress(update)))
        if b.artifact is not None:
            _report(b.artifact)
    typer.echo(b.artifact_key)


def _is_id(value: str) -> bool:
    return re.fullmatch(r"[0-9a-f]{64}", value) is not None


def _floats(text: str, n: tuple[int, ...], what: str) -> list[float]:
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        fail(f"{what}: {text!r} is not a comma-separated list of numbers")
    if len(vals) not in n:
        fail(f"{what}: {text!r} must have {' or '.join(str(k) for k in n)} numbers")
    return vals


def _rgb(text: str, what: str) -> list[float]:
    v = _floats(text, (1, 3), what)
    return v * 3 if len(v) == 1 else v


def _parse_lights(specs: list[str], lights_file: Path | None, c: Client | None) -> list[dict[str, Any]]:
    """``--light`` values (JSON objects or shorthands) and a ``--lights`` JSON file -> RelightLight dicts.
    Environment maps (``env:FILE[:N]``) are uploaded with ``c``."""
    lights: list[dict[str, Any]] = []
    if lights_file is not None:
        try:
            doc = json.loads(lights_file.read_text())
        except (OSError, ValueError) as exc:
            fail(f"--lights {lights_file}: {exc}")
        if isinstance(doc, dict) and "lights" in doc:
            doc = doc["lights"]
        if not isinstance(doc, list) or not all(isinstance(x, dict) for x in doc):
            fail(f"--lights {lights_file}: must be a JSON list of light objects (or {{\"lights\": [...]}})")
        lights += doc
    for i, spec in enumerate(specs):
        what = f"--light #{i + 1} ({spec!r})"
        if spec.lstrip().startswith("{"):
            try:
                light = json.loads(spec)
            except ValueError as exc:
                fail(f"{what}: not valid JSON: {exc}")
            if not isinstance(light, dict):
                fail(f"{what}: must be a JSON object")
            lights.append(light)
            continue
        kind, _, rest = spec.partition(":")
        parts = rest.split(":")
        if kind == "point" and rest:
            light = {"type": "point", "position": _floats(parts[0], (3,), what)}
            if len(parts) > 1:
                light["intensity"] = _rgb(parts[1], what)
        elif kind in ("directional", "dir") and rest:
            light = {"type": "directional", "direction": _floats(parts[0], (3,), what)}
            if len(parts) > 1:
                light["irradiance"] = _rgb(parts[1], what)
        elif kind in ("environment", "env") and rest:
            env = Path(parts[0])
            if not env.is_file():
                fail(f"{what}: environment map {env} not found")
            light = {"type": "environment", "image_sha256": _upload(c, env).sha256}
            if len(parts) > 1:
                try:
                    light["n_lights"] = int(parts[1])
                except ValueError:
                    fail(f"{what}: the number of lights must be an integer")
        else:
            fail(f"{what}: use a JSON object, point:X,Y,Z[:I], directional:DX,DY,DZ[:E] or env:FILE.exr[:N]")
        lights.append(light)
    if not lights:
        fail("give at least one --light (or --lights FILE)")
    return lights


def _upload(c: Client | None, path: Path) -> FileUploadPublic:
    if c is None:
        fail(f"{path}: no API client to upload it with")
    if not path.is_file():
        fail(f"{path}: no such file")
    return _call(lambda: c.upload_file(path))


def _relit_outputs(c: Client, key: str, kind: Literal["relight", "composite"], output: Path | None,
                   outside: Path | None) -> None:
    if output is not None:
        which: Literal["exr", "png"] = "exr" if output.suffix.lower() == ".exr" else "png"
        _write(output, _call(lambda: c.download_relight(key, which, kind=kind)))
    if outside is not None:
        _write(outside, _call(lambda: c.download_relight(key, "outside", kind=kind)))


def _check_image_out(output: Path | None, what: str = "-o") -> None:
    if output is not None and output.suffix.lower() not in (".png", ".exr"):
        fail(f"{what} {output}: the service delivers .png or .exr")


def _run_relight(c: Client, kind: Literal["relight", "composite"], submit: Callable[[], RelightPublic],
                 wait: bool) -> ArtifactManifest | None:
    r = _call(submit)
    typer.echo(f"{kind} {r.artifact_key} ({r.status})", err=True)
    if r.artifact is not None:
        return r.artifact
    if not wait:
        typer.echo(r.job.id if r.job is not None else r.artifact_key)
        return None
    with _bar(kind) as update:
        return _call(lambda: c.wait_relight(r, on_progress=_job_progress(update), kind=kind))


LightOpt = Annotated[list[str] | None, typer.Option(
    "--light", help="A light: JSON ({\"type\": \"point\", \"position\": [x, y, z], \"intensity\": [r, g, b]}) or "
                    "point:X,Y,Z[:I], directional:DX,DY,DZ[:E] (direction the light travels), env:FILE.exr[:N]; "
                    "repeat to superpose")]
LightsFileOpt = Annotated[Path | None, typer.Option("--lights", help="JSON file with a list of lights")]


@app.command()
def relight(
    dataset: Annotated[str, typer.Argument(help="Dataset id")],
    light: LightOpt = None,
    lights_file: LightsFileOpt = None,
    output: Annotated[Path | None, typer.Option("-o", "--output", help="Save the relit image (.png or .exr)")] = None,
    outside: Annotated[Path | None, typer.Option(help="Save the coverage mask PNG (white: light outside the "
                                                      "dataset's coverage)")] = None,
    exposure: Annotated[float | None, typer.Option(help="Exposure of the PNG in stops")] = None,
    min_light_distance: Annotated[float | None, typer.Option(help="Point lights nearer than this contribute 0")
                                  ] = None,
    layout: BakeLayoutOpt = None,
    half: HalfOpt = None,
    compress: CompressOpt = None,
    max_face_radius: FaceRadiusOpt = None,
    bake_missing: Annotated[bool, typer.Option("--bake-missing/--fail-missing",
                                               help="Bake the dataset first when it is not baked")] = True,
    wait: WaitOpt = True,
    api_url: ApiOpt = DEFAULT_API,
    api_key: KeyOpt = None,
) -> None:
    """Relight a dataset under new lights (superposed) and fetch the image."""
    _check_image_out(output)
    _check_image_out(outside, "--outside")
    bake_params = _dataset_bake_params(layout, half, compress, max_face_radius)
    with _client(api_url, api_key) as c:
        lights = _parse_lights(light or [], lights_file, c)

        def submit() -> RelightPublic:
            return c.relight(dataset, lights, bake=bake_params or None, exposure_stops=exposure,
                             min_light_distance=min_light_distance, wait=10.0 if wait else 0.0)

        try:
            r = submit()
        except ApiError as exc:
            if not (exc.status == 409 and bake_missing and any(e.get("type") == "not_baked" for e in exc.errors)):
                _api_fail(exc)
            typer.echo(f"dataset {dataset} is not baked with these parameters: baking it first", err=True)
            b = _call(lambda: c.bake_dataset(dataset, bake_params, wait=2.0))
            with _bar("bake") as update:
                _call(lambda: c.wait_dataset_bake(b, bake_params, on_progress=_job_progress(update)))
            r = _call(submit)
        except httpx.HTTPError as exc:
            fail(f"cannot reach the API: {exc}", code=3)
        manifest = _run_relight(c, "relight", lambda: r, wait)
        if manifest is None:
            return
        _report(manifest)
        _relit_outputs(c, manifest.key, "relight", output, outside)
        if output is None and outside is None:
            typer.echo(manifest.key)


@app.command()
def composite(
    object_dataset: Annotated[str, typer.Option("--object", help="Dataset id of the object in its surroundings")],
    background_dataset: Annotated[str, typer.Option("--background", help="Dataset id of the surroundings alone "
                                                                         "(same lights and view)")],
    plate: Annotated[Path, typer.Option(help="Background plate image")],
    mask: Annotated[Path, typer.Option(help="Object mask image (object where the first channel > 0.5)")],
    active: Annotated[Path | None, typer.Option(help="Active region mask (default: the mask dilated by --margin)")
                      ] = None,
    margin: Annotated[int | None, typer.Option(help="Active region: object mask dilated by this many pixels")
                      ] = None,
    plate_transfer: Annotated[str | None, typer.Option(help="srgb, linear or gamma:<g> (8/16-bit plates)")] = None,
    light: LightOpt = None,
    lights_file: LightsFileOpt = None,
    eps: Annotated[float | None, typer.Option(help="Near-black guard of the ratio")] = None,
    max_ratio: Annotated[float | None, typer.Option(help="Clamp of the ratio")] = None,
    exposure: Annotated[float | None, typer.Option(help="Exposure of the PNG in stops")] = None,
    output: Annotated[Path | None, typer.Option("-o", "--output", help="Save the composite (.png or .exr)")] = None,
    wait: WaitOpt = True,
    api_url: ApiOpt = DEFAULT_API,
    api_key: KeyOpt = None,
) -> None:
    """Composite a relit object into a background plate (both datasets must be baked: 'ibr datasets bake')."""
    _check_image_out(output)
    with _client(api_url, api_key) as c:
        lights = _parse_lights(light or [], lights_file, c)
        body: dict[str, Any] = {"object_dataset_id": object_dataset, "background_dataset_id": background_dataset,
                                "plate_sha256": _upload(c, plate).sha256,
                                "object_mask_sha256": _upload(c, mask).sha256, "lights": lights}
        if active is not None:
            body["active_region_sha256"] = _upload(c, active).sha256
        body.update({k: v for k, v in {"active_margin_px": margin, "plate_transfer": plate_transfer, "eps": eps,
                                       "max_ratio": max_ratio, "exposure_stops": exposure}.items() if v is not None})
        manifest = _run_relight(c, "composite", lambda: c.composite(body, wait=10.0 if wait else 0.0), wait)
        if manifest is None:
            return
        _report(manifest)
        _relit_outputs(c, manifest.key, "composite", output, None)
        if output is None:
            typer.echo(manifest.key)


# ------------------------------------------------------------------------------ walkthroughs

walkthroughs_app = typer.Typer(help="Walkthroughs (camera paths rendered from base range images)",
                               no_args_is_help=True)
app.add_typer(walkthroughs_app, name="walkthroughs")


def _path_request(path: Path, width: int | None, height: int | None) -> dict[str, Any]:
    """A camera path file: a JSON list of frames ``{"time", "camera"}``, or an object with ``frames``
    (and optionally other WalkthroughRequest fields). Cameras without ``type`` are perspective."""
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        fail(f"--path {path}: {exc}")
    req: dict[str, Any] = {"frames": doc} if isinstance(doc, list) else doc
    if not isinstance(req, dict) or not isinstance(req.get("frames"), list):
        fail(f"--path {path}: must be a JSON list of frames or an object with 'frames'")
    frames: list[Any] = req["frames"]
    for i, f in enumerate(frames):
        if not isinstance(f, dict) or not isinstance(f.get("camera"), dict):
            fail(f"--path {path}: frames.{i} must be an object with a 'camera'")
        cam = f["camera"]
        cam.setdefault("type", "perspective")
        if width is not None:
            cam["width"] = width
        if height is not None:
            cam["height"] = height
    return req


FrameFormat = Literal["png", "exr", "provenance"]


def _frame_format(value: str) -> FrameFormat:
    for fmt in get_args(FrameFormat):
        if value == fmt:
            return cast(FrameFormat, fmt)
    fail(f"--frame-format {value!r}: use png, exr or provenance")


def _walkthrough_outputs(c: Client, key: str, output: Path | None, frames_dir: Path | None, n: int,
                         frame_format: FrameFormat) -> None:
    if output is not None:
        _write(output, _call(lambda: c.download_walkthrough_video(key)))
    if frames_dir is not None:
        frames_dir.mkdir(parents=True, exist_ok=True)
        ext = "exr" if frame_format == "exr" else "png"
        suffix = ".provenance" if frame_format == "provenance" else ""
        for i in range(n):
            (frames_dir / f"frame_{i:05d}{suffix}.{ext}").write_bytes(
                _call(partial(c.download_walkthrough_frame, key, i, frame_format)))
        typer.echo(str(frames_dir))


def _follow_walkthrough(c: Client, w: WalkthroughPublic) -> WalkthroughPublic:
    with _bar("walkthrough") as update:
        def show(p: WalkthroughPublic) -> None:
            stage = "bake" if p.frames_done == 0 and p.progress < 1 / 3 else f"frames {p.frames_done}/{p.frames}"
            update(p.progress, f"{p.status} {stage}")

        return _call(lambda: c.wait_walkthrough(w, on_progress=show))


FrameFormatOpt = Annotated[str, typer.Option("--frame-format", help="Frames saved by --frames-dir: png, exr or "
                                                                     "provenance")]


@app.command()
def walkthrough(
    scene: Annotated[str, typer.Argument(help="Scene id, scene JSON file, or sample name (with a view_space)")],
    path: Annotated[Path, typer.Option("--path", help="Camera path JSON: a list of frames {time, camera} (or "
                                                      "an object with 'frames')")],
    quality: Annotated[str | None, typer.Option(help="low, medium or high (default: the path file's, or "
                                                     "medium)")] = None,
    fill: Annotated[str | None, typer.Option(help="Hole fill: none, foreground, background, both, trace")] = None,
    face_res: Annotated[int | None, typer.Option(help="Base cube face resolution (even)")] = None,
    indirect: Annotated[int | None, typer.Option(help="Indirect paths per base pixel (0: no GI)")] = None,
    max_views: Annotated[int | None, typer.Option(help="Cap on base viewpoints")] = None,
    max_time_samples: Annotated[int | None, typer.Option(help="Cap on time samples")] = None,
    chunk_frames: Annotated[int | None, typer.Option(help="Frames per render job")] = None,
    fps: Annotated[int | None, typer.Option(help="MP4 frame rate")] = None,
    width: Annotated[int | None, typer.Option(help="Override every frame's width")] = None,
    height: Annotated[int | None, typer.Option(help="Override every frame's height")] = None,
    output: Annotated[Path | None, typer.Option("-o", "--output", help="Save the MP4 (implies --wait)")] = None,
    frames_dir: Annotated[Path | None, typer.Option(help="Save every frame in this directory (implies --wait)")
                          ] = None,
    frame_format: FrameFormatOpt = "png",
    path_noise: Annotated[float | None, typer.Option(
        help="Path-trace every frame to this LRMS against its converged frame (0.005..0.5; each frame sizes "
             "its paths for it) instead of reconstructing it from a bake: no bake, each frame costs a "
             "path-traced render")] = None,
    quality_error: Annotated[float | None, typer.Option(
        help="Quality contract: largest LRMS of every frame against its converged frame, in (0, 1); the planner "
             "picks the bake preset and the fill (needs 'ibr calibrate-walkthroughs' of the scene first)")] = None,
    quality_ms: Annotated[float | None, typer.Option(
        help="Quality contract: largest render time of a frame in the worker, in ms; the planner picks the bake "
             "preset and the fill")] = None,
    best_effort: Annotated[bool, typer.Option(
        "--best-effort/--strict", help="Quality contract no setting meets: render the closest (marked) "
                                       "instead of failing")] = False,
    wait: Annotated[bool, typer.Option("--wait/--no-wait", help="Follow the walkthrough with a progress bar")
                    ] = False,
    api_url: ApiOpt = DEFAULT_API,
    api_key: KeyOpt = None,
) -> None:
    """Render a camera path through a scene's view space from walkthrough bases; prints the walkthrough key.

    With --path-noise every frame is path-traced instead, without a bake. With --quality-error /
    --quality-ms (a quality contract) the service picks the bake preset and the fill, or path-traced
    frames, from the scene's walkthrough calibration and the plan is printed on stderr."""
    if output is not None and output.suffix.lower() != ".mp4":
        fail(f"-o {output}: the walkthrough video is an .mp4")
    fmt = _frame_format(frame_format)
    settings = {"--quality": quality, "--fill": fill, "--face-res": face_res, "--indirect": indirect,
                "--max-views": max_views, "--max-time-samples": max_time_samples}
    if quality_error is not None or quality_ms is not None:
        _refuse_settings_with_contract({**settings, "--path-noise": path_noise}, "--quality-error/--quality-ms")
    if path_noise is not None:
        given = [flag for flag, v in settings.items() if v is not None]
        if given:
            fail(f"--path-noise path-traces every frame without a bake: leave out {', '.join(given)}")
    req = _path_request(path, width, height)
    if _walkthrough_contract(req, path, quality_error, quality_ms, best_effort):
        _refuse_settings_with_contract(settings, f"--path {path}'s 'quality'")
    bake_doc = dict(req.get("bake") or {})
    bake_doc.update({k: v for k, v in {"quality": quality, "face_res": face_res, "indirect_samples": indirect,
                                       "max_views": max_views, "max_time_samples": max_time_samples}.items()
                     if v is not None})
    if path_noise is not None:
        req.pop("bake", None)
        req.pop("fill", None)
        req["path_traced"] = {"noise": path_noise}
    elif bake_doc:
        req["bake"] = bake_doc
    req.update({k: v for k, v in {"fill": fill, "chunk_frames": chunk_frames, "fps": fps}.items() if v is not None})
    req["scene_id"] = _scene_id_of(scene, api_url, api_key)
    with _client(api_url, api_key) as c:
        def submit() -> WalkthroughPublic:
            try:
                return c.walkthrough(req)
            except ApiError as exc:  # a contract on a scene never calibrated: say how to calibrate it
                if exc.status == 409 and "walkthrough-calibrations" in exc.detail:
                    fail(f"{exc}\n(calibrate it with: ibr calibrate-walkthroughs {scene})")
                raise

        w = _call(submit)
        source = f"bake {w.bake_key[:12]}" if w.bake_key else "path-traced"
        typer.echo(f"walkthrough {w.key} ({w.status}, {w.frames} frames, {source})", err=True)
        if w.contract is not None:
            for line in _walkthrough_contract_lines(w.contract):
                say(line)
        if wait or output is not None or frames_dir is not None:
            w = _follow_walkthrough(c, w)
            typer.echo(f"finished: {w.frames_done} frames", err=True)
            if w.contract is not None and w.contract.achieved_frame_ms:
                a = w.contract.achieved_frame_ms
                say(f"achieved: {a['median']:.1f} ms / frame median, {a['max']:.1f} ms max "
                    f"(predicted {w.contract.predicted_frame_ms:.1f} ms)")
                if w.contract.achieved_estimated_error:
                    e = w.contract.achieved_estimated_error
                    say(f"estimated error: {100 * e['median']:.1f} % median, {100 * e['max']:.1f} % max over the "
                        f"frames (each frame's own estimate; predicted {100 * w.contract.predicted_error:.1f} %)")
            _walkthrough_outputs(c, w.key, output, frames_dir, w.frames, fmt)
    typer.echo(w.key)


def _refuse_settings_with_contract(settings: Mapping[str, Any], contract: str) -> None:
    """Exit 2 when a walkthrough's bake / fill options are given with a quality contract."""
    given = [flag for flag, v in settings.items() if v is not None]
    if given:
        fail(f"{contract} let the planner choose the bake preset and the fill: leave out "
             f"{', '.join(given)} (a contract plans onto a preset's default bake)")


def _walkthrough_contract(req: dict[str, Any], path: Path, quality_error: float | None, quality_ms: float | None,
                          best_effort: bool) -> bool:
    """Put the quality contract of the contract options (or the path file's own ``quality``) in ``req``
    and drop the path file's ``bake`` / ``fill``, which it chooses; False when there is no contract."""
    if quality_error is not None or quality_ms is not None:
        if req.get("quality") is not None:
            say(f"--path {path}: its 'quality' is replaced by --quality-error/--quality-ms")
        q: dict[str, Any] = {k: v for k, v in {"max_error": quality_error, "max_ms": quality_ms}.items()
                             if v is not None}
        if best_effort:
            q["on_miss"] = "best_effort"
        req["quality"] = q
    elif req.get("quality") is None:
        if best_effort:
            fail("--best-effort applies to a quality contract: give --quality-error and / or --quality-ms")
        return False
    elif best_effort and isinstance(req["quality"], dict):
        req["quality"]["on_miss"] = "best_effort"
    dropped = [name for name in ("bake", "fill") if name in req]
    if dropped:
        verb = "are" if len(dropped) > 1 else "is"
        say(f"--path {path}: its {' and '.join(dropped)} {verb} left out: the quality contract chooses them")
        for name in dropped:
            del req[name]
    return True


def _walkthrough_contract_lines(con: WalkthroughContractPublic) -> list[str]:
    """What a walkthrough's quality contract chose, on one line (a second when it does not meet it)."""
    bake = "" if con.bake != "waited" else f"; its bake is made first, predicted {con.predicted_bake_ms / 1000:.1f} s"
    setting = f"path-traced frames at noise {con.path_noise:g}" if con.path_noise is not None else \
        f"{con.preset}/{con.fill}"
    lines = [f"contract: {setting}, predicted LRMS {con.predicted_error:.4f}, "
             f"{con.predicted_frame_ms:.1f} ms / frame (rule {con.rule}{bake})"]
    if not con.met:
        lines.append(f"not met: {', '.join(con.unmet) or 'the targets'}" + (f": {con.reason}" if con.reason else ""))
    return lines


def _csv(value: str | None, what: str) -> list[str] | None:
    """``low,medium`` -> ["low", "medium"] (None when not given)."""
    if value is None:
        return None
    items = [v.strip() for v in value.split(",") if v.strip()]
    if not items:
        fail(f"{what}: give a comma-separated list, e.g. {what} low,medium")
    return items


@app.command("calibrate-walkthroughs")
def calibrate_walkthroughs(
    scene: Annotated[str, typer.Argument(help="Scene id, scene JSON file, or sample name (with a view_space; "
                                              "uploaded first)")],
    presets: Annotated[str | None, typer.Option(help="Bake presets measured, comma-separated: low, medium, high "
                                                     "(default: all three)")] = None,
    fills: Annotated[str | None, typer.Option(help="Hole fills measured with each preset, comma-separated: none, "
                                                   "foreground, background, both, trace (default: both,trace)")
                     ] = None,
    probes: Annotated[int | None, typer.Option(help="Probe frames (1..8; default 3)")] = None,
    size: Annotated[int | None, typer.Option(help="Probe frames' longest side, pixels (16..512; default 64)")] = None,
    time_scale: Annotated[int | None, typer.Option(help="Frame times also measured at size x this (2..8)")] = None,
    truth_noise: Annotated[float | None, typer.Option(
        help="Relative standard error the converged probe frames are traced to (0.002..0.05; default 0.01)")] = None,
    path_noises: Annotated[str | None, typer.Option(
        help="Noise targets of the path-traced frames measured, comma-separated (default "
             f"{','.join(f'{n:g}' for n in DEFAULT_PATH_NOISES)}; "
             "'none': no path-traced setting)")] = None,
    wait: Annotated[bool, typer.Option("--wait/--no-wait", help="Follow the calibration")] = True,
    api_url: ApiOpt = DEFAULT_API,
    api_key: KeyOpt = None,
) -> None:
    """Calibrate a scene's walkthrough settings (bake preset x fill) for walkthrough quality contracts
    (walkthrough --quality-error / --quality-ms); prints the calibration key. Bakes the presets whose
    bake is not stored yet."""
    params: dict[str, Any] = {k: v for k, v in {
        "presets": _csv(presets, "--presets"), "fills": _csv(fills, "--fills"), "probes": probes, "size": size,
        "time_scale": time_scale, "truth_noise": truth_noise,
        "path_noises": _noises(path_noises)}.items() if v is not None}
    try:  # checked before the scene is uploaded or anything queued
        WalkthroughCalibrationParams.model_validate(params)
    except pydantic.ValidationError as exc:
        lines = []
        for e in format_validation_error(exc):
            field = str(e["field"])
            lines.append(f"  --{field.split('.', 1)[0].replace('_', '-')} (params.{field}): {e['message']}")
        fail("invalid walkthrough calibration\n" + "\n".join(lines))
    scene_id = _scene_id_of(scene, api_url, api_key)
    with _client(api_url, api_key) as c:
        cal = _call(lambda: c.calibrate_walkthroughs(scene_id, params))
        say(f"walkthrough calibration {cal.key} ({'cached' if cal.cached else cal.state})")
        if wait and cal.state != "finished":
            with _bar("calibrate walkthroughs") as update:
                def show(p: WalkthroughCalibrationPublic) -> None:
                    if p.job is not None:
                        update(p.job.progress.fraction, p.job.progress.stage or p.state)

                cal = _call(lambda: c.wait_walkthrough_calibration(cal, on_progress=show))
        if cal.model is not None:
            for line in _walkthrough_model_lines(cal.model):
                say(line)
    typer.echo(cal.key)


def _noises(value: str | None) -> list[float | str] | None:
    """``0.02,0.05`` -> [0.02, 0.05]; ``none`` -> []; an item that is no number is passed on as given,
    for the request's check to name."""
    if value is None:
        return None
    if value.strip().lower() == "none":
        return []
    out: list[float | str] = []
    for item in _csv(value, "--path-noises") or []:
        try:
            out.append(float(item))
        except ValueError:
            out.append(item)
    return out


def _walkthrough_model_lines(m: Mapping[str, Any]) -> list[str]:
    """A walkthrough calibration's model, a line per setting: its error, its time per frame at the probe
    frames' size and its preset's bake cost."""
    frames = (m.get("probe") or {}).get("frames") or []
    w, h = (int(frames[0]["width"]), int(frames[0]["height"])) if frames else (0, 0)
    parts = (m.get("probe") or {}).get("cost_breakdown_s") or {}
    split = ", ".join(f"{k.replace('_', ' ')} {v:.1f} s" for k, v in parts.items() if isinstance(v, int | float))
    lines = [f"cost: {m['cost_s']:.1f} s" + (f" ({split})" if split else "")]
    excluded: Mapping[str, str] = m.get("excluded") or {}
    for name, fit in (m.get("fits") or {}).items():
        preset = name.split("/", 1)[0]
        bake_s = None if preset == "path" else (m.get("bake_cost_s") or {}).get(preset)
        bake = f"; bake {bake_s:.1f} s" if isinstance(bake_s, int | float) else ""
        note = f"; excluded ({excluded[name]})" if name in excluded else ""
        lines.append(f"{name}: LRMS {fit['error']:.4f}, {fit['b_ms'] + fit['c_ms'] * w * h:.1f} ms / frame "
                     f"at {w} x {h}{bake}{note}")
    return lines


@walkthroughs_app.command("show")
def walkthroughs_show(key: str, api_url: ApiOpt = DEFAULT_API, api_key: KeyOpt = None) -> None:
    """Show a walkthrough (state, progress, jobs, links) as JSON."""
    with _client(api_url, api_key) as c:
        typer.echo(_call(lambda: c.get_walkthrough(key)).model_dump_json(indent=2))


@walkthroughs_app.command("fetch")
def walkthroughs_fetch(
    key: str,
    output: Annotated[Path | None, typer.Option("-o", "--output", help="Save the MP4")] = None,
    frames_dir: Annotated[Path | None, typer.Option(help="Save every frame in this directory")] = None,
    frame_format: FrameFormatOpt = "png",
    wait: Annotated[bool, typer.Option("--wait/--no-wait", help="Wait for it to finish first")] = True,
    api_url: ApiOpt = DEFAULT_API,
    api_key: KeyOpt = None,
) -> None:
    """Download a walkthrough's MP4 and / or frames."""
    if output is not None and output.suffix.lower() != ".mp4":
        fail(f"-o {output}: the walkthrough video is an .mp4")
    fmt = _frame_format(frame_format)
    with _client(api_url, api_key) as c:
        w = _call(lambda: c.get_walkthrough(key))
        if w.status != "finished":
            if not wait:
                fail(f"walkthrough {key} is {w.status} ({w.frames_done}/{w.frames} frames)", code=4
                     if w.status == "failed" else 2)
            w = _follow_walkthrough(c, w)
        _walkthrough_outputs(c, key, output, frames_dir, w.frames, fmt)


@walkthroughs_app.command("delete")
def walkthroughs_delete(key: str, api_url: ApiOpt = DEFAULT_API, api_key: KeyOpt = None) -> None:
    """Delete a walkthrough's video, frames and request (refused while its jobs run; the bake stays)."""
    with _client(api_url, api_key) as c:
        _call(lambda: c.delete_walkthrough(key))


if __name__ == "__main__":
    app()
