"""Cost of the reference renderer's rect-light test (rays that see lights, engine/reference.py) on
a scene without mirrors or glossy surfaces: the diffuse Cornell box, one rect light in view.

Wraps the reference renderer's ``_rect_hits`` (engine/path_vertex.py) with a timer and prints, per
render, the render's wall time, the time spent in the test (summed over the threads that ran it:
the pipelines, or the pieces of a batch split over the thread pool) and the rays it tested.
Run under the benchmark lock:

    flock /tmp/bench.lock python -m bench.reference_light_test_cost
"""

from __future__ import annotations

import argparse
import threading
import time
from dataclasses import replace

from api_schemas.scene import load_scene_file
from engine import reference as R
from engine.reference import ReferenceParams, ReferenceRenderer
from workers.scene_loader import directory_resolver, load_scene


def main(argv: list[str] | None = None) -> None:
    import samples

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args(argv)
    ls = load_scene(load_scene_file(samples.sample_path("cornell_box")), directory_resolver(samples.SAMPLES_DIR))
    cam = replace(ls.camera, width=args.res, height=args.res)
    r = ReferenceRenderer(ls.runtime)
    p = ReferenceParams(spp=16, max_depth=4, area_light_samples=4, indirect_samples=16, indirect_bounces=2)
    r.render(replace(cam, width=32, height=32), p)  # warm-up (numba, BVH)
    orig = R._rect_hits
    spent = [0.0, 0]
    lock = threading.Lock()

    def timed(lo: int, hi: int, *a: object) -> None:
        t0 = time.perf_counter()
        orig(lo, hi, *a)
        with lock:
            spent[0] += time.perf_counter() - t0
            spent[1] += hi - lo

    R._rect_hits = timed  # type: ignore[assignment]
    try:
        for _ in range(args.repeat):
            spent[:] = [0.0, 0]
            t0 = time.perf_counter()
            out = r.render(cam, p)
            tot = time.perf_counter() - t0
            print(f"render {tot:.2f} s, rect-light test {1000 * spent[0]:.1f} ms on {spent[1]} rays "
                  f"({100 * spent[0] / tot:.2f} %), rays: {out.counts}", flush=True)
    finally:
        R._rect_hits = orig


if __name__ == "__main__":
    main()
