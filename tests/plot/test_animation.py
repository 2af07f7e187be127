"""Panels, frame windows, the GIF animation and the contact sheet."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from evdown_torch import EventCount
from evdown_torch.events import Events
from evdown_torch.plot import animate, contact_sheet, panels, save
from evdown_torch.plot.animation import (
    BACKGROUND,
    OFF_COLOUR,
    ON_COLOUR,
    frame_grid,
    window_label,
)
from tests.helpers import DVS_DTYPE, random_stream
from tests.plot.images import big_blobs

SENSOR = (8, 8, 2)


def gapped_stream() -> np.ndarray:
    """Events in [0, 20) ms and [200, 220) ms: windows of 50 ms in between are empty."""
    rng = np.random.default_rng(3)
    a = random_stream(rng, 60, SENSOR, t_max=20_000)
    b = random_stream(rng, 60, SENSOR, t_max=20_000)
    b["t"] += 200_000
    return np.concatenate([a, b])


def test_frame_grid_windows_match_a_slow_count(rng):
    events = random_stream(rng, 300, SENSOR, t_max=123_456)
    events["t"] += 1_000_000
    shown = panels(events, SENSOR, 2, ["downsample", "event_count"])
    grid = frame_grid(shown, window_ms=10)
    t0 = events["t"].min()
    assert grid.t0 == t0
    assert grid.count == (events["t"].max() - t0) // 10_000 + 1
    for i, panel in enumerate(shown):
        t = panel.events.t.numpy()
        for k in range(grid.count):
            inside = ((t >= t0 + 10_000 * k) & (t < t0 + 10_000 * (k + 1))).sum()
            start, stop = grid.counts(i, k)
            assert stop - start == inside
        assert grid.counts(i, grid.count - 1)[1] == len(t)  # every event is in a window


def test_window_image_colours_each_pixel_by_its_events():
    ev = Events.from_columns([0, 0, 1, 1, 1], [0, 0, 0, 1, 1], [0, 1, 2, 3, 4],
                             [1, 1, 0, 1, 0])
    grid = frame_grid(panels(ev, (2, 2, 2), 1, []), window_ms=1)
    image = grid.image(0, 0)
    np.testing.assert_allclose(image[0, 0], ON_COLOUR)  # two ON
    np.testing.assert_allclose(image[0, 1], OFF_COLOUR)  # one OFF
    np.testing.assert_allclose(image[1, 1], (ON_COLOUR + OFF_COLOUR) / 2)  # one of each
    np.testing.assert_allclose(image[1, 0], BACKGROUND)


def test_panels_hold_each_transform_output(rng):
    events = random_stream(rng, 200, SENSOR)
    shown = panels(events, SENSOR, 2, ["event_count", EventCount(SENSOR, 4, threshold=0.25)])
    assert [p.name for p in shown] == ["input", "event_count", "event_count"]
    assert [p.sensor_size for p in shown] == [SENSOR, (4, 4, 2), (2, 2, 2)]
    expected = EventCount(SENSOR, 4, threshold=0.25)(events)
    np.testing.assert_array_equal(shown[2].events.t.numpy(), expected["t"])
    with pytest.raises(TypeError, match="registry names or downscaling transforms"):
        panels(events, SENSOR, 2, [3])
    with pytest.raises(ValueError, match="unknown method"):
        panels(events, SENSOR, 2, ["nope"])


def test_gif_has_one_frame_per_window_and_one_area_per_panel(tmp_path):
    events = gapped_stream()
    # event_count at a threshold no region reaches: an empty output panel
    shown = panels(events, SENSOR, 2, ["downsample", EventCount(SENSOR, 2, threshold=100.0),
                                       "cubic", "lif"])
    assert shown[2].events.num_events == 0
    calls = []
    path = tmp_path / "show.gif"
    save(animate(shown, window_ms=50), str(path), progress=lambda i, n: calls.append((i, n)))
    expected_frames = (events["t"].max() - events["t"].min()) // 50_000 + 1
    assert expected_frames == 5
    with Image.open(path) as gif:
        assert gif.n_frames == expected_frames
        for k in range(gif.n_frames):
            gif.seek(k)
            assert big_blobs(np.asarray(gif.convert("RGB"))) == len(shown) == 5
    assert calls == [(k, expected_frames) for k in range(expected_frames)]


def test_an_empty_window_shows_the_background_only():
    shown = panels(gapped_stream(), SENSOR, 2, ["downsample"])
    grid = frame_grid(shown, window_ms=50)
    for i in range(len(shown)):
        assert grid.counts(i, 2)[0] == grid.counts(i, 2)[1]
        np.testing.assert_allclose(grid.image(i, 2), np.broadcast_to(BACKGROUND, (4, 4, 3))
                                   if i else np.broadcast_to(BACKGROUND, (8, 8, 3)))


def test_an_empty_recording_renders_one_blank_frame(tmp_path):
    empty = np.empty(0, dtype=DVS_DTYPE)
    shown = panels(empty, SENSOR, 2, ["linear", "lif"])
    path = tmp_path / "empty.gif"
    save(animate(shown, window_ms=10), str(path))
    with Image.open(path) as gif:
        assert gif.n_frames == 1
        assert big_blobs(np.asarray(gif.convert("RGB"))) == 3
    sheet = contact_sheet(shown, windows=4)
    assert len(sheet.axes) == 3


def test_contact_sheet_has_windows_times_panels(tmp_path, rng):
    events = random_stream(rng, 400, SENSOR, t_max=1_000_000)
    shown = panels(events, SENSOR, 4, ["downsample", "linear"])
    figure = contact_sheet(shown, window_ms=100, windows=3)
    assert len(figure.axes) == 3 * 3
    path = tmp_path / "sheet.png"
    figure.savefig(path)
    with Image.open(path) as png:
        assert big_blobs(np.asarray(png.convert("RGB"))) == 9
    # a recording shorter than the windows asked for gives fewer rows
    assert len(contact_sheet(shown, window_ms=600, windows=5).axes) == 2 * 3


def test_animation_refuses_too_many_frames_and_bad_windows(rng):
    shown = panels(random_stream(rng, 50, SENSOR, t_max=1_000_000), SENSOR, 2, [])
    with pytest.raises(ValueError, match="more than 20 frames"):
        animate(shown, window_ms=1, max_frames=20)
    with pytest.raises(ValueError, match="window_ms"):
        animate(shown, window_ms=0)
    with pytest.raises(ValueError, match="nothing to show"):
        animate([])


def test_windows_are_labelled_from_the_recording_start(rng):
    events = random_stream(rng, 300, SENSOR, t_max=2_500_000)
    events["t"] += 1_605_537_493_718_000  # AEDAT4's absolute Unix microseconds
    grid = frame_grid(panels(events, SENSOR, 2, []), window_ms=50)
    assert window_label(grid, 0) == "0.000-0.050 s" and window_label(grid, 3) == "0.150-0.200 s"
    sheet = contact_sheet(panels(events, SENSOR, 2, []), window_ms=50, windows=2)
    labels = [ax.get_ylabel() for ax in sheet.axes]
    assert labels[0] == "0.000-\n0.050 s" and "1605537493" not in "".join(labels)
    short = frame_grid(panels(events[events["t"] < events["t"][0] + 400_000], SENSOR, 2, []),
                       window_ms=20)
    assert window_label(short, 1) == "20.0-40.0 ms"  # a recording under a second: ms
