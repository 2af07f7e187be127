"""The study's figure, ``tradeoff.png``: accuracy against output events, and against compute.

The top row is accuracy against output events per second, per factor; the bottom row is
optical consistency with the camera where the data has one (synthetic), else accuracy
against the transform's CPU microseconds per recording: with each method's algorithmic delay
in the legend, the figure shows the whole trade (accuracy, events, compute, delay), each
accuracy with its interval and each row with its Pareto front.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from evdown_torch.evaluation.cells import BASELINE, CONTROL
from evdown_torch.evaluation.results import EvaluationResult

__all__ = ["pareto_front", "plot_tradeoff"]


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the Pareto points ``(events, accuracy)``, in order of events.

    A point is kept when no other beats it with fewer or as many events and higher accuracy.

    Example:
        >>> pareto_front([(10, 0.5), (20, 0.4), (30, 0.9), (5, 0.2)])
        [3, 0, 2]
    """
    order = sorted(range(len(points)), key=lambda i: (points[i][0], -points[i][1]))
    front, best = [], -math.inf
    for i in order:
        if points[i][1] > best:
            front.append(i)
            best = points[i][1]
    return front


def _front(ax: Any, points: list[tuple[float, float]]) -> None:
    """Shade the Pareto front of ``(x, accuracy)`` points on ``ax`` (fewer x, more accuracy)."""
    front = pareto_front(points)
    ax.plot([points[i][0] for i in front], [points[i][1] for i in front],
            color="gold", linewidth=6, alpha=0.35, zorder=0, drawstyle="steps-post")


def plot_tradeoff(result: EvaluationResult, path: Path) -> bool:
    """Draw ``tradeoff.png``: accuracy against events (and consistency, or CPU time) per factor.

    Returns:
        False, drawing nothing, where matplotlib is absent.
    """
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from matplotlib.ticker import NullFormatter
    except ModuleNotFoundError:
        return False
    factors = list(dict.fromkeys(c.factor for c in result.cells if c.method != BASELINE))
    figure = Figure(figsize=(4.2 * len(factors) + 2.5, 7.5), layout="constrained")
    FigureCanvasAgg(figure)
    axes = figure.subplots(2, len(factors), squeeze=False, sharey="row")
    methods = list(dict.fromkeys(c.cell.name for c in result.cells  # a matched control too
                                 if c.cell.name not in (BASELINE, CONTROL)))
    colours = {name: f"C{i % 10}" for i, name in enumerate(methods)}
    colours[CONTROL] = "black"
    baseline = next((c for c in result.cells if c.method == BASELINE), None)
    consistency = any(c.consistency is not None for c in result.cells)
    for column, factor in enumerate(factors):
        here = [c for c in result.cells if c.factor == factor]
        top, bottom = axes[0][column], axes[1][column]
        for name in [*methods, CONTROL]:
            line = sorted((c for c in here if c.cell.name == name),
                          key=lambda c: c.events_per_second)
            if not line:
                continue
            style = dict(color=colours[name], marker="o" if name != CONTROL else "s",
                         linestyle="--" if name == CONTROL else "-", markersize=5, capsize=2)
            x = [c.events_per_second for c in line]
            top.errorbar(x, [c.accuracy for c in line],
                         yerr=[[c.accuracy - c.interval[0] for c in line],
                               [c.interval[1] - c.accuracy for c in line]], **style)
            if consistency and all(c.consistency is not None for c in line):
                bottom.plot(x, [c.consistency for c in line], **{k: v for k, v in style.items()
                                                                   if k != "capsize"})
            timed = [c for c in line if c.cpu_us_per_recording]
            if not consistency and timed:
                bottom.errorbar([c.cpu_us_per_recording for c in timed],
                                [c.accuracy for c in timed],
                                yerr=[[c.accuracy - c.interval[0] for c in timed],
                                      [c.interval[1] - c.accuracy for c in timed]],
                                **{**style, "linestyle": "none"})
        _front(top, [(c.events_per_second, c.accuracy) for c in here])
        if not consistency:
            _front(bottom, [(c.cpu_us_per_recording, c.accuracy) for c in here
                            if c.cpu_us_per_recording])
        if baseline is not None:
            top.axhline(baseline.accuracy, color="grey", linestyle=":", linewidth=1)
        top.set_title(f"factor {factor[0] if factor[0] == factor[1] else factor}")
        for ax in (top, bottom):
            ax.set_xscale("log")
            ax.xaxis.set_minor_formatter(NullFormatter())
            ax.grid(True, which="both", alpha=0.3)
        top.set_xlabel("output events per second")
        bottom.set_xlabel("output events per second" if consistency
                          else "CPU microseconds per recording (one thread)")
    axes[0][0].set_ylabel("test accuracy (95% CI)")
    axes[1][0].set_ylabel("optical consistency with the camera" if consistency
                          else "test accuracy (95% CI)")
    delays = {c.cell.name: c.delay for c in result.cells}
    handles = [axes[0][0].plot([], [], color=colours[n], marker="o",
                               label=f"{n} (delay {delays[n]})")[0] for n in methods]
    handles.append(axes[0][0].plot([], [], color="black", marker="s", linestyle="--",
                                   label="control (thinned Downsample)")[0])
    handles.append(axes[0][0].plot([], [], color="gold", linewidth=6, alpha=0.35,
                                   label="Pareto front")[0])
    if baseline is not None:
        handles.append(axes[0][0].plot([], [], color="grey", linestyle=":",
                                       label=f"{BASELINE} ({baseline.accuracy:.3f})")[0])
    figure.legend(handles=handles, loc="outside right center", frameon=False)
    figure.suptitle(f"evdown evaluate: {result.config.name} ({result.description})",
                    fontsize=10)
    figure.savefig(path, dpi=110)
    return True
