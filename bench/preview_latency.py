"""Preview interaction latency: orbit a BAKED sample scene in the browser page.

Starts the real stack on this machine (embedded Redis, one bake and one render worker, the API via
uvicorn) in a temporary data directory, loads the sample scenes, bakes ``--scene`` through the API
(``POST /v1/scenes/{id}/bakes``, LDC resolution ``--ldc``, light field ``auto``) and waits for it, then
for each method of ``--methods`` opens the preview page in Debian's chromium (Playwright, headless) at
``?size=512&scene=<sample>&method=<method>&ldc=<res>`` (the page picks the finished bake) and drags
the view N times, one mouse move per step, waiting after each for the new image.

Latency per step = the page's own instrumentation (``window.__preview``): ``performance.now()`` at
the pointer event that changed the camera to the ``load`` event of the image showing that camera:
throttling, the request, queueing, the render job, polling, PNG transfer and decode. The methods
are measured in the same run on the same stack, so their ratio is meaningful on this noisy machine.

    python -m bench.preview_latency [--scene teapot_glossy] [--size 512] [--steps 40] [--ref-steps 10]
                                    [--ldc 256] [--methods ldc+llf,reference] [--spp 4]

Writes the ``preview_latency`` block of docs/performance.md (``--no-doc`` to only print).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import tempfile
import time
from datetime import date
from pathlib import Path
from typing import Any
from urllib.parse import quote

import httpx
from playwright.sync_api import Browser, sync_playwright

from bench.docs_writer import replace_block
from service.up import free_port, load_samples, start_stack

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "performance.md"
CHROMIUM = "/usr/bin/chromium"
LAUNCH_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
               "--disable-sync", "--no-first-run"]


def pct(xs: list[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, int(round(q * (len(s) - 1))))]


def bake(api: str, scene_id: str, ldc: int) -> dict[str, Any]:
    """Bake the scene through the API and wait until it is finished; its final state and wall time."""
    t0 = time.perf_counter()
    b = httpx.post(f"{api}/v1/scenes/{scene_id}/bakes", json={"ldc_resolution": ldc, "llf": "auto"},
                   timeout=60).json()
    while b["state"] not in ("finished", "failed", "canceled", "missing"):
        time.sleep(1.0)
        b = httpx.get(f"{api}/v1/scenes/{scene_id}/bakes/{b['key']}", timeout=60).json()
    if b["state"] != "finished":
        raise SystemExit(f"bake {b['key']} {b['state']}: {b.get('error')}")
    b["wall_s"] = time.perf_counter() - t0
    return b


def orbit(browser: Browser, url: str, steps: int, dx: float) -> dict[str, Any]:
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    page.set_default_timeout(180_000)
    page.goto(url)
    page.wait_for_function("window.__preview.loads >= 1")  # the scene's own view (warm-up)
    first = page.evaluate("window.__preview.last")
    box = page.locator("#viewport").bounding_box()
    assert box is not None
    x, y = box["x"] + box["width"] / 2 - steps * dx / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    rows: list[dict[str, Any]] = []
    for i in range(steps):
        loads = page.evaluate("window.__preview.loads")
        x += dx
        page.mouse.move(x, y)  # one pointermove -> one request
        page.wait_for_function(
            f"window.__preview.loads > {loads} && !window.__preview.scheduled && "
            "window.__preview.last.seq === window.__preview.requests")
        last = page.evaluate("window.__preview.last")
        t = last["timings"]
        rows.append({"step": i, "latency_ms": last["latency"], "status": last["status"], "method": last["method"],
                     "job_total_ms": 1000 * float(t.get("job_total", 0.0)),
                     "render_total_ms": 1000 * float(t.get("total", 0.0)),
                     "holes": last["counts"].get("hole_pixels")})
    page.mouse.up()
    error = page.locator("#error").inner_text() if page.locator("#error").is_visible() else ""
    page.close()
    if error:
        raise SystemExit(f"the page shows an error: {error}")
    lat = [r["latency_ms"] for r in rows]
    job = [r["job_total_ms"] for r in rows if r["job_total_ms"] > 0]
    ren = [r["render_total_ms"] for r in rows if r["render_total_ms"] > 0]
    holes = [r["holes"] for r in rows if isinstance(r["holes"], int)]
    return {
        "method": rows[0]["method"], "first_view_ms": first["latency"],
        "p50_ms": statistics.median(lat), "p95_ms": pct(lat, 0.95), "min_ms": min(lat), "max_ms": max(lat),
        "job_total_p50_ms": statistics.median(job) if job else None,
        "render_total_p50_ms": statistics.median(ren) if ren else None,
        "holes_p50": statistics.median(holes) if holes else None,
        "cached": sum(r["status"] == "cached" for r in rows),
        "rows": rows,
    }


def measure(scene: str, size: int, steps: int, spp: int, dx: float, ldc: int, methods: list[str],
            ref_steps: int) -> dict[str, Any]:
    for k in ("IBR_REDIS_URL", "IBR_STORE_URL", "IBR_API_KEYS"):
        os.environ.pop(k, None)
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="ibr-", dir="/tmp") as tmp:
        stack = start_stack(Path(tmp), port=free_port(), log=lambda s: None)
        try:
            ids = load_samples(stack.api_url, log=lambda s: None)
            scene_id = ids[scene] if scene in ids else next(
                s["id"] for s in httpx.get(f"{stack.api_url}/v1/scenes?limit=1000").json()["items"]
                if s["name"] == scene)
            b = bake(stack.api_url, scene_id, ldc) if any(m != "reference" for m in methods) else None
            results = []
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=LAUNCH_ARGS)
                for m in methods:
                    url = (f"{stack.api_url}/preview/?size={size}&spp={spp}&scene={scene}&method={quote(m)}"
                           f"&ldc={ldc}")
                    results.append(orbit(browser, url, ref_steps if m == "reference" else steps, dx))
                browser.close()
        finally:
            stack.stop()
    bake_info = None
    if b is not None:
        plan = b.get("plan") or {}
        bake_info = {"key": b["key"], "wall_s": b["wall_s"], "parts": len(b["parts"]),
                     "llf": bool(plan.get("bake_llf")), "ldc_resolution": ldc}
    return {"scene": scene, "size": size, "steps": steps, "ref_steps": ref_steps, "spp": spp, "dx_px": dx,
            "bake": bake_info, "methods": results, "load": (load_before, os.getloadavg()[0])}


def report(res: dict[str, Any], argv: str) -> str:
    def ms(v: float | None) -> str:
        return "n/a" if v is None else f"{v:,.0f} ms"

    by = {r["method"]: r for r in res["methods"]}
    cols = list(by)
    b = res["bake"]
    lines = [
        "## Browser preview: orbit latency",
        "",
        "`python -m bench.preview_latency` (loopback only, bounded).",
        "",
        f"Measured with `python -m bench.preview_latency {argv}` ({date.today().isoformat()}, "
        f"{os.cpu_count()} cores, {platform.machine()}, 1-minute load average {res['load'][0]:.1f} before and "
        f"{res['load'][1]:.1f} after: other work shared the cores; headless chromium, the API, Redis and the "
        "workers share the machine).",
        "",
        f"Orbiting `{res['scene']}` at {res['size']}x{res['size']}, drag steps of {res['dx_px']:g} px "
        f"({res['steps']} per LDC method, {res['ref_steps']} for `reference`, spp {res['spp']}), each waited "
        "for: time from the pointer event to the `load` event of the image showing that camera (the page's own "
        "`performance.now()` instrumentation). All methods ran in one run on one stack.",
    ]
    if b is not None:
        lines += ["", f"The scene was baked first through the API (LDC resolution {b['ldc_resolution']}, light field "
                  f"{'baked' if b['llf'] else 'not needed'}, {b['parts']} parts on one bake worker: "
                  f"{b['wall_s']:.0f} s); the page picks the finished bake."]
    lines += [
        "",
        "| measurement | " + " | ".join(f"`{c}`" for c in cols) + " |",
        "|---|" + "---:|" * len(cols),
        "| mouse move to new image, p50 / p95 | " + " | ".join(
            f"{ms(by[c]['p50_ms'])} / {ms(by[c]['p95_ms'])}" for c in cols) + " |",
        "| min / max | " + " | ".join(f"{ms(by[c]['min_ms'])} / {ms(by[c]['max_ms'])}" for c in cols) + " |",
        "| of which the render job (`job_total`), p50 | " + " | ".join(
            ms(by[c]['job_total_p50_ms']) for c in cols) + " |",
        "| of which the renderer itself (`total`), p50 | " + " | ".join(
            ms(by[c]['render_total_p50_ms']) for c in cols) + " |",
        "| hole pixels per view, median | " + " | ".join(
            "n/a" if by[c]["holes_p50"] is None else f"{by[c]['holes_p50']:,.0f}" for c in cols) + " |",
        "| first view of the scene (cold worker) | " + " | ".join(ms(by[c]['first_view_ms']) for c in cols) + " |",
        "| views answered from the artifact cache | " + " | ".join(
            f"{by[c]['cached']} of {len(by[c]['rows'])}" for c in cols) + " |",
    ]
    if "reference" in by and len(cols) > 1:
        ref = by["reference"]["p50_ms"]
        lines += ["", "p50 speed-up over the reference renderer in this run: " + ", ".join(
            f"`{c}` {ref / by[c]['p50_ms']:.1f}x" for c in cols if c != "reference") + "."]
    lines += [
        "",
        "Every step is a new camera, so nothing comes from the artifact cache. Besides the render itself the "
        "latency holds the page's request throttle (at most one view request per 100 ms while dragging), "
        "the API's server-side wait (it polls the job from 50 ms, growing 1.5x, for up to 0.25 s; then the "
        "page polls every 50 ms, backing off to 250 ms), the job's PNG/EXR encoding and store writes "
        "(`job_total` minus `total`), and the PNG transfer and decode in the browser.",
    ]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="teapot_glossy")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--ref-steps", type=int, default=10, help="drag steps for the (slow) reference method")
    ap.add_argument("--spp", type=int, default=4, help="reference renderer samples per pixel")
    ap.add_argument("--ldc", type=int, default=256, help="LDC resolution of the bake")
    ap.add_argument("--methods", default="ldc+llf,reference", help="comma list, measured in this order")
    ap.add_argument("--dx", type=float, default=6.0, help="pixels per drag step (0.01 rad per pixel)")
    ap.add_argument("--no-doc", action="store_true")
    a = ap.parse_args()
    t0 = time.perf_counter()
    res = measure(a.scene, a.size, a.steps, a.spp, a.dx, a.ldc, [m.strip() for m in a.methods.split(",")],
                  a.ref_steps)
    res["wall_s"] = time.perf_counter() - t0
    print(json.dumps({**res, "methods": [{k: v for k, v in m.items() if k != "rows"} for m in res["methods"]]},
                     indent=1))
    if not a.no_doc:
        argv = (f"--scene {a.scene} --size {a.size} --steps {a.steps} --ref-steps {a.ref_steps} --spp {a.spp} "
                f"--ldc {a.ldc} "
                f"--methods {a.methods}")
        replace_block(DOC, "preview_latency", report(res, argv))
        print(f"wrote the preview_latency block of {DOC}")


if __name__ == "__main__":
    main()
