"""A DVS pixel model: contrast-threshold crossings of log intensity, refractory period, noise.

Each pixel watches its log intensity ``L(t)`` (natural log of the photocurrent), known at
sample times and linear in between. It keeps a reference level on a lattice of step ``theta``
(its contrast threshold) and follows the reference rule of ``docs/semantics.md``: with
``x(t) = (L(t) - L_ref) / theta`` and an integer reference index ``q`` (starting at 0), it emits
ON and increments ``q`` whenever ``x`` reaches ``q + 1``, and OFF and decrements ``q`` whenever
``x`` reaches ``q - 1``. Several levels crossed between two samples give several events, each at
its own linearly interpolated time, rounded to the nearest microsecond (halves upward). After a
reversal the full threshold must be covered again. ``L_ref = L(t_0) - offset * theta``: the
offset in ``(-1, 1)`` places the reference state within the threshold window (0 by default; the
scene renderer draws it per pixel, as a real sensor starts in an arbitrary state).

The refractory period then drops every event that comes less than ``refractory_us`` after the
pixel's previous emitted event; the reference lattice is not changed by dropped events.
Background activity and hot pixels are Poisson processes sampled directly, in time
proportional to the number of noise events.

The reference index after each sample has a closed form, which makes the model a handful of
vectorised passes over the samples (no loop over time steps or pixels): the index can only
take ``floor(x)`` or ``ceil(x)``; it is forced to ``floor(x_n)`` when ``x`` rises into a new
cell (``floor(x_n) >= ceil(x_{n-1})``), to ``ceil(x_n)`` when it falls into one, and kept
otherwise, so it equals its value at the pixel's last forcing sample.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from evdown_torch.checks import (
    check_non_negative_float,
    check_non_negative_int,
    check_positive_float,
    check_positive_int,
    check_unit_interval,
)

__all__ = ["PixelModelConfig", "noise_events", "pixel_events", "refractory_mask"]


@dataclass(frozen=True)
class PixelModelConfig:
    """Parameters of the simulated pixel array; defaults lie in the range of a DVS128.

    Attributes:
        threshold: contrast threshold ``theta``, natural-log units, for ON and OFF alike
            (0.2, a 22 % change of photocurrent).
        threshold_mismatch: standard deviation of the per-pixel threshold around
            ``threshold``, natural-log units (0.03); per-pixel thresholds are clipped to at
            least ``threshold / 4``.
        refractory_us: refractory period, microseconds (500): a pixel emits nothing for this
            long after each event.
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

    threshold: float = 0.2
    threshold_mismatch: float = 0.03
    refractory_us: int = 500
    background_rate_hz: float = 0.2
    hot_pixel_fraction: float = 2e-4
    hot_pixel_rate_hz: float = 20.0
    max_step_px: float = 1.0
    max_step_us: int = 20000

    def __post_init__(self) -> None:
        check_positive_float("threshold", self.threshold)
        check_non_negative_float("threshold_mismatch", self.threshold_mismatch)
        check_non_negative_int("refractory_us", self.refractory_us)
        check_non_negative_float("background_rate_hz", self.background_rate_hz)
        check_unit_interval("hot_pixel_fraction", self.hot_pixel_fraction)
        check_non_negative_float("hot_pixel_rate_hz", self.hot_pixel_rate_hz)
        check_positive_float("max_step_px", self.max_step_px)
        check_positive_int("max_step_us", self.max_step_us)


def lattice_crossings(
    x: Tensor, t: Tensor, first: Tensor, q_init: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Threshold crossings of piecewise-linear levels, for many pixels at once.

    Args:
        x: ``(M,)`` float level of each sample in threshold units (log intensity minus the
            reference, over the threshold). Samples of one pixel are contiguous, in time order.
        t: ``(M,)`` float64 sample times.
        first: ``(M,)`` bool, True at the first sample of each pixel (its start point, which
            emits nothing).
        q_init: ``(M,)`` int64 reference index at each pixel's first sample (read only there;
            ``floor(x) <= q_init <= ceil(x)`` there).

    Returns:
        ``(segment, time, on, q)``: for each event, the index of the sample that ends its
        segment (int64), its float64 time and its polarity (bool); events are ordered by
        sample, then time. ``q`` is the ``(M,)`` int64 reference index after each sample.
    """
    m = x.shape[0]
    device = x.device
    if m == 0:
        empty = torch.empty(0, dtype=torch.int64, device=device)
        return empty, torch.empty(0, dtype=torch.float64, device=device), empty.bool(), empty
    fl = torch.floor(x)
    ce = torch.ceil(x)
    up = torch.zeros(m, dtype=torch.bool, device=device)
    down = torch.zeros_like(up)
    torch.ge(fl[1:], ce[:-1], out=up[1:])
    torch.le(ce[1:], fl[:-1], out=down[1:])
    forced = first | up | down
    # forced value: floor(x) when rising into a new cell, ceil(x) otherwise, q_init at starts
    value = (ce - up * (ce - fl)).to(torch.int64)
    value = value + first * (q_init - value)
    index = torch.arange(1, m + 1, device=device)
    last = torch.cummax(index * forced, 0).values - 1
    q = value.index_select(0, last)
    dq = torch.zeros(m, dtype=torch.int64, device=device)
    dq[1:] = q[1:] - q[:-1]
    dq *= ~first
    count = dq.abs()
    segment = torch.repeat_interleave(torch.arange(m, device=device), count)
    if segment.numel() == 0:
        return segment, torch.empty(0, dtype=torch.float64, device=device), segment.bool(), q
    starts = torch.cumsum(count, 0) - count
    rank = torch.arange(segment.numel(), device=device) - starts[segment]
    on = dq[segment] > 0
    step = torch.where(on, 1, -1)
    level = (q[segment - 1] + step * (rank + 1)).to(torch.float64)
    x0 = x[segment - 1].to(torch.float64)
    x1 = x[segment].to(torch.float64)
    t0 = t[segment - 1].to(torch.float64)
    t1 = t[segment].to(torch.float64)
    time = t0 + (level - x0) / (x1 - x0) * (t1 - t0)
    return segment, time, on, q


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
    frontier = torch.nonzero(start & ~torch.cat([start[1:], start.new_ones(1)])).squeeze(1)
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


def pixel_events(
    pixel: Tensor,
    t: Tensor,
    log_intensity: Tensor,
    *,
    threshold: float | Tensor,
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
        threshold: contrast threshold, log units: a number, or a 1-D tensor indexed by pixel.
        refractory_us: refractory period, microseconds.
        offset: initial state within the threshold window, in ``(-1, 1)``: the reference
            starts at ``L(t_first) - offset * threshold`` (a number or a per-pixel tensor).

    Returns:
        ``(pixel, t, p)``: int64 pixel index, int64 time (microseconds) and bool polarity
        (True for ON) of each event, sorted by time (ties by pixel).

    Raises:
        ValueError: for mismatched shapes, unsorted samples or bad thresholds.

    Example:
        A ramp of 0.1 log units per 100 us, threshold 0.25, watched from t = 0 to 1000 us:

        >>> pix, t, p = pixel_events(torch.zeros(2, dtype=torch.long),
        ...                          torch.tensor([0, 1000]), torch.tensor([0.0, 1.0]),
        ...                          threshold=0.25)
        >>> t.tolist(), p.tolist()
        ([250, 500, 750, 1000], [True, True, True, True])
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
    theta = _per_pixel("threshold", threshold, pixel, positive=True)
    u = _per_pixel("offset", offset, pixel, positive=False)
    level = log_intensity.to(torch.float64)
    group = torch.cumsum(first, 0) - 1
    start_level = level[first][group]
    x = (level - start_level) / theta + u
    zeros = torch.zeros(pixel.shape, dtype=torch.int64, device=device)
    segment, time, on, _ = lattice_crossings(x, t, first, zeros)
    ev_pixel = pixel[segment]
    ev_t = round_time(time)
    keep = refractory_mask(ev_pixel, ev_t, refractory_us)
    ev_pixel, ev_t, on = ev_pixel[keep], ev_t[keep], on[keep]
    order = torch.sort(ev_t, stable=True).indices
    return ev_pixel[order], ev_t[order], on[order]


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
