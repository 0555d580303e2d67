"""Test-only job functions (enqueued by import path; worker subprocesses run with cwd = repo)
and the small scenes the queue tests render."""

from __future__ import annotations

import time
from typing import Any

from rq import get_current_job

from api_schemas.scene import Scene


def tiny_scene(width: int = 48, height: int = 32, intensity: float = 3.0, name: str = "tiny") -> Scene:
    """A sphere on a floor under one point light: renders in well under a second."""
    return Scene.model_validate({
        "name": name,
        "camera": {"type": "perspective", "eye": [0, 1.5, 4], "look_at": [0, 0.5, 0],
                   "width": width, "height": height},
        "materials": [{"name": "m", "kd": [0.6, 0.5, 0.4], "ks": [0.2, 0.2, 0.2], "shininess": 30.0},
                      {"name": "floor", "kd": [0.5, 0.5, 0.5]}],
        "objects": [{"type": "sphere", "center": [0, 0.6, 0], "radius": 0.6, "material": "m"},
                    {"type": "plane", "material": "floor", "size": [4.0, 4.0]}],
        "lights": [{"type": "point", "position": [1, 3, 2], "intensity": [intensity] * 3}],
    })


def overflow_scene() -> Scene:
    """docs/hard-cases.md #13: a point light so strong, so close, that radiance overflows to Inf."""
    return Scene.model_validate({
        "name": "overflow",
        "camera": {"type": "perspective", "eye": [0, 2, 0.01], "look_at": [0, 0, 0], "width": 16, "height": 16},
        "materials": [{"name": "white", "kd": [1, 1, 1]}],
        "objects": [{"type": "plane", "material": "white", "size": [4.0, 4.0]}],
        "lights": [{"type": "point", "position": [0, 1e-3, 0], "intensity": [1e307, 1e307, 1e307]}],
    })


def _step_progress(i: int, n: int) -> None:
    job = get_current_job()
    if job is not None:
        job.meta["progress"] = {"fraction": i / n, "stage": f"step {i}/{n}", "eta_s": None}
        job.meta["step"] = i
        job.save_meta()


def sleepy(payload: dict[str, Any]) -> dict[str, Any]:
    """Sleeps ``seconds`` in short Python steps (a SIGALRM timeout can interrupt it)."""
    seconds = float(payload.get("seconds", 5.0))
    n = max(1, int(seconds / 0.05))
    for i in range(n):
        time.sleep(seconds / n)
        if i % 10 == 0:
            _step_progress(i, n)
    return {"slept": seconds}


def quick(payload: dict[str, Any]) -> dict[str, Any]:
    return {"echo": payload}


def leave_a_thread_running(payload: dict[str, Any]) -> dict[str, Any]:
    """Finish, but leave behind a (non-daemon) thread that never ends: the interpreter's exit
    joins it forever, as a library's stuck thread would."""
    import threading

    def never_ending_thread() -> None:
        threading.Event().wait()

    threading.Thread(target=never_ending_thread, name="never-ending", daemon=False).start()
    return {"echo": payload}


def slow_artifact(payload: dict[str, Any]) -> dict[str, Any]:
    """A stand-in bake: ``steps`` x ``dt`` seconds of work, then a deterministic artifact
    published through producer.artifacts with the worker's own store (blobs, manifest last)."""
    from producer.artifacts import artifact_key, write_artifact
    from producer.settings import open_settings_store

    steps, dt = int(payload["steps"]), float(payload["dt"])
    params = {"steps": steps, "label": payload["label"]}
    key = artifact_key("test-bake", {"seed": payload["label"]}, params, "test")
    for i in range(steps):
        _step_progress(i, steps)
        time.sleep(dt)
    data = ("".join(f"{payload['label']}:{i}\n" for i in range(1000))).encode()
    write_artifact(open_settings_store(), key, "test-bake", {"seed": payload["label"]}, params, "test",
                   {"data.txt": (data, "text/plain")}, {"steps": steps})
    return {"artifact_key": key}


def slow_artifact_key(label: str, steps: int) -> str:
    from producer.artifacts import artifact_key

    return artifact_key("test-bake", {"seed": label}, {"steps": steps, "label": label}, "test")


def flaky(payload: dict[str, Any]) -> dict[str, Any]:
    """Fails with a transient StoreUnavailable on its first ``failures`` attempts, then succeeds."""
    from producer.store import StoreUnavailable

    job = get_current_job()
    assert job is not None
    attempt = int(job.connection.incr(f"test:attempts:{job.id}"))
    if attempt <= int(payload.get("failures", 1)):
        raise StoreUnavailable(f"store unreachable (attempt {attempt})")
    return {"attempts": attempt}


def canceled_while_running(payload: dict[str, Any]) -> dict[str, Any]:
    """Cancels itself through the API's cancel (the job is started: the cancel sets its flag), then
    polls the flag the way the render jobs do, which stops it."""
    from producer.cancel import cancel
    from workers.jobs.common import ProgressReporter

    job = get_current_job()
    assert job is not None
    time.sleep(float(payload.get("seconds", 0.0)))
    cancel(job.connection, job.id)
    ProgressReporter(job).check_canceled()
    raise AssertionError("check_canceled did not stop the job")


def broken(payload: dict[str, Any]) -> dict[str, Any]:
    raise ValueError(f"broken on purpose: {payload}")
