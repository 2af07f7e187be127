"""Gesture scenes: a person in front of a static textured background, 11 DVS128 Gesture classes.

A scene is drawn from a seed and holds everything needed to render it: where the person stands
and how large, how fast and wide they move, what they and the background look like, and how
noisy the sensor is. The person is a set of capsules (a segment thickened by a radius): torso,
shoulders, neck and head form the body; each arm is an upper arm, a forearm and a hand, driven
by a wrist trajectory per class and two-link inverse kinematics. Arms that do not take part in
a gesture hang at rest. The whole person sways slowly (:meth:`GestureScene.body_pose`): a rigid
motion of a few pixels over seconds, far slower than the gesturing arms, which the renderer
samples at its own few key steps (:mod:`evdown_torch.synthetic.grid`), so the arms' motion
keeps its shape and sense and only the moving parts cost anything to render.

Coordinates: body units have the origin between the shoulders, ``x`` to the right of the
image and ``y`` down; the "right" arm is the performer's right, on the image's left (the camera
faces the performer). ``clockwise`` means clockwise as seen in the image. Pixel ``(i, j)``
covers ``[i, i + 1) x [j, j + 1)``; its centre is ``(i + 0.5, j + 0.5)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from evdown_torch.checks import check_non_negative_int, check_positive_int, check_sensor_size
from evdown_torch.synthetic.body_plan import (
    BODY,
    FOREARM,
    GESTURE_CLASSES,
    HAND,
    HIP,
    LIGHTING,
    MOTIONS,
    RAMP_FRACTION,
    SHOULDER_X,
    UPPER_ARM,
    Look,
    two_link,
)

__all__ = ["GestureScene", "scene_seed"]


def scene_seed(*keys: int) -> int:
    """A 63-bit seed derived from non-negative integer keys (NumPy ``SeedSequence``).

    Example:
        >>> scene_seed(0, 1, 2) == scene_seed(0, 1, 2) != scene_seed(0, 1, 3)
        True
    """
    state = np.random.SeedSequence([int(k) for k in keys]).generate_state(2, dtype=np.uint32)
    return (int(state[0]) << 31) ^ int(state[1])


@dataclass(frozen=True)
class GestureScene:
    """One recording: a person performing a gesture, fully determined by its fields.

    Build one with :meth:`sample`; render it with
    :func:`evdown_torch.synthetic.render_events`.

    Attributes:
        label: class index into :data:`GESTURE_CLASSES`.
        seed: the seed the scene was drawn from; rendering derives its own streams from it.
        sensor_size: ``(W, H, 2)``.
        duration_us: recording length, microseconds.
        origin: pixel position of the point between the shoulders (``x``, ``y``).
        scale: pixels per body unit (0.58 to 0.8 times ``min(W, H)``).
        speed: tempo factor on the class's base frequency (0.7 to 1.45).
        amplitude: factor on the motion's extent (0.7 to 1.3).
        phase: phase of the motion at ``t = 0``, radians.
        tempo: ``(depth, frequency_hz, phase)`` of a slow tempo wobble (depth up to 0.4 rad).
        direction: +1 or -1, the sense of the arm roll.
        rest: wrist offsets ``(dx_right, dy_right, dx_left, dy_left)`` of resting arms, body
            units.
        looks: :class:`Look` of shirt, skin, upper arms, forearms and hands.
        background: ``(k_x, k_y, amplitude, phase)`` of the background's log-intensity
            waves, in cycles per ``min(W, H)``, then rectangles ``(x0, y0, x1, y1, log_gain)``
            in fractions of the sensor, each as a flat tuple.
        noise_scale: factor on the background-activity rate (0.5 to 1.5).
        active: ``(start_us, end_us)`` of the gesture: before and after it the person stands
            with arms at rest (idle start and end, each 3 % to 12 % of the recording); arms
            swing in and out over ``RAMP_FRACTION`` of the recording.
        pauses: ``(start_us, length_us)`` of each pause inside the gesture (1 to 3, each 4 %
            to 10 % of the recording): the motion slows to a halt and resumes, holding its pose.
        accent: depth ``a`` of the speed change within each repetition (0.5 to 0.9): the
            motion phase advances at ``(1 + a cos(psi))**3 / (1 + 3 a**2 / 2)`` times its mean
            rate, so within a cycle the limbs accelerate to ``(1 + a)**3 / (1 + 3 a**2 / 2)``
            (2.5 to 3.1) times their mean speed and nearly stop (``(1 - a)**3 / ...``).
        lighting: ``"natural"``, ``"fluorescent"`` or ``"led"`` (DVS128 Gesture's three
            conditions, equally likely).
        flicker_hz: lamp flicker frequency, twice the mains frequency (100 or 120 Hz; 0 under
            natural light).
        flicker_depth: the lamp's modulation of linear intensity at the brightest surfaces,
            ``(max - min) / (max + min)`` (0 under natural light).
        bias: ON/OFF threshold balance of this recording's bias settings, in ``[-1, 1]``:
            ``log(theta_on / theta_off) = bias * PixelModelConfig.on_off_spread``.
        wander: for "Other gestures", per arm (right, left) a wrist centre and three waves
            ``(frequency_hz, amp_x, amp_y, phase_x, phase_y)``, body units; empty otherwise.
        sway: the body's slow sway (:meth:`body_pose`): waves ``(amplitude, frequency_hz,
            phase)`` of, in turn, the horizontal offset (two waves, amplitudes 0.01 to 0.025
            and 0.003 to 0.01 body units, 0.08 to 0.25 Hz and 0.25 to 0.45 Hz), the vertical
            offset (one, 0.002 to 0.006 body units, 0.1 to 0.35 Hz) and the lean about
            ``HIP`` (one, 0.004 to 0.012 rad, 0.08 to 0.25 Hz), flat; empty: no sway.
    """

    label: int
    seed: int
    sensor_size: tuple[int, int, int]
    duration_us: int
    origin: tuple[float, float]
    scale: float
    speed: float
    amplitude: float
    phase: float
    tempo: tuple[float, float, float]
    direction: int
    rest: tuple[float, float, float, float]
    looks: tuple[Look, Look, Look, Look, Look]
    background: tuple[tuple[float, ...], ...]
    noise_scale: float
    wander: tuple[tuple[float, ...], ...]
    active: tuple[float, float] = (0.0, math.inf)
    pauses: tuple[tuple[float, float], ...] = ()
    accent: float = 0.0
    lighting: str = "natural"
    flicker_hz: float = 0.0
    flicker_depth: float = 0.0
    bias: float = 0.0
    sway: tuple[float, ...] = ()

    @classmethod
    def sample(
        cls,
        label: int,
        seed: int,
        *,
        sensor_size: tuple[int, int, int] = (128, 128, 2),
        duration_us: int = 6_000_000,
    ) -> GestureScene:
        """Draw a scene of class ``label`` from ``seed`` (deterministic).

        Args:
            label: class index in ``[0, 11)``.
            seed: any non-negative integer.
            sensor_size: ``(W, H, 2)``; the person scales with ``min(W, H)``.
            duration_us: recording length, microseconds.

        Returns:
            The scene.

        Example:
            >>> scene = GestureScene.sample(3, seed=7, sensor_size=(64, 48, 2))
            >>> scene == GestureScene.sample(3, seed=7, sensor_size=(64, 48, 2))
            True
        """
        label = check_non_negative_int("label", label)
        if label >= len(GESTURE_CLASSES):
            raise ValueError(f"label must be a class index in [0, 11), got {label}")
        seed = check_non_negative_int("seed", seed)
        sensor_size = check_sensor_size(sensor_size)
        if sensor_size[2] != 2:
            raise ValueError(f"sensor_size must have 2 polarities, got {sensor_size!r}")
        duration_us = check_positive_int("duration_us", duration_us)
        rng = np.random.default_rng(np.random.SeedSequence([seed, 0]))
        w, h, _ = sensor_size
        u = rng.uniform
        origin = (w * (0.5 + u(-0.08, 0.08)), h * (0.36 + u(-0.05, 0.05)))
        scale = min(w, h) * u(0.58, 0.8)
        tempo = (u(0.0, 0.4), u(0.1, 0.3), u(0.0, 2 * math.pi))
        rest = tuple(float(v) for v in u(-0.02, 0.02, 4))
        shirt, skin = u(0.7, 1.4), u(0.8, 1.6)

        def look(gain_log: float) -> Look:
            return Look(math.exp(gain_log), u(-0.3, 0.3), u(0.3, 0.6), u(0.15, 0.4),
                        u(0.04, 0.1), u(0.0, 2 * math.pi))

        sleeves = u() < 0.5
        looks = (look(shirt), look(skin), look(shirt), look(shirt if sleeves else skin),
                 look(skin))
        waves = tuple(
            (u(-4, 4), u(-4, 4), u(0.05, 0.2), u(0, 2 * math.pi)) for _ in range(6)
        )
        rects = []
        for _ in range(3):
            x0, y0 = u(0, 0.8), u(0, 0.8)
            rects.append((x0, y0, x0 + u(0.1, 0.5), y0 + u(0.1, 0.5), u(-0.5, 0.5)))
        background = waves + tuple(rects)
        wander: tuple[tuple[float, ...], ...] = ()
        if label == 10:
            arms = []
            for sign in (-1.0, 1.0):
                centre = (sign * u(0.1, 0.35), u(-0.25, 0.15))
                parts: list[float] = list(centre)
                for _ in range(3):
                    parts += [u(0.2, 0.6), u(0.03, 0.1), u(0.03, 0.1),
                              u(0, 2 * math.pi), u(0, 2 * math.pi)]
                arms.append(tuple(parts))
            wander = tuple(arms)
        life = np.random.default_rng(np.random.SeedSequence([seed, 1]))  # added draws
        v = life.uniform
        start = duration_us * v(0.08, 0.24)
        end = duration_us * (1 - v(0.08, 0.24))
        pauses = []
        for _ in range(int(life.integers(1, 4))):
            length = duration_us * v(0.04, 0.1)
            at = v(start + duration_us * RAMP_FRACTION, end - length - duration_us * RAMP_FRACTION)
            pauses.append((float(at), float(length)))
        lighting = LIGHTING[int(life.integers(0, 3))]
        flicker_hz = 0.0 if lighting == "natural" else (100.0 if life.random() < 0.5 else 120.0)
        depth = {"natural": 0.0, "fluorescent": v(0.08, 0.2), "led": v(0.05, 0.25)}[lighting]
        body = np.random.default_rng(np.random.SeedSequence([seed, 2])).uniform  # the sway
        sway = []
        for low, high, f_low, f_high in ((0.01, 0.025, 0.08, 0.25), (0.003, 0.01, 0.25, 0.45),
                                         (0.002, 0.006, 0.1, 0.35), (0.004, 0.012, 0.08, 0.25)):
            sway += [body(low, high), body(f_low, f_high), body(0.0, 2 * math.pi)]
        return cls(
            label=label,
            seed=seed,
            sensor_size=sensor_size,
            duration_us=duration_us,
            origin=origin,
            scale=scale,
            speed=u(0.7, 1.45),
            amplitude=u(0.7, 1.3),
            phase=u(0.0, 2 * math.pi),
            tempo=tempo,
            direction=1 if u() < 0.5 else -1,
            rest=rest,  # type: ignore[arg-type]
            looks=looks,
            background=background,
            noise_scale=math.exp(u(math.log(0.5), math.log(1.5))),
            wander=wander,
            active=(float(start), float(end)),
            pauses=tuple(sorted(pauses)),
            accent=float(v(0.5, 0.9)),
            lighting=lighting,
            flicker_hz=flicker_hz,
            flicker_depth=float(depth),
            bias=float(v(-1.0, 1.0)),
            sway=tuple(float(x) for x in sway),
        )

    @property
    def moving_arms(self) -> tuple[bool, bool]:
        """Whether the right and the left arm move in this scene."""
        return MOTIONS[self.label][1]

    def body_pose(self, t: Tensor) -> tuple[Tensor, Tensor]:
        """The body's sway at times ``t`` (seconds): lean and offset.

        A point ``p`` of the person (body units) is seen at
        ``HIP + R(lean) (p - HIP) + offset``, ``R`` the rotation by ``lean`` (radians,
        clockwise in the image). The sway goes on over the whole recording, idle stretches
        and pauses included.

        Returns:
            ``(lean, offset)``: ``(S,)`` radians and ``(S, 2)`` body units, float64.

        Example:
            >>> scene = GestureScene.sample(0, 1)
            >>> lean, offset = scene.body_pose(torch.linspace(0, 6, 61, dtype=torch.float64))
            >>> bool(lean.abs().max() < 0.02 and offset.abs().max() < 0.05)
            True
        """
        t = torch.as_tensor(t, dtype=torch.float64)
        waves = [self.sway[k:k + 3] for k in range(0, len(self.sway), 3)]

        def wave(*items: tuple[float, ...]) -> Tensor:
            out = torch.zeros_like(t)
            for amp, freq, phase in items:
                out = out + amp * torch.sin(2 * math.pi * freq * t + phase)
            return out

        if not waves:
            return torch.zeros_like(t), torch.zeros(t.shape + (2,), dtype=torch.float64)
        offset = torch.stack([wave(*waves[:2]), wave(waves[2])], dim=-1)
        return wave(waves[3]), offset

    def _swayed(self, points: Tensor, t: Tensor) -> Tensor:
        """Body-unit points ``(S, K, 2)`` at times ``t`` (seconds) moved by the sway."""
        if not self.sway:
            return points
        lean, offset = self.body_pose(t)
        hip = torch.tensor(HIP, dtype=torch.float64)
        rel = points - hip
        cos, sin = torch.cos(lean)[:, None], torch.sin(lean)[:, None]
        turned = torch.stack([cos * rel[..., 0] - sin * rel[..., 1],
                              sin * rel[..., 0] + cos * rel[..., 1]], dim=-1)
        return hip + turned + offset[:, None, :]

    def body_capsules(self, t_us: Tensor) -> list[tuple[Tensor, Tensor, float, int]]:
        """Torso, shoulders, neck and head at times ``t_us`` (microseconds), swayed.

        Returns:
            Per capsule of ``BODY`` ``(a, b, radius, look)``: ``(S, 2)`` float64 pixel
            coordinates of its ends, its radius in pixels and its index into ``looks``.
        """
        t = torch.as_tensor(t_us, dtype=torch.float64) * 1e-6
        ends = torch.tensor([[a, b] for _, a, b, _, _ in BODY], dtype=torch.float64)
        points = self._swayed(ends.reshape(1, -1, 2).expand(t.numel(), -1, -1), t)
        points = torch.tensor(self.origin, dtype=torch.float64) + self.scale * points
        return [(points[:, 2 * k], points[:, 2 * k + 1], radius * self.scale, look)
                for k, (_, _, _, radius, look) in enumerate(BODY)]

    def _moving_time(self, t: Tensor) -> Tensor:
        """Seconds of motion up to ``t`` (seconds).

        The integral of a gate that is 1 while the person moves, 0 before the gesture, after
        it and in pauses, with linear ramps.
        """
        ramp = RAMP_FRACTION * self.duration_us * 1e-6

        def ramped(x: Tensor) -> Tensor:  # integral of clamp(x / ramp, 0, 1)
            return torch.where(x < ramp, x.clamp_min(0) ** 2 / (2 * ramp), x - ramp / 2)

        start, end = (v * 1e-6 for v in self.active)
        out = ramped(t - start) - ramped(t - end)
        for at, length in self.pauses:
            out = out - ramped(t - at * 1e-6) + ramped(t - (at + length) * 1e-6)
        return out

    def _phase(self, t: Tensor) -> Tensor:
        """Motion phase (radians) at times ``t`` (seconds, float64)."""
        freq = MOTIONS[self.label][0] * self.speed
        depth, wobble, wobble_phase = self.tempo
        moving = self._moving_time(t)  # the tempo wobble too holds still in pauses
        psi = (2 * math.pi * freq * moving + self.phase
               + depth * torch.sin(2 * math.pi * wobble * moving + wobble_phase))
        a, sin = self.accent, torch.sin(psi)  # the integral of (1 + a cos)**3 / (1 + 1.5 a**2)
        return psi + (3 * a * sin + 0.75 * a * a * torch.sin(2 * psi)
                      + a**3 * (sin - sin**3 / 3)) / (1 + 1.5 * a * a)

    def presence(self, t: Tensor) -> Tensor:
        """How far the arms are out of their rest pose at ``t`` (seconds): 0 to 1."""
        ramp = RAMP_FRACTION * self.duration_us * 1e-6
        start, end = (v * 1e-6 for v in self.active)
        return ((t - start) / ramp).clamp(0, 1) - ((t - end) / ramp + 1).clamp(0, 1)

    def _wrists_at_rest(self, t: Tensor) -> tuple[Tensor, Tensor]:
        """Wrists of arms hanging at rest, ``(S, 2)`` body units each."""
        zero = torch.zeros_like(t)
        return (torch.stack([-SHOULDER_X - 0.06 + self.rest[0] + zero, 0.37 + self.rest[1] + zero],
                            dim=1),
                torch.stack([SHOULDER_X + 0.06 + self.rest[2] + zero, 0.37 + self.rest[3] + zero],
                            dim=1))

    def _wrists(self, t: Tensor) -> tuple[Tensor, Tensor]:
        """Wrist targets of the right and the left arm, ``(S, 2)`` body units each."""
        a = self.amplitude
        phase = self._phase(t)
        zero = torch.zeros_like(t)

        def at(x: Tensor | float, y: Tensor | float) -> Tensor:
            return torch.stack([x + zero, y + zero], dim=1)

        rest = self._wrists_at_rest(t)
        label = self.label
        if label == 0:  # clapping: hands meet in front of the chest
            opening = 0.085 + 0.13 * a * 0.5 * (1 + torch.cos(phase))
            y = 0.20 + 0.015 * torch.sin(phase)
            return at(-opening, y), at(opening, y)
        if label in (1, 2):  # wave: forearm up, swinging about the elbow
            side = -1.0 if label == 1 else 1.0
            swing = 0.15 + 0.6 * a * torch.sin(phase)
            ex = side * (SHOULDER_X + UPPER_ARM * math.cos(math.radians(10)))
            ey = UPPER_ARM * math.sin(math.radians(10))
            wrist = at(ex + side * FOREARM * torch.sin(swing), ey - FOREARM * torch.cos(swing))
            return (wrist, rest[1]) if label == 1 else (rest[0], wrist)
        if 3 <= label <= 6:  # big circles about the shoulder, nearly straight arm
            side = -1.0 if label in (3, 4) else 1.0
            sense = 1.0 if label in (3, 5) else -1.0  # clockwise in the image: angle grows
            radius = 0.38 + 0.04 * (a - 1.0)
            angle = sense * phase
            wrist = at(side * SHOULDER_X + radius * torch.cos(angle), radius * torch.sin(angle))
            return (wrist, rest[1]) if side < 0 else (rest[0], wrist)
        if label == 7:  # arm roll: hands orbit each other in front of the chest
            angle = self.direction * phase
            rx, ry = 0.05 * a, 0.08 * a
            right = at(-0.06 + rx * torch.cos(angle), 0.25 + ry * torch.sin(angle))
            left = at(0.06 - rx * torch.cos(angle), 0.25 - ry * torch.sin(angle))
            return right, left
        if label == 8:  # air drums: alternating strokes, drifting between drums
            def stroke(p: Tensor) -> Tensor:
                return torch.sin(p) + 0.35 * torch.sin(2 * p)

            drift = 0.04 * torch.sin(0.3 * phase)
            right = at(-0.15 + drift, 0.22 + 0.07 * a * stroke(phase))
            left = at(0.15 + drift, 0.22 + 0.07 * a * stroke(phase + math.pi))
            return right, left
        if label == 9:  # air guitar: right hand strums at the hip, left hand on the neck
            right = at(-0.05 + 0.02 * torch.sin(phase), 0.30 + 0.08 * a * torch.sin(phase))
            slow = 0.31 * phase
            left = at(0.46 + 0.03 * torch.sin(slow), 0.10 + 0.02 * torch.sin(slow + 1.0))
            return right, left
        # other gestures: smooth, irregular motion of both arms
        out = []
        moving_t = self._moving_time(t)
        for params in self.wander:
            x = params[0] + zero
            y = params[1] + zero
            for k in range(3):
                f, ax, ay, px, py = params[2 + 5 * k: 7 + 5 * k]
                arg = 2 * math.pi * f * self.speed * moving_t
                x = x + a * ax * torch.sin(arg + px)
                y = y + a * ay * torch.sin(arg + py)
            out.append(torch.stack([x, y], dim=1))
        return out[0], out[1]

    def arm_keypoints(self, t_us: Tensor, *, sway: bool = True) -> tuple[Tensor, Tensor]:
        """Shoulder, elbow, wrist and fingertip of each arm at times ``t_us``.

        Args:
            t_us: ``(S,)`` times, microseconds.
            sway: move the arms with the body's sway (:meth:`body_pose`); without it, the
                arms as the gesture alone moves them.

        Returns:
            ``(right, left)``, each ``(S, 4, 2)`` float64 pixel coordinates ``(x, y)`` of
            shoulder, elbow, wrist, fingertip.
        """
        t = torch.as_tensor(t_us, dtype=torch.float64) * 1e-6
        wrists = self._wrists(t)
        rest = self._wrists_at_rest(t)
        out = self.presence(t)[:, None]
        blended = tuple(r + out * (w - r) if moving else w for w, r, moving
                        in zip(wrists, rest, self.moving_arms, strict=True))
        bends = MOTIONS[self.label][2]
        arms = []
        for side, wrist, bend in zip((-1.0, 1.0), blended, bends, strict=True):
            shoulder = torch.tensor([side * SHOULDER_X, 0.0], dtype=torch.float64)
            elbow, wrist = two_link(shoulder, wrist, side * bend)
            along = wrist - elbow
            tip = wrist + HAND * along / along.norm(dim=1, keepdim=True)
            points = torch.stack([shoulder.expand_as(wrist), elbow, wrist, tip], dim=1)
            if sway:
                points = self._swayed(points, t)
            origin = torch.tensor(self.origin, dtype=torch.float64)
            arms.append(origin + self.scale * points)
        return arms[0], arms[1]
