"""The API endpoints only the preview page uses (``service/api/routes/preview.py``): capabilities that
never offer a method the API refuses, and the 8-bit images it makes from ``engine.imageio`` and
``engine.metrics`` (heatmap, exposure, provenance) against what the engine's own writer stores."""

from __future__ import annotations

import io
from typing import Any

import httpx
import numpy as np
import pytest
from PIL import Image

from engine.imageio import decode_image, encode_image, srgb_encode, tonemap_srgb
from engine.metrics import error_heatmap
from engine.metrics import lrms as engine_lrms
from service.api.routes import preview
from service.up import Stack

# Everyday runs skip this file (make test-fast): browser end-to-end: a live stack driven through chromium.
pytestmark = pytest.mark.slow

RNG = np.random.default_rng(7)


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_heatmap_is_the_engine_heatmap_in_8_bit(channels: int) -> None:
    ref = RNG.gamma(2.0, 0.3, size=(17, 23, channels)).astype(np.float32)
    test = (ref * RNG.uniform(0.7, 1.3, size=ref.shape)).astype(np.float32)
    if channels == 4:
        ref[..., 3] = (RNG.uniform(size=ref.shape[:2]) > 0.3).astype(np.float32)
        test[..., 3] = ref[..., 3]
    mask = preview.coverage_mask(ref)
    engine_mask = ref[..., 3] > 0 if channels == 4 else None
    ours = preview.heatmap(test, ref, mask)
    assert ours.dtype == np.uint8 and ours.shape == ref.shape[:2] + (3,)
    # the engine's float32 linear heatmap, re-encoded: equal up to its float32 rounding
    theirs = np.rint(srgb_encode(error_heatmap(test, ref, mask=engine_mask).astype(np.float64)) * 255.0)
    assert np.abs(ours.astype(np.int64) - theirs.astype(np.int64)).max() <= 1
    if channels == 4:
        assert not ours[~mask].any() and ours[mask].min(axis=1).max() > 0


@pytest.mark.parametrize("channels", [1, 3, 4])
@pytest.mark.parametrize("exposure", [-2.0, 0.0, 1.5])
def test_exposure_encoding_is_the_engine_png(channels: int, exposure: float) -> None:
    img = RNG.gamma(1.5, 0.4, size=(9, 11, channels)).astype(np.float32)
    if channels == 4:
        img[..., 3] = RNG.uniform(size=img.shape[:2]) * (RNG.uniform(size=img.shape[:2]) > 0.2)
        img[..., :3] *= img[..., 3:]  # associated alpha, as the engine's images are
    ours = preview.to_srgb8(img, exposure)
    stored = np.asarray(Image.open(io.BytesIO(encode_image("x.png", img, exposure_stops=exposure))))
    np.testing.assert_array_equal(ours, stored.reshape(ours.shape))  # what the worker's writer stores
    if channels == 3:
        np.testing.assert_array_equal(ours, np.rint(tonemap_srgb(img, exposure) * 255.0).astype(np.uint8))


def test_png_roundtrip_and_provenance_codes() -> None:
    rgb = RNG.integers(0, 256, size=(5, 7, 3), dtype=np.uint8)
    back = np.asarray(Image.open(io.BytesIO(preview.png_bytes(rgb))))
    np.testing.assert_array_equal(back, rgb)
    grey = (np.arange(35, dtype=np.uint8).reshape(5, 7, 1) % 5) * 51  # provenance-like codes and larger ones
    codes = decode_image("provenance.png", preview.png_bytes(grey), transfer="linear")[0]
    np.testing.assert_array_equal(np.rint(codes * 255.0).astype(np.uint8), grey)  # codes, not colours
    colours = preview.provenance_rgb(np.array([[0, 1, 2, 3, 4, 9]]))
    assert [tuple(c) for c in colours[0, :5]] == [rgb for _, rgb in preview.PROVENANCE.values()]
    assert tuple(colours[0, 5]) == (255, 0, 255)


def test_capabilities_come_from_the_registry() -> None:
    from engine.methods import METHODS

    with_bakes = preview.capabilities_of(["/v1/renders", "/v1/scenes/{scene_id}/bakes"])
    assert [m.name for m in with_bakes.methods] == [m.name for m in METHODS]
    ibrt = next(m for m in with_bakes.methods if m.k)
    assert ibrt.name == "ldc+ibrt" and ibrt.k == list(range(9)) and ibrt.k_default == 1
    assert ibrt.bake == ["LDC", "LLF"] and ibrt.cost
    ref = with_bakes.methods[0]
    assert ref.name == "reference" and not ref.needs_bake and "spp" in [p.name for p in ref.params]
    without = preview.capabilities_of(["/v1/renders"])
    assert [m.name for m in without.methods] == ["reference"]  # no bake routes: no LDC method


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
        return decode_image("r.exr", httpx.get(f"{api}/v1/artifacts/{key}/image.exr", timeout=30).content)[0]

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


def test_compare_of_relights_walkthroughs_and_ground_truth_names_bad_input(stack: Stack,
                                                                          scene_ids: dict[str, str]) -> None:
    api = stack.api_url
    a = _render(api, scene_ids["teapot_glossy"], 16, 1)["artifact"]["key"]
    q = f"{api}/v1/preview/compare"
    # a render's key is not a relight, a walkthrough or a generation: 404 naming the parameter and the key
    for params, field in (({"test": a, "ref": a, "test_kind": "relight"}, "query.test"),
                          ({"test": a, "ref": a, "test_kind": "walkthrough", "frame": 0}, "query.test"),
                          ({"test": a, "ref": a, "ref_kind": "ground_truth"}, "query.ref")):
        r = httpx.get(q, params=params, timeout=30)
        assert r.status_code == 404 and r.json()["errors"][0]["field"] == field, (params, r.text)
        assert a in r.json()["detail"]
    r = httpx.get(q, params={"test": a, "ref": a, "ref_kind": "ground_truth", "ref_lights": "0;1"}, timeout=30)
    assert r.status_code == 422 and r.json()["errors"][0]["field"] == "query.ref_lights"
    # the reference image of a render at exposure 0 is its stored preview's pixels
    png = httpx.get(f"{api}/v1/preview/reference.png", params={"ref": a}, timeout=30)
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    stored = httpx.get(f"{api}/v1/artifacts/{a}/image.png", timeout=30).content
    np.testing.assert_array_equal(np.asarray(Image.open(io.BytesIO(png.content)).convert("RGB")),
                                  np.asarray(Image.open(io.BytesIO(stored)).convert("RGB")))
