"""Methods by name."""

from __future__ import annotations

import pytest

from evdown_torch.transforms import EventCount
from evdown_torch.transforms.registry import METHODS, make_method, method_settings
from tests.helpers import transform_cases


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


def test_every_registry_method_is_in_the_tests_table_of_instances():
    cases = transform_cases((8, 8, 2), 2, step=10)
    for name, cls in METHODS.items():
        assert cls.name == name
        assert isinstance(cases[name], cls)


def test_a_transform_class_without_method_or_settings_is_refused_when_defined():
    from evdown_torch.transforms import Downscaler, Streaming

    with pytest.raises(TypeError, match="names no method"):
        class NoMethod(Downscaler):
            pass

    with pytest.raises(TypeError, match="has no settings"):
        class NoSettings(Streaming):
            method = EventCount.method
