"""Effect analysis: which parts of the LDC/LLF pipeline a scene actually needs.

``analyze(scene)`` is cheap (numpy over the triangle soup) and conservative:

- material kind (the most demanding term it has): ``mirror`` (kr > 0), ``glossy``
  (kg > 0), ``highlight`` (ks > 0 with shininess > 0), else ``diffuse``;
- ``needs_view_pass`` when any material is not diffuse; ``needs_llf`` when any is glossy
  or mirror (highlights alone need only the visibility bits);
- a light is OCCLUSION-FREE only when provably nothing can block it: the scene is a
  single object whose mesh is closed (every edge shared by exactly two triangles with
  opposite orientation), outward oriented and convex, and the light (every corner of a
  rect light) lies strictly outside one of its face planes (directional lights always
  do). Then, from the outer side of any surface point, a light in front of the tangent
  plane is visible (a convex body lies behind each of its face planes), and from the
  inner side it is not. Everything else is occludable (also a single object of
  more than ``CONVEX_TEST_MAX_TRIANGLES`` triangles: the test is O(V x F)). A scene without occludable lights
  stores no visibility bits and casts no shadow rays;
- ``closed_objects``: per object, closed and outward oriented; the warp culls the
  inner side of those (back-face culling), other surfaces are two-sided;
- emission / ambient present; ``animated`` is always False (the runtime scene has no
  animation yet; the field is here so plans keep their shape when it does).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from engine.scene import RuntimeScene

KINDS = ("diffuse", "highlight", "glossy", "mirror")
# the convexity test is O(vertices x faces); above this many triangles we don't try (occludable)
CONVEX_TEST_MAX_TRIANGLES = 20000


@dataclass(frozen=True)
class EffectPlan:
    material_kinds: tuple[str, ...]
    needs_view_pass: bool
    needs_llf: bool
    occludable_lights: tuple[bool, ...]
    closed_objects: tuple[bool, ...]
    convex_single_object: bool
    has_emission: bool
    has_ambient: bool
    animated: bool = False
    indirect_skip: str = ""
    """Why indirect light cannot reach any diffuse surface (the bake skips its pass), or "" when it can."""

    @property
    def any_occludable(self) -> bool:
        return any(self.occludable_lights)

    def to_dict(self) -> dict:
        return {"material_kinds": list(self.material_kinds), "needs_view_pass": self.needs_view_pass,
                "needs_llf": self.needs_llf, "occludable_lights": list(self.occludable_lights),
                "any_occludable": self.any_occludable, "closed_objects": list(self.closed_objects),
                "convex_single_object": self.convex_single_object, "has_emission": self.has_emission,
                "has_ambient": self.has_ambient, "animated": self.animated, "indirect_skip": self.indirect_skip}


def plan_from_dict(d: dict) -> EffectPlan:
    """Inverse of ``EffectPlan.to_dict()`` (e.g. the plan stored with an LDC bake)."""
    try:
        return EffectPlan(material_kinds=tuple(d["material_kinds"]), needs_view_pass=bool(d["needs_view_pass"]),
                          needs_llf=bool(d["needs_llf"]),
                          occludable_lights=tuple(bool(x) for x in d["occludable_lights"]),
                          closed_objects=tuple(bool(x) for x in d["closed_objects"]),
                          convex_single_object=bool(d["convex_single_object"]), has_emission=bool(d["has_emission"]),
                          has_ambient=bool(d["has_ambient"]), animated=bool(d.get("animated", False)),
                          indirect_skip=str(d.get("indirect_skip", "")))
    except (KeyError, TypeError) as e:
        from engine.errors import InvalidInputError

        raise InvalidInputError(f"effect plan dict is malformed: {e}") from None


def material_kind(kd, ks, shininess, kr, kg) -> str:
    if np.any(np.asarray(kr) > 0):
        return "mirror"
    if np.any(np.asarray(kg) > 0):
        return "glossy"
    if np.any(np.asarray(ks) > 0) and shininess > 0:
        return "highlight"
    return "diffuse"


def _indirect_skip(scene: RuntimeScene, used_mats: list[int], convex: bool, occludable: list[bool]) -> str:
    """Why no diffuse surface can receive indirect light, or "" when one can. Light reaches a
    surface indirectly only from a light or the background (emission and ambient light nothing),
    via another surface or the background itself."""
    mt = scene.materials
    black_background = not np.any(np.asarray(scene.background) > 0)
    if not used_mats or not np.any(mt.kd[used_mats] > 0):
        return "no surface is diffuse (kd = 0 everywhere): nothing receives indirect diffuse light"
    if scene.lights.count == 0 and black_background:
        return "no lights and a black background: nothing lights the scene"
    if convex and black_background and not any(occludable):
        return ("one convex closed object lit from outside under a black background: every path leaving its "
                "outer side escapes to black, and its inner side is dark")
    return ""


def _closed_oriented(tri_p: np.ndarray) -> bool:
    """Every directed edge appears once and its reverse once (exact vertex positions)."""
    if tri_p.shape[0] < 4:
        return False
    v = tri_p.reshape(-1, 3)
    _, vid = np.unique(v, axis=0, return_inverse=True)
    vid = vid.reshape(-1, 3).astype(np.int64)
    a = vid[:, [0, 1, 2]].ravel()
    b = vid[:, [1, 2, 0]].ravel()
    if np.any(a == b):
        return False
    n = int(vid.max()) + 1
    fwd = a * n + b
    rev = b * n + a
    uf, cf = np.unique(fwd, return_counts=True)
    if np.any(cf != 1):
        return False
    if not np.array_equal(np.sort(rev), uf):
        return False
    # outward: positive signed volume
    p = tri_p
    vol = np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6.0
    return bool(vol > 0)


def _convex(tri_p: np.ndarray, ng: np.ndarray, tol: float) -> bool:
    verts = np.unique(tri_p.reshape(-1, 3), axis=0)
    off = np.einsum("ij,ij->i", ng, tri_p[:, 0])
    for s in range(0, ng.shape[0], 256):  # bounded memory: 256 planes at a time
        d = verts @ ng[s:s + 256].T - off[None, s:s + 256]
        if np.any(d > tol):
            return False
    return True


def _outside(points: np.ndarray, tri_p: np.ndarray, ng: np.ndarray, tol: float) -> bool:
    """All points strictly in front of one common face plane."""
    off = np.einsum("ij,ij->i", ng, tri_p[:, 0])
    d = points @ ng.T - off[None]
    return bool(np.any(np.all(d > tol, axis=0)))


def analyze(scene: RuntimeScene) -> EffectPlan:
    mt = scene.materials
    kinds = tuple(material_kind(mt.kd[i], mt.ks[i], mt.shininess[i], mt.kr[i], mt.kg[i]) for i in range(mt.count))
    used = set(np.unique(scene.tri_material).tolist())
    used_kinds = [kinds[i] for i in used] if used else []
    n_obj = len(scene.object_names)
    closed = []
    for o in range(n_obj):
        sel = scene.tri_object == o
        closed.append(bool(sel.any()) and _closed_oriented(scene.tri_p[sel]))
    present = np.unique(scene.tri_object)
    single = present.size == 1
    tol = 1e-9 * max(scene.extent, 1e-300) + 1e-12 * float(np.abs(scene.center).max(initial=0.0))
    convex = bool(single and closed[int(present[0])] and scene.n_triangles <= CONVEX_TEST_MAX_TRIANGLES
                  and _convex(scene.tri_p, scene.tri_ng, tol))
    lt = scene.lights
    occ = []
    for i in range(lt.n_point):
        occ.append(not (convex and _outside(lt.point_position[i:i + 1], scene.tri_p, scene.tri_ng, tol)))
    for _ in range(lt.n_directional):
        occ.append(not convex)
    for i in range(lt.n_rect):
        c = lt.rect_corner[i]
        corners = np.array([c, c + lt.rect_edge_u[i], c + lt.rect_edge_v[i],
                            c + lt.rect_edge_u[i] + lt.rect_edge_v[i]])
        occ.append(not (convex and _outside(corners, scene.tri_p, scene.tri_ng, tol)))
    used_mats = sorted(used)
    return EffectPlan(
        indirect_skip=_indirect_skip(scene, used_mats, convex, occ),
        material_kinds=kinds,
        needs_view_pass=any(k != "diffuse" for k in used_kinds),
        needs_llf=any(k in ("glossy", "mirror") for k in used_kinds),
        occludable_lights=tuple(occ),
        closed_objects=tuple(closed),
        convex_single_object=convex,
        has_emission=bool(np.any(mt.emission[used_mats] > 0)) if used_mats else False,
        has_ambient=bool(np.any(scene.ambient > 0)),
    )
