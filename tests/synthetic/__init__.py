"""Tests of the synthetic gesture generator; shared settings below."""

from evdown_torch.synthetic import PixelModelConfig

QUIET = PixelModelConfig(background_rate_hz=0.0, hot_pixel_fraction=0.0)
"""A pixel model without background noise or hot pixels: only the scene's own events."""
