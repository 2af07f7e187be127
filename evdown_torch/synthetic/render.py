"""Rendering a gesture scene through the DVS pixel model, at full or at lower resolution.

Only what moves is simulated. The background, the torso, the head and resting arms form a
static image, rendered once. At each simulation step every moving capsule is rasterised by
scanlines to the pixels it covers (anti-aliased coverage, its own texture), and those
fragments are composited over the static image. A pixel's log intensity is thus known at the
steps where a moving part covers it; between such stretches it sits at its static value, which
is inserted as a sample just before and after each stretch. The pixel model
(:mod:`evdown_torch.synthetic.pixel_model`) runs on these samples; the cost follows the moving
parts and the events, never sensor area times steps. Steps are processed in chunks that bound
memory; per-pixel state (the reference index) carries across chunks, so the result does not
depend on the chunking.

At a lower resolution (``factor`` ``(fx, fy)``), each output pixel sees the mean linear
intensity (photocurrent) of the block of sensor pixels it covers (edge blocks: the pixels
inside the sensor), computed from the same fragments, and the same pixel model runs on that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from evdown_torch._tensors import stable_sort_small
from evdown_torch.checks import check_factor, check_positive_int, output_size
from evdown_torch.events import Events
from evdown_torch.synthetic.pixel_model import (
    PixelModelConfig,
    lattice_crossings,
    noise_events,
    refractory_mask,
    round_time,
)
from evdown_torch.synthetic.scenes import (
    BODY,
    FOREARM,
    HAND,
    RADIUS_FORE,
    RADIUS_HAND,
    RADIUS_UPPER,
    UPPER_ARM,
    GestureScene,
    Look,
    scene_seed,
)

__all__ = [
    "intensity_frame",
    "pixel_parameters",
    "render_events",
    "step_times",
    "swept_mask",
]

MAX_FRAGMENTS = 1 << 21
"""Default bound on the fragments (covered pixel-steps) rasterised in one chunk."""

_PIXEL_STREAM, _NOISE_STREAM = 1, 2


@dataclass(frozen=True)
class _Part:
    """A moving capsule: endpoints per step (pixels), radius (pixels), appearance."""

    a: Tensor  # (S + 1, 2) float32
    b: Tensor  # (S + 1, 2) float32
    radius: float
    length: float  # |b - a|, the same at every step
    look: Look


def _generator(scene: GestureScene, stream: int, factor: tuple[int, int]) -> torch.Generator:
    return torch.Generator().manual_seed(scene_seed(scene.seed, stream, *factor))


def step_times(scene: GestureScene, config: PixelModelConfig) -> Tensor:
    """Simulation sample times, ``(S + 1,)`` float64 microseconds from 0 to the duration.

    The step is the largest that keeps every moving joint within ``config.max_step_px``
    pixels per step and at most ``config.max_step_us``, shrunk to divide the duration evenly.

    Example:
        >>> scene = GestureScene.sample(1, seed=0, duration_us=100_000)
        >>> times = step_times(scene, PixelModelConfig())
        >>> float(times[0]), float(times[-1])
        (0.0, 100000.0)
    """
    duration = scene.duration_us
    probe = torch.linspace(0, duration, max(2, math.ceil(duration / 250)) + 1,
                           dtype=torch.float64)
    speed = 0.0
    for moving, points in zip(scene.moving_arms, scene.arm_keypoints(probe), strict=True):
        if moving:
            step = (points[1:, 1:] - points[:-1, 1:]).norm(dim=2).max()
            speed = max(speed, float(step) / float(probe[1] - probe[0]))
    dt = float(config.max_step_us)
    if speed > 0:
        dt = min(dt, config.max_step_px / speed)
    steps = max(1, math.ceil(duration / dt))
    return torch.linspace(0, duration, steps + 1, dtype=torch.float64)


def _part_moves(scene: GestureScene) -> list[list[bool]]:
    """Whether each arm part (upper arm, forearm, hand of the right, then the left arm) moves.

    Judged on a fine grid of times: a part whose endpoints stay put is drawn once, into the
    static image (a waving arm's upper arm, say).
    """
    probe = torch.linspace(0, scene.duration_us, 2001, dtype=torch.float64)
    out = []
    for moving, points in zip(scene.moving_arms, scene.arm_keypoints(probe), strict=True):
        drift = (points - points[:1]).abs().amax(dim=(0, 2))  # per keypoint, pixels
        out.append([moving and bool(max(drift[k], drift[k + 1]) > 1e-6) for k in range(3)])
    return out


_RADII = (RADIUS_UPPER, RADIUS_FORE, RADIUS_HAND)
_LENGTHS = (UPPER_ARM, FOREARM, HAND)


def _moving_parts(scene: GestureScene, times: Tensor) -> list[_Part]:
    """The moving capsules, in compositing order, with their endpoints at ``times``."""
    parts = []
    for moves, points in zip(_part_moves(scene), scene.arm_keypoints(times), strict=True):
        points = points.to(torch.float32)
        for k in range(3):
            if moves[k]:
                parts.append(_Part(points[:, k], points[:, k + 1], _RADII[k] * scene.scale,
                                   _LENGTHS[k] * scene.scale, scene.looks[2 + k]))
    return parts


def _static_parts(scene: GestureScene) -> list[tuple[Tensor, Tensor, float, Look]]:
    """Capsules that never move: body, then arm parts at rest; endpoints in pixels."""
    origin = torch.tensor(scene.origin, dtype=torch.float64)
    out = []
    for _, a, b, radius, look in BODY:
        out.append((origin + scene.scale * torch.tensor(a, dtype=torch.float64),
                    origin + scene.scale * torch.tensor(b, dtype=torch.float64),
                    radius * scene.scale, scene.looks[look]))
    zero = torch.zeros(1, dtype=torch.float64)
    for moves, points in zip(_part_moves(scene), scene.arm_keypoints(zero), strict=True):
        for k in range(3):
            if not moves[k]:
                out.append((points[0, k], points[0, k + 1], _RADII[k] * scene.scale,
                            scene.looks[2 + k]))
    return out


def _background(scene: GestureScene) -> Tensor:
    """Static background, ``(H, W)`` float32 linear intensity with mean about 1."""
    w, h, _ = scene.sensor_size
    size = min(w, h)
    xs = (torch.arange(w, dtype=torch.float64) + 0.5) / size
    ys = (torch.arange(h, dtype=torch.float64) + 0.5) / size
    log_image = torch.zeros(h, w, dtype=torch.float64)
    for item in scene.background:
        if len(item) == 4:
            kx, ky, amp, phase = item
            arg_x = 2 * math.pi * kx * xs
            arg_y = 2 * math.pi * ky * ys + phase
            # cos(a + b) from separable factors: O(W + H) trigonometry per wave
            log_image += amp * (torch.cos(arg_y)[:, None] * torch.cos(arg_x)[None, :]
                                - torch.sin(arg_y)[:, None] * torch.sin(arg_x)[None, :])
        else:
            x0, y0, x1, y1, gain = item
            fx = (torch.arange(w, dtype=torch.float64) + 0.5) / w
            fy = (torch.arange(h, dtype=torch.float64) + 0.5) / h
            # soft edges one pixel wide
            inside_x = ((fx - x0) * w + 0.5).clamp(0, 1) * ((x1 - fx) * w + 0.5).clamp(0, 1)
            inside_y = ((fy - y0) * h + 0.5).clamp(0, 1) * ((y1 - fy) * h + 0.5).clamp(0, 1)
            log_image += gain * inside_y[:, None] * inside_x[None, :]
    return torch.exp(log_image).to(torch.float32)


def _shade(px: Tensor, py: Tensor, a: Tensor, b: Tensor, radius: float, look: Look,
           scale: float) -> tuple[Tensor, Tensor]:
    """Coverage and intensity of a capsule at pixel centres.

    Args:
        px, py: ``(N,)`` float32 pixel-centre coordinates.
        a, b: ``(N, 2)`` or ``(2,)`` float32 capsule endpoints.
        radius: capsule radius, pixels.
        look: appearance.
        scale: pixels per body unit (for the stripe period).

    Returns:
        ``(alpha, colour)``: ``(N,)`` float32 coverage in ``[0, 1]`` (one minus the distance
        beyond the radius, a one-pixel anti-aliased edge) and linear intensity.
    """
    ax, ay = a[..., 0], a[..., 1]
    abx, aby = b[..., 0] - ax, b[..., 1] - ay
    apx, apy = px - ax, py - ay
    length2 = abx * abx + aby * aby
    length = torch.sqrt(length2)
    safe = torch.where(length2 > 0, length2, torch.ones_like(length2))
    s = ((apx * abx + apy * aby) / safe).clamp(0.0, 1.0)
    dx, dy = apx - s * abx, apy - s * aby
    dist = torch.sqrt(dx * dx + dy * dy)
    alpha = (radius + 0.5 - dist).clamp(0.0, 1.0)
    safe_len = torch.where(length > 0, length, torch.ones_like(length))
    across = (abx * apy - aby * apx) / safe_len
    v = (across / radius).clamp(-1.0, 1.0)
    u = s * length
    stripes = 1.0 + look.stripe * torch.sin(u * (2 * math.pi / (look.period * scale)) + look.phase)
    colour = look.gain * (1.0 + look.side * v) * (1.0 - look.rim * v * v) * stripes
    return alpha, colour


def _static_image(scene: GestureScene) -> tuple[Tensor, float]:
    """Background with the static capsules over it, ``(H, W)`` float32, and the background's
    mean (the unit of every part's intensity)."""
    w, h, _ = scene.sensor_size
    image = _background(scene)
    mean = float(image.mean())
    for a, b, radius, look in _static_parts(scene):
        reach = radius + 0.5
        lo = torch.minimum(a, b) - reach
        hi = torch.maximum(a, b) + reach
        i0, i1 = max(0, math.floor(float(lo[0]))), min(w, math.ceil(float(hi[0])) + 1)
        j0, j1 = max(0, math.floor(float(lo[1]))), min(h, math.ceil(float(hi[1])) + 1)
        if i0 >= i1 or j0 >= j1:
            continue
        jj, ii = torch.meshgrid(torch.arange(j0, j1), torch.arange(i0, i1), indexing="ij")
        alpha, colour = _shade(ii.reshape(-1).float() + 0.5, jj.reshape(-1).float() + 0.5,
                               a.float(), b.float(), radius, look, scene.scale)
        patch = image[j0:j1, i0:i1].reshape(-1)
        image[j0:j1, i0:i1] = (patch * (1 - alpha) + alpha * (colour * mean)).reshape(
            j1 - j0, i1 - i0)
    return image, mean


def _nonzero(mask: Tensor) -> Tensor:
    """Indices of the True entries of a 1-D CPU bool tensor (NumPy's is much faster)."""
    return torch.from_numpy(np.flatnonzero(mask.numpy()))


def _rows(part: _Part, s0: int, s1: int, width: int, height: int):
    """Scanline spans of a moving capsule at steps ``s0..s1``.

    A pixel can be covered when its centre lies within ``radius + 0.5`` of the segment. On
    row ``j`` (centre ``yc = j + 0.5``) those centres form one interval (the thickened
    capsule is convex): the union of the intervals cut by the two end discs and by the slab
    ``0 <= s <= 1, |perp| < reach``, where the position ``s`` along the segment and the
    signed distance ``perp`` across it are affine in ``x`` along the row.

    Returns:
        ``(step, row, i0, count, k1, c1, k2, c2)`` per row span: step relative to ``s0``,
        row index, first column, number of columns, and ``s = x * k1 + c1``,
        ``perp = x * k2 + c2`` at pixel-centre abscissa ``x``.
    """
    a, b = part.a[s0:s1 + 1], part.b[s0:s1 + 1]
    reach = part.radius + 0.5
    y_lo = torch.minimum(a[:, 1], b[:, 1]) - reach
    y_hi = torch.maximum(a[:, 1], b[:, 1]) + reach
    j0 = (torch.floor(y_lo - 0.5) + 1).clamp(0, height).to(torch.int64)
    j1 = (torch.ceil(y_hi - 0.5) - 1).clamp(-1, height - 1).to(torch.int64)
    n_rows = (j1 - j0 + 1).clamp_min(0)
    step = torch.repeat_interleave(torch.arange(n_rows.numel()), n_rows)
    starts = torch.cumsum(n_rows, 0) - n_rows
    row = j0[step] + (torch.arange(step.numel()) - starts[step])
    ax, ay, bx, by = a[step, 0], a[step, 1], b[step, 0], b[step, 1]
    abx, aby = bx - ax, by - ay
    inv_len2 = 1.0 / (abx * abx + aby * aby)  # parts have a fixed, positive length
    inv_len = torch.sqrt(inv_len2)
    dyc = row.to(torch.float32) + 0.5 - ay
    k1 = abx * inv_len2
    c1 = (dyc * aby - ax * abx) * inv_len2
    k2 = -aby * inv_len
    c2 = (abx * dyc + aby * ax) * inv_len
    inf = torch.full_like(k1, math.inf)
    lo, hi = inf, -inf
    for cx, cy in ((ax, ay), (bx, by)):  # end discs
        h2 = reach * reach - (row.to(torch.float32) + 0.5 - cy) ** 2
        half = torch.sqrt(h2.clamp_min(0))
        lo = torch.where(h2 > 0, torch.minimum(lo, cx - half), lo)
        hi = torch.where(h2 > 0, torch.maximum(hi, cx + half), hi)
    slab_lo, slab_hi = -inf, inf
    for k, c, low, high in ((k1, c1, 0.0, 1.0), (k2, c2, -reach, reach)):
        flat = k == 0
        safe = torch.where(flat, torch.ones_like(k), k)
        e1, e2 = (low - c) / safe, (high - c) / safe
        inside = (c >= low) & (c <= high)
        slab_lo = torch.where(flat, torch.where(inside, slab_lo, inf),
                              torch.maximum(slab_lo, torch.minimum(e1, e2)))
        slab_hi = torch.where(flat, torch.where(inside, slab_hi, -inf),
                              torch.minimum(slab_hi, torch.maximum(e1, e2)))
    slab = slab_lo < slab_hi
    lo = torch.where(slab, torch.minimum(lo, slab_lo), lo)
    hi = torch.where(slab, torch.maximum(hi, slab_hi), hi)
    i0 = (torch.floor(lo - 0.5) + 1).clamp(0, width)
    i1 = (torch.ceil(hi - 0.5) - 1).clamp(-1, width - 1)
    count = (i1 - i0 + 1).clamp_min(0).to(torch.int64)
    return step, row, i0.to(torch.int64), count, k1, c1, k2, c2


def _step_bits(s0: int, s1: int) -> int:
    """Bits that hold a step of ``s0..s1`` relative to ``s0`` (keys are ``pixel << bits``)."""
    return max(1, (s1 - s0).bit_length())


def _rasterise(part: _Part, s0: int, s1: int, width: int, height: int, scale: float):
    """Fragments of a moving capsule at steps ``s0..s1``.

    Returns ``(key, alpha, colour)``: ``key = (pixel << bits) | step`` (``pixel = j * W + i``,
    ``step`` relative to ``s0``, ``bits`` from :func:`_step_bits`), coverage in ``[0, 1]``
    and linear intensity relative to the background's mean (float32).
    """
    bits = _step_bits(s0, s1)
    step, row, i0, count, k1, c1, k2, c2 = _rows(part, s0, s1, width, height)
    owner = torch.repeat_interleave(torch.arange(count.numel()), count)
    starts = torch.cumsum(count, 0) - count
    col = torch.arange(owner.numel()) + (i0 - starts).index_select(0, owner)
    key = (col << bits) + (((row * width) << bits) + step).index_select(0, owner)
    x = col.to(torch.float32) + 0.5
    s_raw = x * k1.index_select(0, owner) + c1.index_select(0, owner)
    perp = x * k2.index_select(0, owner) + c2.index_select(0, owner)
    s = s_raw.clamp(0.0, 1.0)
    beyond = s_raw - s
    length = part.length
    dist = torch.sqrt(beyond * beyond * (length * length) + perp * perp)
    alpha = (part.radius + 0.5 - dist).clamp(0.0, 1.0)
    look = part.look
    v = (perp * (1.0 / part.radius)).clamp(-1.0, 1.0)
    stripes = torch.sin(s * (2 * math.pi * length / (look.period * scale)) + look.phase)
    colour = (look.gain * (1.0 + look.side * v) * (1.0 - look.rim * v * v)
              * (1.0 + look.stripe * stripes))
    return key, alpha, colour


def _composite(parts: list[_Part], s0: int, s1: int, width: int, height: int, scale: float,
               static: Tensor, mean: float):
    """Intensity of every covered (pixel, step) at steps ``s0..s1``, sorted by pixel, step.

    Fragments of one (pixel, step) are composited over the static value in part order.

    Returns:
        ``(pixel, step, value)``: int64 sensor pixel, int64 step relative to ``s0`` and
        float32 linear intensity.
    """
    bits = _step_bits(s0, s1)
    pieces = [_rasterise(p, s0, s1, width, height, scale) for p in parts]
    if not pieces:
        empty = torch.empty(0, dtype=torch.int64)
        return empty, empty.clone(), torch.empty(0)
    key, alpha, colour = (torch.cat(c) for c in zip(*pieces, strict=True))
    key, order = stable_sort_small(key)
    alpha = alpha.index_select(0, order)
    colour = colour.index_select(0, order) * mean
    pixel = key >> bits
    value = static.index_select(0, pixel) * (1 - alpha) + alpha * colour
    repeat = torch.zeros(key.shape, dtype=torch.bool)
    repeat[1:] = key[1:] == key[:-1]
    later = _nonzero(repeat)
    if later.numel() == 0:
        return pixel, key & ((1 << bits) - 1), value
    index = torch.arange(key.numel())
    owner = torch.cummax(index * ~repeat, 0).values.index_select(0, later)
    rank = later - owner
    for r in range(1, int(rank.max()) + 1):
        sel = _nonzero(rank == r)
        d, g = later.index_select(0, sel), owner.index_select(0, sel)
        a = alpha.index_select(0, d)
        value.index_copy_(0, g, value.index_select(0, g) * (1 - a) + a * colour.index_select(0, d))
    starts = _nonzero(~repeat)
    pixel, key, value = (c.index_select(0, starts) for c in (pixel, key, value))
    return pixel, key & ((1 << bits) - 1), value


class _Grid:
    """Sensor and output grids, the static image and its block means."""

    def __init__(self, scene: GestureScene, factor: tuple[int, int]):
        self.width, self.height, _ = scene.sensor_size
        self.factor = factor
        self.out_w, self.out_h, _ = output_size(scene.sensor_size, factor)
        self.static, self.mean = _static_image(scene)
        self.static_flat = self.static.reshape(-1)
        self.scale = scene.scale
        fx, fy = factor
        if factor == (1, 1):
            self.static_out = self.static_flat
        else:
            pad_w, pad_h = self.out_w * fx - self.width, self.out_h * fy - self.height
            padded = torch.nn.functional.pad(self.static, (0, pad_w, 0, pad_h))
            ones = torch.nn.functional.pad(torch.ones_like(self.static), (0, pad_w, 0, pad_h))
            sums = padded.reshape(self.out_h, fy, self.out_w, fx).sum(dim=(1, 3))
            self.count = ones.reshape(self.out_h, fy, self.out_w, fx).sum(dim=(1, 3)).reshape(-1)
            self.sum_out = sums.reshape(-1)
            self.static_out = self.sum_out / self.count

    def samples(self, parts: list[_Part], s0: int, s1: int):
        """Output pixels' linear intensity at steps ``s0..s1`` where moving parts cover them.

        Returns ``(pixel, step, intensity)`` sorted by output pixel then step (``step``
        absolute, int64; intensity float32); pixels absent at a step sit at their static
        value.
        """
        bits = _step_bits(s0, s1)
        pixel, step, value = _composite(parts, s0, s1, self.width, self.height, self.scale,
                                        self.static_flat, self.mean)
        if self.factor != (1, 1):
            fx, fy = self.factor
            delta = value - self.static_flat.index_select(0, pixel)
            block = (pixel // self.width) // fy * self.out_w + (pixel % self.width) // fx
            key, order = stable_sort_small((block << bits) + step)
            delta = delta.index_select(0, order)
            new = torch.ones(key.shape, dtype=torch.bool)
            new[1:] = key[1:] != key[:-1]
            group = torch.cumsum(new, 0) - 1
            sums = torch.zeros(int(group[-1]) + 1 if group.numel() else 0,
                               dtype=delta.dtype).index_add_(0, group, delta)
            key = key[new]
            pixel = key >> bits
            step = key & ((1 << bits) - 1)
            value = (self.sum_out.index_select(0, pixel) + sums) / self.count.index_select(0, pixel)
        return pixel, step + s0, value


def _with_static(pixel: Tensor, step: Tensor, x: Tensor, x_static: Tensor, s0: int, s1: int):
    """Insert static samples just before and after each covered stretch of each pixel.

    Args:
        pixel, step, x: samples sorted by pixel then step (steps within ``[s0, s1]``).
        x_static: ``(P,)`` level of each pixel at its static intensity.

    Returns ``(pixel, step, x, first)`` where ``first`` marks each pixel's first sample.
    """
    n = pixel.numel()
    first = torch.ones(n, dtype=torch.bool)
    first[1:] = pixel[1:] != pixel[:-1]
    last = torch.ones(n, dtype=torch.bool)
    last[:-1] = first[1:]
    gap = step[1:] - step[:-1]
    pre = first & (step > s0)
    pre[1:] |= ~first[1:] & (gap > 2)
    post = last & (step < s1)
    post[:-1] |= ~last[:-1] & (gap > 1)
    count = 1 + pre.to(torch.int64) + post.to(torch.int64)
    end = torch.cumsum(count, 0)
    total = int(end[-1])
    own = end - count + pre.to(torch.int64)
    out_pixel = torch.repeat_interleave(pixel, count)
    out_step = torch.empty(total, dtype=torch.int64).index_copy_(0, own, step)
    out_x = torch.empty(total, dtype=x.dtype).index_copy_(0, own, x)
    for flag, shift in ((pre, -1), (post, 1)):
        where = _nonzero(flag)
        at = own.index_select(0, where) + shift
        out_step.index_copy_(0, at, step.index_select(0, where) + shift)
        out_x.index_copy_(0, at, x_static.index_select(0, pixel.index_select(0, where)))
    out_first = torch.zeros(total, dtype=torch.bool)
    out_first[(end - count)[first]] = True
    return out_pixel, out_step, out_x, out_first


def _chunks(parts: list[_Part], n_steps: int, n_pixels: int, max_fragments: int):
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
) -> tuple[Tensor, Tensor]:
    """Per-pixel threshold and initial offset of the output sensor, drawn from the scene.

    Returns:
        ``(theta, offset)``: ``(W' * H',)`` float64 each; ``theta`` is
        ``threshold + threshold_mismatch * N(0, 1)`` clipped to ``threshold / 4`` or more,
        ``offset`` is uniform in ``(-1, 1)``. Pixel ``(x, y)`` is entry ``y * W' + x``.
    """
    out_w, out_h, _ = output_size(scene.sensor_size, factor)
    generator = _generator(scene, _PIXEL_STREAM, factor)
    n_out = out_w * out_h
    noise = torch.randn(n_out, generator=generator, dtype=torch.float64)
    theta = (config.threshold + config.threshold_mismatch * noise).clamp_min(config.threshold / 4)
    offset = (torch.rand(n_out, generator=generator, dtype=torch.float64) * 2 - 1) * (1 - 2**-20)
    return theta, offset


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
    parts = _moving_parts(scene, times)
    grid = _Grid(scene, factor)
    n_out = grid.out_w * grid.out_h
    theta, offset = pixel_parameters(scene, config, factor)
    log_static = torch.log(grid.static_out).to(torch.float64)
    pixel0, _, value0 = grid.samples(parts, 0, 0)
    log_start = log_static.clone()
    log_start[pixel0] = torch.log(value0).to(torch.float64)
    reference = log_start - offset * theta
    x_static = (log_static - reference) / theta
    q_state = torch.zeros(n_out, dtype=torch.int64)
    ev_pixel, ev_time, ev_on = [], [], []
    n_steps = times.numel() - 1
    for s0, s1 in _chunks(parts, n_steps, grid.width * grid.height, max_fragments):
        pixel, step, value = grid.samples(parts, s0, s1)
        if pixel.numel() == 0:
            continue
        level = torch.log(value).to(torch.float64)
        x = (level - reference.index_select(0, pixel)) / theta.index_select(0, pixel)
        pixel, step, x, first = _with_static(pixel, step, x, x_static, s0, s1)
        q_init = q_state.index_select(0, pixel)
        segment, time, on, q = lattice_crossings(x, times[step], first, q_init)
        ends = torch.ones_like(first)
        ends[:-1] = first[1:]
        q_state[pixel[ends]] = q[ends]
        ev_pixel.append(pixel[segment])
        ev_time.append(round_time(time))
        ev_on.append(on)
    noise = noise_events(
        num_pixels=n_out,
        duration_us=scene.duration_us,
        background_rate_hz=config.background_rate_hz * scene.noise_scale,
        hot_pixel_fraction=config.hot_pixel_fraction,
        hot_pixel_rate_hz=config.hot_pixel_rate_hz,
        generator=_generator(scene, _NOISE_STREAM, factor),
    )
    pixel = torch.cat(ev_pixel + [noise[0]])
    t = torch.cat(ev_time + [noise[1]])
    on = torch.cat(ev_on + [noise[2]])
    inside = t < scene.duration_us
    pixel, t, on = pixel[inside], t[inside], on[inside]
    order = torch.sort(pixel * (scene.duration_us + 1) + t, stable=True).indices
    pixel, t, on = pixel[order], t[order], on[order]
    keep = refractory_mask(pixel, t, config.refractory_us)
    pixel, t, on = pixel[keep], t[keep], on[keep]
    order = torch.sort(t, stable=True).indices
    pixel, t, on = pixel[order], t[order], on[order]
    return Events(pixel % grid.out_w, pixel // grid.out_w, t, on)


def swept_mask(
    scene: GestureScene,
    config: PixelModelConfig | None = None,
    *,
    factor: int | tuple[int, int] = 1,
) -> Tensor:
    """Output pixels that a moving part covers at some simulation step.

    Only these pixels can emit events other than noise. Covering means a coverage above 0
    at a pixel of the block (``factor`` as in :func:`render_events`).

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
    parts = _moving_parts(scene, times)
    width, height, _ = scene.sensor_size
    out_w, out_h, _ = output_size(scene.sensor_size, factor)
    mask = torch.zeros(out_h * out_w, dtype=torch.bool)
    for s0, s1 in _chunks(parts, times.numel() - 1, width * height, MAX_FRAGMENTS):
        for part in parts:
            key, _, _ = _rasterise(part, s0, s1, width, height, scene.scale)
            pixel = key >> _step_bits(s0, s1)
            mask[(pixel // width) // factor[1] * out_w + (pixel % width) // factor[0]] = True
    return mask.reshape(out_h, out_w)


def intensity_frame(
    scene: GestureScene, t_us: float, *, factor: int | tuple[int, int] = 1
) -> Tensor:
    """The scene's linear intensity at one instant, rendered densely (for checks and plots).

    Args:
        scene: the scene.
        t_us: time, microseconds.
        factor: block size of the output pixels (block means), as in :func:`render_events`.

    Returns:
        ``(H', W')`` float32 linear intensity.

    Example:
        >>> scene = GestureScene.sample(5, seed=2, sensor_size=(40, 30, 2))
        >>> intensity_frame(scene, 0.0, factor=4).shape
        torch.Size([8, 10])
    """
    factor = check_factor(factor, scene.sensor_size)
    grid = _Grid(scene, (1, 1))
    times = torch.tensor([float(t_us)], dtype=torch.float64)
    image = grid.static.reshape(-1).clone()
    width, height = grid.width, grid.height
    jj, ii = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    px, py = ii.reshape(-1).float() + 0.5, jj.reshape(-1).float() + 0.5
    for part in _moving_parts(scene, times):
        alpha, colour = _shade(px, py, part.a[0], part.b[0], part.radius, part.look, scene.scale)
        image = image * (1 - alpha) + alpha * (colour * grid.mean)
    image = image.reshape(height, width)
    if factor == (1, 1):
        return image
    fx, fy = factor
    out_w, out_h, _ = output_size(scene.sensor_size, factor)
    pad = (0, out_w * fx - width, 0, out_h * fy - height)
    sums = torch.nn.functional.pad(image, pad).reshape(out_h, fy, out_w, fx).sum(dim=(1, 3))
    counts = torch.nn.functional.pad(torch.ones_like(image), pad).reshape(
        out_h, fy, out_w, fx).sum(dim=(1, 3))
    return sums / counts
