"""The ``ibr`` command line.

Service: ``ibr up`` (everything on one machine), ``ibr api``, ``ibr worker --queue
bake|render``. Client (talks to the API at ``--api`` / ``IBR_API_URL``, default
http://127.0.0.1:8000, key from ``IBR_API_KEY``): ``ibr scenes add|list|show|delete``,
``ibr render`` (request a render, follow it with a progress bar, fetch the image; ``--method
ldc+llf`` renders from the scene's bake), ``ibr bake`` (bake a scene, ``--wait`` follows its parts),
``ibr bakes list|show|delete``,
``ibr fetch``, ``ibr jobs list|show|cancel``, ``ibr batch``. Local, no service:
``ibr render-local``, ``ibr validate``, ``ibr schema``, ``ibr samples``.

Exit codes: 0 ok, 2 bad input (with a message naming the field or file), 3 the
service could not be reached or failed the request, 4 the job failed.
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, NoReturn, TypeVar

import typer

if TYPE_CHECKING:
    from api_schemas.scene import Scene
    from service.client import Client

T = TypeVar("T")

app = typer.Typer(add_completion=False, no_args_is_help=True, help="ibr-service: image-based rendering")


def _fail(msg: str, code: int = 2) -> NoReturn:
    typer.echo(f"error: {msg}", err=True)
    raise typer.Exit(code)


def _load(scene_arg: str) -> tuple[Scene, Path]:
    """A scene file path or the name of a sample scene -> (Scene, base directory)."""
    import pydantic

    from api_schemas import format_validation_error, load_scene_file
    from api_schemas.scene import SceneFileTooLargeError
    from samples import SAMPLES_DIR, sample_names, sample_path

    path = Path(scene_arg)
    if not path.exists() and scene_arg in sample_names():
        path = sample_path(scene_arg)
    if not path.is_file():
        _fail(f"{scene_arg}: no such scene file or sample (samples: {', '.join(sample_names())})")
    try:
        scene = load_scene_file(path)
    except pydantic.ValidationError as exc:
        lines = [f"  {e['field']}: {e['message']}" for e in format_validation_error(exc)]
        _fail(f"{path}: invalid scene\n" + "\n".join(lines))
    except (SceneFileTooLargeError, ValueError, OSError) as exc:
        _fail(f"{path}: {exc}")
    base = path.parent.parent if path.parent.resolve() == (SAMPLES_DIR / "scenes").resolve() else path.parent
    return scene, base


@app.command("render-local")
def render_local(
    scene: Annotated[str, typer.Argument(help="Scene JSON file, or a sample scene name")],
    output: Annotated[Path, typer.Option("-o", "--output", help="Image file (.exr .hdr .png .jpg .tif)")] = Path(
        "out/render.png"),
    spp: Annotated[int, typer.Option(help="Antialiasing samples per pixel")] = 4,
    max_depth: Annotated[int, typer.Option(help="Mirror / glossy recursion depth")] = 4,
    glossy_samples: Annotated[int, typer.Option(help="Samples of the glossy lobe")] = 16,
    area_samples: Annotated[int, typer.Option(help="Samples per area light")] = 16,
    indirect: Annotated[int, typer.Option(help="Indirect paths per pixel (0 = off)")] = 0,
    bounces: Annotated[int, typer.Option(help="Bounces per indirect path")] = 2,
    seed: Annotated[int, typer.Option(help="Random seed")] = 0,
    width: Annotated[int | None, typer.Option(help="Override the camera width")] = None,
    height: Annotated[int | None, typer.Option(help="Override the camera height")] = None,
    exposure: Annotated[float, typer.Option(help="Exposure in stops for 8-bit outputs")] = 0.0,
    aovs: Annotated[bool, typer.Option(help="Also write depth/normal/id EXRs beside the image")] = False,
) -> None:
    """Render a scene in this process with the reference renderer (no service) and write the image."""
    from dataclasses import replace

    from engine.errors import EngineError
    from engine.imageio import write_image
    from engine.reference import ReferenceParams, ReferenceRenderer
    from workers.scene_loader import directory_resolver, load_scene

    sc, base = _load(scene)
    try:
        params = ReferenceParams(spp=spp, max_depth=max_depth, glossy_samples=glossy_samples,
                                 area_light_samples=area_samples, indirect_samples=indirect,
                                 indirect_bounces=bounces, seed=seed)
        loaded = load_scene(sc, directory_resolver(base))
        cam = loaded.camera
        if width or height:
            cam = replace(cam, width=width or cam.width, height=height or cam.height)
        last = [-1]

        def progress(frac: float, stage: str) -> None:
            pct = int(frac * 100)
            if pct >= last[0] + 10 or frac >= 1.0:
                last[0] = pct
                typer.echo(f"  {stage}: {pct:3d}%", err=True)

        out = ReferenceRenderer(loaded.runtime).render(cam, params, progress)
        meta = {"camera": cam.to_dict(), "scene_hash": loaded.scene_hash, "render_params": params.to_dict(),
                "method": "reference", "timings": out.timings}
        output.parent.mkdir(parents=True, exist_ok=True)
        write_image(output, out.radiance, exposure_stops=exposure, metadata=meta)
        if aovs:
            stem = output.with_suffix("")
            write_image(f"{stem}.depth.exr", out.depth, metadata=meta)
            write_image(f"{stem}.normal.exr", out.normal, metadata=meta)
            write_image(f"{stem}.object_id.exr", out.object_id.astype("float32"), metadata=meta)
    except EngineError as exc:
        _fail(str(exc))
    summary = {"output": str(output), "scene": sc.name, "scene_hash": loaded.scene_hash,
               "width": cam.width, "height": cam.height, "triangles": loaded.runtime.n_triangles,
               "timings_s": {k: round(v, 4) for k, v in out.timings.items()}, "rays": out.counts,
               "mesh_reports": loaded.mesh_reports}
    typer.echo(json.dumps(summary, indent=2))


@app.command()
def validate(scene: Annotated[str, typer.Argument(help="Scene JSON file or sample name")]) -> None:
    """Validate a scene file (and its meshes); exit 2 with the failing fields."""
    from engine.errors import EngineError
    from workers.scene_loader import directory_resolver, load_scene

    sc, base = _load(scene)
    try:
        loaded = load_scene(sc, directory_resolver(base))
    except EngineError as exc:
        _fail(str(exc))
    typer.echo(json.dumps({"valid": True, "scene_hash": loaded.scene_hash,
                           "triangles": loaded.runtime.n_triangles, "mesh_reports": loaded.mesh_reports},
                          indent=2))


@app.command()
def schema(output: Annotated[Path | None, typer.Option("-o", "--output")] = None) -> None:
    """Print (or write) the scene JSON Schema."""
    from api_schemas import scene_json_schema

    text = json.dumps(scene_json_schema(), indent=2, sort_keys=True) + "\n"
    if output is None:
        sys.stdout.write(text)
    else:
        output.write_text(text)


@app.command()
def samples() -> None:
    """List the sample scenes shipped with the service."""
    from samples import sample_names, sample_path

    for n in sample_names():
        typer.echo(f"{n}\t{sample_path(n)}")


# ============================================================================ service processes

DEFAULT_API = "http://127.0.0.1:8000"
ApiOpt = Annotated[str, typer.Option("--api", envvar="IBR_API_URL", help="API base URL")]
KeyOpt = Annotated[str | None, typer.Option("--api-key", envvar="IBR_API_KEY", help="API key (Bearer)")]


@app.command()
def up(
    data_dir: Annotated[Path, typer.Option(envvar="IBR_DATA_DIR", help="Data directory")] = Path("~/.ibr"),
    port: Annotated[int, typer.Option(help="API port on 127.0.0.1")] = 8000,
    samples_: Annotated[bool, typer.Option("--samples/--no-samples", help="Load the sample scenes")] = True,
    demo: Annotated[str | None, typer.Option(help="Render this sample scene once ready, save a PNG")] = None,
    demo_output: Annotated[Path, typer.Option(help="Where --demo writes its PNG")] = Path("out/demo.png"),
    exit_after_demo: Annotated[bool, typer.Option(help="Stop everything after the demo render")] = False,
) -> None:
    """Start Redis (embedded unless IBR_REDIS_URL is set), a bake and a render worker and the API."""
    from service.up import load_samples, run_forever, start_stack

    try:
        stack = start_stack(data_dir, port=port, log=typer.echo)
    except Exception as exc:  # start-up problems are reported, not tracebacks
        _fail(str(exc), code=3)
    ids: dict[str, str] = {}
    try:
        if samples_ or demo:
            ids = load_samples(stack.api_url, stack.env.get("IBR_API_KEY"), log=typer.echo)
        if demo:
            if demo not in ids:
                raise typer.Exit(_fail_code(f"--demo {demo}: not a sample scene ({', '.join(sorted(ids))})", 2))
            _render_and_fetch(stack.api_url, stack.env.get("IBR_API_KEY"), ids[demo], {}, demo_output, "png",
                              wait=True)
    except BaseException:
        stack.stop(timeout=10)
        raise
    if exit_after_demo:
        stack.stop()
        return
    typer.echo(f"ready: {stack.api_url}  (Ctrl-C to stop)")
    raise typer.Exit(run_forever(stack, log=typer.echo))


@app.command()
def api(
    host: Annotated[str, typer.Option(help="Bind address")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="Port")] = 8000,
    workers: Annotated[int, typer.Option(help="uvicorn worker processes")] = 1,
) -> None:
    """Run the HTTP API (settings from IBR_* environment variables)."""
    import uvicorn

    uvicorn.run("service.main:create_app", factory=True, host=host, port=port, workers=workers,
                access_log=False)  # the app logs every request itself (structured)


@app.command()
def worker(
    queue: Annotated[str, typer.Option(help="bake or render")],
    burst: Annotated[bool, typer.Option(help="Exit when the queue is empty")] = False,
    name: Annotated[str | None, typer.Option(help="Worker name")] = None,
) -> None:
    """Run one RQ worker on the bake or render queue (settings from IBR_* variables)."""
    if queue not in ("bake", "render"):
        _fail(f"--queue must be bake or render, got {queue!r}")
    from workers.runner import main as run_worker

    argv = ["--queue", queue] + (["--burst"] if burst else []) + (["--name", name] if name else [])
    raise typer.Exit(run_worker(argv))


# ============================================================================ client commands

scenes_app = typer.Typer(help="Scenes stored in the service", no_args_is_help=True)
jobs_app = typer.Typer(help="Jobs in the queues", no_args_is_help=True)
app.add_typer(scenes_app, name="scenes")
app.add_typer(jobs_app, name="jobs")
bakes_app = typer.Typer(help="Bakes (LDC + LLF) of stored scenes", no_args_is_help=True)
app.add_typer(bakes_app, name="bakes")


def _fail_code(msg: str, code: int) -> int:
    typer.echo(f"error: {msg}", err=True)
    return code


def _client(api_url: str, api_key: str | None) -> Client:
    from service.client import Client

    return Client(api_url, api_key=api_key)


def _call(fn: Callable[[], T]) -> T:
    """Run a client call; map API and connection errors to exit codes 2 / 3."""
    import httpx

    from service.client import ApiError

    try:
        return fn()
    except ApiError as exc:
        _fail(str(exc), code=2 if 400 <= exc.status < 500 and exc.status not in (401, 403, 429) else 3)
    except httpx.HTTPError as exc:
        _fail(f"cannot reach the API: {exc}", code=3)


def _scene_doc(scene_arg: str) -> tuple[dict[str, Any], dict[str, Path]]:
    """Scene JSON (validated locally first) and its mesh files, from a path or sample name."""
    sc, base = _load(scene_arg)
    doc = sc.model_dump(mode="json", exclude_defaults=False)
    from api_schemas.scene import MeshFileObject

    meshes = {o.path: base / o.path for o in sc.objects if isinstance(o, MeshFileObject)}
    for rel, p in meshes.items():
        if not p.is_file():
            _fail(f"mesh file {rel} not found next to the scene ({p})")
    return doc, meshes


@scenes_app.command("add")
def scenes_add(scene: Annotated[str, typer.Argument(help="Scene JSON file or sample name")],
               api_url: ApiOpt = DEFAULT_API, api_key: KeyOpt = None) -> None:
    """Upload a scene (and its mesh files); prints the scene id."""
    doc, meshes = _scene_doc(scene)
    with _client(api_url, api_key) as c:
        pub = _call(lambda: c.create_scene(doc, meshes or None))
    typer.echo(pub.id)


@scenes_app.command("list")
def scenes_list(api_url: ApiOpt = DEFAULT_API, api_key: KeyOpt = None) -> None:
    """List stored scenes."""
    with _client(api_url, api_key) as c:
        res = _call(c.list_scenes)
    for s in res.items:
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


def _render_and_fetch(api_url: str, api_key: str | None, scene_id: str, params: dict[str, Any],
                      output: Path | None, fmt: str, wait: bool, camera: dict[str, Any] | None = None,
                      method: str = "reference", bake: dict[str, Any] | None = None,
                      missing_bake: str | None = None) -> None:
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    from api_schemas.service import JobPublic

    with _client(api_url, api_key) as c:
        r = _call(lambda: c.render(scene_id, camera=camera, params=params or None, wait=2.0 if wait else 0.0,
                                   method=method, bake=bake or None,
                                   missing_bake="bake" if missing_bake == "bake" else None))
        typer.echo(f"artifact {r.artifact_key} ({r.status})", err=True)
        if r.bake is not None:
            typer.echo(f"waiting for bake {r.bake.key} ({r.bake.state}; follow it with "
                       f"'ibr bake {scene_id} --wait')", err=True)
        if r.artifact is None and not wait:
            if r.job is not None:
                typer.echo(r.job.id)
            return
        if r.artifact is None:
            with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.percentage:>5.1f}%"),
                          TimeRemainingColumn(), transient=True) as bar:
                task = bar.add_task("render", total=1.0)

                def show(j: JobPublic) -> None:
                    bar.update(task, completed=j.progress.fraction, description=j.progress.stage or j.state)

                from service.client import ApiError

                try:
                    manifest = _call(lambda: c.wait_render(r, on_progress=show))
                except ApiError as exc:  # the job itself failed
                    _fail(str(exc), code=4)
        else:
            manifest = r.artifact
        if manifest.result.get("timings"):
            t = manifest.result["timings"]
            typer.echo("timings: " + ", ".join(f"{k}={v:.3f}s" for k, v in t.items()
                                               if isinstance(v, int | float)), err=True)
        counts = manifest.result.get("counts") or {}
        if "hole_pixels" in counts:
            typer.echo(f"hole pixels: {counts['hole_pixels']}, provenance: {counts.get('provenance')}", err=True)
        if output is not None:
            data = _call(lambda: c.download(manifest.key, "exr" if fmt == "exr" else "png"))
            output.parent.mkdir(parents=True, exist_ok=True)
            output.write_bytes(data)
            typer.echo(str(output))


@app.command()
def render(
    scene: Annotated[str, typer.Argument(help="Scene id, scene JSON file, or sample name (uploaded first)")],
    output: Annotated[Path | None, typer.Option("-o", "--output", help="Save the image (.png or .exr)")] = None,
    spp: Annotated[int | None, typer.Option(help="Antialiasing samples per pixel")] = None,
    indirect: Annotated[int | None, typer.Option(help="Indirect paths per pixel")] = None,
    bounces: Annotated[int | None, typer.Option(help="Bounces per indirect path")] = None,
    seed: Annotated[int | None, typer.Option(help="Random seed")] = None,
    method: Annotated[str, typer.Option(help="reference, ldc, ldc+llf or ldc+ibrt:k (k = 0..8)")] = "reference",
    ldc_resolution: Annotated[int | None, typer.Option(help="LDC methods: the bake's LDC resolution")] = None,
    llf_f: Annotated[int | None, typer.Option(help="LDC methods: the bake's LLF subdivision f")] = None,
    bake_missing: Annotated[bool, typer.Option("--bake-missing/--fail-missing",
                                               help="LDC methods: bake first when the bake is missing")] = False,
    wait: Annotated[bool, typer.Option("--wait/--no-wait", help="Follow the job with a progress bar")] = True,
    api_url: ApiOpt = DEFAULT_API,
    api_key: KeyOpt = None,
) -> None:
    """Request a render from the service, follow it with a progress bar and fetch the image."""
    import re

    params = {k: v for k, v in {"spp": spp, "indirect_samples": indirect, "indirect_bounces": bounces,
                                "seed": seed}.items() if v is not None}
    bake = {k: v for k, v in {"ldc_resolution": ldc_resolution, "llf_f": llf_f}.items() if v is not None}
    if method != "reference" and params:
        _fail("--spp/--indirect/--bounces/--seed apply to --method reference; LDC methods use the bake's settings")
    if re.fullmatch(r"[0-9a-f]{64}", scene):
        scene_id = scene
    else:
        doc, meshes = _scene_doc(scene)
        with _client(api_url, api_key) as c:
            scene_id = _call(lambda: c.create_scene(doc, meshes or None)).id
    fmt = "exr" if output is not None and output.suffix.lower() == ".exr" else "png"
    if output is not None and output.suffix.lower() not in (".png", ".exr"):
        _fail(f"{output}: the service delivers .png or .exr")
    _render_and_fetch(api_url, api_key, scene_id, params, output, fmt, wait, method=method, bake=bake,
                      missing_bake="bake" if bake_missing else None)


def _scene_id_of(scene: str, api_url: str, api_key: str | None) -> str:
    """A scene id as given, or the id of a scene file / sample uploaded first."""
    import re

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
    wait: Annotated[bool, typer.Option("--wait/--no-wait", help="Follow the bake's parts with a progress bar")] = False,
    api_url: ApiOpt = DEFAULT_API,
    api_key: KeyOpt = None,
) -> None:
    """Bake a scene's layered depth cube (+ light field when needed) for the LDC render methods; prints the key."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    from api_schemas.service import BakePublic
    from service.client import ApiError

    params = {k: v for k, v in {"ldc_resolution": ldc_resolution, "max_layers": max_layers, "llf": llf,
                                "llf_f": llf_f, "llf_resolution": llf_resolution,
                                "llf_chunk": llf_chunk}.items() if v is not None}
    scene_id = _scene_id_of(scene, api_url, api_key)
    with _client(api_url, api_key) as c:
        b = _call(lambda: c.bake(scene_id, params))
        typer.echo(f"bake {b.key} ({'cached' if b.cached else b.state})", err=True)
        if wait and b.state != "finished":
            with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.percentage:>5.1f}%"),
                          TimeRemainingColumn(), transient=True) as bar:
                task = bar.add_task("bake", total=1.0)

                def show(p: BakePublic) -> None:
                    bar.update(task, completed=p.progress.fraction, description=p.progress.stage or p.state)

                try:
                    b = _call(lambda: c.wait_bake(b, on_progress=show))
                except ApiError as exc:
                    _fail(str(exc), code=4)
        if b.plan is not None:
            typer.echo(f"plan: light field {'yes' if b.plan.get('bake_llf') else 'no'} ({b.plan.get('reason')}); "
                       f"parts: {', '.join(p.name for p in b.parts)}", err=True)
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
        _fail(f"{output}: the service delivers .png or .exr")
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
    scenes: Annotated[list[str], typer.Argument(help="Scene JSON files or sample names (inline meshes only)")],
    render_them: Annotated[bool, typer.Option("--render/--no-render", help="Also request a render of each")] = True,
    spp: Annotated[int | None, typer.Option(help="Antialiasing samples per pixel for the renders")] = None,
    follow: Annotated[bool, typer.Option(help="Follow the batch until every job ended")] = False,
    api_url: ApiOpt = DEFAULT_API,
    api_key: KeyOpt = None,
) -> None:
    """Submit many scenes (and renders of them) in one call; prints the batch id."""
    import time

    docs: list[Mapping[str, Any]] = []
    for s in scenes:
        doc, meshes = _scene_doc(s)
        if meshes:
            _fail(f"{s}: scenes with mesh files can't go in a batch; upload them with 'ibr scenes add'")
        docs.append(doc)
    with _client(api_url, api_key) as c:
        b = _call(lambda: c.batch(scenes=docs))
        if render_them:
            params = {"spp": spp} if spp else {}
            b = _call(lambda: c.batch(renders=[{"scene_id": sid, "params": params} for sid in b.scene_ids]))
        typer.echo(b.id)
        batch_id = b.id
        while follow:
            b = _call(lambda: c.get_batch(batch_id))
            typer.echo(f"  {b.progress.fraction * 100:5.1f}%  {b.counts}", err=True)
            if not any(b.counts.get(k, 0) for k in ("queued", "started")):
                break
            time.sleep(1.0)


if __name__ == "__main__":
    app()
