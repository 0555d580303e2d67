"""Mesh files and mesh validation: the one place where outside geometry enters the engine.

Validation policy (:func:`validate_mesh`; every loader ends there)
-------------------------------------------------------------------
Steps run in this order; every removal is counted in the :class:`MeshReport`, nothing
is dropped silently (least of all later by Embree, which skips bad triangles without
telling anyone).

1. **Shape.** ``vertices`` must be ``(n, 3)`` real numbers, ``faces`` ``(m, 3)`` integers;
   anything else raises :class:`~engine.errors.MeshValidationError`.
2. **Index range.** A face index ``< 0`` or ``>= n`` *always* raises, whatever
   ``on_invalid`` says: a broken index buffer means the data is corrupt, and cleaning
   would hide that. The error's ``counts`` hold ``out_of_range_indices`` (index entries),
   ``negative_indices`` and ``faces_affected``.
3. **Non-finite vertices.** NaN/Inf coordinates, or ``|x| > 1e18`` (Embree silently
   ignores primitives with huge coordinates): with ``on_invalid="reject"`` any such vertex
   raises; with ``"clean"`` every face touching one is dropped (``nonfinite_faces_removed``).
4. **Degenerate faces** are always removed and counted: a repeated index, zero area in
   float64 (``|cross| <= 1e-12 * longest_edge**2``: coincident or collinear corners), or zero
   area once the vertices are cast to float32, which is what Embree intersects. They are
   common in real meshes (patch poles, STL exporters) and carry no surface. The float64
   threshold is relative to the triangle, not to the mesh's bounding box: a bbox-relative one
   would delete the small, valid triangles of a large mesh and open holes in it.
5. **Duplicate faces**, same vertex set whatever the order or winding, keep the first.
6. **Unreferenced vertices** (including those orphaned by steps 3-5) are removed.
7. **Normals.** A given normal that is finite and nonzero is renormalised and used as is.
   Every other vertex gets smooth, angle-weighted normals (Thürmer & Wüthrich 1998) over
   smoothing fans: the faces around a vertex *position* (so split seams and STL triangle soup
   shade smoothly) connected through shared edges that meet at less than 60 degrees. Where
   faces meet at a sharper crease (an STL cube, the teapot's handle joint) or only touch at
   the vertex, the vertex is split into one copy per fan (``crease_vertices_split``): a
   computed normal is never ~0 and never points behind its face (a corner whose fan normal
   would is given its face's normal instead).
8. **Duplicate vertices**, same position and same normal (to 1e-7), are merged
   (``duplicate_vertices_merged``), and faces made identical by that are removed (counted in
   ``duplicate_faces_removed``). Split and merged copies have bit-identical positions, so
   the surface stays watertight for Embree, which compares positions, not indices.
9. A mesh left without faces raises ``MeshValidationError("... no valid triangles")``.

Counts add up: ``n_faces_out = n_faces_in - nonfinite_faces_removed -
degenerate_faces_removed - duplicate_faces_removed`` and ``n_vertices_out = n_vertices_in
- unreferenced_vertices_removed - duplicate_vertices_merged + crease_vertices_split``.

Files
-----
:func:`load_mesh_file` / :func:`load_mesh_bytes` read OBJ, PLY, STL, glTF and GLB with
trimesh (``process=False``, materials and textures skipped), the format chosen by the
extension / ``file_type``. Scenes with several geometries are concatenated with their
node transforms applied. Vertex normals are kept only where the file stores them. Any
parse failure, wrong file type, truncation or size over ``max_bytes`` is a
``MeshValidationError`` whose ``source`` is the file name. Counts refer to the arrays the
format decodes to: STL stores three vertices per triangle, and trimesh's OBJ reader splits
vertices used with different ``vn``/``vt`` and drops vertices no face uses.

OBJ relative (negative) indices are resolved here before trimesh sees the text, because
trimesh resolves them against the end of the file rather than the current line (this turns
the McGuire Cornell box into eight copies of the light); an index of 0 or out of range is
counted and rejected like any other bad index.
"""

from __future__ import annotations

import dataclasses
import io
import json
import re
import urllib.parse
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from engine.errors import InvalidInputError, MeshValidationError
from engine.geometry.mesh import TriMesh

__all__ = [
    "MeshReport",
    "validate_mesh",
    "load_mesh_file",
    "load_mesh_bytes",
    "SUPPORTED_MESH_TYPES",
    "DEFAULT_MAX_MESH_BYTES",
]

OnInvalid = Literal["reject", "clean"]

SUPPORTED_MESH_TYPES: tuple[str, ...] = ("obj", "ply", "stl", "glb", "gltf")
DEFAULT_MAX_MESH_BYTES = 256 * 2**20
MAX_COORDINATE = 1e18  # Embree ignores primitives beyond this without an error
DEGENERATE_REL_AREA = 1e-12  # |cross| <= this * longest_edge**2 counts as zero area
CREASE_COS = 0.5  # faces meeting at more than 60 degrees do not smooth into each other
_NORMAL_MERGE_QUANTUM = 1e-7


@dataclass(frozen=True)
class MeshReport:
    """What validation found and changed; counts are exact, never estimates."""

    source: str
    n_vertices_in: int
    n_faces_in: int
    n_vertices_out: int
    n_faces_out: int
    out_of_range_indices: int  # always 0 in a report: out-of-range indices raise
    nonfinite_vertices: int  # NaN/Inf or |coordinate| > 1e18
    degenerate_faces_removed: int
    duplicate_faces_removed: int
    unreferenced_vertices_removed: int
    normals_computed: bool  # True when any vertex normal was computed rather than given
    nonfinite_faces_removed: int = 0  # faces dropped for touching a non-finite vertex ("clean")
    duplicate_vertices_merged: int = 0  # same position and normal
    crease_vertices_split: int = 0  # extra copies made where computed normals meet at a crease

    def to_dict(self) -> dict[str, object]:
        return dataclasses.asdict(self)


# =========================================================================== validation


def _fail(source: str, message: str, **counts: int) -> MeshValidationError:
    return MeshValidationError(f"{source}: {message}", source=source, counts=counts)


def _as_vertices(vertices: object, source: str) -> np.ndarray:
    try:
        v = np.asarray(vertices)
    except (TypeError, ValueError) as exc:
        raise _fail(source, f"vertices are not an (n, 3) numeric array ({exc})") from exc
    if v.dtype.kind not in "fiu" or v.ndim != 2 or v.shape[1] != 3:
        raise _fail(source, f"vertices must be an (n, 3) array of numbers, got shape {v.shape} {v.dtype}")
    return v.astype(np.float64, copy=False)


def _as_faces(faces: object, source: str) -> np.ndarray:
    try:
        f = np.asarray(faces)
    except (TypeError, ValueError) as exc:
        raise _fail(source, f"faces are not an (m, 3) integer array ({exc})") from exc
    if f.size == 0 and f.dtype.kind in "fiu":  # "no faces" is reported as such, not as a shape error
        return np.zeros((0, 3), dtype=np.int64)
    if f.dtype.kind not in "iu" or f.ndim != 2 or f.shape[1] != 3:
        raise _fail(source, f"faces must be an (m, 3) array of integers, got shape {f.shape} {f.dtype}")
    return f


def _unique_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(first, inverse)`` for the distinct rows of an integer array, groups in key order.

    ``first[g]`` is the lowest row index of group ``g``. Much faster than
    ``np.unique(axis=0)``, which sorts opaque byte strings.
    """
    if rows.shape[0] == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    order = np.lexsort(rows.T[::-1])  # stable: equal rows stay in index order
    ordered = rows[order]
    new = np.r_[True, np.any(ordered[1:] != ordered[:-1], axis=1)]
    inverse = np.empty(rows.shape[0], dtype=np.int64)
    inverse[order] = np.cumsum(new) - 1
    return order[new], inverse


def _first_occurrence_unique(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(keep, inverse)``: indices of first occurrences in original order and, per row, its new id."""
    if rows.shape[0] == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    first, inverse = _unique_rows(rows)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return first[order], rank[inverse.reshape(-1)]


def _unit_rows(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows scaled to unit length and their original lengths (zero rows stay zero)."""
    length = np.linalg.norm(a, axis=1)
    safe = np.where(length > 0, length, 1.0)
    return a / safe[:, None], length


def _corner_angles(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """(m, 3) interior angle at each corner; atan2 keeps slivers accurate."""
    p = v[f]  # (m, 3, 3)
    angles = np.empty(f.shape, dtype=np.float64)
    for k in range(3):
        a = p[:, (k + 1) % 3] - p[:, k]
        b = p[:, (k + 2) % 3] - p[:, k]
        angles[:, k] = np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.einsum("ij,ij->i", a, b))
    return angles


def _position_ids(v: np.ndarray) -> np.ndarray:
    """Same id for vertices at the same position (-0.0 and 0.0 alike)."""
    bits = np.ascontiguousarray(v + 0.0).view(np.int64)  # +0.0 turns -0.0 into 0.0; no NaN here
    return _unique_rows(bits)[1]


def _group_pairs(starts: np.ndarray, sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All ordered pairs (i < j) of sorted positions inside each group ``[start, start + size)``."""
    row_start = np.repeat(starts, sizes)
    row_size = np.repeat(sizes, sizes)
    rows = row_start + (np.arange(row_start.size) - np.repeat(np.cumsum(sizes) - sizes, sizes))
    pi = np.repeat(rows, row_size)
    pj = np.repeat(row_start, row_size) + (
        np.arange(pi.size) - np.repeat(np.cumsum(row_size) - row_size, row_size)
    )
    keep = pi < pj
    return pi[keep], pj[keep]


def _corner_normals(v: np.ndarray, f: np.ndarray, face_unit: np.ndarray) -> np.ndarray:
    """(m, 3, 3) unit smooth normal at each face corner, split at creases.

    The corners around a vertex position form smoothing fans: two corners join when their
    faces share an edge (by position, so split seams and STL soup join too) and meet at less
    than the crease angle. Each fan gets the angle-weighted sum (Thürmer & Wüthrich 1998) of
    its faces' normals; a corner whose fan normal does not point in front of its own face
    falls back to the face normal.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    m = f.shape[0]
    pos = _position_ids(v)[f]  # (m, 3) position id of each corner
    corner = np.arange(3 * m).reshape(m, 3)
    # half-edges k -> k+1 of every face, keyed by their unordered pair of positions
    a_pos, b_pos = pos.reshape(-1), pos[:, [1, 2, 0]].reshape(-1)
    a_corner, b_corner = corner.reshape(-1), corner[:, [1, 2, 0]].reshape(-1)
    he_face = np.repeat(np.arange(m), 3)
    key = np.stack([np.minimum(a_pos, b_pos), np.maximum(a_pos, b_pos)], axis=1)
    order = np.lexsort((key[:, 1], key[:, 0]))
    ks = key[order]
    starts = np.flatnonzero(np.r_[True, np.any(ks[1:] != ks[:-1], axis=1)])
    sizes = np.diff(np.r_[starts, ks.shape[0]])
    # edges shared by more than 16 faces are junk junctions: treat them as creases
    shared = (sizes >= 2) & (sizes <= 16)
    pi, pj = _group_pairs(starts[shared], sizes[shared])
    h1, h2 = order[pi], order[pj]
    smooth = np.einsum("ij,ij->i", face_unit[he_face[h1]], face_unit[he_face[h2]]) > CREASE_COS
    h1, h2 = h1[smooth], h2[smooth]
    same_dir = a_pos[h1] == a_pos[h2]  # consistently wound neighbours traverse the edge oppositely
    u = np.concatenate([a_corner[h1], b_corner[h1]])
    w = np.concatenate(
        [np.where(same_dir, a_corner[h2], b_corner[h2]), np.where(same_dir, b_corner[h2], a_corner[h2])]
    )
    graph = coo_matrix((np.ones(u.size, dtype=np.int8), (u, w)), shape=(3 * m, 3 * m))
    _, fan = connected_components(graph, directed=False)

    weighted = face_unit[he_face] * _corner_angles(v, f).reshape(-1, 1)
    fan_sum = np.stack([np.bincount(fan, weights=weighted[:, k]) for k in range(3)], axis=1)
    normals, length = _unit_rows(fan_sum[fan])
    own = face_unit[he_face]
    fallback = ~(np.einsum("ij,ij->i", normals, own) > 0) | (length == 0)
    normals[fallback] = own[fallback]
    return normals.reshape(m, 3, 3)


def _bad_index_counts(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """[out-of-range index entries, negative ones, faces affected] for an integer (m, 3) array."""
    negative = faces < 0 if faces.dtype.kind == "i" else np.zeros(faces.shape, dtype=bool)
    bad = negative | (faces >= n_vertices)
    return np.array([bad.sum(), negative.sum(), bad.any(axis=1).sum()], dtype=np.int64)


def _raise_on_bad_indices(counts: np.ndarray, n_vertices: int, n_faces: int, source: str) -> None:
    n_bad, n_neg, n_faces_bad = (int(c) for c in counts)
    if n_bad:
        raise _fail(
            source,
            f"{n_bad} face indices out of range [0, {n_vertices}) ({n_neg} negative) in {n_faces_bad} of "
            f"{n_faces} faces; the index buffer is corrupt",
            out_of_range_indices=n_bad,
            negative_indices=n_neg,
            faces_affected=n_faces_bad,
        )


def validate_mesh(
    vertices: object,
    faces: object,
    normals: object | None = None,
    *,
    source: str,
    on_invalid: OnInvalid = "reject",
) -> tuple[TriMesh, MeshReport]:
    """Check and clean a triangle mesh; see the module docstring for the policy.

    vertices: (n, 3) real; faces: (m, 3) integer; normals: (n, 3) or None (rows that are
    non-finite or zero are recomputed). Returns the cleaned :class:`TriMesh` (float64
    vertices, int32 faces, unit normals) and a :class:`MeshReport`.
    Raises :class:`MeshValidationError` (with ``source`` and ``counts``).
    """
    if on_invalid not in ("reject", "clean"):
        raise InvalidInputError(f"on_invalid must be 'reject' or 'clean', got {on_invalid!r}")
    v = _as_vertices(vertices, source)
    f_raw = _as_faces(faces, source)
    n_in, m_in = int(v.shape[0]), int(f_raw.shape[0])

    # 2. index range: always fatal
    _raise_on_bad_indices(_bad_index_counts(f_raw, n_in), n_in, m_in, source)
    f = f_raw.astype(np.int64, copy=False)

    # 3. non-finite or huge coordinates
    finite = np.all(np.isfinite(v), axis=1)
    with np.errstate(invalid="ignore"):
        huge = finite & np.any(np.abs(v) > MAX_COORDINATE, axis=1)
    invalid_vertex = ~finite | huge
    n_nonfinite = int(invalid_vertex.sum())
    nonfinite_faces = 0
    if n_nonfinite:
        if on_invalid == "reject":
            raise _fail(
                source,
                f"{n_nonfinite} of {n_in} vertices are non-finite ({int((~finite).sum())} NaN/Inf, "
                f"{int(huge.sum())} with |coordinate| > {MAX_COORDINATE:g}); pass on_invalid='clean' "
                f"to drop the faces that use them",
                nonfinite_vertices=n_nonfinite,
                nan_inf_vertices=int((~finite).sum()),
                huge_vertices=int(huge.sum()),
            )
        touched = invalid_vertex[f].any(axis=1)
        nonfinite_faces = int(touched.sum())
        f = f[~touched]
        v = np.where(invalid_vertex[:, None], 0.0, v)  # orphaned now; keeps the arithmetic below quiet

    # 4. degenerate faces
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    p = v[f]
    cross64 = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    longest = np.max(np.linalg.norm(p - p[:, [1, 2, 0]], axis=2), axis=1)
    # Relative to the triangle's own longest edge, not the mesh's bounding box: a bbox-relative
    # threshold would delete every small triangle of a large mesh (1 cm tiles on a 1 km terrain)
    # and punch real holes; this catches coincident and collinear corners (sin(angle) <= 1e-12).
    zero64 = np.linalg.norm(cross64, axis=1) <= DEGENERATE_REL_AREA * longest**2
    p32 = p.astype(np.float32)
    cross32 = np.cross(p32[:, 1] - p32[:, 0], p32[:, 2] - p32[:, 0])
    zero32 = ~np.any(cross32 != 0, axis=1) | ~np.all(np.isfinite(cross32), axis=1)
    degenerate = repeated | zero64 | zero32
    n_degenerate = int(degenerate.sum())
    f, cross64 = f[~degenerate], cross64[~degenerate]

    # 5. duplicate faces (same vertex set)
    keep, _ = _first_occurrence_unique(np.sort(f, axis=1))
    keep.sort()
    n_duplicate = int(f.shape[0] - keep.size)
    f, cross64 = f[keep], cross64[keep]

    if f.shape[0] == 0:
        raise _fail(
            source,
            f"no valid triangles ({m_in} faces in: {nonfinite_faces} non-finite, {n_degenerate} degenerate, "
            f"{n_duplicate} duplicate)",
            n_faces_in=m_in,
            nonfinite_faces_removed=nonfinite_faces,
            degenerate_faces_removed=n_degenerate,
            duplicate_faces_removed=n_duplicate,
        )

    # 6. unreferenced vertices
    referenced = np.zeros(n_in, dtype=bool)
    referenced[f.reshape(-1)] = True
    n_unreferenced = int(n_in - referenced.sum())
    remap = np.cumsum(referenced) - 1
    f = remap[f]
    v = v[referenced]

    # 7. normals, per corner: given ones (renormalised) or smooth ones split at creases
    given = None
    if normals is not None:
        try:
            nrm = np.asarray(normals, dtype=np.float64)
        except (TypeError, ValueError):
            nrm = None
        if nrm is not None and nrm.shape == (n_in, 3):
            given = nrm[referenced]
    ok = np.zeros(v.shape[0], dtype=bool)
    unit_given = np.zeros_like(v)
    if given is not None:
        with np.errstate(invalid="ignore", over="ignore"):
            unit_given, length = _unit_rows(np.where(np.isfinite(given), given, 0.0))
        ok = np.all(np.isfinite(given), axis=1) & (length > 0) & np.all(np.isfinite(unit_given), axis=1)
    normals_computed = not bool(np.all(ok))
    corner_n = unit_given[f]  # (m, 3, 3)
    if normals_computed:
        face_unit, _ = _unit_rows(cross64)
        computed = _corner_normals(v, f, face_unit)
        use = ~ok[f]
        corner_n[use] = computed[use]

    # 8. one output vertex per distinct (position, normal) among the corners: merges duplicate
    # vertices, splits computed normals at creases; original vertex order is kept
    corner_vertex = f.reshape(-1)
    key = np.column_stack(
        [
            _position_ids(v)[corner_vertex],
            np.round(corner_n.reshape(-1, 3) / _NORMAL_MERGE_QUANTUM).astype(np.int64),
        ]
    )
    first_corner, out_of_corner = _unique_rows(key)
    n_out_v = first_corner.size
    lowest_vertex = np.full(n_out_v, v.shape[0], dtype=np.int64)
    np.minimum.at(lowest_vertex, out_of_corner, corner_vertex)
    order = np.lexsort((first_corner, lowest_vertex))
    rank = np.empty(n_out_v, dtype=np.int64)
    rank[order] = np.arange(n_out_v)
    out_of_corner = rank[out_of_corner]
    n_pairs = _unique_rows(np.column_stack([corner_vertex, out_of_corner]))[0].size
    n_split = int(n_pairs - v.shape[0])
    n_merged = int(v.shape[0] + n_split - n_out_v)
    source_corner = first_corner[order]
    v = v[corner_vertex[source_corner]]
    out_normals = corner_n.reshape(-1, 3)[source_corner]
    f = out_of_corner.reshape(-1, 3)
    if n_merged:  # merging can make faces identical
        keep, _ = _first_occurrence_unique(np.sort(f, axis=1))
        keep.sort()
        n_duplicate += int(f.shape[0] - keep.size)
        f = f[keep]

    if v.shape[0] > np.iinfo(np.int32).max:
        raise _fail(source, f"{v.shape[0]} vertices exceed the int32 index range", n_vertices=int(v.shape[0]))
    mesh = TriMesh(
        np.ascontiguousarray(v, dtype=np.float64),
        np.ascontiguousarray(f, dtype=np.int32),
        np.ascontiguousarray(out_normals, dtype=np.float64),
    )
    report = MeshReport(
        source=source,
        n_vertices_in=n_in,
        n_faces_in=m_in,
        n_vertices_out=mesh.n_vertices,
        n_faces_out=mesh.n_faces,
        out_of_range_indices=0,
        nonfinite_vertices=n_nonfinite,
        degenerate_faces_removed=n_degenerate,
        duplicate_faces_removed=n_duplicate,
        unreferenced_vertices_removed=n_unreferenced,
        normals_computed=normals_computed,
        nonfinite_faces_removed=nonfinite_faces,
        duplicate_vertices_merged=n_merged,
        crease_vertices_split=n_split,
    )
    return mesh, report


# =========================================================================== file formats


def _normalise_type(file_type: str, source: str) -> str:
    ft = str(file_type).strip().lower().lstrip(".")
    if ft not in SUPPORTED_MESH_TYPES:
        raise _fail(
            source,
            f"unsupported mesh file type {file_type!r}; supported: "
            + ", ".join(f".{t}" for t in SUPPORTED_MESH_TYPES),
        )
    return ft


def _as_utf8_text(data: bytes, source: str, kind: str) -> bytes:
    """Text formats: refuse binary data, accept any 8-bit encoding (only ASCII matters)."""
    if b"\x00" in data:
        raise _fail(source, f"not a {kind} file: it contains binary data (NUL bytes)")
    try:
        data.decode("utf-8")
        return data
    except UnicodeDecodeError:
        return data.decode("latin-1").encode("utf-8")


# --------------------------------------------------------------------------- OBJ

_OBJ_NEEDS_AUDIT = re.compile(rb"(?m)^[ \t]*f(?=[ \t])[^\n]*?[ \t/](?:-|0+(?:[ \t/\r]|$))")
_OBJ_KINDS = {b"v": 0, b"vt": 1, b"vn": 2}


def _obj_audit(text: bytes, source: str) -> bytes:
    """Resolve relative (negative) OBJ indices and reject 0 / out-of-range ones, with counts.

    Positive indices are checked against the file's final counts, negative ones against
    the elements defined before the face line, as the OBJ specification says.
    """
    text = text.replace(b"\r\n", b"\n").replace(b"\\\n", b"")
    lines = text.split(b"\n")
    totals = [0, 0, 0]
    for line in lines:
        word = line.split(None, 1)[0] if line.strip() else b""
        if word in _OBJ_KINDS:
            totals[_OBJ_KINDS[word]] += 1
    counts = [0, 0, 0]
    bad = zero = faces_affected = 0
    out = []
    for line in lines:
        stripped = line.lstrip()
        word = stripped.split(None, 1)[0] if stripped else b""
        if word in _OBJ_KINDS:
            counts[_OBJ_KINDS[word]] += 1
            out.append(line)
            continue
        if word != b"f":
            out.append(line)
            continue
        tokens = stripped.split()[1:]
        new_tokens, face_bad = [], False
        for tok in tokens:
            parts = tok.split(b"/")
            new_parts = []
            for k, part in enumerate(parts[:3]):
                if not part:
                    new_parts.append(part)
                    continue
                try:
                    idx = int(part)
                except ValueError:
                    bad += 1
                    face_bad = True
                    new_parts.append(part)
                    continue
                if idx < 0:
                    idx = counts[k] + idx + 1  # relative to what is defined so far
                    if idx < 1:
                        bad += 1
                        face_bad = True
                elif idx == 0:
                    zero += 1
                    bad += 1
                    face_bad = True
                elif idx > totals[k]:
                    bad += 1
                    face_bad = True
                new_parts.append(str(idx).encode())
            new_tokens.append(b"/".join(new_parts))
        faces_affected += face_bad
        out.append(b"f " + b" ".join(new_tokens))
    if bad:
        raise _fail(
            source,
            f"{bad} OBJ face indices out of range ({zero} zero; OBJ indices start at 1) in {faces_affected} "
            f"faces; the index data is corrupt",
            out_of_range_indices=bad,
            zero_indices=zero,
            faces_affected=faces_affected,
        )
    return b"\n".join(out)


# --------------------------------------------------------------------------- PLY / STL sniffing

_PLY_ELEMENT = re.compile(rb"^element\s+(\S+)\s+(\d+)\s*$")


def _ply_header(data: bytes, source: str) -> tuple[str, dict[str, int], int]:
    """(format, {element: count}, offset of the body)."""
    if not data.startswith(b"ply"):
        raise _fail(source, "not a PLY file: missing the 'ply' magic line")
    m = re.search(rb"end_header[ \t]*\r?\n", data[: 1 << 20])
    if m is None:
        raise _fail(source, "PLY header has no end_header line (not a PLY file, or truncated)")
    fmt, elements = "", {}
    for raw in data[: m.start()].splitlines():
        line = raw.strip()
        if line.startswith(b"format"):
            fmt = line.split()[1].decode("ascii", "replace") if len(line.split()) > 1 else ""
        e = _PLY_ELEMENT.match(line)
        if e:
            elements[e.group(1).decode("ascii", "replace")] = int(e.group(2))
    return fmt, elements, m.end()


def _check_ply_body(data: bytes, source: str) -> tuple[str, dict[str, int]]:
    fmt, elements, body_at = _ply_header(data, source)
    if fmt == "ascii":
        body = data[body_at:]
        rows = body.count(b"\n") + (1 if body and not body.endswith(b"\n") else 0)
        declared = sum(elements.values())
        if rows < declared:
            raise _fail(
                source,
                f"truncated ASCII PLY: the header declares {declared} element rows, the file has {rows}",
                declared_rows=declared,
                rows=rows,
            )
    return fmt, elements


def _check_stl(data: bytes, source: str) -> bytes:
    """Binary STL must match its triangle count; otherwise it must be complete ASCII STL."""
    if len(data) >= 84:
        count = int.from_bytes(data[80:84], "little")
        if len(data) == 84 + 50 * count:
            return data
    if data.lstrip()[:5].lower() != b"solid" or b"\x00" in data:
        size_note = ""
        if len(data) >= 84:
            count = int.from_bytes(data[80:84], "little")
            size_note = f" ({len(data)} bytes, a binary STL of {count} triangles needs {84 + 50 * count})"
        raise _fail(
            source, f"not a valid STL file: neither binary STL with a matching size nor ASCII{size_note}"
        )
    if b"endsolid" not in data[-4096:].lower():
        raise _fail(source, "truncated ASCII STL: no 'endsolid' at the end")
    return _as_utf8_text(data, source, "ASCII STL")


# --------------------------------------------------------------------------- resolvers (glTF buffers)


def _resolver_classes():
    from trimesh.resolvers import Resolver

    class NoExternalResolver(Resolver):
        """Uploads may not reference other files: that would read the server's disk."""

        def __init__(self) -> None:
            pass

        def get(self, key: str) -> bytes:
            raise MeshValidationError(
                f"external file reference {key!r} is not allowed here; use GLB or embed buffers as data: URIs"
            )

        def write(self, name: str, data: object) -> None:
            raise NotImplementedError

        def namespaced(self, namespace: str) -> NoExternalResolver:
            return self

        def keys(self) -> list[str]:
            return []

    class DirectoryResolver(Resolver):
        """Files next to a glTF, never outside its directory, within a byte budget."""

        def __init__(self, directory: Path, budget: int) -> None:
            self.directory = directory.resolve()
            self.budget = budget

        def get(self, key: str) -> bytes:
            target = (self.directory / urllib.parse.unquote(key)).resolve()
            if not target.is_relative_to(self.directory):
                raise MeshValidationError(f"external reference {key!r} points outside the file's directory")
            size = target.stat().st_size
            if size > self.budget:
                raise MeshValidationError(f"external buffer {key!r} exceeds the size limit")
            self.budget -= size
            return target.read_bytes()

        def write(self, name: str, data: object) -> None:
            raise NotImplementedError

        def namespaced(self, namespace: str) -> DirectoryResolver:
            return DirectoryResolver(self.directory / namespace, self.budget)

        def keys(self) -> list[str]:
            return []

    return NoExternalResolver, DirectoryResolver


# --------------------------------------------------------------------------- trimesh scene -> arrays


def _file_normals(geom: object) -> np.ndarray | None:
    """Vertex normals only if the file stored them (never trimesh's lazily computed ones)."""
    try:
        cache = geom._cache  # type: ignore[attr-defined]
        if "vertex_normals" not in cache:
            return None
        values = np.asarray(cache["vertex_normals"], dtype=np.float64)
    except Exception:  # trimesh internals changed: compute our own
        return None
    if values.shape != np.shape(geom.vertices):  # type: ignore[attr-defined]
        return None
    return values


def _scene_arrays(scene: object, source: str) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Concatenate every triangle geometry instance, node transforms applied."""
    import trimesh

    verts, faces, norms = [], [], []
    any_normals = False
    offset = 0
    bad_indices = np.zeros(3, dtype=np.int64)  # per geometry: after concatenation they could alias
    for node in scene.graph.nodes_geometry:  # type: ignore[attr-defined]
        world_from_node, geom_name = scene.graph[node]  # type: ignore[attr-defined]
        geom = scene.geometry[geom_name]  # type: ignore[attr-defined]
        if not isinstance(geom, trimesh.Trimesh):
            continue  # points and lines carry no surface
        v = np.asarray(geom.vertices, dtype=np.float64).reshape(-1, 3)
        f = np.asarray(geom.faces)
        if f.size == 0:
            continue
        f = f.reshape(-1, 3)
        bad_indices += _bad_index_counts(f, v.shape[0])
        nrm = _file_normals(geom)
        t = np.asarray(world_from_node, dtype=np.float64)
        if not np.array_equal(t, np.eye(4)):
            if not np.all(np.isfinite(t)):
                raise _fail(source, f"node {node!r} has a non-finite transform")
            lin = t[:3, :3]
            v = v @ lin.T + t[:3, 3]
            det = float(np.linalg.det(lin))
            if nrm is not None:
                nrm = nrm @ np.linalg.inv(lin) if det != 0.0 else None  # inverse transpose
            if det < 0:
                f = f[:, ::-1]  # a mirroring transform flips winding
        verts.append(v)
        faces.append(f.astype(np.int64) + offset)
        norms.append(nrm if nrm is not None else np.full(v.shape, np.nan))
        any_normals |= nrm is not None
        offset += v.shape[0]
    if not faces:
        raise _fail(source, "the file contains no triangles")
    _raise_on_bad_indices(bad_indices, offset, sum(len(f) for f in faces), source)
    return np.concatenate(verts), np.concatenate(faces), (np.concatenate(norms) if any_normals else None)


# --------------------------------------------------------------------------- public loaders


def _load(
    data: bytes,
    ft: str,
    source: str,
    on_invalid: OnInvalid,
    max_bytes: int,
    directory: Path | None,
) -> tuple[TriMesh, MeshReport]:
    import trimesh

    if len(data) > max_bytes:
        raise _fail(
            source,
            f"mesh file is {len(data)} bytes, over the {max_bytes}-byte limit",
            n_bytes=len(data),
            max_bytes=max_bytes,
        )
    if not data:
        raise _fail(source, "the file is empty")
    no_external, in_directory = _resolver_classes()
    resolver = in_directory(directory, max_bytes - len(data)) if directory is not None else no_external()
    kwargs: dict[str, object] = {"process": False, "skip_materials": True}
    ply_elements: dict[str, int] = {}
    if ft == "obj":
        data = _as_utf8_text(data, source, "OBJ")
        if _OBJ_NEEDS_AUDIT.search(data):
            data = _obj_audit(data, source)
        kwargs.update(maintain_order=False, group_material=True)
    elif ft == "ply":
        _, ply_elements = _check_ply_body(data, source)
        kwargs.update(fix_texture=False)
    elif ft == "stl":
        data = _check_stl(data, source)
    elif ft == "glb":
        if data[:4] != b"glTF":
            raise _fail(source, "not a GLB file: missing the 'glTF' magic bytes")
    elif ft == "gltf":
        try:
            json.loads(data)
        except ValueError as exc:
            raise _fail(source, f"not a glTF file: invalid JSON ({exc})") from exc

    try:
        scene = trimesh.load_scene(io.BytesIO(data), file_type=ft, resolver=resolver, **kwargs)
    except MeshValidationError as exc:
        raise _fail(source, str(exc), **exc.counts) from exc
    except IndexError as exc:
        if ft == "obj":  # trimesh indexes first and asks later: count what is wrong
            _obj_audit(data, source)
        raise _fail(source, f"cannot parse {ft.upper()} data: index out of range ({exc})") from exc
    except Exception as exc:  # any parser failure is a bad file, never a crash
        raise _fail(source, f"cannot parse {ft.upper()} data: {type(exc).__name__}: {exc}") from exc

    try:
        vertices, faces, normals = _scene_arrays(scene, source)
    except MeshValidationError:
        raise
    except Exception as exc:
        raise _fail(source, f"cannot read {ft.upper()} geometry: {type(exc).__name__}: {exc}") from exc

    if ft == "ply" and "vertex" in ply_elements and vertices.shape[0] != ply_elements["vertex"]:
        raise _fail(
            source,
            f"PLY header declares {ply_elements['vertex']} vertices, {vertices.shape[0]} were read "
            f"(truncated or corrupt)",
            declared_vertices=ply_elements["vertex"],
            read_vertices=int(vertices.shape[0]),
        )
    if ft == "ply" and faces.shape[0] < ply_elements.get("face", 0):
        raise _fail(
            source,
            f"PLY header declares {ply_elements['face']} faces, {faces.shape[0]} triangles were read "
            f"(truncated or corrupt)",
            declared_faces=ply_elements["face"],
            read_faces=int(faces.shape[0]),
        )
    return validate_mesh(vertices, faces, normals, source=source, on_invalid=on_invalid)


def load_mesh_bytes(
    data: bytes,
    *,
    file_type: str,
    source: str,
    on_invalid: OnInvalid = "reject",
    max_bytes: int = DEFAULT_MAX_MESH_BYTES,
) -> tuple[TriMesh, MeshReport]:
    """Load an uploaded mesh held in memory (``file_type``: obj, ply, stl, glb, gltf).

    glTF may not reference external files (only ``data:`` URIs); use GLB for uploads.
    ``source`` names the upload in errors and in the report.
    """
    if on_invalid not in ("reject", "clean"):
        raise InvalidInputError(f"on_invalid must be 'reject' or 'clean', got {on_invalid!r}")
    ft = _normalise_type(file_type, source)
    if not isinstance(data, bytes | bytearray | memoryview):
        raise _fail(source, f"mesh data must be bytes, got {type(data).__name__}")
    return _load(bytes(data), ft, source, on_invalid, max_bytes, directory=None)


def load_mesh_file(
    path: str | Path,
    *,
    on_invalid: OnInvalid = "reject",
    max_bytes: int = DEFAULT_MAX_MESH_BYTES,
) -> tuple[TriMesh, MeshReport]:
    """Load a mesh file; the format comes from the extension (.obj .ply .stl .glb .gltf).

    A .gltf may reference buffers in its own directory (counted against ``max_bytes``).
    Errors name the file (``source`` = file name). A missing file raises ``FileNotFoundError``.
    """
    if on_invalid not in ("reject", "clean"):
        raise InvalidInputError(f"on_invalid must be 'reject' or 'clean', got {on_invalid!r}")
    p = Path(path)
    source = p.name
    ft = _normalise_type(p.suffix, source) if p.suffix else _normalise_type("", source)
    size = p.stat().st_size
    if size > max_bytes:
        raise _fail(
            source,
            f"mesh file is {size} bytes, over the {max_bytes}-byte limit",
            n_bytes=size,
            max_bytes=max_bytes,
        )
    with p.open("rb") as fh:
        data = fh.read(max_bytes + 1)  # the file may grow between stat and read
    return _load(data, ft, source, on_invalid, max_bytes, directory=p.parent)
