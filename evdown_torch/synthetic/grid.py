"""The sensor grid over time: a static background, the slowly swaying body, the moving arms.

The person sways slowly (:meth:`~evdown_torch.synthetic.GestureScene.body_pose`): a few pixels
over seconds, far slower than the gesturing arms. So the body (torso, shoulders, neck, head
and the arm parts at rest) is rendered only at key steps (:func:`key_steps`), chosen among the
simulation steps so that no point of the body moves more than about ``max_step_px`` pixels
between two of them. A pixel whose intensity differs between key steps is a swaying pixel;
between key steps its log intensity is linear in time (what the pixel model assumes between
samples anyway), and every other pixel keeps its static value (:class:`KeyedImage`). The arm
parts that move are composited over that, at every simulation step.

At a lower resolution (``factor`` ``(fx, fy)``) each output pixel sees the mean linear
intensity of its block of sensor pixels: a block holding a swaying pixel sways, its key values
being the block means of the key images, interpolated the same way; under the moving arms a
block receives the mean of its pixels' values (the arms composited over their own bodies).
"""

from __future__ import annotations

import torch
from torch import Tensor

from evdown_torch._tensors import stable_sort_small, where_true
from evdown_torch.checks import output_size
from evdown_torch.synthetic.body_plan import BODY_REACH
from evdown_torch.synthetic.raster import (
    _Part,
    background_image,
    block_of,
    block_sums,
    body_parts,
    composite,
    step_bits,
)
from evdown_torch.synthetic.scenes import GestureScene

__all__ = ["Grid", "KeyedImage", "key_steps"]


def key_steps(scene: GestureScene, times: Tensor, max_step_px: float) -> Tensor:
    """Steps at which the swaying body is rendered, ``(K,)`` int64, first and last included.

    A new key step is taken whenever the body's travel since the last one reaches
    ``max_step_px`` (bound: the offset's travel plus the lean's change times
    :data:`~evdown_torch.synthetic.body_plan.BODY_REACH`, in pixels); without sway, the first and
    the last step only.

    Example:
        >>> from evdown_torch.synthetic import PixelModelConfig, step_times
        >>> scene = GestureScene.sample(2, seed=3)
        >>> keys = key_steps(scene, step_times(scene, PixelModelConfig()), 1.0)
        >>> 2 < keys.numel() < 200, int(keys[0])
        (True, 0)
    """
    lean, offset = scene.body_pose(times * 1e-6)
    travel = scene.scale * (lean.diff().abs() * BODY_REACH + offset.diff(dim=0).norm(dim=1))
    reached = torch.floor(torch.cumsum(travel, 0) / max_step_px)
    crossed = torch.ones_like(reached, dtype=torch.bool)
    crossed[1:] = reached[1:] > reached[:-1]
    crossed &= reached > 0
    last = times.numel() - 1
    steps = torch.cat([torch.zeros(1, dtype=torch.int64), where_true(crossed) + 1,
                       torch.tensor([last])])
    return torch.unique(steps)


class KeyedImage:
    """A grid of pixels over the simulation steps: static, except its swaying pixels.

    A swaying pixel's log intensity is known at the key steps and linear in time between them.

    Attributes:
        static: ``(P,)`` float32 linear intensity at step 0.
        pixels: ``(n,)`` int64 swaying pixels, ascending.
        log_keys: ``(n, K)`` float64 their log intensity at the key steps.
    """

    def __init__(self, static: Tensor, pixels: Tensor, log_keys: Tensor, key_of_step: Tensor,
                 weight: Tensor):
        self.static = static
        self.log_static = torch.log(static).to(torch.float64)
        self.pixels = pixels
        self.log_keys = log_keys
        self.row = torch.full(static.shape, -1, dtype=torch.int64)
        self.row[pixels] = torch.arange(pixels.numel())
        self._key, self._weight = key_of_step, weight

    def _sway(self, pixel: Tensor, step: Tensor) -> tuple[Tensor, Tensor]:
        """Which samples sway, and their log intensity."""
        row = self.row.index_select(0, pixel)
        where = where_true(row >= 0)
        row, step = row.index_select(0, where), step.index_select(0, where)
        k = self._key.index_select(0, step)
        w = self._weight.index_select(0, step)
        lower = self.log_keys[row, k]
        return where, lower + w * (self.log_keys[row, k + 1] - lower)

    def level(self, pixel: Tensor, step: Tensor) -> Tensor:
        """Log intensity (float64) of ``pixel`` at absolute ``step``."""
        out = self.log_static.index_select(0, pixel)
        if self.pixels.numel():
            where, level = self._sway(pixel, step)
            out.index_copy_(0, where, level)
        return out

    def intensity(self, pixel: Tensor, step: Tensor) -> Tensor:
        """Linear intensity (float32) of ``pixel`` at absolute ``step``."""
        out = self.static.index_select(0, pixel)
        if self.pixels.numel():
            where, level = self._sway(pixel, step)
            out.index_copy_(0, where, torch.exp(level).to(out.dtype))
        return out


class Grid:
    """Sensor and output grids over the simulation ``times``: background, swaying body.

    Attributes:
        static: ``(H, W)`` float32 sensor image at step 0 (background and body).
        static_out: ``(H' * W',)`` float32 its block means.
        keys: ``(K,)`` int64 key steps of the body (:func:`key_steps`).
        full, out: :class:`KeyedImage` of the sensor and of the output pixels (the same object
            at factor 1).
    """

    def __init__(self, scene: GestureScene, factor: tuple[int, int], times: Tensor,
                 max_step_px: float):
        self.width, self.height, _ = scene.sensor_size
        self.factor = factor
        self.out_w, self.out_h, _ = output_size(scene.sensor_size, factor)
        self.scale = scene.scale
        background, self.mean = background_image(scene)
        flat = background.reshape(-1)
        self.keys = key_steps(scene, times, max_step_px)
        n_keys = self.keys.numel()
        at_keys = times.index_select(0, self.keys)
        k = (torch.searchsorted(self.keys, torch.arange(times.numel()), right=True) - 1)
        k = k.clamp(0, n_keys - 2)
        weight = ((times - at_keys[k]) / (at_keys[k + 1] - at_keys[k])).clamp(0, 1)

        # the body at its key steps, over the background
        pixel, key, value, _ = composite(
            body_parts(scene, at_keys), 0, n_keys - 1, self.width, self.height, scene.scale,
            lambda p, _s: flat.index_select(0, p), self.mean)
        covered, inverse = torch.unique_consecutive(pixel, return_inverse=True)
        values = flat.index_select(0, covered)[:, None].repeat(1, n_keys)
        values[inverse, key] = value
        static = flat.clone()
        static[covered] = values[:, 0]
        swaying = (values != values[:, :1]).any(dim=1)
        sway_pixels, values = covered[swaying], values[swaying].to(torch.float64)
        self.static = static.reshape(self.height, self.width)
        self.full = KeyedImage(static, sway_pixels, torch.log(values), k, weight)
        if factor == (1, 1):
            self.out = self.full
        else:
            sums, count = block_sums(self.static, factor)
            self.count = count.reshape(-1)
            block = block_of(sway_pixels, self.width, factor, self.out_w)
            blocks, inverse = torch.unique(block, return_inverse=True)
            change = values - static.index_select(0, sway_pixels).to(torch.float64)[:, None]
            block_values = sums.reshape(-1).index_select(0, blocks).to(torch.float64)[:, None]
            block_values = block_values.repeat(1, n_keys).index_add_(0, inverse, change)
            block_values /= self.count.index_select(0, blocks).to(torch.float64)[:, None]
            self.out = KeyedImage((sums / count).reshape(-1), blocks, torch.log(block_values),
                                  k, weight)
        self.static_out = self.out.static

    def samples(self, parts: list[_Part], s0: int, s1: int
                ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Samples of the output pixels that change at steps ``s0..s1``.

        The pixels the moving ``parts`` cover, at the steps they cover them, and every swaying
        output pixel at the key steps within ``s0..s1`` and at ``s0`` and ``s1`` (unless a
        part covers it then). Pixels absent at a step sit at their static value or, if they
        sway, on their line between key steps (:meth:`KeyedImage.level`).

        Returns:
            ``(pixel, step, level, covered)`` sorted by output pixel then step: int64 output
            pixel, int64 absolute step, float64 log intensity, bool whether a moving part
            covers it.
        """
        bits = step_bits(s0, s1)
        full, out = self.full, self.out
        pixel, step, value, beneath = composite(
            parts, s0, s1, self.width, self.height, self.scale,
            lambda p, s: full.intensity(p, s + s0), self.mean)
        if self.factor != (1, 1):
            delta = value - beneath
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
            value = (out.intensity(pixel, step + s0)
                     + sums / self.count.index_select(0, pixel))
        level = torch.log(value).to(torch.float64)
        if out.pixels.numel() == 0:
            return pixel, step + s0, level, torch.ones(pixel.shape, dtype=torch.bool)
        # the swaying pixels at the key steps of the chunk and its ends, merged in where no
        # moving part covers them
        inside = self.keys[(self.keys > s0) & (self.keys < s1)]
        steps = torch.cat([torch.tensor([0]), inside - s0, torch.tensor([s1 - s0])]).unique()
        sway_key = ((out.pixels[:, None] << bits) + steps[None, :]).reshape(-1)
        arm_key = (pixel << bits) + step
        at = torch.searchsorted(arm_key, sway_key)
        taken = torch.zeros(sway_key.shape, dtype=torch.bool)
        if arm_key.numel():
            taken = arm_key[at.clamp_max(arm_key.numel() - 1)] == sway_key
        sway_key, at = sway_key[~taken], at[~taken]
        sway_pixel, sway_step = sway_key >> bits, (sway_key & ((1 << bits) - 1)) + s0
        total = arm_key.numel() + sway_key.numel()
        sway_at = at + torch.arange(sway_key.numel())  # places in the merged order
        covered = torch.ones(total, dtype=torch.bool)
        covered[sway_at] = False
        arm_at = where_true(covered)
        merged = []
        for arm, sway in ((pixel, sway_pixel), (step + s0, sway_step),
                          (level, out.level(sway_pixel, sway_step))):
            merged.append(torch.empty(total, dtype=arm.dtype).index_copy_(0, arm_at, arm)
                          .index_copy_(0, sway_at, sway))
        return merged[0], merged[1], merged[2], covered
