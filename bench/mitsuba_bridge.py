"""The same scene for Mitsuba 3, to cross-check the reference renderer against it.

Two ways to get a Mitsuba scene:

- :func:`runtime_to_mitsuba` converts one of our runtime scenes (after ``load_scene``) plus a
  camera into a Mitsuba scene: every object becomes a PLY mesh holding exactly our world-space
  triangles and per-corner shading normals, every material a BSDF with the same reflectance
  (:func:`bsdf_dict`: ``diffuse``; a pure mirror (only ``kr``) a ``conductor`` with ``material =
  "none"`` and ``specular_reflectance = kr``; ``kd`` + ``kg`` the ``ibr_phong`` plugin registered
  here, our ``kd / pi + kg (g + 2) / (2 pi) cos^g`` exactly), point / directional lights the
  Mitsuba emitters of the same name, a rect light a ``rectangle`` shape with a one-sided
  ``area`` emitter and a black BSDF, the camera a ``perspective`` sensor with ``fov_axis="y"``
  (our fov is vertical) and a box pixel filter.
- :func:`load_cornell_box` / :func:`load_directional_sphere` load Mitsuba's own scene files
  from ``../shared/data`` (the Cornell box ``cbox-rgb.xml`` and the ``floating_sphere`` test
  scene), so our JSON translation of them is checked too, not only the renderer.

Only what both renderers express identically is converted; anything else raises
``ValueError`` rather than producing a scene that differs silently:

- Phong highlights (``ks``): ours reflects the lights only (next-event estimation), a Mitsuba BSDF
  reflects everything; mirrors mixed with other lobes (``kr`` with ``kd``/``kg``);
- emissive materials: our ``emission`` is only *seen* (camera and specular rays) and lights
  nothing, while a Mitsuba area emitter also lights the scene;
- ``ambient`` and ``background``: ours are not an environment light (NEE never samples them);
- two-sided rect lights and orthographic cameras.

A rect light is a real (black, one-sided) rectangle for Mitsuba. For us its emitting side is
seen by camera, mirror and glossy rays as well (they end there), but diffuse path rays and
shadow rays pass through it: give it a black "housing" just behind it (as
``samples/scenes/cornell_mirror_glossy.json`` does) so that diffuse rays find nothing behind
the light in both renderers, and keep it out of the way of other lights' shadow rays.

``ibr_phong`` is a Python plugin, so scenes with glossy materials want a JIT variant
(``llvm_ad_rgb``: the plugin is traced into the kernel once); in ``scalar_rgb`` it runs but every
BSDF call goes through Python. :func:`mitsuba` points Dr.Jit at an LLVM library
(``$DRJIT_LIBLLVM_PATH``, else Debian's ``libLLVM.so.19.1``) before selecting an LLVM variant.

Integrators: ``direct`` is Mitsuba's ``direct`` (emitter + BSDF sampling with MIS); ``path``
with ``bounces`` B is Mitsuba's ``path`` with ``max_depth = B + 2`` (depth 1 is the emitter
seen by the camera, depth 2 direct light, every further depth one diffuse bounce), which is
our ``indirect_bounces = B`` (next-event estimation at the camera hit and at B path vertices).

Orientation: Mitsuba's ``look_at`` frame has camera-space +x pointing to the image's *left*
and its film x flipped back, so image column 0 is on the side of ``cross(up, forward)``, the
same as our camera (``right = cross(forward, up)``, pixel (0, 0) top-left); ``mi.render``
returns rows top to bottom. ``tests/engine/test_mitsuba_crosscheck.py`` checks this on an
asymmetric scene (the mirrored image must be far worse than the unmirrored one).
"""

from __future__ import annotations

import glob
import math
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from engine.scene import CameraParams, RuntimeScene

MITSUBA_VARIANT = "scalar_rgb"
REPO_ROOT = Path(__file__).resolve().parents[1]

CBOX_XML = Path("cornell-box-mitsuba") / "cbox-rgb.xml"
DIRECTIONAL_XML = Path("mitsuba-ref-directional-sphere") / "test_directional_direct.xml"
DIRECTIONAL_REF = Path("mitsuba-ref-directional-sphere") / "refs" / "test_directional_ref_rgb.exr"


def shared_data_dir() -> Path | None:
    """``$IBR_SHARED_DATA`` if set, else ``../shared/data`` beside the repository; None if absent."""
    env = os.environ.get("IBR_SHARED_DATA")
    p = Path(env) if env else REPO_ROOT.parent / "shared" / "data"
    return p if p.is_dir() else None


def require_shared(rel: Path) -> Path:
    root = shared_data_dir()
    if root is None or not (root / rel).is_file():
        raise FileNotFoundError(f"{rel} not found under the shared data directory ({root}); "
                                "set IBR_SHARED_DATA to the folder that holds it")
    return root / rel


LLVM_VARIANT = "llvm_ad_rgb"
# Dr.Jit's LLVM backend needs a recent libLLVM; Debian 12's libllvm19 package puts it here
LIBLLVM_CANDIDATES = ("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1", "/usr/lib/llvm-19/lib/libLLVM.so.1")
_registered: set[str] = set()


def mitsuba(variant: str = MITSUBA_VARIANT):
    """The ``mitsuba`` module with ``variant`` selected (scalar_rgb needs no LLVM) and the
    ``ibr_phong`` BSDF registered in it."""
    if variant.startswith("llvm") and not os.environ.get("DRJIT_LIBLLVM_PATH"):
        found = [p for p in LIBLLVM_CANDIDATES if os.path.isfile(p)]
        found += sorted(glob.glob("/usr/lib/llvm-1[6-9]/lib/libLLVM*.so*"))
        if not found:
            raise RuntimeError(f"variant {variant} needs libLLVM (apt-get install libllvm19, or set "
                               "DRJIT_LIBLLVM_PATH)")
        os.environ["DRJIT_LIBLLVM_PATH"] = found[0]
    import mitsuba as mi

    if mi.variant() != variant:
        mi.set_variant(variant)
    if variant not in _registered:
        _register_phong(mi)
        _registered.add(variant)
    return mi


def _register_phong(mi) -> None:
    """Register ``ibr_phong``: our ``kd / pi + kg (g + 2) / (2 pi) max(0, cos a)^g`` with a the
    angle between the outgoing direction and the mirror direction of the incoming one (both in
    the shading frame), zero below the horizon on either side; properties ``kd_r`` ... ``kg_b``
    and ``g``. Sampled by picking the diffuse (cosine) or the glossy (``cos^g`` around the mirror
    direction) lobe with probability proportional to its mean albedo; ``pdf`` is the mixture."""
    import drjit as dr

    class IbrPhong(mi.BSDF):
        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.kd = [float(props["kd_" + c]) for c in "rgb"]
            self.kg = [float(props["kg_" + c]) for c in "rgb"]
            self.g = float(props["g"])
            ad, ag = sum(self.kd) / 3.0, sum(self.kg) / 3.0
            self.pg = ag / (ad + ag) if ad + ag > 0 else 0.0
            diffuse = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
            glossy = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
            self.m_components = [diffuse, glossy]
            self.m_flags = diffuse | glossy

        def _value_pdf(self, si, wo, active):
            ci = mi.Frame3f.cos_theta(si.wi)
            co = mi.Frame3f.cos_theta(wo)
            ok = active & (ci > 0) & (co > 0)
            ca = dr.dot(wo, mi.Vector3f(-si.wi.x, -si.wi.y, si.wi.z))
            lobe = dr.select(ca > 0, dr.power(dr.maximum(ca, 1e-30), self.g), 0.0)
            f = (mi.Color3f(self.kd) * dr.inv_pi
                 + mi.Color3f(self.kg) * ((self.g + 2.0) * 0.5 * dr.inv_pi * lobe))
            pdf = (1.0 - self.pg) * co * dr.inv_pi + self.pg * (self.g + 1.0) * 0.5 * dr.inv_pi * lobe
            return dr.select(ok, f * co, 0.0), dr.select(ok, pdf, 0.0)

        def eval(self, ctx, si, wo, active=True):
            return self._value_pdf(si, wo, active)[0]

        def pdf(self, ctx, si, wo, active=True):
            return self._value_pdf(si, wo, active)[1]

        def eval_pdf(self, ctx, si, wo, active=True):
            return self._value_pdf(si, wo, active)

        def sample(self, ctx, si, sample1, sample2, active=True):
            glossy = sample1 < self.pg
            ca = dr.power(dr.maximum(sample2.x, 1e-30), 1.0 / (self.g + 1.0))
            sa = dr.safe_sqrt(1.0 - ca * ca)
            phi = 2.0 * dr.pi * sample2.y
            around = mi.Frame3f(mi.Vector3f(-si.wi.x, -si.wi.y, si.wi.z))
            wo_g = around.to_world(mi.Vector3f(sa * dr.cos(phi), sa * dr.sin(phi), ca))
            wo = dr.select(glossy, wo_g, mi.warp.square_to_cosine_hemisphere(sample2))
            value, pdf = self._value_pdf(si, wo, active)
            bs = mi.BSDFSample3f()
            bs.wo = wo
            bs.pdf = pdf
            bs.eta = 1.0
            bs.sampled_type = dr.select(glossy, mi.UInt32(+mi.BSDFFlags.GlossyReflection),
                                        mi.UInt32(+mi.BSDFFlags.DiffuseReflection))
            bs.sampled_component = dr.select(glossy, mi.UInt32(1), mi.UInt32(0))
            return bs, dr.select(active & (pdf > 0), value / dr.maximum(pdf, 1e-30), 0.0)

        def traverse(self, callback):
            pass

        def parameters_changed(self, keys):
            pass

        def to_string(self):
            return f"IbrPhong[kd={self.kd}, kg={self.kg}, g={self.g}]"

    mi.register_bsdf("ibr_phong", lambda props: IbrPhong(props))


# ============================================================================ conversion


def integrator_dict(kind: str, bounces: int = 0) -> dict:
    """Mitsuba integrator matching our ``indirect_samples = 0`` (``direct``) or
    ``indirect_bounces = bounces`` (``path``)."""
    if kind == "direct":
        return {"type": "direct"}
    if kind == "path":
        if bounces < 1:
            raise ValueError("path needs bounces >= 1")
        return {"type": "path", "max_depth": int(bounces) + 2}
    raise ValueError(f"unknown integrator kind {kind!r}")


def sensor_dict(camera: CameraParams, spp: int = 16, sampler: str = "independent",
                variant: str = MITSUBA_VARIANT) -> dict:
    """Perspective sensor with our camera's eye, target, up and *vertical* fov, box filter."""
    mi = mitsuba(variant)
    if camera.kind != "perspective":
        raise ValueError("only perspective cameras are converted")
    return {
        "type": "perspective",
        "fov_axis": "y",
        "fov": float(camera.fov_y_deg),
        "near_clip": 1e-4 * _camera_scale(camera),
        "far_clip": 1e6 * _camera_scale(camera),
        "to_world": mi.ScalarTransform4f().look_at(origin=list(map(float, camera.eye)),
                                                   target=list(map(float, camera.look_at)),
                                                   up=list(map(float, camera.up))),
        "sampler": {"type": sampler, "sample_count": int(spp)},
        "film": {"type": "hdrfilm", "width": int(camera.width), "height": int(camera.height),
                 "rfilter": {"type": "box"}, "pixel_format": "rgb"},
    }


def _camera_scale(camera: CameraParams) -> float:
    return float(np.linalg.norm(np.subtract(camera.look_at, camera.eye)))


def write_ply(path: Path, tri_p: np.ndarray, tri_n: np.ndarray) -> None:
    """Binary PLY with 3 unshared vertices per triangle (exact corners and corner normals)."""
    nt = tri_p.shape[0]
    vert = np.empty(nt * 3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"),
                                   ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")])
    p = tri_p.reshape(-1, 3)
    n = tri_n.reshape(-1, 3)
    for k, name in enumerate("xyz"):
        vert[name] = p[:, k]
        vert["n" + name] = n[:, k]
    face = np.empty(nt, dtype=[("n", "u1"), ("i", "<i4", (3,))])
    face["n"] = 3
    face["i"] = np.arange(nt * 3, dtype=np.int32).reshape(nt, 3)
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {nt * 3}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property float nx\nproperty float ny\nproperty float nz\n"
        f"element face {nt}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(vert.tobytes())
        fh.write(face.tobytes())


def _rgb(v) -> dict:
    return {"type": "rgb", "value": [float(x) for x in v]}


def bsdf_dict(kd, ks, kr, kg, gloss_exponent: float) -> dict:
    """The Mitsuba BSDF of one of our materials; ValueError when there is none that is identical."""
    kd, ks, kr, kg = (np.asarray(x, dtype=np.float64) for x in (kd, ks, kr, kg))
    if np.any(ks > 0):
        raise ValueError("is not diffuse, mirror or glossy: its Phong highlight (ks) reflects the lights only, "
                         "no Mitsuba BSDF does that")
    if np.any(kr > 0):
        if np.any(kd > 0) or np.any(kg > 0):
            raise ValueError("is not diffuse, mirror or glossy: a mirror (kr) mixed with kd / kg")
        return {"type": "conductor", "material": "none", "specular_reflectance": _rgb(kr)}
    if np.any(kg > 0):
        if not math.isfinite(gloss_exponent) or gloss_exponent < 1:
            raise ValueError("glossy exponent must be >= 1")
        d = {"type": "ibr_phong", "g": float(gloss_exponent)}
        for k, c in enumerate("rgb"):
            d["kd_" + c] = float(kd[k])
            d["kg_" + c] = float(kg[k])
        return d
    return {"type": "diffuse", "reflectance": _rgb(kd)}


def check_convertible(scene: RuntimeScene, camera: CameraParams) -> None:
    """Raise ValueError naming the first feature with no identical Mitsuba equivalent."""
    mt = scene.materials
    for i, name in enumerate(mt.names):
        try:
            bsdf_dict(mt.kd[i], mt.ks[i], mt.kr[i], mt.kg[i], float(mt.gloss_exponent[i]))
        except ValueError as e:
            raise ValueError(f"material {name!r} {e}") from None
        used = np.any(scene.tri_material == i)
        if used and np.any(mt.emission[i] > 0):
            raise ValueError(f"material {name!r} is emissive: Mitsuba's area emitter would also light "
                             "the scene, ours only shows it; use the Mitsuba-native scene file")
    if np.any(scene.ambient > 0):
        raise ValueError("ambient light has no Mitsuba equivalent")
    if np.any(scene.background > 0):
        raise ValueError("a non-black background has no Mitsuba equivalent (it is not sampled by NEE)")
    if np.any(scene.lights.rect_two_sided):
        raise ValueError("two-sided rect lights are not converted")
    if camera.kind != "perspective":
        raise ValueError("only perspective cameras are converted")


def runtime_to_mitsuba_dict(scene: RuntimeScene, camera: CameraParams, workdir: str | Path,
                            spp: int = 16, sampler: str = "independent", variant: str = MITSUBA_VARIANT) -> dict:
    """Mitsuba scene dict for ``scene`` seen by ``camera``; meshes are written to ``workdir``
    (which must outlive the ``mi.load_dict`` call)."""
    mi = mitsuba(variant)
    check_convertible(scene, camera)
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    d: dict = {"type": "scene", "integrator": integrator_dict("direct"),
               "sensor": sensor_dict(camera, spp, sampler, variant)}
    mt = scene.materials
    for i in range(mt.count):
        d[f"bsdf_{i}"] = {**bsdf_dict(mt.kd[i], mt.ks[i], mt.kr[i], mt.kg[i], float(mt.gloss_exponent[i])),
                          "id": f"bsdf_{i}"}
    for oid in range(len(scene.object_names)):
        sel = scene.tri_object == oid
        if not np.any(sel):
            continue
        mats = np.unique(scene.tri_material[sel])
        for m in mats:  # one object has one material; split defensively anyway
            s = sel & (scene.tri_material == m)
            path = workdir / f"obj{oid}_m{int(m)}.ply"
            write_ply(path, scene.tri_p[s], scene.tri_n[s])
            d[f"shape_{oid}_{int(m)}"] = {"type": "ply", "filename": str(path),
                                          "bsdf": {"type": "ref", "id": f"bsdf_{int(m)}"}}
    lt = scene.lights
    for j in range(lt.n_point):
        d[f"point_{j}"] = {"type": "point", "position": [float(x) for x in lt.point_position[j]],
                           "intensity": _rgb(lt.point_intensity[j])}
    for j in range(lt.n_directional):
        d[f"directional_{j}"] = {"type": "directional",
                                 "direction": [float(x) for x in lt.dir_direction[j]],
                                 "irradiance": _rgb(lt.dir_irradiance[j])}
    for j in range(lt.n_rect):
        u, v, c = lt.rect_edge_u[j], lt.rect_edge_v[j], lt.rect_corner[j]
        n = np.cross(u, v)
        n /= np.linalg.norm(n)
        m = np.eye(4)
        # Mitsuba's rectangle is [-1, 1]^2 in local xy with normal +z: x -> u/2, y -> v/2,
        # z -> the unit normal cross(u, v) (positive determinant, so it emits toward it)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = 0.5 * u, 0.5 * v, n, c + 0.5 * (u + v)
        d[f"rect_{j}"] = {
            "type": "rectangle",
            "to_world": mi.ScalarTransform4f(m.tolist()),
            "bsdf": {"type": "diffuse", "reflectance": _rgb((0.0, 0.0, 0.0))},
            "emitter": {"type": "area", "radiance": _rgb(lt.rect_radiance[j])},
        }
    return d


def runtime_to_mitsuba(scene: RuntimeScene, camera: CameraParams, workdir: str | Path, spp: int = 16,
                       sampler: str = "independent", variant: str = MITSUBA_VARIANT):
    """``mi.Scene`` for ``scene`` seen by ``camera`` (see :func:`runtime_to_mitsuba_dict`), loaded
    in ``variant``."""
    return mitsuba(variant).load_dict(runtime_to_mitsuba_dict(scene, camera, workdir, spp, sampler, variant))


def resampled_sensor(scene, sampler: str = "multijitter", spp: int = 16, variant: str = MITSUBA_VARIANT):
    """A copy of ``scene``'s first sensor (same fov, frame, film size, box filter) with another
    sampler, to pass as ``mi.render(..., sensor=...)``.

    Mitsuba's native scene files use the ``independent`` sampler; a stratified one converges
    much faster on pixel edges (anti-aliasing) and area-light penumbrae, and both are unbiased.
    Refuses sensors this copy would not reproduce (non-perspective, off-centre principal
    point, a pixel filter other than box). ``variant``: the one ``scene`` was loaded in."""
    mi = mitsuba(variant)
    s = scene.sensors()[0]
    p = mi.traverse(s)

    def scalar(x) -> float:  # a Python float in scalar variants, a 1-wide Dr.Jit array in JIT ones
        return float(np.asarray(x, dtype=np.float64).ravel()[0])

    if "x_fov" not in p or abs(scalar(p["principal_point_offset_x"])) + abs(scalar(p["principal_point_offset_y"])) > 0:
        raise ValueError(f"cannot copy sensor {s}")
    film = s.film()
    if "BoxFilter" not in str(film.rfilter()):
        raise ValueError(f"sensor filter is {film.rfilter()}, expected box")
    size = film.size()
    m = np.array(s.world_transform().matrix, dtype=np.float64).reshape(4, 4)
    return mi.load_dict({
        "type": "perspective", "fov_axis": "x", "fov": scalar(p["x_fov"]),
        "near_clip": scalar(p["near_clip"]), "far_clip": scalar(p["far_clip"]),
        "to_world": mi.ScalarTransform4f(m.tolist()),
        "sampler": {"type": sampler, "sample_count": int(spp)},
        "film": {"type": "hdrfilm", "width": int(size[0]), "height": int(size[1]),
                 "rfilter": {"type": "box"}, "pixel_format": "rgb"},
    })


# ============================================================================ native scenes


def load_cornell_box(res: int = 256, spp: int = 16):
    """Mitsuba's own ``cbox-rgb.xml`` (box filter, fov 39.3077 on the smaller axis = vertical
    for a square film) at ``res`` x ``res``."""
    path = require_shared(CBOX_XML)
    return mitsuba().load_file(str(path), res=int(res), spp=int(spp))


def load_directional_sphere(spp: int = 16):
    """Mitsuba's ``floating_sphere`` test scene (48 x 48, box filter).

    Its sensor sets no ``fov``, so Mitsuba derives it from the default 50 mm focal length on a
    film with the 35 mm diagonal: ``x_fov = 2 atan(sqrt(36^2 + 24^2) / sqrt(2) / 100)`` =
    34.0221 degrees for the square film (not 45)."""
    path = require_shared(DIRECTIONAL_XML)
    text = path.read_text()
    # The file points at Mitsuba's repository layout (<path value="../../../common"/>, which
    # Mitsuba refuses when the folder is missing); the shared copy keeps the two meshes in
    # meshes/ beside it, so drop the search path and make the mesh paths absolute.
    text = re.sub(r"<path\s+value=\"[^\"]*\"\s*/>", "", text)
    text = text.replace('value="meshes/', f'value="{(path.parent / "meshes").as_posix()}/')
    return mitsuba().load_string(text, spp=int(spp), integrator="direct")


def read_directional_reference() -> np.ndarray:
    """Mitsuba's 32k-spp ``direct`` reference of the floating sphere, (48, 48, 3) float32.

    The file is the *mean* image already (3 channels R, G, B; the ``moment`` integrator's
    second moments went to the separate ``*_var.exr``); anything else is an error."""
    from engine.imageio import image_info, read_image

    path = require_shared(DIRECTIONAL_REF)
    info = image_info(path)
    if info["channel_names"][:3] != ["R", "G", "B"]:
        raise ValueError(f"{path}: unexpected channels {info['channel_names']}")
    px, _ = read_image(path)
    return np.ascontiguousarray(px[..., :3], dtype=np.float32)


# ============================================================================ rendering


@dataclass
class MitsubaRender:
    radiance: np.ndarray  # (h, w, 3) float32, row 0 at the top
    seconds: float
    spp: int
    integrator: dict


def render(scene, kind: str, bounces: int = 0, spp: int = 256, seed: int = 0, sensor=None,
           variant: str = MITSUBA_VARIANT) -> MitsubaRender:
    """Render a Mitsuba scene (loaded in ``variant``) with the integrator matching ``kind`` /
    ``bounces`` (optionally from another ``sensor``, e.g. :func:`resampled_sensor`)."""
    mi = mitsuba(variant)
    integ = integrator_dict(kind, bounces)
    t0 = time.perf_counter()
    img = mi.render(scene, sensor=0 if sensor is None else sensor, integrator=mi.load_dict(integ),
                    spp=int(spp), seed=int(seed))
    arr = np.array(img, dtype=np.float32)[..., :3]
    return MitsubaRender(np.ascontiguousarray(arr), time.perf_counter() - t0, int(spp), integ)
