"""The ``ibr`` command line.

Engine-side commands for now (the service commands arrive with the API):
``ibr render`` renders a scene file with the reference renderer, ``ibr validate``
checks a scene, ``ibr schema`` writes the scene JSON Schema, ``ibr samples``
lists the shipped sample scenes. Exit code 2 on bad input, with a message that
names the field or file.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import typer

app = typer.Typer(add_completion=False, no_args_is_help=True, help="ibr-service: image-based rendering")


def _fail(msg: str, code: int = 2) -> None:
    typer.echo(f"error: {msg}", err=True)
    raise typer.Exit(code)


def _load(scene_arg: str):
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


@app.command()
def render(
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
    """Render a scene with the reference renderer and write the image."""
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


if __name__ == "__main__":
    app()
