"""The render job's image encoding (``encode_render_blobs``) and concurrent artifact commits
(``write_artifact(max_workers=...)``): every blob decodes back to the engine's output (EXR float data
bit for bit, the preview equal to the reference tonemap), and the blobs-then-manifest rule holds
while blob writes overlap."""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import OpenImageIO as oiio
import pytest

from engine.errors import NonFiniteOutputError
from engine.imageio import read_image, tonemap_srgb
from producer import artifacts as art
from producer.store import LocalStore, NotFound, StoreUnavailable
from workers.jobs.render import EXR, OUTPUT_BLOBS, PNG, PROVENANCE_CODES, encode_render_blobs


def _render_like(h: int = 48, w: int = 64, seed: int = 0) -> dict[str, np.ndarray]:
    """Arrays shaped and typed like an LDC render's output, with awkward values."""
    rng = np.random.default_rng(seed)
    radiance = (rng.exponential(0.4, (h, w, 3)) * (rng.random((h, w, 1)) < 0.9)).astype(np.float32)
    radiance[0, 0] = [0.0, 1e-30, 3.0e4]
    radiance[0, 1] = imageio_threshold_values()[:3]
    normal = rng.standard_normal((h, w, 3)).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=2, keepdims=True)
    depth = np.where(rng.random((h, w)) < 0.2, 0.0, rng.uniform(0.5, 40.0, (h, w))).astype(np.float32)
    object_id = rng.integers(-1, 5, (h, w)).astype(np.int32)
    object_id[0, 0] = 2**24 - 1  # the largest id float32 stores exactly
    material_id = rng.integers(-1, 3, (h, w)).astype(np.int32)
    provenance = rng.integers(0, 5, (h, w)).astype(np.uint8)
    return {"radiance": radiance, "depth": depth, "normal": normal, "object_id": object_id,
            "material_id": material_id, "provenance": provenance}


def imageio_threshold_values() -> np.ndarray:
    from engine import imageio

    return imageio._srgb8_thresholds()[100:110].astype(np.float32)


def _decode(tmp_path: Path, name: str, data: bytes, **kw: Any) -> tuple[np.ndarray, dict[str, Any]]:
    p = tmp_path / name
    p.write_bytes(data)
    return read_image(p, **kw)


def test_blobs_decode_to_the_render_output(tmp_path: Path) -> None:
    out = _render_like()
    meta = {"camera": {"eye": [1.0, 2.0, 3.0]}, "scene_id": "a" * 64, "method": "ldc+llf", "artifact_key": "b" * 64}
    blobs = encode_render_blobs(out, meta)
    assert set(blobs) == {"preview.png", "radiance.exr", "depth.exr", "normal.exr", "object_id.exr",
                          "material_id.exr", "provenance.png"}
    assert all(ctype == (PNG if name.endswith(".png") else EXR) for name, (_, ctype) in blobs.items())

    for name, key, aov in [("radiance.exr", "radiance", None), ("normal.exr", "normal", "normal"),
                           ("depth.exr", "depth", "depth"), ("object_id.exr", "object_id", "object_id"),
                           ("material_id.exr", "material_id", "material_id")]:
        back, md = _decode(tmp_path, name, blobs[name][0])
        expected = out[key].astype(np.float32).reshape(back.shape)
        np.testing.assert_array_equal(back.view(np.uint32), expected.view(np.uint32))  # bit-exact
        assert md["camera"] == meta["camera"] and md["artifact_key"] == meta["artifact_key"]
        assert md.get("aov") == aov

    png = tmp_path / "preview.png"
    png.write_bytes(blobs["preview.png"][0])
    inp = oiio.ImageInput.open(str(png))
    codes = inp.read_image(oiio.UINT8)
    inp.close()
    reference = np.rint(tonemap_srgb(out["radiance"]) * 255).astype(np.int64)
    assert int(np.max(np.abs(codes.astype(np.int64) - reference))) <= 1
    np.testing.assert_array_equal(codes, reference)  # in fact exact
    _, md = _decode(tmp_path, "preview.png", blobs["preview.png"][0])
    assert md["exposure_stops"] == 0.0 and md["scene_id"] == meta["scene_id"]

    prov = tmp_path / "provenance.png"
    prov.write_bytes(blobs["provenance.png"][0])
    inp = oiio.ImageInput.open(str(prov))
    got = inp.read_image(oiio.UINT8)[:, :, 0]
    codes_attr = inp.spec().get_string_attribute("ibr:provenance_codes")
    inp.close()
    np.testing.assert_array_equal(got, out["provenance"])
    assert codes_attr and set(PROVENANCE_CODES.values()) <= set(codes_attr.replace('"', " ").split())


def test_encoding_is_deterministic_and_reference_renders_have_no_provenance() -> None:
    out = _render_like(seed=4)
    meta = {"scene_id": "c" * 64}
    a = encode_render_blobs(out, meta)
    assert a == encode_render_blobs(out, meta)
    no_prov = {k: v for k, v in out.items() if k != "provenance"}
    b = encode_render_blobs(no_prov, meta)
    assert "provenance.png" not in b and {k: v for k, v in a.items() if k != "provenance.png"} == b


@pytest.mark.parametrize("outputs", [["preview"], ["radiance"], ["preview", "radiance"], ["provenance", "depth"],
                                     ["material_id", "object_id", "normal"]])
def test_an_outputs_subset_encodes_exactly_those_blobs_with_the_same_bytes(outputs: list[str]) -> None:
    out = _render_like(seed=5)
    meta = {"scene_id": "d" * 64, "method": "ldc+ibrt:1"}
    full = encode_render_blobs(out, meta)
    lean = encode_render_blobs(out, meta, outputs)
    assert set(lean) == {OUTPUT_BLOBS[o] for o in outputs}
    assert lean == {name: full[name] for name in lean}  # same bytes and content types as in a full artifact
    assert encode_render_blobs(out, meta, list(OUTPUT_BLOBS)) == full


def test_bad_outputs_are_refused_before_encoding() -> None:
    out = _render_like(seed=6)
    with pytest.raises(ValueError, match="non-empty subset"):
        encode_render_blobs(out, {}, [])
    with pytest.raises(ValueError, match="'aovs'"):
        encode_render_blobs(out, {}, ["preview", "aovs"])
    no_prov = {k: v for k, v in out.items() if k != "provenance"}
    with pytest.raises(ValueError, match="only the LDC methods"):
        encode_render_blobs(no_prov, {}, ["preview", "provenance"])
    # the schema's names and the job's names are the same set
    from api_schemas.service import RENDER_OUTPUTS

    assert set(RENDER_OUTPUTS) == set(OUTPUT_BLOBS)


def test_a_non_finite_render_encodes_nothing() -> None:
    out = _render_like(seed=2)
    out["radiance"][3, 4, 1] = np.inf
    with pytest.raises(NonFiniteOutputError, match="non-finite"):
        encode_render_blobs(out, {})


# ------------------------------------------------------------------------------ concurrent artifact commits


class SlowRecording:
    """A store whose blob writes take a while and are recorded with their start and end times."""

    def __init__(self, inner: LocalStore, delay: float = 0.05, fail: str | None = None) -> None:
        self.inner, self.delay, self.fail = inner, delay, fail
        self.events: list[tuple[str, float, float]] = []
        self.lock = threading.Lock()

    def put_bytes(self, key: str, data: bytes, content_type: str = "application/octet-stream") -> None:
        t0 = time.monotonic()
        if not key.endswith("manifest.json"):
            time.sleep(self.delay)
        if self.fail and key.endswith(self.fail):
            raise StoreUnavailable(f"injected failure writing {key}")
        self.inner.put_bytes(key, data, content_type)
        with self.lock:
            self.events.append((key, t0, time.monotonic()))

    def __getattr__(self, name: str) -> Any:
        return getattr(self.inner, name)


def _commit(store: Any, blobs: dict[str, tuple[bytes, str]], workers: int) -> str:
    params = {"n": len(blobs)}
    key = art.artifact_key("render", {}, params, "t")
    art.write_artifact(store, key, "render", {}, params, "t", blobs, {"ok": True}, max_workers=workers)
    return key


def test_concurrent_blob_writes_overlap_and_the_manifest_comes_last(tmp_path: Path) -> None:
    blobs = {f"b{i}.bin": (bytes([i]) * (1000 + i), "application/octet-stream") for i in range(6)}
    store = SlowRecording(LocalStore(tmp_path / "s"))
    key = _commit(store, blobs, workers=4)
    names = [k.rsplit("/", 1)[1] for k, _, _ in store.events]
    assert names[-1] == "manifest.json" and sorted(names[:-1]) == sorted(blobs)
    manifest_start = store.events[-1][1]
    assert all(end <= manifest_start for _, _, end in store.events[:-1])  # every blob durable first
    starts = sorted(t0 for _, t0, _ in store.events[:-1])
    assert starts[3] - starts[0] < store.delay  # four writes were in flight together
    for name, (data, _) in blobs.items():
        assert art.read_blob(store.inner, key, name) == data


def test_concurrent_writes_start_in_the_callers_order(tmp_path: Path) -> None:
    blobs = {name: (name.encode() * 50, "application/octet-stream") for name in ("z.png", "a.exr", "m.exr")}
    store = SlowRecording(LocalStore(tmp_path / "s"), delay=0.0)
    started: list[str] = []
    real = store.put_bytes

    def put(key: str, data: bytes, content_type: str = "application/octet-stream") -> None:
        with store.lock:
            started.append(key.rsplit("/", 1)[1])
        real(key, data, content_type)

    store.put_bytes = put  # type: ignore[method-assign]
    _commit(store, blobs, workers=2)
    # FIFO pool of 2: z.png is taken before m.exr can be (in sorted order it would be started last)
    assert started.index("z.png") < started.index("m.exr") and started[-1] == "manifest.json"


def test_a_failed_concurrent_write_publishes_no_artifact(tmp_path: Path) -> None:
    blobs = {f"b{i}.bin": (bytes([i]) * 100, "application/octet-stream") for i in range(5)}
    inner = LocalStore(tmp_path / "s")
    store = SlowRecording(inner, delay=0.01, fail="b2.bin")
    with pytest.raises(StoreUnavailable, match="b2.bin"):
        _commit(store, blobs, workers=3)
    key = art.artifact_key("render", {}, {"n": 5}, "t")
    assert art.read_manifest(inner, key) is None
    assert not any(k.endswith("manifest.json") for k, _, _ in store.events)
    with pytest.raises(NotFound):
        art.read_blob(inner, key, "b0.bin")
    _commit(inner, blobs, workers=3)  # the retry commits
    assert art.read_blob(inner, key, "b2.bin") == blobs["b2.bin"][0]


@pytest.mark.parametrize("bad", [0, -1, 1.5, True])
def test_max_workers_must_be_a_positive_int(tmp_path: Path, bad: Any) -> None:
    with pytest.raises(ValueError, match="max_workers"):
        _commit(LocalStore(tmp_path / "s"), {"a.bin": (b"x", "text/plain")}, workers=bad)
