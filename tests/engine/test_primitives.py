"""Tessellated primitives: counts, unit outward normals, watertight consistent winding, volumes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from engine.errors import InvalidInputError
from engine.geometry import primitives as P
from engine.geometry.mesh import TriMesh

# --------------------------------------------------------------------------- naive references


def face_cross(mesh: TriMesh) -> np.ndarray:
    v, f = mesh.vertices, mesh.faces
    return np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])


def signed_volume(mesh: TriMesh) -> float:
    """Divergence theorem: positive for a closed mesh with outward CCW winding."""
    v, f = mesh.vertices, mesh.faces
    return float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0)


def merged_faces(mesh: TriMesh) -> np.ndarray:
    """Faces re-indexed so that vertices at bit-identical positions share one index."""
    _, inverse = np.unique(mesh.vertices, axis=0, return_inverse=True)
    return inverse.reshape(-1)[mesh.faces]


def assert_watertight_and_consistent(mesh: TriMesh) -> None:
    """Every undirected edge in exactly two faces, traversed once in each direction."""
    f = merged_faces(mesh)
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    undirected, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    assert np.all(counts == 2), f"{int(np.sum(counts != 2))} edges not shared by exactly two faces"
    uniq_directed, dcounts = np.unique(directed, axis=0, return_counts=True)
    assert np.all(dcounts == 1), "an edge is traversed twice in the same direction (inconsistent winding)"
    assert uniq_directed.shape[0] == 2 * undirected.shape[0]


def assert_well_formed(mesh: TriMesh) -> None:
    assert mesh.vertices.dtype == np.float64 and mesh.faces.dtype == np.int32
    assert np.all(np.isfinite(mesh.vertices)) and np.all(np.isfinite(mesh.normals))
    assert mesh.faces.min() >= 0 and mesh.faces.max() < mesh.n_vertices
    np.testing.assert_allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, atol=1e-12)
    # no degenerate triangles, not even once Embree casts to float32
    f = mesh.faces
    assert np.all((f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2]))
    v32 = mesh.vertices.astype(np.float32)
    c32 = np.cross(v32[f[:, 1]] - v32[f[:, 0]], v32[f[:, 2]] - v32[f[:, 0]])
    assert np.all(np.linalg.norm(c32, axis=1) > 0)
    # every vertex used
    assert np.unique(f).size == mesh.n_vertices


def assert_face_normals_agree(mesh: TriMesh) -> None:
    c = face_cross(mesh)
    for k in range(3):
        dots = np.einsum("ij,ij->i", c, mesh.normals[mesh.faces[:, k]])
        assert np.all(dots > 0), f"{int(np.sum(dots <= 0))} faces wind against their vertex normals"


# --------------------------------------------------------------------------- sphere


@pytest.mark.parametrize("level", [0, 1, 2, 3, 5])
def test_sphere_counts(level):
    m = P.sphere((0, 0, 0), 1.0, subdivisions=level)
    assert m.n_vertices == 10 * 4**level + 2
    assert m.n_faces == 20 * 4**level
    assert_well_formed(m)


def test_sphere_default_is_level_5():
    assert P.sphere().n_faces == 20 * 4**5


@pytest.mark.parametrize("level", [0, 2, 5])
def test_sphere_closed_outward_and_volume(level):
    c, r = np.array([1.0, -2.0, 3.5]), 0.75
    m = P.sphere(c, r, subdivisions=level)
    assert_watertight_and_consistent(m)
    assert_face_normals_agree(m)
    radial = m.vertices - c
    assert np.all(np.einsum("ij,ij->i", m.normals, radial) > 0)
    np.testing.assert_allclose(np.linalg.norm(radial, axis=1), r, rtol=1e-14)
    np.testing.assert_allclose(m.normals, radial / r, atol=1e-14)
    # signed volume is translation invariant for a closed mesh
    exact = 4.0 / 3.0 * math.pi * r**3
    vol = signed_volume(m)
    assert 0 < vol < exact  # inscribed polyhedron
    if level == 5:
        assert abs(vol - exact) / exact < 0.005


def test_sphere_vertices_are_deduplicated():
    m = P.sphere(subdivisions=3)
    assert np.unique(m.vertices, axis=0).shape[0] == m.n_vertices


# --------------------------------------------------------------------------- box


def test_box_counts_normals_volume():
    c, s = np.array([0.5, -1.0, 2.0]), np.array([1.0, 2.0, 3.0])
    m = P.box(c, s)
    assert (m.n_vertices, m.n_faces) == (24, 12)
    assert_well_formed(m)
    assert_face_normals_agree(m)
    # flat per-face normals: each is a signed axis and equals the face's own normal
    assert np.all(np.sort(np.abs(m.normals), axis=1) == [0.0, 0.0, 1.0])
    unit_face = face_cross(m) / np.linalg.norm(face_cross(m), axis=1, keepdims=True)
    for k in range(3):
        np.testing.assert_allclose(m.normals[m.faces[:, k]], unit_face, atol=1e-15)
    assert np.all(np.einsum("ij,ij->i", m.normals, m.vertices - c) > 0)
    assert_watertight_and_consistent(m)
    assert signed_volume(m) == pytest.approx(6.0, rel=1e-14)
    np.testing.assert_allclose(m.vertices.min(axis=0), c - s / 2)
    np.testing.assert_allclose(m.vertices.max(axis=0), c + s / 2)


def test_box_scalar_size_is_a_cube():
    m = P.box((0, 0, 0), 2.0)
    assert signed_volume(m) == pytest.approx(8.0, rel=1e-14)


# --------------------------------------------------------------------------- cylinder


@pytest.mark.parametrize("segments", [3, 7, 64])
def test_cylinder_capped_closed_and_volume(segments):
    c, r, h = np.array([1.0, 2.0, -3.0]), 0.5, 2.0
    m = P.cylinder(c, r, h, segments=segments)
    assert m.n_vertices == 2 * segments + 2 * (segments + 1)
    assert m.n_faces == 4 * segments
    assert_well_formed(m)
    assert_face_normals_agree(m)
    assert_watertight_and_consistent(m)
    prism = 0.5 * segments * r**2 * math.sin(2 * math.pi / segments) * h  # inscribed polygon prism
    assert signed_volume(m) == pytest.approx(prism, rel=1e-12)
    if segments == 64:
        exact = math.pi * r**2 * h
        assert abs(signed_volume(m) - exact) / exact < 0.005
    np.testing.assert_allclose([m.vertices[:, 1].min(), m.vertices[:, 1].max()], [c[1] - h / 2, c[1] + h / 2])


def test_cylinder_normals_radial_side_flat_caps():
    c = np.array([0.0, 1.0, 0.0])
    m = P.cylinder(c, 2.0, 1.0, segments=16)
    side = m.normals[:, 1] == 0.0
    assert side.sum() == 32
    radial = m.vertices[side] - c
    radial[:, 1] = 0.0
    np.testing.assert_allclose(m.normals[side], radial / 2.0, atol=1e-15)
    assert np.all(np.einsum("ij,ij->i", m.normals[side], m.vertices[side] - c) > 0)
    caps = ~side
    assert np.all(np.abs(m.normals[caps, 1]) == 1.0)
    # the +y cap is on top, the -y cap at the bottom
    assert np.all(np.sign(m.normals[caps, 1]) == np.sign(m.vertices[caps, 1] - c[1]))


def test_cylinder_uncapped_is_an_open_tube():
    m = P.cylinder((0, 0, 0), 1.0, 1.0, segments=12, capped=False)
    assert (m.n_vertices, m.n_faces) == (24, 24)
    assert_well_formed(m)
    assert_face_normals_agree(m)
    f = merged_faces(m)
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.sum(counts == 1) == 24  # the two rims


# --------------------------------------------------------------------------- plane, disk


@pytest.mark.parametrize("segments", [1, 4])
def test_plane(segments):
    c = np.array([1.0, 2.0, 3.0])
    m = P.plane(c, (2.0, 4.0), segments=segments)
    assert m.n_vertices == (segments + 1) ** 2
    assert m.n_faces == 2 * segments**2
    assert_well_formed(m)
    assert_face_normals_agree(m)
    assert np.all(m.normals == [0.0, 1.0, 0.0])
    assert np.all(m.vertices[:, 1] == c[1])
    cross = face_cross(m)
    assert np.all(cross[:, 1] > 0) and np.allclose(cross[:, [0, 2]], 0.0)
    assert cross[:, 1].sum() / 2 == pytest.approx(8.0, rel=1e-14)
    np.testing.assert_allclose(m.vertices.min(axis=0), [0.0, 2.0, 1.0])
    np.testing.assert_allclose(m.vertices.max(axis=0), [2.0, 2.0, 5.0])


def test_disk():
    c = np.array([0.0, -1.0, 0.0])
    m = P.disk(c, 2.0, segments=64)
    assert (m.n_vertices, m.n_faces) == (65, 64)
    assert_well_formed(m)
    assert_face_normals_agree(m)
    assert np.all(m.normals == [0.0, 1.0, 0.0])
    area = face_cross(m)[:, 1].sum() / 2
    assert area == pytest.approx(0.5 * 64 * 4.0 * math.sin(2 * math.pi / 64), rel=1e-12)
    assert abs(area - math.pi * 4.0) / (math.pi * 4.0) < 0.005


def test_transformed_primitive_stays_outward():
    mirror = np.diag([-1.0, 2.0, 1.0, 1.0])
    m = P.sphere((0, 0, 0), 1.0, subdivisions=2).transformed(mirror)
    assert signed_volume(m) > 0
    assert_face_normals_agree(m)


# --------------------------------------------------------------------------- bad arguments


@pytest.mark.parametrize(
    ("call", "name"),
    [
        (lambda: P.sphere((0, 0, 0), 0.0), "radius"),
        (lambda: P.sphere((0, 0, 0), -1.0), "radius"),
        (lambda: P.sphere((0, 0, 0), float("nan")), "radius"),
        (lambda: P.sphere((0, 0, 0), float("inf")), "radius"),
        (lambda: P.sphere((0, 0, 0), "1"), "radius"),
        (lambda: P.sphere((0, 0, 0), True), "radius"),
        (lambda: P.sphere((0, 0, 0), 1.0, subdivisions=-1), "subdivisions"),
        (lambda: P.sphere((0, 0, 0), 1.0, subdivisions=P.MAX_SPHERE_SUBDIVISIONS + 1), "subdivisions"),
        (lambda: P.sphere((0, 0, 0), 1.0, subdivisions=2.0), "subdivisions"),
        (lambda: P.sphere((0, 0), 1.0), "center"),
        (lambda: P.sphere((0, float("nan"), 0), 1.0), "center"),
        (lambda: P.sphere("abc", 1.0), "center"),
        (lambda: P.sphere((1e19, 0, 0), 1.0), "center"),
        (lambda: P.sphere((0, 0, 0), 2e18), "radius"),
        (lambda: P.sphere((1e6, 0, 0), 1e-3), "radius"),  # lost in float32 next to the centre
        (lambda: P.box((0, 0, 0), (1.0, 0.0, 1.0)), "size"),
        (lambda: P.box((0, 0, 0), (1.0, 1.0)), "size"),
        (lambda: P.box((0, 0, 0), -2.0), "size"),
        (lambda: P.box((0, 0, 0), (1.0, float("inf"), 1.0)), "size"),
        (lambda: P.cylinder((0, 0, 0), 1.0, 0.0), "height"),
        (lambda: P.cylinder((0, 0, 0), -1.0, 1.0), "radius"),
        (lambda: P.cylinder((0, 0, 0), 1.0, 1.0, segments=2), "segments"),
        (lambda: P.cylinder((0, 0, 0), 1.0, 1.0, segments=8.0), "segments"),
        (lambda: P.cylinder((0, 0, 0), 1.0, 1.0, segments=P.MAX_SEGMENTS + 1), "segments"),
        (lambda: P.cylinder((0, 0, 0), 1.0, 1.0, capped="yes"), "capped"),
        (lambda: P.plane((0, 0, 0), (1.0, -1.0)), "size"),
        (lambda: P.plane((0, 0, 0), (1.0, 1.0), segments=0), "segments"),
        (lambda: P.disk((0, 0, 0), 0.0), "radius"),
        (lambda: P.disk((0, 0, 0), 1.0, segments=2), "segments"),
    ],
)
def test_bad_arguments_raise_naming_the_argument(call, name):
    with pytest.raises(InvalidInputError, match=name):
        call()
