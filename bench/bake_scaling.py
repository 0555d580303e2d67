"""Bake scaling: the same bake with 1 and with 2 bake worker processes, speed-up measured in one run.

Starts an embedded Redis and a local object store in a temporary directory, stores a sample scene,
then for each worker count: starts that many real ``python -m workers.runner --queue bake`` processes,
requests the bake (``producer.bakes.enqueue_bake``: plan job -> one job per LDC axis and per LLF chunk
-> merge job), waits for the manifest, records the wall time and each part's job time, stops the
workers and deletes the bake (so the next run redoes exactly the same work). This is the mechanism a
deployment uses to spread bakes over many machines sharing Redis and S3.

``--rounds N`` repeats the pair N times, interleaved (1, 2, 1, 2, ...), and reports each round's
ratio and their median: this machine's speed drifts by tens of per cent over minutes, so a single
pair can read well above or below what the second worker brings. The docs table shows the round
whose ratio is the median (the lower middle one for an even count).

Each worker's numba kernels run on ``--threads`` threads (default 1), so the comparison is "one core
per worker" in both runs; on a machine whose cores are busy with other work the speed-up is bounded by
the cores actually free (the report prints the machine's load average).

    python -m bench.bake_scaling [--scene teapot_glossy] [--ldc-resolution 192] [--llf-f 4]
                                 [--llf-resolution 24] [--llf-chunk 11] [--threads 1]
    python -m bench.bake_scaling --gi [--scene cornell_box] [--ldc-resolution 160] [--chunks 6]
                                 [--noise 0.02] [--max-paths 512] [--bounces 3]

Without ``--gi`` the bake has no indirect light (``indirect.mode=off``) and the run writes the
``bake_scaling`` block of docs/performance.md and docs/data/bake_scaling.json. With ``--gi`` the
bake path-traces indirect light (``indirect.mode=auto``, ``--chunks`` jobs per LDC axis) and the
run writes the ``bake_scaling_gi`` block of docs/scaling.md and docs/data/bake_scaling_gi.json.

Besides wall time, each run reports the CPU time of the worker processes (their own and their
reaped job horses', from /proc), the Redis commands the bake cost (INFO's
``total_commands_processed``, minus this script's own polling), the bytes written to the object
store, and the indirect paths traced (the paths per second per core that ``IBR_BAKE_PATHS_PER_S``
should be set to).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.docs_writer import replace_block

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "performance.md"
DATA = ROOT / "docs" / "data" / "bake_scaling.json"
GI_DOC = ROOT / "docs" / "scaling.md"
GI_DATA = ROOT / "docs" / "data" / "bake_scaling_gi.json"
_TICK = os.sysconf("SC_CLK_TCK")


def _cpu_s(pid: int) -> float:
    """CPU seconds of a process and its reaped children (utime + stime + cutime + cstime)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return sum(int(x) for x in fields[11:15]) / _TICK


def _store_bytes(root: Path) -> int:
    return sum(f.stat().st_size for f in root.rglob("*") if f.is_file())


def _start_workers(n: int, env: dict[str, str], logdir: Path) -> list[subprocess.Popen[bytes]]:
    procs = []
    for i in range(n):
        log = open(logdir / f"bake-worker-{n}-{i}.log", "wb")  # noqa: SIM115 - closed with the process
        procs.append(subprocess.Popen([sys.executable, "-m", "workers.runner", "--queue", "bake",
                                       "--maintenance-interval", "5", "--name", f"bench-bake-{n}-{i}"],
                                      cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT,
                                      start_new_session=True))
    return procs


def _stop(procs: list[subprocess.Popen[bytes]]) -> None:
    for p in procs:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGTERM)
    for p in procs:
        try:
            p.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()


def _wait_workers(redis: Any, n: int, timeout: float = 60.0) -> None:
    from rq import Worker

    from producer.queue import get_queue

    deadline = time.monotonic() + timeout
    while Worker.count(connection=redis, queue=get_queue(redis, "bake")) < n:
        if time.monotonic() > deadline:
            raise RuntimeError(f"{n} bake workers did not register within {timeout} s")
        time.sleep(0.1)


def run_once(redis: Any, store: Any, scene_id: str, params: Any, n: int, env: dict[str, str],
             logdir: Path) -> dict[str, Any]:
    from producer import bakes
    from producer.artifacts import read_manifest
    from producer.names import scene_bake_job_id, scene_bake_part_job_id, scene_bake_plan_job_id
    from producer.queue import fetch_job

    procs = _start_workers(n, env, logdir)
    store_root = Path(str(store.root)) if hasattr(store, "root") else None
    try:
        _wait_workers(redis, n)
        time.sleep(1.0)  # the workers' start-up Redis traffic is not the bake's
        cpu0 = [_cpu_s(p.pid) for p in procs]
        bytes0 = _store_bytes(store_root) if store_root is not None else 0
        stats0 = redis.info("commandstats")
        cmds0 = int(redis.info("stats")["total_commands_processed"])
        t0 = time.perf_counter()
        key, job = bakes.enqueue_bake(redis, store, scene_id, params, owner=None)
        assert job is not None, "the bake was cached: delete it first"
        # follow the merge job with ONE command per poll (its status field), so the bake's own
        # Redis traffic is the total minus the polls
        polls = 0
        while True:
            status = redis.hget(job.key, "status")
            polls += 1
            if status in (b"finished", b"failed", b"canceled", b"stopped"):
                break
            time.sleep(0.25)
        wall = time.perf_counter() - t0
        cmds1 = int(redis.info("stats")["total_commands_processed"])
        stats1 = redis.info("commandstats")
        per_poll = 1
        st = bakes.bake_status(redis, store, scene_id, key, params)
        if st.state != "finished":
            raise RuntimeError(f"bake {st.state}: {st.error}")
        cpu = sum(_cpu_s(p.pid) - c for p, c in zip(procs, cpu0, strict=True))
        written = (_store_bytes(store_root) - bytes0) if store_root is not None else 0
    finally:
        _stop(procs)
    redis_ops = cmds1 - cmds0 - polls * per_poll - 2
    by_cmd = {k.removeprefix("cmdstat_"): int(v["calls"]) - int(stats0.get(k, {}).get("calls", 0))
              for k, v in stats1.items()}
    by_cmd["hget"] = by_cmd.get("hget", 0) - polls
    by_cmd = dict(sorted(((k, v) for k, v in by_cmd.items() if v > 0), key=lambda kv: -kv[1])[:12])
    manifest = read_manifest(store, key)
    assert manifest is not None
    jobs: dict[str, float] = {}
    workers_used: dict[str, str] = {}
    overhead = {"fork_import_s": 0.0, "load_scene_s": 0.0, "compute_s": 0.0}
    for part in st.parts:
        pj = fetch_job(redis, scene_bake_part_job_id(part.key))
        pm = read_manifest(store, part.key)
        if pj is not None and pj.started_at and pj.ended_at and pm is not None:
            dur = (pj.ended_at - pj.started_at).total_seconds()
            jobs[part.name] = dur
            workers_used[part.name] = str(pj.worker_name)
            t = pm.result.get("timings", {})
            overhead["fork_import_s"] += max(0.0, dur - float(t.get("job_total", 0.0)))
            load = float(t.get("load_scene", t.get("load", 0.0)))
            overhead["load_scene_s"] += load
            overhead["compute_s"] += float(t.get("job_total", 0.0)) - load
    serial: dict[str, float] = {}
    for name, jid in (("plan", scene_bake_plan_job_id(key)), ("merge", scene_bake_job_id(key))):
        j = fetch_job(redis, jid)
        if j is not None and j.started_at and j.ended_at:
            serial[name] = (j.ended_at - j.started_at).total_seconds()
    ind = manifest.result["plan"].get("indirect", {})
    summary = ind.get("summary", {})
    # the chunk jobs' own times: the merged summary has none (the merge job loads the chunks from the store)
    ind_time = sum(jobs.get(p.name, 0.0) for p in st.parts if p.kind == "ldc_indirect")
    result = {"workers": n, "wall_s": wall, "cpu_s": cpu, "redis_ops": redis_ops, "redis_ops_by_command": by_cmd,
              "jobs": len(st.parts) + 2,
              "store_bytes_written": written, "indirect": {
                  "state": ind.get("state"), "paths_total": summary.get("paths_total", 0),
                  "paths_mean": summary.get("paths_mean", 0.0), "sides": summary.get("sides", 0),
                  "rel_stderr_p95_of_chunks": summary.get("rel_stderr_p95_of_chunks"),
                  "met_target": summary.get("met_target"), "time_s": ind_time,
                  "paths_per_s": summary.get("paths_total", 0) / ind_time if ind_time else None},
              "estimates": manifest.result.get("estimates", {}),
              "n_chunks": sum(p.kind == "ldc_indirect" for p in st.parts),
              "parts": len(st.parts), "part_job_s": jobs,
              "part_time_split_s": overhead, "serial_job_s": serial,
              "part_job_sum_s": sum(jobs.values()), "workers_used": sorted(set(workers_used.values())),
              "plan": {k: manifest.result["plan"][k] for k in ("bake_llf", "llf_directions", "needs_llf")},
              "sizes": manifest.result["sizes"], "key": key}
    bakes.delete_bake(redis, store, scene_id, key, params)
    redis.flushdb()
    return result


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="teapot_glossy", help="sample scene name")
    ap.add_argument("--ldc-resolution", type=int, default=192)
    ap.add_argument("--max-layers", type=int, default=16)
    ap.add_argument("--llf-f", type=int, default=4)
    ap.add_argument("--llf-resolution", type=int, default=24)
    ap.add_argument("--llf-chunk", type=int, default=11)
    ap.add_argument("--threads", type=int, default=1, help="numba threads per worker process")
    ap.add_argument("--gi", action="store_true", help="bake indirect light (docs/scaling.md block)")
    ap.add_argument("--chunks", type=int, default=6, help="--gi: indirect jobs per LDC axis")
    ap.add_argument("--noise", type=float, default=0.02, help="--gi: noise target")
    ap.add_argument("--max-paths", type=int, default=512, help="--gi: most paths per sample side")
    ap.add_argument("--bounces", type=int, default=3, help="--gi: diffuse bounces per path")
    ap.add_argument("--rounds", type=int, default=1, help="pairs of runs (1 then 2 workers), interleaved")
    ap.add_argument("--no-docs", action="store_true", help="print only, do not write docs/")
    ap.add_argument("--docs-only", action="store_true", help="re-render the docs block from the saved JSON")
    args = ap.parse_args(argv)
    if args.docs_only:
        if args.gi:
            write_gi_docs(json.loads(GI_DATA.read_text()))
        else:
            write_docs(json.loads(DATA.read_text()))
        return 0

    from api_schemas import load_scene_file
    from api_schemas.scene import MeshFileObject
    from api_schemas.service import BakeParams
    from producer.artifacts import put_scene
    from producer.embedded import start_embedded_redis
    from producer.queue import redis_from_url
    from producer.store import open_store
    from samples import SAMPLES_DIR, sample_path

    scene = load_scene_file(sample_path(args.scene))
    meshes = {o.path: (SAMPLES_DIR / o.path).read_bytes() for o in scene.objects if isinstance(o, MeshFileObject)}
    indirect = ({"mode": "auto", "chunks": args.chunks, "noise": args.noise, "max_paths": args.max_paths,
                 "bounces": args.bounces} if args.gi else {"mode": "off"})
    params = BakeParams.model_validate({
        "ldc_resolution": args.ldc_resolution, "max_layers": args.max_layers, "llf_f": args.llf_f,
        "llf_resolution": args.llf_resolution, "llf_chunk": args.llf_chunk, "indirect": indirect})
    with tempfile.TemporaryDirectory(prefix="ibr-bench-", dir="/tmp") as tmp:
        tmpd = Path(tmp)
        server = start_embedded_redis(tmpd / "redis")
        try:
            redis = redis_from_url(server.url)
            store = open_store(str(tmpd / "store"))
            scene_id = put_scene(store, scene, meshes, None).id
            env = {**os.environ, "IBR_REDIS_URL": server.url, "IBR_STORE_URL": f"file://{tmpd / 'store'}",
                   "IBR_DATA_DIR": str(tmpd / "data"), "NUMBA_NUM_THREADS": str(args.threads),
                   "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)}
            load_before = os.getloadavg()
            rounds = []
            for i in range(max(1, args.rounds)):
                pair = [run_once(redis, store, scene_id, params, n, env, tmpd) for n in (1, 2)]
                rounds.append(pair)
                print(f"round {i + 1}: {pair[0]['wall_s']:.1f} s / {pair[1]['wall_s']:.1f} s = "
                      f"{pair[0]['wall_s'] / pair[1]['wall_s']:.2f}x", flush=True)
            load_after = os.getloadavg()
        finally:
            server.stop()
    ratios = [one["wall_s"] / two["wall_s"] for one, two in rounds]
    median_round = sorted(range(len(rounds)), key=lambda i: ratios[i])[(len(rounds) - 1) // 2]
    runs = rounds[median_round]
    speedup = ratios[median_round]
    report = {"scene": args.scene, "params": params.model_dump(mode="json"), "threads_per_worker": args.threads,
              "cpu_count": os.cpu_count(), "loadavg_before": load_before, "loadavg_after": load_after,
              "runs": runs, "speedup": speedup, "round_speedups": ratios,
              "round_walls_s": [[one["wall_s"], two["wall_s"]] for one, two in rounds],
              "round_cpus_s": [[one["cpu_s"], two["cpu_s"]] for one, two in rounds],
              "command": "python -m bench.bake_scaling " + " ".join(argv if argv is not None else sys.argv[1:])}
    print(json.dumps({k: v for k, v in report.items() if k != "runs"}, indent=2))
    for r in runs:
        print(f"{r['workers']} worker(s): {r['wall_s']:.1f} s wall, {r['cpu_s']:.1f} s CPU, {r['parts']} parts, "
              f"sum of part jobs {r['part_job_sum_s']:.1f} s, workers used {r['workers_used']}, "
              f"{r['redis_ops']} Redis commands {r['redis_ops_by_command']}, "
              f"{r['store_bytes_written'] / 2**20:.1f} MiB written; "
              f"indirect {r['indirect']}")
    print(f"speed-up 1 -> 2 workers: {speedup:.2f}x (rounds: {', '.join(f'{r:.2f}x' for r in ratios)})")
    if args.no_docs:
        return 0
    data = GI_DATA if args.gi else DATA
    data.parent.mkdir(parents=True, exist_ok=True)
    data.write_text(json.dumps(report, indent=2) + "\n")
    (write_gi_docs if args.gi else write_docs)(report)
    return 0


def write_docs(report: dict[str, Any]) -> None:
    """The ``bake_scaling`` block of docs/performance.md from a report (``--docs-only`` re-renders
    it from docs/data/bake_scaling.json without baking)."""
    one, two = report["runs"]
    p = report["params"]
    speedup = report["speedup"]
    n_llf = one["parts"] - 3
    lb, la = report["loadavg_before"][0], report["loadavg_after"][0]
    lines = [
        "### Bake scaling: 1 vs 2 bake workers",
        "",
        f"`{report['command'].strip()}` — scene `{report['scene']}`, LDC {p['ldc_resolution']} px x "
        f"{p['max_layers']} layers, LLF f={p['llf_f']} ({one['plan']['llf_directions']} directions) at "
        f"{p['llf_resolution']} px in chunks of {p['llf_chunk']}: {one['parts']} parts (3 LDC axes + {n_llf} LLF "
        f"chunks) + plan + merge jobs. {report['threads_per_worker']} numba thread(s) per worker, "
        f"{report['cpu_count']} cores on this machine (load average {lb:.1f} before, {la:.1f} after: the cores "
        "are shared with other work).",
        "",
        "| bake workers | wall time | sum of part job times (fork + import / scene load / baking) "
        "| plan + merge jobs | workers that ran parts |",
        "|---|---|---|---|---|",
    ]
    for r in report["runs"]:
        sp = r["part_time_split_s"]
        lines.append(f"| {r['workers']} | {r['wall_s']:.1f} s | {r['part_job_sum_s']:.1f} s "
                     f"({sp['fork_import_s']:.1f} / {sp['load_scene_s']:.1f} / {sp['compute_s']:.1f} s) | "
                     f"{sum(r['serial_job_s'].values()):.1f} s | {len(r['workers_used'])} |")
    per = one["part_time_split_s"]
    lines += ["", f"**Speed-up with 2 workers: {speedup:.2f}x** (same run; ideal 2x on two free cores). Per part, "
              f"the fixed cost is {per['fork_import_s'] / one['parts']:.2f} s fork + import and "
              f"{per['load_scene_s'] / one['parts']:.2f} s scene load (the bake worker's parent preloads the "
              "engine, mesh loading and Embree's bindings once, so a forked horse does not import them per job); "
              "the plan and merge jobs are serial. The same mechanism spreads a bake over machines sharing "
              "Redis and the object store. Raw data: `docs/data/bake_scaling.json`."]
    replace_block(DOC, "bake_scaling", "\n".join(lines), title="Performance")


def _rounds_sentence(report: dict[str, Any]) -> str:
    """The interleaved rounds (``--rounds``): each pair's wall and CPU times and its ratio."""
    walls, cpus = report["round_walls_s"], report["round_cpus_s"]
    parts = [f"{w1:.0f} s / {w2:.0f} s wall ({c1:.0f} / {c2:.0f} CPU-s) = {r:.2f}x"
             for (w1, w2), (c1, c2), r in zip(walls, cpus, report["round_speedups"], strict=True)]
    busy = [(c2 / w2) / (c1 / w1) for (w1, w2), (c1, c2) in zip(walls, cpus, strict=True)]
    return (f"Over {len(parts)} interleaved rounds (1 worker, then 2, repeated; the table is the median "
            f"round): {'; '.join(parts)}. The same work took from {min(c for pair in cpus for c in pair):.0f} to "
            f"{max(c for pair in cpus for c in pair):.0f} CPU-s in these runs (this machine's speed drifts), which "
            "moves the wall-time ratio either way; the cores a 2-worker bake keeps busy (CPU time over wall time, "
            "relative to the 1-worker run of its round), which that drift does not move, were "
            f"{', '.join(f'{b:.2f}' for b in busy)}. ")


def write_gi_docs(report: dict[str, Any]) -> None:
    """The ``bake_scaling_gi`` block of docs/scaling.md (``--gi --docs-only`` re-renders it from
    docs/data/bake_scaling_gi.json)."""
    one, two = report["runs"]
    p = report["params"]
    ip = p["indirect"]
    lb, la = report["loadavg_before"][0], report["loadavg_after"][0]
    ind = one["indirect"]
    lines = [
        "### Measured: a bake with indirect light on 1 and 2 bake workers",
        "",
        f"`flock /tmp/bench.lock {report['command'].strip()}` — scene `{report['scene']}`, LDC "
        f"{p['ldc_resolution']} px x {p['max_layers']} layers, indirect light to a noise target of "
        f"{ip['noise'] * 100:g} % ("
        + (f"the fixed sampler: {ind['paths_mean']:.0f} paths per sample side" if ip.get("sampling") == "fixed" else
           f"{ip['min_paths']}..{ip['max_paths']} paths per sample side")
        + f", {ip['bounces']} bounces) in {ip['chunks']} chunks per axis: {one['parts']} parts "
        f"({one['n_chunks']} indirect chunks) + "
        f"plan + merge jobs. {report['threads_per_worker']} numba thread per worker, {report['cpu_count']} cores "
        f"(1-minute load average {lb:.1f} before the run, {la:.1f} at its end, its own workers included).",
        "",
        "| bake workers | wall time | CPU time (workers + their job horses) | sum of part job times "
        + ("| Redis commands " if "redis_ops_by_command" in one else
           "| Redis commands (a run that polled the bake's full status every 0.25 s: over-counted) ")
        + "| bytes written to the store |",
        "|---|---|---|---|---|---|",
    ]
    for r in report["runs"]:
        lines.append(f"| {r['workers']} | {r['wall_s']:.1f} s | {r['cpu_s']:.1f} s | {r['part_job_sum_s']:.1f} s | "
                     f"{r['redis_ops']} | {r['store_bytes_written'] / 2**20:.2f} MiB |")
    est = one.get("estimates", {})
    pps = ind.get("paths_per_s") or 0.0
    lines += [
        "",
        f"**Speed-up with 2 workers: {report['speedup']:.2f}x** wall (CPU time {one['cpu_s']:.1f} s vs "
        f"{two['cpu_s']:.1f} s: the work is the same; what is lost is the serial plan / axis / merge stages and the "
        "last chunk's tail). "
        + (_rounds_sentence(report) if len(report.get("round_speedups", [])) > 1 else "")
        + f"Indirect pass: {ind['paths_total'] / 1e6:.1f} M paths over {ind['sides']} sample sides "
        f"({ind['paths_mean']:.0f} per side; noise p95 {100 * (ind['rel_stderr_p95_of_chunks'] or 0):.2f} %, "
        f"{100 * (ind['met_target'] or 0):.0f} % of the sides met the target) in {ind['time_s']:.1f} s of chunk "
        f"time: {pps / 1e3:.0f} k paths/s per second of job time, "
        f"{ind['paths_total'] / max(one['cpu_s'], 1e-9) / 1e3:.0f} k per CPU second of the whole bake. "
        + (f"Redis commands per bake with 1 worker, by command: "
           f"{', '.join(f'{k} {v}' for k, v in one['redis_ops_by_command'].items())}. "
           if one.get("redis_ops_by_command") else "")
        + f"The plan estimated {est.get('indirect_cpu_s', 0.0):.1f} s "
        f"of indirect CPU ({est.get('indirect_paths_expected', 0) / 1e6:.1f} M paths at "
        f"{est.get('paths_per_s', 0.0) / 1e3:.0f} k paths/s). Raw data: `docs/data/bake_scaling_gi.json`.",
    ]
    replace_block(GI_DOC, "bake_scaling_gi", "\n".join(lines), title="Scaling bakes over workers")


if __name__ == "__main__":
    sys.exit(main())
