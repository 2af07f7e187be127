"""Statistics of the study: seeds as the unit, one-sided tests, equivalence, Holm, power.

Every resampling takes an explicit seed; nothing reads global random state. Correctness is a
``[S, N]`` boolean matrix: seed ``s`` of a cell classified test recording ``n`` correctly.
Training seeds are the unit of replication (each seed draws its own training recordings,
initial weights, batch order and, for the control, thinning); the test recordings are shared
by every cell, so they are resampled jointly (:func:`hierarchical_means`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from statistics import NormalDist
from typing import NamedTuple

import torch
from torch import Tensor

__all__ = [
    "CorrectedT", "corrected_resampled_t", "detectable_difference", "dunnett_seeds",
    "hierarchical_means", "holm", "interval_of", "one_sided_p", "student_t_cdf",
    "student_t_quantile", "tost",
]


def _generator(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(int(seed))


def _check_matrix(name: str, correct: Tensor) -> Tensor:
    if not isinstance(correct, Tensor) or correct.ndim != 2 or correct.numel() == 0:
        raise ValueError(f"{name} must be a non-empty [seeds, recordings] tensor, got "
                         f"{getattr(correct, 'shape', correct)!r}")
    return correct.to(torch.float64)


def holm(p_values: Sequence[float]) -> list[float]:
    """Holm's step-down adjusted p-values, in the input order.

    Sorted ascending, the ``i``-th smallest (from 0) becomes ``(m - i) * p``, made
    non-decreasing along the order and capped at 1. Rejecting where the adjusted value is
    below ``alpha`` controls the family-wise error rate at ``alpha``.

    Example:
        >>> holm([0.01, 0.04, 0.03, 0.005])
        [0.03, 0.06, 0.06, 0.02]
    """
    m = len(p_values)
    for p in p_values:
        if not 0 <= p <= 1:
            raise ValueError(f"p-values must lie in [0, 1], got {p!r}")
    order = sorted(range(m), key=lambda i: p_values[i])
    adjusted = [0.0] * m
    running = 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p_values[i]))
        adjusted[i] = running
    return adjusted


# ----------------------------------------------------------------------------- seeds as the unit


def _resample_counts(size: int, resamples: int, generator: torch.Generator) -> Tensor:
    """``[resamples, size]`` multiplicities of ``size`` items drawn with replacement."""
    draws = torch.randint(0, size, (resamples, size), generator=generator)
    counts = torch.zeros(resamples, size, dtype=torch.float64)
    return counts.scatter_add_(1, draws, torch.ones_like(draws, dtype=torch.float64))


def hierarchical_means(
    cells: Sequence[Tensor], *, resamples: int = 50_000, seed: int = 0, chunk: int = 2_000,
    paired: bool = False,
) -> Tensor:
    """Bootstrap means of several cells tested on the same recordings, seeds as the unit.

    Each resample draws, for every cell independently, as many of its training seeds as it
    has (with replacement: the outer level, the unit of replication), and one draw of the
    ``N`` test recordings shared by all cells (the inner level: the cells were tested on the
    same recordings, so the draw keeps that pairing). A cell's resampled accuracy is the mean
    of its correctness over the drawn seeds and recordings. With ``paired`` the cells trained
    on the same seeds (row ``s`` of every cell is seed ``s``): one draw of seeds is shared
    by all cells, as the draw of recordings is, so a seed's effect on every cell (its training
    draw, initial weights, batch order) stays paired.

    Args:
        cells: ``[S_i, N]`` correctness of each cell (bool or 0/1); ``S_i`` may differ
            (not with ``paired``), ``N`` may not.
        resamples: number of resamples.
        seed: seed of the draws.
        chunk: resamples computed at once (memory ``~ chunk * N * 8`` bytes per cell).
        paired: resample the seeds jointly (every cell's row ``s`` is the same seed).

    Returns:
        ``[resamples, len(cells)]`` float64 resampled accuracies.

    Example:
        >>> import torch
        >>> a = torch.tensor([[1, 1, 0, 1], [1, 0, 0, 1]], dtype=torch.bool)
        >>> means = hierarchical_means([a, a], resamples=1000)
        >>> means.shape, bool((means[:, 0] == means[:, 1]).all())  # same draws of recordings
        (torch.Size([1000, 2]), False)
    """
    matrices = [_check_matrix(f"cells[{i}]", c) for i, c in enumerate(cells)]
    if not matrices:
        raise ValueError("cells must hold at least one [seeds, recordings] tensor")
    n = matrices[0].shape[1]
    for i, m in enumerate(matrices):
        if m.shape[1] != n:
            raise ValueError(f"every cell must be tested on the same {n} recordings, "
                             f"cells[{i}] has {m.shape[1]}")
    if paired and len({m.shape[0] for m in matrices}) > 1:
        raise ValueError("paired cells must have the same seeds, got "
                         f"{[m.shape[0] for m in matrices]} seeds")
    resamples = int(resamples)
    if resamples < 1:
        raise ValueError(f"resamples must be a positive integer, got {resamples!r}")
    g = _generator(seed)
    out = torch.empty(resamples, len(matrices), dtype=torch.float64)
    for lo in range(0, resamples, chunk):
        r = min(chunk, resamples - lo)
        recordings = _resample_counts(n, r, g)  # [r, N]
        shared = _resample_counts(matrices[0].shape[0], r, g) if paired else None
        for j, m in enumerate(matrices):
            seeds = shared if shared is not None else _resample_counts(m.shape[0], r, g)
            out[lo:lo + r, j] = ((seeds @ m) * recordings).sum(1) / (m.shape[0] * n)
    return out


def interval_of(samples: Tensor, *, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided percentile interval of bootstrap ``samples`` (1-D)."""
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence!r}")
    tail = (1 - confidence) / 2
    q = torch.quantile(samples.to(torch.float64),
                       torch.tensor([tail, 1 - tail], dtype=torch.float64))
    return float(q[0]), float(q[1])


def one_sided_p(samples: Tensor, observed: float) -> float:
    """p-value of ``H1: difference > 0`` from the bootstrap ``samples`` of a difference.

    The centred bootstrap: the samples shifted to mean zero stand for the null, so
    ``p = (1 + #{d* - d >= d}) / (1 + B)``; its floor is ``1 / (1 + B)``.

    Example:
        >>> import torch
        >>> one_sided_p(torch.tensor([0.1, 0.2, 0.3]), 0.2)  # (1 + #{d* >= 0.4}) / 4
        0.25
    """
    b = samples.numel()
    exceed = int(((samples.to(torch.float64) - observed) >= observed - 1e-12).sum())
    return min(1.0, (1 + exceed) / (1 + b))


def tost(samples: Tensor, margin: float) -> float:
    """Two one-sided tests of equivalence within ``+-margin`` from bootstrap ``samples``.

    Equivalence is claimed at level ``alpha`` when both ``P*(d* <= -margin)`` and
    ``P*(d* >= margin)`` (each ``(1 + count) / (1 + B)``) are below ``alpha``, i.e. when the
    ``1 - 2 alpha`` percentile interval of the difference lies within ``(-margin, margin)``.

    Returns:
        The TOST p-value, the larger of the two.

    Example:
        >>> import torch
        >>> round(tost(torch.linspace(-0.02, 0.02, 999), 0.03), 4)  # inside: 1 / 1000
        0.001
        >>> tost(torch.linspace(0.0, 0.1, 999), 0.03) > 0.5
        True
    """
    margin = float(margin)
    if not margin > 0:
        raise ValueError(f"margin must be positive, got {margin!r}")
    b = samples.numel()
    low = (1 + int((samples <= -margin).sum())) / (1 + b)
    high = (1 + int((samples >= margin).sum())) / (1 + b)
    return min(1.0, max(low, high))


def dunnett_seeds(per_method: int, methods: int) -> int:
    """Seeds of a control shared by ``methods`` comparisons: ``ceil(sqrt(k) * n)``.

    The square-root allocation (Dunnett 1955) minimises the variance of the ``k``
    differences with the shared control for a given total number of trainings.

    Example:
        >>> dunnett_seeds(10, 3), dunnett_seeds(10, 1)
        (18, 10)
    """
    for name, value in (("per_method", per_method), ("methods", methods)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return math.ceil(math.sqrt(methods) * per_method - 1e-9)


def detectable_difference(standard_error: float, *, alpha: float, tests: int = 1,
                          power: float = 0.8) -> float:
    """Smallest true difference a one-sided test detects with probability ``power``.

    A normal approximation, at Holm's first step (``alpha / tests``, the strictest):
    ``(z(1 - alpha / tests) + z(power)) * standard_error``.

    Example:
        >>> round(detectable_difference(0.02, alpha=0.05, tests=6), 4)
        0.0647
    """
    if not standard_error >= 0:
        raise ValueError(f"standard_error must be non-negative, got {standard_error!r}")
    normal = NormalDist()
    return (normal.inv_cdf(1 - alpha / tests) + normal.inv_cdf(power)) * standard_error


def _beta_fraction(a: float, b: float, x: float) -> float:
    """The continued fraction of the incomplete beta function (modified Lentz)."""
    tiny = 1e-300
    c, d = 1.0, 1.0 - (a + b) * x / (a + 1)
    d = 1.0 / (d if abs(d) > tiny else tiny)
    h = d
    for m in range(1, 500):
        for aa in (m * (b - m) * x / ((a - 1 + 2 * m) * (a + 2 * m)),
                   -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 1 + 2 * m))):
            d = 1.0 + aa * d
            d = 1.0 / (d if abs(d) > tiny else tiny)
            c = 1.0 + aa / c
            c = c if abs(c) > tiny else tiny
            h *= d * c
        if abs(d * c - 1.0) < 1e-15:
            break
    return h


def _regularised_beta(a: float, b: float, x: float, y: float) -> float:
    """``I_x(a, b)``, with ``y = 1 - x`` given exactly (no cancellation near ``x = 1``)."""
    if x <= 0:
        return 0.0
    if y <= 0:
        return 1.0
    front = math.exp(a * math.log(x) + b * math.log(y)
                     + math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b))
    if x < (a + 1) / (a + b + 2):
        return front * _beta_fraction(a, b, x) / a
    return 1.0 - front * _beta_fraction(b, a, y) / b


def student_t_cdf(x: float, df: float) -> float:
    """``P(T <= x)`` for Student's t with ``df`` degrees of freedom.

    Example:
        >>> student_t_cdf(0.0, 3), round(student_t_cdf(1.0, 1), 6)  # Cauchy: 1/2 + atan(1)/pi
        (0.5, 0.75)
    """
    if not df > 0:
        raise ValueError(f"df must be positive, got {df!r}")
    if math.isinf(x):
        return 1.0 if x > 0 else 0.0
    tail = 0.5 * _regularised_beta(df / 2, 0.5, df / (df + x * x), x * x / (df + x * x))
    return 1.0 - tail if x > 0 else tail


def student_t_quantile(p: float, df: float) -> float:
    """The ``x`` with ``student_t_cdf(x, df) == p`` (bisection, to 1e-12).

    Example:
        >>> round(student_t_quantile(0.75, 1), 9)  # Cauchy: tan(pi / 4)
        1.0
    """
    if not 0 < p < 1:
        raise ValueError(f"p must lie in (0, 1), got {p!r}")
    low, high = -1.0, 1.0
    while student_t_cdf(low, df) > p:
        low *= 2
    while student_t_cdf(high, df) < p:
        high *= 2
    while high - low > 1e-12 * max(1.0, abs(low)):
        middle = (low + high) / 2
        low, high = (middle, high) if student_t_cdf(middle, df) < p else (low, middle)
    return (low + high) / 2


class CorrectedT(NamedTuple):
    """A mean difference over resampled train/test splits and its corrected spread.

    Attributes:
        difference: the mean of the per-split differences.
        standard_error: ``sqrt((1 / J + n_test / n_train) * s^2)``.
        df: degrees of freedom, ``J - 1``.
    """

    difference: float
    standard_error: float
    df: int


def corrected_resampled_t(differences: Tensor, *, test_over_train: float) -> CorrectedT:
    """The corrected resampled t statistic of Nadeau and Bengio (2003).

    ``J`` paired differences (one per train/test split: with repeated k-fold cross-validation,
    one per repeat and fold, each the mean over the split's seeds) come from overlapping
    training sets, so their sample variance ``s^2`` understates the variance of their mean;
    the correction inflates ``s^2 / J`` to ``(1 / J + n_test / n_train) s^2`` and the
    statistic ``difference / standard_error`` is referred to Student's t with ``J - 1``
    degrees of freedom (Bouckaert and Frank 2004 for repeated k-fold).

    Args:
        differences: ``[J]`` per-split differences (float), ``J >= 2``.
        test_over_train: ``n_test / n_train`` of a split (``1 / (k - 1)`` for k folds).

    Returns:
        The :class:`CorrectedT`.

    Example:
        >>> import torch
        >>> t = corrected_resampled_t(torch.tensor([0.02, 0.04, 0.0, 0.06]), test_over_train=0.25)
        >>> round(t.difference, 4), round(t.standard_error, 6), t.df
        (0.03, 0.018257, 3)
    """
    if not isinstance(differences, Tensor) or differences.ndim != 1 or differences.numel() < 2:
        raise ValueError("differences must be a 1-D tensor of at least 2 splits, got "
                         f"{getattr(differences, 'shape', differences)!r}")
    if not test_over_train > 0:
        raise ValueError(f"test_over_train must be positive, got {test_over_train!r}")
    d = differences.to(torch.float64)
    j = d.numel()
    variance = float(d.var(unbiased=True))
    return CorrectedT(float(d.mean()), math.sqrt((1 / j + test_over_train) * variance), j - 1)
