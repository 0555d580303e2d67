"""The triangle mesh type every geometry producer returns."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TriMesh:
    """An indexed triangle mesh with smooth per-vertex normals.

    vertices: (n, 3) float64, finite.
    faces:    (m, 3) int32, every index in [0, n).
    normals:  (n, 3) float64, unit length (smooth shading normals).
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray

    def __post_init__(self) -> None:
        v, f, n = self.vertices, self.faces, self.normals
        if v.ndim != 2 or v.shape[1] != 3 or v.dtype != np.float64:
            raise ValueError(f"vertices must be (n, 3) float64, got {v.shape} {v.dtype}")
        if f.ndim != 2 or f.shape[1] != 3 or f.dtype != np.int32:
            raise ValueError(f"faces must be (m, 3) int32, got {f.shape} {f.dtype}")
        if n.shape != v.shape or n.dtype != np.float64:
            raise ValueError(f"normals must match vertices {v.shape} float64, got {n.shape} {n.dtype}")

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def n_faces(self) -> int:
        return int(self.faces.shape[0])

    def transformed(self, world_from_object: np.ndarray) -> TriMesh:
        """Apply a 4x4 affine transform; normals use the inverse transpose and are renormalised."""
        m = np.asarray(world_from_object, dtype=np.float64)
        if m.shape != (4, 4):
            raise ValueError("transform must be 4x4")
        lin = m[:3, :3]
        v = self.vertices @ lin.T + m[:3, 3]
        n = self.normals @ np.linalg.inv(lin)  # == (inv(lin).T @ n.T).T
        ln = np.linalg.norm(n, axis=1, keepdims=True)
        n = np.where(ln > 0, n / np.where(ln > 0, ln, 1.0), 0.0)
        f = self.faces
        if np.linalg.det(lin) < 0:  # a mirroring transform flips winding; keep faces outward
            f = f[:, ::-1].copy()
        return TriMesh(np.ascontiguousarray(v), np.ascontiguousarray(f), np.ascontiguousarray(n))
