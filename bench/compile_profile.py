"""Cold numba compile cost of the render worker's warm-up, per step and per kernel.

``python -m bench.compile_profile [--cache-dir DIR] [--top 40] [--write]`` runs
``workers.warmup.warm_up`` in this process with ``NUMBA_CACHE_DIR`` pointing at an empty
temporary directory (so nothing is loaded from, or written to, the shared cache) and records
every ``numba:compile`` event numba broadcasts: per dispatcher, how many signatures it compiled,
the wall time of its compilations including the kernels compiled inside them (``inclusive``)
and without them (``exclusive``, the time that kernel's own typing, lowering and LLVM
optimisation took). ``--write`` puts the tables into docs/performance.md.

``--first-ldc`` profiles instead what the first image-based view on a fresh machine compiles: a
direct-light LDC bake of the diffuse Cornell box (``bench.first_run.DIFFUSE_BAKE``, its part jobs run
in this process) and then one ``ldc`` render of it at 128 x 128, each phase's wall and CPU time and
kernels apart -- the work a user who asks for an ``ldc`` view the moment ``/healthz`` answers waits
for (``python -m bench.first_run --at-healthz`` times that on a live stack).

Run it under the shared benchmark lock (``flock /tmp/bench.lock``): it keeps one core busy for
the whole warm-up.
"""

from __future__ import annotations

import argparse
import os
import resource
import sys
import tempfile
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


@dataclass
class KernelCost:
    """The compilations of one numba dispatcher."""

    name: str
    signatures: list[str] = field(default_factory=list)
    inclusive: float = 0.0
    exclusive: float = 0.0


class CompileRecorder:
    """A numba event listener: times each ``numba:compile`` event, nested ones subtracted from
    their caller's exclusive time (numba compiles a callee while typing its caller, in the same
    thread, so the events nest as a stack per thread)."""

    def __init__(self) -> None:
        self.kernels: dict[str, KernelCost] = {}
        self._stack: dict[int, list[list[Any]]] = defaultdict(list)

    def _name(self, disp: Any) -> str:
        fn = disp.py_func
        return f"{fn.__module__}.{fn.__qualname__}"

    def on_start(self, event: Any) -> None:
        import threading

        self._stack[threading.get_ident()].append([time.perf_counter(), 0.0])

    def on_end(self, event: Any) -> None:
        import threading

        stack = self._stack[threading.get_ident()]
        t0, nested = stack.pop()
        took = time.perf_counter() - t0
        if stack:
            stack[-1][1] += took
        data = event.data
        name = self._name(data["dispatcher"])
        k = self.kernels.setdefault(name, KernelCost(name))
        k.signatures.append(", ".join(str(a) for a in data["args"]))
        k.inclusive += took
        k.exclusive += took - nested


def _listener(rec: CompileRecorder) -> Any:
    from numba.core import event as ev

    class _L(ev.Listener):  # type: ignore[misc]
        def on_start(self, event: Any) -> None:
            rec.on_start(event)

        def on_end(self, event: Any) -> None:
            rec.on_end(event)

    return _L()


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def profile(top: int, steps: list[str] | None = None) -> tuple[str, Any, CompileRecorder]:
    """Run the warm-up cold (only ``steps`` and what they need, when given); return (markdown, the
    warm-up report, the recorder)."""
    from numba.core import event as ev

    t_import = time.perf_counter()
    from workers.warmup import warm_up

    import_s = time.perf_counter() - t_import
    rec = CompileRecorder()
    cpu0 = _cpu()
    with ev.install_listener("numba:compile", _listener(rec)):
        report = warm_up(only=steps)
    cpu = _cpu() - cpu0
    kernels = sorted(rec.kernels.values(), key=lambda k: -k.exclusive)
    total_excl = sum(k.exclusive for k in kernels)
    n_sigs = sum(len(k.signatures) for k in kernels)
    lines = [
        f"Cold warm-up: {report.seconds:.1f} s wall, {cpu:.1f} s CPU (imports before it {import_s:.1f} s), "
        f"{n_sigs} signatures of {len(kernels)} kernels compiled, compile time {total_excl:.1f} s; "
        f"{os.cpu_count()} cores, load average before {_LOAD_BEFORE}, after {os.getloadavg()[0]:.2f}.",
        "",
        "| step | seconds | signatures compiled |",
        "|---|---:|---:|",
    ]
    lines += [f"| {s.name} | {s.seconds:.1f} | {s.compiled} |" for s in report.steps]
    lines += ["", f"Kernels by own compile time (top {top}; exclusive = without the kernels compiled inside it):", ""]
    lines += _kernel_lines(rec, top)
    return "\n".join(lines), report, rec


_LOAD_BEFORE = ""


def _kernel_lines(rec: CompileRecorder, top: int) -> list[str]:
    kernels = sorted(rec.kernels.values(), key=lambda k: -k.exclusive)
    lines = ["| kernel | signatures | exclusive s | inclusive s |", "|---|---:|---:|---:|"]
    lines += [f"| `{k.name}` | {len(k.signatures)} | {k.exclusive:.1f} | {k.inclusive:.1f} |" for k in kernels[:top]]
    return lines


def profile_first_ldc(top: int) -> str:
    """Cold compile of a direct-light LDC bake of the diffuse Cornell box and of its first ``ldc``
    render (module docstring), per phase and kernel; markdown."""
    import json

    from numba.core import event as ev

    from api_schemas.scene import Scene
    from api_schemas.service import BakeParams
    from bench.first_run import DIFFUSE_BAKE, DIFFUSE_SCENE, SIZE
    from producer.artifacts import put_scene
    from producer.store.local import LocalStore
    from samples import SAMPLES_DIR, sample_path
    from workers.warmup import _Run, _scratch_jobs

    doc = json.loads(sample_path(DIFFUSE_SCENE).read_text())
    meshes = {o["path"]: (SAMPLES_DIR / o["path"]).read_bytes() for o in doc.get("objects", []) if o.get("path")}
    lines = [f"Cold compile of the first `ldc` view of `{DIFFUSE_SCENE}` ({SIZE['width']} x {SIZE['height']}) "
             f"and of its direct-light bake, one process; {os.cpu_count()} cores, load average before "
             f"{_LOAD_BEFORE}.", ""]
    with tempfile.TemporaryDirectory(prefix="ibr-first-ldc-") as tmp:
        run = _Run(LocalStore(Path(tmp)))
        with _scratch_jobs(run.store):
            run.scene_id = put_scene(run.store, Scene.model_validate(doc), meshes, owner=None).id
            params = BakeParams.model_validate(DIFFUSE_BAKE)
            phases: list[tuple[str, Any]] = [
                ("direct-light LDC bake (bake worker)", lambda: run._publish_bake(params, with_llf=False)),
                ("first `ldc` render (render worker)",
                 lambda: run.render(method="ldc", bake=params.model_dump(mode="json"),
                                    camera={**doc["camera"], **SIZE}))]
            for title, fn in phases:
                rec = CompileRecorder()
                cpu0, t0 = _cpu(), time.perf_counter()
                with ev.install_listener("numba:compile", _listener(rec)):
                    fn()
                wall, cpu = time.perf_counter() - t0, _cpu() - cpu0
                n_sigs = sum(len(k.signatures) for k in rec.kernels.values())
                excl = sum(k.exclusive for k in rec.kernels.values())
                lines += [f"**{title}**: {wall:.1f} s wall, {cpu:.1f} s CPU, {n_sigs} signatures of "
                          f"{len(rec.kernels)} kernels compiled in {excl:.1f} s.", ""]
                lines += _kernel_lines(rec, top) + [""]
    return "\n".join(lines)


def _with_needs(steps: list[str]) -> list[str]:
    """``steps`` and, transitively, the warm-up steps they need."""
    from workers.warmup import needs_of

    out: list[str] = []
    todo = list(steps)
    while todo:
        name = todo.pop()
        if name not in out:
            out.append(name)
            todo.extend(needs_of(name))
    return out


def main(argv: list[str] | None = None) -> int:
    global _LOAD_BEFORE
    p = argparse.ArgumentParser(prog="python -m bench.compile_profile", description=__doc__)
    p.add_argument("--cache-dir", help="numba cache parent (default: a new empty temporary directory)")
    p.add_argument("--top", type=int, default=40)
    p.add_argument("--signatures", action="store_true", help="also print every compiled signature")
    p.add_argument("--write", action="store_true", help="write the tables into docs/performance.md")
    p.add_argument("--label", default="cold-compile")
    p.add_argument("--first-ldc", action="store_true",
                   help="profile the first ldc view of a diffuse scene and its bake instead of the warm-up")
    p.add_argument("--steps", help="comma-separated warm-up steps to run (default: all); the steps they "
                                   "need are added (workers.warmup)")
    args = p.parse_args(argv)
    if "numba" in sys.modules:
        raise SystemExit("import bench.compile_profile before numba (the cache directory is read at import)")
    _LOAD_BEFORE = f"{os.getloadavg()[0]:.2f}"
    with tempfile.TemporaryDirectory(prefix="ibr-numba-cold-") as tmp:
        os.environ["NUMBA_CACHE_DIR"] = args.cache_dir or tmp
        if args.first_ldc:
            print(profile_first_ldc(args.top))
            return 0
        text, report, rec = profile(args.top, _with_needs(args.steps.split(",")) if args.steps else None)
    print(report.table())
    print(text)
    if args.signatures:
        for k in sorted(rec.kernels.values(), key=lambda k: -k.exclusive):
            for sig in k.signatures:
                print(f"{k.name}\t({sig})")
    if args.write:
        from bench.docs_writer import replace_block

        cmd = "flock /tmp/bench.lock python -m bench.compile_profile --write"
        replace_block("docs/performance.md", args.label,
                      f"### Cold numba compile per warm-up step and kernel: `{cmd}`\n\n{text}")
    return 0 if report.ok else 1


if __name__ == "__main__":
    sys.exit(main())
