"""Lamp flicker: the modulation of fluorescent and LED light, and where the sensor sees it.

DVS128 Gesture was recorded under natural light, fluorescent light and LED light. Lamps on the
mains flicker at twice its frequency (100 Hz on 50 Hz mains, 120 Hz on 60 Hz); the sensor sees
the flicker where the lamp's light dominates and the photoreceptor is fast enough, i.e. on the
brightest surfaces. Model:

* the lamp multiplies the linear intensity of pixel ``p`` by ``1 + m_p * w(t)``, where ``w``
  is a periodic waveform in ``[-1, 1]`` (fluorescent: a triangle, the rectified sine's
  piecewise-linear stand-in; LED: a trapezoid, its PWM driver's fast edges and flat tops),
  ``m_p = scene.flicker_depth * lit_p`` and ``lit_p`` in ``[0, 1]`` grows with the static
  image's log brightness over its 99th percentile (:func:`lamp_share`);
* a block of a lower-resolution sensor receives the block's mean photocurrent, so its depth is
  the intensity-weighted mean of its pixels' depths, the same light seen by a larger pixel;
* the flicker of the static image is simulated through the pixel model for every pixel whose
  peak-to-peak log modulation reaches its smaller threshold (a smaller modulation can only
  ever emit one event, at the start, which is left out), at the image of the recording's
  start. The moving limbs and the swaying body are rendered without the lamp's modulation and
  do not occlude or move the flicker (a simplification: limbs cover a lit pixel for a few
  milliseconds at a time, and the body moves a few pixels over seconds).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from evdown_torch._tensors import where_true
from evdown_torch.synthetic.scenes import GestureScene

__all__ = ["flicker_depth", "flicker_samples", "lamp_share", "waveform"]

#: Waveform breakpoints per period: (fraction of the period, value in [-1, 1]).
WAVEFORMS = {
    "fluorescent": ((0.0, -1.0), (0.5, 1.0)),
    "led": ((0.0, -1.0), (0.1, 1.0), (0.5, 1.0), (0.6, -1.0)),
}


def waveform(scene: GestureScene, t_us: Tensor) -> Tensor:
    """The lamp's waveform ``w(t)`` in ``[-1, 1]`` at times ``t_us`` (0 under natural light).

    Example:
        >>> import dataclasses
        >>> scene = GestureScene.sample(0, 1)
        >>> lamp = dataclasses.replace(scene, lighting="fluorescent", flicker_hz=100.0)
        >>> w = waveform(lamp, torch.tensor([0.0, 1250.0, 5000.0, 6250.0]))
        >>> w.round(decimals=6).tolist()
        [-1.0, -0.5, 1.0, 0.5]
    """
    t_us = torch.as_tensor(t_us, dtype=torch.float64)
    if scene.flicker_hz <= 0 or scene.lighting not in WAVEFORMS:
        return torch.zeros_like(t_us)
    points = WAVEFORMS[scene.lighting]
    xs = torch.tensor([p for p, _ in points] + [1.0], dtype=torch.float64)
    ys = torch.tensor([v for _, v in points] + [points[0][1]], dtype=torch.float64)
    frac = torch.remainder(t_us * (scene.flicker_hz * 1e-6), 1.0)
    k = (torch.searchsorted(xs, frac, right=True) - 1).clamp(0, len(points) - 1)
    x0, x1, y0, y1 = xs[k], xs[k + 1], ys[k], ys[k + 1]
    return y0 + (frac - x0) / (x1 - x0) * (y1 - y0)


def lamp_share(static: Tensor) -> Tensor:
    """``lit_p``: how much of the lamp's modulation pixel ``p`` of the static image shows.

    ``clamp((log I_p - q) / 0.3, 0, 1)`` with ``q`` the 99th percentile of the log
    intensities: the brightest hundredth of the scene (highlights facing the lamp), fully
    from 0.3 log units above it.
    """
    log_image = torch.log(static.to(torch.float64))
    q = torch.quantile(log_image.reshape(-1), 0.99)
    return ((log_image - q) / 0.3).clamp(0, 1)


def flicker_depth(scene: GestureScene, static: Tensor, factor: tuple[int, int],
                  block_sums: Callable[[Tensor, tuple[int, int]], tuple[Tensor, Tensor]]
                  ) -> Tensor:
    """Per output pixel depth ``m`` of the lamp's modulation, ``(H' * W',)`` float64.

    Args:
        scene: the scene (its ``flicker_depth``).
        static: ``(H, W)`` static linear intensity of the full-resolution sensor.
        factor: ``(fx, fy)`` of the output sensor.
        block_sums: the block-sum function of the rasteriser (sums, counts over blocks).
    """
    depth = scene.flicker_depth * lamp_share(static)
    if factor == (1, 1):
        return depth.reshape(-1)
    weighted, _ = block_sums(static.to(torch.float64) * depth, factor)
    light, _ = block_sums(static.to(torch.float64), factor)
    return (weighted / light).reshape(-1)


def flicker_samples(scene: GestureScene, depth: Tensor, log_static: Tensor,
                    min_threshold: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Samples of the flickering static image, for the pixels whose flicker can fire.

    Args:
        scene: the scene (lighting, frequency, duration).
        depth: ``(P,)`` modulation depth of each output pixel.
        log_static: ``(P,)`` static log intensity of each output pixel.
        min_threshold: ``(P,)`` the smaller of each pixel's ON and OFF thresholds.

    Returns:
        ``(pixel, t, level)``: int64 pixel, float64 time (microseconds, from 0 to the
        duration) and float64 log intensity of each sample, sorted by pixel then time; the
        waveform's breakpoints are the samples, so the level is exact between them.
    """
    empty = (torch.empty(0, dtype=torch.int64), torch.empty(0, dtype=torch.float64),
             torch.empty(0, dtype=torch.float64))
    if scene.flicker_hz <= 0 or scene.lighting not in WAVEFORMS:
        return empty
    swing = torch.log1p(depth) - torch.log1p(-depth.clamp(max=1 - 1e-9))
    lit = where_true(swing >= min_threshold)
    if lit.numel() == 0:
        return empty
    period = 1e6 / scene.flicker_hz
    fractions = torch.tensor([p for p, _ in WAVEFORMS[scene.lighting]], dtype=torch.float64)
    cycles = torch.arange(math.ceil(scene.duration_us / period) + 1, dtype=torch.float64)
    breaks = ((cycles[:, None] + fractions[None, :]) * period).reshape(-1)
    inner = breaks[(breaks > 0) & (breaks < scene.duration_us)]
    times = torch.cat([torch.zeros(1, dtype=torch.float64), inner,
                       torch.tensor([float(scene.duration_us)], dtype=torch.float64)])
    w = waveform(scene, times)
    level = (log_static.index_select(0, lit)[:, None]
             + torch.log1p(depth.index_select(0, lit)[:, None] * w[None, :]))
    pixel = lit.repeat_interleave(times.numel())
    return pixel, times.repeat(lit.numel()), level.reshape(-1)
