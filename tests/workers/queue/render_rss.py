"""``python -m tests.workers.queue.render_rss METHOD WIDTH HEIGHT SPP [PARAMS_JSON]``: run the real render job (render,
encode, publish) of the tiny scene at that size in this process, after a warm-up render at 16 x 16,
and print as JSON how much the process's peak RSS grew during the big one.

For reference renders only the scene is needed; for the LDC methods a tiny bake is published first
with the render worker's warm-up machinery (``workers.warmup``)."""

from __future__ import annotations

import json
import os
import resource
import sys
import tempfile
from typing import Any

import psutil


def _peak() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def main() -> None:
    method, w, h, spp = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
    tmp = tempfile.mkdtemp(prefix="ibr-render-rss-")
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
        run.render(camera={**cam, "width": 16, "height": 16}, **extra)
        before = max(psutil.Process().memory_info().rss, _peak())
        run.render(camera={**cam, "width": w, "height": h}, **extra)
        print(json.dumps({"grew_bytes": _peak() - before, "base_bytes": before}))


if __name__ == "__main__":
    main()
