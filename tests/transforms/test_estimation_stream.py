"""Bounded-delay estimator sessions: hand-computed chunked cases and a bounded state."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from evdown_torch import CubicEstimation, Events, LinearEstimation
from tests.helpers import random_stream

EPOCH = 1_700_000_000_000_000  # an int64 microsecond clock today


def feed(transform, chunks):
    """Each chunk's output as a list of rows, then the flush's."""
    session = transform.session()
    outputs = [session(chunk).tolist() for chunk in chunks]
    return outputs + [session.flush().tolist()]


# Linear, D = 3, region of two pixels, threshold 0.25 (sum of levels crosses at 0.5 steps).
# Pixel (0, 0): ON at 0, ON at 20 (held knot (17, 1)). Pixel (1, 0): front (0, 0), held knot
# (7, 0), ON at 10, OFF at 25 (held knot (22, 1)). The sum is 1 at 0 (two ON), rises to 2 on
# [7, 10] (1.5 at 8.5, rounded to 9), to 3 on [17, 20] (2.5 at 18.5 -> 19), falls to 2 on
# [22, 25] (2.5 at 23.5 -> 24). A session emits what is earlier than tau - D.
LINEAR_EVENTS = [[0, 0, 0, 1], [1, 0, 10, 1], [0, 0, 20, 1], [1, 0, 25, 0]]
LINEAR_OUTPUTS = [
    [],  # tau 0
    [[0, 0, 0, 1], [0, 0, 0, 1]],  # tau 10: before 7
    [[0, 0, 9, 1], [0, 0, 10, 1]],  # tau 20: before 17
    [[0, 0, 19, 1], [0, 0, 20, 1]],  # tau 25: before 22
    [[0, 0, 24, 0], [0, 0, 25, 0]],  # flush
]


def check_event_by_event(events, outputs, transform, shift):
    """Feeding ``events`` (shifted by ``shift``) one at a time gives ``outputs`` per chunk,
    then the flush; together they are the batch output."""
    ev = torch.tensor(events) + torch.tensor([0, 0, shift, 0])
    got = feed(transform, [ev[i:i + 1] for i in range(len(events))])
    expected = [[[x, y, t + shift, p] for x, y, t, p in part] for part in outputs]
    assert got == expected
    assert sum(got, []) == transform(ev).tolist()


@pytest.mark.parametrize("shift", [0, EPOCH])
def test_linear_session_hand_computed_across_chunks(shift):
    transform = LinearEstimation((2, 1, 2), factor=(2, 1), threshold=0.25, max_delay=3)
    check_event_by_event(LINEAR_EVENTS, LINEAR_OUTPUTS, transform, shift)


def test_linear_session_hand_computed_float_times():
    # The same stream at half the time scale (D = 1.5): crossings at exact binary fractions.
    ev = torch.tensor(LINEAR_EVENTS, dtype=torch.float64) * torch.tensor([1, 1, 0.5, 1])
    transform = LinearEstimation((2, 1, 2), factor=(2, 1), threshold=0.25, max_delay=1.5)
    outputs = feed(transform, [ev[:2], ev[2:2], ev[2:]])
    assert outputs == [
        [[0, 0, 0.0, 1], [0, 0, 0.0, 1]],  # tau 5: before 3.5
        [],
        [[0, 0, 4.25, 1], [0, 0, 5.0, 1], [0, 0, 9.25, 1], [0, 0, 10.0, 1]],  # before 11
        [[0, 0, 11.75, 0], [0, 0, 12.5, 0]],
    ]
    assert sum(outputs, []) == transform(ev).tolist()


# Cubic, D = 4: a ramp between a held knot and a knot with flat segments on both sides has
# zero PCHIP slopes at both ends, so it is the smoothstep 3 s^2 - 2 s^3 (half-way at s = 1/2).
# Pixel (0, 0): ON at 0, OFF at 40 (held knot (36, 1)); pixel (1, 0): ON at 20 (held knot
# (16, 0)), OFF at 60 (held knot (56, 1)). Sum: 1 at 0 (two ON), 2 by [16, 20] (1.5 at 18),
# 1 by [36, 40] (1.5 at 38), 0 by [56, 60]; that last ramp ends at the stream's last knot,
# where SciPy's end slope is ((2 * 4 + 36) * -1/4) / 40 = -0.275 per us: the piece is
# 1 - 1.9 s^2 + 0.9 s^3, which is 1/2 at s = 0.6077..., t = 58.43, rounded to 58.
CUBIC_EVENTS = [[0, 0, 0, 1], [1, 0, 20, 1], [0, 0, 40, 0], [1, 0, 60, 0]]
CUBIC_OUTPUTS = [
    [],  # tau 0
    [[0, 0, 0, 1], [0, 0, 0, 1]],  # tau 20: before 12
    [[0, 0, 18, 1], [0, 0, 20, 1]],  # tau 40: before 32
    [[0, 0, 38, 0], [0, 0, 40, 0]],  # tau 60: before 52
    [[0, 0, 58, 0], [0, 0, 60, 0]],  # flush
]


def smoothstep_end_root() -> float:
    """Root in (0, 1) of 0.9 s^3 - 1.9 s^2 + 0.5 (bisection)."""
    low, high = 0.0, 1.0
    for _ in range(100):
        mid = (low + high) / 2
        low, high = (mid, high) if 0.9 * mid**3 - 1.9 * mid**2 + 0.5 > 0 else (low, mid)
    return low


@pytest.mark.parametrize("shift", [0, EPOCH])
def test_cubic_session_hand_computed_across_chunks(shift):
    assert math.floor(56 + 4 * smoothstep_end_root() + 0.5) == 58
    transform = CubicEstimation((2, 1, 2), factor=(2, 1), threshold=0.25, max_delay=4)
    check_event_by_event(CUBIC_EVENTS, CUBIC_OUTPUTS, transform, shift)


def test_cubic_session_hand_computed_float_times():
    ev = torch.tensor(CUBIC_EVENTS, dtype=torch.float64)
    transform = CubicEstimation((2, 1, 2), factor=(2, 1), threshold=0.25, max_delay=4.0)
    outputs = feed(transform, [ev[:3], ev[3:]])
    flat = sum(outputs, [])
    assert [row[2] for row in flat[:6]] == [0.0, 0.0, 18.0, 20.0, 38.0, 40.0]
    assert flat[6][2] == pytest.approx(56 + 4 * smoothstep_end_root(), abs=1e-9)
    assert [row[3] for row in flat] == [1, 1, 1, 1, 0, 0, 0, 0]
    assert flat == transform(ev).tolist()


def regular_stream(sensor: tuple[int, int, int], period: int, duration: int) -> torch.Tensor:
    """Every pixel fires every ``period`` us (phases spread), polarity alternating."""
    w, h, _ = sensor
    pixel = torch.arange(w * h)
    rows = []
    for k in range(duration // period):
        t = k * period + (pixel * 7) % period
        rows.append(torch.stack([pixel % w, pixel // w, t, (pixel + k) % 2], 1))
    ev = torch.cat(rows)
    return ev[torch.sort(ev[:, 2], stable=True).indices]


@pytest.mark.parametrize(("cls", "lag"), [(LinearEstimation, 1), (CubicEstimation, 2)])
def test_session_state_stays_bounded_on_a_long_stream(cls, lag):
    sensor, period, delay, chunk_us = (6, 4, 2), 13, 10, 25
    ev = regular_stream(sensor, period, duration=3000)
    transform = cls(sensor, factor=2, threshold=0.25, max_delay=delay)
    session = transform.session()
    sizes, parts = [], []
    for start in range(0, 3000, chunk_us):
        chunk = ev[(ev[:, 2] >= start) & (ev[:, 2] < start + chunk_us)]
        parts.append(session(chunk))
        sizes.append(session.state.knots.num_events)
        assert session.state.change.shape == (sizes[-1],)
        assert session.state.pixel_t.shape == (sensor[0] * sensor[1],)
        assert session.state.q.shape == (3 * 2,)
    # Held: each pixel's last `lag` knots before the horizon tau - lag * D and its knots
    # since (its events of the last lag * D, each with at most one held knot).
    per_pixel = lag + 2 * (lag * delay // period + 1)
    assert max(sizes) <= sensor[0] * sensor[1] * per_pixel
    n = len(sizes)
    assert max(sizes[n // 2:]) <= max(sizes[: n // 4])  # it does not grow with the stream
    parts.append(session.flush())
    assert torch.equal(torch.cat(parts), transform(ev))


@pytest.mark.parametrize("cls", [LinearEstimation, CubicEstimation])
def test_session_on_a_random_stream_with_many_small_chunks(cls, rng):
    sensor = (9, 7, 2)
    arr = random_stream(rng, 1000, sensor, t_max=10_000)
    transform = cls(sensor, factor=(3, 2), threshold=0.3, max_delay=50)
    session = transform.session()
    parts = [session(chunk) for chunk in np.array_split(arr, 100)] + [session.flush()]
    np.testing.assert_array_equal(np.concatenate(parts), transform(arr))
    assert isinstance(session.flush(), Events)


@pytest.mark.parametrize("dtype", [torch.int64, torch.float64])
def test_cubic_front_slope_is_decided_within_the_delay(dtype):
    # Pixel (1, 0): front knot (0, 0), ON at 5, then flat until its held knot (990, 1). SciPy's
    # end slope at 0 would be (2 * 5 + h1) / (5 + h1) * 0.2 with h1 = 985 in the whole stream
    # but h1 = 95 when the session decides [0, 5] (at tau = 100); with a bounded delay it is 0
    # (docs/semantics.md, "Bounded delay"), so the session's head is the batch's.
    ev = torch.tensor([[0, 0, 0, 1], [1, 0, 5, 1], [0, 0, 100, 1], [1, 0, 1000, 1]], dtype=dtype)
    transform = CubicEstimation((2, 1, 2), factor=(2, 1), threshold=0.05, max_delay=10)
    session = transform.session()
    head = session(ev[:3])
    batch = transform(ev)
    assert torch.equal(head, batch[batch[:, 2] < 100 - 2 * 10])
    assert head.shape[0] > 2  # crossings on the front ramp are among them
    assert torch.equal(torch.cat([head, session(ev[3:]), session.flush()]), batch)


@pytest.mark.parametrize("shift", [0, EPOCH])
def test_cubic_front_knot_at_rest_hand_computed(shift):
    # Region 0 (pixels (0, 0) and (1, 0)), D = 100, threshold 0.25: the sum of levels S
    # crosses a level every 0.5. Pixel (1, 0): front knot (0, 0), ON at 10, flat to the
    # stream's end. At rest before the stream, its slope at 0 is 0, and 0 at 10 (flat after):
    # the ramp is the smoothstep 3 s^2 - 2 s^3, so S = 1 + smoothstep crosses 1.5 at s = 1/2,
    # t = 5 (SciPy's end slope 0.1005 would make it 1.005 s + 0.99 s^2 - 0.995 s^3: t = 4).
    # Pixel (0, 0): ON at 0 and 500, held knot (400, 1), flat on both sides: S crosses 2.5 at
    # 450. Pixel (2, 0) (region 1) only sets the stream's end, 2000.
    ev = torch.tensor([[0, 0, 0, 1], [1, 0, 10, 1], [0, 0, 500, 1], [2, 0, 2000, 1]])
    ev[:, 2] += shift
    transform = CubicEstimation((4, 1, 2), factor=(2, 1), threshold=0.25, max_delay=100)
    out = transform(ev)
    region0 = out[out[:, 0] == 0]
    assert (region0[:, 2] - shift).tolist() == [0, 0, 5, 10, 450, 500]
    assert region0[:, 3].tolist() == [1] * 6
    session = transform.session()
    parts = [session(ev[i:i + 1]) for i in range(4)] + [session.flush()]
    assert torch.equal(torch.cat(parts), out)


@pytest.mark.parametrize("cls", [LinearEstimation, CubicEstimation])
def test_a_refused_chunk_leaves_the_state_as_it_was(cls, rng):
    sensor = (9, 7, 2)
    arr = random_stream(rng, 300, sensor, t_max=3000)
    transform = cls(sensor, factor=2, threshold=0.3, max_delay=40)
    session = transform.session()
    head = session(arr[:150])
    knots_before = session.state.knots.num_events
    late = arr[150:].copy()
    late["t"][-1] = arr["t"][149] - 1
    with pytest.raises(ValueError, match="follow each other in time"):
        session(late)
    assert session.state.knots.num_events == knots_before
    out = np.concatenate([head, session(arr[150:]), session.flush()])
    np.testing.assert_array_equal(out, transform(arr))


@pytest.mark.parametrize("value", ["1e300", str(10**19)])
def test_cli_downscale_with_a_huge_delay(value, tmp_path, rng, capsys):
    # Issue 27: a delay longer than every gap holds nothing; the CLI downscales with it.
    from evdown_torch.cli import main

    sensor = (9, 7, 2)
    arr = random_stream(rng, 300, sensor, t_max=3000)
    source, target = tmp_path / "in.npy", tmp_path / "out.npy"
    np.save(source, arr)
    code = main(["downscale", str(source), str(target), "--method", "cubic", "--factor", "2",
                 "--set", f"max_delay={value}", "--sensor-size", "9", "7", "2"])
    assert code == 0, capsys.readouterr().err
    expected = CubicEstimation(sensor, factor=2, max_delay=10**6)(arr)
    np.testing.assert_array_equal(np.load(target), expected)
