"""Synthetic DVS gesture recordings: a DVS pixel model, 11 gesture classes, low-res ground truth.

Scenes (:mod:`.scenes`) are rasterised (:mod:`.raster`), lit (:mod:`.lighting`) and rendered
through the pixel model (:mod:`.pixel_model`) by :mod:`.render`; :mod:`.dataset` wraps them
in ``tonic.datasets.DVSGesture``'s interface. The statistics measured against DVS128 Gesture
are in the README ("Synthetic gestures") and ``benchmarks/synthetic_stats.py`` prints them.
"""

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
from evdown_torch.synthetic.scenes import GESTURE_CLASSES, LIGHTING, GestureScene, Look

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
