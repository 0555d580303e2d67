"""Sample scenes shipped with ibr-service (reproducing the first paper's test scenes in spirit).

- ``mirror_box``: a mirror sphere and a mirror cylinder in a diffuse box with a glossy,
  non-reflective floor, open top and one missing wall, four point lights.
- ``teapot_glossy``: the Utah teapot on a glossy reflective floor.
- ``teapot_spheres``: the teapot with several spheres; depth complexity >= 10 along x.
- ``cornell_box``: the Cornell box with its measured dimensions as Mitsuba ships it (diffuse).
- ``cornell_mirror_glossy``: the same box with a mirror sphere in place of the short box and a
  glossy (kd + kg) tall box; the ceiling light is a rect light seen directly, with a black housing
  behind it (the caustic cross-check against Mitsuba, docs/accuracy-reference.md).
"""

from __future__ import annotations

from pathlib import Path

SAMPLES_DIR = Path(__file__).resolve().parent
SCENES_DIR = SAMPLES_DIR / "scenes"
MESHES_DIR = SAMPLES_DIR / "meshes"


def sample_names() -> list[str]:
    return sorted(p.stem for p in SCENES_DIR.glob("*.json"))


def sample_path(name: str) -> Path:
    p = SCENES_DIR / f"{name}.json"
    if not p.is_file():
        raise KeyError(f"unknown sample scene {name!r}; available: {', '.join(sample_names())}")
    return p
