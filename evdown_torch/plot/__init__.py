"""Pictures of what each downscaler does (needs matplotlib: ``pip install evdown_torch[plot]``).

* :func:`panels`: a recording and its downscaled versions, one :class:`Panel` each;
* :func:`animate` / :func:`save`: those panels side by side as an animation, saved as a GIF;
* :func:`contact_sheet`: a figure of a few time windows of the panels;
* :func:`curve_figure`: the paper's Figure 5 for one output pixel (its region's levels, the
  reconstructions each method watches, the threshold lines and the events each method emits);
  :func:`region_curves` computes what it draws.

Importing this package does not import matplotlib: only drawing does, and without matplotlib
drawing raises :class:`MissingMatplotlib`, whose message names the extra to install. The
figures are plain ``matplotlib.figure.Figure`` objects (no pyplot state), so notebooks show
them and ``fig.savefig(path)`` writes them.
"""

from evdown_torch.plot._mpl import MissingMatplotlib
from evdown_torch.plot.animation import animate, contact_sheet, save
from evdown_torch.plot.curve import MethodEvents, RegionCurves, curve_figure, region_curves
from evdown_torch.plot.recording import Panel, ShownRecording, load_recording, panels

__all__ = [
    "MethodEvents",
    "MissingMatplotlib",
    "Panel",
    "ShownRecording",
    "RegionCurves",
    "animate",
    "contact_sheet",
    "curve_figure",
    "load_recording",
    "panels",
    "region_curves",
    "save",
]
