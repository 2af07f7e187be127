"""LinearEstimation and CubicEstimation against hand-computed cases and slow oracles.

The oracles (``tests/helpers.py``) are written for clarity, not speed: each pixel's curve is
built with ``numpy.interp`` (linear) or ``scipy.interpolate.PchipInterpolator`` (cubic) through
the knots of docs/semantics.md, the region's mean is their sum over ``n_r``, its pieces are
split at the extrema found on a fine grid (refined with ``brentq``), and the DVS reference rule
is applied step by step in Python, each crossing solved exactly (linear) or with ``brentq``
(cubic).
A second oracle for the linear method works in exact rationals (``fractions.Fraction``)
throughout, so its integer crossing times are exact.

Integer output times must equal the oracle's crossing time rounded half up, except where that
time lies within 1e-6 of a half tick (float arithmetic cannot tell which way it rounds there).
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest

from evdown_torch import CubicEstimation, LinearEstimation
from tests.helpers import (
    DVS_DTYPE,
    ESTIMATORS,
    FLOAT_DTYPE,
    as_tuples,
    assert_matches_reference,
    by_output_pixel,
    exact_linear_reference,
    random_stream,
    reference,
)

SENSOR = (10, 7, 2)
KINDS = [(LinearEstimation, "linear"), (CubicEstimation, "cubic")]


# --- hand-computed cases -------------------------------------------------------------------


def test_linear_hand_computed():
    # One 2x1 region (n_r = 2), theta = 0.25: a level is 0.5 in the sum of the two pixels.
    # Pixel 0: ON at 0, OFF at 30 -> knots (0, 1), (30, 0). Pixel 1: ON at 10 -> knots
    # (0, 0), (10, 1), (30, 1). Sum at 0: 1 (two ON at t_start); on [0, 10] 1 + t / 15
    # reaches 1.5 at t = 7.5 (rounded half up to 8); on [10, 30] 2 - t / 30 comes back to 1
    # exactly at t = 30 (one OFF).
    ev = np.array([(0, 0, True, 0), (1, 0, True, 10), (0, 0, False, 30)], dtype=DVS_DTYPE)
    out = LinearEstimation((2, 1, 2), factor=(2, 1), threshold=0.25)(ev)
    assert out.tolist() == [(0, 0, True, 0), (0, 0, True, 0), (0, 0, True, 8), (0, 0, False, 30)]
    out_f = LinearEstimation((2, 1, 2), factor=(2, 1), threshold=0.25)(ev.astype(FLOAT_DTYPE))
    assert out_f["t"].tolist() == pytest.approx([0.0, 0.0, 7.5, 30.0], abs=1e-12)


def test_cubic_hand_computed():
    # Pixel 1's PCHIP curve on knots (0, 0), (10, 1), (20, 1) has slopes 0.15, 0, 0 (SciPy's
    # end rule and a flat segment); with pixel 0's line 1 - t / 20 the sum on [0, 10] is
    # 1 + s - s^3 / 2 (s = t / 10); the third level 1.5 is reached at s^3 - 2 s + 1 = 0,
    # s = (sqrt(5) - 1) / 2; back to the second level exactly at t = 20.
    ev = np.array([(0, 0, True, 0), (1, 0, True, 10), (0, 0, False, 20)], dtype=FLOAT_DTYPE)
    out = CubicEstimation((2, 1, 2), factor=(2, 1), threshold=0.25)(ev)
    assert out["p"].tolist() == [True, True, True, False]
    golden = 10 * (math.sqrt(5) - 1) / 2
    assert out["t"].tolist() == pytest.approx([0.0, 0.0, golden, 20.0], abs=1e-12)
    out_int = CubicEstimation((2, 1, 2), factor=(2, 1), threshold=0.25)(ev.astype(DVS_DTYPE))
    assert out_int["t"].tolist() == [0, 0, 6, 20]


@pytest.mark.parametrize("cls", ESTIMATORS)
def test_pixel_whose_only_event_is_at_t_end(cls):
    # Pixel 0: ON at 0 (flat at 1). Pixel 1: its only event at t_end = 10, so a front knot
    # (0, 0) and a line up to (10, 1) (two knots: a line for the cubic too). Sum 1 + t / 10;
    # theta = 0.2, n_r = 2: levels every 0.4, so 2 ON at 0, then at 1.2, 1.6, 2.0: t = 2, 6, 10.
    ev = np.array([(0, 0, True, 0), (1, 0, True, 10)], dtype=DVS_DTYPE)
    out = cls((2, 1, 2), factor=(2, 1), threshold=0.2)(ev)
    assert out["t"].tolist() == [0, 0, 2, 6, 10]
    assert out["p"].all()
    # Alone in its region (factor 1), the pixel's ramp reaches level 1 exactly at t_end.
    alone = cls((2, 1, 2), factor=1, threshold=1.0)(ev)
    assert as_tuples(alone) == as_tuples(ev)


@pytest.mark.parametrize("cls", ESTIMATORS)
@pytest.mark.parametrize(("threshold", "expected"), [(1.0, 0), (0.25, 1), (0.1, 2)])
def test_single_event(cls, threshold, expected):
    # One ON event: t_start = t_end, the region's mean jumps from 0 to 1 / 4 at that instant.
    ev = np.array([(3, 2, True, 123)], dtype=DVS_DTYPE)
    out = cls(SENSOR, factor=2, threshold=threshold)(ev)
    assert out.tolist() == [(1, 1, True, 123)] * expected


# --- oracle comparisons --------------------------------------------------------------------


@pytest.mark.parametrize(("cls", "kind"), KINDS)
@pytest.mark.parametrize("factor", [2, 3, 4, (3, 2), (10, 7)])
@pytest.mark.parametrize("threshold", [0.1, 0.5])
def test_matches_slow_reference(cls, kind, factor, threshold, rng):
    arr = random_stream(rng, 400, SENSOR, t_max=3000)
    out = cls(SENSOR, factor=factor, threshold=threshold)(arr)
    fxy = (factor, factor) if isinstance(factor, int) else factor
    assert_matches_reference(out, reference(arr, SENSOR, fxy, threshold, kind), True)


@pytest.mark.parametrize("factor", [2, 3, (3, 2), (10, 7)])
@pytest.mark.parametrize("threshold", [0.1, 0.37, 1.5])
@pytest.mark.parametrize("t0", [0, 1_700_000_000_000_000])
def test_linear_matches_exact_rational_reference(factor, threshold, t0, rng):
    arr = random_stream(rng, 300, SENSOR, t_max=2000)
    arr["t"] += t0
    out = LinearEstimation(SENSOR, factor=factor, threshold=threshold)(arr)
    fxy = (factor, factor) if isinstance(factor, int) else factor
    assert_matches_reference(out, exact_linear_reference(arr, SENSOR, fxy, threshold), True)


def test_exact_rational_reference_on_the_hand_computed_case():
    ev = np.array([(0, 0, True, 0), (1, 0, True, 10), (0, 0, False, 30)], dtype=DVS_DTYPE)
    assert exact_linear_reference(ev, (2, 1, 2), (2, 1), 0.25) == {
        (0, 0): [(0, True), (0, True), (Fraction(15, 2), True), (30, False)]
    }


@pytest.mark.parametrize(("cls", "kind"), KINDS)
@pytest.mark.parametrize(("factor", "threshold"), [(2, 0.05), ((4, 3), 0.3), (3, 1.0)])
def test_matches_slow_reference_float_times(cls, kind, factor, threshold, rng):
    arr = random_stream(rng, 500, SENSOR, dtype=FLOAT_DTYPE)
    arr["t"] = np.sort(rng.random(500) * 1e3)
    out = cls(SENSOR, factor=factor, threshold=threshold)(arr)
    fxy = (factor, factor) if isinstance(factor, int) else factor
    assert_matches_reference(out, reference(arr, SENSOR, fxy, threshold, kind), False)


@pytest.mark.parametrize(("cls", "kind"), KINDS)
@pytest.mark.parametrize(("threshold", "n"), [(0.01, 120), (0.3, 800), (7.5, 800), (100.0, 4000)])
def test_thresholds_from_001_to_100(cls, kind, threshold, n, rng):
    # Dense ties (many events per pixel and timestamp) so that large thresholds are reached.
    arr = random_stream(rng, n, (4, 4, 2), t_max=50 if threshold < 1 else 8)
    if threshold > 1:
        arr["p"] = rng.random(n) < 0.95  # mostly ON: levels climb past 100 thresholds
    out = cls((4, 4, 2), factor=2, threshold=threshold)(arr)
    assert_matches_reference(out, reference(arr, (4, 4, 2), (2, 2), threshold, kind), True)
    assert len(out) > 0


@pytest.mark.parametrize(("cls", "kind"), KINDS)
def test_burst_at_one_pixel_and_timestamp(cls, kind, rng):
    arr = random_stream(rng, 200, SENSOR, t_max=1000)
    burst = np.zeros(3000, dtype=DVS_DTYPE)
    burst["x"], burst["y"], burst["t"], burst["p"] = 4, 3, 500, True
    burst["p"][::10] = False  # 2400 net ON at one knot
    arr = np.sort(np.concatenate([arr, burst]), order="t", kind="stable")
    out = cls(SENSOR, factor=2, threshold=0.5)(arr)
    assert_matches_reference(out, reference(arr, SENSOR, (2, 2), 0.5, kind), True)
    # The burst lifts the region's mean by 2400 / 4 = 1200 thresholds (less up to one cell).
    ons = sum(on for _, on in by_output_pixel(out)[(2, 1)])
    assert ons >= 1150


# --- invariants ----------------------------------------------------------------------------
