"""Statistics of the study: bootstrap intervals, paired tests and Holm's correction.

Every resampling takes an explicit seed; nothing reads global random state. Correctness is a
``[S, N]`` boolean matrix: seed ``s`` of a cell classified test recording ``n`` correctly.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

__all__ = ["bootstrap_interval", "holm", "mcnemar", "paired_bootstrap"]


def _generator(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(int(seed))


def _check_matrix(name: str, correct: Tensor) -> Tensor:
    if not isinstance(correct, Tensor) or correct.ndim != 2 or correct.numel() == 0:
        raise ValueError(f"{name} must be a non-empty [seeds, recordings] tensor, got "
                         f"{getattr(correct, 'shape', correct)!r}")
    return correct.to(torch.float64)


def _resampled_means(correct: Tensor, resamples: int, seed: int) -> Tensor:
    """Means over ``resamples`` draws of recordings and seeds, with replacement."""
    s, n = correct.shape
    g = _generator(seed)
    rows = torch.randint(0, s, (resamples, s), generator=g)
    cols = torch.randint(0, n, (resamples, n), generator=g)
    per_recording = correct[:, cols]  # [S, B, N]
    picked = per_recording.gather(0, rows.T.unsqueeze(-1).expand(s, resamples, n))
    return picked.mean(dim=(0, 2))


def bootstrap_interval(
    correct: Tensor, *, confidence: float = 0.95, resamples: int = 2000, seed: int = 0
) -> tuple[float, float]:
    """Percentile bootstrap interval of the mean accuracy, over test recordings and seeds.

    Each resample draws ``N`` recordings and ``S`` seeds with replacement (two-stage), and
    takes the mean of the drawn cells; the interval is the ``(1 - confidence) / 2`` and
    ``(1 + confidence) / 2`` quantiles of those means.

    Args:
        correct: ``[S, N]`` booleans (or 0/1): seed ``s`` got recording ``n`` right.
        confidence: in ``(0, 1)``.
        resamples: number of bootstrap resamples.
        seed: seed of the resampling.

    Returns:
        ``(low, high)``.

    Example:
        >>> import torch
        >>> correct = torch.tensor([[1, 1, 1, 0, 1, 0, 1, 1, 1, 1]], dtype=torch.bool)
        >>> low, high = bootstrap_interval(correct, resamples=4000)
        >>> low <= 0.8 <= high, 0.4 <= low, high <= 1.0
        (True, True, True)
    """
    values = _check_matrix("correct", correct)
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must lie in (0, 1), got {confidence!r}")
    means = _resampled_means(values, resamples, seed)
    tail = (1 - confidence) / 2
    q = torch.quantile(means, torch.tensor([tail, 1 - tail], dtype=torch.float64))
    return float(q[0]), float(q[1])


def paired_bootstrap(
    a: Tensor, b: Tensor, *, resamples: int = 2000, seed: int = 0
) -> tuple[float, float]:
    """Mean accuracy difference ``a - b`` and its two-sided paired-bootstrap p-value.

    ``a`` and ``b`` are ``[S, N]`` correctness of two cells on the same test recordings with
    the same training seeds (row ``s`` of both used seed ``s``). Recordings and seeds are
    resampled together for both cells (the pairing is kept); the p-value is that of the
    centred bootstrap, ``(1 + #{|d* - d| >= |d|}) / (1 + resamples)``.

    Returns:
        ``(difference, p_value)``.

    Example:
        >>> import torch
        >>> a = torch.ones(3, 50, dtype=torch.bool)
        >>> d, p = paired_bootstrap(a, a.clone())
        >>> d, p
        (0.0, 1.0)
    """
    x, y = _check_matrix("a", a), _check_matrix("b", b)
    if x.shape != y.shape:
        raise ValueError(f"a and b must have the same shape, got {tuple(x.shape)} and "
                         f"{tuple(y.shape)}")
    diff = x - y
    observed = float(diff.mean())
    means = _resampled_means(diff, resamples, seed)
    extreme = int(((means - observed).abs() >= abs(observed) - 1e-12).sum())
    return observed, min(1.0, (1 + extreme) / (1 + resamples))


def mcnemar(only_a: int, only_b: int) -> float:
    """Exact two-sided McNemar test: p-value from the discordant pairs.

    Args:
        only_a: pairs cell A got right and cell B wrong.
        only_b: pairs B got right and A wrong.

    Returns:
        ``min(1, 2 * P[X <= min(only_a, only_b)])`` for ``X ~ Binomial(only_a + only_b,
        1/2)``; 1 when there is no discordant pair.

    Example:
        >>> round(mcnemar(1, 9), 6)  # 2 * (1 + 10) / 2**10
        0.021484
    """
    for name, value in (("only_a", only_a), ("only_b", only_b)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"{name} must be a non-negative integer, got {value!r}")
    n, k = only_a + only_b, min(only_a, only_b)
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2**n
    return min(1.0, 2 * tail)


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
