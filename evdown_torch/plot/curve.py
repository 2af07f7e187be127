"""The paper's Figure 5 for one output pixel: what each method watches and what it emits.

:func:`region_curves` computes, for the region behind one output pixel, the values the kernels
work with, from the kernels' own machinery (docs/semantics.md, methods 3 to 5 and 7):

* each pixel's level ``L_p`` (ON +1, OFF -1) after each of its events;
* the region's mean level ``M_r = sum L_p / n_r`` after each event (what EventCount watches);
* ``M_r`` under the linear reconstruction, at the region's breakpoints (exact: it is linear in
  between), from the knots of
  :func:`~evdown_torch.transforms.functional.estimation.knots.pixel_knots`;
* ``M_r`` under the cubic reconstruction, on a fine grid that includes every breakpoint and
  every output event of the estimators, from the same knots and the PCHIP slopes of
  :func:`~evdown_torch.transforms.functional.estimation.cubic.pchip_slopes`;
* with PhotocurrentPooling (events mode), ``log I_r / c`` (in level units, so it shares the
  axis: ``log I_r`` with ``c -> 0`` tends to ``c M_r``);
* the events each method emits at the pixel (the transforms' own output), and for the methods
  that follow the reference rule the threshold level each event crossed, ``theta * q`` with
  ``q`` the running sum of the emitted polarities.

:func:`curve_figure` draws them on one time axis.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, NamedTuple, cast

import numpy as np
import torch
from torch import Tensor

from evdown_torch._regions import region_of, region_pixel_count
from evdown_torch.checks import check_factor, check_positive_int, check_sensor_size, output_size
from evdown_torch.events import Events, EventsLike, sort_by_time, to_events
from evdown_torch.plot import _mpl
from evdown_torch.plot.recording import method_name
from evdown_torch.time_units import display_unit
from evdown_torch.transforms import Downscaler, ThresholdDownscaler
from evdown_torch.transforms.estimation import CubicEstimation, LinearEstimation
from evdown_torch.transforms.event_count import EventCount
from evdown_torch.transforms.functional.estimation.cubic import pchip_slopes
from evdown_torch.transforms.functional.estimation.knots import pixel_knots, region_chunks
from evdown_torch.transforms.registry import METHODS, make_method

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["MethodEvents", "RegionCurves", "curve_figure", "region_curves"]

#: Samples of the cubic reconstruction over the recording (besides breakpoints and events).
SAMPLES = 2000

#: Most threshold lines drawn per threshold (a tiny threshold would fill the plot).
MAX_LINES = 60


class MethodEvents(NamedTuple):
    """The events one method emits at the output pixel.

    Attributes:
        t: ``(K,)`` float64 times (the transform's output ``t``, microseconds).
        on: ``(K,)`` bool polarity.
        level: ``(K,)`` float64 threshold level crossed, in level units, for methods that
            follow the reference rule; ``None`` for the others.
        threshold: the method's threshold in level units (``None`` likewise).
    """

    t: np.ndarray
    on: np.ndarray
    level: np.ndarray | None
    threshold: float | None


@dataclass(frozen=True)
class RegionCurves:
    """What happens in the region behind one output pixel (all times in microseconds).

    Attributes:
        pixel: the output pixel ``(X, Y)``.
        region: ``(x0, x1, y0, y1)``, the input pixels ``x0 <= x < x1``, ``y0 <= y < y1``.
        pixels_in_region: ``n_r``.
        t_start: first timestamp of the whole recording.
        t_end: last timestamp of the whole recording.
        input_events: ``(t, on)`` of the region's input events, in time order.
        pixel_levels: per active input pixel, ``((x, y), t, level)``: its level after each of
            its events, from ``(t_start, 0)`` to ``t_end`` (draw as steps).
        count_mean: ``(t, M_r)`` after each region event, from ``(t_start, 0)`` to ``t_end``
            (draw as steps): what EventCount watches.
        linear_mean: ``(t, M_r)`` of the linear reconstruction at the region's breakpoints.
        cubic_mean: ``(t, M_r)`` of the cubic reconstruction on a fine grid.
        photocurrent: ``(t, log I_r / c)`` as steps, with PhotocurrentPooling (events mode),
            else ``None``.
        events: method name -> :class:`MethodEvents`, in the order of the methods (a method
            given twice is numbered: ``"event_count"``, ``"event_count 2"``), then
            ``"ground truth"`` when given.
    """

    pixel: tuple[int, int]
    region: tuple[int, int, int, int]
    pixels_in_region: int
    t_start: float
    t_end: float
    input_events: tuple[np.ndarray, np.ndarray]
    pixel_levels: list[tuple[tuple[int, int], np.ndarray, np.ndarray]]
    count_mean: tuple[np.ndarray, np.ndarray]
    linear_mean: tuple[np.ndarray, np.ndarray]
    cubic_mean: tuple[np.ndarray, np.ndarray]
    photocurrent: tuple[np.ndarray, np.ndarray] | None
    events: dict[str, MethodEvents] = field(default_factory=dict)


def _is_photocurrent(transform: Downscaler) -> bool:
    return type(transform).__name__ == "PhotocurrentPooling"


def _level_threshold(transform: Downscaler) -> float | None:
    """The threshold, in level units, of a method that follows the reference rule."""
    if isinstance(transform, (EventCount, LinearEstimation, CubicEstimation)):
        return float(transform.threshold)
    if _is_photocurrent(transform):
        contrast = float(cast(Any, transform).contrast)
        theta = getattr(transform, "threshold", None)
        return (contrast if theta is None else float(theta)) / contrast
    return None


def build_methods(
    names: Sequence[str | Downscaler] | None,
    sensor_size: tuple[int, int, int],
    factor: int | tuple[int, int],
    threshold: float | None = None,
) -> list[Downscaler]:
    """Transforms for registry names; transforms are kept as they are.

    ``threshold`` goes to the contrast-threshold methods, EventCount, LinearEstimation and
    CubicEstimation.
    """
    out = []
    for method in list(METHODS) if names is None else names:
        if isinstance(method, Downscaler):
            out.append(method)
            continue
        settings = {}
        if threshold is not None and isinstance(method, str) and method in METHODS and (
            issubclass(METHODS[method], ThresholdDownscaler)
        ):
            settings["threshold"] = threshold
        out.append(make_method(method, sensor_size, factor, **settings))
    return out


def _numpy_t(t: torch.Tensor) -> np.ndarray:
    return t.to(torch.float64).cpu().numpy()


def _reconstructions(events: Events, t_start: Tensor, t_end: Tensor, factor: tuple[int, int],
                     out_width: int, n_r: int, grid: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The reconstructions, from the kernels' knots and slopes.

    The cubic one's ``M_r`` at ``grid`` (float64 offsets from ``t_start``), and the linear
    one's at the region's breakpoints (offsets).
    """
    chunk = next(region_chunks(events, factor=factor, out_width=out_width))
    knots = pixel_knots(chunk, factor=factor, t_start=t_start, t_end=t_end)
    slope, width, rise = (v.cpu().numpy() for v in pchip_slopes(knots))
    knot_t = _numpy_t(knots.t - t_start)
    level = knots.level.cpu().numpy().astype(np.float64)
    bp = np.unique(_numpy_t(knots.bp_t - t_start))
    starts = np.flatnonzero(knots.first.cpu().numpy())
    stops = np.append(starts[1:], knot_t.shape[0])
    cubic = np.zeros_like(grid)
    linear = np.zeros_like(bp)
    for a, b in zip(starts, stops, strict=True):
        if b - a == 1:  # one knot: a constant
            cubic += level[a]
            linear += level[a]
            continue
        linear += np.interp(bp, knot_t[a:b], level[a:b])
        seg = a + np.clip(np.searchsorted(knot_t[a:b], grid, side="right") - 1, 0, b - a - 2)
        s = (grid - knot_t[seg]) / width[seg]
        c1 = width[seg] * slope[seg]
        c2_end = width[seg] * slope[seg + 1]
        c2 = 3 * rise[seg] - 2 * c1 - c2_end
        c3 = c1 + c2_end - 2 * rise[seg]
        cubic += level[seg] + s * (c1 + s * (c2 + s * c3))
    return cubic / n_r, bp, linear / n_r


def region_curves(
    events: EventsLike,
    sensor_size: tuple[int, int, int],
    factor: int | tuple[int, int],
    pixel: tuple[int, int],
    methods: Sequence[str | Downscaler] | None = None,
    *,
    threshold: float | None = None,
    samples: int = SAMPLES,
    ground_truth: EventsLike | None = None,
) -> RegionCurves:
    """What each method sees and emits at one output pixel.

    Args:
        events: a Tonic structured array, an ``(N, 4)`` tensor or Events (``t`` in
            microseconds).
        sensor_size: input ``(W, H, P)``.
        factor: ``f`` or ``(fx, fy)``.
        pixel: the output pixel ``(X, Y)``.
        methods: registry names or transforms (default: every registry method).
        threshold: contrast threshold of the methods built by name (default: theirs).
        samples: points of the cubic curve over the recording (plus breakpoints and events).
        ground_truth: events on the output sensor to show beside the methods' (e.g. a
            synthetic recording's low-resolution rendering), under the name
            ``"ground truth"``.

    Returns:
        The :class:`RegionCurves`.

    Raises:
        ValueError: for a pixel outside the output sensor or bad settings.

    Example:
        >>> ev = torch.tensor([[0, 0, 0, 1], [1, 0, 10, 1]])
        >>> c = region_curves(ev, (2, 1, 2), (2, 1), (0, 0), ["linear"], threshold=0.25)
        >>> c.linear_mean[1].tolist(), c.events["linear"].t.tolist()
        ([0.5, 1.0], [0.0, 0.0, 5.0, 10.0])
    """
    sensor_size = check_sensor_size(sensor_size)
    fx, fy = check_factor(factor, sensor_size)
    out_w, out_h, _ = output_size(sensor_size, (fx, fy))
    px, py = _check_pixel(pixel, out_w, out_h)
    samples = check_positive_int("samples", samples)
    transforms = build_methods(methods, sensor_size, factor, threshold)
    ev = sort_by_time(to_events(events, sensor_size)[0])
    w, h, _ = sensor_size
    region = (px * fx, min(px * fx + fx, w), py * fy, min(py * fy + fy, h))
    n_r = int(region_pixel_count(torch.tensor([py * out_w + px]), sensor_size, (fx, fy)))
    rx, ry = region_of(ev, (fx, fy))
    sub = ev.select((rx == px) & (ry == py))
    if ev.num_events:
        t0_tensor, t1_tensor = ev.t[0], ev.t[-1]
        t_start, t_end = float(t0_tensor), float(t1_tensor)
    else:
        t_start = t_end = 0.0
    t = _numpy_t(sub.t)
    on = sub.p.cpu().numpy()
    step = np.where(on, 1, -1)
    local = ((sub.y - region[2]) * fx + (sub.x - region[0])).cpu().numpy()

    # Each pixel's level after its events; the region's sum after each event.
    order = np.argsort(local, kind="stable")
    level_after = np.empty(t.shape[0], dtype=np.int64)
    pixel_levels = []
    bounds = np.flatnonzero(np.diff(local[order], prepend=-1, append=-1))
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        at = order[a:b]
        levels = np.cumsum(step[at])
        level_after[at] = levels
        lx, ly = region[0] + int(local[at[0]]) % fx, region[2] + int(local[at[0]]) // fx
        pixel_levels.append(((lx, ly), np.concatenate([[t_start], t[at], [t_end]]),
                             np.concatenate([[0], levels, levels[-1:]]).astype(np.float64)))
    total = np.cumsum(step)
    count_mean = (np.concatenate([[t_start], t, [t_end]]),
                  np.concatenate([[0], total, total[-1:] if total.size else [0]]) / n_r)

    # What each method emits at the pixel, and the level each reference-rule event crossed.
    results: dict[str, MethodEvents] = {}
    photocurrent = None
    for transform in transforms:
        out = cast(Events, transform(ev))  # Events in, Events out
        hit = (out.x == px) & (out.y == py)
        out_t, out_on = _numpy_t(out.t[hit]), out.p[hit].cpu().numpy()
        theta = _level_threshold(transform)
        crossed = None if theta is None else theta * np.cumsum(np.where(out_on, 1.0, -1.0))
        name, copy = method_name(transform), 1
        while name in results:  # the same method twice (other settings): number them
            copy += 1
            name = f"{method_name(transform)} {copy}"
        results[name] = MethodEvents(out_t, out_on, crossed, theta)
        if _is_photocurrent(transform) and getattr(transform, "fps", None) is None:
            c = float(cast(Any, transform).contrast)
            change = np.exp(c * level_after) - np.exp(c * (level_after - step))
            log_mean = np.log1p(np.cumsum(change) / n_r) / c
            last = log_mean[-1:] if log_mean.size else [0]  # a region without events stays at 0
            photocurrent = (count_mean[0], np.concatenate([[0], log_mean, last]))
    if ground_truth is not None:
        truth = sort_by_time(to_events(ground_truth, (out_w, out_h, 2))[0])
        hit = (truth.x == px) & (truth.y == py)
        results["ground truth"] = MethodEvents(_numpy_t(truth.t[hit]), truth.p[hit].cpu().numpy(),
                                               None, None)

    # The linear and cubic reconstructions, from the kernels' knots and PCHIP slopes.
    if sub.num_events:
        marks = [r.t for r in results.values()]
        grid = np.unique(np.concatenate([np.linspace(t_start, t_end, samples), *marks]))
        cubic, bp, linear = _reconstructions(sub, t0_tensor, t1_tensor, (fx, fy), out_w, n_r,
                                        grid - t_start)
        linear_mean, cubic_mean = (bp + t_start, linear), (grid, cubic)
    else:
        flat = (np.array([t_start, t_end]), np.zeros(2))
        linear_mean = cubic_mean = flat
    return RegionCurves(
        (px, py), region, n_r, t_start, t_end, (t, on), pixel_levels, count_mean, linear_mean,
        cubic_mean, photocurrent, results,
    )


def _check_pixel(pixel: Any, out_w: int, out_h: int) -> tuple[int, int]:
    try:
        px, py = (int(v) for v in pixel)
        ok = (px, py) == tuple(pixel)
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"pixel must be a pair of integers (X, Y), got {pixel!r}")
    if not (0 <= px < out_w and 0 <= py < out_h):
        raise ValueError(
            f"pixel ({px}, {py}) is outside the {out_w}x{out_h} output sensor "
            f"(0 <= X < {out_w}, 0 <= Y < {out_h})"
        )
    return px, py


COLOURS = {
    "event_count": "tab:green",
    "linear": "tab:red",
    "cubic": "tab:purple",
    "photocurrent": "tab:brown",
    "downsample": "tab:gray",
    "funnelling": "tab:olive",
    "lif": "tab:cyan",
    "ground truth": "black",
}
ON_COLOUR, OFF_COLOUR = "tab:orange", "tab:blue"


def curve_figure(curves: RegionCurves, *, width: float = 10.0, dpi: float = 100.0) -> Figure:
    """The paper's Figure 5 for one output pixel.

    Top: the region's pixels' levels (thin grey steps), the region's mean level as EventCount
    (steps), the linear and the cubic reconstructions see it, with PhotocurrentPooling its
    ``log I_r / c``, the threshold lines ``theta * k``, and the events of the reference-rule
    methods where they cross them (triangles up ON, down OFF). Bottom: every method's events
    at the pixel on one row each (ON orange, OFF blue), under the region's input events. The
    time axis is in milliseconds (the artists hold microseconds, the events' own ``t``).

    Artists carry ids (``get_gid()``): ``"pixel:x,y"``, ``"mean:event_count"``,
    ``"mean:linear"``, ``"mean:cubic"``, ``"mean:photocurrent"``, ``"threshold:NAME"``,
    ``"crossings:NAME:on"``/``"off"`` (top) and ``"events:NAME:on"``/``"off"`` (bottom,
    ``NAME`` a method or ``input``).

    Args:
        curves: what to draw, from :func:`region_curves`.
        width: figure width, inches.
        dpi: resolution.

    Returns:
        A matplotlib ``Figure`` with two axes sharing the time axis.
    """
    mpl = _mpl.matplotlib()
    rows = 1 + len(curves.events)
    fig = _mpl.new_figure(width, 4.2 + 0.22 * rows, dpi)
    grid = fig.add_gridspec(2, 1, height_ratios=[4.0, 0.35 + 0.22 * rows], hspace=0.08)
    top = fig.add_subplot(grid[0])
    bottom = fig.add_subplot(grid[1], sharex=top)

    for (x, y), t, level in curves.pixel_levels:
        top.plot(t, level, drawstyle="steps-post", color="0.6", lw=0.7, alpha=0.6,
                 gid=f"pixel:{x},{y}")
    if curves.pixel_levels:
        top.lines[0].set_label("pixel levels $L_p$")
    top.plot(*curves.count_mean, drawstyle="steps-post", color=COLOURS["event_count"], lw=1.2,
             label="mean level $M_r$ (event count)", gid="mean:event_count")
    top.plot(*curves.linear_mean, color=COLOURS["linear"], lw=1.2,
             label="linear reconstruction", gid="mean:linear")
    top.plot(*curves.cubic_mean, color=COLOURS["cubic"], lw=1.2,
             label="cubic reconstruction", gid="mean:cubic")
    if curves.photocurrent is not None:
        top.plot(*curves.photocurrent, drawstyle="steps-post", color=COLOURS["photocurrent"],
                 lw=1.2, label="log mean photocurrent / c", gid="mean:photocurrent")

    values = np.concatenate([v for _, _, v in curves.pixel_levels] + [
        curves.count_mean[1], curves.linear_mean[1], curves.cubic_mean[1], np.zeros(1)])
    low, high = float(values.min()), float(values.max())
    drawn: set[float] = set()
    for name, result in curves.events.items():
        if result.threshold is None or result.level is None:
            continue
        colour = COLOURS.get(name, "black")
        theta = result.threshold
        first, last = int(np.floor(low / theta)), int(np.ceil(high / theta))
        if theta not in drawn and last - first < MAX_LINES:
            drawn.add(theta)
            for k in range(first, last + 1):
                top.axhline(theta * k, color="0.3" if len(drawn) == 1 else colour, lw=0.5,
                            ls=":", gid=f"threshold:{name}",
                            label=f"thresholds $\\theta k$, $\\theta$ = {theta:g}"
                            if k == first else None)
        for polarity, marker in ((True, "^"), (False, "v")):
            sel = result.on == polarity
            top.plot(result.t[sel], result.level[sel], ls="none", marker=marker, ms=5,
                     color=colour, markeredgecolor="black", markeredgewidth=0.4,
                     gid=f"crossings:{name}:{'on' if polarity else 'off'}")
    top.set_ylabel("level (events per pixel)")
    top.legend(fontsize=7, loc="upper left", ncols=2, framealpha=0.8)
    x0, x1, y0, y1 = curves.region
    n_in = curves.input_events[0].shape[0]
    top.set_title(
        f"output pixel {curves.pixel}: input x {x0}-{x1 - 1}, y {y0}-{y1 - 1} "
        f"($n_r$ = {curves.pixels_in_region}), {n_in} input events", fontsize=9)
    top.tick_params(labelbottom=False)

    names = ["input", *curves.events]
    rasters = [curves.input_events] + [(r.t, r.on) for r in curves.events.values()]
    for row, (name, (t, on)) in enumerate(zip(names, rasters, strict=True)):
        y = rows - 1 - row
        for polarity, colour in ((True, ON_COLOUR), (False, OFF_COLOUR)):
            sel = on == polarity
            bottom.plot(t[sel], np.full(int(sel.sum()), float(y)), ls="none", marker="|", ms=7,
                        color=colour, gid=f"events:{name}:{'on' if polarity else 'off'}")
    bottom.set_yticks(range(rows))
    bottom.set_yticklabels(
        [f"{n} ({len(r[0])})" for n, r in zip(names, rasters, strict=True)][::-1], fontsize=7)
    bottom.set_ylim(-0.6, rows - 0.4)
    span = max(curves.t_end - curves.t_start, 1.0)
    bottom.set_xlim(curves.t_start - 0.01 * span, curves.t_end + 0.01 * span)
    unit, scale = display_unit(curves.t_end - curves.t_start)  # from the recording's start
    ticks = mpl.ticker.MaxNLocator(8).tick_values(0, span / scale)  # round in that unit
    bottom.xaxis.set_major_locator(mpl.ticker.FixedLocator(curves.t_start + ticks * scale))
    bottom.xaxis.set_major_formatter(
        mpl.ticker.FuncFormatter(lambda v, _: f"{(v - curves.t_start) / scale:.6g}"))
    bottom.set_xlabel(f"time from the recording's start ({unit})")
    fig.subplots_adjust(left=0.14, right=0.98, top=1 - 0.3 / fig.get_figheight(),
                        bottom=0.5 / fig.get_figheight())
    return fig
