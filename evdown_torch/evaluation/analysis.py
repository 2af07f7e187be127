"""The study's inference: the primary family, its replication, the sanity checks, the rest.

Seeds are the unit of replication: every comparison resamples each cell's training seeds
(outer level) and the shared test recordings (inner level) with
:func:`~evdown_torch.evaluation.statistics.hierarchical_means`. The *primary family* (each
primary method against the thinning control at the primary factors and budget) is tested
one-sided, Holm-corrected within the family only; its two halves of the seeds are reported
beside the pooled verdict. Every other comparison is exploratory: a difference and its
interval, an equivalence test (TOST), never a star.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import cast

from torch import Tensor

from evdown_torch.evaluation.statistics import (
    detectable_difference,
    hierarchical_means,
    holm,
    interval_of,
    one_sided_p,
    tost,
)

__all__ = ["Comparison", "Half", "compare", "halves", "replicated", "sanity_check"]


@dataclass(frozen=True)
class Half:
    """One half of the seeds of a comparison (seeds at even or odd positions of each cell).

    Attributes:
        difference: accuracy difference on this half.
        interval: its two-sided bootstrap interval.
    """

    difference: float
    interval: tuple[float, float]


@dataclass(frozen=True)
class Comparison:
    """A cell against a reference cell.

    The reference is the thinning control at the same factor and budget, or for the sanity
    check, Downsample against its thinning.

    Attributes:
        difference: accuracy of the cell minus the reference's (same test recordings).
        interval: two-sided bootstrap interval of the difference (``confidence``).
        standard_error: standard deviation of the bootstrap differences.
        p_value: one-sided ``H1: difference > 0`` (primary and sanity checks), else ``None``.
        p_holm: Holm-adjusted within the primary family; ``None`` outside it.
        significant: ``p_holm < alpha``; ``None`` outside the primary family.
        equivalence_p: TOST p-value for ``|difference| < margin``.
        detectable: the smallest true difference this design detects with 80 % probability
            (one-sided, at Holm's strictest step for the primary family).
        halves: the two halves of the seeds (primary family only), else ``()``.
    """

    difference: float
    interval: tuple[float, float]
    standard_error: float
    p_value: float | None
    p_holm: float | None
    significant: bool | None
    equivalence_p: float
    detectable: float
    halves: tuple[Half, ...] = ()


def halves(correct: Tensor) -> tuple[Tensor, Tensor]:
    """The seeds at even and at odd positions of a ``[S, N]`` matrix (``S >= 2``)."""
    if correct.shape[0] < 2:
        raise ValueError(f"halves need at least 2 seeds, got {correct.shape[0]}")
    return correct[0::2], correct[1::2]


def _difference(a: Tensor, b: Tensor, resamples: int, seed: int) -> tuple[float, Tensor]:
    means = hierarchical_means([a, b], resamples=resamples, seed=seed)
    observed = float(a.double().mean() - b.double().mean())
    return observed, means[:, 0] - means[:, 1]


def compare(
    pairs: list[tuple[Tensor, Tensor]],
    *,
    primary: bool,
    resamples: int,
    seed: int,
    confidence: float,
    alpha: float,
    margin: float,
) -> list[Comparison]:
    """Compare each ``(cell, reference)`` pair of ``[S, N]`` correctness matrices.

    With ``primary`` the pairs form one family: each gets a one-sided p-value, Holm's
    correction over the family, and the two halves of its seeds (``resamples // 5`` each).
    Otherwise each gets its difference, interval and TOST only.

    Example:
        >>> import torch
        >>> g = torch.Generator().manual_seed(0)
        >>> better = torch.rand(10, 200, generator=g) < 0.9
        >>> worse = torch.rand(18, 200, generator=g) < 0.7
        >>> (k,) = compare([(better, worse)], primary=True, resamples=5000, seed=0,
        ...                confidence=0.95, alpha=0.05, margin=0.03)
        >>> round(k.difference, 2), k.significant, len(k.halves)
        (0.18, True, 2)
    """
    out = []
    for i, (a, b) in enumerate(pairs):
        observed, diffs = _difference(a, b, resamples, seed + i)
        se = float(diffs.std())
        parts: tuple[Half, ...] = ()
        if primary and a.shape[0] >= 2 and b.shape[0] >= 2:
            parts = tuple(
                Half(d, interval_of(s, confidence=confidence))
                for d, s in (_difference(x, y, max(resamples // 5, 1), seed + 1000 + 2 * i + j)
                             for j, (x, y) in enumerate(zip(halves(a), halves(b))))
            )
        out.append(Comparison(
            difference=observed,
            interval=interval_of(diffs, confidence=confidence),
            standard_error=se,
            p_value=one_sided_p(diffs, observed) if primary else None,
            p_holm=None,
            significant=None,
            equivalence_p=tost(diffs, margin),
            detectable=detectable_difference(se, alpha=alpha,
                                             tests=len(pairs) if primary else 1),
            halves=parts,
        ))
    if primary and out:
        adjusted = holm([cast(float, k.p_value) for k in out])  # primary: all have one
        out = [replace(k, p_holm=q, significant=q < alpha) for k, q in zip(out, adjusted)]
    return out


def replicated(comparison: Comparison) -> bool:
    """A claim the README may make.

    The pooled verdict is significant (its interval excludes zero) and the difference has the
    same sign in both halves of the seeds.
    """
    return bool(comparison.significant) and comparison.interval[0] > 0 and all(
        h.difference > 0 for h in comparison.halves) and len(comparison.halves) == 2


def sanity_check(superset: Tensor, subset: Tensor, *, resamples: int, seed: int,
                 confidence: float, alpha: float, margin: float) -> Comparison:
    """Check (a): a superset of events must not score significantly below a random subset.

    Tests ``H1: subset > superset`` one-sided, as a family of one; the check fails where
    that is significant.
    """
    (k,) = compare([(subset, superset)], primary=True, resamples=resamples, seed=seed,
                   confidence=confidence, alpha=alpha, margin=margin)
    return k
