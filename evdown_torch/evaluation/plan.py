"""The study's plan: which cells, in which role, on which seeds; and each method's delay.

The *primary family* is stated in the config before the run (``[methods] primary``,
``primary_factors``, ``primary_budget``): each primary method against the thinning control at
the same factor and budget, ``training.primary_seeds`` seeds per method cell and more on the
shared control (``training.control_seeds``, by default Dunnett's ``ceil(sqrt(k) * n)``). The
*sanity* rows run Downsample at its own rate on the primary seeds, to test that a superset of
events does not score below its random subset (the control). Everything else is
*exploratory*: the grid of ``[methods] include x factors x budgets`` with its controls (and
each budgeted method at its own settings with ``native``), ``peers`` at each primary factor
and budget, the estimators with ``max_delay = live_delay``, Tonic's ``EventDownsampling`` with
``tonic_peer`` (at its own rate, beside a control thinned to its output count: see
:attr:`~evdown_torch.evaluation.cells.Cell.matches`), the ``[robustness]`` rows (primary methods
and their control with a stronger classifier) and the full-resolution row, on
``training.seeds``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

from evdown_torch.evaluation.cells import BASELINE, CONTROL, TONIC, TONIC_DT_MS, Cell
from evdown_torch.evaluation.config import EvaluationConfig
from evdown_torch.evaluation.statistics import dunnett_seeds
from evdown_torch.transforms.registry import METHODS

__all__ = [
    "CONTROL_ROLE", "EXPLORATORY", "PRIMARY", "SANITY", "Planned", "delay_of", "plan",
    "selection_cells",
]

#: Roles of the cells: the primary family's methods, its shared control, the sanity check's
#: Downsample, and every other (exploratory) cell.
PRIMARY, CONTROL_ROLE, SANITY, EXPLORATORY = "primary", "control", "sanity", "exploratory"
_ORDER = {PRIMARY: 0, CONTROL_ROLE: 1, SANITY: 2, EXPLORATORY: 3}
#: The estimators, whose sessions need ``max_delay``.
ESTIMATORS = tuple(name for name, cls in METHODS.items()
                   if "max_delay" in {f.name for f in fields(cls)})


@dataclass(frozen=True)
class Planned:
    """A cell of the plan: its role and the seeds it trains on."""

    cell: Cell
    role: str
    seeds: tuple[int, ...]


def pair(factor: Any) -> tuple[int, int]:
    """A config factor as ``(fx, fy)``."""
    return (factor, factor) if isinstance(factor, int) else tuple(factor)


def plan(config: EvaluationConfig) -> list[Planned]:
    """Every cell of ``config`` (budget settings still at their configured start).

    Returns:
        The full-resolution row first (if any), then per factor (primary factors first): the
        primary cells, their control, the sanity row, then the exploratory cells. A cell
        planned in two roles keeps the first role and the larger set of seeds.

    Example:
        >>> from evdown_torch.evaluation.config import parse_config
        >>> config = parse_config({"methods": {
        ...     "include": ["event_count"], "factors": [4], "budgets": [0.25, 1.0],
        ...     "primary": ["event_count", "linear"], "primary_factors": [4],
        ...     "full_resolution": False}, "training": {"primary_seeds": 4, "seeds": [0, 1]}})
        >>> [(p.cell.label, p.role, len(p.seeds))
        ...  for p in plan(config)]  # doctest: +NORMALIZE_WHITESPACE
        [('event_count x4 @ 1', 'primary', 4), ('linear x4 @ 1', 'primary', 4),
         ('control x4 @ 1', 'control', 6), ('downsample x4', 'sanity', 4),
         ('event_count x4 @ 0.25', 'exploratory', 2), ('control x4 @ 0.25', 'exploratory', 2)]
    """
    methods, training = config.methods, config.training
    primary_seeds = tuple(range(training.primary_seeds))
    control_seeds = tuple(range(training.control_seeds or (
        dunnett_seeds(training.primary_seeds, len(methods.primary)) if methods.primary else 1)))
    explore = tuple(training.seeds)
    planned: list[Planned] = []

    def settings(name: str, **extra: Any) -> tuple[tuple[str, Any], ...]:
        return tuple(sorted({**config.method_settings(name), **extra}.items()))

    def add(cell: Cell, role: str, seeds: tuple[int, ...]) -> None:
        for i, p in enumerate(planned):
            if p.cell == cell:
                merged = tuple(sorted(set(p.seeds) | set(seeds)))
                planned[i] = Planned(cell, p.role, merged)
                return
        planned.append(Planned(cell, role, seeds))

    for factor in (pair(f) for f in methods.primary_factors):
        b = methods.budget_at(factor)
        for name in methods.primary:
            add(Cell(name, factor, b, settings(name)), PRIMARY, primary_seeds)
        if methods.primary:
            add(Cell(CONTROL, factor, b), CONTROL_ROLE, control_seeds)
        if methods.primary_peer:
            peer = methods.primary_peer
            add(Cell(peer, factor, b, settings(peer)), CONTROL_ROLE, control_seeds)
        if methods.sanity:
            add(Cell("downsample", factor, None, settings("downsample")), SANITY, primary_seeds)
        for name in methods.peers:
            add(Cell(name, factor, b, settings(name)), EXPLORATORY, explore)
    for factor in (pair(f) for f in methods.factors):
        for name in methods.names:
            if METHODS[name].budget_setting is None or not methods.budgets:
                add(Cell(name, factor, None, settings(name)), EXPLORATORY, explore)
                continue
            for b in methods.budgets:
                add(Cell(name, factor, b, settings(name)), EXPLORATORY, explore)
            if methods.native:
                add(Cell(name, factor, None, settings(name)), EXPLORATORY, explore)
        if methods.tonic_peer:
            add(Cell(TONIC, factor), EXPLORATORY, explore)
            add(Cell(CONTROL, factor, matches=TONIC), EXPLORATORY, explore)
        if methods.control:
            for b in methods.budgets:
                add(Cell(CONTROL, factor, b), EXPLORATORY, explore)
        if methods.live_delay:
            for name in ESTIMATORS:
                add(Cell(name, factor, methods.budget_at(factor),
                         settings(name, max_delay=methods.live_delay)), EXPLORATORY, explore)
    robust = config.robustness
    if robust.methods:
        factor = pair(robust.factor)
        b = methods.budget_at(factor)
        for name in robust.methods:
            add(Cell(name, factor, b, settings(name), classifier=robust.classifier),
                EXPLORATORY, explore)
        add(Cell(CONTROL, factor, b, classifier=robust.classifier), EXPLORATORY, explore)
    factors = list(dict.fromkeys(pair(f) for f in methods.all_factors))
    planned.sort(key=lambda p: (factors.index(p.cell.factor), _ORDER[p.role]))
    if methods.full_resolution:
        baseline = training.baseline_seeds
        planned.insert(0, Planned(Cell(BASELINE, (1, 1)), EXPLORATORY, baseline))
    return planned


def selection_cells(config: EvaluationConfig, planned: list[Planned]
                    ) -> dict[tuple[int, int], Cell]:
    """The cell each factor's learning rate is chosen on.

    The control at the primary budget, else the factor's first control, else its first cell.

    Example:
        >>> from evdown_torch.evaluation.config import parse_config
        >>> def chosen(budgets):
        ...     config = parse_config({"methods": {"include": ["event_count"], "factors": [4],
        ...         "budgets": budgets, "primary": [], "full_resolution": False}})
        ...     return selection_cells(config, plan(config))[(4, 4)].label
        >>> chosen([0.5, 1.0]), chosen([0.5, 2.0])  # the primary budget is 1.0
        ('control x4 @ 1', 'control x4 @ 0.5')
    """
    selection = {}
    for f in dict.fromkeys(p.cell.factor for p in planned):
        cells = [p.cell for p in planned if p.cell.factor == f]
        controls = [c for c in cells if c.method == CONTROL and not c.classifier
                    and c.matches is None]
        preferred = [c for c in controls if c.budget == config.methods.budget_at(f)]
        selection[f] = (preferred or controls or cells)[0]
    return selection


def delay_of(cell: Cell) -> str:
    """A cell's algorithmic delay: how long after an input event its output can be final.

    0 for the causal methods (Downsample, EventFunnelling, EventCount, the events mode of
    PhotocurrentPooling, the control); ``D`` (LinearEstimation) and ``2 * D``
    (CubicEstimation) with ``max_delay = D``, and the whole recording without it; one time
    step ``dt`` for LIFPooling; one frame for PhotocurrentPooling's frames mode.

    Example:
        >>> delay_of(Cell("cubic", (4, 4), 1.0, (("max_delay", 10000),)))
        '20 ms'
        >>> delay_of(Cell("linear", (4, 4), 1.0)), delay_of(Cell("event_count", (4, 4), 1.0))
        ('whole recording', '0')
    """
    if cell.method == TONIC:
        return f"{TONIC_DT_MS:g} ms"
    if cell.method not in METHODS:
        return "0" if cell.method != BASELINE else "–"
    # The class's own delay, asked of an instance on one region (timestamps in microseconds).
    fx, fy = cell.factor
    delay = METHODS[cell.method]((fx, fy, 2), cell.factor, **dict(cell.settings))
    us = delay.algorithmic_delay()
    if math.isinf(us):
        return "whole recording"
    return f"{us / 1000:g} ms" if us else "0"
