"""Scenes and the sparse renderer: kinematics, dense oracles, chunking, event statistics."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from evdown_torch.synthetic import (
    GESTURE_CLASSES,
    GestureScene,
    PixelModelConfig,
    intensity_frame,
    pixel_events,
    render_events,
    step_times,
    swept_mask,
)
from evdown_torch.synthetic.body_plan import FOREARM, HAND, REACH, UPPER_ARM
from evdown_torch.synthetic.grid import Grid
from evdown_torch.synthetic.raster import moving_parts
from evdown_torch.synthetic.render import pixel_parameters
from tests.synthetic import QUIET


def with_sway(scene, gain):
    """The scene with its sway's amplitudes (every third entry from the first) times ``gain``."""
    sway = tuple(v * gain if k % 3 == 0 else v for k, v in enumerate(scene.sway))
    return dataclasses.replace(scene, sway=sway)


def as_list(events):
    return list(zip(events.x.tolist(), events.y.tolist(), events.t.tolist(), events.p.tolist(),
                    strict=True))


def test_scene_is_deterministic_per_seed():
    a = GestureScene.sample(4, 11, sensor_size=(60, 50, 2), duration_us=500_000)
    assert a == GestureScene.sample(4, 11, sensor_size=(60, 50, 2), duration_us=500_000)
    assert a != GestureScene.sample(4, 12, sensor_size=(60, 50, 2), duration_us=500_000)
    ev_a = render_events(a)
    assert as_list(ev_a) == as_list(render_events(a))
    other = GestureScene.sample(4, 12, sensor_size=(60, 50, 2), duration_us=500_000)
    assert as_list(ev_a) != as_list(render_events(other))


@pytest.mark.parametrize("label", range(len(GESTURE_CLASSES)))
def test_arms_keep_their_lengths_and_person_scales_with_sensor(label):
    scene = GestureScene.sample(label, label, sensor_size=(320, 200, 2), duration_us=3_000_000)
    assert 0.58 <= scene.scale / 200 <= 0.8
    assert 0 < scene.origin[0] < 320 and 0 < scene.origin[1] < 200
    t = torch.linspace(0, 3_000_000, 301, dtype=torch.float64)
    for points in scene.arm_keypoints(t):
        seg = (points[:, 1:] - points[:, :-1]).norm(dim=2) / scene.scale
        torch.testing.assert_close(seg[:, 0], torch.full_like(seg[:, 0], UPPER_ARM))
        torch.testing.assert_close(seg[:, 1], torch.full_like(seg[:, 1], FOREARM))
        torch.testing.assert_close(seg[:, 2], torch.full_like(seg[:, 2], HAND))
        reach = (points[:, 2] - points[:, 0]).norm(dim=1) / scene.scale
        assert float(reach.max()) <= REACH + 1e-9
    right, left = scene.arm_keypoints(t, sway=False)
    for arm, moving in zip((right, left), scene.moving_arms, strict=True):
        travelled = float((arm[1:, 3] - arm[:-1, 3]).norm(dim=1).sum())
        assert (travelled > 0.05 * scene.scale) if moving else travelled == 0.0
    # with the sway, an arm at rest moves only with the body: a few pixels, slowly
    for arm, still, moving in zip(scene.arm_keypoints(t), (right, left), scene.moving_arms,
                                  strict=True):
        if not moving:
            shift = (arm - still).norm(dim=2)
            assert 0 < float(shift.max()) < 0.1 * scene.scale


def test_rotation_sense_of_arm_circles():
    for label, arm, sense in ((3, 0, 1), (4, 0, -1), (5, 1, 1), (6, 1, -1)):
        scene = GestureScene.sample(label, 5)
        t = torch.linspace(*scene.active, 4001, dtype=torch.float64)  # while gesturing
        points = scene.arm_keypoints(t)[arm]
        rel = points[:, 2] - points[:, 0]
        angle = torch.atan2(rel[:, 1], rel[:, 0])
        step = torch.remainder(angle[1:] - angle[:-1] + math.pi, 2 * math.pi) - math.pi
        assert sense * float(step.sum()) > 2 * math.pi  # more than a turn, the right way


@pytest.mark.parametrize(("sensor", "factor"), [((37, 29, 2), 1), ((37, 29, 2), (3, 2)),
                                                ((37, 29, 2), 5)])
def test_sparse_intensity_matches_dense_frames(sensor, factor):
    # a sway large enough for several key steps in 0.4 s on this small sensor
    scene = with_sway(GestureScene.sample(7, 3, sensor_size=sensor, duration_us=400_000), 20)
    config = PixelModelConfig()
    times = step_times(scene, config)
    parts = moving_parts(scene, times)
    fx, fy = (factor, factor) if isinstance(factor, int) else factor
    grid = Grid(scene, (fx, fy), times, config.max_step_px)
    assert grid.keys.numel() >= 3 and grid.out.pixels.numel() > 0
    checked = 0
    # at the body's key steps the sparse samples are exact (in between its log intensity is
    # interpolated)
    for k in grid.keys.tolist():
        pixel, step, level, covered = grid.samples(parts, k, k)
        assert bool((step == k).all())
        sparse = grid.static_out.clone()
        sparse[pixel] = torch.exp(level).float()
        dense = intensity_frame(scene, float(times[k]), factor=(fx, fy)).reshape(-1)
        torch.testing.assert_close(sparse, dense, rtol=1e-5, atol=1e-6)
        checked += int(covered.sum())
    assert checked > 30


def test_block_means_of_the_static_image_handle_edge_blocks():
    scene = GestureScene.sample(1, 0, sensor_size=(10, 7, 2))
    times = step_times(scene, PixelModelConfig())
    full = Grid(scene, (1, 1), times, 1.0).static
    low = Grid(scene, (4, 3), times, 1.0).static_out.reshape(3, 3)
    torch.testing.assert_close(low[0, 0], full[0:3, 0:4].mean())
    torch.testing.assert_close(low[2, 2], full[6:7, 8:10].mean())  # a 2 x 1 edge block
    torch.testing.assert_close(low[1, 2], full[3:6, 8:10].mean())


@pytest.mark.parametrize("factor", [1, (2, 3)])
def test_render_equals_the_pixel_model_on_dense_sequences(factor):
    """Oracle: every output pixel's full log-intensity sequence through ``pixel_events``."""
    config = PixelModelConfig(background_rate_hz=0.0, hot_pixel_fraction=0.0,
                              refractory_us=300, max_step_px=0.7, readout_us=0)
    scene = dataclasses.replace(  # a sway of several key steps
        with_sway(GestureScene.sample(5, 21, sensor_size=(40, 34, 2), duration_us=300_000), 20),
        lighting="natural", flicker_hz=0.0, flicker_depth=0.0)
    fx, fy = (factor, factor) if isinstance(factor, int) else factor
    times = step_times(scene, config)
    grid = Grid(scene, (fx, fy), times, config.max_step_px)
    pixel, step, value, covered = grid.samples(moving_parts(scene, times), 0,
                                               times.numel() - 1)
    assert grid.keys.numel() > 3 and grid.out.pixels.numel() > 0  # the body sways
    n_out = grid.out_w * grid.out_h
    # every pixel at every step: covered samples, else its static or swaying level
    steps = torch.arange(times.numel())
    level = grid.out.level(torch.arange(n_out).repeat(times.numel()),
                           steps.repeat_interleave(n_out)).reshape(times.numel(), n_out)
    level[step[covered], pixel[covered]] = value[covered]
    theta_on, theta_off, offset = pixel_parameters(scene, config, (fx, fy))
    ids = torch.arange(n_out).repeat_interleave(times.numel())
    pix, t, p = pixel_events(ids, times.repeat(n_out), level.t().reshape(-1).double(),
                             threshold=theta_on, off_threshold=theta_off, offset=offset,
                             refractory_us=300)
    expected = list(zip((pix % grid.out_w).tolist(), (pix // grid.out_w).tolist(), t.tolist(),
                        p.tolist(), strict=True))
    got = render_events(scene, config, factor=factor, max_fragments=4000)  # several chunks
    assert len(expected) > 100
    assert as_list(got) == expected


def test_chunking_does_not_change_the_result():
    scene = with_sway(GestureScene.sample(10, 8, sensor_size=(48, 40, 2), duration_us=600_000),
                      10)  # chunk ends between the body's key steps
    whole = as_list(render_events(scene))
    for budget in (700, 5000, 20_000):
        assert as_list(render_events(scene, max_fragments=budget)) == whole


def test_factor_one_is_the_full_render():
    scene = GestureScene.sample(2, 4, sensor_size=(40, 40, 2), duration_us=400_000)
    full = as_list(render_events(scene))
    assert as_list(render_events(scene, factor=1)) == full
    assert as_list(render_events(scene, factor=(1, 1))) == full


@pytest.mark.parametrize("factor", [2, (4, 3), (7, 5)])
def test_low_resolution_events_lie_inside_the_smaller_sensor(factor):
    scene = GestureScene.sample(6, 4, sensor_size=(50, 41, 2), duration_us=500_000)
    fx, fy = (factor, factor) if isinstance(factor, int) else factor
    low = render_events(scene, factor=factor)
    full = render_events(scene)
    assert 0 < low.num_events < full.num_events
    assert int(low.x.max()) < -(-50 // fx) and int(low.y.max()) < -(-41 // fy)
    assert int(low.x.min()) >= 0 and int(low.y.min()) >= 0
    assert bool((low.t[1:] >= low.t[:-1]).all())


def test_signal_events_only_on_pixels_swept_bymoving_parts():
    scene = dataclasses.replace(  # no lamp: its flicker lights static pixels too
        GestureScene.sample(8, 2, sensor_size=(64, 64, 2), duration_us=800_000),
        lighting="natural", flicker_hz=0.0, flicker_depth=0.0)
    for factor in (1, 3):
        events = render_events(scene, QUIET, factor=factor)
        mask = swept_mask(scene, QUIET, factor=factor)
        assert events.num_events > 50
        assert bool(mask[events.y, events.x].all())
        assert 0.02 < float(mask.float().mean()) < 0.5


def test_event_statistics_at_128x128():
    """Rates, ON/OFF balance and the share of events on moving parts, per class."""
    for label in range(len(GESTURE_CLASSES)):
        scene = GestureScene.sample(label, 100 + label, duration_us=1_000_000)
        events = render_events(scene)
        rate = events.num_events / 1.0
        on = float(events.p.float().mean())
        share = float(swept_mask(scene)[events.y, events.x].float().mean())
        assert 12_000 < rate < 120_000, (label, rate)  # 6 s: 72k to 720k events
        assert 0.4 < on < 0.6, (label, on)
        assert 0.6 < share < 0.995, (label, share)


def test_direction_of_motion_shows_in_polarity():
    """ON leads OFF: in short windows the ON events of a circling arm lie ahead of its OFF."""
    for label, sense in ((3, 1), (4, -1), (5, 1), (6, -1)):
        scene = GestureScene.sample(label, 30 + label, sensor_size=(64, 64, 2),
                                    duration_us=2_000_000)  # idle start/end: 2 s
        events = render_events(scene, QUIET)
        shoulder = scene.arm_keypoints(torch.zeros(1))[0 if label < 5 else 1][0, 0]
        angle = torch.atan2(events.y + 0.5 - shoulder[1], events.x + 0.5 - shoulder[0])
        window = events.t // 20_000
        votes = 0.0
        for w in torch.unique(window).tolist():
            sel = window == w
            on, off = sel & events.p, sel & ~events.p
            if int(on.sum()) < 10 or int(off.sum()) < 10:
                continue
            mean_on = torch.atan2(torch.sin(angle[on]).mean(), torch.cos(angle[on]).mean())
            mean_off = torch.atan2(torch.sin(angle[off]).mean(), torch.cos(angle[off]).mean())
            lead = torch.remainder(mean_on - mean_off + math.pi, 2 * math.pi) - math.pi
            votes += float(torch.sign(lead))
        assert sense * votes > 10, (label, votes)


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match="label"):
        GestureScene.sample(11, 0)
    with pytest.raises(ValueError, match="seed"):
        GestureScene.sample(0, -1)
    with pytest.raises(ValueError, match="2 polarities"):
        GestureScene.sample(0, 0, sensor_size=(64, 64, 1))
    with pytest.raises(ValueError, match="duration_us"):
        GestureScene.sample(0, 0, duration_us=0)
    with pytest.raises(TypeError, match="sensor_size"):
        GestureScene.sample(0, 0, sensor_size=(64.0, 64, 2))
    scene = GestureScene.sample(0, 0, sensor_size=(32, 32, 2), duration_us=100_000)
    with pytest.raises(ValueError, match="factor"):
        render_events(scene, factor=0)
    with pytest.raises(ValueError, match="larger than the sensor"):
        render_events(scene, factor=(33, 1))
    with pytest.raises(TypeError, match="PixelModelConfig"):
        render_events(scene, {"threshold": 0.2})
    with pytest.raises(ValueError, match="max_fragments"):
        render_events(scene, max_fragments=0)
