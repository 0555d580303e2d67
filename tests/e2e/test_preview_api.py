"""The API endpoints only the preview page uses (``service/api/routes/preview.py``): capabilities that
never offer a method the API refuses, and the engine-free LRMS / heatmap / exposure / provenance code
checked against ``engine.metrics`` and ``engine.imageio`` (which the API process must not import)."""

from __future__ import annotations

import io
from typing import Any

import httpx
import numpy as np
import pytest
from PIL import Image

from engine.imageio import srgb_encode, tonemap_srgb
from engine.metrics import error_heatmap
from engine.metrics import lrms as engine_lrms
from service.api.routes import preview
from service.up import Stack

RNG = np.random.default_rng(7)


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_lrms_and_heatmap_match_engine_metrics(channels: int) -> None:
    ref = RNG.gamma(2.0, 0.3, size=(17, 23, channels)).astype(np.float32)
    test = (ref * RNG.uniform(0.7, 1.3, size=ref.shape)).astype(np.float32)
    if channels == 4:
        ref[..., 3] = (RNG.uniform(size=ref.shape[:2]) > 0.3).astype(np.float32)
        test[..., 3] = ref[..., 3]
    mask = preview.coverage_mask(ref)
    engine_mask = ref[..., 3] > 0 if channels == 4 else None
    assert preview.lrms(test, ref, mask) == pytest.approx(engine_lrms(test, ref, engine_mask), rel=1e-12)
    ours = preview.heatmap(test, ref, mask)
    theirs = np.rint(srgb_encode(error_heatmap(test, ref, mask=engine_mask).astype(np.float64)) * 255.0)
    assert np.abs(ours.astype(np.int64) - theirs.astype(np.int64)).max() <= 1


def test_lrms_of_black_reference() -> None:
    black = np.zeros((4, 4, 3), np.float32)
    mask = preview.coverage_mask(black)
    assert preview.lrms(black, black, mask) == 0.0 == engine_lrms(black, black)
    other = black.copy()
    other[0, 0] = 1.0
    assert preview.lrms(other, black, mask) == np.inf == engine_lrms(other, black)


@pytest.mark.parametrize("exposure", [-2.0, 0.0, 1.5])
def test_exposure_encoding_matches_engine_png_transform(exposure: float) -> None:
    img = RNG.gamma(1.5, 0.4, size=(9, 11, 3)).astype(np.float32)
    ours = preview.to_srgb8(img, exposure)
    theirs = np.rint(tonemap_srgb(img, exposure) * 255.0).astype(np.uint8)
    np.testing.assert_array_equal(ours, theirs)


def test_png_and_exr_roundtrip() -> None:
    rgb = RNG.integers(0, 256, size=(5, 7, 3), dtype=np.uint8)
    back = np.asarray(Image.open(io.BytesIO(preview.png_bytes(rgb))))
    np.testing.assert_array_equal(back, rgb)
    codes = preview.read_image(preview.png_bytes(np.repeat(np.arange(35, dtype=np.uint8).reshape(5, 7, 1) % 5, 3, 2)),
                               ".png")
    assert codes[..., 0].max() == 4  # PNG codes come back as integers, not normalised
    colours = preview.provenance_rgb(np.array([[0, 1, 2, 3, 4, 9]]))
    assert [tuple(c) for c in colours[0, :5]] == [rgb for _, rgb in preview.PROVENANCE.values()]
    assert tuple(colours[0, 5]) == (255, 0, 255)


# ------------------------------------------------------------------ against the live stack


def _render(api: str, scene_id: str, size: int, spp: int, method: str = "reference") -> dict[str, Any]:
    body = {"scene_id": scene_id, "method": method, "params": {"spp": spp},
            "camera": {"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0.5, 0], "fov_y_deg": 45,
                       "width": size, "height": size}}
    r = httpx.post(f"{api}/v1/renders?wait=60", json=body, timeout=90)
    assert r.status_code == 200, r.text
    out: dict[str, Any] = r.json()
    assert out["status"] in ("cached", "finished"), out
    return out


def test_every_offered_method_is_accepted(stack: Stack, scene_ids: dict[str, str],
                                          capabilities: dict[str, Any]) -> None:
    names = []
    for m in capabilities["methods"]:
        names += [f"{m['name']}:{k}" for k in m["k"]] if m["k"] else [m["name"]]
    assert "reference" in names
    if capabilities["bakes"]:
        assert {"ldc", "ldc+llf", "ldc+ibrt:0"} <= set(names)
    for name in names:
        body = {"scene_id": scene_ids["teapot_glossy"], "method": name, "params": {"spp": 1},
                "camera": {"type": "perspective", "eye": [0, 1, 4], "look_at": [0, 0.5, 0], "width": 8, "height": 8}}
        r = httpx.post(f"{stack.api_url}/v1/renders", json=body, timeout=30)
        assert r.status_code in (200, 202, 409), (name, r.text)  # 409: an LDC method before its bake
        if r.status_code == 202:
            httpx.post(f"{stack.api_url}/v1/jobs/{r.json()['job']['id']}/cancel", timeout=30)
    bad = {"scene_id": scene_ids["teapot_glossy"], "method": "ldc+ibrt:99"}
    assert httpx.post(f"{stack.api_url}/v1/renders", json=bad, timeout=30).status_code == 422


def test_compare_exposure_and_errors(stack: Stack, scene_ids: dict[str, str]) -> None:
    api = stack.api_url
    sid = scene_ids["teapot_glossy"]
    a = _render(api, sid, 16, 1)["artifact"]["key"]
    b = _render(api, sid, 16, 2)["artifact"]["key"]
    c = _render(api, sid, 8, 1)["artifact"]["key"]
    got = httpx.get(f"{api}/v1/preview/compare", params={"test": a, "ref": b}, timeout=30).json()

    def exr(key: str) -> np.ndarray:
        return preview.read_image(httpx.get(f"{api}/v1/artifacts/{key}/image.exr", timeout=30).content)

    ta, tb = exr(a), exr(b)
    assert got["lrms"] == pytest.approx(engine_lrms(ta, tb), rel=1e-12)
    assert got["n_pixels"] == 256 and got["width"] == 16
    assert httpx.get(f"{api}/v1/preview/compare", params={"test": a, "ref": a}, timeout=30).json()["lrms"] == 0.0
    heat = httpx.get(f"{api}{got['links']['heatmap']}", timeout=30)
    assert heat.status_code == 200 and heat.headers["content-type"] == "image/png"
    assert Image.open(io.BytesIO(heat.content)).size == (16, 16)
    # size mismatch: a 422 naming the field and both sizes
    r = httpx.get(f"{api}/v1/preview/compare", params={"test": c, "ref": a}, timeout=30)
    assert r.status_code == 422
    err = r.json()["errors"][0]
    assert err["field"] == "query.test" and "8 x 8" in err["message"] and "16 x 16" in err["message"]
    # unknown artifact: 404; malformed key: 422 naming the parameter
    r = httpx.get(f"{api}/v1/preview/compare", params={"test": "0" * 64, "ref": a}, timeout=30)
    assert r.status_code == 404
    r = httpx.get(f"{api}/v1/preview/compare", params={"test": "xyz", "ref": a}, timeout=30)
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "query.test"
    # exposure 0 is the stored preview; another exposure re-encodes the linear radiance
    same = httpx.get(f"{api}/v1/preview/artifacts/{a}/image.png", timeout=30).content
    assert same == httpx.get(f"{api}/v1/artifacts/{a}/image.png", timeout=30).content
    bright = np.asarray(Image.open(io.BytesIO(
        httpx.get(f"{api}/v1/preview/artifacts/{a}/image.png", params={"exposure": 1.5}, timeout=30).content)))
    np.testing.assert_array_equal(bright, np.rint(tonemap_srgb(ta, 1.5) * 255).astype(np.uint8))
    r = httpx.get(f"{api}/v1/preview/artifacts/{a}/image.png", params={"exposure": 99}, timeout=30)
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "query.exposure"
    # a reference render has no provenance
    r = httpx.get(f"{api}/v1/preview/artifacts/{a}/provenance.png", timeout=30)
    assert r.status_code == 404 and "provenance" in r.json()["detail"]
