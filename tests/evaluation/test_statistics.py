"""The study's statistics on hand-computed cases."""

from __future__ import annotations

import math

import pytest
import torch

from evdown_torch.evaluation.analysis import compare, sanity_check
from evdown_torch.evaluation.statistics import (
    detectable_difference,
    dunnett_seeds,
    hierarchical_means,
    holm,
    interval_of,
    one_sided_p,
    tost,
)


def test_hierarchical_means_on_a_fixed_matrix():
    # one recording, two seeds that disagree: only the seed draw matters, and the mean of two
    # seeds drawn with replacement from {1, 0} is 1, 1/2, 0 with probabilities 1/4, 1/2, 1/4
    means = hierarchical_means([torch.tensor([[1], [0]])], resamples=40_000, seed=1)[:, 0]
    assert set(means.tolist()) == {0.0, 0.5, 1.0}
    for value, share in ((1.0, 0.25), (0.5, 0.5), (0.0, 0.25)):
        assert float((means == value).double().mean()) == pytest.approx(share, abs=0.01)
    # one seed, four recordings 1, 1, 1, 0: only the recording draw matters; the variance of
    # the mean of 4 draws is p (1 - p) / 4 = 3 / 64
    means = hierarchical_means([torch.tensor([[1, 1, 1, 0]])], resamples=40_000, seed=2)[:, 0]
    assert float(means.mean()) == pytest.approx(0.75, abs=0.005)
    assert float(means.var()) == pytest.approx(3 / 64, rel=0.05)
    # cells share the draw of recordings: a cell and its copy always agree when each has one
    # seed (no seed draw to differ)
    a = torch.tensor([[1, 0, 1, 1, 0]], dtype=torch.bool)
    both = hierarchical_means([a, a], resamples=500, seed=3)
    assert torch.equal(both[:, 0], both[:, 1])
    # same seed, same draws
    assert torch.equal(hierarchical_means([a], resamples=100, seed=4),
                       hierarchical_means([a], resamples=100, seed=4))


def test_hierarchical_means_checks():
    with pytest.raises(ValueError, match="same 3 recordings"):
        hierarchical_means([torch.ones(2, 3), torch.ones(2, 4)])
    with pytest.raises(ValueError, match="at least one"):
        hierarchical_means([])
    with pytest.raises(ValueError, match="resamples"):
        hierarchical_means([torch.ones(2, 3)], resamples=0)


def test_one_sided_p_and_interval():
    samples = torch.tensor([0.1, 0.2, 0.3, 0.4])
    # centred: d* - 0.25 >= 0.25 only for 0.5 (none here) -> (1 + 0) / 5
    assert one_sided_p(samples, 0.25) == pytest.approx(1 / 5)
    assert one_sided_p(samples, -0.1) == 1.0  # a negative difference is never significant
    low, high = interval_of(torch.linspace(0, 1, 1001), confidence=0.9)
    assert (low, high) == (pytest.approx(0.05), pytest.approx(0.95))


def test_tost_known_cases():
    inside = torch.linspace(-0.02, 0.02, 1999)
    assert tost(inside, 0.03) == pytest.approx(1 / 2000)  # nothing beyond either margin
    # 10 % of the samples at or above +0.03: p = (1 + 200) / 2000
    shifted = torch.cat([torch.zeros(1800), torch.full((199,), 0.05)])
    assert tost(shifted, 0.03) == pytest.approx(200 / 2000)
    assert tost(torch.full((99,), -0.05), 0.03) == 1.0
    with pytest.raises(ValueError, match="margin"):
        tost(inside, 0.0)


def test_dunnett_allocation():
    assert dunnett_seeds(10, 3) == 18  # ceil(17.32)
    assert dunnett_seeds(10, 4) == 20 and dunnett_seeds(10, 1) == 10
    assert dunnett_seeds(7, 2) == 10  # ceil(9.899)
    with pytest.raises(ValueError, match="per_method"):
        dunnett_seeds(0, 3)


def test_detectable_difference():
    # z(1 - 0.05) + z(0.8) = 1.6449 + 0.8416
    assert detectable_difference(0.01, alpha=0.05) == pytest.approx(0.024865, abs=1e-5)
    # Holm's first step over 6 tests: z(1 - 0.05 / 6) = 2.3940
    assert detectable_difference(0.01, alpha=0.05, tests=6) == pytest.approx(0.032356, abs=1e-5)


def test_holm_adjusted_order():
    p = [0.04, 0.001, 0.03, 0.2, 0.012]
    # ascending: 0.001*5, 0.012*4, 0.03*3, 0.04*2, 0.2*1 -> 0.005, 0.048, 0.09, 0.09 (monotone), 0.2
    expected = [0.09, 0.005, 0.09, 0.2, 0.048]
    assert holm(p) == pytest.approx(expected)
    assert [q < 0.05 for q in holm(p)] == [False, True, False, False, True]
    assert holm([]) == []
    assert holm([0.6, 0.7]) == [1.0, 1.0]
    assert all(math.isclose(a, b) for a, b in zip(holm([0.01]), [0.01]))


def _cell(rng, seeds, recordings, accuracy_of_seed):
    """Correctness of a cell whose seed ``s`` is right with probability accuracy_of_seed[s]."""
    rates = torch.tensor(accuracy_of_seed, dtype=torch.float64).unsqueeze(1)
    return torch.rand(seeds, recordings, generator=rng, dtype=torch.float64) < rates


def test_compare_primary_family():
    rng = torch.Generator().manual_seed(5)
    control = _cell(rng, 18, 264, [0.75] * 18)
    better = _cell(rng, 10, 264, [0.88] * 10)
    same = _cell(rng, 10, 264, [0.75] * 10)
    k_better, k_same = compare([(better, control), (same, control)], primary=True,
                               resamples=20_000, seed=0, confidence=0.95, alpha=0.05, margin=0.06)
    assert k_better.difference == pytest.approx(float(better.double().mean()
                                                      - control.double().mean()))
    assert k_better.significant and not k_better.paired
    assert k_better.p_holm == pytest.approx(min(1.0, 2 * k_better.p_value)) or \
        k_better.p_holm >= k_better.p_value
    assert not k_same.significant
    assert k_same.equivalence_p < 0.05  # equal rates: equivalent within the design's 0.06
    # exploratory comparisons carry no p-value
    (k,) = compare([(better, control)], primary=False, resamples=2000, seed=0, confidence=0.95,
                   alpha=0.05, margin=0.03)
    assert k.p_value is None and k.significant is None
    with pytest.raises(ValueError, match="one flag per pair"):
        compare([(better, control)], primary=False, resamples=10, seed=0, confidence=0.95,
                alpha=0.05, margin=0.03, paired=[True, False])


def test_paired_seeds_share_one_draw_and_narrow_a_correlated_difference():
    # seed s shifts both cells alike (its training draw, weights, order): strongly correlated
    rng = torch.Generator().manual_seed(8)
    per_seed = [0.55 + 0.04 * s for s in range(10)]
    a = _cell(rng, 10, 400, [p + 0.03 for p in per_seed])
    b = _cell(rng, 10, 400, per_seed)
    means = hierarchical_means([a, a], resamples=300, seed=1, paired=True)
    assert torch.equal(means[:, 0], means[:, 1])  # one draw of seeds and of recordings
    assert not torch.equal(*hierarchical_means([a, a], resamples=300, seed=1).unbind(1))
    # by hand: resampling seeds as pairs removes the seeds' shared spread from the difference
    paired = hierarchical_means([a, b], resamples=4000, seed=2, paired=True)
    apart = hierarchical_means([a, b], resamples=4000, seed=2)
    spread_paired = float((paired[:, 0] - paired[:, 1]).std())
    spread_apart = float((apart[:, 0] - apart[:, 1]).std())
    seed_sd = float(torch.tensor(per_seed).std()) / math.sqrt(10)  # each cell's seed term
    assert spread_apart == pytest.approx(math.hypot(seed_sd, seed_sd), rel=0.35)
    assert spread_paired < 0.6 * spread_apart
    with pytest.raises(ValueError, match="paired cells must have the same seeds"):
        hierarchical_means([a, b[:9]], paired=True)
    (k,) = compare([(a, b)], primary=True, resamples=4000, seed=0, confidence=0.95,
                   alpha=0.05, margin=0.03, paired=[True])
    assert k.paired and k.standard_error == pytest.approx(spread_paired, rel=0.1)


def test_sanity_check_flags_a_superset_that_scores_lower():
    rng = torch.Generator().manual_seed(6)
    superset = _cell(rng, 10, 264, [0.58] * 10)
    subset = _cell(rng, 18, 264, [0.68] * 18)
    flagged = sanity_check(superset, subset, resamples=20_000, seed=0, confidence=0.95,
                           alpha=0.05, margin=0.03)
    assert flagged.difference > 0.05 and flagged.significant
    fine = sanity_check(_cell(rng, 10, 264, [0.8] * 10), subset, resamples=20_000, seed=0,
                        confidence=0.95, alpha=0.05, margin=0.03)
    assert not fine.significant


def test_false_positive_rate_of_the_design_under_the_null():
    # Seeds differ (a per-seed spread of 0.05) and both cells have the same mean: one-sided
    # tests at 0.05 must reject about 5 % of the time, not the 14-23 % of the 3-seed design.
    rng = torch.Generator().manual_seed(7)
    spread = torch.distributions.Normal(0.8, 0.05)
    rejected = 0
    trials = 60
    for t in range(trials):
        a = _cell(rng, 10, 264, spread.sample((10,)).clamp(0, 1).tolist())
        b = _cell(rng, 18, 264, spread.sample((18,)).clamp(0, 1).tolist())
        (k,) = compare([(a, b)], primary=True, resamples=2000, seed=t, confidence=0.95,
                       alpha=0.05, margin=0.03)
        rejected += bool(k.significant)
    assert rejected <= 9  # 15 %: about 5 % expected, 3 sigma of a binomial(60, 0.05) is 5.1
