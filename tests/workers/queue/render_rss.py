"""``python -m tests.workers.queue.render_rss METHOD WIDTH HEIGHT SPP [PARAMS_JSON]``: run the real render
job (render, encode, publish) of the tiny scene at that size in this process, after a warm-up render at
64 x 64 (four wavefront chunks: the pipelined path), and print as JSON how much the process's peak RSS
grew during the big one and its wall and CPU seconds. The peak is the kernel's VmHWM, reset after the
warm-up (``/proc/self/clear_refs``): on a cold numba cache the warm-up compiles every kernel, and the
compiler's own peak would otherwise hide the render's.

For reference renders only the scene is needed; for the LDC methods a tiny bake is published first
with the render worker's warm-up machinery (``workers.warmup``)."""

from __future__ import annotations

import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any


def _status_kib(field: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise RuntimeError(f"/proc/self/status has no {field}")


def _reset_peak() -> None:
    Path("/proc/self/clear_refs").write_text("5")  # 5: reset the peak RSS (VmHWM) to the current RSS


def main() -> None:
    method, w, h, spp = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
    with tempfile.TemporaryDirectory(prefix="ibr-render-rss-") as tmp:
        os.environ["IBR_STORE_URL"] = tmp

        from producer.store import open_store
        from workers import warmup

        store = open_store(tmp)
        run = warmup._Run(store)
        cam = dict(warmup.WARMUP_SCENE["camera"])
        with warmup._scratch_jobs(store):
            run.scene()
            params = json.loads(sys.argv[5]) if len(sys.argv) > 5 else {}
            extra: dict[str, Any] = {"params": {**params, "spp": spp}}
            if method != "reference":
                run.ldc_bake()
                extra = {"method": method, "bake": run.bake_params.model_dump(mode="json")}
            run.render(camera={**cam, "width": 64, "height": 64}, **extra)
            _reset_peak()
            before = _status_kib("VmRSS") * 1024
            t0, c0 = time.perf_counter(), time.process_time()
            run.render(camera={**cam, "width": w, "height": h}, **extra)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            print(json.dumps({"grew_bytes": _status_kib("VmHWM") * 1024 - before, "base_bytes": before,
                              "wall_s": wall, "cpu_s": cpu}))


if __name__ == "__main__":
    main()
