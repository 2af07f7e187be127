"""The LIF decays ``beta ** g``: the exact power rounded once, whatever the cell's place."""

from __future__ import annotations

import random
from decimal import Context, Decimal
from fractions import Fraction

import numpy as np
import pytest
import torch

from evdown_torch import Events
from evdown_torch.transforms.functional.lif.pooling import lif_pooling
from evdown_torch.transforms.functional.lif.powers import Powers
from evdown_torch.transforms.functional.lif.settings import LIFPoolingSettings, LIFSettings
from evdown_torch.transforms.functional.lif.stream import (
    lif_pooling_finish,
    lif_pooling_init,
    lif_pooling_step,
    lif_pooling_whole,
)
from tests.helpers import assert_identical, both_paths

_WIDE = Context(prec=90)


def _exact_power(beta: float, g: int) -> Fraction:
    """``beta ** g``: exact for ``g <= 4096`` (ties included), else to 90 digits by Decimal's
    correctly rounded ``exp`` and ``ln`` (not the products the kernel uses)."""
    if beta == 0.0 or g <= 4096:
        return Fraction(beta) ** g
    log = _WIDE.ln(Decimal(beta))
    return Fraction(_WIDE.exp(_WIDE.multiply(log, Decimal(g))))


def _nearest_float32(x: Fraction) -> float:
    """The float32 nearest ``x >= 0``, ties to even (checked against both neighbours)."""
    c = np.float32(float(x))
    candidates = [c, np.nextafter(c, np.float32(0)), np.nextafter(c, np.float32(np.inf))]
    return float(min(candidates, key=lambda v: (abs(Fraction(float(v)) - x),
                                                int(np.float32(v).view(np.int32)) & 1)))


def _betas() -> list[float]:
    rng = random.Random(38)
    named = [0.0, 1.0, 0.5, 0.999, 0.9, 0.1, 1.0 - 2.0**-24, 1.0 - 2.0**-23, 2.0**-30,
             float(np.exp(np.float32(-1e-6)))]
    drawn = [rng.random() for _ in range(8)] + [1.0 - rng.random() * 1e-4 for _ in range(8)]
    return [float(np.float32(b)) for b in named + drawn]  # the neurons' float32 beta


def _exponents(beta: float) -> list[int]:
    rng = random.Random(int(beta * 2**30))
    edges = [0, 1, 2, 3, 126, 149, 150, 168, 1023, 1024, 1025, 4095, 4096, 2**24 + 1,
             2**31 - 1, 2**40 - 1, 2**40, 2**62, 2**63 - 1]
    return edges + [rng.randrange(2**e) for e in (5, 10, 11, 16, 20, 27, 33, 40)
                    for _ in range(3)]


@pytest.mark.parametrize("beta", _betas())
def test_powers_are_the_exact_power_rounded_once(beta):
    gs = _exponents(beta)
    powers = Powers(beta, torch.device("cpu"))
    got32 = powers.float32(torch.tensor(gs)).tolist()
    got64 = powers.float64(torch.tensor(gs)).tolist()
    for g, p32, p64 in zip(gs, got32, got64):
        exact = _exact_power(beta, g)
        assert p32 == _nearest_float32(exact), (beta, g)
        assert p64 == float(exact), (beta, g)  # float(Fraction): correctly rounded


def test_powers_of_a_batch_are_the_powers_one_at_a_time():
    rng = torch.Generator().manual_seed(38)
    for beta in (0.999, float(np.float32(0.3)), 1.0 - 2.0**-20):
        powers = Powers(beta, torch.device("cpu"))
        small = torch.randint(0, 2000, (350,), generator=rng)
        large = torch.randint(0, 2**40, (150,), generator=rng)
        gs = torch.cat([small, large])[torch.randperm(500, generator=rng)]
        batch32, batch64 = powers.float32(gs), powers.float64(gs)
        alone32 = torch.cat([powers.float32(g[None]) for g in gs])
        alone64 = torch.cat([powers.float64(g[None]) for g in gs])
        assert_identical(batch32, alone32)
        assert_identical(batch64, alone64)
        # any shape and any slice give the same values
        assert_identical(powers.float32(gs.view(20, 25)).view(-1), batch32)
        assert_identical(powers.float32(gs[1::3]), batch32[1::3])


# The neuron of the regressions: torch's float32 pow rounds 0.999 ** 168 one unit apart in its
# vectorised loop and its scalar tail, and the threshold lies between the two membranes.
_NEURON = LIFSettings(dt=1, beta=0.999, threshold=1.3599953651428223, weight=0.3)
_GAP = 168


def _fires_after_the_gap() -> bool:
    """Whether a neuron given 3 ON events, then 2 after 168 empty steps, fires then: snntorch's
    float32 update with the exact decay rounded once."""
    f32 = np.float32
    beta, weight = f32(_NEURON.constants.beta), f32(_NEURON.weight)
    decay = f32(_nearest_float32(_exact_power(float(beta), _GAP)))
    membrane = f32(3) * weight
    return bool(beta * (membrane * decay) + f32(2) * weight > f32(_NEURON.threshold))


def _pixels(x: list[int], t: list[int]) -> Events:
    return Events.from_columns(x, [0] * len(x), t, [1] * len(x))


def test_a_cells_decay_does_not_depend_on_the_other_pixels():
    pixels = 40
    x = [r for r in range(pixels) for _ in range(5)]
    t = [0, 0, 0, _GAP + 1, _GAP + 1] * pixels
    expected = list(range(pixels)) if _fires_after_the_gap() else []
    for n in (1, pixels):
        events = _pixels(x[: 5 * n], t[: 5 * n])
        compiled, eager = both_paths(lambda events=events, n=n: lif_pooling(
            events, _NEURON, sensor_size=(pixels, 1, 2), factor=(1, 1)))
        assert_identical(compiled, eager)
        assert sorted(eager.x.tolist()) == expected[:n]


def test_a_session_equals_the_whole_stream_whatever_the_decays_layout():
    pixels = 41
    x = [0] * 5 + [r for r in range(1, 40) for _ in range(5)] + [40]
    t = [0, 0, 0, _GAP + 1, _GAP + 1] + [1000, 1000, 1000, 1000 + _GAP + 1, 1000 + _GAP + 1] * 39
    events = _pixels(x, t + [2000])
    settings = LIFPoolingSettings((pixels, 1, 2), (1, 1), _NEURON)
    expected = list(range(40)) if _fires_after_the_gap() else []

    def session() -> Events:
        first = events.select(torch.arange(5))
        out, state = lif_pooling_step(first, lif_pooling_init(settings, first), settings)
        rest, state = lif_pooling_step(events.select(torch.arange(5, len(x))), state,
                                       settings)
        tail = lif_pooling_finish(state, settings)
        return Events.cat([out, rest] + ([] if tail is None else [tail]))

    for chunked, whole in zip(both_paths(session),
                              both_paths(lambda: lif_pooling_whole(events, settings))):
        assert_identical(chunked, whole)
        assert sorted(whole.x.tolist()) == expected
