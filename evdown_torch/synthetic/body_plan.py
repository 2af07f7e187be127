"""What a synthetic gesture is made of: the 11 classes, the body's geometry, each class's motion.

Body units have the origin between the shoulders, ``x`` to the right of the image and ``y``
down (:mod:`evdown_torch.synthetic.scenes` draws a scene from them); the "right" arm is the
performer's right, on the image's left.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = [
    "BODY",
    "BODY_REACH",
    "FOREARM",
    "GESTURE_CLASSES",
    "HAND",
    "HIP",
    "LIGHTING",
    "MOTIONS",
    "RADIUS_FORE",
    "RADIUS_HAND",
    "RADIUS_UPPER",
    "RAMP_FRACTION",
    "REACH",
    "SHOULDER_X",
    "UPPER_ARM",
    "Look",
    "two_link",
]

LIGHTING = ("natural", "fluorescent", "led")
"""DVS128 Gesture's three lighting conditions."""

RAMP_FRACTION = 0.04
"""Share of the recording over which arms swing in, out, and slow into and out of pauses."""

GESTURE_CLASSES: list[str] = [
    "Hand clapping",
    "Right hand wave",
    "Left hand wave",
    "Right arm cw",
    "Right arm ccw",
    "Left arm cw",
    "Left arm ccw",
    "Arm roll",
    "Air drums",
    "Air guitar",
    "Other gestures",
]
"""Class names in DVS128 Gesture's order (``tonic.datasets.DVSGesture.classes``)."""

# Body geometry, body units.
SHOULDER_X = 0.18
UPPER_ARM = 0.22
FOREARM = 0.21
HAND = 0.06
REACH = 0.95 * (UPPER_ARM + FOREARM)  # the arm never locks straight
RADIUS_UPPER = 0.048
RADIUS_FORE = 0.040
RADIUS_HAND = 0.045
# Static capsules: (name, a, b, radius, look index into GestureScene.looks).
BODY = (
    ("torso", (0.0, 0.12), (0.0, 0.70), 0.17, 0),
    ("shoulders", (-0.15, 0.06), (0.15, 0.06), 0.075, 0),
    ("neck", (0.0, -0.07), (0.0, 0.02), 0.045, 1),
    ("head", (0.0, -0.21), (0.0, -0.15), 0.095, 1),
)
HIP = (0.0, 0.95)
"""Pivot of the body's lean, body units (below the torso)."""
BODY_REACH = 1.35
"""Largest distance from :data:`HIP` of any point of the body and of arms at rest, body units
(the head's top is 1.26 away); bounds the travel a lean causes."""
# Per class: base frequency (Hz), which arms move (right, left), elbow bend of each arm
# (+1: the elbow turns outward when the wrist is raised; -1: outward when it is lowered).
MOTIONS = (
    (1.8, (True, True), (-1, -1)),  # hand clapping
    (2.0, (True, False), (1, -1)),  # right hand wave
    (2.0, (False, True), (-1, 1)),  # left hand wave
    (0.8, (True, False), (-1, -1)),  # right arm cw
    (0.8, (True, False), (-1, -1)),  # right arm ccw
    (0.8, (False, True), (-1, -1)),  # left arm cw
    (0.8, (False, True), (-1, -1)),  # left arm ccw
    (1.4, (True, True), (-1, -1)),  # arm roll
    (2.2, (True, True), (-1, -1)),  # air drums
    (2.6, (True, True), (-1, 1)),  # air guitar
    (0.6, (True, True), (-1, -1)),  # other gestures
)



@dataclass(frozen=True)
class Look:
    """Appearance of one body part.

    The linear intensity at a point of the part is
    ``gain * mean_background * (1 + side * v) * (1 - rim * v**2)
    * (1 + stripe * sin(2 pi u / period + phase))``, where ``v`` in ``[-1, 1]`` runs across
    the part and ``u`` (body units) along it, so the texture moves with the part.

    Attributes:
        gain: mean intensity relative to the background's (dimensionless, > 0).
        side: side lighting across the part (dimensionless, ``abs(side) < 1``).
        rim: darkening toward the outline (dimensionless, in [0, 1)).
        stripe: contrast of stripes (folds) along the part (dimensionless, in [0, 1)).
        period: stripe period, body units.
        phase: stripe phase, radians.
    """

    gain: float
    side: float
    rim: float
    stripe: float
    period: float
    phase: float


def two_link(shoulder: Tensor, target: Tensor, bend: float) -> tuple[Tensor, Tensor]:
    """Elbow and (reachable) wrist for wrist targets, by two-link inverse kinematics.

    ``bend`` (+1 or -1) picks the elbow side: the elbow lies at the shoulder-to-wrist angle
    plus ``bend`` times the shoulder's inner angle (angles grow clockwise in the image).
    """
    delta = target - shoulder
    dist = delta.norm(dim=1).clamp(abs(UPPER_ARM - FOREARM) + 0.05, REACH)
    base = torch.atan2(delta[:, 1], delta[:, 0])
    cos_inner = (UPPER_ARM**2 + dist**2 - FOREARM**2) / (2 * UPPER_ARM * dist)
    inner = torch.acos(cos_inner.clamp(-1.0, 1.0))
    angle = base + bend * inner
    elbow = shoulder + UPPER_ARM * torch.stack([torch.cos(angle), torch.sin(angle)], dim=1)
    wrist = shoulder + dist[:, None] * torch.stack([torch.cos(base), torch.sin(base)], dim=1)
    return elbow, wrist
