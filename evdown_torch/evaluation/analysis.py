"""The study's inference: the primary family, the sanity checks, the rest.

Seeds are the unit of replication on a fixed train/test split: every comparison resamples
each cell's training seeds (outer level) and the shared test recordings (inner level) with
:func:`~evdown_torch.evaluation.statistics.hierarchical_means`. The *primary family* (each
primary method against the thinning control at the primary factors and budget) is tested
one-sided, Holm-corrected within the family only; where both cells trained on the same
seeds the seeds are resampled as pairs. Replication is another run on other data (another
``data.seed``), not a split of one run's seeds. Every other comparison is exploratory: a
difference and its interval, an equivalence test (TOST), never a star.

Under cross-validation (``data.folds``) the unit is the train/test split, a ``(repeat, fold)``
(its seeds averaged): :func:`compare_splits` applies Nadeau and Bengio's corrected resampled
t-test (:func:`~evdown_torch.evaluation.statistics.corrected_resampled_t`) to the paired
per-split differences, with the same family, Holm correction and TOST.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from statistics import NormalDist
from typing import cast

from torch import Tensor

from evdown_torch.evaluation.statistics import (
    corrected_resampled_t,
    detectable_difference,
    hierarchical_means,
    holm,
    interval_of,
    one_sided_p,
    student_t_cdf,
    student_t_quantile,
    tost,
)

__all__ = [
    "Comparison", "compare", "compare_splits", "noninferiority", "sanity_check",
]


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
        paired: whether the seeds were resampled as pairs (both cells trained on the same
            seeds), or each cell's independently.
    """

    difference: float
    interval: tuple[float, float]
    standard_error: float
    p_value: float | None
    p_holm: float | None
    significant: bool | None
    equivalence_p: float
    detectable: float
    paired: bool = False


def _difference(a: Tensor, b: Tensor, resamples: int, seed: int, paired: bool
                ) -> tuple[float, Tensor]:
    means = hierarchical_means([a, b], resamples=resamples, seed=seed, paired=paired)
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
    paired: Sequence[bool] | None = None,
) -> list[Comparison]:
    """Compare each ``(cell, reference)`` pair of ``[S, N]`` correctness matrices.

    With ``primary`` the pairs form one family: each gets a one-sided p-value and Holm's
    correction over the family. Otherwise each gets its difference, interval and TOST only.
    A pair marked in ``paired`` trained both cells on the same seeds, row for row: its seeds
    are resampled as pairs (:func:`hierarchical_means` with ``paired``), which keeps the
    correlation a seed gives both cells (the same training draw, initial weights and batch
    order); the others resample each cell's seeds independently.

    Example:
        >>> import torch
        >>> g = torch.Generator().manual_seed(0)
        >>> better = torch.rand(10, 200, generator=g) < 0.9
        >>> worse = torch.rand(10, 200, generator=g) < 0.7
        >>> (k,) = compare([(better, worse)], primary=True, resamples=5000, seed=0,
        ...                confidence=0.95, alpha=0.05, margin=0.03, paired=[True])
        >>> round(k.difference, 2), k.significant, k.paired
        (0.17, True, True)
    """
    if paired is None:
        paired = [False] * len(pairs)
    if len(paired) != len(pairs):
        raise ValueError(f"paired must have one flag per pair ({len(pairs)}), got {len(paired)}")
    out = []
    for i, ((a, b), both) in enumerate(zip(pairs, paired)):
        observed, diffs = _difference(a, b, resamples, seed + i, both)
        se = float(diffs.std())
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
            paired=both,
        ))
    if primary and out:
        adjusted = holm([cast(float, k.p_value) for k in out])  # primary: all have one
        out = [replace(k, p_holm=q, significant=q < alpha) for k, q in zip(out, adjusted)]
    return out


def sanity_check(superset: Tensor, subset: Tensor, *, resamples: int, seed: int,
                 confidence: float, alpha: float, margin: float, paired: bool = False
                 ) -> Comparison:
    """Check (a): a superset of events must not score significantly below a random subset.

    Tests ``H1: subset > superset`` one-sided, as a family of one; the check fails where
    that is significant. ``paired`` as in :func:`compare`.
    """
    (k,) = compare([(subset, superset)], primary=True, resamples=resamples, seed=seed,
                   confidence=confidence, alpha=alpha, margin=margin, paired=[paired])
    return k


def _t_p(difference: float, standard_error: float, df: int, shift: float = 0.0) -> float:
    """One-sided ``P(T >= (difference - shift) / se)`` under ``H0: true difference = shift``."""
    if standard_error == 0:
        return 0.0 if difference > shift else 1.0
    return 1.0 - student_t_cdf((difference - shift) / standard_error, df)


def compare_splits(
    pairs: list[tuple[Tensor, Tensor]],
    *,
    primary: bool,
    test_over_train: float,
    confidence: float,
    alpha: float,
    margin: float,
) -> list[Comparison]:
    """Compare each ``(cell, reference)`` pair of ``[J]`` per-split accuracies (paired).

    As :func:`compare`, with the corrected resampled t-test in place of the bootstrap: the
    interval is ``d +- t(df, (1 + confidence) / 2) se``, the one-sided p-value
    ``P(T >= d / se)``, TOST the larger of ``P(T >= (d + margin) / se)`` and
    ``P(T <= (d - margin) / se)``, the detectable difference
    ``(t(df, 1 - alpha / m) + t(df, 0.8)) se``. Every method is tested on the same splits and
    seeds, so every comparison is paired.

    Example:
        >>> import torch
        >>> a, b = torch.tensor([0.82, 0.84, 0.80, 0.86]), torch.tensor([0.80, 0.80, 0.80, 0.80])
        >>> (k,) = compare_splits([(a, b)], primary=True, test_over_train=0.25,
        ...                       confidence=0.95, alpha=0.05, margin=0.05)
        >>> round(k.difference, 3), round(k.standard_error, 4), round(k.p_value, 4)
        (0.03, 0.0183, 0.0994)
    """
    out = []
    for a, b in pairs:
        if a.shape != b.shape:
            raise ValueError(f"paired splits must match, got {tuple(a.shape)} and "
                             f"{tuple(b.shape)}")
        t = corrected_resampled_t(a.double() - b.double(), test_over_train=test_over_train)
        d, se, df = t
        half_width = student_t_quantile((1 + confidence) / 2, df) * se
        tests = len(pairs) if primary else 1
        out.append(Comparison(
            difference=d,
            interval=(d - half_width, d + half_width),
            standard_error=se,
            p_value=_t_p(d, se, df) if primary else None,
            p_holm=None,
            significant=None,
            equivalence_p=max(_t_p(d, se, df, -margin), _t_p(-d, se, df, -margin)),
            detectable=(student_t_quantile(1 - alpha / tests, df)
                        + student_t_quantile(0.8, df)) * se,
            paired=True,
        ))
    if primary and out:
        adjusted = holm([cast(float, k.p_value) for k in out])
        out = [replace(k, p_holm=q, significant=q < alpha) for k, q in zip(out, adjusted)]
    return out


def noninferiority(comparisons: list[Comparison], *, margin: float, alpha: float,
                   splits: int | None = None) -> list[Comparison]:
    """Non-inferiority of each comparison's cell to its reference within ``margin``.

    Tests ``H0: difference <= -margin`` one-sided (Holm over the list): from the corrected
    t of a :func:`compare_splits` result (``splits``: its ``J``), else from the normal
    approximation of a bootstrap result's standard error. ``p_value``, ``p_holm`` and
    ``significant`` (non-inferior) are replaced; the rest is the comparison's.
    """
    if not margin > 0:
        raise ValueError(f"margin must be positive, got {margin!r}")
    p_values = []
    for k in comparisons:
        if splits is not None:
            p_values.append(_t_p(k.difference, k.standard_error, splits - 1, -margin))
        elif k.standard_error == 0:
            p_values.append(0.0 if k.difference > -margin else 1.0)
        else:
            p_values.append(1 - NormalDist().cdf((k.difference + margin) / k.standard_error))
    adjusted = holm(p_values) if p_values else []
    return [replace(k, p_value=p, p_holm=q, significant=q < alpha)
            for k, p, q in zip(comparisons, p_values, adjusted)]
