"""LIFSettings: the LIF settings checked and normalised once, shared by transform and module."""

from __future__ import annotations

import math

import numpy as np
import pytest

from evdown_torch import LIFPooling
from evdown_torch.models import SpikingPooling
from evdown_torch.transforms.functional.lif.settings import (
    DEFAULT_TAU,
    LIFNeuron,
    LIFSettings,
)


def test_every_number_becomes_a_float_and_beta_follows_dt_and_tau():
    s = LIFSettings(dt=np.int64(4), tau=np.float32(8.0), threshold=2, weight=np.float16(0.5),
                    mutual_inhibition=1)
    values = (s.dt, s.tau, s.threshold, s.weight, s.mutual_inhibition, s.beta)
    assert all(type(v) is float for v in values)
    assert values == (4.0, 8.0, 2.0, 0.5, 1.0, math.exp(-0.5))
    assert s.constants == LIFNeuron(math.exp(-0.5), 2.0, 0.5, 1.0, "subtract")


def test_the_leak_is_tau_or_beta_and_defaults_to_ten_steps():
    assert LIFSettings(dt=3).tau == 30.0 and LIFSettings().tau == DEFAULT_TAU == 10_000.0
    assert LIFSettings(dt=3).beta == math.exp(-0.1)
    assert LIFSettings(tau=math.inf).beta == 1.0
    given = LIFSettings(dt=7, beta=0.25)
    assert given.beta == 0.25 and given.tau is None
    with pytest.raises(ValueError, match="tau or as beta, not both"):
        LIFSettings(tau=5.0, beta=0.5)


@pytest.mark.parametrize(
    ("kwargs", "error", "message"),
    [
        ({"dt": 0}, ValueError, "dt must be a positive"),
        ({"tau": 0.0}, ValueError, "tau must be a positive number"),
        ({"beta": 1.5}, ValueError, r"beta must lie in \[0, 1\]"),
        ({"threshold": -1}, ValueError, "threshold must be a positive"),
        ({"weight": True}, TypeError, "weight must be a positive number"),
        ({"mutual_inhibition": math.inf}, ValueError, "mutual_inhibition must be a non-negative"),
        ({"reset_mechanism": "hard"}, ValueError, "reset_mechanism must be one of"),
    ],
)
def test_transform_and_module_refuse_the_same_settings_with_the_same_message(
    kwargs, error, message
):
    with pytest.raises(error, match=message):
        LIFSettings(**kwargs)
    module_kwargs = {"dt": 1.0, **kwargs}
    with pytest.raises(error, match=message):
        SpikingPooling(2, **module_kwargs)
    if "beta" not in kwargs:
        with pytest.raises(error, match=message):
            LIFPooling((4, 4, 2), 2, **kwargs)


def test_the_transform_holds_its_normalised_settings_and_builds_the_module_from_them():
    pool = LIFPooling((8, 8, 2), 2, dt=np.int32(500), tau=2000, threshold=np.float64(1.5),
                      weight=1, mutual_inhibition=np.float32(0.25), reset_mechanism="zero")
    assert (type(pool.dt), type(pool.tau), type(pool.weight)) == (float, float, float)
    assert pool.settings.neuron == LIFSettings(500.0, 2000.0, 1.5, 1.0, 0.25, "zero")
    assert pool.beta == pool.settings.neuron.constants.beta == math.exp(-0.25)
    module = SpikingPooling.from_transform(pool)
    assert (module.beta, module.threshold, module.reset_mechanism) == (
        float(np.float32(math.exp(-0.25))), 1.5, "zero")
    assert (module.weight.item(), module.mutual_inhibition.item()) == (1.0, 0.25)
    assert pool == LIFPooling((8, 8, 2), 2, dt=500.0, tau=2000.0, threshold=1.5, weight=1.0,
                              mutual_inhibition=0.25, reset_mechanism="zero")
