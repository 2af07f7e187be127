"""Photocurrent pooling, frames mode (docs/semantics.md, method 7): the paper's literal pipeline.

Frames at ``t_start + k / fps`` (the last one clipped to ``t_end``), each region's log
photocurrent interpolated linearly in time between consecutive frames, crossings at exact
times. Without a leak a region's frame value changes only at frames that follow its events, so
the kernel works on (region, frame) pairs with events and recomputes each such frame value from
the pixels' integer levels (relative to the region's brightest pixel): the cost follows the
events. With a leak (``cutoff_hz > 0``) every pixel decays between frames, so frames are built
densely in bounded chunks of frames (never the whole recording at once). A stream can go
in chunks (:func:`frames_stream`): a frame is processed once an event later than it has been
seen (with a leak, in the same chunks of frames as one call on the whole stream), so the
chunks' outputs concatenated equal one call. The shared pieces
(pixel levels, region geometry, the level snap) live in
:mod:`~evdown_torch.transforms.functional.photocurrent.levels`.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import NamedTuple, cast

import torch
from torch import Tensor

from evdown_torch._regions import region_of, region_pixel_count
from evdown_torch._tensors import changes, chunk_bounds, ends, take, where_true
from evdown_torch.checks import (
    DEFAULT_TIME_UNIT,
    OutputLimitError,
    check_state_memory,
    output_limit,
    output_size,
)
from evdown_torch.events import Events, polarity_sign, sort_by_time
from evdown_torch.transforms.functional.estimation.knots import HALF_TOLERANCE, emit
from evdown_torch.transforms.functional.photocurrent.levels import (
    check_level_range,
    log_mean_exp,
    pixel_levels,
    region_pixel_ids,
    snap,
)
from evdown_torch.transforms.functional.photocurrent.settings import (
    FrameClock,
    PhotocurrentSettings,
)
from evdown_torch.transforms.functional.reference import (
    crossings,
    group_by_region,
    reference_index,
)

#: Frame values per chunk (pixels x frames with a leak, region pixels x steps without one).
CHUNK_VALUES = 1 << 22

Steps = Iterator[tuple[Tensor, Tensor, Tensor, Tensor]]


def photocurrent_frames(
    events: Events,
    *,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
    contrast: float,
    threshold: float,
    fps: float,
    cutoff_hz: float = 0.0,
    time_unit: float = DEFAULT_TIME_UNIT,
) -> Events:
    """Photocurrent pooling, frames mode (docs/semantics.md, method 7): the paper's pipeline.

    Intensity frames at ``t_start + k / fps`` (``t`` counting ``time_unit`` seconds; the last
    frame is clipped to ``t_end``) hold every event up to their time. Each pixel's log intensity is
    ``contrast`` times its level, or, with ``cutoff_hz > 0``, the high-pass filtered sum in
    which each event's ``+-contrast`` decays as ``exp(-2 pi cutoff_hz dt)``. Frames are
    area-averaged over regions in linear intensity; between consecutive frames each region's
    ``log I_r`` is interpolated linearly in time and the DVS reference rule at ``threshold``
    emits events at the exact crossing times (rounded half up when ``t`` is an integer type).

    Args:
        events: ``N`` input events (any order; sorted stably by ``t`` here).
        sensor_size: input ``(W, H, P)``.
        factor: ``(fx, fy)``.
        contrast: ``c`` in log units, in [1e-6, 50].
        threshold: ``theta`` in log units.
        fps: frames per second, > 0.
        cutoff_hz: high-pass cut-off frequency in Hz, >= 0 (0: no leak).
        time_unit: seconds per timestamp unit (default 1e-6: microseconds), validated by the
            caller (:func:`~evdown_torch.checks.check_time_unit`).

    Returns:
        Output events sorted by ``t``, ``t`` of the input's dtype.

    Example:
        Frames at 0, 1000 and 2000 us: the region's log photocurrent goes 0, log 1.5, log 2
        and crosses ``log 2`` exactly at the last frame.

        >>> ev = Events.from_columns([0, 1], [0, 0], [0, 2000], [1, 1])
        >>> out = photocurrent_frames(ev, sensor_size=(2, 1, 2), factor=(2, 1),
        ...                           contrast=math.log(2), threshold=math.log(2), fps=1000)
        >>> out.t.tolist(), out.p.tolist()
        ([2000], [True])
    """
    settings = PhotocurrentSettings(sensor_size, factor, contrast, threshold, fps, cutoff_hz,
                                    time_unit)
    return frames_stream(events, None, settings, final=True)[0]


@dataclass
class FramesCarry:
    """What a frames-mode stream's processed frames leave to the next ones (updated in place).

    Attributes:
        levels: ``(H * W,)`` int64 level of every pixel (no leak).
        ell: ``(H * W,)`` float64 log intensity of every pixel at ``ell_time`` (leak).
        ell_time: offset of the last frame built from ``t_start`` (leak).
        u: ``(Ho * Wo,)`` float64 ``log(I_r) / theta`` of every region at its last frame.
        q: ``(Ho * Wo,)`` int64 reference index of every region.
        emitted: output events so far.
    """

    levels: Tensor
    ell: Tensor
    ell_time: float
    u: Tensor
    q: Tensor
    emitted: int

    def clone(self) -> FramesCarry:
        """A copy with tensors of its own."""
        return FramesCarry(self.levels.clone(), self.ell.clone(), self.ell_time, self.u.clone(),
                           self.q.clone(), self.emitted)


class FramesState(NamedTuple):
    """State of a frames-mode stream between chunks (:func:`frames_stream`).

    Attributes:
        t_start: ``()`` the stream's first timestamp (frame 0).
        pending: the events of frames not complete yet (time-sorted).
        seen: events seen so far.
        next_frame: the first frame not processed yet.
        carry: what the processed frames leave to the next ones.
    """

    t_start: Tensor
    pending: Events
    seen: int
    next_frame: int
    carry: FramesCarry


def fresh_frames_state(
    events: Events, sensor_size: tuple[int, int, int], factor: tuple[int, int]
) -> FramesState:
    """A frames-mode stream's state before its first (time-sorted, non-empty) chunk.

    Frame 0 at the first timestamp of ``events``, every pixel and region at rest.
    """
    w, h, _ = sensor_size
    out_w, out_h, _ = output_size(sensor_size, factor)
    device = events.device
    check_state_memory("PhotocurrentPooling's frames mode", sensor_size, factor,
                       pixel_bytes=16, region_bytes=16, device=device)  # 64-bit pairs
    carry = FramesCarry(levels=torch.zeros(w * h, dtype=torch.int64, device=device),
                        ell=torch.zeros(w * h, dtype=torch.float64, device=device),
                        ell_time=0.0,
                        u=torch.zeros(out_w * out_h, dtype=torch.float64, device=device),
                        q=torch.zeros(out_w * out_h, dtype=torch.int64, device=device),
                        emitted=0)
    return FramesState(events.t[0], Events.empty(events.t.dtype, device), 0, 0, carry)


def frames_stream(
    events: Events, state: FramesState | None, settings: PhotocurrentSettings, *, final: bool
) -> tuple[Events, FramesState | None]:
    """Frames mode on one chunk of a stream: the events of every frame complete so far.

    A frame at ``t_start + k / fps`` is complete once an event later than it has been seen
    (later events cannot change it); with a leak, frames go in whole chunks of
    :func:`leak_chunk` frames, as in one call on the whole stream. ``final`` ends the stream:
    every frame, the last one clipped to ``t_end``. Output events of frame ``k`` lie between
    frames ``k - 1`` and ``k``; ties in ``t`` are ordered by frame, then region, so that the
    chunks' outputs concatenated equal one call on the whole stream.

    Args:
        events: the chunk (time-sorted, at or after every earlier chunk's events; may be empty).
        state: the state returned for the previous chunk, or ``None``.
        settings: the frames mode's settings (``fps`` set).
        final: the chunk ends the stream.

    Returns:
        ``(output events sorted by t, state)``.
    """
    sensor_size, factor = settings.sensor_size, settings.factor
    if settings.fps is None or settings.time_unit is None:
        raise ValueError("the frames mode needs its settings' fps, got fps=None")
    contrast, fps, cutoff_hz = settings.contrast, settings.fps, settings.cutoff_hz
    threshold = cast(float, settings.threshold)  # a float once the settings are built
    events = sort_by_time(events)
    if state is None:
        if events.num_events == 0:
            return Events.empty(events.t.dtype, events.device), None
        state = fresh_frames_state(events, sensor_size, factor)
    seen = events.num_events + state.seen
    events = Events.cat([state.pending, events])
    if events.num_events == 0:
        return Events.empty(events.t.dtype, events.device), state
    check_level_range(seen, contrast, threshold)
    w, h, _ = sensor_size
    out_w, out_h, _ = output_size(sensor_size, factor)
    device = events.device
    t_start = state.t_start
    offset = events.t - t_start
    clock = FrameClock.make(fps, offset[-1].item(), settings.time_unit)
    frame = clock.frame_index(offset)
    carry = state.carry.clone()
    next_frame = state.next_frame
    # Frames before `stop` are processed: all of them at the end, else the complete ones
    # (before the latest event's frame), in whole leak chunks.
    stop = int(frame[-1]) + (1 if final else 0)  # frame[-1]: the first frame not before t
    if not final and cutoff_hz > 0:
        per_chunk = leak_chunk(sensor_size, clock, cutoff_hz)
        stop = next_frame + (stop - next_frame) // per_chunk * per_chunk
    if cutoff_hz > 0:
        check_leaky_frames(stop - next_frame, sensor_size, fps)
    cut = int(torch.searchsorted(frame, torch.tensor([stop], device=device))[0])
    done = events.part(0, cut)
    pending = events.part(cut)
    new_state = FramesState(t_start, pending, seen, max(stop, next_frame), carry)
    if cutoff_hz > 0:
        steps = _leaky_frame_steps(done, offset[:cut], frame[:cut], clock, settings,
                                   (next_frame, stop), carry)
    elif cut:
        steps = _frame_steps(done, frame[:cut], settings, carry)
    else:
        steps = iter(())
    outputs = []
    for step in steps:
        outputs.append(_frame_crossings(*step, carry.u, carry.q, clock, carry.emitted))
        carry.emitted += outputs[-1][0].shape[0]
    if not outputs:
        return Events.empty(events.t.dtype, device), new_state
    region, k, at, on = (torch.cat(column) for column in zip(*outputs, strict=True))
    if events.t.is_floating_point():
        t = t_start + at
    else:
        tick = torch.floor(at.add_(0.5 + HALF_TOLERANCE)).clamp_(max=clock.duration)
        t = t_start + tick.to(torch.int64)
    # Ties in t: by frame, then region (emit sorts stably by t).
    order = torch.sort(k * (out_w * out_h) + region, stable=True).indices
    return emit(take(region, order), take(t, order), take(on, order), out_w), new_state


def _log_photocurrent(
    m: Tensor, spread: Tensor, regions: Tensor, sensor_size: tuple[int, int, int],
    factor: tuple[int, int], contrast: float, threshold: float,
) -> Tensor:
    """``u = log(I_r) / theta`` from the brightest level ``m`` and ``sum exp(c (L - m))``."""
    log_pixels = region_pixel_count(regions, sensor_size, factor).to(torch.float64).log_()
    u = torch.log(spread).sub_(log_pixels).div_(threshold)
    return u.add_(m.to(torch.float64).mul_(contrast / threshold))


def _frame_steps(
    events: Events, frame: Tensor, settings: PhotocurrentSettings, carry: FramesCarry
) -> Steps:
    """Without a leak: ``(region, frame, u, first)`` of every (region, frame) pair that changed.

    Those pairs follow the region's events; region-major, in bounded batches.
    ``carry.levels`` holds the pixel levels before the events and gets those after.
    """
    sensor_size, factor = settings.sensor_size, settings.factor
    contrast = settings.contrast
    threshold = cast(float, settings.threshold)  # a float once the settings are built
    w, h, _ = sensor_size
    out_w = output_size(sensor_size, factor)[0]
    per_region = factor[0] * factor[1]
    level_state = carry.levels
    bounds = chunk_bounds(frame, max(1, CHUNK_VALUES // per_region), split_ties=False)
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        piece = events.part(lo, hi)
        k = frame[lo:hi]
        k0 = int(k[0])
        span = int(k[-1]) - k0 + 1
        levels = pixel_levels(piece, w, h, level_state)
        # Each pixel's level at the end of each frame it has events in, keyed (pixel, frame).
        key = levels.pixel * span + take(k, levels.order) - k0
        last = where_true(ends(changes(key)))
        table_key, table_level = take(key, last), take(levels.level, last)
        del key, last
        # The (region, frame) runs of the piece: one step each.
        rx, ry = region_of(piece, factor)
        groups = group_by_region(rx, ry, out_w)
        k_g = take(k, groups.order)
        step_at = where_true(ends(groups.first | changes(k_g)))
        region, step_frame = take(groups.region, step_at), take(k_g, step_at)
        del groups, k_g, step_at, rx, ry
        # Every pixel of the step's region at the end of the step's frame.
        ids, inside = region_pixel_ids(region, sensor_size, factor)
        query = ids * span + (step_frame - k0)[:, None]
        found = torch.searchsorted(table_key, query.reshape(-1), right=True).view_as(query)
        found -= 1
        hit = found >= 0
        found.clamp_(min=0)
        hit &= table_key[found] >= ids * span  # the same pixel
        lv = torch.where(hit, table_level[found], level_state[ids])
        del query, found, hit
        m, spread = log_mean_exp(lv, inside, contrast)
        u = _log_photocurrent(m, spread, region, sensor_size, factor, contrast, threshold)
        level_state = carry.levels = levels.new_state
        yield region, step_frame, u, changes(region)


def check_leaky_frames(frames: int, sensor_size: tuple[int, int, int], fps: float) -> None:
    """Refuse a leaky call that would build more frame values than the output limit.

    The values are ``frames`` times the sensor's pixels, each computed; the limit in force
    (:func:`~evdown_torch.checks.max_output_events`) is the one bound on a call's work, and
    the check comes before any is built.
    """
    values = frames * sensor_size[0] * sensor_size[1]
    limit = output_limit()
    if limit is not None and values > limit:
        raise OutputLimitError(
            f"fps={fps:g} with a leak (cutoff_hz > 0) means {frames:,} frames in this call, "
            f"each computed for all {sensor_size[0] * sensor_size[1]:,} pixels: {values:,} "
            f"values, more than the limit of {limit:,}; a lower fps or no leak "
            "(its cost follows the events) gives fewer, and "
            "`with evdown_torch.max_output_events(n):` around the call raises the limit"
        )


def leak_chunk(sensor_size: tuple[int, int, int], clock: FrameClock, cutoff_hz: float) -> int:
    """Frames per chunk of the leaky frames mode.

    At most :data:`CHUNK_VALUES` pixel values, and short enough that every decay factor stays
    within ``[1/e, e]`` (no precision lost).
    """
    omega = clock.radians_per_tick(cutoff_hz)
    return max(1, min(CHUNK_VALUES // (sensor_size[0] * sensor_size[1]),
                      int(1 / (omega * clock.period))))


def _leaky_frame_steps(
    events: Events,
    offset: Tensor,
    frame: Tensor,
    clock: FrameClock,
    settings: PhotocurrentSettings,
    frames: tuple[int, int],
    carry: FramesCarry,
) -> Steps:
    """With a leak: ``(region, frame, u, first)`` of every region at every frame of a range.

    The frames are ``range(*frames)`` (the first a multiple of :func:`leak_chunk`), built
    densely in chunks of :func:`leak_chunk` frames. ``carry.ell`` and ``carry.ell_time`` hold
    every pixel's log intensity at the frame before and get those at the last frame.
    """
    sensor_size, factor = settings.sensor_size, settings.factor
    contrast, cutoff_hz = settings.contrast, settings.cutoff_hz
    threshold = cast(float, settings.threshold)  # a float once the settings are built
    w, h, _ = sensor_size
    fx, fy = factor
    out_w, out_h, _ = output_size(sensor_size, factor)
    device = events.device
    omega = clock.radians_per_tick(cutoff_hz)
    per_chunk = leak_chunk(sensor_size, clock, cutoff_hz)
    pixel = events.y * w + events.x
    sign = polarity_sign(events.p, torch.float64).mul_(contrast)
    offset = offset.to(torch.float64)
    regions = torch.arange(out_w * out_h, device=device)
    log_pixels = region_pixel_count(regions, sensor_size, factor).to(torch.float64).log_()
    ell, ell_time = carry.ell, carry.ell_time  # log intensity, last frame
    pad = (0, out_w * fx - w, 0, out_h * fy - h)
    for k0 in range(frames[0], frames[1], per_chunk):
        ks = torch.arange(k0, min(k0 + per_chunk, frames[1]), device=device)
        times = clock.time(ks)
        end = float(times[-1])
        lo, hi = torch.searchsorted(frame, torch.stack([ks[0], ks[-1] + 1])).tolist()
        # Log intensity of every pixel at every frame of the chunk.
        inputs = torch.zeros(ks.shape[0], w * h, dtype=torch.float64, device=device)
        weight = torch.exp((offset[lo:hi] - end) * omega).mul_(sign[lo:hi])
        inputs.index_put_((frame[lo:hi] - k0, pixel[lo:hi]), weight, accumulate=True)
        inputs.cumsum_(0).mul_(torch.exp((end - times) * omega)[:, None])
        inputs += ell * torch.exp((ell_time - times) * omega)[:, None]
        ell, ell_time = inputs[-1].clone(), end
        carry.ell, carry.ell_time = ell, ell_time
        # Area average in linear intensity: log-sum-exp over each region (padding excluded).
        grid = torch.nn.functional.pad(inputs.view(-1, h, w), pad, value=-math.inf)
        grid = grid.view(-1, out_h, fy, out_w, fx).permute(0, 1, 3, 2, 4)
        log_sum = torch.logsumexp(grid.reshape(ks.shape[0], out_h * out_w, fx * fy), 2)
        del inputs, grid
        u = log_sum.sub_(log_pixels).div_(threshold)
        yield (regions.repeat_interleave(ks.shape[0]), ks.repeat(out_w * out_h),
               u.T.reshape(-1), (ks == k0).repeat(out_w * out_h))


def _frame_crossings(
    region: Tensor,
    frame: Tensor,
    u: Tensor,
    first: Tensor,
    carry_u: Tensor,
    carry_q: Tensor,
    clock: FrameClock,
    emitted: int = 0,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The reference rule on the linear ramps from frame ``k - 1`` to each step's frame ``k``.

    Steps are region-major (``first`` marks each region's first), frames ascending; a region's
    value at frame ``k - 1`` is its previous step's (``carry_u`` before its first step).
    ``carry_u`` and ``carry_q`` (per region ``u`` and ``q`` so far) are updated in place.

    Returns:
        ``(region, frame, offset from t_start as float64, on)`` of each crossing.
    """
    floor_u, on_level = snap(u)
    firsts = where_true(first)
    first_region = take(region, firsts)
    q = reference_index(floor_u, on_level, first, take(carry_q, region))
    q_before, u_before = q.roll(1), u.roll(1)
    q_before[firsts] = take(carry_q, first_region)
    u_before[firsts] = take(carry_u, first_region)
    lasts = where_true(ends(first))
    carry_q.scatter_(0, take(region, lasts), take(q, lasts))
    carry_u.scatter_(0, take(region, lasts), take(u, lasts))
    cross = crossings(q_before, q, emitted=emitted)
    end = cross.move
    u0, u1 = take(u_before, end), take(u, end)
    ratio = (cross.level.to(torch.float64) - u0) / (u1 - u0)
    at_end = take(on_level, end) & (cross.level == take(floor_u, end))
    ratio = torch.where(at_end, 1.0, torch.nan_to_num(ratio).clamp(0.0, 1.0))
    k = take(frame, end)
    t0, t1 = clock.time(k - 1), clock.time(k)
    return take(region, end), k, t0 + ratio * (t1 - t0), cross.on
