"""Profile numba kernels with Linux ``perf`` (symbols and instruction-level hot spots).

numba's JIT code has no symbols for perf. This tool writes the ``/tmp/perf-PID.map`` perf
reads for JIT code and can dump a kernel's machine code, so ``perf report`` names the
kernels and ``annotate`` shows the hottest instructions. It only sees functions compiled IN
THIS PROCESS (numba keeps the object code of fresh compiles only): run the workload with an
empty ``NUMBA_CACHE_DIR``.

Profile the LDC renderer (mirror_box, 512x512, LDC 256) for 12 s::

    python -m bench.numba_perf ldc --scene mirror_box --size 512 --seconds 12 --out /tmp/prof

It renders once (compiling), writes the map, starts ``perf record -F 4000 -p PID`` on itself
while rendering, and prints the per-kernel share of the samples. Then, for one kernel::

    python -m bench.numba_perf annotate /tmp/prof/perf.data /tmp/prof/code_trace_chunk_*.bin 10

Caveats (this VM): no hardware counters, perf samples on a timer, so a sample lands on the
instruction AFTER a stall (a cache-missing load's user shows the time); the bodies of
``prange`` loops are separate gufunc symbols that the map may miss (keep loop bodies in
their own njit functions, as the engine does). Needs ``perf`` and ``objdump`` (binutils).
"""

from __future__ import annotations

import argparse
import collections
import ctypes
import gc
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def write_perf_map() -> Path:
    """/tmp/perf-PID.map with every function of every numba dispatcher compiled in this
    process (address, size, mangled name); returns its path."""
    from numba.core.registry import CPUDispatcher

    ents: set[tuple[int, int, str]] = set()
    seen: set[int] = set()
    for obj in gc.get_objects():
        if not isinstance(obj, CPUDispatcher):
            continue
        for cres in list(obj.overloads.values()):
            lib = cres.library
            if id(lib) in seen:
                continue
            seen.add(id(lib))
            try:
                blob = lib._get_compiled_object()  # only fresh compiles keep it (not cache loads)
            except Exception:  # noqa: BLE001 - a cached or never-finalised library: no symbols
                continue
            with tempfile.NamedTemporaryFile(suffix=".o", delete=False) as f:
                f.write(blob)
                name = f.name
            try:
                out = subprocess.run(["nm", "-S", "--defined-only", name], capture_output=True, text=True).stdout
            finally:
                os.unlink(name)
            for line in out.splitlines():
                p = line.split()
                if len(p) == 4 and p[2] in "Tt":
                    try:
                        addr = lib.get_pointer_to_function(p[3])
                    except Exception:  # noqa: BLE001 - not an exported entry
                        addr = 0
                    if addr:
                        ents.add((addr, int(p[1], 16), p[3]))
    path = Path(f"/tmp/perf-{os.getpid()}.map")
    with path.open("w") as f:
        for a, s, n in sorted(ents):
            f.write(f"{a:x} {s:x} {n}\n")
    return path


def dump_code(patterns: list[str], out_dir: Path) -> list[Path]:
    """The machine code of the mapped functions whose names contain a pattern, as
    ``code_<pattern>_<address>.bin`` in out_dir (for ``annotate``)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    files = []
    for line in open(f"/tmp/perf-{os.getpid()}.map"):
        a, s, n = line.split()
        if n.startswith(("_ZN7cpython", "cfunc")):
            continue  # the Python and C wrappers
        hit = [p for p in patterns if p in n]
        if hit:
            addr, size = int(a, 16), int(s, 16)
            path = out_dir / f"code_{hit[0]}_{addr:x}.bin"
            path.write_bytes(ctypes.string_at(addr, size))
            files.append(path)
    return files


def summary(data: Path, top: int = 20) -> str:
    """Share of the samples per function (numba's mangled names shortened)."""
    out = subprocess.run(["perf", "report", "-i", str(data), "--no-children", "--sort", "symbol", "--stdio"],
                         capture_output=True, text=True).stdout
    acc: dict[str, float] = collections.defaultdict(float)
    for line in out.splitlines():
        m = re.match(r"\s*([0-9.]+)%\s+\[[.k]\]\s+(\S+)", line)
        if m:
            name = re.sub(r"B[0-9]+v.*", "", m.group(2))
            acc[name] += float(m.group(1))
    return "\n".join(f"{v:6.2f} %  {k}" for k, v in sorted(acc.items(), key=lambda x: -x[1])[:top])


def annotate(data: Path, code: Path, top: int = 12) -> str:
    """The ``top`` hottest instructions of one dumped function, each with the 6 before it."""
    base = int(re.search(r"_([0-9a-f]+)\.bin$", code.name).group(1), 16)
    size = code.stat().st_size
    ips = subprocess.run(["perf", "script", "-i", str(data), "-F", "ip"], capture_output=True, text=True).stdout.split()
    cnt: collections.Counter = collections.Counter()
    for x in ips:
        v = int(x, 16)
        if base <= v < base + size:
            cnt[v - base] += 1
    tot = max(1, sum(cnt.values()))
    dis = subprocess.run(["objdump", "-D", "-b", "binary", "-m", "i386:x86-64", str(code)], capture_output=True,
                         text=True).stdout
    lines = [ln for ln in dis.splitlines() if re.match(r"\s+[0-9a-f]+:", ln)]
    idx = {int(ln.split(":")[0], 16): i for i, ln in enumerate(lines)}
    rows = [f"samples in the function: {sum(cnt.values())} of {len(ips)}"]
    for off, c in cnt.most_common(top):
        i = idx.get(off)
        if i is None:
            continue
        rows.append(f"---- {c} ({100 * c / tot:.1f} %) at {off:x}")
        for ln in lines[max(0, i - 6):i + 2]:
            rows.append(f"{cnt.get(int(ln.split(':')[0], 16), 0):5d} {ln[:110]}")
    return "\n".join(rows)


def _profile_ldc(args) -> int:
    import numpy as np  # noqa: F401 - imported with the engine anyway

    from bench.ldc_accuracy import LLF_PARAMS, LLF_RES, scene_setup
    from engine.newviews.ldc import bake_ldc
    from engine.newviews.llf import bake_llf
    from engine.newviews.renderer import LDCViewRenderer

    out = Path(args.out)
    sc, caster, plan, cams, _ = scene_setup(args.scene, args.size, 6)
    ldc = bake_ldc(sc, caster, args.ldc, plan=plan)
    llf = bake_llf(sc, caster, 8, LLF_RES, params=LLF_PARAMS) if plan.needs_llf else None
    r = LDCViewRenderer(sc, ldc, llf, plan)
    for c in cams:
        r.render(c, args.method)
    write_perf_map()
    dump_code(["trace_chunk", "view_pass_group", "shade_group", "locate_on_mesh", "refine_point", "write_rows"],
              out)
    data = out / "perf.data"
    perf = subprocess.Popen(["perf", "record", "-F", "4000", "-p", str(os.getpid()), "-o", str(data)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    time.sleep(0.5)
    t0, n = time.perf_counter(), 0
    while time.perf_counter() - t0 < args.seconds:
        for c in cams:
            r.render(c, args.method)
            n += 1
    ms = 1000 * (time.perf_counter() - t0) / n
    perf.send_signal(2)
    perf.wait()
    print(f"{n} renders, {ms:.1f} ms each (under perf)")
    print(summary(data))
    print(f"machine code of the main kernels in {out}/code_*.bin (python -m bench.numba_perf annotate ...)")
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("ldc", help="profile LDC renders of a sample scene")
    p.add_argument("--scene", default="mirror_box")
    p.add_argument("--size", type=int, default=512)
    p.add_argument("--ldc", type=int, default=256)
    p.add_argument("--method", default="ldc+ibrt:1")
    p.add_argument("--seconds", type=float, default=12.0)
    p.add_argument("--out", default="/tmp/numba_perf")
    a = sub.add_parser("annotate", help="hottest instructions of a dumped function")
    a.add_argument("data")
    a.add_argument("code")
    a.add_argument("top", nargs="?", type=int, default=12)
    args = ap.parse_args(argv)
    if args.cmd == "annotate":
        print(annotate(Path(args.data), Path(args.code), args.top))
        return 0
    if not os.environ.get("NUMBA_CACHE_DIR"):
        print("note: set NUMBA_CACHE_DIR to an empty directory, or cached kernels get no symbols", file=sys.stderr)
    return _profile_ldc(args)


if __name__ == "__main__":
    raise SystemExit(main())
