"""First run on a fresh clone: how long until each method is ready, its first render, a warm restart.

``python -m bench.first_run [--repo PATH] [--write]`` clones the repository (``git clone``, default:
this checkout) into a temporary directory and starts ``ibr up`` from the clone (this interpreter,
``PYTHONPATH`` = the clone: the install is excluded) with an empty numba cache (a new
``NUMBA_CACHE_DIR``), as ``make run`` does on a fresh machine. It records:

1. cold start: seconds from the start of ``ibr up`` to ``/healthz`` answering, and from then until
   ``GET /v1/methods`` reports each method and job kind ready (the background warm-up), with the
   CPU time of the whole process tree;
2. the first render of each method once it is ready (``make run`` already running): ``reference``,
   ``ldc``, ``ldc+llf``, ``ldc+ibrt:1`` (after an LDC bake of the scene), a relight (after a dataset
   generated from the scene and its bake), a walkthrough (its bake and frames) -- each the time from
   the request to the finished result, the bakes timed apart;
3. warm restart: ``ibr up`` stopped and started again on the same data and numba cache: seconds to
   ``/healthz`` and until every kind is ready.

``--at-healthz`` measures instead what a user who does not wait for readiness gets: at the moment
``/healthz`` first answers (empty numba cache, the warm-up just started), a direct-light LDC bake of
the diffuse Cornell box (:data:`DIFFUSE_BAKE`) and an ``ldc`` render of it, then a ``reference``
render, each timed from ``/healthz``; a job whose kernels the warm-up has not compiled yet compiles
them itself, and loads those the warm-up has already written to the disk cache. Prints; writes
nothing.

Run it under the shared benchmark lock (``flock /tmp/bench.lock``): the cold warm-up keeps both
cores busy for minutes.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx

from service.client import Client
from service.up import free_port

REPO = Path(__file__).resolve().parents[1]
SCENE = "mirror_box"
WALK_SCENE = "cornell_animated"
SIZE = {"width": 128, "height": 128}
LDC_BAKE = {"ldc_resolution": 128, "max_layers": 8, "llf_resolution": 16, "llf_f": 1}
DIFFUSE_SCENE = "cornell_box"
DIFFUSE_BAKE = {"ldc_resolution": 128, "max_layers": 8, "indirect": {"mode": "off"}}


def _tree_cpu(pid: int) -> float:
    """User + system CPU seconds of ``pid`` and its descendants that are still alive (from /proc)."""
    tick = os.sysconf("SC_CLK_TCK")
    total = 0.0
    children: dict[int, list[int]] = {}
    stats: dict[int, list[str]] = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            parts = (d / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        stats[int(d.name)] = parts
        children.setdefault(int(parts[1]), []).append(int(d.name))
    todo = [pid]
    while todo:
        p = todo.pop()
        if p in stats:
            s = stats[p]
            total += (int(s[11]) + int(s[12]) + int(s[13]) + int(s[14])) / tick  # utime stime cutime cstime
        todo.extend(children.get(p, []))
    return total


class Stack:
    """``ibr up`` from the clone, its output in a log file."""

    def __init__(self, clone: Path, data: Path, cache: Path, port: int, log: Path):
        env = {k: v for k, v in os.environ.items() if not k.startswith("IBR_")}
        env.update(PYTHONPATH=str(clone), NUMBA_CACHE_DIR=str(cache), PYTHONUNBUFFERED="1")
        self.url = f"http://127.0.0.1:{port}"
        self.t0 = time.monotonic()
        with open(log, "ab") as out:
            self.proc = subprocess.Popen([sys.executable, "-m", "service.cli", "up", "--data-dir", str(data),
                                          "--port", str(port)], cwd=clone, env=env, stdout=out,
                                         stderr=subprocess.STDOUT, start_new_session=True)

    def since_start(self) -> float:
        return time.monotonic() - self.t0

    def cpu(self) -> float:
        return _tree_cpu(self.proc.pid)

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(timeout=10)


def _wait(cond: Callable[[], bool], timeout: float, what: str, poll: float = 0.2) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what}: not within {timeout:g} s")
        time.sleep(poll)


@contextlib.contextmanager
def _running(st: Stack, log: Path) -> Iterator[None]:
    """Stop the stack ``st`` on leaving; on an error, print the tail of its log ``log`` first."""
    try:
        yield
    except BaseException:
        print(log.read_text()[-5000:], file=sys.stderr)
        raise
    finally:
        st.stop()


def _healthy(url: str) -> bool:
    try:
        return httpx.get(f"{url}/healthz", timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


def wait_ready(st: Stack, timeout: float) -> tuple[float, dict[str, float], float]:
    """(seconds from start to /healthz, per kind seconds from /healthz to ready, CPU seconds of the
    stack until every kind was ready)."""
    _wait(lambda: _healthy(st.url), 300, "/healthz", poll=0.05)
    health = st.since_start()
    t_health = time.monotonic()
    ready: dict[str, float] = {}
    deadline = time.monotonic() + timeout
    cpu = 0.0
    while time.monotonic() < deadline:
        try:
            doc = httpx.get(f"{st.url}/v1/methods", timeout=5).json()
        except httpx.HTTPError:
            doc = {"methods": []}
        cpu = st.cpu()
        for m in doc["methods"]:
            if m["state"] in ("ready", "failed") and m["method"] not in ready:
                ready[m["method"]] = time.monotonic() - t_health
                if m["state"] == "failed":
                    print(f"  {m['method']}: warm-up step failed", file=sys.stderr)
        if doc["methods"] and len(ready) == len(doc["methods"]):
            return health, ready, cpu
        time.sleep(0.25)
    raise TimeoutError(f"not every kind ready within {timeout:g} s: {ready}")


def _timed(fn: Callable[[], Any]) -> float:
    t = time.perf_counter()
    fn()
    return time.perf_counter() - t


def first_renders(url: str) -> dict[str, float]:
    """Seconds of each first request, from the request to the finished result (module docstring)."""
    out: dict[str, float] = {}
    with Client(url, timeout=120) as c:
        ids = {s.name: s.id for s in c.iter_scenes()}
        sid = ids[SCENE]
        camera = {**c.get_scene_document(sid)["camera"], **SIZE}
        small = {**camera, "width": 64, "height": 64}
        out["reference"] = _timed(lambda: c.wait_render(c.render(sid, camera=camera, params={"spp": 4})))
        out["LDC bake (bake worker)"] = _timed(lambda: c.wait_bake(c.bake(sid, LDC_BAKE)))
        for method in ("ldc", "ldc+llf", "ldc+ibrt:1"):
            out[method] = _timed(lambda m=method: c.wait_render(c.render(sid, camera=camera, method=m,  # type: ignore[misc]
                                                                         bake=LDC_BAKE)))
        holder: dict[str, str] = {}

        def generate() -> None:
            g = c.generate_dataset(sid, placement={"region": "hemisphere", "spacing_deg": 30.0},
                                   params={"spp": 1, "max_depth": 1}, camera=small)
            holder["ds"] = c.wait_generation(g)
            c.wait_dataset_bake(c.bake_dataset(holder["ds"]))

        out["dataset generation + bake (bake worker)"] = _timed(generate)
        light = {"type": "point", "position": [2.0, 3.0, 2.0], "intensity": [5.0, 5.0, 5.0]}
        out["relight"] = _timed(lambda: c.wait_relight(c.relight(holder["ds"], [light])))
        frames = [{"camera": {"type": "perspective", "eye": [278.0, 273.0, 70.0], "look_at": [278.0, 220.0, 559.0],
                              "fov_y_deg": 60.0, "width": 32, "height": 24}, "time": t} for t in (0.0, 1.0)]
        out["walkthrough (bake + 2 frames)"] = _timed(lambda: c.wait_walkthrough(c.walkthrough(
            {"scene_id": ids[WALK_SCENE], "frames": frames, "bake": {"quality": "low"}})))
    return out


def requests_at_healthz(url: str) -> dict[str, float]:
    """Seconds from ``/healthz`` answering to each result of ``--at-healthz`` (module docstring)."""
    t0 = time.perf_counter()
    out: dict[str, float] = {}
    with Client(url, timeout=600) as c:
        ids: dict[str, str] = {}

        def loaded() -> bool:
            ids.update({s.name: s.id for s in c.iter_scenes()})
            return DIFFUSE_SCENE in ids

        _wait(loaded, 120, f"{DIFFUSE_SCENE} among the samples `ibr up` loads", poll=0.2)
        sid = ids[DIFFUSE_SCENE]
        out["sample scenes loaded"] = time.perf_counter() - t0
        camera = {**c.get_scene_document(sid)["camera"], **SIZE}
        c.wait_bake(c.bake(sid, DIFFUSE_BAKE))
        out[f"{DIFFUSE_SCENE} LDC bake, direct light (bake worker)"] = time.perf_counter() - t0
        c.wait_render(c.render(sid, camera=camera, method="ldc", bake=DIFFUSE_BAKE))
        out[f"{DIFFUSE_SCENE} ldc render after it"] = time.perf_counter() - t0
        c.wait_render(c.render(sid, camera=camera, params={"spp": 4}))
        out[f"{DIFFUSE_SCENE} reference render after them"] = time.perf_counter() - t0
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.first_run", description=__doc__)
    p.add_argument("--repo", type=Path, default=REPO, help="repository to clone (default: this checkout)")
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds to wait for every kind to be ready")
    p.add_argument("--write", action="store_true", help="write the results into docs/performance.md")
    p.add_argument("--at-healthz", action="store_true",
                   help="time a bake and the first renders requested the moment /healthz answers (prints only)")
    args = p.parse_args(argv)
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="ibr-first-run-", dir="/tmp") as tmp_s:
        tmp = Path(tmp_s)
        clone, data, cache, log = tmp / "clone", tmp / "data", tmp / "numba-cache", tmp / "up.log"
        t = time.perf_counter()
        subprocess.run(["git", "clone", "--quiet", str(args.repo), str(clone)], check=True)
        clone_s = time.perf_counter() - t
        commit = subprocess.run(["git", "-C", str(clone), "rev-parse", "--short", "HEAD"], check=True,
                                capture_output=True, text=True).stdout.strip()
        st = Stack(clone, data, cache, free_port(), log)
        if args.at_healthz:
            with _running(st, log):
                _wait(lambda: _healthy(st.url), 300, "/healthz", poll=0.05)
                print(f"cold: /healthz {st.since_start():.1f} s after start", flush=True)
                for k, v in requests_at_healthz(st.url).items():
                    print(f"  {k}: {v:.1f} s after /healthz", flush=True)
            return 0
        with _running(st, log):
            health, ready, cpu = wait_ready(st, args.timeout)
            print(f"cold: /healthz {health:.1f} s after start; ready after /healthz: {ready}; CPU {cpu:.0f} s",
                  flush=True)
            renders = first_renders(st.url)
            print(f"first renders: {renders}", flush=True)
        st = Stack(clone, data, cache, free_port(), log)
        try:
            w_health, w_ready, w_cpu = wait_ready(st, 300)
        finally:
            st.stop()
        print(f"warm restart: /healthz {w_health:.1f} s; ready after /healthz: {w_ready}", flush=True)
    load_after = os.getloadavg()[0]
    all_ready = max(ready.values())
    lines = [
        f"Fresh clone of {commit} (`git clone` {clone_s:.1f} s; install excluded: the existing virtualenv's "
        f"interpreter with `PYTHONPATH` = the clone), empty numba cache, `ibr up` (samples loaded); "
        f"{os.cpu_count()} cores, 1-minute load average {load_before:.1f} before and {load_after:.1f} after "
        "(other work shared the cores).",
        "",
        "| | seconds |",
        "|---|---:|",
        f"| cold start: `ibr up` to `/healthz` answering | {health:.1f} |",
        *[f"| cold: `{k}` ready (from `/healthz`) | {v:.1f} |" for k, v in ready.items()],
        f"| cold: every kind ready (the whole background warm-up), from `/healthz` | {all_ready:.1f} |",
        f"| cold: CPU time of the stack until then (both cores) | {cpu:.0f} |",
        *[f"| first request once ready: {k} | {v:.1f} |" for k, v in renders.items()],
        f"| warm restart: `ibr up` to `/healthz` answering | {w_health:.1f} |",
        f"| warm restart: every kind ready, from `/healthz` | {max(w_ready.values()):.1f} |",
    ]
    text = "\n".join(lines)
    print(text)
    if args.write:
        from bench.docs_writer import replace_block

        replace_block(REPO / "docs/performance.md", "first-run",
                      f"### First run on a fresh clone: `flock /tmp/bench.lock python -m bench.first_run --write`"
                      f"\n\n{text}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
