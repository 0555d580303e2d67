"""Progress and cancellation of one LDC axis bake (the bake job reports it per RQ part)."""

from __future__ import annotations

import numpy as np
import pytest

import engine.newviews.ldc as ldc_mod
from engine.newviews.ldc import bake_ldc_axis
from engine.raycast import EmbreeCaster
from tests.engine.scenes import mat, quad, scene, sphere_mesh

LIGHTS = [dict(type="point", position=(1.5, 2.5, 2.0), intensity=(4.0, 4.0, 4.0)),
          dict(type="point", position=(-2.0, 1.5, 1.0), intensity=(1.0, 2.0, 3.0))]


def _scene():
    return scene([(quad((0, -0.5, 0), 3.0, normal_axis=1), mat("floor")),
                  (sphere_mesh((0.0, 0.1, 0.0), 0.5, subdivisions=3), mat("ball", kd=(0.2, 0.3, 0.7)))],
                 LIGHTS)


class _Cancel(Exception):
    pass


def test_progress_is_monotone_ends_at_one_and_slices_are_reported(monkeypatch):
    sc = _scene()
    caster = EmbreeCaster(sc)
    events: list[tuple[float, str]] = []
    whole = bake_ldc_axis(sc, caster, 1, 48)
    # tiny slices: one report per 50 samples (2 lights -> 100 light rows per slice)
    orig = ldc_mod.shade_samples
    monkeypatch.setattr(ldc_mod, "shade_samples", lambda *a, **k: orig(*a, **{**k, "rows_per_slice": 100}))
    part = bake_ldc_axis(sc, caster, 1, 48, progress=lambda f, s: events.append((f, s)))
    fr = [f for f, _ in events]
    assert events[0][1] == "cast" and all(s == "shade" for _, s in events[1:])
    assert len(events) >= 1 + part.n_samples // 50
    assert all(b >= a for a, b in zip(fr, fr[1:], strict=False)) and fr[-1] == pytest.approx(1.0)
    assert 0.0 < fr[0] < 1.0
    # reporting (and slicing) does not change the bake
    assert np.array_equal(part.diffuse, whole.diffuse)
    assert np.array_equal(part.ldi.depth, whole.ldi.depth)


def test_a_raising_callback_cancels_the_bake():
    sc = _scene()
    caster = EmbreeCaster(sc)

    def cancel(f, stage):
        if stage == "shade":
            raise _Cancel()

    with pytest.raises(_Cancel):
        bake_ldc_axis(sc, caster, 0, 32, progress=cancel)
