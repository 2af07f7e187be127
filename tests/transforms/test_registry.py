"""Methods by name."""

from __future__ import annotations

import pytest

from evdown_torch.transforms import EventCount
from evdown_torch.transforms.registry import METHODS, make_method, method_settings


def test_every_method_builds_with_defaults():
    for name in METHODS:
        transform = make_method(name, (8, 8, 2), 2)
        assert transform.output_sensor_size == (4, 4, 2)


def test_settings_reach_the_transform():
    transform = make_method("event_count", (8, 8, 2), (2, 4), threshold=0.5)
    assert transform == EventCount((8, 8, 2), (2, 4), threshold=0.5)
    assert method_settings("event_count") == ("threshold",)


def test_unknown_method_and_setting():
    with pytest.raises(ValueError, match="unknown method 'nope'"):
        make_method("nope", (8, 8, 2), 2)
    with pytest.raises(ValueError, match="does not take setting"):
        make_method("downsample", (8, 8, 2), 2, threshold=1.0)
