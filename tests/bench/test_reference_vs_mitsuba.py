"""The time-to-error reading of bench/reference_vs_mitsuba.py: interpolated on a ladder, bounded by
the cheapest render, and not invented where adaptive renders all stopped at the spp cap."""

from __future__ import annotations

import math

import pytest

from bench.reference_vs_mitsuba import NOT_REACHED, _fmt, _ratio, seconds_for

# (spp, LRMS, wall s, CPU s): error halving per 4x samples, time linear in samples
LADDER = [(4, 0.08, 0.1, 0.2), (16, 0.04, 0.4, 0.8), (64, 0.02, 1.6, 3.2), (256, 0.01, 6.4, 12.8)]


def test_a_uniform_ladder_is_read_at_its_best_speed():
    t, mark = seconds_for(LADDER, 0.02, uniform=True)
    assert mark == "" and t == pytest.approx(1.6)
    t, mark = seconds_for(LADDER, 0.005, uniform=True)  # past the ladder's end
    assert mark == "~" and t == pytest.approx(25.6)
    t, mark = seconds_for(LADDER, 0.1, uniform=True)  # the cheapest render already reaches it
    assert mark == "<=" and t == pytest.approx(0.1)


def test_adaptive_renders_are_interpolated_in_time():
    rows = [(20, 0.097, 0.3, 0.6), (68, 0.047, 0.9, 1.8), (311, 0.0195, 3.9, 7.8)]
    t, mark = seconds_for(rows, 0.03, uniform=False)
    assert mark == "" and 0.9 < t < 3.9


def test_adaptive_renders_stopped_at_the_cap_do_not_reach_lower_targets():
    """Renders asked for 3, 2 and 1 % that all stopped at the cap with the same image: the lower
    targets are not reached (not extrapolated from two equal errors, which gave 0 s)."""
    cap = 0.030375113896713445
    rows = [(295, 0.101, 5.0, 9.5), (1174, 0.0511, 20.1, 38.4), (3768, cap + 6e-13, 64.0, 122.8),
            (3799, cap, 59.0, 115.8), (3880, cap, 57.6, 112.2)]
    for target in (0.02, 0.01):
        t, mark = seconds_for(rows, target, uniform=False)
        assert mark == NOT_REACHED and math.isnan(t)
        assert _fmt((t, mark)) == "not reached" and _ratio((1.0, ""), (t, mark)) == "-"
    t, mark = seconds_for(rows, 0.04, uniform=False)  # between two different errors: read as usual
    assert mark == "" and 20.1 < t < 64.0
