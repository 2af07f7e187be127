"""A tiny seeded stand-in for gesture recordings, for the evaluation's tests.

Class ``k`` of three: a short bar sweeping right (0), down (1) or along the diagonal (2) across a
16x16 sensor for 50 ms, leading edge ON and trailing edge OFF, plus uniform noise. Its "ground
truth" at factor ``f`` is the same sweep drawn on the small sensor (one event per small pixel
and time step), which is what a smaller camera would see of a sweep this simple.
"""

from __future__ import annotations

import numpy as np

from evdown_torch.evaluate import EvaluationData
from tests.helpers import DVS_DTYPE

SENSOR = (16, 16, 2)
STEPS = 25
STEP_US = 2_000


def _sweep(label: int, offset: int, size: tuple[int, int], scale: int) -> np.ndarray:
    w, h = size
    rows = []
    for step in range(STEPS):
        pos = step * (min(w, h) - 1) // (STEPS - 1)
        for along in range(max(1, 4 // scale)):
            a = (offset // scale + along) % min(w, h)
            if label == 0:
                lead, trail = (pos, a), (max(pos - 1, 0), a)
            elif label == 1:
                lead, trail = (a, pos), (a, max(pos - 1, 0))
            else:
                lead, trail = (pos, pos), (max(pos - 1, 0), max(pos - 1, 0))
            rows.append((lead[0], lead[1], True, step * STEP_US))
            if step:
                rows.append((trail[0], trail[1], False, step * STEP_US))
    return np.array(rows, dtype=DVS_DTYPE)


def _recording(label: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    offset = int(rng.integers(0, 12))
    sweep = _sweep(label, offset, SENSOR[:2], 1)
    n = 40
    noise = np.empty(n, dtype=DVS_DTYPE)
    noise["x"] = rng.integers(0, SENSOR[0], n)
    noise["y"] = rng.integers(0, SENSOR[1], n)
    noise["p"] = rng.random(n) < 0.5
    noise["t"] = rng.integers(0, STEPS * STEP_US, n)
    events = np.concatenate([sweep, noise])
    return events[np.argsort(events["t"], kind="stable")]


def stand_in_data(train: int = 12, test: int = 6, seed: int = 0) -> EvaluationData:
    """``train`` and ``test`` recordings, classes in turn, with a ground truth."""
    items = [(_recording(i % 3, seed * 1000 + i), i % 3) for i in range(train + test)]
    offsets = [int(np.random.default_rng(seed * 1000 + i).integers(0, 12))
               for i in range(train, train + test)]

    def ground_truth(i: int, factor: tuple[int, int]) -> np.ndarray:
        size = (-(-SENSOR[0] // factor[0]), -(-SENSOR[1] // factor[1]))
        return _sweep(test_labels[i], offsets[i], size, factor[0])

    test_labels = [label for _, label in items[train:]]
    return EvaluationData(
        description="stand-in sweeps, 16x16, 50 ms",
        sensor_size=SENSOR,
        num_classes=3,
        train=items[:train],
        test=items[train:],
        ground_truth=ground_truth,
    )
