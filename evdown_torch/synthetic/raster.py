"""Rasterising a gesture scene: the static image, the moving limbs' fragments, block means.

The background, the torso, the head and resting arms form a static image, rendered once. At
each simulation step every moving capsule is rasterised by scanlines to the pixels it covers
(anti-aliased coverage, its own texture), and those fragments are composited over the static
image, so the cost follows the moving parts, never the sensor area times the steps. At a lower
resolution (``factor`` ``(fx, fy)``) each output pixel sees the mean linear intensity
(photocurrent) of the block of sensor pixels it covers (edge blocks: the pixels inside the
sensor), computed from the same fragments.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from evdown_torch._tensors import region_xy, stable_sort_small
from evdown_torch.checks import check_factor, output_size
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
)

__all__ = [
    "Grid",
    "block_of",
    "block_sums",
    "intensity_frame",
    "moving_parts",
    "rasterise",
    "step_bits",
]


@dataclass(frozen=True)
class _Part:
    """A moving capsule: endpoints per step (pixels), radius (pixels), appearance."""

    a: Tensor  # (S + 1, 2) float32
    b: Tensor  # (S + 1, 2) float32
    radius: float
    length: float  # |b - a|, the same at every step
    look: Look


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


def moving_parts(scene: GestureScene, times: Tensor) -> list[_Part]:
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


def block_of(pixel: Tensor, width: int, factor: tuple[int, int], out_width: int) -> Tensor:
    """Flat output pixel ``(y // fy) * out_width + x // fx`` of flat sensor pixels ``y * W + x``.
    """
    x, y = region_xy(pixel, width)
    return torch.div(y, factor[1], rounding_mode="floor") * out_width + torch.div(
        x, factor[0], rounding_mode="floor")


def step_bits(s0: int, s1: int) -> int:
    """Bits that hold a step of ``s0..s1`` relative to ``s0`` (keys are ``pixel << bits``)."""
    return max(1, (s1 - s0).bit_length())


def rasterise(part: _Part, s0: int, s1: int, width: int, height: int, scale: float):
    """Fragments of a moving capsule at steps ``s0..s1``.

    Returns ``(key, alpha, colour)``: ``key = (pixel << bits) | step`` (``pixel = j * W + i``,
    ``step`` relative to ``s0``, ``bits`` from :func:`step_bits`), coverage in ``[0, 1]``
    and linear intensity relative to the background's mean (float32).
    """
    bits = step_bits(s0, s1)
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
    bits = step_bits(s0, s1)
    pieces = [rasterise(p, s0, s1, width, height, scale) for p in parts]
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


def block_sums(image: Tensor, factor: tuple[int, int]) -> tuple[Tensor, Tensor]:
    """Sums of an ``(H, W)`` image over ``fx x fy`` blocks and the pixels in each block.

    Returns:
        ``(sums, counts)``, each ``(H', W')`` (:func:`~evdown_torch.checks.output_size`); edge
        blocks hold the pixels inside the image only.
    """
    height, width = image.shape
    fx, fy = factor
    out_w, out_h, _ = output_size((width, height, 1), factor)
    pad = (0, out_w * fx - width, 0, out_h * fy - height)
    sums = torch.nn.functional.pad(image, pad).reshape(out_h, fy, out_w, fx).sum(dim=(1, 3))
    counts = torch.nn.functional.pad(torch.ones_like(image), pad).reshape(
        out_h, fy, out_w, fx).sum(dim=(1, 3))
    return sums, counts


class Grid:
    """Sensor and output grids, the static image and its block means."""

    def __init__(self, scene: GestureScene, factor: tuple[int, int]):
        self.width, self.height, _ = scene.sensor_size
        self.factor = factor
        self.out_w, self.out_h, _ = output_size(scene.sensor_size, factor)
        self.static, self.mean = _static_image(scene)
        self.static_flat = self.static.reshape(-1)
        self.scale = scene.scale
        if factor == (1, 1):
            self.static_out = self.static_flat
        else:
            sums, count = block_sums(self.static, factor)
            self.sum_out, self.count = sums.reshape(-1), count.reshape(-1)
            self.static_out = self.sum_out / self.count

    def samples(self, parts: list[_Part], s0: int, s1: int):
        """Output pixels' linear intensity at steps ``s0..s1`` where moving parts cover them.

        Returns ``(pixel, step, intensity)`` sorted by output pixel then step (``step``
        absolute, int64; intensity float32); pixels absent at a step sit at their static
        value.
        """
        bits = step_bits(s0, s1)
        pixel, step, value = _composite(parts, s0, s1, self.width, self.height, self.scale,
                                        self.static_flat, self.mean)
        if self.factor != (1, 1):
            delta = value - self.static_flat.index_select(0, pixel)
            block = block_of(pixel, self.width, self.factor, self.out_w)
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
    grid = Grid(scene, (1, 1))
    times = torch.tensor([float(t_us)], dtype=torch.float64)
    image = grid.static.reshape(-1).clone()
    width, height = grid.width, grid.height
    jj, ii = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    px, py = ii.reshape(-1).float() + 0.5, jj.reshape(-1).float() + 0.5
    for part in moving_parts(scene, times):
        alpha, colour = _shade(px, py, part.a[0], part.b[0], part.radius, part.look, scene.scale)
        image = image * (1 - alpha) + alpha * (colour * grid.mean)
    image = image.reshape(height, width)
    if factor == (1, 1):
        return image
    sums, counts = block_sums(image, factor)
    return sums / counts
