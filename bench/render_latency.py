"""Render latency through the API with a warm render worker (issue 4, "Interactive use": a 512x512 view
of a baked scene in under 250 ms end to end).

Starts the real stack on this machine (embedded Redis, one bake and one render worker, the API via uvicorn;
``service.up.start_stack``) in a temporary data directory with a local store, uploads the sample scenes,
bakes ``--scene`` through the API and waits for the bake, then per method of ``--methods`` sends
``--warmup`` + ``--n`` render requests (``--ref-n`` for ``reference``), each with a NEW camera (the scene's
camera orbited by a random angle, so no request is an artifact-cache hit):

- ``request``: ``POST /v1/renders?wait=30`` until its 200 answer (job queued, run by the warm render
  worker, artifact committed, the API's server-side polling noticed it);
- ``+ preview``: that plus ``GET image.png`` (the preview an interactive client shows).

Besides the client-side times it reports the job's own numbers from the artifact's result (render stages,
``encode``, ``store``, ``job_total``) and RQ's time stamps (queue wait, and the time from the job's end to
the API's answer, i.e. the server-side poll delay), so each request's time splits into its parts.

Then ``--encode-runs`` times of the encode + store path in THIS process on real data (the last LDC
render's images read back from the store): the previous implementation (``engine.imageio.write_image``
per image into a disk temp dir, EXR ZIP, float64 sRGB, libpng defaults; sequential blob writes) against
the job's current one (``workers.jobs.render.encode_render_blobs`` + ``write_artifact(max_workers=4)``),
so their ratio comes from one run on the same data.

    python -m bench.render_latency [--scene teapot_glossy] [--n 20] [--warmup 3] [--ref-n 3] [--ref-spp 1]
                                   [--methods ldc,ldc+llf,ldc+ibrt:1,reference] [--ldc 256] [--label after]

Saves the run under ``--label`` in ``docs/data/render_latency.json`` and rewrites the
``render_latency`` block of docs/performance.md from every label stored there (``--no-doc``: print only).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import socket
import statistics
import tempfile
import time
from datetime import date, datetime
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from bench.docs_writer import replace_block
from service.up import load_samples, start_stack

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "performance.md"
DATA = ROOT / "docs" / "data" / "render_latency.json"
STAGES = ("warp", "holes", "fill", "surfaces", "highlights", "gather", "ibrt")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def pct(xs: list[float], q: float) -> float:
    s = sorted(xs)
    return s[min(len(s) - 1, int(round(q * (len(s) - 1))))]


def _ts(value: str | None) -> float | None:
    return None if value is None else datetime.fromisoformat(value.replace("Z", "+00:00")).timestamp()


def orbit_camera(base: dict[str, Any], size: int, rng: np.random.Generator) -> dict[str, Any]:
    """The scene camera turned around its look-at point by a random azimuth (+-30 deg) and elevation
    (+-10 deg): a new view every call."""
    eye, at = np.array(base["eye"], float), np.array(base["look_at"], float)
    v = eye - at
    r = float(np.linalg.norm(v))
    az = math.atan2(v[0], v[2]) + math.radians(rng.uniform(-30, 30))
    el = math.asin(v[1] / r) + math.radians(rng.uniform(-10, 10))
    new = at + r * np.array([math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az)])
    return {**base, "eye": [float(x) for x in new], "width": size, "height": size}


def bake(c: httpx.Client, scene_id: str, ldc: int) -> dict[str, Any]:
    t0 = time.perf_counter()
    b = c.post(f"/v1/scenes/{scene_id}/bakes", json={"ldc_resolution": ldc, "llf": "auto"}).json()
    while b["state"] not in ("finished", "failed", "canceled", "missing"):
        time.sleep(0.5)
        b = c.get(f"/v1/scenes/{scene_id}/bakes/{b['key']}").json()
    if b["state"] != "finished":
        raise SystemExit(f"bake {b['key']} {b['state']}: {b.get('error')}")
    return {"key": b["key"], "wall_s": time.perf_counter() - t0, "parts": len(b["parts"])}


def one_request(c: httpx.Client, body: dict[str, Any], warmup: bool = False) -> dict[str, Any]:
    t0, w0 = time.perf_counter(), time.time()
    r = c.post("/v1/renders?wait=30", json=body)
    t1, w1 = time.perf_counter(), time.time()
    ans = r.json()
    if r.status_code == 202 and warmup:  # a cold worker compiles its kernels first: wait for it
        while ans.get("status") in ("queued", "running"):
            time.sleep(0.5)
            ans = c.post("/v1/renders?wait=30", json=body).json()
        t1, w1 = time.perf_counter(), time.time()
        ans["status"] = "finished" if ans.get("status") == "cached" else ans.get("status")
    if ans.get("status") != "finished":
        raise SystemExit(f"render {body['method']} answered {r.status_code}: {json.dumps(ans)[:500]}")
    png = c.get(ans["links"]["image.png"])
    t2 = time.perf_counter()
    png.raise_for_status()
    job = ans.get("job") or {}
    # the job's own result holds the store and job_total times too (the manifest is written before them)
    res = job.get("result") or ans["artifact"]["result"]
    tm = {k: 1e3 * float(v) for k, v in res["timings"].items() if isinstance(v, (int, float))}
    created, started, ended = (_ts(job.get(k)) for k in ("created_at", "started_at", "ended_at"))
    return {
        "request_ms": 1e3 * (t1 - t0), "with_preview_ms": 1e3 * (t2 - t0), "preview_bytes": len(png.content),
        "timings_ms": tm,
        "queue_ms": None if created is None or started is None else 1e3 * (started - max(created, w0)),
        "rq_job_ms": None if started is None or ended is None else 1e3 * (ended - started),
        "answer_after_end_ms": None if ended is None else 1e3 * (w1 - ended),
        "artifact_bytes": sum(b["size"] for b in ans["artifact"]["blobs"]),
        "blobs": {b["name"]: b["size"] for b in ans["artifact"]["blobs"]},
        "key": ans["artifact_key"],
    }


def summarize(rows: list[dict[str, Any]]) -> dict[str, Any]:
    def med(vals: list[float | None]) -> float | None:
        v = [x for x in vals if x is not None]
        return statistics.median(v) if v else None

    keys = sorted({k for r in rows for k in r["timings_ms"]})
    return {
        "n": len(rows),
        "request_p50_ms": med([r["request_ms"] for r in rows]), "request_p95_ms": pct([r["request_ms"] for r in rows],
                                                                                      0.95),
        "with_preview_p50_ms": med([r["with_preview_ms"] for r in rows]),
        "with_preview_p95_ms": pct([r["with_preview_ms"] for r in rows], 0.95),
        "timings_p50_ms": {k: med([r["timings_ms"].get(k) for r in rows]) for k in keys},
        "queue_p50_ms": med([r["queue_ms"] for r in rows]),
        "rq_job_p50_ms": med([r["rq_job_ms"] for r in rows]),
        "answer_after_end_p50_ms": med([r["answer_after_end_ms"] for r in rows]),
        "artifact_bytes_p50": med([r["artifact_bytes"] for r in rows]),
        "blobs_p50": {k: med([r["blobs"].get(k) for r in rows]) for k in rows[0]["blobs"]},
    }


# ---------------------------------------------------------------------------- in-process encode path


def _legacy_encode(out: dict[str, np.ndarray], meta: dict[str, Any]) -> dict[str, tuple[bytes, str]]:
    """The encode path before the render-latency work (kept here as the yardstick): one
    ``engine.imageio.write_image`` per image (atomic write with fsync into a disk temp dir, EXR ZIP,
    float64 sRGB transform, libpng's default zlib level) on a 4-thread pool."""
    from concurrent.futures import ThreadPoolExecutor

    import OpenImageIO as oiio

    from engine.imageio import write_image
    from workers.jobs.render import PROVENANCE_CODES

    def provenance(tmp: Path, codes: np.ndarray) -> bytes:
        path = tmp / "provenance.png"
        out = oiio.ImageOutput.create(str(path))
        spec = oiio.ImageSpec(codes.shape[1], codes.shape[0], 1, "uint8")
        spec.attribute("ibr:provenance_codes", json.dumps(PROVENANCE_CODES))
        out.open(str(path), spec)
        out.write_image(np.ascontiguousarray(codes, dtype=np.uint8)[:, :, None])
        out.close()
        return path.read_bytes()

    def enc(tmp: Path, name: str, px: Any, md: dict[str, Any]) -> bytes:
        write_image(tmp / name, px, metadata=md)
        return (tmp / name).read_bytes()

    with tempfile.TemporaryDirectory(prefix="ibr-render-") as tmpdir:
        tmp = Path(tmpdir)
        jobs = {"radiance.exr": (out["radiance"], meta),
                "preview.png": (out["radiance"], {**meta, "exposure_stops": 0.0}),
                "depth.exr": (out["depth"], {**meta, "aov": "depth"}),
                "normal.exr": (out["normal"], {**meta, "aov": "normal"}),
                "object_id.exr": (out["object_id"].astype("float32"), {**meta, "aov": "object_id"}),
                "material_id.exr": (out["material_id"].astype("float32"), {**meta, "aov": "material_id"})}
        with ThreadPoolExecutor(max_workers=4) as pool:
            fut = {n: pool.submit(enc, tmp, n, px, md) for n, (px, md) in jobs.items()}
            prov = pool.submit(provenance, tmp, out["provenance"])
            blobs = {n: (f.result(), "image/png" if n.endswith(".png") else "image/x-exr") for n, f in fut.items()}
            blobs["provenance.png"] = (prov.result(), "image/png")
    return blobs


def encode_profile(store_dir: Path, key: str, runs: int) -> dict[str, Any]:
    """Old vs new encode + store of one real LDC render (read back from the stack's store), same process."""
    from engine.imageio import read_image
    from workers.artifacts import read_blob, read_manifest, write_artifact
    from workers.jobs.render import encode_render_blobs
    from workers.store.local import LocalStore

    src = LocalStore(store_dir)
    manifest = read_manifest(src, key)
    assert manifest is not None
    arrays: dict[str, np.ndarray] = {}
    with tempfile.TemporaryDirectory(prefix="ibr-bench-") as tmpdir:
        for name in ("radiance.exr", "depth.exr", "normal.exr", "object_id.exr", "material_id.exr", "provenance.png"):
            p = Path(tmpdir) / name
            p.write_bytes(read_blob(src, key, name))
            px, _ = read_image(p, transfer="linear")
            arrays[name.split(".")[0]] = px
    out = {"radiance": arrays["radiance"], "depth": arrays["depth"][..., 0], "normal": arrays["normal"],
           "object_id": arrays["object_id"][..., 0].astype(np.int32),
           "material_id": arrays["material_id"][..., 0].astype(np.int32),
           "provenance": np.rint(arrays["provenance"][..., 0] * 255).astype(np.uint8)}
    meta = {"scene_id": manifest.inputs["scene"], "method": manifest.params.get("method", "?"), "artifact_key": key}
    times: dict[str, list[float]] = {"legacy_encode": [], "encode": [], "legacy_store": [], "store": [],
                                     "lean_encode": []}
    sizes: dict[str, dict[str, int]] = {}
    with tempfile.TemporaryDirectory(prefix="ibr-bench-store-", dir=store_dir.parent) as sdir:
        dst = LocalStore(Path(sdir))
        for i in range(runs):
            for label, fn, workers in (("legacy", _legacy_encode, 1), ("", None, 4)):
                t0 = time.perf_counter()
                blobs = fn(out, meta) if fn is not None else encode_render_blobs(out, meta)
                t1 = time.perf_counter()
                # a fresh artifact key per run: same blob writes, no "already committed" shortcut
                params = {"run": i, "label": label}
                akey = _key(params)
                write_artifact(dst, akey, "bench", {}, params, "bench", blobs, {}, max_workers=workers)
                t2 = time.perf_counter()
                times[f"{label}_encode".lstrip("_")].append(1e3 * (t1 - t0))
                times[f"{label}_store".lstrip("_")].append(1e3 * (t2 - t1))
                sizes[label or "new"] = {n: len(b) for n, (b, _) in blobs.items()}
            t0 = time.perf_counter()
            _lean_encode(out, meta)
            times["lean_encode"].append(1e3 * (time.perf_counter() - t0))
    return {"runs": runs, "p50_ms": {k: statistics.median(v) for k, v in times.items()}, "sizes": sizes}


def _lean_encode(out: dict[str, np.ndarray], meta: dict[str, Any]) -> dict[str, bytes]:
    """Only what an interactive client shows or downloads: preview.png and radiance.exr."""
    from concurrent.futures import ThreadPoolExecutor

    from engine.imageio import encode_image
    from workers.jobs.render import EXR_COMPRESSION, PNG_COMPRESSION

    with ThreadPoolExecutor(2) as pool:
        png = pool.submit(encode_image, "preview.png", out["radiance"], metadata={**meta, "exposure_stops": 0.0},
                          compression=PNG_COMPRESSION)
        exr = pool.submit(encode_image, "radiance.exr", out["radiance"], metadata=meta,
                          compression=EXR_COMPRESSION["radiance.exr"])
        return {"preview.png": png.result(), "radiance.exr": exr.result()}


def _key(params: dict[str, Any]) -> str:
    from workers.artifacts import artifact_key

    return artifact_key("bench", {}, params, "bench")


# ---------------------------------------------------------------------------- main measurement


def measure(scene: str, size: int, n: int, warmup: int, ref_n: int, ref_spp: int, ldc: int, methods: list[str],
            encode_runs: int, seed: int) -> dict[str, Any]:
    for k in ("IBR_REDIS_URL", "IBR_STORE_URL", "IBR_API_KEYS"):
        os.environ.pop(k, None)
    load_before = os.getloadavg()[0]
    rng = np.random.default_rng(seed)
    results: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="ibr-", dir="/tmp") as tmp:
        stack = start_stack(Path(tmp), port=_free_port(), log=lambda s: None)
        try:
            ids = load_samples(stack.api_url, log=lambda s: None)
            scene_id = ids[scene]
            with httpx.Client(base_url=stack.api_url, timeout=120) as c:
                base = c.get(f"/v1/scenes/{scene_id}").json()
                cam = base.get("scene", {}).get("camera") or _sample_camera(scene)
                b = bake(c, scene_id, ldc) if any(m != "reference" for m in methods) else None
                last_ldc_key = None
                for m in methods:
                    count = ref_n if m == "reference" else n
                    body: dict[str, Any] = {"scene_id": scene_id, "method": m}
                    if m == "reference":
                        body["params"] = {"spp": ref_spp}
                    else:
                        body["bake"] = {"ldc_resolution": ldc, "llf": "auto"}
                    rows = []
                    for i in range(warmup + count):
                        row = one_request(c, {**body, "camera": orbit_camera(cam, size, rng)}, warmup=i < warmup)
                        if i >= warmup:
                            rows.append(row)
                    results[m] = {**summarize(rows), "rows": rows}
                    if m != "reference":
                        last_ldc_key = rows[-1]["key"]
                    print(f"{m}: request p50 {results[m]['request_p50_ms']:.0f} ms, + preview p50 "
                          f"{results[m]['with_preview_p50_ms']:.0f} ms, job_total p50 "
                          f"{results[m]['timings_p50_ms'].get('job_total', float('nan')):.0f} ms", flush=True)
            enc = encode_profile(Path(stack.env["IBR_STORE_URL"]), last_ldc_key, encode_runs) \
                if last_ldc_key and encode_runs else None
        finally:
            stack.stop()
    return {"date": date.today().isoformat(), "scene": scene, "size": size, "n": n, "warmup": warmup, "ref_n": ref_n,
            "ref_spp": ref_spp, "ldc": ldc, "bake": b, "methods": results, "encode_profile": enc,
            "load": [load_before, os.getloadavg()[0]], "cores": os.cpu_count(), "machine": platform.machine()}


def _sample_camera(scene: str) -> dict[str, Any]:
    from samples import sample_path

    cam: dict[str, Any] = json.loads(sample_path(scene).read_text())["camera"]
    return cam


# ---------------------------------------------------------------------------- report


def _ms(v: float | None) -> str:
    return "n/a" if v is None else f"{v:,.0f}"


def report(runs: dict[str, Any]) -> str:
    lines = ["## Render latency through the API (warm render worker)", "",
             "`python -m bench.render_latency` (issue 4, interactive use: a 512x512 view of a baked scene in "
             "<= 250 ms end to end). Real stack: embedded Redis, one bake and one render worker, the API "
             "(uvicorn), local store, all on this 2-core machine with the client. Each request is a new camera "
             "(no artifact-cache hits); times in ms, p50 unless marked."]
    for label, res in runs.items():
        meths = list(res["methods"])
        by = res["methods"]
        lines += ["", f"### {label}: `{res['argv']}`", "",
                  f"{res['date']}, scene `{res['scene']}` {res['size']}x{res['size']}, LDC {res['ldc']} "
                  f"(bake {res['bake']['wall_s']:.0f} s, {res['bake']['parts']} parts)" if res.get("bake") else "",
                  f"{res['n']} requests per LDC method after {res['warmup']} warm-up ones, {res['ref_n']} for "
                  f"`reference` (spp {res['ref_spp']}); 1-minute load average {res['load'][0]:.1f} before and "
                  f"{res['load'][1]:.1f} after.", "",
                  "| | " + " | ".join(f"`{m}`" for m in meths) + " |", "|---|" + "---:|" * len(meths)]

        def row(title: str, f: Any, by: dict[str, Any] = by, meths: list[str] = meths) -> str:
            return f"| {title} | " + " | ".join(f(by[m]) for m in meths) + " |"

        def tm(k: str) -> Any:
            return lambda r: _ms(r["timings_p50_ms"].get(k))

        lines += [
            row("**request -> preview downloaded, p50 / p95**",
                lambda r: f"**{_ms(r['with_preview_p50_ms'])}** / {_ms(r['with_preview_p95_ms'])}"),
            row("request -> 200 answer, p50 / p95",
                lambda r: f"{_ms(r['request_p50_ms'])} / {_ms(r['request_p95_ms'])}"),
            row("queue wait (enqueue -> job start)", lambda r: _ms(r["queue_p50_ms"])),
            row("job (`job_total`)", tm("job_total")),
            row("... renderer (`total`)", tm("total")),
            row("... render stages warp / holes+fill / surfaces / highlights / gather / ibrt", lambda r: " / ".join(
                _ms(r["timings_p50_ms"].get(s)) if s != "holes" else
                _ms((r["timings_p50_ms"].get("holes") or 0) + (r["timings_p50_ms"].get("fill") or 0))
                for s in STAGES if s != "fill") if "warp" in r["timings_p50_ms"] else "n/a"),
            row("... encode (all images)", tm("encode")),
            row("... store (blobs + manifest)", tm("store")),
            row("RQ bookkeeping around the job", lambda r: _ms(
                None if r["rq_job_p50_ms"] is None or "job_total" not in r["timings_p50_ms"] else
                r["rq_job_p50_ms"] - r["timings_p50_ms"]["job_total"])),
            row("job end -> API answer (server-side polling)", lambda r: _ms(r["answer_after_end_p50_ms"])),
            row("request -> job end (the answer if the API saw the end at once)", lambda r: _ms(statistics.median(
                x["request_ms"] - x["answer_after_end_ms"] for x in r["rows"]
                if x["answer_after_end_ms"] is not None))),
            row("artifact size (KiB)", lambda r: f"{r['artifact_bytes_p50'] / 1024:,.0f}"),
        ]
        ldc_m = [m for m in meths if m != "reference"]
        if ldc_m:
            def share(r: dict[str, Any]) -> str:
                t, whole = r["timings_p50_ms"], r["with_preview_p50_ms"]
                enc = t["encode"] + t.get("store", 0.0)
                return (f"{t['total'] / whole:.0%} render / {enc / whole:.0%} encode+store"
                        f" / {(r['answer_after_end_p50_ms'] or 0.0) / whole:.0%} waiting for the API's next poll")

            shares = ", ".join(f"`{m}` {share(by[m])}" for m in ldc_m)
            lines += ["", f"Share of the request -> preview time (p50s): {shares}."]
        e = res.get("encode_profile")
        if e:
            p = e["p50_ms"]
            old, new = p["legacy_encode"] + p["legacy_store"], p["encode"] + p["store"]
            lines += ["", f"Encode + store of one real LDC render in one process ({e['runs']} runs each, alternating, "
                      f"p50, same data): previous path {p['legacy_encode']:.0f} + {p['legacy_store']:.0f} ms, current "
                      f"{p['encode']:.0f} + {p['store']:.0f} ms: **{old / new:.1f}x** (encode "
                      f"{p['legacy_encode'] / p['encode']:.1f}x, store {p['legacy_store'] / p['store']:.1f}x); "
                      f"encoding only preview + radiance (a possible lean mode) {p['lean_encode']:.0f} ms. "
                      "Blob sizes (KiB) previous -> current: " + ", ".join(
                          f"{n} {e['sizes']['legacy'][n] / 1024:,.0f} -> {e['sizes']['new'][n] / 1024:,.0f}"
                          for n in sorted(e["sizes"]["new"])) + "."]
    lines += ["", "### What the encode/store path does now, and what is left", "", *NOTES]
    return "\n".join(lines)


NOTES = [
    "- Images are encoded in memory (`engine.imageio.encode_image`: same checks and bytes as `write_image`, "
    "scratch file in `/dev/shm`, no fsync). Before, each image was written atomically with two fsyncs into a "
    "disk temp directory, read back, and written (with fsync) once more by the store.",
    "- The preview's sRGB transform uses exact code-value thresholds (one table look-up and one comparison per "
    "sample): bit-identical to `rint(tonemap_srgb(x) * 255)` in float64 (tests compare every threshold +-1 ulp), "
    "several times faster; `write_image` uses it too. PNGs are written with zlib level 1 and the 'sub' row "
    "filter (`compression=\"fast\"`, lossless, ~3-4x faster than libpng's default, files ~30-40 % larger).",
    "- The 6-7 images are encoded on 3 threads, the preview first; blob writes run on 4 threads (again the "
    "preview first) and the "
    "manifest is written only after every blob write returned (`write_artifact(max_workers=4)`; a failed "
    "blob write publishes nothing).",
    "- EXRs stay ZIP (lossless, the smallest files; readable everywhere). Measured alternatives on a 512x512 "
    "render: `none` encodes the radiance ~4x faster (~11 vs ~35-55 ms CPU) but makes it 1.8x larger (3.1 MiB); "
    "ZIP levels 1-3 save under 20 %; RLE does not shrink float radiance at all; PIZ is slower. Switching is one "
    "entry of `workers.jobs.render.EXR_COMPRESSION`.",
    "- Left outside this work, and the reason the end-to-end p50 hardly moves: the API's server-side wait "
    "polls the job at 50 ms, then 1.5x longer each time (`service/api/routes/renders.py`), i.e. at 50, 125, "
    "238, 406, 659 ms after the request, so every job that ends between ~240 and ~400 ms is answered at "
    "~410-440 ms (row \"job end -> API answer\"; the row below it is what an answer at the job's end would "
    "give). Blocking on the job's completion (RQ 3's result stream, `XREAD BLOCK`) or polling every ~10-20 ms "
    "would turn the job's savings into end-to-end savings. A lean "
    "request flag (preview + radiance only, see \"a possible lean mode\" above) needs a `RenderRequest` "
    "field in `api_schemas/service.py`, so it is not built.",
]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="teapot_glossy")
    ap.add_argument("--size", type=int, default=512)
    ap.add_argument("--n", type=int, default=20, help="measured requests per LDC method")
    ap.add_argument("--warmup", type=int, default=3)
    ap.add_argument("--ref-n", type=int, default=3, help="measured requests for the (slow) reference method")
    ap.add_argument("--ref-spp", type=int, default=1)
    ap.add_argument("--ldc", type=int, default=256, help="LDC resolution of the bake")
    ap.add_argument("--methods", default="ldc,ldc+llf,ldc+ibrt:1,reference")
    ap.add_argument("--encode-runs", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--label", default="current", help="name of this run in docs/data/render_latency.json")
    ap.add_argument("--no-doc", action="store_true")
    ap.add_argument("--doc-only", action="store_true", help="rewrite the doc block from the stored runs only")
    ap.add_argument("--import-run", metavar="FILE", help="with --doc-only: also store --label from FILE's runs")
    a = ap.parse_args()
    if a.doc_only:
        runs = json.loads(DATA.read_text()) if DATA.exists() else {}
        if a.import_run:
            runs[a.label] = json.loads(Path(a.import_run).read_text())[a.label]
            DATA.write_text(json.dumps(runs, indent=1) + "\n")
        replace_block(DOC, "render_latency", report(runs))
        print(f"wrote the render_latency block of {DOC}")
        return
    res = measure(a.scene, a.size, a.n, a.warmup, a.ref_n, a.ref_spp, a.ldc, [m.strip() for m in a.methods.split(",")],
                  a.encode_runs, a.seed)
    res["argv"] = (f"python -m bench.render_latency --scene {a.scene} --size {a.size} --n {a.n} --warmup {a.warmup} "
                   f"--ref-n {a.ref_n} --ref-spp {a.ref_spp} --ldc {a.ldc} --methods {a.methods} --label {a.label}")
    print(json.dumps({**res, "methods": {m: {k: v for k, v in r.items() if k != "rows"}
                                         for m, r in res["methods"].items()}}, indent=1))
    if a.no_doc:
        return
    runs = json.loads(DATA.read_text()) if DATA.exists() else {}
    runs[a.label] = res
    DATA.parent.mkdir(parents=True, exist_ok=True)
    DATA.write_text(json.dumps(runs, indent=1) + "\n")
    replace_block(DOC, "render_latency", report(runs))
    print(f"wrote the render_latency block of {DOC} and {DATA}")


if __name__ == "__main__":
    main()
