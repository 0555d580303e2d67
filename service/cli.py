"""The ``ibr`` command line of the service: the client commands (``ibr_client.cli``: scenes,
renders, bakes, batches, datasets, relighting, walkthroughs, jobs) plus the commands that run the
service or the engine in this process: ``ibr up`` (everything on one machine), ``ibr api``,
``ibr worker --queue bake|render``, ``ibr render-local`` and ``ibr validate`` (no service).

Exit codes: 0 ok, 2 bad input (with a message naming the field or file), 3 the
service could not be reached or failed the request, 4 the job failed.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Annotated

import typer

from ibr_client.cli import app, fail, fail_code, load_scene_arg, render_and_fetch, say
from service.up import load_samples, run_forever, start_stack

__all__ = ["app"]


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
    # deferred on purpose: the engine's renderer imports numba and Embree, which only the local
    # commands need (the client commands start without them)
    from engine.errors import EngineError
    from engine.imageio import write_image
    from engine.reference import ReferenceParams, ReferenceRenderer
    from workers.scene_loader import directory_resolver, load_scene

    sc, base = load_scene_arg(scene)
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
        fail(str(exc))
    summary = {"output": str(output), "scene": sc.name, "scene_hash": loaded.scene_hash,
               "width": cam.width, "height": cam.height, "triangles": loaded.runtime.n_triangles,
               "timings_s": {k: round(v, 4) for k, v in out.timings.items()}, "rays": out.counts,
               "mesh_reports": loaded.mesh_reports}
    typer.echo(json.dumps(summary, indent=2))


@app.command()
def validate(scene: Annotated[str, typer.Argument(help="Scene JSON file or sample name")]) -> None:
    """Validate a scene file (and its meshes); exit 2 with the failing fields."""
    # deferred on purpose: the scene loader imports the engine (numba, Embree)
    from engine.errors import EngineError
    from workers.scene_loader import directory_resolver, load_scene

    sc, base = load_scene_arg(scene)
    try:
        loaded = load_scene(sc, directory_resolver(base))
    except EngineError as exc:
        fail(str(exc))
    typer.echo(json.dumps({"valid": True, "scene_hash": loaded.scene_hash,
                           "triangles": loaded.runtime.n_triangles, "mesh_reports": loaded.mesh_reports},
                          indent=2))


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
    try:
        stack = start_stack(data_dir, port=port, log=say)
    except Exception as exc:  # start-up problems are reported, not tracebacks
        fail(str(exc), code=3)
    ids: dict[str, str] = {}
    try:
        if samples_ or demo:
            ids = load_samples(stack.api_url, stack.env.get("IBR_API_KEY"), log=say)
        if demo:
            if demo not in ids:
                raise typer.Exit(fail_code(f"--demo {demo}: not a sample scene ({', '.join(sorted(ids))})", 2))
            render_and_fetch(stack.api_url, stack.env.get("IBR_API_KEY"), ids[demo], {}, demo_output, "png",
                             wait=True)
    except BaseException:
        stack.stop(timeout=10)
        raise
    if exit_after_demo:
        stack.stop()
        return
    say(f"ready: {stack.api_url}  (Ctrl-C to stop)")
    raise typer.Exit(run_forever(stack, log=say))


@app.command()
def api(
    host: Annotated[str, typer.Option(help="Bind address")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="Port")] = 8000,
    workers: Annotated[int, typer.Option(help="uvicorn worker processes")] = 1,
) -> None:
    """Run the HTTP API (settings from IBR_* environment variables)."""
    import uvicorn  # deferred on purpose: only ``ibr api`` serves HTTP from this process

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
        fail(f"--queue must be bake or render, got {queue!r}")
    from workers.runner import main as run_worker  # deferred on purpose: the worker runtime imports numba

    argv = ["--queue", queue] + (["--burst"] if burst else []) + (["--name", name] if name else [])
    raise typer.Exit(run_worker(argv))


if __name__ == "__main__":  # python -m service.cli (bench.first_run starts the stack from a clone this way)
    app()
