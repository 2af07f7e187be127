"""Synthetic DVS gesture recordings: a DVS pixel model, 11 gesture classes, low-res ground truth.

Scenes (``scenes``: a person who sways slowly and gestures) are rasterised
(``raster``) onto a grid whose swaying body is rendered at its own key steps
(``grid``), lit (``lighting``) and rendered through the pixel model
(``pixel_model``) by ``render``; ``dataset`` wraps them in
``tonic.datasets.DVSGesture``'s interface.

Measured against DVS128 Gesture (``python benchmarks/synthetic_stats.py --seeds 2``: 22
recordings of 6 s at 128 x 128, one per class for seeds 0 to 10 and 1000 to 1010;
docs/benchmarks.md, "Synthetic gestures", has the figures of every recording):

=====================================  ============================  ========================
statistic                              synthetic                     DVS128 Gesture / target
=====================================  ============================  ========================
events per recording                   123k to 441k, mean 238k       200k to 400k (mean 194k)
ON share                               0.420 to 0.567                about 0.4 to 0.6
peak / mean rate in 10 ms bins         3.2 to 18.6, median 4.6       at least 3
EventFunnelling at factor 4 removes    1.7 to 8.8 %, mean 4.6 %      4.1 % (the paper)
render time, one core                  0.14 to 0.41 s, median 0.22   under 0.5 s
=====================================  ============================  ========================

The share EventFunnelling removes follows the class (how fast edges sweep: big arm circles
most, small hand rolls least), not the lighting; the body's sway gives a median 9 % of the
events.
"""

from evdown_torch.synthetic.body_plan import GESTURE_CLASSES, LIGHTING, Look
from evdown_torch.synthetic.dataset import DVS_GESTURE_DTYPE, SyntheticGestures, render_gesture
from evdown_torch.synthetic.pixel_model import (
    PixelModelConfig,
    noise_events,
    pixel_events,
    readout_times,
    refractory_mask,
)
from evdown_torch.synthetic.raster import intensity_frame
from evdown_torch.synthetic.render import render_events, step_times, swept_mask
from evdown_torch.synthetic.scenes import GestureScene

__all__ = [
    "DVS_GESTURE_DTYPE",
    "GESTURE_CLASSES",
    "LIGHTING",
    "GestureScene",
    "Look",
    "PixelModelConfig",
    "intensity_frame",
    "noise_events",
    "pixel_events",
    "readout_times",
    "refractory_mask",
    "render_events",
    "render_gesture",
    "step_times",
    "swept_mask",
    "SyntheticGestures",
]
