"""Mesh validation and file loading: the policy in engine.geometry.meshio, one case per rule."""

from __future__ import annotations

import json
import os
import zlib
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from engine.errors import InvalidInputError, MeshValidationError
from engine.geometry.mesh import TriMesh
from engine.geometry.meshio import (
    SUPPORTED_MESH_TYPES,
    MeshReport,
    load_mesh_bytes,
    load_mesh_file,
    validate_mesh,
)

REPO = Path(__file__).resolve().parents[2]
DATA = REPO.parent / "shared" / "data"
TEAPOT = DATA / "utah-teapot" / "teapot.ply"
MITSUBA_MESHES = DATA / "cornell-box-mitsuba" / "meshes"
MCGUIRE_ORIGINAL = DATA / "cornell-box-mcguire" / "CornellBox-Original.obj"
# Skipped only off CI: .ci/run runs beside ../shared, so there a missing folder must fail.
needs_data = pytest.mark.skipif(not os.environ.get("CI") and not DATA.is_dir(), reason="shared data not available")

TRI = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


# --------------------------------------------------------------------------- helpers


def tetra() -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    return v, f


def check_report(mesh: TriMesh, report: MeshReport) -> None:
    """The bookkeeping identities the module docstring promises, and a well-formed mesh."""
    assert report.n_vertices_out == mesh.n_vertices and report.n_faces_out == mesh.n_faces
    assert report.n_faces_out == (
        report.n_faces_in
        - report.nonfinite_faces_removed
        - report.degenerate_faces_removed
        - report.duplicate_faces_removed
    )
    assert report.n_vertices_out == (
        report.n_vertices_in
        - report.unreferenced_vertices_removed
        - report.duplicate_vertices_merged
        + report.crease_vertices_split
    )
    assert report.out_of_range_indices == 0
    assert np.all(np.isfinite(mesh.vertices)) and np.all(np.isfinite(mesh.normals))
    np.testing.assert_allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, atol=1e-12)
    assert mesh.faces.min() >= 0 and mesh.faces.max() < mesh.n_vertices
    assert np.unique(mesh.faces).size == mesh.n_vertices  # no unreferenced vertex left
    # no two vertices with the same position and normal
    assert np.unique(np.column_stack([mesh.vertices, mesh.normals]), axis=0).shape[0] == mesh.n_vertices
    assert json.loads(json.dumps(report.to_dict()))["source"] == report.source
    if report.normals_computed:
        assert_normals_in_front_of_faces(mesh)


def assert_normals_in_front_of_faces(mesh: TriMesh) -> None:
    v, f = mesh.vertices, mesh.faces
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    for k in range(3):
        dots = np.einsum("ij,ij->i", cross, mesh.normals[f[:, k]])
        assert np.all(dots > 0), f"{int(np.sum(dots <= 0))} corner normals point behind their face"


def canonical_triangles(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m, 9): each triangle's corners rotated to start at its lexicographically smallest corner.

    Rotation keeps the winding, so two meshes match only with the same orientation.
    """
    tri = vertices[faces]  # (m, 3, 3)
    keys = np.round(tri, 6)
    start = np.array([min(range(3), key=lambda k: tuple(t[k])) for t in keys])
    idx = (start[:, None] + np.arange(3)) % 3
    return np.take_along_axis(tri, idx[:, :, None], axis=1).reshape(-1, 9)


def assert_same_triangles(mesh: TriMesh, ref_vertices: np.ndarray, ref_faces: np.ndarray, tol=1e-5):
    got = canonical_triangles(mesh.vertices, mesh.faces)
    want = canonical_triangles(np.asarray(ref_vertices, dtype=np.float64), np.asarray(ref_faces))
    assert got.shape == want.shape
    dist, nearest = cKDTree(want).query(got)
    assert dist.max() < tol
    assert np.unique(nearest).size == want.shape[0]  # a bijection, not many-to-one


def signed_volume(mesh: TriMesh) -> float:
    v, f = mesh.vertices, mesh.faces
    return float(np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6.0)


def ascii_ply(vertices, faces) -> bytes:
    lines = [
        "ply",
        "format ascii 1.0",
        f"element vertex {len(vertices)}",
        "property float x",
        "property float y",
        "property float z",
        f"element face {len(faces)}",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    lines += [" ".join(repr(float(x)) for x in p) for p in vertices]
    lines += [f"{len(f)} " + " ".join(str(int(i)) for i in f) for f in faces]
    return ("\n".join(lines) + "\n").encode()


def png_bytes() -> bytes:
    """A tiny but valid PNG, built by hand."""

    def chunk(tag: bytes, body: bytes) -> bytes:
        return len(body).to_bytes(4, "big") + tag + body + zlib.crc32(tag + body).to_bytes(4, "big")

    ihdr = (4).to_bytes(4, "big") * 2 + bytes([8, 2, 0, 0, 0])
    raw = b"".join(b"\x00" + b"\x80\x40\x20" * 4 for _ in range(4))
    return (
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")
    )


@pytest.fixture(scope="module")
def sphere_tm() -> trimesh.Trimesh:
    m = trimesh.creation.icosphere(subdivisions=3, radius=2.0)
    m.apply_translation([1.0, -2.0, 0.5])
    return m


# =========================================================================== validate_mesh


def tetra_normals() -> np.ndarray:
    v, _ = tetra()
    return v - v.mean(axis=0)


def test_clean_mesh_passes_unchanged():
    v, f = tetra()
    mesh, report = validate_mesh(v, f, tetra_normals(), source="tetra")
    check_report(mesh, report)
    assert (report.n_vertices_out, report.n_faces_out) == (4, 4)
    np.testing.assert_array_equal(mesh.vertices, v)
    np.testing.assert_array_equal(mesh.faces, f)
    assert not report.normals_computed
    assert signed_volume(mesh) == pytest.approx(1 / 6)


def test_all_crease_mesh_is_flat_shaded():
    """Every tetrahedron edge is sharper than the crease angle: one vertex copy per face."""
    v, f = tetra()
    mesh, report = validate_mesh(v, f, source="tetra")
    check_report(mesh, report)
    assert report.normals_computed
    assert (report.n_vertices_out, report.n_faces_out, report.crease_vertices_split) == (12, 4, 8)
    assert_same_triangles(mesh, v, f)
    assert signed_volume(mesh) == pytest.approx(1 / 6)
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    for k in range(3):  # flat: each corner has its face's normal
        got = mesh.normals[mesh.faces[:, k]]
        np.testing.assert_allclose(
            np.sort(got, axis=0), np.sort(cross / np.linalg.norm(cross, axis=1, keepdims=True), axis=0)
        )


@pytest.mark.parametrize("on_invalid", ["reject", "clean"])
def test_out_of_range_and_negative_indices_always_rejected(on_invalid):
    v, f = tetra()
    f = f.copy()
    f[1, 2] = 4  # == n
    f[2, 0] = -1
    f[3, 1] = 99
    with pytest.raises(MeshValidationError) as err:
        validate_mesh(v, f, source="bad.ply", on_invalid=on_invalid)
    e = err.value
    assert e.source == "bad.ply"
    assert e.counts["out_of_range_indices"] == 3
    assert e.counts["negative_indices"] == 1
    assert e.counts["faces_affected"] == 3
    assert "bad.ply" in str(e) and "3 face indices out of range" in str(e)


def test_unsigned_index_overflow_is_out_of_range():
    v, f = tetra()
    f = f.astype(np.uint64)
    f[0, 0] = np.iinfo(np.uint64).max
    with pytest.raises(MeshValidationError) as err:
        validate_mesh(v, f, source="u64")
    assert err.value.counts["out_of_range_indices"] == 1


@pytest.mark.parametrize("bad_value", [np.nan, np.inf, -np.inf, 1e19])
def test_nonfinite_vertices_rejected_with_count(bad_value):
    v, f = tetra()
    v = np.concatenate([v, [[2.0, 2.0, 2.0], [3.0, 3.0, 3.0]]])
    v[4, 1] = bad_value
    v[5, 2] = bad_value
    f = np.concatenate([f, [[0, 1, 4], [1, 2, 5]]])
    with pytest.raises(MeshValidationError) as err:
        validate_mesh(v, f, source="nan.obj")
    assert err.value.counts["nonfinite_vertices"] == 2
    assert "2 of 6 vertices are non-finite" in str(err.value)


def test_nonfinite_vertices_cleaned_with_count():
    v, f = tetra()
    v = np.concatenate([v, [[np.nan, 0.0, 0.0], [0.0, np.inf, 0.0]]])
    f = np.concatenate([f, [[0, 1, 4], [1, 2, 5], [4, 5, 3]]])
    normals = np.concatenate([tetra_normals(), np.ones((2, 3))])
    mesh, report = validate_mesh(v, f, normals, source="nan.obj", on_invalid="clean")
    check_report(mesh, report)
    assert report.nonfinite_vertices == 2
    assert report.nonfinite_faces_removed == 3
    assert report.unreferenced_vertices_removed == 2  # the NaN vertices, orphaned
    assert (report.n_vertices_out, report.n_faces_out) == (4, 4)
    assert_same_triangles(mesh, *tetra())


def test_degenerate_faces_removed_and_counted():
    v, f = tetra()
    v = np.concatenate(
        [
            v,
            [[0.0, 0.0, 0.0]],  # 4: same position as vertex 0
            [[0.5, 0.5, 0.0]],  # 5: collinear with 1 and 2
            [[1e8, 0.0, 0.0], [1e8 + 1e-3, 0.0, 0.0], [1e8, 1e-3, 0.0]],  # 6-8: vanish in float32
        ]
    )
    degenerate = [
        [0, 0, 1],  # repeated index
        [1, 2, 2],  # repeated index
        [4, 0, 1],  # zero area (coincident positions, distinct indices)
        [1, 2, 5],  # collinear
        [6, 7, 8],  # non-zero in float64, zero once cast to float32 (Embree)
    ]
    mesh, report = validate_mesh(v, np.concatenate([f, degenerate]), source="deg")
    check_report(mesh, report)
    assert report.degenerate_faces_removed == 5
    assert report.unreferenced_vertices_removed == 5
    assert_same_triangles(mesh, *tetra())


def test_tiny_but_valid_triangles_are_kept():
    """Zero area means zero for the triangle itself, not small next to the rest of the mesh."""
    v, f = tetra()
    mesh, report = validate_mesh(v * 1e-6, f, source="tiny")
    assert report.degenerate_faces_removed == 0 and mesh.n_faces == 4
    # a 1 mm tetrahedron beside a 1 km ground quad: removing it would open holes
    ground = np.array([[-500.0, 0, -500], [500, 0, -500], [500, 0, 500], [-500, 0, 500]])
    v2 = np.concatenate([v * 1e-3 + [0, 1, 0], ground])
    f2 = np.concatenate([f, [[4, 6, 5], [4, 7, 6]]])
    mesh, report = validate_mesh(v2, f2, source="scene")
    assert report.degenerate_faces_removed == 0 and mesh.n_faces == 6


def test_needle_sliver_is_degenerate():
    v, f = tetra()
    sliver = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 1e-14, 0.0]])
    mesh, report = validate_mesh(np.concatenate([v, sliver]), np.concatenate([f, [[4, 5, 6]]]), source="s")
    assert report.degenerate_faces_removed == 1 and mesh.n_faces == 4


def test_duplicate_faces_removed_and_counted():
    v, f = tetra()
    dup = np.concatenate([f, f[[0]], f[[1]][:, [1, 2, 0]], f[[2]][:, ::-1]])  # same, rotated, reversed
    mesh, report = validate_mesh(v, dup, source="dup")
    check_report(mesh, report)
    assert report.duplicate_faces_removed == 3
    assert_same_triangles(mesh, v, f)  # the first occurrence (and its winding) wins


def test_unreferenced_vertices_removed_and_reindexed():
    v, f = tetra()
    v2 = np.concatenate([[[9.0, 9.0, 9.0]], v, [[7.0, 7.0, 7.0]]])
    n2 = np.concatenate([[[1.0, 0, 0]], tetra_normals(), [[1.0, 0, 0]]])
    mesh, report = validate_mesh(v2, f + 1, n2, source="unref")
    check_report(mesh, report)
    assert report.unreferenced_vertices_removed == 2
    np.testing.assert_array_equal(mesh.vertices, v)
    np.testing.assert_array_equal(mesh.faces, f)


@pytest.mark.parametrize("on_invalid", ["reject", "clean"])
def test_nothing_left_is_an_error(on_invalid):
    with pytest.raises(MeshValidationError, match="no valid triangles"):
        validate_mesh(np.zeros((3, 3)), [[0, 1, 2]], source="flat", on_invalid=on_invalid)
    with pytest.raises(MeshValidationError, match="no valid triangles"):
        validate_mesh(TRI, np.zeros((0, 3), dtype=np.int64), source="empty", on_invalid=on_invalid)
    with pytest.raises(MeshValidationError, match="no valid triangles") as err:
        validate_mesh(np.concatenate([TRI, [[np.nan] * 3]]), [[0, 1, 3]], source="x", on_invalid="clean")
    assert err.value.counts["nonfinite_faces_removed"] == 1


@pytest.mark.parametrize(
    ("vertices", "faces"),
    [
        (TRI, [[0, 1, 2, 0]]),  # quads
        (TRI, [0, 1, 2]),  # flat
        (TRI, [[0.0, 1.0, 2.0]]),  # float indices
        (TRI, [[True, False, True]]),  # bool
        (TRI, [["0", "1", "2"]]),  # strings
        (TRI[:, :2], [[0, 1, 2]]),  # 2-D vertices
        ([[0, 0, 0], [1, 0], [0, 1, 0]], [[0, 1, 2]]),  # ragged
        (TRI.astype(complex), [[0, 1, 2]]),
        (np.array([["a", "b", "c"]] * 3), [[0, 1, 2]]),
    ],
)
def test_wrong_shapes_and_types(vertices, faces):
    with pytest.raises(MeshValidationError):
        validate_mesh(vertices, faces, source="shape")


def test_bad_policy_name():
    with pytest.raises(InvalidInputError, match="on_invalid"):
        validate_mesh(TRI, [[0, 1, 2]], source="x", on_invalid="fix")  # type: ignore[arg-type]


def test_given_normals_renormalised_and_bad_ones_recomputed():
    v, f = tetra()
    given = (v - v.mean(axis=0)) * 5.0
    mesh, report = validate_mesh(v, f, given, source="n")
    assert not report.normals_computed
    np.testing.assert_allclose(mesh.normals, given / np.linalg.norm(given, axis=1, keepdims=True))
    bad = given.copy()
    bad[0] = 0.0
    bad[1, 2] = np.nan
    mesh, report = validate_mesh(v, f, bad, source="n")
    assert report.normals_computed
    # vertices 2 and 3 keep their given normal; 0 and 1 get flat normals per face (3 copies each)
    assert mesh.n_vertices == 2 + 3 + 3
    for i in (2, 3):
        rows = np.all(mesh.vertices == v[i], axis=1)
        assert rows.sum() == 1
        np.testing.assert_allclose(mesh.normals[rows][0], given[i] / np.linalg.norm(given[i]))
    assert np.all(np.einsum("ij,ij->i", mesh.normals, mesh.vertices - v.mean(axis=0)) > 0)
    # wrong shape: ignored, all computed
    mesh, report = validate_mesh(v, f, given[:2], source="n")
    assert report.normals_computed


def test_opposing_faces_split_the_vertex_instead_of_cancelling():
    # two right triangles meeting at vertex 0, facing +z and -z: a shared normal would be ~0
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [-1, 0, 0]], dtype=np.float64)
    f = np.array([[0, 1, 2], [0, 3, 4]])
    mesh, report = validate_mesh(v, f, source="bowtie")
    check_report(mesh, report)
    assert report.crease_vertices_split == 1 and mesh.n_vertices == 6
    at_origin = np.all(mesh.vertices == 0.0, axis=1)
    np.testing.assert_allclose(np.sort(mesh.normals[at_origin][:, 2]), [-1.0, 1.0])
    assert_normals_in_front_of_faces(mesh)


def test_shared_vertex_cube_gets_flat_faces():
    cube = trimesh.creation.box()  # 8 shared vertices
    mesh, report = validate_mesh(cube.vertices, cube.faces, source="cube")
    check_report(mesh, report)
    assert report.crease_vertices_split == 16 and mesh.n_vertices == 24
    assert np.allclose(np.sort(np.abs(mesh.normals), axis=1), [0.0, 0.0, 1.0])
    assert signed_volume(mesh) == pytest.approx(1.0)


def test_smooth_normals_of_a_fine_sphere_are_radial():
    m = trimesh.creation.icosphere(subdivisions=4)
    mesh, report = validate_mesh(m.vertices, m.faces, source="sphere")
    check_report(mesh, report)
    cos = np.einsum("ij,ij->i", mesh.normals, mesh.vertices / np.linalg.norm(mesh.vertices, axis=1)[:, None])
    assert cos.min() > 0.9999


def test_triangle_soup_is_welded_but_creases_stay_sharp():
    sphere = trimesh.creation.icosphere(subdivisions=2)
    soup_v = sphere.vertices[sphere.faces].reshape(-1, 3)
    soup_f = np.arange(soup_v.shape[0]).reshape(-1, 3)
    mesh, report = validate_mesh(soup_v, soup_f, source="soup.stl")
    check_report(mesh, report)
    assert report.duplicate_vertices_merged == soup_v.shape[0] - sphere.vertices.shape[0]
    cos = np.einsum("ij,ij->i", mesh.normals, mesh.vertices / np.linalg.norm(mesh.vertices, axis=1)[:, None])
    assert cos.min() > 0.99  # smooth, not faceted

    cube = trimesh.creation.box()
    soup_v = cube.vertices[cube.faces].reshape(-1, 3)
    soup_f = np.arange(soup_v.shape[0]).reshape(-1, 3)
    mesh, report = validate_mesh(soup_v, soup_f, source="cube.stl")
    check_report(mesh, report)
    assert mesh.n_vertices == 24  # 4 per face: 90 degree edges are creases
    assert np.allclose(np.sort(np.abs(mesh.normals), axis=1), [0.0, 0.0, 1.0])
    assert signed_volume(mesh) == pytest.approx(1.0)


# =========================================================================== files: round trips


@pytest.mark.parametrize("file_type", ["obj", "ply", "stl", "glb"])
def test_round_trip_every_format(tmp_path, sphere_tm, file_type):
    path = tmp_path / f"sphere.{file_type}"
    sphere_tm.export(path)
    mesh, report = load_mesh_file(path)
    check_report(mesh, report)
    assert report.source == path.name
    assert mesh.n_faces == len(sphere_tm.faces)
    assert mesh.n_vertices == len(sphere_tm.vertices)  # STL's soup is welded back
    assert_same_triangles(mesh, sphere_tm.vertices, sphere_tm.faces)
    assert signed_volume(mesh) == pytest.approx(sphere_tm.volume, rel=1e-6)
    cos = np.einsum("ij,ij->i", mesh.normals, mesh.vertices - sphere_tm.center_mass)
    assert np.all(cos > 0)
    if file_type == "stl":
        assert (
            report.normals_computed and report.duplicate_vertices_merged == 3 * mesh.n_faces - mesh.n_vertices
        )


def test_round_trip_bytes_matches_file(tmp_path, sphere_tm):
    data = sphere_tm.export(file_type="ply")
    mesh, report = load_mesh_bytes(data, file_type="PLY", source="upload-1")
    assert report.source == "upload-1"
    assert_same_triangles(mesh, sphere_tm.vertices, sphere_tm.faces)


def test_file_normals_kept_only_when_present(tmp_path):
    v, f = tetra()
    odd = np.tile([[0.0, 0.0, 2.0]], (4, 1))  # deliberately not the geometric normal
    obj = "".join(f"v {a} {b} {c}\n" for a, b, c in v) + "vn 0 0 2\n"
    obj += "".join(f"f {a + 1}//1 {b + 1}//1 {c + 1}//1\n" for a, b, c in f)
    mesh, report = load_mesh_bytes(obj.encode(), file_type="obj", source="n.obj")
    assert not report.normals_computed
    np.testing.assert_allclose(mesh.normals, odd / 2.0)
    # same file without vn: our own smooth normals, not trimesh's
    obj_plain = "".join(f"v {a} {b} {c}\n" for a, b, c in v) + "".join(
        f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in f
    )
    mesh, report = load_mesh_bytes(obj_plain.encode(), file_type="obj", source="p.obj")
    assert report.normals_computed


def test_gltf_scene_nodes_are_transformed_and_concatenated(tmp_path):
    box = trimesh.creation.box()
    scene = trimesh.Scene()
    scene.add_geometry(box, node_name="a", transform=trimesh.transformations.translation_matrix([5, 0, 0]))
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0]) @ trimesh.transformations.translation_matrix([-10, 0, 0])
    scene.add_geometry(box, node_name="b", transform=mirror)
    scaled = trimesh.transformations.scale_matrix(2.0) @ trimesh.transformations.translation_matrix([0, 5, 0])
    scene.add_geometry(trimesh.creation.icosphere(2), node_name="c", transform=scaled)
    path = tmp_path / "scene.glb"
    path.write_bytes(scene.export(file_type="glb"))
    mesh, report = load_mesh_file(path)
    check_report(mesh, report)
    assert mesh.n_faces == 12 + 12 + 320
    # the mirrored box keeps outward winding, so the total volume is the sum of positives
    expected = 1.0 + 1.0 + trimesh.creation.icosphere(2).volume * 8.0
    assert signed_volume(mesh) == pytest.approx(expected, rel=1e-6)
    np.testing.assert_allclose(mesh.vertices.min(axis=0), [-2.0, -0.5, -2.0], atol=1e-6)
    np.testing.assert_allclose(mesh.vertices.max(axis=0), [10.5, 12.0, 2.0], atol=1e-6)


def test_gltf_with_external_buffers(tmp_path, sphere_tm):
    files = trimesh.Scene(sphere_tm).export(file_type="gltf")
    for name, blob in files.items():
        (tmp_path / name).write_bytes(blob)
    mesh, report = load_mesh_file(tmp_path / "model.gltf")
    check_report(mesh, report)
    assert_same_triangles(mesh, sphere_tm.vertices, sphere_tm.faces)
    # as an upload it may not read other files
    with pytest.raises(MeshValidationError, match="external"):
        load_mesh_bytes(files["model.gltf"], file_type="gltf", source="up.gltf")
    # nor, as a file, anything outside its directory
    secret = tmp_path / "secret.bin"
    secret.write_bytes(files["gltf_buffer_0.bin"])
    sub = tmp_path / "sub"
    sub.mkdir()
    tree = json.loads(files["model.gltf"])
    tree["buffers"][0]["uri"] = "../secret.bin"
    (sub / "model.gltf").write_text(json.dumps(tree))
    with pytest.raises(MeshValidationError, match="outside"):
        load_mesh_file(sub / "model.gltf")


# =========================================================================== files: bad indices / values


def test_ply_out_of_range_and_negative_indices(tmp_path):
    v, f = tetra()
    f = f.copy()
    f[0, 0] = 7
    f[1, 1] = -2
    path = tmp_path / "broken.ply"
    path.write_bytes(ascii_ply(v, f))
    with pytest.raises(MeshValidationError) as err:
        load_mesh_file(path, on_invalid="clean")
    assert err.value.source == "broken.ply"
    assert err.value.counts["out_of_range_indices"] == 2
    assert err.value.counts["negative_indices"] == 1


@pytest.mark.parametrize(
    ("faces", "n_bad"),
    [("f 1 2 9\nf 1 2 3\n", 1), ("f 0 1 2\n", 1), ("f -1 -2 -9\nf 1 2 5\n", 2), ("f 1/1 2/1 -3/-2\n", 1)],
)
def test_obj_bad_indices_counted(faces, n_bad):
    obj = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nvt 0 0\n" + faces
    with pytest.raises(MeshValidationError) as err:
        load_mesh_bytes(obj.encode(), file_type="obj", source="bad.obj")
    assert err.value.counts["out_of_range_indices"] == n_bad
    assert err.value.source == "bad.obj"


def test_obj_relative_indices_resolved_per_line():
    obj = (
        "v 0 0 0\nv 1 0 0\nv 0 1 0\nf -3 -2 -1\n"  # first triangle
        "v 5 0 0\nv 6 0 0\nv 5 1 0\nf -3 -2 -1\n"  # second triangle, same relative indices
    )
    mesh, report = load_mesh_bytes(obj.encode(), file_type="obj", source="rel.obj")
    check_report(mesh, report)
    assert report.n_faces_out == 2 and report.duplicate_faces_removed == 0
    np.testing.assert_allclose(mesh.vertices[:, 0].max(), 6.0)


def test_obj_nan_vertices_reject_and_clean():
    obj = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv nan 0 1\nf 1 2 3\nf 1 2 4\n"
    with pytest.raises(MeshValidationError) as err:
        load_mesh_bytes(obj, file_type="obj", source="nan.obj")
    assert err.value.counts["nonfinite_vertices"] == 1
    mesh, report = load_mesh_bytes(obj, file_type="obj", source="nan.obj", on_invalid="clean")
    check_report(mesh, report)
    assert (report.nonfinite_vertices, report.nonfinite_faces_removed, mesh.n_faces) == (1, 1, 1)


def test_stl_degenerate_and_duplicate_facets_counted(tmp_path):
    m = trimesh.creation.icosphere(1)
    soup = m.vertices[m.faces]
    extra = np.array([[[0, 0, 0], [1, 1, 1], [2, 2, 2]], [[3, 0, 0], [3, 0, 0], [3, 1, 0]]], dtype=float)
    soup = np.concatenate([soup, soup[:2], extra])  # 2 duplicates, collinear, repeated point
    stl = trimesh.Trimesh(soup.reshape(-1, 3), np.arange(soup.shape[0] * 3).reshape(-1, 3), process=False)
    path = tmp_path / "facets.stl"
    stl.export(path)
    mesh, report = load_mesh_file(path)
    check_report(mesh, report)
    assert report.degenerate_faces_removed == 2
    assert report.duplicate_faces_removed == 2
    assert mesh.n_faces == len(m.faces)


# ========================================================================= files: wrong type, truncated, big


GARBAGE = {
    "png": png_bytes(),
    "random": np.random.default_rng(7).integers(0, 256, 4096, dtype=np.uint8).tobytes(),
    "random_text": bytes(np.random.default_rng(8).integers(32, 127, 4096, dtype=np.uint8)),
    "empty": b"",
    "json": b'{"asset": {"version": "2.0"}}',
    "html": b"<html><body>not a mesh</body></html>",
    "ply_magic_only": b"ply\nformat ascii 1.0\n",
    "solid_header_only": b"solid x\n",
}


@pytest.mark.parametrize("file_type", list(SUPPORTED_MESH_TYPES))
@pytest.mark.parametrize("payload", list(GARBAGE))
def test_wrong_file_type_is_a_validation_error(tmp_path, file_type, payload):
    path = tmp_path / f"upload.{file_type}"
    path.write_bytes(GARBAGE[payload])
    with pytest.raises(MeshValidationError) as err:
        load_mesh_file(path)
    assert err.value.source == path.name
    with pytest.raises(MeshValidationError):
        load_mesh_bytes(GARBAGE[payload], file_type=file_type, source="upload")


@pytest.mark.parametrize("file_type", ["ply-ascii", "ply-binary", "stl-ascii", "stl-binary", "glb"])
@pytest.mark.parametrize("keep", [0.3, 0.6, 0.9, 0.999])
def test_truncated_files_are_validation_errors(sphere_tm, file_type, keep):
    if file_type == "ply-ascii":
        data, ft = trimesh.exchange.ply.export_ply(sphere_tm, encoding="ascii"), "ply"
    elif file_type == "ply-binary":
        data, ft = trimesh.exchange.ply.export_ply(sphere_tm, encoding="binary"), "ply"
    elif file_type == "stl-ascii":
        data, ft = trimesh.exchange.stl.export_stl_ascii(sphere_tm).encode(), "stl"
    elif file_type == "stl-binary":
        data, ft = trimesh.exchange.stl.export_stl(sphere_tm), "stl"
    else:
        data, ft = sphere_tm.export(file_type="glb"), "glb"
    cut = data[: int(len(data) * keep)]
    if file_type == "ply-ascii":
        cut = cut[: cut.rfind(b"\n") + 1]  # a cut inside the last number is undetectable in ASCII
    with pytest.raises(MeshValidationError, match="upload"):
        load_mesh_bytes(cut, file_type=ft, source="upload")


@pytest.mark.parametrize("file_type", ["obj", "ply", "stl", "glb"])
def test_mutated_files_never_raise_anything_else(sphere_tm, file_type):
    """Random byte corruption: a mesh or a MeshValidationError, nothing else."""
    small = trimesh.creation.icosphere(1)
    data = bytearray(
        small.export(file_type=file_type).encode()
        if file_type == "obj"
        else small.export(file_type=file_type)
    )
    rng = np.random.default_rng(11)
    for _ in range(60):
        mutated = bytearray(data)
        for pos in rng.integers(0, len(mutated), size=rng.integers(1, 8)):
            mutated[pos] = int(rng.integers(0, 256))
        try:
            mesh, report = load_mesh_bytes(bytes(mutated), file_type=file_type, source="m")
        except MeshValidationError:
            continue
        check_report(mesh, report)


def test_unknown_extension_lists_supported(tmp_path):
    path = tmp_path / "model.fbx"
    path.write_bytes(b"whatever")
    with pytest.raises(MeshValidationError) as err:
        load_mesh_file(path)
    for ext in (".obj", ".ply", ".stl", ".glb"):
        assert ext in str(err.value)
    with pytest.raises(MeshValidationError, match="supported"):
        load_mesh_bytes(b"x", file_type="3ds", source="u")


def test_oversize_rejected_before_parsing(tmp_path, sphere_tm, monkeypatch):
    data = sphere_tm.export(file_type="ply")
    path = tmp_path / "big.ply"
    path.write_bytes(data)

    def no_parse(*args, **kwargs):
        raise AssertionError("parsed an oversize file")

    monkeypatch.setattr(trimesh, "load_scene", no_parse)
    with pytest.raises(MeshValidationError, match="limit") as err:
        load_mesh_file(path, max_bytes=len(data) - 1)
    assert err.value.counts["n_bytes"] == len(data)
    with pytest.raises(MeshValidationError, match="limit"):
        load_mesh_bytes(data, file_type="ply", source="u", max_bytes=1000)


# =========================================================================== real data


@needs_data
def test_utah_teapot():
    mesh, report = load_mesh_file(TEAPOT)
    print("teapot:", report.to_dict())
    check_report(mesh, report)
    assert report.source == "teapot.ply"
    assert (report.n_vertices_in, report.n_faces_in) == (1177, 2256)
    assert report.n_faces_out > 2000
    assert report.normals_computed  # the PLY stores no normals
    # smooth normals agree with the face orientation everywhere
    v, f = mesh.vertices, mesh.faces
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    for k in range(3):
        assert np.all(np.einsum("ij,ij->i", cross, mesh.normals[f[:, k]]) > 0)


@needs_data
@pytest.mark.parametrize(
    "name", sorted(p.name for p in MITSUBA_MESHES.glob("*.obj")) if DATA.is_dir() else []
)
def test_mitsuba_cornell_box_meshes(name):
    mesh, report = load_mesh_file(MITSUBA_MESHES / name)
    check_report(mesh, report)
    assert mesh.n_faces >= 2
    assert np.all(mesh.vertices >= -1e-9) and np.all(mesh.vertices <= 560.0)
    if name in ("cbox_smallbox.obj", "cbox_largebox.obj"):
        assert (mesh.n_vertices, mesh.n_faces) == (24, 12)
        assert not report.normals_computed  # the files carry vn
        assert signed_volume(mesh) > 0  # closed and outward


@needs_data
def test_mcguire_cornell_box():
    mesh, report = load_mesh_file(MCGUIRE_ORIGINAL)
    check_report(mesh, report)
    # 8 quads (floor, ceiling, 3 walls, light... ) + 2 boxes x 6 quads = 36 triangles in; each box's
    # "Bottom Face" line repeats the "Right Face" indices, so 4 triangles are duplicates
    assert report.n_faces_in == 36
    assert report.duplicate_faces_removed == 4
    assert mesh.n_faces == 32
    np.testing.assert_allclose(mesh.vertices.min(axis=0), [-1.02, 0.0, -1.04])
    np.testing.assert_allclose(mesh.vertices.max(axis=0), [1.0, 1.99, 0.99])


@pytest.mark.parametrize("corrupt", [0, 1])
def test_bad_index_in_one_glb_primitive_cannot_alias_into_another(corrupt):
    """Per-geometry range check: after concatenation the bad index of the first mesh would be valid."""
    v, f = tetra()
    first = trimesh.Trimesh(v, f, process=False)
    second = trimesh.Trimesh(v + [3.0, 0, 0], f[[1, 0, 3, 2]], process=False)  # own index buffer
    scene = trimesh.Scene([first, second])
    data = scene.export(file_type="glb")
    mesh, _ = load_mesh_bytes(data, file_type="glb", source="ok.glb")
    assert mesh.n_faces == 8
    # corrupt the first primitive's index buffer in place: find its (uint) indices and bump one
    tree_len = int.from_bytes(data[12:16], "little")
    tree = json.loads(data[20 : 20 + tree_len])
    accessor = tree["accessors"][tree["meshes"][corrupt]["primitives"][0]["indices"]]
    view = tree["bufferViews"][accessor["bufferView"]]
    dtype = {5121: np.uint8, 5123: np.uint16, 5125: np.uint32}[accessor["componentType"]]
    bin_start = 20 + tree_len + 8 + view.get("byteOffset", 0) + accessor.get("byteOffset", 0)
    corrupted = bytearray(data)
    corrupted[bin_start : bin_start + np.dtype(dtype).itemsize] = np.array([4], dtype=dtype).tobytes()
    with pytest.raises(MeshValidationError) as err:
        load_mesh_bytes(bytes(corrupted), file_type="glb", source="bad.glb")
    assert err.value.counts["out_of_range_indices"] == 1


def test_truncated_ascii_ply_of_quads():
    """Quads triangulate into more faces than declared: only the row count shows the cut."""
    v = np.array([[x, y, 0.0] for y in range(4) for x in range(4)])
    quads = [[4 * y + x, 4 * y + x + 1, 4 * y + x + 5, 4 * y + x + 4] for y in range(3) for x in range(3)]
    data = ascii_ply(v, quads)
    mesh, report = load_mesh_bytes(data, file_type="ply", source="quads.ply")
    assert report.n_faces_in == 18 and mesh.n_faces == 18
    cut = data[: data.rstrip(b"\n").rfind(b"\n") + 1]  # drop the last quad
    cut = cut[: cut.rstrip(b"\n").rfind(b"\n") + 1]  # and the one before
    with pytest.raises(MeshValidationError, match="truncated"):
        load_mesh_bytes(cut, file_type="ply", source="quads.ply")
