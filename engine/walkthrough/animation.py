"""Keyframed animation: the runtime scene at any time of the animation interval.

Engine-owned types (no ``api_schemas`` import; ``workers/scene_loader.load_animated_scene``
converts a schema scene). Interpolation (docs/scene-format.md, Animation):

- object transforms: each keyframe's 4x4 affine matrix is split into translation ``T``, a
  proper rotation ``R`` and a symmetric stretch ``P`` (``M = T R P``; a TRS keyframe gives
  ``P = diag(scale)``, an explicit matrix its polar decomposition, a mirroring matrix a
  negative ``P``). Between keyframes ``T`` and ``P`` are interpolated linearly and ``R`` by
  quaternion slerp (shortest arc); before the first and after the last keyframe the
  keyframe is held. A keyframe replaces the object's own transform.
- lights: position (point light position, rect light corner) and intensity (the light's
  emission) are interpolated linearly per component, each over the keyframes that set it,
  held outside them.

``AnimatedScene.scene_at(t)`` rebuilds the runtime scene at ``t``: only animated objects are
re-transformed (their local meshes are kept); static objects keep their world-space meshes.
A scene with nothing animated returns the same ``RuntimeScene`` object for every ``t``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import polar
from scipy.spatial.transform import Rotation, Slerp

from engine.errors import InvalidInputError
from engine.geometry.mesh import TriMesh
from engine.scene import LightTable, MaterialTable, RuntimeScene, SceneObjectPart, build_runtime_scene

__all__ = ["AnimatedScene", "LightTrack", "TransformTrack", "decompose_affine"]

# relative change below which two states count as equal (time-coherence tests)
_SAME_REL = 1e-12


def decompose_affine(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(translation (3,), rotation quaternion xyzw (4,), stretch (3, 3)) with
    ``m[:3, :3] == R @ P``, ``det(R) = +1`` (a mirror goes into ``P``)."""
    m = np.asarray(m, dtype=np.float64)
    if m.shape != (4, 4):
        raise InvalidInputError("transform must be a 4x4 matrix")
    lin = m[:3, :3]
    u, p = polar(lin)  # lin = u @ p, u orthogonal, p symmetric positive semidefinite
    if np.linalg.det(u) < 0:
        u, p = -u, -p
    return m[:3, 3].copy(), Rotation.from_matrix(u).as_quat(), p


@dataclass(frozen=True)
class TransformTrack:
    """Keyframed world-from-local transform of one object.

    times (k,) strictly increasing; translate (k, 3); quat (k, 4) xyzw; stretch (k, 3, 3)."""

    object_index: int
    times: np.ndarray
    translate: np.ndarray
    quat: np.ndarray
    stretch: np.ndarray
    _slerp: Slerp | None = field(default=None, compare=False, repr=False)

    @staticmethod
    def from_matrices(object_index: int, times: list[float] | np.ndarray,
                      matrices: list[np.ndarray]) -> TransformTrack:
        t = np.asarray(times, dtype=np.float64)
        if t.ndim != 1 or t.size == 0 or t.size != len(matrices):
            raise InvalidInputError("a transform track needs one matrix per keyframe time")
        if np.any(np.diff(t) <= 0):
            raise InvalidInputError("keyframe times must increase strictly")
        parts = [decompose_affine(m) for m in matrices]
        q = np.array([p[1] for p in parts])
        for i in range(1, len(q)):  # shortest arc: keep consecutive quaternions in one hemisphere
            if np.dot(q[i], q[i - 1]) < 0:
                q[i] = -q[i]
        slerp = Slerp(t, Rotation.from_quat(q)) if t.size >= 2 else None
        return TransformTrack(object_index, t, np.array([p[0] for p in parts]), q,
                              np.array([p[2] for p in parts]), slerp)

    def matrix_at(self, time: float) -> np.ndarray:
        """World-from-local 4x4 matrix at ``time`` (held outside the keyframes)."""
        t = self.times
        if time <= t[0] or t.size == 1:
            i, a = 0, 0.0
        elif time >= t[-1]:
            i, a = t.size - 2, 1.0
        else:
            i = int(np.searchsorted(t, time, side="right") - 1)
            a = (time - t[i]) / (t[i + 1] - t[i])
        m = np.eye(4)
        if t.size == 1:
            rot = Rotation.from_quat(self.quat[0]).as_matrix()
            m[:3, :3] = rot @ self.stretch[0]
            m[:3, 3] = self.translate[0]
            return m
        if a == 0.0:  # exact at keyframes
            rot = Rotation.from_quat(self.quat[i]).as_matrix()
        elif a == 1.0:
            rot = Rotation.from_quat(self.quat[i + 1]).as_matrix()
        else:
            assert self._slerp is not None
            rot = self._slerp([time]).as_matrix()[0]
        m[:3, :3] = rot @ ((1 - a) * self.stretch[i] + a * self.stretch[i + 1])
        m[:3, 3] = (1 - a) * self.translate[i] + a * self.translate[i + 1]
        return m

    def changes_within(self, t0: float, t1: float) -> bool:
        """Whether the transform is not constant on [t0, t1]."""
        return _track_changes(self.times, [self.translate, self.quat, self.stretch.reshape(-1, 9)], t0, t1)


def _track_changes(times: np.ndarray, values: list[np.ndarray], t0: float, t1: float) -> bool:
    """A piecewise-linear track (held outside its keyframes) changes on [t0, t1] when two
    keyframes that bound a segment overlapping [t0, t1] differ."""
    if times.size < 2 or t1 <= times[0] or t0 >= times[-1]:
        return False
    lo = max(0, int(np.searchsorted(times, t0, side="right")) - 1)
    hi = min(times.size - 1, int(np.searchsorted(times, t1, side="left")))
    for v in values:
        seg = v[lo:hi + 1]
        scale = max(float(np.abs(seg).max()), 1e-300)
        if float(np.abs(seg - seg[0]).max()) > _SAME_REL * scale:
            return True
    return False


@dataclass(frozen=True)
class LightTrack:
    """Keyframed position and/or intensity of one light.

    light_row: index of the light in the scene's light list (``AnimatedScene.light_rows``).
    pos_times/positions, int_times/intensities: keyframes that set that quantity (may be empty)."""

    light_row: int
    pos_times: np.ndarray
    positions: np.ndarray
    int_times: np.ndarray
    intensities: np.ndarray

    def position_at(self, time: float) -> np.ndarray | None:
        if self.pos_times.size == 0:
            return None
        return np.array([np.interp(time, self.pos_times, self.positions[:, k]) for k in range(3)])

    def intensity_at(self, time: float) -> np.ndarray | None:
        if self.int_times.size == 0:
            return None
        return np.array([np.interp(time, self.int_times, self.intensities[:, k]) for k in range(3)])

    def changes_within(self, t0: float, t1: float) -> bool:
        return (_track_changes(self.pos_times, [self.positions], t0, t1)
                or _track_changes(self.int_times, [self.intensities], t0, t1))


_POSITION_FIELD = {"point": "position", "rect": "corner"}
_EMISSION_FIELD = {"point": "intensity", "directional": "irradiance", "rect": "radiance"}


class AnimatedScene:
    """A scene whose objects and lights move over [start, end].

    parts: every object at rest (world-space meshes; index = object id). local_meshes: the
    object-space mesh of every animated object (keyed by object index). light_rows: the
    scene's lights as LightTable rows (dicts, schema order)."""

    def __init__(self, parts: list[SceneObjectPart], materials: MaterialTable, light_rows: list[dict],
                 *, ambient: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 background: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 start: float = 0.0, end: float = 0.0,
                 object_tracks: list[TransformTrack] | None = None,
                 local_meshes: dict[int, TriMesh] | None = None,
                 light_tracks: list[LightTrack] | None = None):
        if not end >= start:
            raise InvalidInputError(f"animation end ({end}) must be >= start ({start})")
        self.parts = list(parts)
        self.materials = materials
        self.light_rows = [dict(r) for r in light_rows]
        self.ambient = ambient
        self.background = background
        self.start = float(start)
        self.end = float(end)
        self.object_tracks = list(object_tracks or [])
        self.local_meshes = dict(local_meshes or {})
        self.light_tracks = list(light_tracks or [])
        for tr in self.object_tracks:
            if tr.object_index not in self.local_meshes or not 0 <= tr.object_index < len(self.parts):
                raise InvalidInputError(f"object track {tr.object_index}: no such object / local mesh")
        for lt in self.light_tracks:
            if not 0 <= lt.light_row < len(self.light_rows):
                raise InvalidInputError(f"light track {lt.light_row}: no such light")
        self._cache: tuple[float, RuntimeScene] | None = None
        self._static_scene: RuntimeScene | None = None

    # ------------------------------------------------------------------ queries
    @property
    def is_static(self) -> bool:
        """Nothing changes over the interval (no track varies)."""
        return not self.moving_objects(self.start, self.end) and not self.changing_lights(self.start, self.end)

    @property
    def object_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parts)

    def check_time(self, t: float, field_name: str = "time") -> float:
        """``t`` as float, or InvalidInputError naming ``field_name`` and the allowed range."""
        t = float(t)
        if not np.isfinite(t) or not self.start <= t <= self.end:
            raise InvalidInputError(f"{field_name}: {t:g} is outside the animation interval "
                                    f"[{self.start:g}, {self.end:g}]")
        return t

    def moving_objects(self, t0: float, t1: float) -> list[int]:
        """Object ids whose transform is not constant on [t0, t1]."""
        return sorted(tr.object_index for tr in self.object_tracks if tr.changes_within(t0, t1))

    def changing_lights(self, t0: float, t1: float) -> list[int]:
        """Light rows (schema order) whose position or intensity changes on [t0, t1]."""
        return sorted(lt.light_row for lt in self.light_tracks if lt.changes_within(t0, t1))

    def lights_at(self, t: float) -> LightTable:
        rows = [dict(r) for r in self.light_rows]
        for lt in self.light_tracks:
            row = rows[lt.light_row]
            pos = lt.position_at(t)
            if pos is not None:
                key = _POSITION_FIELD.get(row["type"])
                if key is None:
                    raise InvalidInputError(f"light {lt.light_row}: a {row['type']} light has no position")
                row[key] = tuple(pos)
            em = lt.intensity_at(t)
            if em is not None:
                row[_EMISSION_FIELD[row["type"]]] = tuple(em)
        return LightTable.from_rows(rows)

    def parts_at(self, t: float) -> list[SceneObjectPart]:
        parts = list(self.parts)
        for tr in self.object_tracks:
            p = parts[tr.object_index]
            parts[tr.object_index] = SceneObjectPart(
                p.name, self.local_meshes[tr.object_index].transformed(tr.matrix_at(t)), p.material_id)
        return parts

    def scene_at(self, t: float) -> RuntimeScene:
        """The runtime scene at time ``t`` (clamped into [start, end] by the hold rule; use
        ``check_time`` first to reject out-of-range requests)."""
        t = float(t)
        if not self.object_tracks and not self.light_tracks:
            if self._static_scene is None:
                self._static_scene = self._build(t)
            return self._static_scene
        if self._cache is not None and self._cache[0] == t:
            return self._cache[1]
        sc = self._build(t)
        self._cache = (t, sc)
        return sc

    def _build(self, t: float) -> RuntimeScene:
        return build_runtime_scene(self.parts_at(t), self.materials, self.lights_at(t),
                                   ambient=self.ambient, background=self.background)
