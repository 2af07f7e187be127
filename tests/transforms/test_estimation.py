"""LinearEstimation and CubicEstimation against hand-computed cases, slow oracles and invariants.

The oracles below are written for clarity, not speed: each pixel's curve is built with
``numpy.interp`` (linear) or ``scipy.interpolate.PchipInterpolator`` (cubic) through the knots
of docs/semantics.md, the region's mean is their sum over ``n_r``, its pieces are split at the
extrema found on a fine grid (refined with ``brentq``), and the DVS reference rule is applied
step by step in Python, each crossing solved exactly (linear) or with ``brentq`` (cubic).
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
from scipy.interpolate import PchipInterpolator
from scipy.optimize import brentq

from evdown_torch import CubicEstimation, EventCount, LinearEstimation
from tests.helpers import (
    DVS_DTYPE,
    FLOAT_DTYPE,
    as_tuples,
    crossed_levels,
    random_stream,
    reference_index,
)

SENSOR = (10, 7, 2)
ESTIMATORS = [LinearEstimation, CubicEstimation]
LOG_LUMINANCE = [EventCount, LinearEstimation, CubicEstimation]
KINDS = [(LinearEstimation, "linear"), (CubicEstimation, "cubic")]
SNAP = 1e-9  # the kernels' tolerance for "on a level", in thresholds
HALF_TICK = 1e-6  # an oracle time this close to a half tick may round either way


# --- slow oracles --------------------------------------------------------------------------


def reference_knots(arr: np.ndarray) -> tuple[dict, float, float]:
    """Knots of every pixel with events: ``{(x, y): [(t, level), ...]}``, t_start, t_end."""
    order = np.argsort(arr["t"], kind="stable")
    t_start, t_end = arr["t"][order[0]], arr["t"][order[-1]]
    levels: dict = {}
    knots: dict = {}
    for i in order:
        key = (int(arr["x"][i]), int(arr["y"][i]))
        t = arr["t"][i]
        levels[key] = levels.get(key, 0) + (1 if arr["p"][i] > 0 else -1)
        pixel = knots.setdefault(key, [])
        if pixel and pixel[-1][0] == t:
            pixel[-1] = (t, levels[key])  # several events at one time: one knot
        else:
            pixel.append((t, levels[key]))
    for pixel in knots.values():
        if pixel[0][0] > t_start:
            pixel.insert(0, (t_start, 0))
        if pixel[-1][0] < t_end:
            pixel.append((t_end, pixel[-1][1]))
    return knots, t_start, t_end


def reference_curve(kind: str, knots: list) -> tuple:
    """``(f, df)`` of one pixel, in time relative to t_start."""
    ts = np.array([k[0] for k in knots], dtype=np.float64)
    ls = np.array([k[1] for k in knots], dtype=np.float64)
    if len(knots) == 1:
        return (lambda t: np.full(np.shape(t), ls[0])), (lambda t: np.zeros(np.shape(t)))
    if kind == "linear":
        slopes = np.diff(ls) / np.diff(ts)
        return (lambda t: np.interp(t, ts, ls)), (
            lambda t: slopes[np.clip(np.searchsorted(ts, t, side="right") - 1, 0, len(slopes) - 1)]
        )
    curve = PchipInterpolator(ts, ls)
    return curve, curve.derivative()


def reference_rule(q: int, u: float) -> tuple[int, bool]:
    """The reference index after a monotone step ending at ``u = M / theta``."""
    nearest = round(u)
    if abs(u - nearest) <= SNAP:
        return nearest, True
    return reference_index(q, u), False


def reference(arr: np.ndarray, sensor, factor, threshold: float, kind: str) -> dict:
    """Per output pixel, the list of ``(t, on)`` events in time order (t unrounded)."""
    fx, fy = factor
    w, h, _ = sensor
    knots, t_start, t_end = reference_knots(arr)
    t0 = float(t_start)
    regions: dict = {}
    for (x, y), pixel in knots.items():
        regions.setdefault((x // fx, y // fy), []).append(pixel)
    out = {}
    for (rx, ry), pixels in regions.items():
        n_r = min(fx, w - rx * fx) * min(fy, h - ry * fy)
        curves = [reference_curve(kind, [(float(t) - t0, lev) for t, lev in p]) for p in pixels]

        def u(t, curves=curves, n_r=n_r):
            return sum(c[0](t) for c in curves) / n_r / threshold

        def du(t, curves=curves, n_r=n_r):
            return sum(c[1](t) for c in curves) / n_r / threshold

        breakpoints = sorted({float(t) - t0 for p in pixels for t, _ in p})
        steps = []
        for ta, tb in zip(breakpoints[:-1], breakpoints[1:], strict=True):
            cuts = [ta]
            if kind == "cubic":  # split at the extrema: sign changes of M' on a fine grid
                grid = np.linspace(ta, tb, 201)
                d = du(grid)
                nonzero = [i for i in range(201) if d[i] != 0]
                for i, j in zip(nonzero[:-1], nonzero[1:], strict=True):
                    if d[i] * d[j] < 0:
                        root = brentq(du, grid[i], grid[j], xtol=1e-13 * (tb - ta))
                        if 1e-9 < (root - ta) / (tb - ta) < 1 - 1e-9:
                            cuts.append(root)
            cuts.append(tb)
            steps.extend(zip(cuts[:-1], cuts[1:], strict=True))
        events = []
        q, _ = reference_rule(0, u(0.0))  # the jump at t_start from level 0
        events += [(t0, q > 0)] * abs(q)
        for ta, tb in steps:
            ua, ub = u(ta), u(tb)
            new_q, on_level = reference_rule(q, ub)
            for level, up in crossed_levels(q, new_q):
                if on_level and level == new_q:
                    tc = tb
                elif kind == "linear":
                    tc = ta + (level - ua) / (ub - ua) * (tb - ta)
                else:
                    fa, fb = u(ta) - level, u(tb) - level
                    tc = tb if fa * fb > 0 else brentq(
                        lambda t, level=level: u(t) - level, ta, tb, xtol=1e-12 * (tb - ta)
                    )
                events.append((t0 + tc, up))
            q = new_q
        out[(rx, ry)] = events
    return {key: value for key, value in out.items() if value}


def by_output_pixel(out: np.ndarray) -> dict:
    """Output events grouped by output pixel, in output (time) order."""
    got: dict = {}
    for x, y, t, p in zip(out["x"], out["y"], out["t"], out["p"], strict=True):
        got.setdefault((int(x), int(y)), []).append((t.item(), bool(p > 0)))
    return got


def assert_rounded(t: int, t_ref: float | Fraction, key) -> None:
    """``t`` is ``t_ref`` rounded half up, or either neighbour within HALF_TICK of a half."""
    rounded = math.floor(t_ref + Fraction(1, 2))
    if abs((t_ref - math.floor(t_ref)) - Fraction(1, 2)) <= HALF_TICK:
        assert t in (math.floor(t_ref), math.ceil(t_ref)), (key, t, t_ref)
    else:
        assert t == rounded, (key, t, t_ref)


def assert_matches_reference(out: np.ndarray, expected: dict, integer_time: bool) -> None:
    """Same events per output pixel: count, polarity order, and times (rounded half up)."""
    got = by_output_pixel(out)
    assert got.keys() == expected.keys()
    for key, ref in expected.items():
        mine = got[key]
        assert len(mine) == len(ref), key
        assert [p for _, p in mine] == [p for _, p in ref], key
        for (t, _), (t_ref, _) in zip(mine, ref, strict=True):
            if integer_time:
                assert_rounded(t, Fraction(t_ref), key)
            else:
                assert t == pytest.approx(t_ref, rel=1e-12, abs=1e-6), (key, t, t_ref)


def exact_linear_reference(arr: np.ndarray, sensor, factor, threshold: float) -> dict:
    """The linear method in exact rationals: per output pixel, ``(t, on)`` with t a Fraction.

    Each pixel's polyline is evaluated at every breakpoint of its region as a Fraction; the
    region's sum is linear between breakpoints, so each crossing time is the exact rational
    ``ta + (level - ua) / (ub - ua) * (tb - ta)``. A value is on a level only when it equals it.
    """
    theta = Fraction(threshold).limit_denominator(10**6)
    fx, fy = factor
    w, h, _ = sensor
    knots, t_start, _ = reference_knots(arr)
    regions: dict = {}
    for (x, y), pixel in knots.items():
        regions.setdefault((x // fx, y // fy), []).append(
            [(int(t), level) for t, level in pixel])

    def value(pixel: list, t: int) -> Fraction:
        for (ta, la), (tb, lb) in zip(pixel[:-1], pixel[1:], strict=True):
            if ta <= t <= tb:
                return la + Fraction(lb - la, tb - ta) * (t - ta)
        return Fraction(pixel[0][1])  # one knot: t_start == t_end

    def rule(q: int, u: Fraction) -> int:
        return int(u) if u.denominator == 1 else reference_index(q, u)

    out = {}
    for (rx, ry), pixels in regions.items():
        n_r = min(fx, w - rx * fx) * min(fy, h - ry * fy)
        times = sorted({t for p in pixels for t, _ in p})
        us = [sum(value(p, t) for p in pixels) / (n_r * theta) for t in times]
        q = rule(0, us[0])
        events = [(Fraction(int(t_start)), q > 0)] * abs(q)
        for ta, tb, ua, ub in zip(times[:-1], times[1:], us[:-1], us[1:], strict=True):
            new_q = rule(q, ub)
            for level, up in crossed_levels(q, new_q):
                events.append((ta + (level - ua) / (ub - ua) * (tb - ta), up))
            q = new_q
        if events:
            out[(rx, ry)] = events
    return out


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
