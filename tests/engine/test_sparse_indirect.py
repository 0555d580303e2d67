"""Indirect light traced on a coarser lattice of LDC samples and interpolated in between
(engine/newviews/sparse_indirect.py, ``IndirectParams.stride``)."""

from __future__ import annotations

import numpy as np
import pytest

from engine.errors import InvalidInputError
from engine.newviews.indirect import IndirectParams
from engine.newviews.ldc import bake_ldc_axis, indirect_chunk, with_indirect
from engine.newviews.sparse_indirect import interpolate_untraced, traced_samples
from engine.raycast import EmbreeCaster
from tests.engine.scenes import box_room, mat, quad, scene

LUMA = np.array([0.2126, 0.7152, 0.0722])


def _pixels(ax):
    f = ax.ldi.frame
    k = ax.ldi.sample_pixels().astype(np.int64)
    return k % f.nu, k // f.nu


def test_stride_one_traces_every_sample_and_stride_two_about_a_quarter_of_a_plane():
    sc = scene([(quad((0, 0, 0), 2.0, 1), mat("floor"))], [dict(type="point", position=(0, 1, 0),
                                                                  intensity=(1, 1, 1))])
    ax = bake_ldc_axis(sc, EmbreeCaster(sc), 1, 40)  # the floor seen face-on: one sample per pixel
    assert traced_samples(ax.ldi, ax.geo_normal, ax.object, ax.material, 1).all()
    traced = traced_samples(ax.ldi, ax.geo_normal, ax.object, ax.material, 2)
    ci, cj = _pixels(ax)
    on_lattice = (ci % 2 == 0) & (cj % 2 == 0)
    assert np.array_equal(traced, on_lattice)  # a plane has neighbours everywhere: only the lattice
    assert 0.2 < traced.mean() < 0.3


def test_a_linear_function_is_reproduced_between_the_lattice_and_borders_keep_their_own_value():
    sc = scene([(quad((0, 0, 0), 2.0, 1), mat("floor"))], [dict(type="point", position=(0, 1, 0),
                                                                  intensity=(1, 1, 1))])
    ax = bake_ldc_axis(sc, EmbreeCaster(sc), 1, 41)
    traced = traced_samples(ax.ldi, ax.geo_normal, ax.object, ax.material, 2)
    ci, cj = _pixels(ax)
    truth = np.zeros((ax.n_samples, 2, 3), np.float32)
    truth[:, 0, 0] = 1.0 + 0.5 * ci + 0.25 * cj
    truth[:, 1, 2] = 3.0 + 0.1 * cj
    known = np.where(traced[:, None, None], truth, np.float32(-7.0))  # untraced values must not be read
    got = interpolate_untraced(ax.ldi, ax.geo_normal, ax.object, ax.material, 2, traced, known)
    # past the floor's last lattice row / column the neighbours are on one side only: renormalised
    last_i, last_j = ci[traced].max(), cj[traced].max()
    inner = (ci <= last_i) & (cj <= last_j) & (ci >= ci[traced].min()) & (cj >= cj[traced].min())
    assert inner.mean() > 0.8
    np.testing.assert_allclose(got[inner], truth[inner], rtol=1e-6)
    assert np.array_equal(got[traced], truth[traced])
    assert not np.any(got == -7.0)


def test_samples_without_a_traced_neighbour_on_their_surface_are_traced_themselves():
    # a red speck on the floor, smaller than an LDC pixel, centred on a pixel off the lattice: its
    # sample has no red neighbour at a lattice pixel (the floor's there are another object)
    light = [dict(type="point", position=(0, 1, 0), intensity=(1, 1, 1))]
    floor = (quad((0, 0, 0), 2.0, 1), mat("floor"))
    f = bake_ldc_axis(scene([floor], light), EmbreeCaster(scene([floor], light)), 1, 100).ldi.frame
    centre = np.asarray(f.origin) + 51.5 * f.h * np.asarray(f.u) + 51.5 * f.h * np.asarray(f.v)
    centre[1] = 0.01
    sc = scene([floor, (quad(tuple(centre), 0.6 * f.h, 1), mat("red", kd=(0.8, 0.1, 0.1)))], light)
    ax = bake_ldc_axis(sc, EmbreeCaster(sc), 1, 100)
    assert abs(ax.ldi.frame.h - f.h) < 1e-12
    traced = traced_samples(ax.ldi, ax.geo_normal, ax.object, ax.material, 2)
    ci, cj = _pixels(ax)
    red = np.flatnonzero(ax.object == 1)
    assert red.size == 1 and ci[red[0]] % 2 == 1 and cj[red[0]] % 2 == 1
    assert traced[red[0]]
    # the floor's samples around it still interpolate between floor samples
    floor_odd = (ax.object == 0) & (ci % 2 == 1) & (cj % 2 == 1)
    assert not traced[floor_odd].any()


def test_a_stride_two_bake_is_split_invariant_and_agrees_with_stride_one_on_average():
    sc = box_room()
    caster = EmbreeCaster(sc)
    ax = bake_ldc_axis(sc, caster, 0, 24)
    n = ax.n_samples
    p2 = IndirectParams(noise=0.05, bounces=2, seed=3, stride=2)
    whole = with_indirect(ax, [indirect_chunk(sc, caster, ax, 0, n, p2)], p2)
    k = n // 3
    split = with_indirect(ax, [indirect_chunk(sc, caster, ax, a, b, p2) for a, b in ((k, n), (0, k))], p2)
    assert np.array_equal(whole.diffuse, split.diffuse)
    summary = whole.timings["indirect"]
    traced = traced_samples(ax.ldi, ax.geo_normal, ax.object, ax.material, 2)
    assert summary["stride"] == 2 and summary["interpolated_samples"] == n - traced.sum() > n // 2
    assert summary["sides"] == 2 * traced.sum()
    p1 = IndirectParams(noise=0.05, bounces=2, seed=3)
    one = with_indirect(ax, [indirect_chunk(sc, caster, ax, 0, n, p1)], p1)
    ind2 = (whole.diffuse - ax.diffuse).astype(np.float64) @ LUMA
    ind1 = (one.diffuse - ax.diffuse).astype(np.float64) @ LUMA
    assert np.all(ind2[~traced].sum(axis=1) > 0.0)  # every interpolated sample got light (on its inner side)
    assert abs(ind2.mean() / ind1.mean() - 1.0) < 0.03, ind2.mean() / ind1.mean()


def test_stride_out_of_range_names_the_allowed_range():
    with pytest.raises(InvalidInputError, match=r"stride must be an integer in \[1, 8\]"):
        IndirectParams(stride=0)
