"""Side-by-side views of a recording and its downscaled versions: a GIF animation and a sheet.

Time is cut into windows of ``window_ms`` milliseconds from the first event of any panel,
``[t0 + k w, t0 + (k + 1) w)``, labelled from the recording's start ``t0`` (in seconds, or in
milliseconds for recordings under a second: absolute timestamps, such as AEDAT4's Unix
microseconds, say nothing to a reader); a panel's image in window ``k`` colours every pixel that has
events there, ON in orange and OFF in blue (mixed by their counts where both occur), on a dark
background. Panels are drawn at one size whatever their resolution, with nearest-neighbour
upscaling, so an 8x8 output shows as 8x8 blocks rather than a blur.
"""

from __future__ import annotations

import io
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from evdown_torch.checks import check_positive_float, check_positive_int
from evdown_torch.plot import _mpl
from evdown_torch.plot.recording import Panel, to_numpy
from evdown_torch.time_units import display_unit

if TYPE_CHECKING:
    from matplotlib.animation import AbstractMovieWriter, FuncAnimation
    from matplotlib.artist import Artist
    from matplotlib.figure import Figure

__all__ = ["FrameGrid", "animate", "contact_sheet", "frame_grid", "save", "window_image",
           "window_label"]

ON_COLOUR = np.array([1.0, 0.55, 0.1])
OFF_COLOUR = np.array([0.3, 0.65, 1.0])
BACKGROUND = np.array([0.13, 0.13, 0.13])

#: Most frames :func:`animate` renders (each frame is held in memory until the GIF is written).
MAX_FRAMES = 600

#: Panels per row.
COLUMNS = 4


class FrameGrid:
    """The windows of a set of panels and each panel's events in each window.

    Attributes:
        t0: start of the first window (the first event of any panel), microseconds.
        window_us: window length, microseconds.
        count: number of windows (at least 1).
        bounds: per panel, ``(count + 1,)`` int64 index of each window's first event.
    """

    def __init__(self, panels: Sequence[Panel], window_ms: float) -> None:
        window_us = 1000.0 * check_positive_float("window_ms", window_ms)
        times = [to_numpy(p.events)[2] for p in panels]
        nonempty = [t for t in times if t.shape[0]]
        t0 = min(float(t[0]) for t in nonempty) if nonempty else 0.0
        t_last = max(float(t[-1]) for t in nonempty) if nonempty else 0.0
        self.t0, self.window_us = t0, window_us
        self.count = int((t_last - t0) // window_us) + 1
        edges = t0 + window_us * np.arange(self.count + 1, dtype=np.float64)
        self.bounds = [np.searchsorted(t, edges, side="left") for t in times]
        self._columns = [(p.events.x.cpu().numpy(), p.events.y.cpu().numpy(),
                          p.events.p.cpu().numpy(), p.sensor_size) for p in panels]
        self.seconds = (t_last - t0) / 1e6

    def counts(self, i: int, k: int) -> tuple[int, int]:
        """First and one-past-last event of panel ``i`` in window ``k``."""
        return int(self.bounds[i][k]), int(self.bounds[i][k + 1])

    def image(self, i: int, k: int) -> np.ndarray:
        """``(H, W, 3)`` image of panel ``i`` in window ``k`` (see :func:`window_image`)."""
        start, stop = self.counts(i, k)
        x, y, on, size = self._columns[i]
        return window_image(x[start:stop], y[start:stop], on[start:stop], size)

    def window(self, k: int) -> tuple[float, float]:
        """Start and end of window ``k``, microseconds."""
        return self.t0 + k * self.window_us, self.t0 + (k + 1) * self.window_us


def frame_grid(panels: Sequence[Panel], window_ms: float) -> FrameGrid:
    """The :class:`FrameGrid` of ``panels`` with windows of ``window_ms`` milliseconds."""
    return FrameGrid(panels, window_ms)


def window_image(
    x: np.ndarray, y: np.ndarray, on: np.ndarray, sensor_size: tuple[int, int, int]
) -> np.ndarray:
    """``(H, W, 3)`` float RGB image of some events (``x``, ``y`` int, ``on`` bool arrays).

    A pixel with ``on`` ON and ``off`` OFF events takes ``(on * ON + off * OFF) / (on + off)``;
    a pixel without events the background.

    Example:
        >>> image = window_image(np.array([0, 0]), np.array([1, 1]), np.array([True, False]),
        ...                      (2, 2, 2))
        >>> image.shape, bool((image[1, 0] == (ON_COLOUR + OFF_COLOUR) / 2).all())
        ((2, 2, 3), True)
    """
    w, h, _ = sensor_size
    pixel = y * w + x
    n_on = np.bincount(pixel[on], minlength=w * h).reshape(h, w, 1)
    n_off = np.bincount(pixel[~on], minlength=w * h).reshape(h, w, 1)
    total = n_on + n_off
    mixed = (n_on * ON_COLOUR + n_off * OFF_COLOUR) / np.maximum(total, 1)
    return np.where(total > 0, mixed, BACKGROUND)


def _rate(count: int, seconds: float) -> str:
    if seconds <= 0:
        return "- ev/s"
    rate = count / seconds
    for unit, scale in (("M", 1e6), ("k", 1e3)):
        if rate >= scale:
            return f"{rate / scale:.1f} {unit}ev/s"
    return f"{rate:.1f} ev/s"


def panel_title(panel: Panel, seconds: float) -> str:
    """``name WxH`` over ``N ev, rate`` (the whole stream's count and mean rate)."""
    w, h, _ = panel.sensor_size
    n = panel.events.num_events
    return f"{panel.name} {w}x{h}\n{n:,} ev, {_rate(n, seconds)}"


def window_label(grid: FrameGrid, k: int, separator: str = "-") -> str:
    """Window ``k``'s start and end from the recording's start, e.g. ``"0.050-0.100 s"``.

    In s for recordings of a second or more, else in ms
    (:func:`~evdown_torch.time_units.display_unit`).
    """
    unit, scale = display_unit(grid.seconds * 1e6)
    start, end = ((v - grid.t0) / scale for v in grid.window(k))
    digits = 3 if unit == "s" else 1
    return f"{start:.{digits}f}{separator}{end:.{digits}f} {unit}"


def _time_label(grid: FrameGrid, k: int) -> str:
    return f"t = {window_label(grid, k)}"


def animate(
    panels: Sequence[Panel],
    *,
    window_ms: float = 50.0,
    panel_inches: float = 2.4,
    dpi: float = 80.0,
    max_frames: int = MAX_FRAMES,
) -> FuncAnimation:
    """An animation of the panels side by side, one frame per window.

    Args:
        panels: the streams (see :func:`~evdown_torch.plot.recording.panels`).
        window_ms: frame length, milliseconds of recording (the GIF plays in real time).
        panel_inches: size of each panel.
        dpi: resolution.
        max_frames: refuse recordings longer than this many windows.

    Returns:
        A ``matplotlib.animation.FuncAnimation`` (save it with :func:`save`, or show it in a
        notebook with ``to_jshtml()``); its figure has one image axes per panel.

    Raises:
        ValueError: for no panels, a bad window or more than ``max_frames`` windows.
    """
    mpl = _mpl.matplotlib()
    if not panels:
        raise ValueError("there is nothing to show: no panels")
    grid = frame_grid(panels, window_ms)
    max_frames = check_positive_int("max_frames", max_frames)
    if grid.count > max_frames:
        raise ValueError(
            f"the recording spans {grid.count} windows of {window_ms:g} ms, more than "
            f"{max_frames} frames: choose a longer window or a shorter duration"
        )
    cols = min(len(panels), COLUMNS)
    rows = math.ceil(len(panels) / cols)
    title, clock_strip = 0.42, 0.22  # inches above each panel and above the first row
    height = rows * (panel_inches + title) + clock_strip
    fig = _mpl.new_figure(cols * panel_inches, height, dpi, agg=False)
    images, counts = [], []
    for i, panel in enumerate(panels):
        ax = fig.add_subplot(rows, cols, i + 1)
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(panel_title(panel, grid.seconds), fontsize=8)
        image = ax.imshow(grid.image(i, 0), interpolation="nearest", resample=False)
        images.append(image)
        counts.append(ax.text(0.02, 0.02, "", transform=ax.transAxes, fontsize=7,
                              color="white", va="bottom"))
    clock = fig.text(0.01, 0.995, "", fontsize=8, va="top", family="monospace")
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01,
                        top=1 - (title + clock_strip) / height, wspace=0.05,
                        hspace=title / panel_inches)

    def update(k: int) -> list[Artist]:
        for i in range(len(panels)):
            start, stop = grid.counts(i, k)
            images[i].set_data(grid.image(i, k))
            counts[i].set_text(f"{stop - start} ev")
        clock.set_text(_time_label(grid, k))
        return [*images, *counts, clock]

    update(0)
    return mpl.animation.FuncAnimation(
        fig, update, frames=grid.count, interval=max(grid.window_us / 1000, 20), blit=False,
        repeat=True,
    )


def save(animation: FuncAnimation, path: str, *,
         progress: Callable[[int, int], None] | None = None) -> None:
    """Write an animation from :func:`animate` to a GIF with Pillow.

    Args:
        animation: the ``FuncAnimation``.
        path: output file, ``.gif``; it plays at one frame per window of the animation.
        progress: called as ``progress(frame, total)`` before each frame is drawn.
    """
    _mpl.matplotlib()  # a clear error without matplotlib
    if animation.event_source is None:
        raise ValueError("the animation has been stopped; make a new one with animate()")
    interval = cast(Any, animation.event_source).interval  # a timer: it has an interval
    fps = 1000.0 / interval  # one frame per window, in real time
    animation.save(path, writer=_gif_writer()(fps=fps), progress_callback=progress)


def _gif_writer() -> type[AbstractMovieWriter]:
    """A GIF writer (matplotlib's movie-writer interface, Pillow underneath).

    It keeps each frame as a 1-byte-per-pixel palette image, a third of what matplotlib's
    PillowWriter holds until the file is written.
    """
    from matplotlib.animation import AbstractMovieWriter
    from PIL import Image

    class GifWriter(AbstractMovieWriter):
        frames: list[Image.Image]

        def setup(self, fig: Figure, outfile: str | Path, dpi: float | None = None) -> None:
            super().setup(fig, outfile, dpi=dpi)
            self.frames = []

        def grab_frame(self, **savefig_kwargs: Any) -> None:
            buffer = io.BytesIO()
            self.fig.savefig(buffer, **{**savefig_kwargs, "format": "rgba", "dpi": self.dpi})
            rgba = Image.frombuffer("RGBA", self.frame_size, buffer.getvalue(), "raw", "RGBA",
                                    0, 1)
            self.frames.append(rgba.convert("RGB").quantize(method=Image.Quantize.FASTOCTREE))

        def finish(self) -> None:
            self.frames[0].save(self.outfile, save_all=True, append_images=self.frames[1:],
                                duration=round(1000 / self.fps), loop=0)

    return GifWriter


def contact_sheet(
    panels: Sequence[Panel],
    *,
    window_ms: float = 50.0,
    windows: int = 4,
    panel_inches: float = 1.8,
    dpi: float = 100.0,
) -> Figure:
    """A sheet of a few windows.

    One row per window (evenly spread over the recording), one column per panel.

    Args:
        panels: the streams (see :func:`~evdown_torch.plot.recording.panels`).
        window_ms: window length, milliseconds.
        windows: how many windows (fewer when the recording is shorter).
        panel_inches: size of each cell.
        dpi: resolution.

    Returns:
        A matplotlib ``Figure`` with ``rows x len(panels)`` image axes.
    """
    _mpl.matplotlib()
    if not panels:
        raise ValueError("there is nothing to show: no panels")
    grid = frame_grid(panels, window_ms)
    windows = check_positive_int("windows", windows)
    chosen = np.unique(np.round(np.linspace(0, grid.count - 1, min(windows, grid.count))))
    rows, cols = len(chosen), len(panels)
    fig = _mpl.new_figure(cols * panel_inches + 0.4, rows * panel_inches + 0.5, dpi)
    for r, k in enumerate(int(k) for k in chosen):
        for i, panel in enumerate(panels):
            ax = fig.add_subplot(rows, cols, r * cols + i + 1)
            ax.set_xticks([])
            ax.set_yticks([])
            start, stop = grid.counts(i, k)
            ax.imshow(grid.image(i, k), interpolation="nearest", resample=False)
            ax.text(0.02, 0.02, f"{stop - start} ev", transform=ax.transAxes, fontsize=7,
                    color="white", va="bottom")
            if r == 0:
                ax.set_title(panel_title(panel, grid.seconds), fontsize=8)
            if i == 0:
                ax.set_ylabel(window_label(grid, k, "-\n"), fontsize=7)
    fig.subplots_adjust(left=0.4 / fig.get_figwidth() + 0.01, right=0.99, bottom=0.01,
                        top=1 - 0.45 / fig.get_figheight(), wspace=0.05, hspace=0.05)
    return fig
