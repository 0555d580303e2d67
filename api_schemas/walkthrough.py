"""Walkthrough requests and their public state (``/v1/walkthroughs``, docs/walkthrough.md).

A walkthrough renders every frame of a camera path through a stored scene's view space from
a walkthrough bake (base range images at chosen viewpoints and times). Checks that need the
scene (eyes inside ``view_space``, times inside the animation) are made by the API with
:func:`producer.walkthroughs.check_against_scene`; this module checks the request alone.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal, Self

from pydantic import Field, model_validator
from pydantic_core import InitErrorDetails

from api_schemas.common import FiniteFloat, FrozenModel, error_at, raise_errors
from api_schemas.scene import Camera
from api_schemas.service import ContractRule, JobPublic, QualityContract, QualityMiss, Sha256

__all__ = [
    "BYTES_PER_BASE_PIXEL",
    "INDIRECT_MAX_PATHS_RANGE",
    "INDIRECT_NOISE_RANGE",
    "DEFAULT_PATH_NOISES",
    "MAX_WALKTHROUGH_FRAMES",
    "PATH_NOISE_RANGE",
    "PRESET_SIZES",
    "PathTracedFrames",
    "WalkthroughCalibrationParams",
    "WalkthroughCalibrationPublic",
    "WalkthroughCalibrationRequest",
    "WalkthroughContractPublic",
    "WalkthroughFrame",
    "WalkthroughPublic",
    "WalkthroughRequest",
    "WalkthroughSettings",
]

MAX_WALKTHROUGH_FRAMES = 10_000
INDIRECT_NOISE_RANGE = (0.001, 0.5)
"""Allowed indirect_noise (engine.walkthrough.bake.INDIRECT_NOISE_RANGE; a test keeps them equal)."""
INDIRECT_MAX_PATHS_RANGE = (128, 65536)
"""Allowed indirect_max_paths (engine.walkthrough.bake.INDIRECT_MAX_PATHS_RANGE)."""
PRESET_SIZES: dict[str, dict[str, int]] = {
    "low": {"face_res": 96, "max_views": 4, "max_time_samples": 5},
    "medium": {"face_res": 160, "max_views": 8, "max_time_samples": 9},
    "high": {"face_res": 256, "max_views": 12, "max_time_samples": 17},
}
"""The size-setting fields of engine.walkthrough.bake.PRESETS (a test keeps them equal); the API
bounds a bake's memory with them before anything is queued."""
BYTES_PER_BASE_PIXEL = 2 * 12 + 4 + 4
"""direct + indirect (float32 RGB), depth (float32), object id (int32) per cube pixel and time."""
PATH_NOISE_RANGE = (0.005, 0.5)
"""Allowed ``path_traced.noise`` (and calibrated ``path_noises``)."""
DEFAULT_PATH_NOISES: tuple[float, ...] = (0.02, 0.03, 0.05, 0.07, 0.1, 0.14, 0.2)
"""The path-traced noise targets a walkthrough calibration measures by default, about 1.4x apart; the
planner weighs targets between them too (``engine.walkthrough.quality.interpolated_path_fit``), and
the finest two cost most of the calibration's path-traced part."""
Quality = Literal["low", "medium", "high"]
Fill = Literal["none", "foreground", "background", "both", "trace"]


class WalkthroughFrame(FrozenModel):
    """One frame: the camera (its eye inside the scene's view space) and the animation time."""

    camera: Camera
    """Camera of this frame; every frame of a walkthrough has the same width and height."""
    time: FiniteFloat = 0.0
    """Animation time, inside [animation.start, animation.end] (any value for a static scene)."""


class WalkthroughSettings(FrozenModel):
    """The bake: a quality preset plus optional overrides (docs/walkthrough.md, presets)."""

    quality: Quality = "medium"
    """Preset: decomposition thresholds, base image resolution and samples."""
    face_res: Annotated[int, Field(strict=True, ge=8, le=1024)] | None = None
    """Base cube face resolution (default: the preset's); a multiple of 2."""
    indirect_samples: Annotated[int, Field(strict=True, ge=0, le=1024)] | None = None
    """0: no global illumination; > 0: indirect light in the bases (traced to ``indirect_noise``) and
    this many indirect paths per pixel where fill "trace" traces a hole."""
    indirect_noise: Annotated[float, Field(ge=INDIRECT_NOISE_RANGE[0], le=INDIRECT_NOISE_RANGE[1])] | None = None
    """Target relative standard error of each base pixel's indirect light (against the pixel's
    brightness); default: the preset's (low 0.05, medium 0.02, high 0.01)."""
    indirect_max_paths: Annotated[int, Field(strict=True, ge=INDIRECT_MAX_PATHS_RANGE[0],
                                             le=INDIRECT_MAX_PATHS_RANGE[1])] | None = None
    """Most indirect paths any base pixel traces (default: the preset's, low 256, medium 1024, high 4096)."""
    max_views: Annotated[int, Field(strict=True, ge=1, le=256)] | None = None
    """Cap on the number of base viewpoints."""
    max_time_samples: Annotated[int, Field(strict=True, ge=1, le=257)] | None = None
    """Cap on the number of time samples."""
    seed: Annotated[int, Field(strict=True, ge=0, le=2**31 - 1)] = 0
    """Random seed of the base renders."""

    @model_validator(mode="after")
    def _even(self) -> Self:
        if self.face_res is not None and self.face_res % 2:
            raise_errors("WalkthroughSettings", [error_at(("face_res",), "face_res_even",
                                                          f"face_res must be even (got {self.face_res})",
                                                          self.face_res)])
        return self

    def upper_bound_bytes(self) -> int:
        """Largest bake these settings can produce (every view and time sample used)."""
        size = {**PRESET_SIZES[self.quality], **self.overrides()}
        return int(size["max_views"] * size["max_time_samples"] * 6 * size["face_res"] ** 2 * BYTES_PER_BASE_PIXEL)

    def overrides(self) -> dict[str, int | float]:
        out: dict[str, int | float] = {"seed": self.seed}
        for name in ("face_res", "indirect_samples", "indirect_max_paths", "max_views", "max_time_samples"):
            v = getattr(self, name)
            if v is not None:
                out[name] = int(v)
        if self.indirect_noise is not None:
            out["indirect_noise"] = float(self.indirect_noise)
        return out


class PathTracedFrames(FrozenModel):
    """Every frame path-traced instead of reconstructed from a bake (docs/walkthrough.md,
    "Path-traced frames"): no bake to wait for, each frame costs what a reference render of it
    costs. The image model is the bases': one sample at each pixel centre, direct light plus
    indirect light of the preset's bounces."""

    noise: Annotated[float, Field(ge=PATH_NOISE_RANGE[0], le=PATH_NOISE_RANGE[1])]
    """The frame LRMS to aim for, against the converged frame: each frame traces a pilot of indirect
    paths, estimates its own LRMS from them and traces the paths per pixel that bring it to this
    (4..4096; about ``(0.3 / noise)^2`` on the sample scenes); each frame's result states its
    estimate."""
    seed: Annotated[int, Field(strict=True, ge=0, le=2**31 - 1)] = 0
    """Sampler seed (equal seeds give identical frames)."""
    max_ms: Annotated[float | None, Field(gt=0, le=3_600_000)] = None
    """Each frame's time budget in the worker, milliseconds: a frame traces no more paths than the time
    left allows (its direct light and its pilot always), so one that runs out of time ends above
    ``noise`` and its estimate says by how much. A quality contract with ``max_ms`` planned onto
    path-traced frames sets it."""


class WalkthroughRequest(FrozenModel):
    """Render a camera path through a stored scene from image-based walkthrough bases."""

    scene_id: Sha256
    """A stored scene with a ``view_space``."""
    bake: WalkthroughSettings = WalkthroughSettings()
    """Bake settings (quality preset)."""
    fill: Fill = "both"
    """Hole fill of the reconstruction: none, foreground, background, both, trace."""
    path_traced: PathTracedFrames | None = None
    """Path-trace every frame instead of reconstructing it from a bake (excludes ``bake`` and
    ``fill``): worth it for short walkthroughs, where the bake costs more than the frames it saves."""
    frames: Annotated[list[WalkthroughFrame], Field(min_length=1, max_length=MAX_WALKTHROUGH_FRAMES)]
    """The camera path with times, in playback order."""
    chunk_frames: Annotated[int, Field(strict=True, ge=1, le=1000)] = 16
    """Frames per render job (several workers share a walkthrough)."""
    fps: Annotated[int, Field(strict=True, ge=1, le=120)] = 24
    """Frame rate of the MP4 preview."""
    quality: QualityContract | None = None
    """A quality contract instead of ``bake`` and ``fill`` (docs/quality-contracts.md, "Walkthroughs"):
    ``max_error`` bounds every frame's LRMS against its converged frame, ``max_ms`` every frame's
    render time in the worker; the planner picks the bake preset and the fill from the scene's
    walkthrough calibration. ``verify`` is for renders only."""

    @model_validator(mode="after")
    def _same_size(self) -> Self:
        errors: list[InitErrorDetails] = []
        if self.path_traced is not None:
            # compared with the defaults, not by presence: a stored request round-trips every field
            for name, default in (("bake", WalkthroughSettings()), ("fill", "both"), ("quality", None)):
                if getattr(self, name) != default:
                    errors.append(error_at((name,), "path_traced_with_settings",
                                           f"{name} and path_traced exclude each other: path-traced frames need no "
                                           f"bake and no fill", getattr(self, name)))
        if self.quality is not None:
            for name in ("bake", "fill"):
                if name in self.model_fields_set:
                    errors.append(error_at((name,), "quality_with_settings",
                                           f"{name} and quality exclude each other: with quality the planner "
                                           f"chooses the bake preset and the fill", getattr(self, name)))
            if self.quality.verify:
                errors.append(error_at(("quality", "verify"), "verify_walkthrough",
                                       "verify is not offered for walkthroughs (a converged reference of every "
                                       "frame would cost more than the walkthrough); the error is the "
                                       "calibration's prediction", True))
        w0, h0 = self.frames[0].camera.width, self.frames[0].camera.height
        for i, f in enumerate(self.frames[1:], start=1):
            if (f.camera.width, f.camera.height) != (w0, h0):
                errors.append(error_at(("frames", i, "camera", "width"), "frame_size",
                                       f"every frame must be {w0} x {h0} like frames.0 "
                                       f"(got {f.camera.width} x {f.camera.height})", f.camera.width))
                if len(errors) >= 10:
                    break
        if w0 % 2 or h0 % 2:
            errors.append(error_at(("frames", 0, "camera", "width"), "frame_size_even",
                                   f"frame width and height must be even for the MP4 (got {w0} x {h0})", w0))
        raise_errors("WalkthroughRequest", errors)
        return self


class WalkthroughContractPublic(FrozenModel):
    """What a walkthrough's quality contract got: the setting chosen, by which rule, what it predicts
    and, once the frames are rendered, what they took (docs/quality-contracts.md, "Walkthroughs")."""

    max_error: float | None = None
    max_ms: float | None = None
    on_miss: QualityMiss = "fail"
    rule: ContractRule
    met: bool
    """The chosen setting is predicted to meet every target."""
    unmet: list[str] = []
    reason: str = ""
    preset: Quality | None
    """The bake preset chosen (``bake.quality``; the bake's other settings at their defaults); None
    for path-traced frames."""
    fill: Fill | None
    """The hole fill chosen; None for path-traced frames."""
    path_noise: float | None = None
    """Path-traced frames chosen (``path_traced.noise``): every frame traced to this noise, no bake."""
    frames: int
    width: int
    height: int
    predicted_error: float
    """Every frame's LRMS against its converged frame, from the calibration (its worst probe frame)."""
    predicted_frame_ms: float
    """Render time of one frame in the worker (the reconstruction)."""
    predicted_bake_ms: float = 0.0
    """The bake's cost when the plan waits for a bake that is not made yet."""
    predicted_total_ms: float
    """What was ranked: the bake (when missing) plus every frame."""
    achieved_frame_ms: dict[str, float] | None = None
    """Once every frame is rendered: ``median`` and ``max`` of the frames' render times."""
    achieved_estimated_error: dict[str, float] | None = None
    """Path-traced frames, once every frame is rendered: ``median`` and ``max`` of the frames' own
    estimates of their LRMS (each frame sizes its paths from it; on held-out frames of the sample
    scenes an estimate was 0.74-1.04x the error measured against the converged frame). None for
    reconstructed frames, which estimate nothing."""
    estimated_error: float
    estimated_error_source: Literal["calibration"] = "calibration"
    """The calibration's prediction: no converged frames are rendered for a walkthrough."""
    planned_for: dict[str, float] = {}
    """The targets the choice was planned against: the request's times the margins, or the request's
    own when no setting keeps the margin (``reason`` says so)."""
    bake: Literal["ready", "waited", "none"]
    """``ready``: the preset's bake was in the store; ``waited``: it is made first (its cost counted);
    ``none``: path-traced frames need no bake."""
    excluded: dict[str, str] = {}
    calibration: dict[str, Any] = {}
    """Which calibration planned it: its key, when it was made, what it cost."""


class WalkthroughPublic(FrozenModel):
    """State of a walkthrough: the bake, the chunk jobs, the finished video."""

    key: Sha256
    """The walkthrough's artifact key (its id)."""
    status: Literal["queued", "running", "finished", "failed"]
    """Overall state."""
    progress: Annotated[float, Field(ge=0, le=1)]
    """Fraction done (bake counts as one third)."""
    frames: int
    """Number of frames."""
    frames_done: int
    """Frames rendered so far."""
    bake_key: Sha256 | None
    """Key of the walkthrough bake (shared by requests with the same scene and bake settings); None
    for path-traced frames."""
    jobs: list[JobPublic] = []
    """The bake job, the chunk jobs and the video job (when known)."""
    error: str | None = None
    """First error, when failed."""
    links: dict[str, str] = {}
    """video.mp4 and the frame chunks once finished."""
    contract: WalkthroughContractPublic | None = None
    """What the quality contract chose and predicts (a request with ``quality`` only)."""


# ------------------------------------------------------------------------------ calibrations


class WalkthroughCalibrationParams(FrozenModel):
    """How a scene's walkthrough settings are calibrated: probe frames spread over the view space and
    the animation, each rendered converged and from every preset's bake with every fill."""

    presets: Annotated[list[Quality], Field(min_length=1, max_length=3)] = ["low", "medium", "high"]
    """The bake presets measured (each is baked unless its bake is in the store; the bakes stay, so a
    walkthrough planned onto one renders at once)."""
    fills: Annotated[list[Fill], Field(min_length=1, max_length=5)] = ["both", "trace"]
    """The hole fills measured with each preset."""
    path_noises: Annotated[list[Annotated[float, Field(ge=PATH_NOISE_RANGE[0], le=PATH_NOISE_RANGE[1])]],
                           Field(max_length=8)] = list(DEFAULT_PATH_NOISES)
    """Path-traced frames measured at these noise targets (``path_traced.noise``; each a setting of
    its own, ``path/0.05``, needing no bake); empty: none."""
    probes: Annotated[int, Field(strict=True, ge=1, le=8)] = 3
    """Probe frames (eyes spread over the view space, times over the animation)."""
    size: Annotated[int, Field(strict=True, ge=16, le=512)] = 64
    """Longest side of the probe frames (the scene camera's aspect ratio)."""
    time_scale: Annotated[int, Field(strict=True, ge=2, le=8)] = 4
    """Frame times are also measured at ``size x time_scale`` (their per-pixel part)."""
    truth_noise: Annotated[float, Field(ge=0.002, le=0.05)] = 0.01
    """Relative standard error each converged probe pixel's indirect light is traced to."""

    @model_validator(mode="after")
    def _distinct(self) -> Self:
        for name in ("presets", "fills", "path_noises"):
            v = getattr(self, name)
            if len(set(v)) != len(v):
                raise_errors("WalkthroughCalibrationParams", [error_at((name,), "duplicate",
                                                                       f"{name} lists a value twice", v)])
        return self


class WalkthroughCalibrationRequest(FrozenModel):
    """Body of ``POST /v1/scenes/{scene_id}/walkthrough-calibrations``."""

    params: WalkthroughCalibrationParams = WalkthroughCalibrationParams()


class WalkthroughCalibrationPublic(FrozenModel):
    """A scene's walkthrough calibration: the job making it, then the fitted model."""

    scene_id: Sha256
    key: Sha256
    """Content key of the calibration (scene, params, engine version)."""
    state: Literal["queued", "running", "finished", "failed", "missing"]
    cached: bool = False
    job: JobPublic | None = None
    model: dict[str, Any] | None = None
    """The fitted model (``engine.walkthrough.quality.WalkthroughModel``): per setting
    (``preset/fill``) its error and frame-time fit, each preset's bake and its cost, ``cost_s``."""
    links: dict[str, str] = {}
