"""Small hand-built runtime scenes for engine tests (no schema, no files), and the sample scenes
loaded as the service loads them (:func:`sample_scene`)."""

from __future__ import annotations

import numpy as np
import trimesh

from engine.geometry.mesh import TriMesh
from engine.scene import CameraParams, LightTable, MaterialTable, SceneObjectPart, build_runtime_scene


def mat(name="m", kd=(0.5, 0.5, 0.5), ks=(0, 0, 0), shininess=0.0, kr=(0, 0, 0), kg=(0, 0, 0),
        gloss_exponent=0.0, emission=(0, 0, 0)) -> dict:
    return dict(name=name, kd=kd, ks=ks, shininess=shininess, kr=kr, kg=kg,
                gloss_exponent=gloss_exponent, emission=emission)


def from_trimesh(m: trimesh.Trimesh, smooth: bool = True) -> TriMesh:
    v = np.asarray(m.vertices, dtype=np.float64)
    f = np.asarray(m.faces, dtype=np.int32)
    n = np.asarray(m.vertex_normals if smooth else np.zeros_like(v), dtype=np.float64)
    if not smooth:
        # flat: unshare vertices so every corner carries its face normal
        v = v[f].reshape(-1, 3)
        n = np.repeat(np.asarray(m.face_normals, dtype=np.float64), 3, axis=0)
        f = np.arange(v.shape[0], dtype=np.int32).reshape(-1, 3)
    return TriMesh(np.ascontiguousarray(v), np.ascontiguousarray(f), np.ascontiguousarray(n))


def quad(center, size, normal_axis=1, flip=False) -> TriMesh:
    """Axis-aligned square facing +axis (or -axis when flip)."""
    c = np.asarray(center, dtype=np.float64)
    a, b = [k for k in range(3) if k != normal_axis]
    h = 0.5 * size
    corners = []
    for sa, sb in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
        p = c.copy()
        p[a] += sa * h
        p[b] += sb * h
        corners.append(p)
    v = np.array(corners)
    f = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)
    e = np.cross(v[1] - v[0], v[2] - v[0])
    want = np.zeros(3)
    want[normal_axis] = -1.0 if flip else 1.0
    if np.dot(e, want) < 0:
        f = f[:, ::-1].copy()
    n = np.tile(want, (4, 1))
    return TriMesh(v, f, n)


def scene(parts: list[tuple[TriMesh, dict]], lights: list[dict] | None = None, ambient=(0, 0, 0),
          background=(0, 0, 0)):
    mats = [p[1] for p in parts]
    names = []
    rows = []
    for m in mats:
        if m["name"] not in names:
            names.append(m["name"])
            rows.append(m)
    objs = [SceneObjectPart(f"o{i}", mesh, names.index(m["name"])) for i, (mesh, m) in enumerate(parts)]
    return build_runtime_scene(objs, MaterialTable.from_rows(rows), LightTable.from_rows(lights or []),
                               ambient=ambient, background=background)


def box_room():
    """Two facing coloured walls, a floor and a point light: colour bleeds between them."""
    return scene([(quad((0, 0, 0), 2.0, 1), mat("floor", kd=(0.7, 0.7, 0.7))),
                  (quad((-1, 1, 0), 2.0, 0), mat("red", kd=(0.8, 0.1, 0.1))),
                  (quad((1, 1, 0), 2.0, 0, flip=True), mat("green", kd=(0.1, 0.8, 0.1)))],
                 [dict(type="point", position=(0.0, 1.5, 0.3), intensity=(3.0, 3.0, 3.0))])


def sphere_mesh(center=(0, 0, 0), radius=1.0, subdivisions=4, jitter=0.0, seed=0) -> TriMesh:
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    if jitter:
        rng = np.random.default_rng(seed)
        m.vertices = m.vertices * (1.0 + jitter * rng.uniform(-1, 1, (len(m.vertices), 1)))
    m.apply_translation(center)
    return from_trimesh(m)


def degenerate_cameras(frame_origin, width: int, height: int) -> list[CameraParams]:
    """The degenerate cameras of docs/hard-cases.md #11 for a test scene whose LDC z-axis frame
    starts at ``frame_origin``: an eye inside the scene's box, one on the frame's near plane, a view
    along -x, a top-down orthographic one, fields of view of 1e-4 and 179.99 degrees (all
    ``width`` x ``height``), and a 16 x 16 one on the frame's corner."""
    o = tuple(float(x) for x in frame_origin)
    return [
        CameraParams("perspective", (0.6, -0.1, -0.2), (0.6, -0.1, -2.0), (0, 1, 0), width, height, 60.0),
        CameraParams("perspective", (0.0, 0.2, o[2]), (0.0, 0.0, 0.5), (0, 1, 0), width, height, 60.0),
        CameraParams("perspective", (5.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0, 1, 0), width, height, 45.0),
        CameraParams("orthographic", (0.0, 6.0, 0.0), (0.0, 0.0, 0.0), (0, 0, -1), width, height, ortho_height=3.0),
        CameraParams("perspective", (2.0, 1.0, 3.0), (0.0, 0.0, 0.0), (0, 1, 0), width, height, 1e-4),
        CameraParams("perspective", (2.0, 1.0, 3.0), (0.0, 0.0, 0.0), (0, 1, 0), width, height, 179.99),
        CameraParams("perspective", o, (0.0, 0.0, 0.0), (0, 1, 0), 16, 16, 90.0),
    ]


def sample_scene(name: str):
    """The sample scene ``samples/scenes/NAME.json`` loaded as the workers load it
    (``workers.scene_loader.LoadedScene``: ``.runtime``, ``.camera``)."""
    from api_schemas import load_scene_file
    from samples import SAMPLES_DIR, sample_path
    from workers.scene_loader import directory_resolver, load_scene

    return load_scene(load_scene_file(sample_path(name)), directory_resolver(SAMPLES_DIR))
