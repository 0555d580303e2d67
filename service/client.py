"""A small typed Python client for the ibr-service HTTP API (httpx).

    from service.client import Client
    with Client("http://127.0.0.1:8000", api_key=None) as c:
        scene = c.create_scene(scene_dict)                     # ScenePublic
        r = c.render(scene.id, params={"spp": 16}, wait=30)    # RenderPublic (cached / finished / queued)
        r = c.wait_render(r, on_progress=print)                # until the artifact exists
        png = c.download(r.artifact_key, "png")
        b = c.wait_bake(c.bake(scene.id, {"ldc_resolution": 256}))      # BakePublic, finished
        r = c.render(scene.id, method="ldc+llf", bake={"ldc_resolution": 256}, wait=30)

Errors from the API (problem+json) raise :class:`ApiError` with the status, the
title/detail and the per-field errors; connection problems raise ``httpx`` errors.
The client imports no engine code: other applications can use it on their own.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Literal

import httpx

from api_schemas.service import (
    ArtifactManifest,
    BakeList,
    BakePublic,
    BatchPublic,
    JobList,
    JobPublic,
    RenderPublic,
    SceneList,
    ScenePublic,
)


class ApiError(Exception):
    """An error answer from the API (4xx/5xx), with the problem details."""

    def __init__(self, status: int, title: str, detail: str = "", errors: list[dict[str, Any]] | None = None):
        self.status = status
        self.title = title
        self.detail = detail
        self.errors = list(errors or [])
        lines = [f"{status} {title}" + (f": {detail}" if detail else "")]
        lines += [f"  {e.get('field') or '(body)'}: {e.get('message')}" for e in self.errors]
        super().__init__("\n".join(lines))


class Client:
    """Synchronous client. ``base_url`` like ``http://127.0.0.1:8000``."""

    def __init__(self, base_url: str, api_key: str | None = None, timeout: float = 30.0,
                 transport: httpx.BaseTransport | None = None):
        headers = {"Authorization": f"Bearer {api_key}"} if api_key else {}
        self._http = httpx.Client(base_url=base_url.rstrip("/"), headers=headers, timeout=timeout,
                                  transport=transport)

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._http.close()

    # ------------------------------------------------------------------ plumbing
    def _request(self, method: str, url: str, **kw: Any) -> httpx.Response:
        r = self._http.request(method, url, **kw)
        if r.status_code >= 400:
            raise _error(r)
        return r

    # ------------------------------------------------------------------ health
    def ready(self) -> bool:
        """True when the API, Redis and the object store all answer."""
        try:
            return self._http.get("/readyz").status_code == 200
        except httpx.HTTPError:
            return False

    # ------------------------------------------------------------------ scenes
    def create_scene(self, scene: Mapping[str, Any], meshes: Mapping[str, bytes | Path] | None = None) -> ScenePublic:
        """Store a scene; ``meshes`` maps each ``mesh_file`` path in the scene to its bytes or a file."""
        if not meshes:
            r = self._request("POST", "/v1/scenes", json={"scene": scene})
        else:
            files: list[tuple[str, tuple[str, bytes, str]]] = [
                ("scene", ("scene.json", json.dumps({"scene": scene}).encode(), "application/json"))]
            for path, data in meshes.items():
                blob = Path(data).read_bytes() if isinstance(data, Path) else bytes(data)
                files.append((path, (Path(path).name, blob, "application/octet-stream")))
            r = self._request("POST", "/v1/scenes", files=files)
        return ScenePublic.model_validate(r.json())

    def get_scene(self, scene_id: str) -> ScenePublic:
        return ScenePublic.model_validate(self._request("GET", f"/v1/scenes/{scene_id}").json())

    def list_scenes(self) -> SceneList:
        return SceneList.model_validate(self._request("GET", "/v1/scenes").json())

    def delete_scene(self, scene_id: str) -> None:
        self._request("DELETE", f"/v1/scenes/{scene_id}")

    # ------------------------------------------------------------------ renders and jobs
    def render(self, scene_id: str, camera: Mapping[str, Any] | None = None, method: str = "reference",
               params: Mapping[str, Any] | None = None, wait: float = 0.0, bake: Mapping[str, Any] | None = None,
               missing_bake: Literal["fail", "bake"] | None = None) -> RenderPublic:
        """Request a render; the answer says ``cached``, ``finished``, ``queued``, ``running`` or ``failed``.

        ``method``: ``reference``, ``ldc``, ``ldc+llf`` or ``ldc+ibrt:k``; the LDC methods render from
        the bake named by ``bake`` (its params; default params when None). Without that bake the API
        answers 409 (ApiError), unless ``missing_bake="bake"`` queues the render after the bake."""
        body: dict[str, Any] = {"scene_id": scene_id, "method": method}
        if camera is not None:
            body["camera"] = dict(camera)
        if params:
            body["params"] = dict(params)
        if bake:
            body["bake"] = dict(bake)
        if missing_bake is not None:
            body["missing_bake"] = missing_bake
        r = self._request("POST", "/v1/renders", json=body, params={"wait": wait} if wait else None)
        return RenderPublic.model_validate(r.json())

    def job(self, job_id: str) -> JobPublic:
        return JobPublic.model_validate(self._request("GET", f"/v1/jobs/{job_id}").json())

    def jobs(self) -> JobList:
        return JobList.model_validate(self._request("GET", "/v1/jobs").json())

    def cancel(self, job_id: str) -> JobPublic:
        return JobPublic.model_validate(self._request("POST", f"/v1/jobs/{job_id}/cancel").json())

    def wait_job(self, job_id: str, timeout: float = 600.0, poll: float = 0.2,
                 on_progress: Callable[[JobPublic], None] | None = None) -> JobPublic:
        """Poll a job until it ends (finished / failed / canceled) or ``timeout`` seconds pass."""
        deadline = time.monotonic() + timeout
        delay = poll
        while True:
            j = self.job(job_id)
            if on_progress is not None:
                on_progress(j)
            if j.state in ("finished", "failed", "canceled"):
                return j
            if time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} still {j.state} after {timeout} s")
            time.sleep(delay)
            delay = min(2.0, delay * 1.3)

    def wait_render(self, r: RenderPublic, timeout: float = 600.0,
                    on_progress: Callable[[JobPublic], None] | None = None) -> ArtifactManifest:
        """The artifact of a render request, waiting for its job if needed. Raises ApiError if it failed."""
        if r.artifact is not None:
            return r.artifact
        if r.job is None:
            return self.artifact(r.artifact_key)
        j = self.wait_job(r.job.id, timeout=timeout, on_progress=on_progress)
        if j.state != "finished":
            raise ApiError(500 if j.state == "failed" else 409, f"render job {j.state}", j.error or "")
        return self.artifact(r.artifact_key)

    # ------------------------------------------------------------------ bakes
    def bake(self, scene_id: str, params: Mapping[str, Any] | None = None) -> BakePublic:
        """Request a bake of a scene (``BakeParams`` fields); ``cached`` when it exists already."""
        r = self._request("POST", f"/v1/scenes/{scene_id}/bakes", json=dict(params or {}))
        return BakePublic.model_validate(r.json())

    def get_bake(self, scene_id: str, key: str) -> BakePublic:
        return BakePublic.model_validate(self._request("GET", f"/v1/scenes/{scene_id}/bakes/{key}").json())

    def list_bakes(self, scene_id: str) -> BakeList:
        return BakeList.model_validate(self._request("GET", f"/v1/scenes/{scene_id}/bakes").json())

    def delete_bake(self, scene_id: str, key: str) -> None:
        self._request("DELETE", f"/v1/scenes/{scene_id}/bakes/{key}")

    def wait_bake(self, b: BakePublic, timeout: float = 3600.0, poll: float = 0.3,
                  on_progress: Callable[[BakePublic], None] | None = None) -> BakePublic:
        """Poll a bake until it is finished (returned) or failed / canceled / missing (ApiError)."""
        deadline = time.monotonic() + timeout
        delay = poll
        while True:
            if on_progress is not None:
                on_progress(b)
            if b.state == "finished":
                return b
            if b.state in ("failed", "canceled", "missing"):
                raise ApiError(500 if b.state == "failed" else 409, f"bake {b.state}", b.error or "")
            if time.monotonic() > deadline:
                raise TimeoutError(f"bake {b.key} still {b.state} after {timeout} s")
            time.sleep(delay)
            delay = min(2.0, delay * 1.3)
            b = self.get_bake(b.scene_id, b.key)

    # ------------------------------------------------------------------ artifacts
    def artifact(self, key: str) -> ArtifactManifest:
        return ArtifactManifest.model_validate(self._request("GET", f"/v1/artifacts/{key}").json())

    def download(self, key: str, fmt: Literal["exr", "png"] = "png") -> bytes:
        return self._request("GET", f"/v1/artifacts/{key}/image.{fmt}").content

    # ------------------------------------------------------------------ batches
    def batch(self, scenes: list[Mapping[str, Any]] | None = None,
              renders: list[Mapping[str, Any]] | None = None) -> BatchPublic:
        body = {"scenes": [{"scene": s} for s in (scenes or [])], "renders": list(renders or [])}
        return BatchPublic.model_validate(self._request("POST", "/v1/batches", json=body).json())

    def get_batch(self, batch_id: str) -> BatchPublic:
        return BatchPublic.model_validate(self._request("GET", f"/v1/batches/{batch_id}").json())


def _error(r: httpx.Response) -> ApiError:
    try:
        body = r.json()
    except ValueError:
        return ApiError(r.status_code, r.reason_phrase or "error", r.text[:500])
    if isinstance(body, dict):
        return ApiError(r.status_code, str(body.get("title") or r.reason_phrase), str(body.get("detail") or ""),
                        body.get("errors") if isinstance(body.get("errors"), list) else None)
    return ApiError(r.status_code, r.reason_phrase or "error", str(body)[:500])
