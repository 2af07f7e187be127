"""The benchmark's input streams: synthetic gestures, moving bars, pauses, N-MNIST files."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from evdown_torch.checks import check_positive_int, check_sensor_size
from evdown_torch.events import DVS_DTYPE

__all__ = [
    "EVENTS_SWEEP_RATE",
    "LARGE_RATE",
    "BenchInput",
    "dvs_like_stream",
    "gesture_stream",
    "read_nmnist",
    "stream_duration_s",
    "with_pauses",
]

#: Events per second of the large 1280x720 stream.
LARGE_RATE = 2_000_000.0
#: Events per second of the streams of the events sweep.
EVENTS_SWEEP_RATE = 500_000.0

def dvs_like_stream(
    num_events: int,
    sensor_size: tuple[int, int, int] = (128, 128, 2),
    *,
    duration_us: int = 6_000_000,
    seed: int = 0,
    num_objects: int = 4,
    noise: float = 0.05,
    start_us: int = 0,
) -> np.ndarray:
    """A DVS-like random stream: edges of bars sweeping round like arms, plus background noise.

    Each object is a bar along a radius of a circle, turning at 1 to 4 turns per second; its
    leading edge emits one polarity and its trailing edge the other (bright or dark bars),
    with half a pixel of jitter. A share ``noise`` of the events is uniform background
    activity. Event times are uniform over ``[start_us, start_us + duration_us)``, sorted;
    several events can share a timestamp when the rate exceeds one per microsecond. The bars
    depend on ``seed`` only, so consecutive pieces (same seed, ``start_us`` advancing by
    ``duration_us``) continue one recording: long streams can be made piece by piece.

    Args:
        num_events: number of events ``N`` (>= 0).
        sensor_size: ``(W, H, P)``.
        duration_us: length of the recording in microseconds (> 0).
        seed: seed of the NumPy generator; the same seed gives the same stream.
        num_objects: number of moving bars (> 0).
        noise: share of background events, in ``[0, 1]``.
        start_us: time of the piece's start, microseconds (>= 0).

    Returns:
        ``(N,)`` structured array of :data:`DVS_DTYPE` (``t`` int64 microseconds), sorted by
        ``t``, inside the sensor.

    Example:
        >>> ev = dvs_like_stream(1000, (64, 48, 2), duration_us=10_000, seed=1)
        >>> len(ev), int(ev["x"].max()) < 64, bool((np.diff(ev["t"]) >= 0).all())
        (1000, True, True)
    """
    if not isinstance(num_events, (int, np.integer)) or isinstance(num_events, bool):
        raise TypeError(f"num_events must be a non-negative integer, got {num_events!r}")
    if num_events < 0:
        raise ValueError(f"num_events must be a non-negative integer, got {num_events!r}")
    w, h, _ = check_sensor_size(sensor_size)
    duration_us = check_positive_int("duration_us", duration_us)
    k = check_positive_int("num_objects", num_objects)
    if not 0.0 <= float(noise) <= 1.0:
        raise ValueError(f"noise must be a share in [0, 1], got {noise!r}")
    if not isinstance(start_us, (int, np.integer)) or isinstance(start_us, bool) or start_us < 0:
        raise ValueError(f"start_us must be a non-negative integer, got {start_us!r}")
    rng = np.random.default_rng(seed)
    n = int(num_events)
    size = min(w, h)
    centre = rng.uniform(0.4, 0.6, (k, 2)) * np.array([w, h])
    radius = rng.uniform(0.08, 0.2, k) * size
    length = rng.uniform(0.1, 0.25, k) * size
    width = rng.uniform(0.02, 0.05, k) * size + 1.0
    turn = rng.choice([-1.0, 1.0], k)
    omega = rng.uniform(1.0, 4.0, k) * turn * 2 * np.pi / 1e6  # radians per microsecond
    phase = rng.uniform(0, 2 * np.pi, k)
    bright = rng.random(k) < 0.5

    rng = np.random.default_rng([seed, int(start_us)])  # this piece's events
    t = np.sort(rng.integers(start_us, start_us + duration_us, n))
    obj = rng.integers(0, k, n)
    angle = phase[obj] + omega[obj] * t
    cos, sin = np.cos(angle), np.sin(angle)
    along = radius[obj] + (rng.random(n) - 0.5) * length[obj]
    leading = rng.random(n) < 0.5
    across = np.where(leading, 0.5, -0.5) * width[obj] + rng.normal(0.0, 0.5, n)
    px = centre[obj, 0] + along * cos - across * sin * turn[obj]
    py = centre[obj, 1] + along * sin + across * cos * turn[obj]
    p = leading == bright[obj]

    background = rng.random(n) < noise
    nb = int(background.sum())
    px[background] = rng.uniform(0, w, nb)
    py[background] = rng.uniform(0, h, nb)
    p[background] = rng.random(nb) < 0.5

    out = np.empty(n, dtype=DVS_DTYPE)
    out["x"] = np.clip(np.floor(px), 0, w - 1)
    out["y"] = np.clip(np.floor(py), 0, h - 1)
    out["p"] = p
    out["t"] = t
    return out


def gesture_stream(num_events: int, *, seed: int = 0,
                   sensor_size: tuple[int, int, int] = (128, 128, 2)) -> np.ndarray:
    """``num_events`` events of synthetic DVS128-Gesture-like recordings, one after another.

    Renders 6 s recordings of the 11 classes in turn with :mod:`evdown_torch.synthetic`
    (class ``k % 11``, seed ``seed + k``), each starting 6 s after the previous one, until
    there are enough events, and keeps the first ``num_events``.

    Returns:
        Structured array of :data:`DVS_DTYPE`, sorted by ``t`` (int64 microseconds).

    Example:
        >>> ev = gesture_stream(1000, sensor_size=(32, 32, 2))
        >>> len(ev), bool((np.diff(ev["t"]) >= 0).all())
        (1000, True)
    """
    from evdown_torch.synthetic import render_gesture

    n = check_positive_int("num_events", num_events)
    parts, total, k = [], 0, 0
    while total < n:
        part = render_gesture(k % 11, seed + k, sensor_size=sensor_size, duration_us=6_000_000)
        part["t"] += k * 6_000_000
        parts.append(part)
        total += len(part)
        k += 1
    return np.concatenate(parts)[:n].astype(DVS_DTYPE)


def with_pauses(events: np.ndarray, duration_us: int, *, bursts: int = 10) -> np.ndarray:
    """Spread a stream over ``duration_us`` as ``bursts`` equal bursts separated by pauses.

    The stream's span is cut into ``bursts`` equal time slices; slice ``k`` is shifted to start
    at ``k * duration_us / bursts``. The events, their order and the event rate inside each
    burst are unchanged; only the pauses between bursts grow.

    Args:
        events: structured array sorted by ``t`` (integer microseconds), starting at ``t >= 0``.
        duration_us: the new recording length, at least the stream's span.
        bursts: number of bursts (> 0).

    Returns:
        A new structured array of the same dtype.

    Example:
        >>> ev = dvs_like_stream(100, (32, 32, 2), duration_us=1000, seed=0)
        >>> int(with_pauses(ev, 100_000)["t"].max()) > 90_000
        True
    """
    bursts = check_positive_int("bursts", bursts)
    out = events.copy()
    if len(out) == 0:
        return out
    t = out["t"].astype(np.int64)
    t0 = int(t.min())
    span = int(t.max()) - t0 + 1
    if duration_us < span:
        raise ValueError(
            f"duration_us must be at least the stream's span {span}, got {duration_us}"
        )
    index = ((t - t0) * bursts) // span
    out["t"] = t + index * ((duration_us - span) // bursts)
    return out


def read_nmnist(path: str | Path) -> np.ndarray:
    """Read an N-MNIST ``.bin`` recording (40-bit events) without Tonic.

    Each event is 5 bytes, big-endian: x (8 bits), y (8 bits), polarity (1 bit), timestamp
    (23 bits, microseconds). An event with ``y == 240`` marks a timestamp overflow: it adds
    ``2**13`` to the timestamps of all later events and is not itself an event (as
    ``tonic.io.read_mnist_file`` reads it).

    Returns:
        Structured array of :data:`DVS_DTYPE`, in file order.
    """
    raw = np.fromfile(str(path), dtype=np.uint8)
    if raw.size % 5:
        raise ValueError(f"{str(path)!r} is not an N-MNIST file: {raw.size} bytes is not 5 * N")
    raw = raw.reshape(-1, 5).astype(np.int64)
    t = ((raw[:, 2] & 127) << 16) | (raw[:, 3] << 8) | raw[:, 4]
    overflow = raw[:, 1] == 240
    t = t + np.cumsum(overflow) * 2**13
    keep = ~overflow
    out = np.empty(int(keep.sum()), dtype=DVS_DTYPE)
    out["x"] = raw[keep, 0]
    out["y"] = raw[keep, 1]
    out["p"] = (raw[keep, 2] & 128) > 0
    out["t"] = t[keep]
    return out


def stream_duration_s(events: np.ndarray) -> float:
    """Seconds from the first to the last timestamp (microseconds) of a stream."""
    if len(events) == 0:
        return 0.0
    return float(int(events["t"].max()) - int(events["t"].min())) / 1e6


@dataclass(frozen=True)
class BenchInput:
    """An input stream of a benchmark (metadata; the events live in ``path``)."""

    name: str
    sensor_size: tuple[int, int, int]
    num_events: int
    duration_s: float
    source: str
    path: str
