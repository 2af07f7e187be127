"""The curve plot draws what the kernels compute: reconstructions and the transforms' events."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from scipy.interpolate import PchipInterpolator

from evdown_torch import CubicEstimation, EventCount, LinearEstimation
from evdown_torch.events import Events
from evdown_torch.plot import curve_figure, region_curves
from evdown_torch.transforms import Downscaler
from evdown_torch.transforms.functional.downsample import DOWNSAMPLE
from evdown_torch.transforms.registry import METHODS, make_method
from tests.helpers import DVS_DTYPE, random_stream

SENSOR = (8, 6, 2)
FACTOR = (4, 3)
PIXEL = (1, 0)  # input x 4..7, y 0..2


def lines(figure, gid: str):
    found = [a for ax in figure.axes for a in ax.lines if a.get_gid() == gid]
    assert len(found) == 1, gid
    return found[0]


def float_stream(rng) -> np.ndarray:
    """Float timestamps: the estimators' crossing times are then exact reals, not rounded."""
    dtype = np.dtype([("x", np.int16), ("y", np.int16), ("t", np.float64), ("p", bool)])
    events = random_stream(rng, 300, SENSOR, t_max=50_000)
    out = np.empty(len(events), dtype=dtype)
    for name in ("x", "y", "p"):
        out[name] = events[name]
    out["t"] = events["t"] + rng.random(len(events))
    return out[np.argsort(out["t"], kind="stable")]


def slow_knots(events: np.ndarray, x: int, y: int) -> tuple[np.ndarray, np.ndarray]:
    """A pixel's knots by SEMANTICS.md, one event at a time."""
    t_start, t_end = events["t"].min(), events["t"].max()
    level, knots = 0, {}
    for e in events[(events["x"] == x) & (events["y"] == y)]:
        level += 1 if e["p"] else -1
        knots[float(e["t"])] = level
    times, levels = list(knots), list(knots.values())
    if times[0] > t_start:
        times, levels = [t_start, *times], [0, *levels]
    if times[-1] < t_end:
        times, levels = [*times, t_end], [*levels, levels[-1]]
    return np.array(times, dtype=np.float64), np.array(levels, dtype=np.float64)


def region_oracle(events: np.ndarray, at: np.ndarray, kind: str) -> np.ndarray:
    """``M_r`` of the region of PIXEL at times ``at``: PCHIP (SciPy) or polyline per pixel."""
    total = np.zeros_like(at)
    for x in range(4, 8):
        for y in range(3):
            if not ((events["x"] == x) & (events["y"] == y)).any():
                continue
            t, level = slow_knots(events, x, y)
            if len(t) == 1:
                total += level[0]
            elif kind == "cubic":
                total += PchipInterpolator(t, level)(at)
            else:
                total += np.interp(at, t, level)
    return total / 12


@pytest.mark.parametrize("integer_t", [True, False])
def test_plotted_events_are_the_transforms_output_at_the_pixel(rng, integer_t):
    events = random_stream(rng, 400, SENSOR, t_max=30_000) if integer_t else float_stream(rng)
    figure = curve_figure(region_curves(events, SENSOR, FACTOR, PIXEL, threshold=0.5))
    for name in METHODS:
        settings = {"threshold": 0.5} if name in ("event_count", "linear", "cubic") else {}
        out = make_method(name, SENSOR, FACTOR, **settings)(events)
        here = out[(out["x"] == PIXEL[0]) & (out["y"] == PIXEL[1])]
        for polarity, suffix in ((True, "on"), (False, "off")):
            expected = here["t"][(here["p"] > 0) == polarity].astype(np.float64)
            np.testing.assert_array_equal(lines(figure, f"events:{name}:{suffix}").get_xdata(),
                                          expected)
            if name in ("event_count", "linear", "cubic"):
                np.testing.assert_array_equal(
                    lines(figure, f"crossings:{name}:{suffix}").get_xdata(), expected)
    region = events[(events["x"] >= 4) & (events["y"] < 3)]
    assert len(lines(figure, "events:input:on").get_xdata()) == (region["p"] > 0).sum()


def test_reconstructions_match_scipy_and_numpy_oracles(rng):
    events = float_stream(rng)
    curves = region_curves(events, SENSOR, FACTOR, PIXEL, ["linear", "cubic"], threshold=0.5)
    t, cubic = curves.cubic_mean
    np.testing.assert_allclose(cubic, region_oracle(events, t, "cubic"), atol=1e-9)
    t, linear = curves.linear_mean
    np.testing.assert_allclose(linear, region_oracle(events, t, "linear"), atol=1e-12)
    # breakpoints: the union of the region's knot times
    knot_times = {float(k) for x in range(4, 8) for y in range(3)
                  if ((events["x"] == x) & (events["y"] == y)).any()
                  for k in slow_knots(events, x, y)[0]}
    assert sorted(knot_times) == t.tolist()


def test_crossings_sit_on_the_plotted_curves_at_threshold_levels(rng):
    events = float_stream(rng)
    theta = 0.1
    curves = region_curves(events, SENSOR, FACTOR, PIXEL, ["event_count", "linear", "cubic"],
                           threshold=theta)
    figure = curve_figure(curves)
    for name, kind in (("linear", "linear"), ("cubic", "cubic")):
        curve = lines(figure, f"mean:{kind}")
        for suffix in ("on", "off"):
            marks = lines(figure, f"crossings:{name}:{suffix}")
            t, level = marks.get_xdata(), marks.get_ydata()
            assert len(t) > 0
            np.testing.assert_allclose(level / theta, np.round(level / theta), atol=1e-12)
            if kind == "linear":
                on_curve = np.interp(t, curve.get_xdata(), curve.get_ydata())
            else:  # the cubic curve is sampled at every output event
                on_curve = curve.get_ydata()[np.searchsorted(curve.get_xdata(), t)]
            np.testing.assert_allclose(on_curve, level, atol=1e-9)
    # EventCount: the level crossed is between the mean just before and just after the event
    step = lines(figure, "mean:event_count")
    st, sm = step.get_xdata(), step.get_ydata()
    for suffix, sign in (("on", 1), ("off", -1)):
        marks = lines(figure, f"crossings:event_count:{suffix}")
        for t, level in zip(marks.get_xdata(), marks.get_ydata(), strict=True):
            before = sm[np.searchsorted(st, t, side="left") - 1]
            after = sm[np.searchsorted(st, t, side="right") - 1]
            assert sign * (after - level) >= -1e-12 and sign * (level - before) > 0


def test_pixel_levels_and_event_count_mean_by_hand():
    # pixel (4, 0): ON at 0, ON at 10, OFF at 30; pixel (5, 1): OFF at 20; recording ends at 40
    ev = Events.from_columns([4, 4, 5, 4, 0], [0, 0, 1, 0, 5], [0, 10, 20, 30, 40],
                             [1, 1, 0, 0, 1])
    curves = region_curves(ev, SENSOR, FACTOR, PIXEL, [])
    (xy_a, t_a, l_a), (xy_b, t_b, l_b) = curves.pixel_levels
    assert (xy_a, t_a.tolist(), l_a.tolist()) == ((4, 0), [0, 0, 10, 30, 40], [0, 1, 2, 1, 1])
    assert (xy_b, t_b.tolist(), l_b.tolist()) == ((5, 1), [0, 20, 40], [0, -1, -1])
    t, mean = curves.count_mean
    assert t.tolist() == [0, 0, 10, 20, 30, 40]
    np.testing.assert_allclose(mean * 12, [0, 1, 2, 1, 0, 0])
    assert curves.pixels_in_region == 12 and curves.region == (4, 8, 0, 3)
    # linear: pixel a 0 -> 1 (t 0) -> 2 (t 10) -> 1 (t 30) -> 1; pixel b 0 -> -1 (t 20) -> -1
    t, linear = curves.linear_mean
    assert t.tolist() == [0, 10, 20, 30, 40]
    np.testing.assert_allclose(linear * 12, [1, 2 - 0.5, 1.5 - 1, 1 - 1, 1 - 1])


def test_edge_regions_count_only_pixels_inside_the_sensor():
    ev = Events.from_columns([8], [6], [0], [1])
    curves = region_curves(ev, (9, 7, 2), (4, 3), (2, 2), ["event_count"], threshold=1.0)
    assert curves.pixels_in_region == 1
    assert curves.events["event_count"].t.tolist() == [0.0]  # 1 event / 1 pixel reaches 1


def test_an_empty_region_and_an_empty_recording_render(rng):
    events = random_stream(rng, 100, SENSOR)
    events = events[events["x"] < 4]  # nothing in PIXEL's region
    figure = curve_figure(region_curves(events, SENSOR, FACTOR, PIXEL))
    assert lines(figure, "mean:cubic").get_ydata().tolist() == [0.0, 0.0]
    assert len(lines(figure, "events:cubic:on").get_xdata()) == 0
    figure.canvas.draw()
    empty = np.empty(0, dtype=DVS_DTYPE)
    figure = curve_figure(region_curves(empty, SENSOR, FACTOR, PIXEL))
    figure.canvas.draw()
    assert not [a for a in figure.axes[0].lines if (a.get_gid() or "").startswith("pixel:")]


def test_bad_pixels_are_refused(rng):
    events = random_stream(rng, 10, SENSOR)
    with pytest.raises(ValueError, match=r"pixel \(2, 0\) is outside the 2x2 output sensor"):
        region_curves(events, SENSOR, FACTOR, (2, 0))
    with pytest.raises(ValueError, match="pair of integers"):
        region_curves(events, SENSOR, FACTOR, (0.5, 0))
    with pytest.raises(ValueError, match="pair of integers"):
        region_curves(events, SENSOR, FACTOR, 3)


@dataclass(frozen=True)
class PhotocurrentPooling(Downscaler):
    """A stand-in with the registry class's name and settings (its output is not used here)."""

    method = DOWNSAMPLE

    contrast: float = 0.5
    threshold: float | None = None

    def kernel(self, events: Events) -> Events:
        return Events.empty(events.t.dtype, events.device)


def test_photocurrent_curve_is_the_log_mean_intensity_in_levels():
    ev = Events.from_columns([4, 4, 5, 4], [0, 0, 1, 0], [0, 10, 20, 30], [1, 1, 0, 0])
    c = 0.5
    curves = region_curves(ev, SENSOR, FACTOR, PIXEL,
                           [PhotocurrentPooling(SENSOR, FACTOR, contrast=c)])
    t, value = curves.photocurrent
    # intensities exp(c L) of the 12 pixels (10 idle at 1) after each event
    sums = [12, 11 + np.exp(c), 11 + np.exp(2 * c), 10 + np.exp(2 * c) + np.exp(-c),
            10 + np.exp(c) + np.exp(-c), 10 + np.exp(c) + np.exp(-c)]
    np.testing.assert_allclose(value, np.log(np.array(sums) / 12) / c, rtol=1e-12)
    assert t.tolist() == [0, 0, 10, 20, 30, 30]
    assert curves.events["PhotocurrentPooling"].threshold == 1.0  # theta = c by default
    figure = curve_figure(region_curves(ev, SENSOR, FACTOR, PIXEL,
                                        [PhotocurrentPooling(SENSOR, FACTOR)]))
    assert len(lines(figure, "mean:photocurrent").get_xdata()) == 6


def test_threshold_goes_to_contrast_methods_only(rng):
    events = random_stream(rng, 200, SENSOR)
    curves = region_curves(events, SENSOR, FACTOR, PIXEL, ["event_count", "cubic", "lif"],
                           threshold=0.75)
    assert curves.events["event_count"].threshold == 0.75
    assert curves.events["cubic"].threshold == 0.75
    assert curves.events["lif"].threshold is None and curves.events["lif"].level is None
    own = EventCount(SENSOR, FACTOR, threshold=2.0)
    curves = region_curves(events, SENSOR, FACTOR, PIXEL, [own, LinearEstimation(SENSOR, FACTOR),
                                                           CubicEstimation(SENSOR, FACTOR)],
                           threshold=0.75)
    assert [r.threshold for r in curves.events.values()] == [2.0, 1.0, 1.0]


def test_ground_truth_events_at_the_pixel_get_their_own_row(rng):
    events = random_stream(rng, 100, SENSOR)
    truth = random_stream(rng, 50, (2, 2, 2))
    figure = curve_figure(region_curves(events, SENSOR, FACTOR, PIXEL, ["cubic"],
                                        ground_truth=truth))
    here = truth[(truth["x"] == PIXEL[0]) & (truth["y"] == PIXEL[1])]
    for polarity, suffix in ((True, "on"), (False, "off")):
        np.testing.assert_array_equal(
            lines(figure, f"events:ground truth:{suffix}").get_xdata(),
            here["t"][here["p"] == polarity].astype(np.float64))


def test_a_method_given_twice_keeps_both_results(rng):
    events = random_stream(rng, 300, SENSOR)
    curves = region_curves(events, SENSOR, FACTOR, PIXEL,
                           [EventCount(SENSOR, FACTOR, threshold=0.25), "event_count"])
    assert list(curves.events) == ["event_count", "event_count 2"]
    assert [r.threshold for r in curves.events.values()] == [0.25, 1.0]


def test_time_axis_counts_from_the_recording_start(rng):
    events = random_stream(rng, 200, SENSOR, t_max=300_000)
    events["t"] += 1_605_537_493_718_000  # absolute Unix microseconds, as AEDAT4 stores them
    figure = curve_figure(region_curves(events, SENSOR, FACTOR, PIXEL, ["event_count"]))
    figure.canvas.draw()
    axis = figure.axes[1]
    labels = [tick.get_text() for tick in axis.get_xticklabels()]
    start = float(events["t"].min())
    positions = [(v - start) / 1000 for v in axis.get_xticks()]  # ms from the start, by hand
    assert axis.get_xlabel() == "time from the recording's start (ms)"
    assert labels[0] == "0" and [float(text) for text in labels] == pytest.approx(positions)
    assert all(float(text) == round(float(text)) for text in labels)  # round numbers
