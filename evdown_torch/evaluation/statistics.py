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

import torch
from torch import Tensor

__all__ = [
    "detectable_difference", "dunnett_seeds", "hierarchical_means", "holm", "interval_of",
    "one_sided_p", "tost",
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
    cells: Sequence[Tensor], *, resamples: int = 50_000, seed: int = 0, chunk: int = 2_000
) -> Tensor:
    """Bootstrap means of several cells tested on the same recordings, seeds as the unit.

    Each resample draws, for every cell independently, as many of its training seeds as it
    has (with replacement: the outer level, the unit of replication), and one draw of the
    ``N`` test recordings shared by all cells (the inner level: the cells were tested on the
    same recordings, so the draw keeps that pairing). A cell's resampled accuracy is the mean
    of its correctness over the drawn seeds and recordings.

    Args:
        cells: ``[S_i, N]`` correctness of each cell (bool or 0/1); ``S_i`` may differ, ``N``
            may not.
        resamples: number of resamples.
        seed: seed of the draws.
        chunk: resamples computed at once (memory ``~ chunk * N * 8`` bytes per cell).

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
    resamples = int(resamples)
    if resamples < 1:
        raise ValueError(f"resamples must be a positive integer, got {resamples!r}")
    g = _generator(seed)
    out = torch.empty(resamples, len(matrices), dtype=torch.float64)
    for lo in range(0, resamples, chunk):
        r = min(chunk, resamples - lo)
        recordings = _resample_counts(n, r, g)  # [r, N]
        for j, m in enumerate(matrices):
            seeds = _resample_counts(m.shape[0], r, g)  # [r, S]
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
