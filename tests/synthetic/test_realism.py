"""The generator against DVS128 Gesture's anchors: rates, polarity, bursts, readout, flicker."""

from __future__ import annotations

import dataclasses
import statistics

import numpy as np
import pytest
import torch

from evdown_torch.synthetic import (
    GESTURE_CLASSES,
    LIGHTING,
    GestureScene,
    PixelModelConfig,
    render_events,
    swept_mask,
)
from tests.synthetic import QUIET


def funnel_share(events, factor=4):
    """Share of events equal in (x // f, y // f, t, p) to an earlier one (plain NumPy)."""
    key = np.stack([events.x.numpy() // factor, events.y.numpy() // factor, events.t.numpy(),
                    events.p.numpy().astype(np.int64)], axis=1)
    return 1 - len(np.unique(key, axis=0)) / len(key)


@pytest.fixture(scope="module")
def recordings():
    """One 6 s, 128x128 recording per class, seeds 0 to 10 (benchmarks/synthetic_stats.py's
    first seed set)."""
    torch.set_num_threads(1)
    return [(GestureScene.sample(label, label), render_events(GestureScene.sample(label, label)))
            for label in range(len(GESTURE_CLASSES))]


@pytest.mark.slow
def test_event_counts_within_dvs128_gesture_range(recordings):
    counts = [events.num_events for _, events in recordings]
    assert 190_000 <= statistics.mean(counts) <= 400_000, counts
    assert min(counts) > 50_000 and max(counts) < 800_000, counts


@pytest.mark.slow
def test_on_share_varies_by_recording(recordings):
    shares = [float(events.p.float().mean()) for _, events in recordings]
    assert all(0.4 <= s <= 0.6 for s in shares), shares
    assert max(shares) - min(shares) >= 0.08, shares  # not 0.50 everywhere


@pytest.mark.slow
def test_rate_is_bursty_in_10_ms_bins(recordings):
    ratios = []
    for scene, events in recordings:
        bins = torch.bincount(events.t // 10_000, minlength=scene.duration_us // 10_000)
        ratios.append(float(bins.max()) / float(bins.float().mean()))
        # idle start and end: the first and last 5 % hold far fewer events than the middle
        edge = scene.duration_us // 20
        quiet = int(((events.t < edge) | (events.t >= scene.duration_us - edge)).sum())
        assert quiet < 0.1 * 0.5 * events.num_events / 0.9, scene.label
    assert min(ratios) >= 3, ratios


@pytest.mark.slow
def test_funnelling_at_factor_4_removes_a_few_percent(recordings):
    shares = [funnel_share(events) for _, events in recordings]
    assert 0.02 <= statistics.mean(shares) <= 0.06, shares
    # per recording it follows how fast edges sweep: big arm circles most, small hand rolls
    # least (not the lighting: the lamp's flicker adds few duplicates)
    assert all(0.01 <= s <= 0.09 for s in shares), shares
    circles = statistics.mean(shares[3:7])
    small = statistics.mean(shares[7:10])  # arm roll, air drums, air guitar
    assert circles > 2 * small, shares


def test_readout_stamps_bursts_on_its_grid():
    scene = GestureScene.sample(3, 4, sensor_size=(48, 48, 2), duration_us=500_000)
    events = render_events(scene, PixelModelConfig(readout_us=40))
    assert bool((events.t % 40 == 0).all())
    exact = render_events(scene, PixelModelConfig(readout_us=0))
    assert not bool((exact.t % 40 == 0).all())
    assert funnel_share(events) > funnel_share(exact)


def test_lighting_is_drawn_per_recording_with_mains_flicker():
    scenes = [GestureScene.sample(i % 11, i) for i in range(60)]
    assert {s.lighting for s in scenes} == set(LIGHTING)
    for s in scenes:
        if s.lighting == "natural":
            assert s.flicker_hz == 0 and s.flicker_depth == 0
        else:
            assert s.flicker_hz in (100.0, 120.0) and 0 < s.flicker_depth < 1
    assert {s.flicker_hz for s in scenes} == {0.0, 100.0, 120.0}


@pytest.mark.parametrize(("lighting", "hz"), [("fluorescent", 100.0), ("led", 120.0)])
def test_flicker_frequency_shows_in_a_static_lit_pixel(lighting, hz):
    scene = dataclasses.replace(  # a still body: its brightest pixels stay static
        GestureScene.sample(1, 3, sensor_size=(48, 48, 2), duration_us=1_000_000),
        lighting=lighting, flicker_hz=hz, flicker_depth=0.3, sway=())
    events = render_events(scene, QUIET)
    static = ~swept_mask(scene, QUIET)[events.y, events.x]
    pixel = events.y[static] * 48 + events.x[static]
    assert pixel.numel() > 0
    busiest = int(torch.mode(pixel).values)
    mine = pixel == busiest
    times, polarity = events.t[static][mine], events.p[static][mine]
    assert times.numel() >= hz  # at least one event a cycle
    # signed train (ON +1, OFF -1) in 1 ms bins over 1 s: its spectrum at 1 Hz resolution
    train = torch.bincount(times // 1000, weights=polarity.double() * 2 - 1, minlength=1000)
    spectrum = torch.fft.rfft(train - train.mean()).abs()
    assert int(spectrum[1:].argmax()) + 1 == int(hz)
    # natural light: the same scene has no events off the moving limbs
    natural = dataclasses.replace(scene, lighting="natural", flicker_hz=0.0, flicker_depth=0.0)
    events = render_events(natural, QUIET)
    assert bool(swept_mask(natural, QUIET)[events.y, events.x].all())


def test_low_resolution_sees_the_same_lamp():
    scene = dataclasses.replace(
        GestureScene.sample(1, 3, sensor_size=(48, 48, 2), duration_us=500_000),
        lighting="fluorescent", flicker_hz=100.0, flicker_depth=0.6, sway=())
    low = render_events(scene, QUIET, factor=2)
    static = ~swept_mask(scene, QUIET, factor=2)[low.y, low.x]
    assert int(static.sum()) > 0  # the flicker of the lit blocks


def test_gesture_life_idle_pauses_and_variation():
    scene = GestureScene.sample(3, 1)
    start, end = scene.active
    assert 0.08 * 6e6 <= start <= 0.24 * 6e6 and 0.76 * 6e6 <= end <= 0.92 * 6e6
    assert 1 <= len(scene.pauses) <= 3
    t = torch.tensor([0.0, start - 1.0, (start + end) / 2], dtype=torch.float64)
    right, _ = scene.arm_keypoints(t, sway=False)
    torch.testing.assert_close(right[0], right[1])  # at rest until the gesture starts
    at, length = scene.pauses[0]
    ramp = 0.04 * 6e6
    hold = torch.linspace(at + ramp, at + length, 5, dtype=torch.float64)
    if length > ramp:  # fully stopped within the pause
        pose = scene.arm_keypoints(hold, sway=False)[0]
        assert float((pose - pose[:1]).abs().max()) < 1e-6
    speeds = {round(GestureScene.sample(3, s).speed, 3) for s in range(30)}
    assert max(speeds) / min(speeds) > 1.6  # tempo varies widely between recordings


def test_lamp_batches_and_chunks_do_not_change_the_result():
    scene = dataclasses.replace(
        GestureScene.sample(4, 6, sensor_size=(48, 40, 2), duration_us=400_000),
        lighting="led", flicker_hz=120.0, flicker_depth=0.4, sway=())
    whole = render_events(scene)
    for budget in (500, 3000, 20_000):  # several limb chunks and lamp batches
        part = render_events(scene, max_fragments=budget)
        for name in ("x", "y", "t", "p"):
            assert torch.equal(getattr(part, name), getattr(whole, name))
    static = ~swept_mask(scene)[whole.y, whole.x]
    assert int(static.sum()) > 100  # the lamp is in the picture
