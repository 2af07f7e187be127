"""The subsamplers' budgets on real N-MNIST recordings: monotone in the setting, and reached
by calibrate within 5 %."""

from __future__ import annotations

import pytest
import torch

from evdown_torch import DensitySubsampling, PoissonSubsampling
from evdown_torch.data.sources import NMNISTSource
from evdown_torch.transforms.calibrate import BudgetTarget, calibration
from tests.conftest import SHARED_DATA

REAL = SHARED_DATA / "nmnist_small"
SENSOR = (34, 34, 2)

#: The budget setting of each subsampler and settings to sweep, small to large.
SWEEPS = {
    DensitySubsampling: ("s", [0.002, 0.005, 0.01, 0.03, 0.1, 1.0]),
    PoissonSubsampling: ("alpha", [0.01, 0.03, 0.1, 0.25, 0.6, 1.0]),
}


@pytest.fixture(scope="module")
def recordings():
    pytest.importorskip("tonic")
    torch.set_num_threads(1)  # as the study's workers run (small tensors: threads cost)
    if not REAL.is_dir():
        pytest.skip(f"{REAL} is absent")
    source = NMNISTSource(REAL, split="train")
    labels = source.labels
    chosen = [i for d in range(10) for i in [j for j, k in enumerate(labels) if k == d][:2]]
    return [source.load(i)[0] for i in chosen]


@pytest.mark.parametrize("cls", list(SWEEPS))
def test_the_output_grows_with_the_budget_setting(cls, recordings):
    name, values = SWEEPS[cls]
    inputs = sum(len(r) for r in recordings)
    totals = [sum(len(out) for out in cls(SENSOR, 2, **{name: v}).batch(recordings))
              for v in values]
    assert totals == sorted(totals) and totals[0] < 0.1 * inputs, totals
    assert totals[-1] > 0.9 * inputs


@pytest.mark.parametrize("cls", list(SWEEPS))
@pytest.mark.parametrize("ratio", [0.25, 0.05])
def test_calibrate_reaches_the_budget_within_5_percent(cls, ratio, recordings):
    inputs = sum(len(r) for r in recordings)
    found = calibration(cls(SENSOR, 4), recordings, BudgetTarget.ratio(ratio))
    out = sum(len(found.transform(r)) for r in recordings)
    assert out == found.count
    assert abs(out - ratio * inputs) <= 0.05 * ratio * inputs, (out, ratio * inputs)
    setting = cls.budget_setting
    assert getattr(found.transform, setting) == found.value != getattr(cls(SENSOR, 4), setting)
