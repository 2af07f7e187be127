"""The corrected resampled t-test (Nadeau and Bengio 2003) of the cross-validated study."""

from __future__ import annotations

import math

import pytest
import torch

from evdown_torch.evaluation.analysis import compare_splits, noninferiority
from evdown_torch.evaluation.statistics import (
    corrected_resampled_t,
    student_t_cdf,
    student_t_quantile,
)


def _t3_cdf(t):  # closed form for 3 degrees of freedom
    u = t / math.sqrt(3)
    return 0.5 + (u / (1 + u * u) + math.atan(u)) / math.pi


@pytest.mark.parametrize("x", [-7.5, -1.2, -0.1, 0.0, 0.4, 1.6431676725, 3.0, 40.0])
def test_student_t_cdf_matches_closed_forms(x):
    assert student_t_cdf(x, 1) == pytest.approx(0.5 + math.atan(x) / math.pi, abs=1e-12)
    assert student_t_cdf(x, 2) == pytest.approx(0.5 + x / (2 * math.sqrt(2 + x * x)),
                                                abs=1e-12)
    assert student_t_cdf(x, 3) == pytest.approx(_t3_cdf(x), abs=1e-12)


@pytest.mark.parametrize("df", [1, 2, 3, 9, 49, 99.5])
@pytest.mark.parametrize("p", [0.001, 0.05, 0.2, 0.5, 0.8, 0.975, 0.9999])
def test_student_t_quantile_inverts_the_cdf_and_agrees_with_scipy(df, p):
    x = student_t_quantile(p, df)
    assert student_t_cdf(x, df) == pytest.approx(p, abs=1e-10)
    stats = pytest.importorskip("scipy.stats")
    assert x == pytest.approx(float(stats.t.ppf(p, df)), rel=1e-8, abs=1e-9)


def test_corrected_t_by_hand():
    # d = (0.02, 0.04, 0, 0.06): mean 0.03, s^2 = (1 + 1 + 9 + 9) e-4 / 3; 5 folds: 1/4
    t = corrected_resampled_t(torch.tensor([0.02, 0.04, 0.0, 0.06], dtype=torch.float64),
                              test_over_train=0.25)
    s2 = 0.002 / 3
    assert t.difference == pytest.approx(0.03)
    assert t.standard_error == pytest.approx(math.sqrt((1 / 4 + 1 / 4) * s2))
    assert t.df == 3
    # the uncorrected paired t would divide by sqrt(s^2 / J): the correction doubles the
    # variance here (1/J = n_test / n_train)
    assert t.standard_error ** 2 == pytest.approx(2 * s2 / 4)


def test_compare_splits_by_hand():
    a = torch.tensor([0.82, 0.84, 0.80, 0.86], dtype=torch.float64)
    b = torch.full((4,), 0.80, dtype=torch.float64)
    se = math.sqrt(0.5 * 0.002 / 3)
    k, worse = compare_splits([(a, b), (b, a)], primary=True, test_over_train=0.25,
                              confidence=0.95, alpha=0.05, margin=0.05)
    assert k.p_value == pytest.approx(1 - _t3_cdf(0.03 / se), abs=1e-12)
    assert worse.p_value == pytest.approx(_t3_cdf(0.03 / se), abs=1e-12)
    assert k.p_holm == pytest.approx(2 * k.p_value) and not k.significant  # Holm over 2
    q = 3.182446305284263  # t(3, 0.975)
    assert k.interval == pytest.approx((0.03 - q * se, 0.03 + q * se), abs=1e-9)
    # TOST within 0.05: the larger of P(T >= 0.08/se) and P(T <= -0.02/se)
    assert k.equivalence_p == pytest.approx(_t3_cdf(-0.02 / se), abs=1e-12)
    with pytest.raises(ValueError, match="paired splits must match"):
        compare_splits([(a, b[:3])], primary=False, test_over_train=0.25, confidence=0.95,
                       alpha=0.05, margin=0.05)
    with pytest.raises(ValueError, match="at least 2 splits"):
        corrected_resampled_t(torch.tensor([0.1]), test_over_train=0.25)


def test_noninferiority_by_hand():
    a = torch.tensor([0.82, 0.84, 0.80, 0.86], dtype=torch.float64)
    b = torch.full((4,), 0.80, dtype=torch.float64)
    se = math.sqrt(0.5 * 0.002 / 3)
    (k,) = compare_splits([(b, a)], primary=False, test_over_train=0.25, confidence=0.95,
                          alpha=0.05, margin=0.05)
    (n,) = noninferiority([k], margin=0.05, alpha=0.05, splits=4)
    # H0: difference <= -0.05, with difference = -0.03: t = 0.02 / se
    assert n.p_value == pytest.approx(1 - _t3_cdf(0.02 / se), abs=1e-12)
    assert n.significant is False and n.difference == k.difference
    (m,) = noninferiority([k], margin=0.2, alpha=0.05, splits=4)
    assert m.significant is True
