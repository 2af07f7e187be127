"""The body's sway: small, slow, per-recording, carried by the arms and seen at every resolution."""

from __future__ import annotations

import dataclasses
import math

import torch

from evdown_torch.synthetic import (
    GESTURE_CLASSES,
    GestureScene,
    SyntheticGestures,
    render_events,
    swept_mask,
)
from tests.synthetic import QUIET


def torso_top(scene, t_us):
    return scene.body_capsules(t_us)[0][0]  # (S, 2) pixels


def test_torso_moves_a_few_pixels_slowly_and_per_seed():
    t = torch.linspace(0, 6e6, 1201, dtype=torch.float64)
    ranges = []
    for seed in range(12):
        scene = GestureScene.sample(seed % len(GESTURE_CLASSES), seed)
        assert scene == GestureScene.sample(seed % len(GESTURE_CLASSES), seed)
        top = torso_top(scene, t)
        torch.testing.assert_close(top, torso_top(GestureScene.sample(scene.label, seed), t))
        extent = top.amax(dim=0) - top.amin(dim=0)
        ranges.append(float(extent[0]))
        assert 0.5 < float(extent.norm()) < 0.1 * scene.scale  # a few pixels (128x128)
        body_speed = float((top[1:] - top[:-1]).norm(dim=1).max()) / 0.005  # pixels per s
        assert body_speed < 10.0
        # the gesturing hand moves far faster on average than the body ever does
        arm = scene.arm_keypoints(t)[0 if scene.moving_arms[0] else 1][:, 3]
        start, end = scene.active
        during = (t[1:] > start) & (t[1:] < end)
        hand_speed = float((arm[1:] - arm[:-1]).norm(dim=1)[during].mean()) / 0.005
        assert hand_speed > 5 * body_speed, (seed, hand_speed, body_speed)
    assert max(ranges) - min(ranges) > 1.0  # it differs between recordings
    other = GestureScene.sample(0, 1)
    assert not torch.equal(torso_top(GestureScene.sample(0, 0), t), torso_top(other, t))


def test_sway_moves_the_arms_rigidly_with_the_body():
    """With the sway, every arm point is the still pose turned by the lean and shifted:
    the gesture keeps its shape and its sense of rotation."""
    scene = GestureScene.sample(4, 9)
    t = torch.linspace(0, 6e6, 301, dtype=torch.float64)
    lean, offset = scene.body_pose(t * 1e-6)
    assert float(lean.abs().max()) > 0 and float(offset.abs().max()) > 0
    for swayed, still in zip(scene.arm_keypoints(t), scene.arm_keypoints(t, sway=False),
                             strict=True):
        a, b = swayed[:, 2] - swayed[:, 0], still[:, 2] - still[:, 0]  # shoulder to wrist
        torch.testing.assert_close(a.norm(dim=1), b.norm(dim=1))
        turn = torch.atan2(b[:, 0] * a[:, 1] - b[:, 1] * a[:, 0], (a * b).sum(dim=1))
        torch.testing.assert_close(turn, lean)
        # the shoulder follows the torso: both move by the same rigid motion
        shoulder_shift = swayed[:, 0] - still[:, 0]
        torso_shift = torso_top(scene, t) - torso_top(dataclasses.replace(scene, sway=()), t)
        assert float((shoulder_shift - torso_shift).norm(dim=1).max()) < (
            0.25 * scene.scale * float(lean.abs().max()) + 1e-9)


def test_a_still_person_emits_through_the_sway_at_every_resolution():
    base = GestureScene.sample(3, 5, sensor_size=(64, 64, 2), duration_us=3_000_000)
    duration = base.duration_us
    still = dataclasses.replace(  # no gesture, no lamp: only the sway can make events
        base, active=(2.0 * duration, 3.0 * duration), pauses=(), lighting="natural",
        flicker_hz=0.0, flicker_depth=0.0)
    assert render_events(dataclasses.replace(still, sway=()), QUIET).num_events == 0
    profiles = []
    for factor in (1, 4):
        events = render_events(still, QUIET, factor=factor)
        mask = swept_mask(still, QUIET, factor=factor)
        assert events.num_events > 50, factor
        assert bool(mask[events.y, events.x].all())
        assert float(mask.float().mean()) < 0.5
        profiles.append(torch.bincount(events.t // 250_000, minlength=12).double())
        assert render_events(dataclasses.replace(still, sway=()), QUIET,
                             factor=factor).num_events == 0
    # the low-resolution sensor sees the same sway: its events come and go with the full
    # sensor's (fast sway, many events; slow sway, few)
    full, low = (p - p.mean() for p in profiles)
    correlation = float((full * low).sum() / (full.norm() * low.norm()))
    assert correlation > 0.5, profiles


def test_ground_truth_follows_the_sway():
    data = SyntheticGestures(samples_per_class=1, duration_us=1_000_000, sensor_size=(48, 48, 2))
    events, _ = data[5]
    truth = data.ground_truth(5, 1)
    for name in ("x", "y", "t", "p"):
        assert (truth[name] == events[name]).all()
    scene = data.scene(5)
    assert scene.sway and math.isfinite(sum(scene.sway))
    low = data.ground_truth(5, 3)
    mask = swept_mask(scene, data.pixel_model, factor=3)
    # signal (not noise) lies on blocks the arms or the sway change
    on_mask = mask[torch.tensor(low["y"].astype("int64")), torch.tensor(low["x"].astype("int64"))]
    assert float(on_mask.float().mean()) > 0.9
    # the body's blocks join the arms' (which move a little with it)
    still = swept_mask(dataclasses.replace(scene, sway=()), data.pixel_model, factor=3)
    assert int(mask.sum()) > int(still.sum())
