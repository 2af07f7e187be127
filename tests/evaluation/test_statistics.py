"""The study's statistics on hand-computed cases."""

from __future__ import annotations

import math

import pytest
import torch

from evdown_torch.evaluation.statistics import bootstrap_interval, holm, mcnemar, paired_bootstrap


def test_mcnemar_table():
    # discordant pairs b = 2, c = 8: P[X <= 2] for Binomial(10, 1/2) = (1 + 10 + 45) / 1024
    assert mcnemar(2, 8) == pytest.approx(2 * 56 / 1024)
    assert mcnemar(8, 2) == mcnemar(2, 8)
    assert mcnemar(5, 5) == 1.0 and mcnemar(0, 0) == 1.0
    assert mcnemar(0, 6) == pytest.approx(2 / 64)
    with pytest.raises(ValueError, match="only_a"):
        mcnemar(-1, 2)


def test_bootstrap_interval_on_a_fixed_sample():
    # 320 of 400 right, one seed: the percentile interval is close to the normal one,
    # 0.8 +- 1.96 * sqrt(0.8 * 0.2 / 400) = 0.8 +- 0.0392
    correct = torch.zeros(1, 400, dtype=torch.bool)
    correct[0, :320] = True
    low, high = bootstrap_interval(correct, resamples=4000, seed=3)
    assert low == pytest.approx(0.8 - 0.0392, abs=0.008)
    assert high == pytest.approx(0.8 + 0.0392, abs=0.008)
    assert bootstrap_interval(correct, resamples=4000, seed=3) == (low, high)
    assert bootstrap_interval(torch.ones(3, 20, dtype=torch.bool)) == (1.0, 1.0)
    # seeds that disagree widen the interval
    seeds = torch.zeros(2, 400, dtype=torch.bool)
    seeds[0, :360] = True
    seeds[1, :280] = True
    wide = bootstrap_interval(seeds, resamples=4000, seed=3)
    assert wide[1] - wide[0] > high - low
    with pytest.raises(ValueError, match="confidence"):
        bootstrap_interval(correct, confidence=1.5)


def test_paired_bootstrap():
    a = torch.ones(2, 100, dtype=torch.bool)
    b = a.clone()
    b[:, :30] = False  # a wins 30 recordings, b none
    d, p = paired_bootstrap(a, b, resamples=1999)
    assert d == pytest.approx(0.3) and p == pytest.approx(1 / 2000)
    d, p = paired_bootstrap(b, a, resamples=1999)
    assert d == pytest.approx(-0.3) and p == pytest.approx(1 / 2000)
    # one recording of difference out of 100 is no evidence
    c = a.clone()
    c[:, 0] = False
    assert paired_bootstrap(a, c, resamples=1999)[1] > 0.2
    with pytest.raises(ValueError, match="same shape"):
        paired_bootstrap(a, b[:, :50])


def test_holm_adjusted_order():
    p = [0.04, 0.001, 0.03, 0.2, 0.012]
    # ascending: 0.001*5, 0.012*4, 0.03*3, 0.04*2, 0.2*1 -> 0.005, 0.048, 0.09, 0.09 (monotone), 0.2
    expected = [0.09, 0.005, 0.09, 0.2, 0.048]
    assert holm(p) == pytest.approx(expected)
    assert [q < 0.05 for q in holm(p)] == [False, True, False, False, True]
    assert holm([]) == []
    assert holm([0.6, 0.7]) == [1.0, 1.0]
    assert all(math.isclose(a, b) for a, b in zip(holm([0.01]), [0.01]))
