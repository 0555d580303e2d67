"""``python -m tests.workers.queue.scene_build_rss N_SPHERES SUBDIVISIONS``: build, in this process, what a
worker builds for a scene of ``N_SPHERES`` icospheres at ``SUBDIVISIONS`` (tessellation, the runtime
scene's flat arrays, Embree's BVH) after a warm-up build of a tiny scene, and print as JSON the
triangles, how much the process's peak RSS grew (VmHWM, reset after the warm-up) and the seconds it took.

The warm-up compiles or loads every kernel the build uses, so neither the compiler's memory nor its
time counts."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from typing import Any


def _status_kib(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"/proc/self/status has no {field}")


def sphere_scene(n_spheres: int, subdivisions: int) -> dict[str, Any]:
    """A scene of ``n_spheres`` unit-spaced spheres in a row (one material, one point light)."""
    return {
        "camera": {"type": "perspective", "eye": [0, 0, 5], "look_at": [0, 0, 0], "fov_y_deg": 45.0, "width": 16,
                   "height": 16},
        "materials": [{"name": "m", "kd": [0.5, 0.5, 0.5]}],
        "lights": [{"type": "point", "position": [0, 3, 3], "intensity": [1, 1, 1]}],
        "objects": [{"type": "sphere", "center": [1.1 * i, 0, 0], "radius": 0.5, "subdivisions": subdivisions,
                     "material": "m"} for i in range(n_spheres)],
    }


def main() -> None:
    n, sub = int(sys.argv[1]), int(sys.argv[2])
    from api_schemas.scene import Scene
    from engine.raycast import make_caster
    from workers.scene_loader import load_scene

    def build(doc: dict[str, Any]) -> int:
        loaded = load_scene(Scene.model_validate(doc))
        caster = make_caster(loaded.runtime)
        del caster
        return int(loaded.runtime.n_triangles)

    build(sphere_scene(2, 1))
    doc = sphere_scene(n, sub)
    scene = Scene.model_validate(doc)  # the request's own validation is not the build
    Path("/proc/self/clear_refs").write_text("5")  # 5: reset the peak RSS (VmHWM) to the current RSS
    before = _status_kib("VmRSS") * 1024
    t0, c0 = time.perf_counter(), time.process_time()
    loaded = load_scene(scene)
    caster = make_caster(loaded.runtime)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    grew = _status_kib("VmHWM") * 1024 - before
    print(json.dumps({"triangles": int(loaded.runtime.n_triangles), "grew_bytes": grew, "wall_s": wall,
                      "cpu_s": cpu, "held": caster is not None}))


if __name__ == "__main__":
    main()
