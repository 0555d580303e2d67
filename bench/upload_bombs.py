"""Upload bombs against a real API process held under a hard 1 GiB memory ceiling.

Starts the embedded Redis and ``uvicorn service.main:create_app`` (a local file store) with the API
process in a memory cgroup of its own whose limit is ``--ceiling-mib`` (cgroup v2 ``memory.max`` or
cgroup v1 ``memory.limit_in_bytes``, whichever this machine mounts writable; over it the kernel's
OOM killer ends the process), then sends each bomb once:

- PNG of zeros, 4000x4000 and 8000x8000 RGB (tens to hundreds of KiB; 192 MB and 768 MB as floats);
- a zip EXR of zeros, 8000x8000 with 16 half channels (4 GiB as floats);
- scenes whose inline mesh makes a JSON body over the API's body limit (``IBR_MAX_BODY_BYTES``),
  just under it (48 MiB, about 0.8 M vertices and as many triangles inline: over the JSON-document
  limit ``IBR_MAX_JSON_BYTES``) and just under the JSON-document limit;
- a PLY mesh upload whose header declares 2,000,000,000 vertices and faces (a few hundred bytes);
- a scene of 10,000 spheres at subdivision 8 (13 billion triangles once tessellated).

Measured per bomb: the HTTP status and message, the cgroup's peak memory during the request (its
counter reset before each one), whether the API process was still alive and answering, and the
cgroup's OOM kill count (an API killed is started again for the next bomb). At the end: whether
the API process mapped numba or llvmlite.

    flock /tmp/bench.lock python -m bench.upload_bombs [--ceiling-mib 1024]

Writes the ``upload_bombs`` block of docs/reliability.md and docs/data/upload_bombs.json.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import httpx

from bench.docs_writer import replace_block
from producer.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "reliability.md"
DATA = ROOT / "docs" / "data" / "upload_bombs.json"
MIB = 1 << 20


class MemoryCgroup:
    """A memory cgroup of its own (v2 if mounted writable, else v1) with a hard limit."""

    def __init__(self, limit_bytes: int):
        self.limit = limit_bytes
        name = f"ibr-bombs-{os.getpid()}"
        v2 = Path("/sys/fs/cgroup")
        if (v2 / "cgroup.controllers").exists() and "memory" in (v2 / "cgroup.subtree_control").read_text():
            self.kind, self.path = "v2", v2 / name
            self.path.mkdir()
            (self.path / "memory.max").write_text(str(limit_bytes))
            (self.path / "memory.swap.max").write_text("0")
        elif (Path("/sys/fs/cgroup/memory") / "memory.limit_in_bytes").exists():
            self.kind, self.path = "v1", Path("/sys/fs/cgroup/memory") / name
            self.path.mkdir()
            (self.path / "memory.limit_in_bytes").write_text(str(limit_bytes))
            swap = self.path / "memory.memsw.limit_in_bytes"
            if swap.exists():
                swap.write_text(str(limit_bytes))
        else:
            raise SystemExit("no writable memory cgroup (v2 memory.max or v1 memory.limit_in_bytes): run as root")

    def enter(self) -> None:
        """Move the calling process into the cgroup (``preexec_fn`` of the API process)."""
        (self.path / "cgroup.procs").write_text(str(os.getpid()))

    def limit_read(self) -> int:
        return int((self.path / ("memory.max" if self.kind == "v2" else "memory.limit_in_bytes")).read_text())

    def reset_peak(self) -> None:
        if self.kind == "v1":
            (self.path / "memory.max_usage_in_bytes").write_text("0")
        elif (self.path / "memory.peak").exists():
            try:
                (self.path / "memory.peak").write_text("0")  # kernels >= 6.12
            except OSError:
                pass

    def peak(self) -> int:
        return int((self.path / ("memory.peak" if self.kind == "v2" else "memory.max_usage_in_bytes")).read_text())

    def current(self) -> int:
        return int((self.path / ("memory.current" if self.kind == "v2" else "memory.usage_in_bytes")).read_text())

    def oom_kills(self) -> int:
        f = self.path / ("memory.events" if self.kind == "v2" else "memory.oom_control")
        for line in f.read_text().splitlines():
            k, _, v = line.partition(" ")
            if k == "oom_kill":
                return int(v)
        return 0

    def remove(self) -> None:
        for _ in range(50):
            try:
                self.path.rmdir()
                return
            except OSError:
                time.sleep(0.1)


# -- the bombs ------------------------------------------------------------------------------------

def _scene(objects: list[Any]) -> dict[str, Any]:
    return {"name": "bomb", "camera": {"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0.5, 0],
                                       "fov_y_deg": 40, "width": 32, "height": 24},
            "materials": [{"name": "m", "kd": [0.8, 0.8, 0.8]}], "objects": objects,
            "lights": [{"type": "point", "position": [2, 3, 2], "intensity": [10, 10, 10]}]}


def inline_mesh_body(target_bytes: int) -> bytes:
    """A ``{"scene": ...}`` JSON body of about ``target_bytes``: one inline mesh, half the bytes
    vertices and half faces (a strip of triangles over them)."""
    n = max(3, target_bytes // 2 // 30)
    verts = ",".join(f"[{(i % 1000) * 1e-3:.6f},{(i // 1000) * 1e-3:.6f},0.000001]" for i in range(n))
    faces = ",".join(f"[{i},{i + 1},{i + 2}]" for i in range(n - 2))
    mesh = '{"type":"mesh","material":"m","vertices":[' + verts + '],"faces":[' + faces + "]}"
    doc = json.dumps({"scene": _scene([])})
    return doc.replace('"objects": []', '"objects": [' + mesh + "]").encode()


def absurd_ply() -> bytes:
    return (b"ply\nformat binary_little_endian 1.0\nelement vertex 2000000000\nproperty float x\n"
            b"property float y\nproperty float z\nelement face 2000000000\nproperty list uchar int vertex_indices\n"
            b"end_header\n" + b"\0" * 256)


def spheres_body() -> bytes:
    objs = [{"type": "sphere", "radius": 0.1, "subdivisions": 8, "material": "m",
             "center": [0.3 * (i % 100), 0, 0.3 * (i // 100)]} for i in range(10_000)]
    return json.dumps({"scene": _scene(objs)}).encode()


Request = Callable[[httpx.Client], httpx.Response]


def bombs(tmp: Path, body_limit: int, json_limit: int) -> list[tuple[str, str, Request]]:
    """(name, what it is, how it is sent)."""
    from tests.service.api.test_upload_bombs import exr_file, png_bomb

    def upload(data: bytes) -> Request:
        digest = hashlib.sha256(data).hexdigest()
        return lambda c: c.put(f"/v1/datasets/uploads/{digest}", content=data)

    def post_json(body: bytes) -> Request:
        return lambda c: c.post("/v1/scenes", content=body, headers={"Content-Type": "application/json"})

    png4, png8 = png_bomb(4000, 4000, 3), png_bomb(8000, 8000, 3)
    exr = exr_file(tmp / "bomb.exr", 8000, 8000, 16)
    over, under = inline_mesh_body(body_limit + 16 * MIB), inline_mesh_body(body_limit - 8 * MIB)
    at_json_limit = inline_mesh_body(json_limit - MIB)
    ply = absurd_ply()
    ply_scene = json.dumps(_scene([{"type": "mesh_file", "path": "bomb.ply", "material": "m"}]))
    spheres = spheres_body()
    mib = 1 / MIB
    return [
        ("PNG 4000x4000 RGB", f"{len(png4) * mib:.2f} MiB, 192 MB as floats: dataset image upload",
         upload(png4)),
        ("PNG 8000x8000 RGB", f"{len(png8) * mib:.2f} MiB, 768 MB as floats: dataset image upload",
         upload(png8)),
        ("EXR 8000x8000, 16 channels", f"{len(exr) * mib:.2f} MiB, 4 GiB as floats: dataset image upload",
         upload(exr)),
        ("inline-vertex scene over the body limit", f"{len(over) * mib:.0f} MiB JSON", post_json(over)),
        ("inline-vertex scene under the body limit", f"{len(under) * mib:.0f} MiB JSON, about "
         f"{len(under) // 60 / 1e6:.1f} M vertices and as many triangles", post_json(under)),
        ("inline-vertex scene under the JSON-document limit", f"{len(at_json_limit) * mib:.0f} MiB JSON, about "
         f"{len(at_json_limit) // 60 / 1e6:.2f} M vertices and as many triangles", post_json(at_json_limit)),
        ("PLY declaring 2e9 vertices and faces", f"{len(ply)} B mesh file in a multipart scene",
         lambda c: c.post("/v1/scenes", files={"scene": (None, ply_scene),
                                               "bomb.ply": ("bomb.ply", ply, "application/octet-stream")})),
        ("10,000 spheres at subdivision 8", f"{len(spheres) * mib:.1f} MiB JSON, 13 billion triangles "
         "once tessellated", post_json(spheres)),
    ]


def message(r: httpx.Response) -> str:
    try:
        body = r.json()
    except ValueError:
        return r.text[:300]
    if isinstance(body, dict):
        if body.get("errors"):
            e = body["errors"][0]
            return f"{e.get('type')}: {e.get('message')}"
        return str(body.get("detail") or body.get("title") or body)[:300]
    return str(body)[:300]


def maps_numba(pid: int) -> bool:
    try:
        maps = Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return False
    return "numba" in maps or "llvmlite" in maps


def run(args: argparse.Namespace) -> dict[str, Any]:
    from producer.embedded import start_embedded_redis
    from service.up import free_port

    rows: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory(prefix="ibr-bombs-", dir="/tmp") as d:
        tmp = Path(d)
        defaults = Settings()
        body_limit, json_limit = defaults.max_body_bytes, defaults.max_json_bytes
        print("building the bombs...", flush=True)
        plan = bombs(tmp, body_limit, json_limit)
        server = start_embedded_redis(tmp / "redis")
        cg = MemoryCgroup(args.ceiling_mib * MIB)
        port = free_port()
        env = {**os.environ, "IBR_REDIS_URL": server.url, "IBR_STORE_URL": f"file://{tmp / 'store'}",
               "IBR_DATA_DIR": str(tmp / "data"), "IBR_LOG_JSON": "false", "TMPDIR": str(tmp),
               "PYTHONPATH": str(ROOT), "IBR_MAX_BODY_BYTES": str(body_limit)}
        env.pop("IBR_API_KEYS", None)
        log = open(tmp / "api.log", "wb")  # noqa: SIM115 - closed below
        url = f"http://127.0.0.1:{port}"
        restarts = 0

        def start_api(c: httpx.Client) -> subprocess.Popen[bytes]:
            proc = subprocess.Popen([sys.executable, "-m", "uvicorn", "service.main:create_app", "--factory",
                                     "--host", "127.0.0.1", "--port", str(port), "--no-access-log"],
                                    cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT,
                                    preexec_fn=cg.enter)  # noqa: PLW1509
            deadline = time.monotonic() + 120
            while True:
                try:
                    if c.get("/readyz").status_code == 200:
                        return proc
                except httpx.HTTPError:
                    pass
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise SystemExit(f"the API did not start:\n{(tmp / 'api.log').read_text()[-3000:]}")
                time.sleep(0.3)

        api: subprocess.Popen[bytes] | None = None
        try:
            with httpx.Client(base_url=url, timeout=300) as c:
                api = start_api(c)
                from tests.service.api.test_upload_bombs import exr_file

                warm = exr_file(tmp / "warm.exr", 16, 16, 3, "float")  # imports OpenImageIO, warms the path
                c.put(f"/v1/datasets/uploads/{hashlib.sha256(warm).hexdigest()}", content=warm)
                idle = cg.current()
                print(f"API up in cgroup {cg.kind} {cg.path} (limit {cg.limit_read() / MIB:.0f} MiB), "
                      f"{idle / MIB:.0f} MiB charged when idle", flush=True)
                for name, what, send in plan:
                    cg.reset_peak()
                    kills = cg.oom_kills()
                    t0 = time.monotonic()
                    try:
                        r = send(c)
                        status, msg = r.status_code, message(r)
                    except httpx.HTTPError as exc:
                        status, msg = None, f"no answer: {exc!r}"
                    took = time.monotonic() - t0
                    peak = cg.peak()
                    alive = api.poll() is None
                    try:
                        answers = alive and c.get("/readyz").status_code == 200
                    except httpx.HTTPError:
                        answers = False
                    rows.append({"bomb": name, "what": what, "status": status, "message": msg,
                                 "peak_mib": round(peak / MIB, 1), "seconds": round(took, 1), "api_alive": alive,
                                 "api_answers": answers, "oom_kills": cg.oom_kills() - kills})
                    print(rows[-1], flush=True)
                    if not alive:  # the next bombs need an API: start it again, as a supervisor would
                        restarts += 1
                        api = start_api(c)
                numba = maps_numba(api.pid)
        finally:
            if api is not None:
                api.terminate()
                try:
                    api.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    api.kill()
                    api.wait(timeout=10)
            log.close()
            server.stop()
            cg.remove()
    return {"ceiling_mib": args.ceiling_mib, "cgroup": cg.kind, "body_limit_mib": body_limit // MIB,
            "json_limit_mib": json_limit // MIB, "idle_mib": round(idle / MIB, 1), "api_mapped_numba": numba,
            "api_restarts": restarts, "bombs": rows}


def table(res: dict[str, Any]) -> str:
    rows = res["bombs"]
    lines = [
        f"`flock /tmp/bench.lock python -m bench.upload_bombs --ceiling-mib {res['ceiling_mib']}` "
        f"(the API process, uvicorn, in a memory cgroup {res['cgroup']} of its own limited to "
        f"{res['ceiling_mib']} MiB, swap included; body limit {res['body_limit_mib']} MiB, JSON-document limit "
        f"{res.get('json_limit_mib', res['body_limit_mib'])} MiB; {res['idle_mib']:.0f} "
        "MiB charged to the cgroup when idle, after a warm-up upload). Peak = the cgroup's peak memory during "
        "that request.",
        "",
        "| bomb | size | answer | peak MiB | s | API alive and ready after |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        msg = r["message"].replace("|", "\\|")
        if len(msg) > 220:
            msg = msg[:217] + "..."
        lines.append(f"| {r['bomb']} | {r['what']} | {r['status']}: {msg} | {r['peak_mib']:.0f} | {r['seconds']} | "
                     f"{'yes' if r['api_alive'] and r['api_answers'] else 'NO'} |")
    kills = sum(r["oom_kills"] for r in rows)
    lines += [
        "",
        f"- OOM kills in the API's cgroup: {kills} (after one the API is started again for the next bomb); "
        f"the API process mapped numba or llvmlite: {'yes' if res['api_mapped_numba'] else 'no'}.",
    ]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ceiling-mib", type=int, default=1024, help="the API process's hard memory limit")
    ap.add_argument("--no-write", action="store_true")
    args = ap.parse_args(argv)
    res = run(args)
    print(json.dumps({k: v for k, v in res.items() if k != "bombs"}))
    if args.no_write:
        return
    DATA.parent.mkdir(parents=True, exist_ok=True)
    DATA.write_text(json.dumps(res, indent=2) + "\n")
    replace_block(DOC, "upload_bombs", table(res))


if __name__ == "__main__":
    main()
