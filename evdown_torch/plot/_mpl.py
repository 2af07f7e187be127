"""The one place matplotlib is imported from, on demand, with a clear error when it is absent."""

from __future__ import annotations

from importlib import import_module
from types import ModuleType
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from matplotlib.figure import Figure

INSTALL_HINT = "pip install evdown_torch[plot]"


class MissingMatplotlib(ImportError):
    """matplotlib is needed for a plot and is not installed."""


def matplotlib() -> ModuleType:
    """Import matplotlib (without pyplot: figures here never touch global state).

    Raises:
        MissingMatplotlib: when matplotlib is not installed; the message names the extra.
    """
    try:
        mpl = import_module("matplotlib")
        for part in ("animation", "backends.backend_agg", "figure", "ticker"):
            import_module(f"matplotlib.{part}")
    except ImportError as error:
        raise MissingMatplotlib(
            f"plots need matplotlib, which is not installed ({error}): {INSTALL_HINT}"
        ) from None
    return mpl


def new_figure(width: float, height: float, dpi: float = 100.0, *, agg: bool = True) -> Figure:
    """A matplotlib ``Figure`` of ``width x height`` inches (no pyplot).

    With ``agg`` it gets an Agg canvas, so ``figure.canvas.draw()`` renders it; without, the
    base canvas, whose ``draw()`` does nothing: an animation's figure, which matplotlib would
    otherwise draw twice per frame (once to save it, once on its idle redraw).
    """
    mpl = matplotlib()
    figure = mpl.figure.Figure(figsize=(width, height), dpi=dpi)
    if agg:
        mpl.backends.backend_agg.FigureCanvasAgg(figure)
    return figure
