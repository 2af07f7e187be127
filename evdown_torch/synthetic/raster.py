"""Rasterising a gesture scene: the background, the capsules' fragments, block means.

The background is rendered once. The person's capsules are rasterised by scanlines, at many
steps at once, to the pixels they cover (anti-aliased coverage, their own texture), and those
fragments are composited over what lies beneath (:func:`composite`), so the cost follows the
parts, never the sensor area times the steps: the gesturing arm parts at every simulation step
(:func:`moving_parts`), the body and the arms at rest at the few key steps of its slow sway
(:func:`body_parts`; :mod:`evdown_torch.synthetic.grid` assembles both). At a lower resolution
(``factor`` ``(fx, fy)``) each output pixel sees the mean linear intensity (photocurrent) of the
block of sensor pixels it covers (edge blocks: the pixels inside the sensor).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from evdown_torch._regions import region_xy
from evdown_torch._tensors import stable_sort_small, where_true
from evdown_torch.checks import check_factor, output_size
from evdown_torch.synthetic.body_plan import (
    FOREARM,
    HAND,
    RADIUS_FORE,
    RADIUS_HAND,
    RADIUS_UPPER,
    UPPER_ARM,
    Look,
)
from evdown_torch.synthetic.scenes import GestureScene

__all__ = [
    "background_image",
    "block_of",
    "block_sums",
    "body_parts",
    "composite",
    "intensity_frame",
    "moving_parts",
    "rasterise",
    "step_bits",
]


@dataclass(frozen=True)
class _Part:
    """A capsule: endpoints per step (pixels), radius (pixels), appearance."""

    a: Tensor  # (S + 1, 2) float32
    b: Tensor  # (S + 1, 2) float32
    radius: float
    length: float  # |b - a|, the same at every step
    look: Look


def _part_moves(scene: GestureScene) -> list[list[bool]]:
    """Whether each arm part (upper arm, forearm, hand of the right, then the left arm) moves.

    Judged on a fine grid of times, without the body's sway: a part that only sways with the
    body belongs to the body (a waving arm's upper arm, say), drawn at its key steps.
    """
    probe = torch.linspace(0, scene.duration_us, 2001, dtype=torch.float64)
    out = []
    for moving, points in zip(scene.moving_arms, scene.arm_keypoints(probe, sway=False),
                              strict=True):
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


def body_parts(scene: GestureScene, times: Tensor) -> list[_Part]:
    """The body's capsules at ``times``, in compositing order.

    Torso, shoulders, neck, head, then the arm parts that do not take part in the gesture (they
    sway with the body).
    """
    out = []
    for a, b, radius, look in scene.body_capsules(times):
        length = float((b[0] - a[0]).norm())
        out.append(_Part(a.to(torch.float32), b.to(torch.float32), radius, length,
                         scene.looks[look]))
    for moves, points in zip(_part_moves(scene), scene.arm_keypoints(times), strict=True):
        points = points.to(torch.float32)
        for k in range(3):
            if not moves[k]:
                out.append(_Part(points[:, k], points[:, k + 1], _RADII[k] * scene.scale,
                                 _LENGTHS[k] * scene.scale, scene.looks[2 + k]))
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
        px: ``(N,)`` float32 pixel-centre x coordinates.
        py: ``(N,)`` float32 pixel-centre y coordinates.
        a: ``(N, 2)`` or ``(2,)`` float32 first capsule endpoint.
        b: ``(N, 2)`` or ``(2,)`` float32 second capsule endpoint.
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


def background_image(scene: GestureScene) -> tuple[Tensor, float]:
    """The background, ``(H, W)`` float32, and its mean (the unit of every part's intensity)."""
    image = _background(scene)
    return image, float(image.mean())


def _rows(part: _Part, s0: int, s1: int, width: int, height: int
          ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
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
    """Flat output pixel ``(y // fy) * out_width + x // fx`` of flat sensor pixels ``y * W + x``."""
    x, y = region_xy(pixel, width)
    return torch.div(y, factor[1], rounding_mode="floor") * out_width + torch.div(
        x, factor[0], rounding_mode="floor")


def step_bits(s0: int, s1: int) -> int:
    """Bits that hold a step of ``s0..s1`` relative to ``s0`` (keys are ``pixel << bits``)."""
    return max(1, (s1 - s0).bit_length())


def rasterise(part: _Part, s0: int, s1: int, width: int, height: int, scale: float
              ) -> tuple[Tensor, Tensor, Tensor]:
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


def composite(parts: list[_Part], s0: int, s1: int, width: int, height: int, scale: float,
              base: Callable[[Tensor, Tensor], Tensor], mean: float
              ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Intensity of every covered (pixel, step) at steps ``s0..s1``, sorted by pixel, step.

    Fragments of one (pixel, step) are composited over ``base(pixel, step)`` (float32 linear
    intensity beneath the parts; ``step`` relative to ``s0``) in part order.

    Returns:
        ``(pixel, step, value, beneath)``: int64 sensor pixel, int64 step relative to ``s0``,
        float32 linear intensity and the float32 ``base`` beneath it.
    """
    bits = step_bits(s0, s1)
    pieces = [rasterise(p, s0, s1, width, height, scale) for p in parts]
    if not pieces:
        empty = torch.empty(0, dtype=torch.int64)
        return empty, empty.clone(), torch.empty(0), torch.empty(0)
    key, alpha, colour = (torch.cat(c) for c in zip(*pieces, strict=True))
    key, order = stable_sort_small(key)
    alpha = alpha.index_select(0, order)
    colour = colour.index_select(0, order) * mean
    pixel = key >> bits
    step = key & ((1 << bits) - 1)
    beneath = base(pixel, step)
    value = beneath * (1 - alpha) + alpha * colour
    repeat = torch.zeros(key.shape, dtype=torch.bool)
    repeat[1:] = key[1:] == key[:-1]
    later = where_true(repeat)
    if later.numel() == 0:
        return pixel, step, value, beneath
    index = torch.arange(key.numel())
    owner = torch.cummax(index * ~repeat, 0).values.index_select(0, later)
    rank = later - owner
    for r in range(1, int(rank.max()) + 1):
        sel = where_true(rank == r)
        d, g = later.index_select(0, sel), owner.index_select(0, sel)
        a = alpha.index_select(0, d)
        value.index_copy_(0, g, value.index_select(0, g) * (1 - a) + a * colour.index_select(0, d))
    starts = where_true(~repeat)
    return (pixel.index_select(0, starts), step.index_select(0, starts),
            value.index_select(0, starts), beneath.index_select(0, starts))


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


def intensity_frame(
    scene: GestureScene, t_us: float, *, factor: int | tuple[int, int] = 1
) -> Tensor:
    """The scene's linear intensity at one instant, rendered densely (for checks and plots).

    The body is drawn where its sway has it at ``t_us`` (the event renderer interpolates it
    between key steps; at a key step the two agree).

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
    width, height, _ = scene.sensor_size
    background, mean = background_image(scene)
    times = torch.tensor([float(t_us)], dtype=torch.float64)
    image = background.reshape(-1).clone()
    jj, ii = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    px, py = ii.reshape(-1).float() + 0.5, jj.reshape(-1).float() + 0.5
    for part in body_parts(scene, times) + moving_parts(scene, times):
        alpha, colour = _shade(px, py, part.a[0], part.b[0], part.radius, part.look, scene.scale)
        image = image * (1 - alpha) + alpha * (colour * mean)
    image = image.reshape(height, width)
    if factor == (1, 1):
        return image
    sums, counts = block_sums(image, factor)
    return sums / counts
