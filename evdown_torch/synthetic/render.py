"""Rendering a gesture scene through the DVS pixel model, at full or at lower resolution.

Only what moves is simulated (:mod:`evdown_torch.synthetic.raster` rasterises the moving limbs
over the body, which :mod:`evdown_torch.synthetic.grid` renders at the few key steps of its
slow sway, over a static background). A pixel's log intensity is thus known at the steps where
a moving part covers it and, if the body's sway changes it, at the body's key steps (linear in
time between them); between such samples it sits at its static value or on the body's line,
which is inserted as a sample just before and after each covered stretch. The pixel model
(:mod:`evdown_torch.synthetic.pixel_model`, separate ON and OFF thresholds with per-pixel
mismatch) runs on these samples; the cost
follows the moving parts and the events, never sensor area times steps. Steps are processed
in chunks that bound memory; per-pixel state (the reference's ON and OFF counts) carries
across chunks, so the result does not depend on the chunking. Under a flickering lamp the lit
static pixels are simulated too (:mod:`evdown_torch.synthetic.lighting`). Noise, the
refractory period and the burst readout (:func:`~evdown_torch.synthetic.readout_times`) come
last.

At a lower resolution (``factor`` ``(fx, fy)``), each output pixel sees the mean linear
intensity (photocurrent) of the block of sensor pixels it covers (edge blocks: the pixels
inside the sensor), computed from the same fragments and the same swaying body (block means
of its key images), and the same pixel model, lamp, noise and readout run on that.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from evdown_torch._regions import region_xy
from evdown_torch._tensors import where_true
from evdown_torch.checks import check_factor, check_positive_int, output_size
from evdown_torch.events import Events
from evdown_torch.synthetic.grid import Grid
from evdown_torch.synthetic.lighting import flicker_depth, flicker_samples
from evdown_torch.synthetic.pixel_model import (
    PixelModelConfig,
    level_crossings,
    noise_events,
    readout_times,
    refractory_mask,
    round_time,
    start_reference,
)
from evdown_torch.synthetic.raster import (
    _Part,
    block_of,
    block_sums,
    moving_parts,
    rasterise,
    step_bits,
)
from evdown_torch.synthetic.scenes import GestureScene, scene_seed

__all__ = [
    "pixel_parameters",
    "render_events",
    "step_times",
    "swept_mask",
]

MAX_FRAGMENTS = 1 << 21
"""Default bound on the fragments (covered pixel-steps) rasterised in one chunk."""

_PIXEL_STREAM, _NOISE_STREAM = 1, 2


def _generator(scene: GestureScene, stream: int, factor: tuple[int, int]) -> torch.Generator:
    return torch.Generator().manual_seed(scene_seed(scene.seed, stream, *factor))


def step_times(scene: GestureScene, config: PixelModelConfig) -> Tensor:
    """Simulation sample times, ``(S + 1,)`` float64 microseconds from 0 to the duration.

    Steps follow the motion: between two steps no moving joint travels more than about
    ``config.max_step_px`` pixels, and no step is longer than ``config.max_step_us``; idle
    stretches and pauses thus cost few steps. (The joints' travel is measured on a 250 us
    grid, and the steps are spread evenly over the cumulative travel.)

    Example:
        >>> scene = GestureScene.sample(1, seed=0, duration_us=100_000)
        >>> times = step_times(scene, PixelModelConfig())
        >>> float(times[0]), float(times[-1])
        (0.0, 100000.0)
    """
    duration = scene.duration_us
    probe = torch.linspace(0, duration, max(2, math.ceil(duration / 250)) + 1,
                           dtype=torch.float64)
    travel = torch.zeros(probe.numel() - 1, dtype=torch.float64)
    for moving, points in zip(scene.moving_arms, scene.arm_keypoints(probe), strict=True):
        if moving:
            step = (points[1:, 1:] - points[:-1, 1:]).norm(dim=2).amax(dim=1)
            travel = torch.maximum(travel, step)
    cost = torch.maximum(travel / config.max_step_px,
                         (probe[1:] - probe[:-1]) / config.max_step_us)
    cumulative = torch.cat([torch.zeros(1, dtype=torch.float64), torch.cumsum(cost, 0)])
    steps = max(1, math.ceil(float(cumulative[-1]) - 1e-9))
    targets = torch.linspace(0, float(cumulative[-1]), steps + 1, dtype=torch.float64)
    k = (torch.searchsorted(cumulative, targets, right=True) - 1).clamp(0, cost.numel() - 1)
    frac = ((targets - cumulative[k]) / cost[k]).clamp(0, 1)
    times = probe[k] + frac * (probe[k + 1] - probe[k])
    times[0], times[-1] = 0.0, float(duration)
    # strictly increasing (pixel samples need it); equal neighbours cannot arise from a
    # positive cost, but guard against rounding
    return torch.cummax(times, 0).values


def _with_static(pixel: Tensor, step: Tensor, x: Tensor, covered: Tensor,
                 level_at: Callable[[Tensor, Tensor], Tensor], s0: int, s1: int
                 ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Insert the uncovered level just before and after each covered stretch of each pixel.

    Args:
        pixel: the samples' pixels; samples sorted by pixel then step.
        step: the samples' steps, within ``[s0, s1]``.
        x: the samples' levels.
        covered: a moving part covers the sample (else it lies on the pixel's own line).
        level_at: ``(pixel, step) -> level`` of the pixel where no moving part covers it.
        s0: the first step.
        s1: the last step.

    Returns:
        ``(pixel, step, x, first)`` where ``first`` marks each pixel's first sample.
    """
    n = pixel.numel()
    first = torch.ones(n, dtype=torch.bool)
    if n == 0:
        return pixel, step, x, first
    first[1:] = pixel[1:] != pixel[:-1]
    last = torch.ones(n, dtype=torch.bool)
    last[:-1] = first[1:]
    gap = step[1:] - step[:-1]
    # before a covered sample (unless the previous covered one's "after" lands there), and
    # after one
    pre = first & (step > s0)
    pre[1:] |= ~first[1:] & ((gap > 2) | ((gap == 2) & ~covered[:-1]))
    pre &= covered
    post = last & (step < s1)
    post[:-1] |= ~last[:-1] & (gap > 1)
    post &= covered
    count = 1 + pre.to(torch.int64) + post.to(torch.int64)
    end = torch.cumsum(count, 0)
    total = int(end[-1])
    own = end - count + pre.to(torch.int64)
    out_pixel = torch.repeat_interleave(pixel, count)
    out_step = torch.empty(total, dtype=torch.int64).index_copy_(0, own, step)
    out_x = torch.empty(total, dtype=x.dtype).index_copy_(0, own, x)
    for flag, shift in ((pre, -1), (post, 1)):
        where = where_true(flag)
        at = own.index_select(0, where) + shift
        steps = step.index_select(0, where) + shift
        out_step.index_copy_(0, at, steps)
        out_x.index_copy_(0, at, level_at(pixel.index_select(0, where), steps))
    out_first = torch.zeros(total, dtype=torch.bool)
    out_first[(end - count)[first]] = True
    return out_pixel, out_step, out_x, out_first


def _chunks(parts: list[_Part], n_steps: int, n_pixels: int, max_fragments: int
            ) -> list[tuple[int, int]]:
    """Consecutive step ranges ``[s0, s1]`` sharing endpoints, each within the budget."""
    per_step = 1
    for p in parts:
        reach = 2 * p.radius + 3
        per_step += int(reach * (p.length + reach))
    # keys (pixel << bits) | step stay below 2**31 (int32 sorts) when possible
    room = 31 - max(n_pixels - 1, 1).bit_length()
    span = max(1, min(max_fragments // per_step, (1 << max(room, 1)) - 1))
    return [(s0, min(s0 + span, n_steps)) for s0 in range(0, max(n_steps, 1), span)]


def pixel_parameters(
    scene: GestureScene, config: PixelModelConfig, factor: tuple[int, int]
) -> tuple[Tensor, Tensor, Tensor]:
    """Per-pixel ON and OFF thresholds and initial offset of the output sensor, from the scene.

    The recording's thresholds are ``threshold * exp(+-bias * on_off_spread / 2)`` (ON, OFF;
    their geometric mean is ``threshold``); each pixel's deviates from them by
    ``threshold_mismatch * N(0, 1)``, independently per polarity, clipped to a quarter of the
    nominal threshold or more.

    Returns:
        ``(theta_on, theta_off, offset)``: ``(W' * H',)`` float64 each; ``offset`` is uniform
        in ``(-1, 1)``. Pixel ``(x, y)`` is entry ``y * W' + x``.
    """
    out_w, out_h, _ = output_size(scene.sensor_size, factor)
    generator = _generator(scene, _PIXEL_STREAM, factor)
    n_out = out_w * out_h
    half = 0.5 * scene.bias * config.on_off_spread
    low = config.threshold / 4
    thetas = []
    for sign in (1.0, -1.0):
        noise = torch.randn(n_out, generator=generator, dtype=torch.float64)
        nominal = config.threshold * math.exp(sign * half)
        thetas.append((nominal + config.threshold_mismatch * noise).clamp_min(low))
    offset = (torch.rand(n_out, generator=generator, dtype=torch.float64) * 2 - 1) * (1 - 2**-20)
    return thetas[0], thetas[1], offset


def render_events(
    scene: GestureScene,
    config: PixelModelConfig | None = None,
    *,
    factor: int | tuple[int, int] = 1,
    max_fragments: int = MAX_FRAGMENTS,
) -> Events:
    """Render a scene to events through the pixel model, at full or lower resolution.

    Args:
        scene: the scene.
        config: pixel-model parameters (defaults: :class:`PixelModelConfig`).
        factor: ``f`` or ``(fx, fy)``: render on a sensor ``(ceil(W / fx), ceil(H / fy))``
            whose pixels see the mean linear intensity of the blocks they cover; 1 is the
            full-resolution recording.
        max_fragments: memory bound, covered pixel-steps rasterised at once (the result does
            not depend on it).

    Returns:
        Events with int64 ``x``, ``y``, int64 ``t`` (microseconds in
        ``[0, scene.duration_us)``) and bool ``p``, sorted by ``t`` (ties by pixel), on CPU.

    Example:
        >>> scene = GestureScene.sample(0, seed=1, sensor_size=(32, 32, 2), duration_us=200_000)
        >>> ev = render_events(scene)
        >>> ev.num_events > 0, bool((ev.t[1:] >= ev.t[:-1]).all())
        (True, True)
    """
    if not isinstance(scene, GestureScene):
        raise TypeError(f"scene must be a GestureScene, got {type(scene).__name__}")
    config = PixelModelConfig() if config is None else config
    if not isinstance(config, PixelModelConfig):
        raise TypeError(f"config must be a PixelModelConfig, got {type(config).__name__}")
    factor = check_factor(factor, scene.sensor_size)
    max_fragments = check_positive_int("max_fragments", max_fragments)
    times = step_times(scene, config)
    parts = moving_parts(scene, times)
    grid = Grid(scene, factor, times, config.max_step_px)
    n_out = grid.out_w * grid.out_h
    theta_on, theta_off, offset = pixel_parameters(scene, config, factor)
    log_static = grid.out.log_static
    pixel0, _, level0, _ = grid.samples(parts, 0, 0)
    log_start = log_static.clone()
    log_start[pixel0] = level0
    base = start_reference(log_start, offset, theta_on, theta_off)
    a_state = torch.zeros(n_out, dtype=torch.int64)
    b_state = torch.zeros(n_out, dtype=torch.int64)

    # The lamp's flicker on lit static pixels: its own groups of samples, without carried
    # state, run in the same call as the first chunk (the scan's iterations then cover both).
    depth = flicker_depth(scene, grid.static, factor, block_sums)
    lamp_pixel, lamp_t, lamp_level = flicker_samples(scene, depth, log_static,
                                                     torch.minimum(theta_on, theta_off))
    lamp_first = torch.ones(lamp_pixel.shape, dtype=torch.bool)
    lamp_first[1:] = lamp_pixel[1:] != lamp_pixel[:-1]
    group = torch.cumsum(lamp_first, 0) - 1
    # each lit pixel starts in the same place within its window as in the scene
    lamp_base = start_reference(lamp_level[lamp_first][group],
                                offset.index_select(0, lamp_pixel),
                                theta_on.index_select(0, lamp_pixel),
                                theta_off.index_select(0, lamp_pixel))
    # batches of whole lit pixels (all have the same samples), each within the memory budget
    n_lit = int(lamp_first.sum())
    lamp_batches = []
    if n_lit:
        per_batch = max(1, max_fragments // (lamp_pixel.numel() // n_lit))
        per_batch *= lamp_pixel.numel() // n_lit
        lamp_batches = [slice(i, i + per_batch) for i in range(0, lamp_pixel.numel(), per_batch)]
    lamp = (lamp_pixel, lamp_t, lamp_level, lamp_first, lamp_base)
    events: tuple[list[Tensor], list[Tensor], list[Tensor]] = ([], [], [])
    lamp_events: tuple[list[Tensor], list[Tensor], list[Tensor]] = ([], [], [])
    n_steps = times.numel() - 1
    chunks = _chunks(parts, n_steps, grid.width * grid.height, max_fragments)
    empty = torch.empty(0, dtype=torch.int64)
    for index in range(max(len(chunks), len(lamp_batches))):
        # job `index`: chunk `index` of the moving limbs and batch `index` of the lamp's
        # pixels (no carried state), in one scan
        if index < len(chunks):
            s0, s1 = chunks[index]
            pixel, step, level, covered = grid.samples(parts, s0, s1)
            pixel, step, level, first = _with_static(pixel, step, level, covered,
                                                     grid.out.level, s0, s1)
            t = times.index_select(0, step)
        else:
            pixel, t, level, first = empty, empty.double(), empty.double(), empty.bool()
        a0, b0 = a_state.index_select(0, pixel), b_state.index_select(0, pixel)
        base_at = base.index_select(0, pixel)
        n_moving = pixel.numel()
        if index < len(lamp_batches):
            batch = lamp_batches[index]
            pixel, t, level, first, base_at = (torch.cat([u, v[batch]]) for u, v in zip(
                (pixel, t, level, first, base_at), lamp, strict=True))
            zeros = torch.zeros(pixel.numel() - n_moving, dtype=torch.int64)
            a0, b0 = torch.cat([a0, zeros]), torch.cat([b0, zeros])
        if pixel.numel() == 0:
            continue
        segment, time, on, a, b = level_crossings(
            level, t, first, base=base_at, theta_on=theta_on.index_select(0, pixel),
            theta_off=theta_off.index_select(0, pixel), a_start=a0, b_start=b0)
        ends = torch.ones_like(first)
        ends[:-1] = first[1:]
        ends[n_moving:] = False  # the lamp's groups carry no state
        a_state[pixel[ends]] = a[ends]
        b_state[pixel[ends]] = b[ends]
        # the limbs' events, then the lamp's: an order that does not depend on the chunking
        moving = segment < n_moving
        for out, keep in ((events, moving), (lamp_events, ~moving)):
            out[0].append(pixel.index_select(0, segment[keep]))
            out[1].append(round_time(time[keep]))
            out[2].append(on[keep])
    noise = noise_events(
        num_pixels=n_out,
        duration_us=scene.duration_us,
        background_rate_hz=config.background_rate_hz * scene.noise_scale,
        hot_pixel_fraction=config.hot_pixel_fraction,
        hot_pixel_rate_hz=config.hot_pixel_rate_hz,
        generator=_generator(scene, _NOISE_STREAM, factor),
    )
    pixel = torch.cat(events[0] + lamp_events[0] + [noise[0]])
    t = torch.cat(events[1] + lamp_events[1] + [noise[1]])
    on = torch.cat(events[2] + lamp_events[2] + [noise[2]])
    inside = t < scene.duration_us
    pixel, t, on = pixel[inside], t[inside], on[inside]
    order = torch.sort(pixel * (scene.duration_us + 1) + t, stable=True).indices
    pixel, t, on = pixel[order], t[order], on[order]
    keep = refractory_mask(pixel, t, config.refractory_us)
    pixel, t, on = pixel[keep], readout_times(t[keep], config.readout_us), on[keep]
    order = torch.sort(t, stable=True).indices
    x, y = region_xy(pixel[order], grid.out_w)
    return Events(x, y, t[order], on[order])


def swept_mask(
    scene: GestureScene,
    config: PixelModelConfig | None = None,
    *,
    factor: int | tuple[int, int] = 1,
) -> Tensor:
    """Output pixels that a moving part covers at some step, or that the body's sway changes.

    Only these pixels can emit events other than noise and lamp flicker. Covering means a
    coverage above 0 at a pixel of the block (``factor`` as in :func:`render_events`); the
    sway changes a block when it changes the intensity of one of its pixels between the
    body's key steps.

    Returns:
        ``(H', W')`` bool tensor (``W' = ceil(W / fx)``, ``H' = ceil(H / fy)``).

    Example:
        >>> scene = GestureScene.sample(1, seed=0, sensor_size=(32, 32, 2), duration_us=200_000)
        >>> mask = swept_mask(scene)
        >>> mask.shape, 0 < int(mask.sum()) < 32 * 32
        (torch.Size([32, 32]), True)
    """
    config = PixelModelConfig() if config is None else config
    factor = check_factor(factor, scene.sensor_size)
    times = step_times(scene, config)
    parts = moving_parts(scene, times)
    width, height, _ = scene.sensor_size
    out_w, out_h, _ = output_size(scene.sensor_size, factor)
    mask = torch.zeros(out_h * out_w, dtype=torch.bool)
    mask[Grid(scene, factor, times, config.max_step_px).out.pixels] = True
    for s0, s1 in _chunks(parts, times.numel() - 1, width * height, MAX_FRAGMENTS):
        for part in parts:
            key, _, _ = rasterise(part, s0, s1, width, height, scene.scale)
            pixel = key >> step_bits(s0, s1)
            mask[block_of(pixel, width, factor, out_w)] = True
    return mask.reshape(out_h, out_w)


