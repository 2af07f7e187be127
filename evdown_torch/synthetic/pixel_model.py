"""A DVS pixel model: ON and OFF thresholds, refractory period, readout, noise.

Each pixel watches its log intensity ``L(t)`` (natural log of the photocurrent), known at
sample times and linear in between, and follows the reference rule of ``docs/semantics.md``
with separate thresholds, as a real DVS pixel's two comparators do: it keeps a reference level
``r``; whenever ``L`` reaches ``r + theta_on`` it emits ON and raises ``r`` by ``theta_on``,
whenever ``L`` reaches ``r - theta_off`` it emits OFF and lowers ``r`` by ``theta_off``.
Several levels crossed between two samples give several events, each at its own linearly
interpolated time, rounded to the nearest microsecond (halves upward). After a reversal the
full threshold of the other polarity must be covered. The reference starts at
``L(t_0) - offset * theta`` (``theta_on`` for a positive offset, ``theta_off`` otherwise): the
offset in ``(-1, 1)`` places the pixel's starting state within its window (the scene renderer
draws it per pixel, as a real sensor starts in an arbitrary state). With one threshold for
both polarities this is exactly the contract's rule.

The rule itself lives once, in :mod:`evdown_torch.transforms.functional.reference`: its
closed form (one threshold) and its scan over monotone runs (two thresholds).

The refractory period then drops every event that comes less than ``refractory_us`` after the
pixel's previous emitted event; the reference is not changed by dropped events. The readout
stamps events in bursts (:func:`readout_times`). Background activity and hot pixels are
Poisson processes sampled directly, in time proportional to the number of noise events.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from evdown_torch._tensors import where_true
from evdown_torch.checks import (
    check_non_negative_float,
    check_non_negative_int,
    check_positive_float,
    check_positive_int,
    check_unit_interval,
)
from evdown_torch.synthetic.two_thresholds import (
    PixelSamples,
    two_threshold_counts,
    two_threshold_crossings,
)
from evdown_torch.transforms.functional.reference import crossings, reference_index

__all__ = [
    "PixelModelConfig",
    "noise_events",
    "pixel_events",
    "readout_times",
    "refractory_mask",
]


@dataclass(frozen=True)
class PixelModelConfig:
    """Parameters of the simulated pixel array; defaults lie in the range of a DVS128.

    Attributes:
        threshold: nominal contrast threshold, natural-log units: the geometric mean of the
            ON and the OFF threshold (0.12, a 13 % change of photocurrent).
        on_off_spread: largest ``|log(theta_on / theta_off)|`` of a recording's bias
            settings (0.35): each scene draws its balance (``GestureScene.bias``) in
            ``[-1, 1]`` times this, so the ON share varies by recording (about 0.41 to
            0.59 for a passing edge).
        threshold_mismatch: standard deviation of each pixel's ON and OFF threshold
            (independently) around the recording's, natural-log units (0.03); per-pixel
            thresholds are clipped to at least a quarter of the nominal one.
        refractory_us: refractory period, microseconds (500): a pixel emits nothing for this
            long after each event.
        readout_us: readout burst, microseconds (40; see :func:`readout_times`): events are
            stamped with the start of the burst that reads them out, so events of one burst
            share a timestamp, as a real sensor's row-wise readout stamps them (0: exact
            times). 40 us makes EventFunnelling at factor 4 remove about the 4 % it removes
            from DVS128 Gesture (the paper's Table 1).
        background_rate_hz: background-activity rate per pixel, events per second (0.2);
            each event lands on a uniformly random pixel and time, ON or OFF with equal odds.
        hot_pixel_fraction: probability that a pixel is hot (2e-4, about three pixels of a
            128 x 128 sensor).
        hot_pixel_rate_hz: firing rate of each hot pixel, events per second (20.0).
        max_step_px: simulation step bound, pixels: between two samples of the scene no
            joint moves more than this (1.0); log intensity is linear between samples.
        max_step_us: simulation step bound, microseconds (20000), for slow motions.

    Example:
        >>> PixelModelConfig(threshold=0.3).refractory_us
        500
    """

    threshold: float = 0.12
    on_off_spread: float = 0.35
    threshold_mismatch: float = 0.03
    refractory_us: int = 500
    readout_us: int = 40
    background_rate_hz: float = 0.2
    hot_pixel_fraction: float = 2e-4
    hot_pixel_rate_hz: float = 20.0
    max_step_px: float = 1.0
    max_step_us: int = 20000

    def __post_init__(self) -> None:
        check_positive_float("threshold", self.threshold)
        check_non_negative_float("on_off_spread", self.on_off_spread)
        check_non_negative_float("threshold_mismatch", self.threshold_mismatch)
        check_non_negative_int("refractory_us", self.refractory_us)
        check_non_negative_int("readout_us", self.readout_us)
        check_non_negative_float("background_rate_hz", self.background_rate_hz)
        check_unit_interval("hot_pixel_fraction", self.hot_pixel_fraction)
        check_non_negative_float("hot_pixel_rate_hz", self.hot_pixel_rate_hz)
        check_positive_float("max_step_px", self.max_step_px)
        check_positive_int("max_step_us", self.max_step_us)


def round_time(t: Tensor) -> Tensor:
    """Real times to int64 microseconds, to the nearest, halves upward (``floor(t + 0.5)``)."""
    return torch.floor(t + 0.5).to(torch.int64)


def refractory_mask(pixel: Tensor, t: Tensor, refractory_us: int) -> Tensor:
    """Which events survive a refractory period.

    Per pixel, in time order, an event is kept when it comes at least ``refractory_us``
    after the pixel's previous kept event (the first event of a pixel is always kept).

    Args:
        pixel: ``(N,)`` int64 pixel index, non-decreasing.
        t: ``(N,)`` int64 times, non-decreasing within each pixel.
        refractory_us: the period, microseconds (0 keeps everything).

    Returns:
        ``(N,)`` bool mask of kept events.

    Example:
        >>> mask = refractory_mask(torch.tensor([0, 0, 0, 0, 1]),
        ...                        torch.tensor([0, 300, 600, 700, 650]), 500)
        >>> mask.tolist()
        [True, False, True, False, True]
    """
    n = t.shape[0]
    keep = torch.ones(n, dtype=torch.bool, device=t.device)
    if refractory_us <= 0 or n < 2:
        return keep
    start = torch.ones(n, dtype=torch.bool, device=t.device)
    start[1:] = (pixel[1:] != pixel[:-1]) | (t[1:] - t[:-1] >= refractory_us)
    if bool(start.all()):
        return keep
    # Events of one cluster (gaps shorter than the period) are decided by following, from the
    # cluster's first event, "the first event at least one period later"; a chain stops where
    # it reaches the next cluster's first event, which is kept anyway.
    t_rel = t - t.min()
    span = int(t_rel.max()) + refractory_us + 1
    key = pixel * span + t_rel
    following = torch.searchsorted(key, key + refractory_us)
    keep = start.clone()
    frontier = where_true(start & ~torch.cat([start[1:], start.new_ones(1)]))
    while frontier.numel() > 0:
        frontier = following[frontier]
        frontier = frontier[frontier < n]
        frontier = frontier[~keep[frontier]]
        keep[frontier] = True
    return keep


def _per_pixel(name: str, value: float | Tensor, pixel: Tensor, positive: bool) -> Tensor:
    """A scalar or a per-pixel tensor, read at each sample's pixel, as float64."""
    if isinstance(value, Tensor):
        if value.ndim != 1:
            raise ValueError(f"{name} must be a number or a 1-D tensor indexed by pixel, "
                             f"got shape {tuple(value.shape)}")
        if pixel.numel() and int(pixel.max()) >= value.shape[0]:
            raise ValueError(f"{name} has {value.shape[0]} entries but pixel indices reach "
                             f"{int(pixel.max())}")
        out = value.to(device=pixel.device, dtype=torch.float64)[pixel]
        bad = ~torch.isfinite(out) | ((out <= 0) if positive else (out.abs() >= 1))
        if bool(bad.any()):
            what = "positive" if positive else "in (-1, 1)"
            raise ValueError(f"{name} must be finite and {what} at every pixel")
        return out
    if positive:
        value = check_positive_float(name, value)
    elif not isinstance(value, (int, float)) or isinstance(value, bool) or abs(value) >= 1:
        raise ValueError(f"{name} must be a number in (-1, 1), got {value!r}")
    return torch.full(pixel.shape, float(value), dtype=torch.float64, device=pixel.device)


def level_crossings(
    level: Tensor,
    t: Tensor,
    first: Tensor,
    *,
    base: Tensor,
    theta_on: Tensor,
    theta_off: Tensor | None,
    a_start: Tensor,
    b_start: Tensor,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Events of sampled pixels under the reference rule, with their exact (float) times.

    Args:
        level: ``(M,)`` float64 log intensity at each sample; samples of one pixel are
            contiguous and in time order.
        t: ``(M,)`` float64 sample times.
        first: ``(M,)`` bool, the sample is its pixel's first (it emits nothing).
        base: ``(M,)`` float64 reference level of the sample's pixel at counts ``(0, 0)``.
        theta_on: ``(M,)`` float64 ON threshold of the sample's pixel.
        theta_off: ``(M,)`` float64 OFF threshold, or None for one threshold (``theta_on``)
            for both polarities (the closed form, no scan).
        a_start: ``(M,)`` int64 ON count of the pixel before its first sample (read where
            ``first``); the reference is ``base + a * theta_on - b * theta_off``.
        b_start: ``(M,)`` int64 OFF count of the pixel before its first sample, likewise.

    Returns:
        ``(segment, time, on, a, b)``: per event the index of the sample ending its segment
        (int64), its float64 time and polarity (bool), ordered by sample then time; and the
        ``(M,)`` int64 counts after each sample (with one threshold, ``a`` holds the net
        count and ``b`` is 0).
    """
    if theta_off is None:
        u = (level - base) / theta_on
        floor_u = torch.floor(u)
        q = reference_index(floor_u.to(torch.int64), u == floor_u, first, a_start - b_start)
        q_before = torch.empty_like(q)
        q_before[1:] = q[:-1]
        found = crossings(torch.where(first, q, q_before), q)
        segment, on = found.move, found.on
        at = base.index_select(0, segment)
        at += found.level.to(torch.float64) * theta_on.index_select(0, segment)
        a, b = q, torch.zeros_like(q)
    else:
        samples = PixelSamples(level, first, base, theta_on, theta_off)
        a, b = two_threshold_counts(samples, a_start, b_start)
        segment, at, on = two_threshold_crossings(samples, a, b)
    x0 = level.index_select(0, segment - 1)
    x1 = level.index_select(0, segment)
    t0 = t.index_select(0, segment - 1)
    time = t0 + (at - x0) / (x1 - x0) * (t.index_select(0, segment) - t0)
    return segment, time, on, a, b


def start_reference(level: Tensor, offset: Tensor, theta_on: Tensor,
                    theta_off: Tensor | None) -> Tensor:
    """Reference level of a pixel starting at ``level`` with ``offset`` in ``(-1, 1)``.

    ``level - offset * theta_on`` for a positive offset, ``level - offset * theta_off``
    otherwise (``theta_on`` when there is one threshold).
    """
    theta = theta_on if theta_off is None else torch.where(offset > 0, theta_on, theta_off)
    return level - offset * theta


def pixel_events(
    pixel: Tensor,
    t: Tensor,
    log_intensity: Tensor,
    *,
    threshold: float | Tensor,
    off_threshold: float | Tensor | None = None,
    refractory_us: int = 0,
    offset: float | Tensor = 0.0,
) -> tuple[Tensor, Tensor, Tensor]:
    """Events of DVS pixels watching sampled, piecewise-linear log intensities.

    Args:
        pixel: ``(M,)`` integer pixel index of each sample; sorted (the samples of one pixel
            are contiguous).
        t: ``(M,)`` sample times, microseconds (integer or float), strictly increasing within
            each pixel.
        log_intensity: ``(M,)`` float natural-log intensity at each sample.
        threshold: ON contrast threshold, log units (for both polarities when
            ``off_threshold`` is None): a number, or a 1-D tensor indexed by pixel.
        off_threshold: OFF contrast threshold, as ``threshold``; None: the same as the ON
            threshold (the contract's one-threshold rule, solved in closed form).
        refractory_us: refractory period, microseconds.
        offset: initial state within the threshold window, in ``(-1, 1)``: the reference
            starts at ``L(t_first) - offset * theta`` with the ON threshold for a positive
            offset and the OFF threshold otherwise (a number or a per-pixel tensor).

    Returns:
        ``(pixel, t, p)``: int64 pixel index, int64 time (microseconds) and bool polarity
        (True for ON) of each event, sorted by time (ties by pixel).

    Raises:
        ValueError: for mismatched shapes, unsorted samples or bad thresholds.

    Example:
        A ramp up by 1 log unit over 1000 us and back down, ON threshold 0.25, OFF 0.4:

        >>> pix, t, p = pixel_events(torch.zeros(3, dtype=torch.long),
        ...                          torch.tensor([0, 1000, 2000]),
        ...                          torch.tensor([0.0, 1.0, 0.0]),
        ...                          threshold=0.25, off_threshold=0.4)
        >>> t.tolist(), p.tolist()
        ([250, 500, 750, 1000, 1400, 1800], [True, True, True, True, False, False])
    """
    pixel = torch.as_tensor(pixel)
    t = torch.as_tensor(t)
    log_intensity = torch.as_tensor(log_intensity)
    if not (pixel.ndim == t.ndim == log_intensity.ndim == 1) or not (
        pixel.shape == t.shape == log_intensity.shape
    ):
        raise ValueError(
            "pixel, t and log_intensity must be 1-D tensors of one length, got shapes "
            f"{tuple(pixel.shape)}, {tuple(t.shape)}, {tuple(log_intensity.shape)}"
        )
    if pixel.dtype.is_floating_point or pixel.dtype == torch.bool:
        raise TypeError(f"pixel must hold integers, got {pixel.dtype}")
    if not log_intensity.dtype.is_floating_point:
        raise TypeError(f"log_intensity must be a float tensor, got {log_intensity.dtype}")
    refractory_us = check_non_negative_int("refractory_us", refractory_us)
    pixel = pixel.to(torch.int64)
    t = t.to(torch.float64)
    device = t.device
    if pixel.numel() and int(pixel.min()) < 0:
        raise ValueError("pixel indices must be non-negative")
    if not bool(torch.isfinite(t).all()) or not bool(torch.isfinite(log_intensity).all()):
        raise ValueError("t and log_intensity must be finite")
    first = torch.ones(pixel.shape, dtype=torch.bool, device=device)
    first[1:] = pixel[1:] != pixel[:-1]
    if bool((pixel[1:] < pixel[:-1]).any()):
        raise ValueError("samples must be sorted by pixel (each pixel's samples contiguous)")
    if bool(((t[1:] <= t[:-1]) & ~first[1:]).any()):
        raise ValueError("sample times must increase strictly within each pixel")
    theta_on = _per_pixel("threshold", threshold, pixel, positive=True)
    theta_off = (None if off_threshold is None
                 else _per_pixel("off_threshold", off_threshold, pixel, positive=True))
    u = _per_pixel("offset", offset, pixel, positive=False)
    level = log_intensity.to(torch.float64)
    group = torch.cumsum(first, 0) - 1
    base = start_reference(level[first][group], u, theta_on, theta_off)
    zeros = torch.zeros(pixel.shape, dtype=torch.int64, device=device)
    segment, time, on, _, _ = level_crossings(level, t, first, base=base, theta_on=theta_on,
                                              theta_off=theta_off, a_start=zeros,
                                              b_start=zeros)
    ev_pixel = pixel[segment]
    ev_t = round_time(time)  # grouped by pixel, in time order within each
    keep = refractory_mask(ev_pixel, ev_t, refractory_us)
    ev_pixel, ev_t, on = ev_pixel[keep], ev_t[keep], on[keep]
    order = torch.sort(ev_t, stable=True).indices
    return ev_pixel[order], ev_t[order], on[order]


def readout_times(t: Tensor, readout_us: int) -> Tensor:
    """Timestamps after a burst readout: the start of the ``readout_us`` burst holding ``t``.

    A DVS reads its pixel array out in bursts (the arbiter serves a row's pending events
    together) and stamps a burst with one time. Modelled as a fixed grid of bursts from
    ``t = 0``: an event at ``t`` gets ``floor(t / readout_us) * readout_us``, so the events of
    one burst share a timestamp (and EventFunnelling finds the duplicates a real recording
    has). ``readout_us = 0`` keeps ``t``.

    Example:
        >>> readout_times(torch.tensor([0, 99, 100, 250]), 100).tolist()
        [0, 0, 100, 200]
    """
    if readout_us <= 1:
        return t
    return torch.div(t, readout_us, rounding_mode="floor") * readout_us


def noise_events(
    *,
    num_pixels: int,
    duration_us: int,
    background_rate_hz: float,
    hot_pixel_fraction: float,
    hot_pixel_rate_hz: float,
    generator: torch.Generator,
) -> tuple[Tensor, Tensor, Tensor]:
    """Background activity and hot-pixel events, sampled in O(number of events).

    Background activity: a Poisson number of events with mean
    ``background_rate_hz * num_pixels * duration``, each on a uniform pixel at a uniform
    time, ON or OFF with equal odds. Hot pixels: a binomial number of pixels (probability
    ``hot_pixel_fraction`` each), drawn uniformly, each firing a Poisson number of events
    (mean ``hot_pixel_rate_hz * duration``) at uniform times, ON or OFF with equal odds.

    Args:
        num_pixels: number of pixels ``W * H``; events carry flat indices ``y * W + x``.
        duration_us: recording length, microseconds; times lie in ``[0, duration_us)``.
        background_rate_hz: events per pixel per second.
        hot_pixel_fraction: probability that a pixel is hot.
        hot_pixel_rate_hz: events per hot pixel per second.
        generator: the CPU ``torch.Generator`` all draws come from.

    Returns:
        ``(pixel, t, p)``: int64 flat pixel index, int64 time, bool polarity, unsorted.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> pix, t, p = noise_events(num_pixels=100, duration_us=1_000_000,
        ...                          background_rate_hz=1.0, hot_pixel_fraction=0.0,
        ...                          hot_pixel_rate_hz=0.0, generator=g)
        >>> 60 < pix.numel() < 140, bool((t >= 0).all() and (t < 1_000_000).all())
        (True, True)
    """
    seconds = duration_us * 1e-6
    mean = torch.tensor(background_rate_hz * num_pixels * seconds, dtype=torch.float64)
    n_background = int(torch.poisson(mean, generator=generator))
    pixel = torch.randint(0, num_pixels, (n_background,), generator=generator)
    n_hot = int(torch.binomial(torch.tensor(float(num_pixels)),
                               torch.tensor(float(hot_pixel_fraction)), generator=generator))
    hot = torch.randint(0, num_pixels, (n_hot,), generator=generator)
    per_hot = torch.poisson(torch.full((n_hot,), hot_pixel_rate_hz * seconds,
                                       dtype=torch.float64), generator=generator)
    pixel = torch.cat([pixel, torch.repeat_interleave(hot, per_hot.to(torch.int64))])
    n = pixel.numel()
    t = torch.randint(0, max(int(duration_us), 1), (n,), generator=generator)
    p = torch.rand(n, generator=generator) < 0.5
    return pixel, t, p
