"""A small typed Python client for the ibr-service HTTP API (httpx).

    from ibr_client import Client
    with Client("http://127.0.0.1:8000", api_key=None) as c:
        scene = c.create_scene(scene_dict)                     # ScenePublic
        r = c.render(scene.id, params={"spp": 16}, wait=30)    # RenderPublic (cached / finished / queued)
        r = c.wait_render(r, on_progress=print)                # until the artifact exists
        png = c.download(r.artifact_key, "png")
        b = c.wait_bake(c.bake(scene.id, {"ldc_resolution": 256}))      # BakePublic, finished
        r = c.render(scene.id, method="ldc+llf", bake={"ldc_resolution": 256}, wait=30)

        ds = c.upload_dataset_resumable(*read_dataset_dir("ball/"))         # DatasetPublic
        c.wait_dataset_bake(c.bake_dataset(ds.id))                           # DatasetBakePublic, finished
        rel = c.wait_relight(c.relight(ds.id, [{"type": "point", "position": [0, 2, 3]}]))
        png = c.download_relight(rel.key, "png")                             # also "exr", "outside"
        w = c.wait_walkthrough(c.walkthrough({"scene_id": scene.id, "frames": [...]}), on_progress=print)
        mp4 = c.download_walkthrough_video(w.key)
        c.wait_walkthrough_calibration(c.calibrate_walkthroughs(scene.id, {"presets": ["low", "medium"]}))
        w = c.walkthrough({"scene_id": scene.id, "frames": [...], "quality": {"max_error": 0.1}})  # w.contract

Errors from the API (problem+json) raise :class:`ApiError` with the status, the
title/detail and the per-field errors; a job that ended failed or canceled raises
:class:`JobFailed` (an ApiError); connection problems raise ``httpx`` errors.
The client imports no engine code (no numba, Embree or OpenImageIO): the ``ibr-client``
distribution (clients/python/) installs it, the models and the client commands on their own.
"""

from __future__ import annotations

import hashlib
import json
import re
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, Literal, TypeVar

import httpx

from api_schemas.datasets import (
    DatasetBakePublic,
    DatasetList,
    DatasetPublic,
    DatasetUploadStatus,
    FileUploadPublic,
    GenerationPublic,
    RelightPublic,
)
from api_schemas.service import (
    ArtifactManifest,
    BakeList,
    BakePublic,
    BatchPublic,
    CalibrationPublic,
    JobList,
    JobPublic,
    RenderPublic,
    SceneImportPublic,
    SceneList,
    ScenePublic,
)
from api_schemas.walkthrough import WalkthroughCalibrationPublic, WalkthroughPublic

FileData = bytes | Path
"""A file's bytes, or a path to read them from (read when sent)."""


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


class InvalidId(ValueError):
    """An id or key given to the client is not one (e.g. it holds whitespace or a '/'): raised
    before any request, so a stray newline from a shell capture never reaches the URL."""


_ID = re.compile(r"[A-Za-z0-9._:~-]{1,256}")


def _id(value: str, what: str) -> str:
    """``value`` as one URL path segment, or InvalidId naming ``what`` and the value."""
    if not isinstance(value, str) or not _ID.fullmatch(value) or value in (".", ".."):
        raise InvalidId(f"invalid {what} {value!r}: expected letters, digits, '.', '_', ':', '~' or '-' only")
    return value


class JobFailed(ApiError):
    """A job (render, bake, relight, walkthrough ...) ended failed or canceled: ``detail`` says why."""


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

    def import_scene(self, fmt: Literal["gltf", "glb", "obj"], data: bytes | Path,
                     files: Mapping[str, bytes | Path] | None = None, filename: str | None = None,
                     width: int | None = None, height: int | None = None,
                     name: str | None = None) -> SceneImportPublic:
        """Import a glTF 2.0 / GLB / OBJ file as a scene (docs/scene-import.md). ``files``: the other
        files it names by relative path (glTF buffers, MTL files), keyed by that path. The answer's
        ``import_warnings`` list what the conversion left out or approximated."""
        main = Path(data).read_bytes() if isinstance(data, Path) else bytes(data)
        fname = filename or (data.name if isinstance(data, Path) else f"scene.{fmt}")
        parts: list[tuple[str, tuple[str, bytes, str]]] = [(fmt, (fname, main, "application/octet-stream"))]
        for path, blob in (files or {}).items():
            content = Path(blob).read_bytes() if isinstance(blob, Path) else bytes(blob)
            parts.append((path, (Path(path).name, content, "application/octet-stream")))
        params = {k: v for k, v in (("width", width), ("height", height), ("name", name)) if v is not None}
        r = self._request("POST", "/v1/scenes", files=parts, params=params or None)
        return SceneImportPublic.model_validate(r.json())

    def get_scene(self, scene_id: str) -> ScenePublic:
        return ScenePublic.model_validate(self._request("GET", f"/v1/scenes/{_id(scene_id, 'scene id')}").json())

    def get_scene_document(self, scene_id: str) -> dict[str, Any]:
        """The stored scene JSON (``GET /v1/scenes/{id}/document``)."""
        doc: dict[str, Any] = self._request("GET", f"/v1/scenes/{_id(scene_id, 'scene id')}/document").json()
        return doc

    def list_scenes(self, limit: int = 100, cursor: str | None = None) -> SceneList:
        """One page of this key's scenes, oldest first; pass ``next_cursor`` for the next one."""
        params: dict[str, Any] = {"limit": limit, **({"cursor": cursor} if cursor else {})}
        return SceneList.model_validate(self._request("GET", "/v1/scenes", params=params).json())

    def iter_scenes(self, page_size: int = 100) -> Iterator[ScenePublic]:
        """Every scene of this key, oldest first, a page at a time."""
        cursor: str | None = None
        while True:
            page = self.list_scenes(page_size, cursor)
            yield from page.items
            if page.next_cursor is None:
                return
            cursor = page.next_cursor

    def delete_scene(self, scene_id: str) -> None:
        self._request("DELETE", f"/v1/scenes/{_id(scene_id, 'scene id')}")

    # ------------------------------------------------------------------ renders and jobs
    def render(self, scene_id: str, camera: Mapping[str, Any] | None = None, method: str | None = None,
               params: Mapping[str, Any] | None = None, wait: float = 0.0, bake: Mapping[str, Any] | None = None,
               missing_bake: Literal["fail", "bake"] | None = None, max_error: float | None = None,
               max_ms: float | None = None, best_effort: bool = False, verify: bool = False,
               time: float | None = None, view: Mapping[str, Any] | None = None) -> RenderPublic:
        """Request a render; the answer says ``cached``, ``finished``, ``queued``, ``running`` or ``failed``.

        ``method``: ``reference`` (the default), ``ldc``, ``ldc+llf`` or ``ldc+ibrt:k``; the LDC methods
        render from the bake named by ``bake`` (its params; default params when None). Without that bake
        the API answers 409 (ApiError), unless ``missing_bake="bake"`` queues the render after the bake.
        ``view``: how an LDC method renders the view, e.g. ``{"supersample": 4, "antialias": "edges"}``
        (default: one sample per pixel).

        ``max_error`` (LRMS against the converged image) and / or ``max_ms`` (render time in the worker)
        instead of a method: a quality contract, planned from the scene's calibration (see
        :meth:`calibrate`); the answer's ``contract`` states the plan. ``best_effort``: when no setting
        meets the targets, render the closest one, marked, instead of an ApiError (422). ``verify``: also
        measure the image against a converged reference of the view (a follow-up job, at the caller's
        cost: ``contract.verification`` names it; its result holds ``measured_error``).

        ``time``: an animated scene at that moment of its animation (method ``reference`` only; a time
        outside the animation, or on a scene without one, is an ApiError 422 naming the interval)."""
        body: dict[str, Any] = {"scene_id": scene_id}
        if max_error is not None or max_ms is not None:
            if method is not None or params:
                raise ValueError("max_error / max_ms let the planner choose the method: leave out method and params")
            body["quality"] = {k: v for k, v in (("max_error", max_error), ("max_ms", max_ms)) if v is not None}
            if best_effort:
                body["quality"]["on_miss"] = "best_effort"
            if verify:
                body["quality"]["verify"] = True
        elif verify:
            raise ValueError("verify measures a quality contract's render: give max_error and / or max_ms")
        else:
            body["method"] = method or "reference"
        if camera is not None:
            body["camera"] = dict(camera)
        if params:
            body["params"] = dict(params)
        if bake:
            body["bake"] = dict(bake)
        if view:
            body["view"] = dict(view)
        if missing_bake is not None:
            body["missing_bake"] = missing_bake
        if time is not None:
            body["time"] = time
        r = self._request("POST", "/v1/renders", json=body, params={"wait": wait} if wait else None)
        return RenderPublic.model_validate(r.json())

    def job(self, job_id: str) -> JobPublic:
        return JobPublic.model_validate(self._request("GET", f"/v1/jobs/{_id(job_id, 'job id')}").json())

    def jobs(self, limit: int = 100, cursor: str | None = None, state: Sequence[str] | None = None) -> JobList:
        """One page of this key's jobs, newest first (only ``state`` when given); pass
        ``next_cursor`` for the next one."""
        params: dict[str, Any] = {"limit": limit, **({"cursor": cursor} if cursor else {})}
        if state:
            params["state"] = list(state)
        return JobList.model_validate(self._request("GET", "/v1/jobs", params=params).json())

    def cancel(self, job_id: str) -> JobPublic:
        return JobPublic.model_validate(self._request("POST", f"/v1/jobs/{_id(job_id, 'job id')}/cancel").json())

    def wait_job(self, job_id: str, timeout: float = 600.0, poll: float = 0.2,
                 on_progress: Callable[[JobPublic], None] | None = None) -> JobPublic:
        """Poll a job until it ends (finished / failed / canceled) or ``timeout`` seconds pass."""
        return _poll(self.job(job_id), lambda x: self.job(job_id),
                     lambda x: x.state in ("finished", "failed", "canceled"), lambda x: None,
                     lambda x: f"job {job_id} still {x.state}", timeout, poll, on_progress)

    def wait_render(self, r: RenderPublic, timeout: float = 600.0,
                    on_progress: Callable[[JobPublic], None] | None = None) -> ArtifactManifest:
        """The artifact of a render request, waiting for its job if needed. Raises ApiError if it failed."""
        if r.artifact is not None:
            return r.artifact
        if r.job is None:
            return self.artifact(r.artifact_key)
        j = self.wait_job(r.job.id, timeout=timeout, on_progress=on_progress)
        if j.state != "finished":
            raise JobFailed(500 if j.state == "failed" else 409, f"render job {j.state}", j.error or "")
        return self.artifact(r.artifact_key)

    # ------------------------------------------------------------------ bakes
    def bake(self, scene_id: str, params: Mapping[str, Any] | None = None) -> BakePublic:
        """Request a bake of a scene (``BakeParams`` fields); ``cached`` when it exists already."""
        r = self._request("POST", f"/v1/scenes/{_id(scene_id, 'scene id')}/bakes", json=dict(params or {}))
        return BakePublic.model_validate(r.json())

    def get_bake(self, scene_id: str, key: str) -> BakePublic:
        url = f"/v1/scenes/{_id(scene_id, 'scene id')}/bakes/{_id(key, 'bake key')}"
        return BakePublic.model_validate(self._request("GET", url).json())

    def list_bakes(self, scene_id: str) -> BakeList:
        return BakeList.model_validate(self._request("GET", f"/v1/scenes/{_id(scene_id, 'scene id')}/bakes").json())

    def delete_bake(self, scene_id: str, key: str) -> None:
        self._request("DELETE", f"/v1/scenes/{_id(scene_id, 'scene id')}/bakes/{_id(key, 'bake key')}")

    def wait_bake(self, b: BakePublic, timeout: float = 3600.0, poll: float = 0.3,
                  on_progress: Callable[[BakePublic], None] | None = None) -> BakePublic:
        """Poll a bake until it is finished (returned) or failed / canceled / missing (ApiError)."""
        def failed(x: BakePublic) -> JobFailed | None:
            if x.state in ("failed", "canceled", "missing"):
                return JobFailed(500 if x.state == "failed" else 409, f"bake {x.state}", x.error or "")
            return None

        return _poll(b, lambda x: self.get_bake(x.scene_id, x.key), lambda x: x.state == "finished", failed,
                     lambda x: f"bake {x.key} still {x.state}", timeout, poll, on_progress)

    # ------------------------------------------------------------------ calibrations
    def calibrate(self, scene_id: str, bake: Mapping[str, Any] | None = None,
                  params: Mapping[str, Any] | None = None,
                  missing_bake: Literal["fail", "bake"] | None = None) -> CalibrationPublic:
        """Calibrate a scene's bake for quality contracts (``CalibrationParams`` fields in ``params``);
        ``cached`` when this calibration exists already."""
        body: dict[str, Any] = {"bake": dict(bake or {}), "params": dict(params or {})}
        if missing_bake is not None:
            body["missing_bake"] = missing_bake
        r = self._request("POST", f"/v1/scenes/{_id(scene_id, 'scene id')}/calibrations", json=body)
        return CalibrationPublic.model_validate(r.json())

    def get_calibration(self, scene_id: str, bake_key: str, key: str | None = None) -> CalibrationPublic:
        r = self._request("GET", f"/v1/scenes/{_id(scene_id, 'scene id')}/calibrations/{_id(bake_key, 'bake key')}",
                          params={"key": key} if key else None)
        return CalibrationPublic.model_validate(r.json())

    def wait_calibration(self, c: CalibrationPublic, timeout: float = 3600.0, poll: float = 0.5,
                         on_progress: Callable[[CalibrationPublic], None] | None = None) -> CalibrationPublic:
        """Poll a calibration until it is finished (returned) or failed / missing (ApiError)."""
        return _poll(c, lambda x: self.get_calibration(x.scene_id, x.bake_key, x.key), lambda x: x.state == "finished",
                     lambda x: _calibration_failed(x, "calibration"), lambda x: f"calibration {x.key} still {x.state}",
                     timeout, poll, on_progress)

    def calibrate_walkthroughs(self, scene_id: str,
                               params: Mapping[str, Any] | None = None) -> WalkthroughCalibrationPublic:
        """Calibrate a scene's walkthrough settings (bake preset x fill) for walkthrough quality contracts
        (``WalkthroughCalibrationParams`` fields in ``params``: presets, fills, probes, size, ...); ``cached``
        when this calibration exists already."""
        body: dict[str, Any] = {"params": dict(params or {})}
        r = self._request("POST", f"/v1/scenes/{_id(scene_id, 'scene id')}/walkthrough-calibrations", json=body)
        return WalkthroughCalibrationPublic.model_validate(r.json())

    def get_walkthrough_calibration(self, scene_id: str, key: str | None = None) -> WalkthroughCalibrationPublic:
        """The scene's walkthrough calibration (its model once made); with ``key`` (from
        :meth:`calibrate_walkthroughs`) that calibration's job. ApiError 404 when there is none and no key."""
        r = self._request("GET", f"/v1/scenes/{_id(scene_id, 'scene id')}/walkthrough-calibrations",
                          params={"key": key} if key else None)
        return WalkthroughCalibrationPublic.model_validate(r.json())

    def wait_walkthrough_calibration(
            self, c: WalkthroughCalibrationPublic, timeout: float = 3600.0, poll: float = 0.5,
            on_progress: Callable[[WalkthroughCalibrationPublic], None] | None = None) -> WalkthroughCalibrationPublic:
        """Poll a walkthrough calibration until it is finished (returned) or failed / missing (ApiError)."""
        return _poll(c, lambda x: self.get_walkthrough_calibration(x.scene_id, x.key), lambda x: x.state == "finished",
                     lambda x: _calibration_failed(x, "walkthrough calibration"),
                     lambda x: f"walkthrough calibration {x.key} still {x.state}", timeout, poll, on_progress)

    # ------------------------------------------------------------------ artifacts
    def artifact(self, key: str) -> ArtifactManifest:
        return ArtifactManifest.model_validate(self._request("GET", f"/v1/artifacts/{_id(key, 'artifact key')}").json())

    def download(self, key: str, fmt: Literal["exr", "png"] = "png") -> bytes:
        return self._request("GET", f"/v1/artifacts/{_id(key, 'artifact key')}/image.{fmt}").content

    # ------------------------------------------------------------------ batches
    def batch(self, scenes: list[Mapping[str, Any]] | None = None,
              renders: list[Mapping[str, Any]] | None = None,
              meshes: Sequence[Mapping[str, FileData] | None] | None = None) -> BatchPublic:
        """Store ``scenes`` and queue ``renders`` in one call. ``meshes[i]``: the mesh files of
        ``scenes[i]`` by ``mesh_file`` path (bytes or a file); with any, the batch goes as multipart."""
        body = {"scenes": [{"scene": s} for s in (scenes or [])], "renders": list(renders or [])}
        files = [(f"scenes.{i}.{path}", (Path(path).name, _bytes(data), "application/octet-stream"))
                 for i, scene_meshes in enumerate(meshes or []) for path, data in (scene_meshes or {}).items()]
        if not files:
            return BatchPublic.model_validate(self._request("POST", "/v1/batches", json=body).json())
        parts: list[tuple[str, tuple[str | None, bytes, str]]] = [
            ("batch", (None, json.dumps(body).encode(), "application/json")), *files]
        return BatchPublic.model_validate(self._request("POST", "/v1/batches", files=parts).json())

    def get_batch(self, batch_id: str) -> BatchPublic:
        return BatchPublic.model_validate(self._request("GET", f"/v1/batches/{_id(batch_id, 'batch id')}").json())

    # ------------------------------------------------------------------ datasets: upload
    def upload_dataset(self, manifest: Mapping[str, Any], files: Mapping[str, FileData]) -> DatasetPublic:
        """Store a dataset in one multipart request: ``manifest`` (a ``DatasetManifest`` as a dict)
        plus ``files`` mapping each file name the manifest uses to its bytes or path."""
        parts: list[tuple[str, tuple[str | None, bytes, str]]] = [
            ("manifest", (None, json.dumps(dict(manifest)).encode(), "application/json"))]
        parts += [(name, (name, _bytes(data), "application/octet-stream")) for name, data in files.items()]
        return DatasetPublic.model_validate(self._request("POST", "/v1/datasets", files=parts).json())

    def dataset_upload_status(self, manifest: Mapping[str, Any]) -> DatasetUploadStatus:
        """Send a manifest with every file's sha256: which files the server still needs."""
        r = self._request("POST", "/v1/datasets", json=dict(manifest))
        return DatasetUploadStatus.model_validate(r.json())

    def upload_file(self, data: FileData, sha256: str | None = None) -> FileUploadPublic:
        """PUT one file (dataset image, depth, mask, environment map, plate) by its sha256."""
        blob = _bytes(data)
        sha = sha256 or hashlib.sha256(blob).hexdigest()
        r = self._request("PUT", f"/v1/datasets/uploads/{_id(sha, 'sha256')}", content=blob,
                          headers={"Content-Type": "application/octet-stream"})
        return FileUploadPublic.model_validate(r.json())

    def commit_dataset(self, dataset_id: str) -> DatasetPublic:
        url = f"/v1/datasets/{_id(dataset_id, 'dataset id')}/commit"
        return DatasetPublic.model_validate(self._request("POST", url).json())

    def upload_dataset_resumable(self, manifest: Mapping[str, Any], files: Mapping[str, FileData],
                                 on_progress: Callable[[int, int, str], None] | None = None) -> DatasetPublic:
        """Resumable upload: fill in the sha256s, send the manifest, PUT only the files the server
        lacks (``on_progress(done, total, name)`` after each), commit. Run again after an interruption:
        files already received are not sent again."""
        full = with_sha256s(manifest, files)
        status = self.dataset_upload_status(full)
        if status.state == "committed":
            return self.get_dataset(status.dataset_id)
        total = len(status.missing)
        for i, item in enumerate(status.missing):
            if item.name not in files:
                raise ValueError(f"{item.field}: no file {item.name!r} given")
            try:
                self._request("PUT", item.upload_url, content=_bytes(files[item.name]),
                              headers={"Content-Type": "application/octet-stream"})
            except ApiError as exc:
                raise _named_upload_error(exc, item.name, item.upload_url) from None
            if on_progress is not None:
                on_progress(i + 1, total, item.name)
        return self.commit_dataset(status.dataset_id)

    # ------------------------------------------------------------------ datasets: read, generate, bake
    def list_datasets(self, limit: int = 100, cursor: str | None = None) -> DatasetList:
        """One page of this key's datasets, oldest first; pass ``next_cursor`` for the next one."""
        params: dict[str, Any] = {"limit": limit, **({"cursor": cursor} if cursor else {})}
        return DatasetList.model_validate(self._request("GET", "/v1/datasets", params=params).json())

    def iter_datasets(self, page_size: int = 100) -> Iterator[DatasetPublic]:
        """Every dataset of this key, oldest first, a page at a time."""
        cursor: str | None = None
        while True:
            page = self.list_datasets(page_size, cursor)
            yield from page.items
            if page.next_cursor is None:
                return
            cursor = page.next_cursor

    def get_dataset(self, dataset_id: str) -> DatasetPublic:
        url = f"/v1/datasets/{_id(dataset_id, 'dataset id')}"
        return DatasetPublic.model_validate(self._request("GET", url).json())

    def delete_dataset(self, dataset_id: str) -> None:
        self._request("DELETE", f"/v1/datasets/{_id(dataset_id, 'dataset id')}")

    def download_dataset_file(self, dataset_id: str, sha256: str) -> bytes:
        url = f"/v1/datasets/{_id(dataset_id, 'dataset id')}/files/{_id(sha256, 'sha256')}"
        return self._request("GET", url).content

    def generate_dataset(self, scene_id: str, placement: Mapping[str, Any] | None = None,
                         params: Mapping[str, Any] | None = None, camera: Mapping[str, Any] | None = None,
                         max_lights: int | None = None, ground_truth: Sequence[Mapping[str, Any]] = (),
                         wait: float = 0.0) -> GenerationPublic:
        """Render a stored scene under point lights placed over a sphere (``LightPlacement`` fields)
        into a dataset (bake queue); ``dataset_id`` is set once finished."""
        body: dict[str, Any] = {"scene_id": scene_id}
        for k, v in (("placement", placement), ("params", params), ("camera", camera)):
            if v is not None:
                body[k] = dict(v)
        if max_lights is not None:
            body["max_lights"] = max_lights
        if ground_truth:
            body["ground_truth"] = [dict(x) for x in ground_truth]
        r = self._request("POST", "/v1/datasets/generate", json=body, params={"wait": wait} if wait else None)
        return GenerationPublic.model_validate(r.json())

    def get_generation(self, key: str) -> ArtifactManifest:
        url = f"/v1/datasets/generations/{_id(key, 'generation key')}"
        return ArtifactManifest.model_validate(self._request("GET", url).json())

    def wait_generation(self, g: GenerationPublic, timeout: float = 3600.0,
                        on_progress: Callable[[JobPublic], None] | None = None) -> str:
        """The generated dataset's id, waiting for the generation job if needed (ApiError if it failed)."""
        if g.dataset_id is not None:
            return g.dataset_id
        self._wait_ok(g.job, "dataset generation", timeout, on_progress)
        return str(self.get_generation(g.artifact_key).result["dataset_id"])

    def bake_dataset(self, dataset_id: str, params: Mapping[str, Any] | None = None,
                     wait: float = 0.0) -> DatasetBakePublic:
        """Bake a dataset for relighting (``BakeParams`` fields); ``cached`` when it exists already."""
        url = f"/v1/datasets/{_id(dataset_id, 'dataset id')}/bake"
        r = self._request("POST", url, json={"params": dict(params or {})},
                          params={"wait": wait} if wait else None)
        return DatasetBakePublic.model_validate(r.json())

    def wait_dataset_bake(self, b: DatasetBakePublic, params: Mapping[str, Any] | None = None,
                          timeout: float = 3600.0,
                          on_progress: Callable[[JobPublic], None] | None = None) -> DatasetBakePublic:
        """The finished bake (with its artifact), waiting for its job if needed (ApiError if it failed).
        ``params``: the bake params ``b`` was requested with (the finished bake is fetched by asking again)."""
        if b.artifact is not None:
            return b
        self._wait_ok(b.job, "dataset bake", timeout, on_progress)
        done = self.bake_dataset(b.dataset_id, params)  # the same request again: the stored artifact
        if done.artifact is None or done.artifact_key != b.artifact_key:
            raise ApiError(409, "dataset bake not stored after its job finished (other params?)", b.artifact_key)
        return done

    # ------------------------------------------------------------------ relight, composite
    def relight(self, dataset_id: str, lights: Sequence[Mapping[str, Any]], bake: Mapping[str, Any] | None = None,
                exposure_stops: float | None = None, min_light_distance: float | None = None,
                wait: float = 0.0) -> RelightPublic:
        """Relight a baked dataset under ``lights`` (``RelightLight`` dicts, superposed). 409 (ApiError)
        when the dataset is not baked with ``bake`` (default bake params)."""
        body: dict[str, Any] = {"dataset_id": dataset_id, "lights": [dict(x) for x in lights]}
        if bake:
            body["bake"] = dict(bake)
        if exposure_stops is not None:
            body["exposure_stops"] = exposure_stops
        if min_light_distance is not None:
            body["min_light_distance"] = min_light_distance
        r = self._request("POST", "/v1/relights", json=body, params={"wait": wait} if wait else None)
        return RelightPublic.model_validate(r.json())

    def composite(self, request: Mapping[str, Any], wait: float = 0.0) -> RelightPublic:
        """Composite a relit object into a plate (a ``CompositeRequest`` as a dict; upload the plate
        and masks first with :meth:`upload_file`)."""
        r = self._request("POST", "/v1/composites", json=dict(request), params={"wait": wait} if wait else None)
        return RelightPublic.model_validate(r.json())

    def get_relight(self, key: str, kind: Literal["relight", "composite"] = "relight") -> ArtifactManifest:
        return ArtifactManifest.model_validate(self._request("GET", f"/v1/{kind}s/{_id(key, kind + ' key')}").json())

    def wait_relight(self, r: RelightPublic, timeout: float = 600.0,
                     on_progress: Callable[[JobPublic], None] | None = None,
                     kind: Literal["relight", "composite"] = "relight") -> ArtifactManifest:
        """The result's manifest (counts, timings), waiting for its job if needed (ApiError if it failed)."""
        if r.artifact is not None:
            return r.artifact
        self._wait_ok(r.job, kind, timeout, on_progress)
        return self.get_relight(r.artifact_key, kind)

    def download_relight(self, key: str, which: Literal["exr", "png", "outside"] = "png",
                         kind: Literal["relight", "composite"] = "relight") -> bytes:
        """The relit (or composite) image: ``exr`` linear float, ``png`` sRGB preview, ``outside`` the
        coverage mask (white where a light direction fell outside the dataset)."""
        name = "outside.png" if which == "outside" else f"image.{which}"
        return self._request("GET", f"/v1/{kind}s/{_id(key, kind + ' key')}/{name}").content

    # ------------------------------------------------------------------ walkthroughs
    def walkthrough(self, request: Mapping[str, Any]) -> WalkthroughPublic:
        """Request a walkthrough (a ``WalkthroughRequest`` as a dict: scene_id, frames, bake, fill, ...).

        ``quality`` (``{"max_error": 0.1, "max_ms": 20, "on_miss": "best_effort"}``) instead of ``bake`` and
        ``fill``: the planner picks both from the scene's walkthrough calibration (see
        :meth:`calibrate_walkthroughs`; ApiError 409 without one, 422 when no setting meets a strict
        contract); the answer's ``contract`` states the plan."""
        return WalkthroughPublic.model_validate(self._request("POST", "/v1/walkthroughs", json=dict(request)).json())

    def get_walkthrough(self, key: str) -> WalkthroughPublic:
        url = f"/v1/walkthroughs/{_id(key, 'walkthrough key')}"
        return WalkthroughPublic.model_validate(self._request("GET", url).json())

    def delete_walkthrough(self, key: str) -> None:
        """Delete a walkthrough's video, frames and request (409 ApiError while its jobs run)."""
        self._request("DELETE", f"/v1/walkthroughs/{_id(key, 'walkthrough key')}")

    def wait_walkthrough(self, w: WalkthroughPublic, timeout: float = 3600.0, poll: float = 0.3,
                         on_progress: Callable[[WalkthroughPublic], None] | None = None) -> WalkthroughPublic:
        """Poll a walkthrough until it is finished (returned) or failed (ApiError naming the first error)."""
        return _poll(w, lambda x: self.get_walkthrough(x.key), lambda x: x.status == "finished",
                     lambda x: JobFailed(500, "walkthrough failed", x.error or "") if x.status == "failed" else None,
                     lambda x: f"walkthrough {x.key} still {x.status}", timeout, poll, on_progress)

    def download_walkthrough_video(self, key: str) -> bytes:
        """The finished walkthrough's MP4 (H.264) preview."""
        return self._request("GET", f"/v1/walkthroughs/{_id(key, 'walkthrough key')}/video.mp4").content

    def download_walkthrough_frame(self, key: str, index: int,
                                   kind: Literal["png", "exr", "provenance"] = "png") -> bytes:
        """Frame ``index``: ``png`` sRGB, ``exr`` linear radiance, ``provenance`` 8-bit codes (PNG)."""
        return self._request("GET", f"/v1/walkthroughs/{_id(key, 'walkthrough key')}/frames/{index}.{kind}").content

    # ------------------------------------------------------------------ helpers
    def _wait_ok(self, job: JobPublic | None, what: str, timeout: float,
                 on_progress: Callable[[JobPublic], None] | None) -> None:
        if job is None:
            raise ApiError(404, f"{what}: no job and no result")
        j = self.wait_job(job.id, timeout=timeout, on_progress=on_progress)
        if j.state != "finished":
            raise JobFailed(500 if j.state == "failed" else 409, f"{what} job {j.state}", j.error or "")


_T = TypeVar("_T")


def _poll(first: _T, refresh: Callable[[_T], _T], done: Callable[[_T], bool],
          failed: Callable[[_T], Exception | None], still: Callable[[_T], str], timeout: float, poll: float,
          on_progress: Callable[[_T], None] | None) -> _T:
    """Poll a resource until ``done`` (returned) or ``failed`` (its error raised): ``on_progress``
    with each state, ``refresh`` every ``poll`` seconds, growing 1.3x to 2 s between polls, and
    TimeoutError (``still(state)`` and the timeout) after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    delay = poll
    x = first
    while True:
        if on_progress is not None:
            on_progress(x)
        if done(x):
            return x
        err = failed(x)
        if err is not None:
            raise err
        if time.monotonic() > deadline:
            raise TimeoutError(f"{still(x)} after {timeout} s")
        time.sleep(delay)
        delay = min(2.0, delay * 1.3)
        x = refresh(x)


def _calibration_failed(c: CalibrationPublic | WalkthroughCalibrationPublic, what: str) -> JobFailed | None:
    if c.state in ("failed", "missing"):
        return JobFailed(500 if c.state == "failed" else 409, f"{what} {c.state}",
                         (c.job.error if c.job is not None else None) or "")
    return None


def _bytes(data: FileData) -> bytes:
    return Path(data).read_bytes() if isinstance(data, Path) else bytes(data)


def with_sha256s(manifest: Mapping[str, Any], files: Mapping[str, FileData]) -> dict[str, Any]:
    """A copy of ``manifest`` with the sha256 of every file it names filled in (ValueError naming
    the field when a file is missing from ``files``)."""
    m: dict[str, Any] = json.loads(json.dumps(dict(manifest)))
    refs: list[tuple[str, dict[str, Any]]] = [(f"images.{i}", img) for i, img in enumerate(m.get("images") or [])
                                              if isinstance(img, dict)]
    for part in ("geometry", "mask"):
        ref = m.get(part)
        if isinstance(ref, dict) and "file" in ref:
            refs.append((part, ref))
    for field, ref in refs:
        name = ref.get("file")
        if not isinstance(name, str) or name not in files:
            raise ValueError(f"{field}.file: no file {name!r}")
        ref["sha256"] = hashlib.sha256(_bytes(files[name])).hexdigest()
    return m


def read_dataset_dir(path: str | Path) -> tuple[dict[str, Any], dict[str, Path]]:
    """A dataset on disk: ``path`` is a manifest JSON file, or a directory holding ``manifest.json``;
    every file the manifest names is looked up next to it. Returns (manifest, {name: path}); raises
    ValueError naming the field (or the manifest) when something is missing or unreadable."""
    p = Path(path)
    mpath = p / "manifest.json" if p.is_dir() else p
    if not mpath.is_file():
        raise ValueError(f"{mpath}: no such manifest file")
    try:
        manifest = json.loads(mpath.read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{mpath}: not valid JSON: {exc}") from None
    if not isinstance(manifest, dict):
        raise ValueError(f"{mpath}: the manifest must be a JSON object")
    files: dict[str, Path] = {}
    refs: list[tuple[str, Any]] = [(f"images.{i}", img) for i, img in enumerate(manifest.get("images") or [])]
    refs += [(part, manifest.get(part)) for part in ("geometry", "mask")]
    for field, ref in refs:
        if not isinstance(ref, dict) or "file" not in ref:
            continue
        name = ref["file"]
        f = mpath.parent / str(name)
        if not f.is_file():
            raise ValueError(f"{field}.file: {name!r} not found next to the manifest ({f})")
        files[str(name)] = f
    return manifest, files


def _named_upload_error(exc: ApiError, name: str, upload_url: str) -> ApiError:
    """``exc`` from the PUT of one file, naming the file as the manifest does (``files.002.png``)
    instead of by the sha256 in its upload URL (``files.580bc0e7...``), as a multipart upload does."""
    sha = upload_url.rstrip("/").rsplit("/", 1)[-1]
    errors = [{**e, "field": f"files.{name}" if e.get("field") == f"files.{sha}" else e.get("field"),
               "message": str(e.get("message", "")).replace(sha, name)} for e in exc.errors]
    detail = exc.detail.replace(sha, name)
    if name not in detail:
        detail = f"{name}: {detail}" if detail else name
    cls = type(exc)
    return cls(exc.status, exc.title, detail, errors)


def _error(r: httpx.Response) -> ApiError:
    try:
        body = r.json()
    except ValueError:
        return ApiError(r.status_code, r.reason_phrase or "error", r.text[:500])
    if isinstance(body, dict):
        return ApiError(r.status_code, str(body.get("title") or r.reason_phrase), str(body.get("detail") or ""),
                        body.get("errors") if isinstance(body.get("errors"), list) else None)
    return ApiError(r.status_code, r.reason_phrase or "error", str(body)[:500])
