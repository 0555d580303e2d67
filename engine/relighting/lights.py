"""The relighting's light specs and their expansion into the relight kernel's lights.

Owns the four light kinds a relight accepts (:class:`PointLight`, :class:`DirectionalLight`,
:class:`RectLight`, :class:`EnvironmentLight`), :func:`light_from_dict` (their ``{"type": ...}``
form, the same field names as the scene format's lights, ``api_schemas.scene``), and their expansion:
:func:`expand_lights` turns a list of specs into the kernel's arrays (kind, position or direction,
intensity or irradiance, emitter normal per expanded light): a rect light becomes ``samples`` oriented
point samples, an environment map ``n_lights`` directional lights (:func:`environment_to_directional`).

How they relate to ``engine.scene.LightTable``: the renderers (reference, LDC) shade with a
``LightTable`` (point, directional and rect lights as arrays; rect lights sampled per shading point
by ``engine.lights.rect_light_sample``); the relight kernel interpolates a dataset per expanded light. The
same light described to both is built once, as a spec here: :func:`light_table` makes the
``LightTable`` of a list of specs (environment maps as the same directional lights the relighting
uses), so a dataset's ground truth is rendered under exactly the lights a relight uses. The service
converts its schema lights to these specs in one place, ``workers.scene_loader``.

No numba: the specs and their expansion are numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from engine.errors import InvalidInputError
from engine.scene import LightTable

# light kinds of the expanded lights, as the relight kernel reads them
K_POINT = 0  # isotropic point light: lp = position, lint = intensity
K_DIRECTIONAL = 1  # distant light: lp = unit direction toward the light, lint = irradiance
K_ORIENTED = 2  # one-sided area sample: lp = position, lint = intensity along lnorm (x cos theta)
K_TWO_SIDED = 3  # two-sided area sample: as K_ORIENTED, |cos theta|


def _vec3(name, v, *, positive=False, nonzero=False) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    if a.ndim == 0:
        a = np.full(3, float(a))
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise InvalidInputError(f"{name}: expected 3 finite numbers, got {v!r}")
    if positive and np.any(a < 0):
        raise InvalidInputError(f"{name}: must be >= 0")
    if nonzero and np.linalg.norm(a) == 0:
        raise InvalidInputError(f"{name}: must be non-zero")
    return a


@dataclass(frozen=True)
class PointLight:
    """Isotropic point light: position (3,), intensity (3,) W/sr (or a scalar)."""

    position: tuple
    intensity: tuple = (1.0, 1.0, 1.0)


@dataclass(frozen=True)
class DirectionalLight:
    """Distant light: ``direction`` (3,) the way the light travels (as in the scene format),
    ``irradiance`` (3,) on a surface facing it."""

    direction: tuple
    irradiance: tuple = (1.0, 1.0, 1.0)


@dataclass(frozen=True)
class RectLight:
    """One-sided rectangle ``corner + a edge_u + b edge_v``, (a, b) in [0, 1]^2, emitting radiance
    ``radiance`` toward ``cross(edge_u, edge_v)`` (both ways if ``two_sided``); sampled with
    ``samples`` stratified, seeded points, each a point light of intensity L A / N cos(theta)."""

    corner: tuple
    edge_u: tuple
    edge_v: tuple
    radiance: tuple = (1.0, 1.0, 1.0)
    two_sided: bool = False
    samples: int = 16
    seed: int = 0


@dataclass(frozen=True)
class EnvironmentLight:
    """Equirectangular radiance map (H, W, 3) (row 0 = +y, the zenith; column u at azimuth
    phi = 2 pi (u + 0.5) / W, direction (sin th cos phi, cos th, sin th sin phi)), turned into
    ``n_lights`` directional lights: ``method="downsample"`` (blocks of equal angular size,
    energy-weighted direction; deterministic) or ``"importance"`` (pixels drawn with probability
    ~ luminance x solid angle, seeded)."""

    image: np.ndarray
    n_lights: int = 64
    method: str = "downsample"
    seed: int = 0
    scale: float = 1.0


LIGHT_TYPES = {"point": PointLight, "directional": DirectionalLight, "rect": RectLight,
               "environment": EnvironmentLight}


def light_from_dict(d: dict):
    """``{"type": "point", "position": [...], ...}`` -> light spec (unknown fields are errors)."""
    d = dict(d)
    kind = d.pop("type", None)
    cls = LIGHT_TYPES.get(kind)
    if cls is None:
        raise InvalidInputError(f"light type must be one of {sorted(LIGHT_TYPES)}, got {kind!r}")
    try:
        return cls(**d)
    except TypeError as e:
        raise InvalidInputError(f"{kind} light: {e}") from None


def environment_to_directional(env: EnvironmentLight) -> tuple[np.ndarray, np.ndarray]:
    """An environment map as directional lights: unit directions TOWARD the lights (n, 3) and their
    irradiance (n, 3) (see :class:`EnvironmentLight` for the two methods)."""
    img = np.asarray(env.image, dtype=np.float64)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 1 or img.shape[1] < 1:
        raise InvalidInputError(f"environment image: expected (H, W, 3), got {img.shape}")
    if not np.all(np.isfinite(img)) or np.any(img < 0):
        raise InvalidInputError("environment image: values must be finite and >= 0")
    n = int(env.n_lights)
    if n < 1:
        raise InvalidInputError("environment n_lights must be >= 1")
    hh, ww = img.shape[:2]
    th = np.pi * (np.arange(hh) + 0.5) / hh
    ph = 2 * np.pi * (np.arange(ww) + 0.5) / ww
    st = np.sin(th)
    dirs = np.stack([st[:, None] * np.cos(ph)[None, :], np.repeat(np.cos(th)[:, None], ww, 1),
                     st[:, None] * np.sin(ph)[None, :]], axis=-1)  # (H, W, 3)
    domega = (np.pi / hh) * (2 * np.pi / ww) * st  # (H,)
    e_pix = img * domega[:, None, None] * env.scale  # irradiance contribution of each pixel
    if env.method == "downsample":
        n_lat = max(1, int(round(math.sqrt(n / 2.0))))
        n_lon = max(1, n // n_lat)
        rows = np.array_split(np.arange(hh), n_lat)
        cols = np.array_split(np.arange(ww), n_lon)
        out_d, out_e = [], []
        for r in rows:
            for c in cols:
                if r.size == 0 or c.size == 0:
                    continue
                e = e_pix[np.ix_(r, c)].reshape(-1, 3)
                dd = dirs[np.ix_(r, c)].reshape(-1, 3)
                wgt = e.sum(axis=1)
                tot = e.sum(axis=0)
                if wgt.sum() <= 0:
                    continue
                v = (dd * wgt[:, None]).sum(axis=0)
                nv = np.linalg.norm(v)
                v = v / nv if nv > 0 else dd[len(dd) // 2]
                out_d.append(v)
                out_e.append(tot)
        return np.array(out_d).reshape(-1, 3), np.array(out_e).reshape(-1, 3)
    if env.method == "importance":
        lum = (0.2126 * e_pix[..., 0] + 0.7152 * e_pix[..., 1] + 0.0722 * e_pix[..., 2]).ravel()
        if lum.sum() <= 0:
            return np.zeros((0, 3)), np.zeros((0, 3))
        p = lum / lum.sum()
        rng = np.random.default_rng(env.seed)
        idx = rng.choice(p.size, size=n, p=p)
        e = e_pix.reshape(-1, 3)[idx] / (p[idx, None] * n)
        return dirs.reshape(-1, 3)[idx], e
    raise InvalidInputError(f"environment method must be 'downsample' or 'importance', got {env.method!r}")


def _rect_samples(r: RectLight):
    """A rect light's stratified, seeded samples: positions, intensities and the emitter normal (each (samples, 3))."""
    c = _vec3("rect corner", r.corner)
    eu, ev = _vec3("rect edge_u", r.edge_u, nonzero=True), _vec3("rect edge_v", r.edge_v, nonzero=True)
    rad = _vec3("rect radiance", r.radiance, positive=True)
    ns = int(r.samples)
    if ns < 1:
        raise InvalidInputError("rect samples must be >= 1")
    nrm = np.cross(eu, ev)
    area = float(np.linalg.norm(nrm))
    if area == 0:
        raise InvalidInputError("rect: edge_u and edge_v are parallel")
    nrm /= area
    gx = int(math.ceil(math.sqrt(ns)))
    gy = int(math.ceil(ns / gx))
    j = np.arange(ns)
    jit = np.random.default_rng(r.seed).random((ns, 2))
    a = ((j % gx) + jit[:, 0]) / gx
    b = ((j // gx) + jit[:, 1]) / gy
    pos = c + a[:, None] * eu + b[:, None] * ev
    inten = np.broadcast_to(rad * area / ns, (ns, 3))  # I(theta) = L A/N cos(theta)
    return pos, inten, np.broadcast_to(nrm, (ns, 3))


def expand_lights(lights) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A light spec, its dict, or a list of them -> the kernel's (kinds (M,) int64, lp (M, 3), lint (M, 3),
    lnorm (M, 3)) (see the ``K_*`` kinds; directional lights as the unit direction toward the light)."""
    kinds, lp, li, ln = [], [], [], []
    if isinstance(lights, (PointLight, DirectionalLight, RectLight, EnvironmentLight, dict)):
        lights = [lights]
    for idx, spec in enumerate(lights):
        if isinstance(spec, dict):
            spec = light_from_dict(spec)
        if isinstance(spec, PointLight):
            pos = _vec3(f"lights[{idx}].position", spec.position)
            if np.max(np.abs(pos)) > 1e100:  # |l - P|^2 would overflow; the limit is a directional light
                raise InvalidInputError(f"lights[{idx}].position: farther than 1e100; use a directional light")
            kinds.append([K_POINT])
            lp.append(pos[None])
            li.append(_vec3(f"lights[{idx}].intensity", spec.intensity, positive=True)[None])
            ln.append(np.zeros((1, 3)))
        elif isinstance(spec, DirectionalLight):
            d = _vec3(f"lights[{idx}].direction", spec.direction, nonzero=True)
            kinds.append([K_DIRECTIONAL])
            lp.append((-d / np.linalg.norm(d))[None])  # the kernel wants the direction toward the light
            li.append(_vec3(f"lights[{idx}].irradiance", spec.irradiance, positive=True)[None])
            ln.append(np.zeros((1, 3)))
        elif isinstance(spec, RectLight):
            p, i, n = _rect_samples(spec)
            kinds.append([K_TWO_SIDED if spec.two_sided else K_ORIENTED] * p.shape[0])
            lp.append(p)
            li.append(i)
            ln.append(n)
        elif isinstance(spec, EnvironmentLight):
            d, e = environment_to_directional(spec)
            kinds.append([K_DIRECTIONAL] * d.shape[0])
            lp.append(d)
            li.append(e)
            ln.append(np.zeros_like(d))
        else:
            raise InvalidInputError(f"lights[{idx}]: unsupported light spec {type(spec).__name__}")
    if not kinds:
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3))
    return (np.concatenate([np.asarray(k, np.int64) for k in kinds]), np.ascontiguousarray(np.concatenate(lp)),
            np.ascontiguousarray(np.concatenate(li)), np.ascontiguousarray(np.concatenate(ln)))


def light_table(lights) -> LightTable:
    """The renderers' ``LightTable`` of relighting light specs (or their dicts, or one spec): point,
    directional and rect lights one for one, an environment map as the directional lights
    :func:`environment_to_directional` gives (the ones a relight uses)."""
    if isinstance(lights, (PointLight, DirectionalLight, RectLight, EnvironmentLight, dict)):
        lights = [lights]
    rows: list[dict] = []
    for i, spec in enumerate(lights):
        if isinstance(spec, dict):
            spec = light_from_dict(spec)
        if isinstance(spec, PointLight):
            rows.append(dict(type="point", position=_vec3(f"lights[{i}].position", spec.position),
                             intensity=np.broadcast_to(np.asarray(spec.intensity, np.float64), (3,))))
        elif isinstance(spec, DirectionalLight):
            rows.append(dict(type="directional", direction=_vec3(f"lights[{i}].direction", spec.direction),
                             irradiance=np.broadcast_to(np.asarray(spec.irradiance, np.float64), (3,))))
        elif isinstance(spec, RectLight):
            rows.append(dict(type="rect", corner=spec.corner, edge_u=spec.edge_u, edge_v=spec.edge_v,
                             radiance=np.broadcast_to(np.asarray(spec.radiance, np.float64), (3,)),
                             two_sided=bool(spec.two_sided)))
        elif isinstance(spec, EnvironmentLight):
            d, e = environment_to_directional(spec)
            rows += [dict(type="directional", direction=-d[j], irradiance=e[j]) for j in range(d.shape[0])]
        else:
            raise InvalidInputError(f"lights[{i}]: unsupported light spec {type(spec).__name__}")
    return LightTable.from_rows(rows)
