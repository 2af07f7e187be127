"""Event-to-frame binning against hand-computed frames and a slow exact reference."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest
import torch

from evdown_torch import Events
from evdown_torch.frames import to_frames
from tests.helpers import DVS_DTYPE, random_stream


def reference_frames(events, sensor_size, bins, t_start, t_end):
    """One event at a time, in exact rational arithmetic."""
    w, h, _ = sensor_size
    out = np.zeros((bins, 2, h, w), dtype=np.float32)
    span = Fraction(t_end) - Fraction(t_start)
    for x, y, t, p in zip(events["x"], events["y"], events["t"], events["p"]):
        if not t_start <= t <= t_end:
            continue
        k = 0 if span == 0 else min(int((Fraction(int(t)) - t_start) * bins / span), bins - 1)
        out[k, int(p > 0), y, x] += 1
    return out


def test_hand_computed_frames():
    ev = np.array(
        [(0, 0, True, 100), (2, 1, False, 103), (2, 1, False, 104), (1, 0, True, 106),
         (1, 0, False, 109)],
        dtype=DVS_DTYPE,
    )
    frames = to_frames(ev, (3, 2, 2), 3)  # window [100, 109], bins of 3 us
    expected = torch.zeros(3, 2, 2, 3)
    expected[0, 1, 0, 0] = 1  # t=100 -> bin 0
    expected[1, 0, 1, 2] = 2  # t=103, 104 -> bin 1 (3*3//9 = 1, 4*3//9 = 1)
    expected[2, 1, 0, 1] = 1  # t=106 -> bin 2 (6*3//9 = 2)
    expected[2, 0, 0, 1] = 1  # t=109 = t_end -> last bin
    assert frames.dtype == torch.float32 and frames.shape == (3, 2, 2, 3)
    torch.testing.assert_close(frames, expected)


def test_window_leaves_out_events_outside():
    ev = torch.tensor([[0, 0, -5, 1], [0, 0, 0, 1], [0, 0, 9, 0], [0, 0, 10, 0], [0, 0, 11, 1]])
    frames = to_frames(ev, (1, 1, 2), 2, t_start=0, t_end=10)
    assert frames.flatten().tolist() == [0.0, 1.0, 2.0, 0.0]


@pytest.mark.parametrize("bins", [1, 4, 7])
def test_matches_exact_reference(rng, bins):
    sensor = (9, 5, 2)
    ev = random_stream(rng, 500, sensor, t_max=1_000)
    got = to_frames(ev, sensor, bins, t_start=13, t_end=977)
    np.testing.assert_array_equal(got.numpy(), reference_frames(ev, sensor, bins, 13, 977))
    whole = to_frames(ev, sensor, bins)
    lo, hi = int(ev["t"].min()), int(ev["t"].max())
    np.testing.assert_array_equal(whole.numpy(), reference_frames(ev, sensor, bins, lo, hi))
    assert float(whole.sum()) == len(ev)


def test_float_timestamps_and_large_clock(rng):
    sensor = (6, 4, 2)
    ev = random_stream(rng, 300, sensor, t_max=10_000)
    shifted = ev.copy()
    shifted["t"] += 2**52
    base = to_frames(ev, sensor, 5)
    torch.testing.assert_close(to_frames(shifted, sensor, 5), base)
    floats = np.empty(len(ev), dtype=[("x", "<i2"), ("y", "<i2"), ("p", "<i1"), ("t", "<f8")])
    for name in ("x", "y", "p", "t"):
        floats[name] = ev[name]
    lo, hi = float(ev["t"].min()), float(ev["t"].max())
    np.testing.assert_array_equal(
        to_frames(floats, sensor, 5).numpy(), reference_frames(ev, sensor, 5, lo, hi)
    )


def test_empty_and_single_timestamp_keep_shape_and_dtype():
    empty = to_frames(np.empty(0, dtype=DVS_DTYPE), (4, 3, 2), 6)
    assert empty.shape == (6, 2, 3, 4) and empty.dtype == torch.float32
    assert float(empty.abs().sum()) == 0
    same_t = Events.from_columns([0, 1, 1], [0, 0, 2], [7, 7, 7], [1, 0, 1])
    frames = to_frames(same_t, (4, 3, 2), 3)
    assert frames.shape == (3, 2, 3, 4) and float(frames[0].sum()) == 3
    assert float(frames[1:].sum()) == 0


def test_device(device):
    ev = torch.tensor([[1, 0, 0, 1], [0, 1, 4, 0]], device=device)
    frames = to_frames(ev, (2, 2, 2), 2)
    assert frames.device.type == device.type and float(frames.sum()) == 2


def test_bad_arguments():
    ev = torch.tensor([[0, 0, 0, 1]])
    with pytest.raises(ValueError, match="n_time_bins must be a positive integer"):
        to_frames(ev, (1, 1, 2), 0)
    with pytest.raises(ValueError, match="t_end must not be before t_start"):
        to_frames(ev, (1, 1, 2), 2, t_start=5, t_end=1)
    with pytest.raises(ValueError, match="must lie in"):
        to_frames(torch.tensor([[3, 0, 0, 1]]), (2, 2, 2), 2)


def reference_mean_times(events, sensor_size, bins, t_start, t_end):
    """Mean position of each pixel's events in their bin, -1 to 1, exact rationals."""
    w, h, _ = sensor_size
    sums = {}
    span = Fraction(t_end) - Fraction(t_start)
    for x, y, t, p in zip(events["x"], events["y"], events["t"], events["p"]):
        if not t_start <= t <= t_end:
            continue
        scaled = (Fraction(int(t)) - t_start) * bins / span
        k = min(int(scaled), bins - 1)
        within = scaled - k  # 1 for t_end itself, at the end of the last bin
        key = (k, int(p > 0), int(y), int(x))
        total, count = sums.get(key, (Fraction(0), 0))
        sums[key] = (total + 2 * within - 1, count + 1)
    out = np.zeros((bins, 2, h, w), dtype=np.float64)
    for (k, c, y, x), (total, count) in sums.items():
        out[k, c, y, x] = float(total / count)
    return out


@pytest.mark.parametrize("bins", [1, 3, 7])
def test_mean_time_matches_exact_reference(rng, bins):
    sensor = (5, 4, 2)
    ev = random_stream(rng, 400, sensor, t_max=1_000)
    t0, t1 = 13, 977
    frames = to_frames(ev, sensor, bins, t_start=t0, t_end=t1, mean_time=True)
    assert frames.shape == (bins, 4, 4, 5) and frames.dtype == torch.float32
    np.testing.assert_array_equal(frames[:, :2].numpy(),
                                  reference_frames(ev, sensor, bins, t0, t1))
    np.testing.assert_allclose(frames[:, 2:].numpy(),
                               reference_mean_times(ev, sensor, bins, t0, t1), atol=1e-6)
    floats = ev.astype([("x", "<i8"), ("y", "<i8"), ("p", "<i8"), ("t", "<f8")])
    np.testing.assert_allclose(
        to_frames(floats, sensor, bins, t_start=t0, t_end=t1, mean_time=True).numpy(),
        frames.numpy(), atol=1e-6)


def test_mean_time_hand_computed():
    ev = np.array([(0, 0, True, 0), (0, 0, True, 2), (0, 0, False, 7), (1, 0, True, 8)],
                  dtype=DVS_DTYPE)
    frames = to_frames(ev, (2, 1, 2), 2, mean_time=True)  # bins [0, 4) and [4, 8]
    assert frames[0, 3, 0, 0] == -0.5  # ON at 0 and 2: positions -1 and 0
    assert frames[1, 2, 0, 0] == 0.5  # OFF at 7: 3/4 of the way, 2 * 0.75 - 1 = 0.5
    assert frames[1, 3, 0, 1] == 1.0  # t_end itself
    assert frames[0, 2].abs().sum() == 0  # no OFF event in bin 0
    empty = to_frames(ev[:0], (2, 1, 2), 3, mean_time=True)
    assert empty.shape == (3, 4, 1, 2) and not empty.any()


def test_to_frames_transform_keeps_the_shape_of_an_empty_output_in_a_dataloader(rng):
    tonic = pytest.importorskip("tonic")
    from torch.utils.data import DataLoader

    from evdown_torch import EventCount
    from evdown_torch.frames import ToFrames

    sensor = (34, 34, 2)
    down = EventCount(sensor, factor=4, threshold=1.0)
    busy = random_stream(rng, 3000, sensor, t_max=300_000)
    quiet = random_stream(rng, 30, sensor, t_max=300_000)
    quiet["p"] = np.arange(30) % 2 == 0  # alternating polarity: no region reaches a level
    assert len(down(busy)) > 0 and len(down(quiet)) == 0
    transform = ToFrames(down.output_sensor_size, n_time_bins=10, transform=down)
    tonic_way = tonic.transforms.Compose([down, ToFrames(down.output_sensor_size, 10)])
    assert tonic_way(quiet).shape == (0,)  # why the downscaler goes inside: Compose stops

    class Dataset(torch.utils.data.Dataset):  # as a Tonic dataset applies transform=
        def __init__(self) -> None:
            self.items = [(busy, 0), (quiet, 1), (busy[:0], 2)]

        def __len__(self) -> int:
            return len(self.items)

        def __getitem__(self, i):
            events, label = self.items[i]
            return transform(events), label

    loader = DataLoader(Dataset(), batch_size=3,
                        collate_fn=tonic.collation.PadTensors(batch_first=True))
    frames, labels = next(iter(loader))
    assert frames.shape == (3, 10, 2, 9, 9) and labels.tolist() == [0, 1, 2]
    assert torch.equal(frames[0], to_frames(down(busy), (9, 9, 2), 10))
    assert not frames[1:].any()
    with pytest.raises(TypeError, match="transform must be callable"):
        ToFrames((9, 9, 2), 4, transform=3)
    with pytest.raises(ValueError, match="n_time_bins must be a positive integer"):
        ToFrames((9, 9, 2), n_time_bins=0)
    with pytest.raises(TypeError, match="mean_time must be a bool"):
        ToFrames((9, 9, 2), 4, mean_time=1)
    assert ToFrames((9, 9, 2), 4, mean_time=True)(busy[:0]).shape == (4, 4, 9, 9)


INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1


@pytest.mark.parametrize("bins", [1, 2, 7, 1000])
@pytest.mark.parametrize(("lo", "hi"), [(-(2**62), 2**62), (0, 2**62), (INT64_MIN, INT64_MAX),
                                        (2**40, 2**40 + 2**57)])
def test_spans_beyond_int64_arithmetic_are_binned_exactly(lo, hi, bins):
    # Spans of 2**62 and more: (t - t_start) * T (or the span itself) leaves int64.
    generator = np.random.default_rng(bins)
    t = np.concatenate([[lo, hi], generator.integers(lo, hi, 60, endpoint=True)])
    edges = [lo + -(-k * (hi - lo) // bins) for k in range(bins + 1)]  # exact bin edges
    t = np.concatenate([t, [min(max(e + d, lo), hi) for e in edges for d in (-1, 0, 1)]])
    ev = np.zeros(len(t), DVS_DTYPE)
    ev["t"], ev["x"], ev["p"] = np.sort(t), generator.integers(0, 3, len(t)), True
    expected = reference_frames(ev, (3, 1, 2), bins, lo, hi)
    np.testing.assert_array_equal(to_frames(ev, (3, 1, 2), bins).numpy(), expected)
    timed = to_frames(ev, (3, 1, 2), bins, mean_time=True)
    np.testing.assert_array_equal(timed[:, :2].numpy(), expected)
    np.testing.assert_allclose(timed[:, 2:].numpy(),
                               reference_mean_times(ev, (3, 1, 2), bins, lo, hi), atol=1e-6)


def test_a_window_far_from_the_events_leaves_them_out_without_overflow():
    ev = np.zeros(3, DVS_DTYPE)
    ev["t"] = [INT64_MIN, 0, INT64_MAX]
    frames = to_frames(ev, (1, 1, 2), 4, t_start=2**62, t_end=INT64_MAX)
    assert frames.sum() == 1 and frames[3].sum() == 1  # only t = INT64_MAX, in the last bin
    frames = to_frames(ev, (1, 1, 2), 4, t_start=INT64_MIN + 5, t_end=-(2**62))
    assert frames.sum() == 0  # INT64_MIN lies before the window (t - t_start wraps in int64)


@pytest.mark.parametrize(("name", "value", "error", "message"), [
    ("t_start", float("nan"), ValueError, "t_start must be a finite number, got nan"),
    ("t_end", float("inf"), ValueError, "t_end must be a finite number, got inf"),
    ("t_start", -float("inf"), ValueError, "t_start must be a finite number, got -inf"),
    ("t_start", "3", TypeError, "t_start must be a finite number, got '3'"),
    ("t_end", True, TypeError, "t_end must be a finite number, got True"),
    ("t_start", 2**70, ValueError, r"t_start must lie in int64's range"),
])
def test_window_bounds_must_be_finite_numbers(name, value, error, message):
    ev = torch.tensor([[0, 0, 5, 1], [0, 0, 9, 0]])
    with pytest.raises(error, match=message):
        to_frames(ev, (1, 1, 2), 2, **{name: value})
    assert to_frames(ev, (1, 1, 2), 2, t_start=np.int64(5), t_end=torch.tensor(9)).sum() == 2
