"""PhotocurrentPooling's frames mode (the paper's literal pipeline) against its slow reference.

Frames at ``fps`` (optionally leaky, ``cutoff_hz``), their limits, sessions and float
timestamps; the events mode is in ``test_photocurrent.py``.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings

from evdown_torch import PhotocurrentPooling, max_output_events
from tests.helpers import (
    DVS_DTYPE,
    chunkings,
    photocurrent_frames_reference,
    random_stream,
    rows,
    run_in_chunks,
)

SENSOR = (10, 7, 2)


@pytest.mark.parametrize("fps", [1000.0, 333.0, 12_500.0])
@pytest.mark.parametrize(("factor", "contrast", "threshold"), [(2, 0.2, None), ((3, 2), 0.4, 0.25)])
def test_frames_mode_matches_reference(fps, factor, contrast, threshold, rng):
    arr = random_stream(rng, 300, SENSOR, t_max=20_000, sort=False)
    pool = PhotocurrentPooling(SENSOR, factor=factor, contrast=contrast, threshold=threshold,
                               fps=fps)
    expected = photocurrent_frames_reference(arr, SENSOR, factor, contrast, pool.threshold, fps)
    assert sorted(rows(pool(arr))) == expected


def leaky_frames_case(rng, n, fps, cutoff_hz):
    """``n`` random events over 20 ms, frames-mode pooling (factor 2, contrast 0.3,
    threshold 0.1) at ``fps`` and ``cutoff_hz``, and the reference's output rows."""
    arr = random_stream(rng, n, SENSOR, t_max=20_000)
    pool = PhotocurrentPooling(SENSOR, factor=2, contrast=0.3, threshold=0.1, fps=fps,
                               cutoff_hz=cutoff_hz)
    return arr, pool, photocurrent_frames_reference(arr, SENSOR, 2, 0.3, 0.1, fps, cutoff_hz)


@pytest.mark.parametrize("cutoff_hz", [5.0, 200.0])
def test_frames_mode_with_leak_matches_reference(cutoff_hz, rng):
    arr, pool, expected = leaky_frames_case(rng, 200, 2000.0, cutoff_hz)
    assert len(expected) > 20
    assert sorted(rows(pool(arr))) == expected


@pytest.mark.parametrize("fps", [1e6, 1e5])
def test_frames_mode_at_high_fps_matches_events_mode_count(fps, rng):
    # A region here has an event every ~1300 us on average. With frames 100 times shorter or
    # more, a frame rarely holds two of a region's events, and only those (whose intermediate
    # value the events mode sees) can change the count. Stated tolerance: 1 %.
    arr = random_stream(rng, 3000, SENSOR, t_max=200_000)
    events_mode = PhotocurrentPooling(SENSOR, factor=2, contrast=0.2, threshold=0.05)(arr)
    frames_mode = PhotocurrentPooling(SENSOR, factor=2, contrast=0.2, threshold=0.05,
                                      fps=fps)(arr)
    assert len(events_mode) > 1000
    assert abs(len(frames_mode) - len(events_mode)) <= 0.01 * len(events_mode)


def test_leaky_frames_beyond_the_limit_are_refused_up_front_naming_the_count():
    # Two events 1 s apart at 1e9 fps: 1,000,000,001 frames of 34 x 34 pixels (this ran for
    # ever); refused before any work, by a call and by a session's chunk alike.
    ev = torch.tensor([[0, 0, 0, 1], [1, 1, 1_000_000, 1]])
    pool = PhotocurrentPooling((34, 34, 2), 2, fps=1e9, cutoff_hz=10.0)
    with pytest.raises(ValueError, match=r"1,000,000,001 frames .* 1,156 pixels"):
        pool(ev)
    with pytest.raises(ValueError, match=r"frames .*max_output_events\(n\)"):
        pool.session()(ev)
    # Without a leak the cost follows the events: the same call is fine.
    assert len(PhotocurrentPooling((34, 34, 2), 2, fps=1e9)(ev)) == 0


def test_the_leaky_frame_limit_is_the_output_limit():
    # Events from 0 to 999 us at 1e6 fps: frames 0..999, 1,000 frames of 4 x 4 pixels.
    arr = np.array([(0, 0, True, 0), (1, 1, True, 300), (0, 0, True, 600), (1, 0, True, 999)],
                   dtype=DVS_DTYPE)
    pool = PhotocurrentPooling((4, 4, 2), 2, contrast=0.5, threshold=0.1, fps=1e6,
                               cutoff_hz=10.0)
    with max_output_events(15_999), pytest.raises(
        ValueError, match=r"1,000 frames .* 16,000 values, more than the limit of 15,999"
    ):
        pool(arr)
    expected = photocurrent_frames_reference(arr, (4, 4, 2), 2, 0.5, 0.1, 1e6, 10.0)
    with max_output_events(16_000):
        assert len(expected) > 3 and sorted(rows(pool(arr))) == expected
    with max_output_events(15_999), max_output_events(None):  # an inner block lifts it
        assert sorted(rows(pool(arr))) == expected


def test_frames_mode_float_timestamps(rng):
    arr = random_stream(rng, 300, SENSOR, t_max=20_000)
    as_float = torch.as_tensor(np.stack([arr["x"], arr["y"], arr["t"], arr["p"]], axis=1)
                               .astype(np.float64))
    pool = PhotocurrentPooling(SENSOR, factor=2, contrast=0.3, threshold=0.1, fps=1000.0)
    expected = photocurrent_frames_reference(arr, SENSOR, 2, 0.3, 0.1, 1000.0)
    out = pool(as_float)
    assert out.dtype == torch.float64
    # Float times are not rounded: each lies within half a tick of the integer result.
    got = sorted((int(x), int(y), float(t), bool(p > 0)) for x, y, t, p in out.tolist())
    assert len(got) == len(expected) > 20
    for (x, y, t, on), (ex, ey, et, eon) in zip(got, expected, strict=True):
        assert (x, y, on) == (ex, ey, eon) and abs(t - et) <= 0.5 + 1e-6


def test_frames_mode_with_whole_regions_matches_reference(rng):
    sensor = (8, 6, 2)  # the factor divides the sensor: no edge regions
    arr = random_stream(rng, 300, sensor, t_max=20_000)
    pool = PhotocurrentPooling(sensor, factor=2, contrast=0.3, threshold=0.15, fps=1000.0)
    expected = photocurrent_frames_reference(arr, sensor, 2, 0.3, 0.15, 1000.0)
    assert len(expected) > 20
    assert sorted(rows(pool(arr))) == expected


FRAME_POOLS = {
    "frames": PhotocurrentPooling(SENSOR, factor=(2, 3), contrast=0.3, threshold=0.1,
                                  fps=100_000.0),  # a frame every 10 us
    "frames_leak": PhotocurrentPooling(SENSOR, factor=2, contrast=0.3, threshold=0.1,
                                       fps=100_000.0, cutoff_hz=3000.0),  # 5 frames a chunk
}


@pytest.mark.parametrize("name", sorted(FRAME_POOLS))
@settings(max_examples=25, deadline=None, derandomize=True)
@given(case=chunkings)
def test_frames_mode_any_chunking_gives_the_batch_result(name, case):
    seed, n, fractions = case
    rng = np.random.default_rng(seed)
    arr = random_stream(rng, n, SENSOR, t_max=120)  # many equal timestamps and frame edges
    pool = FRAME_POOLS[name]
    cuts = [int(f * n) for f in fractions]
    np.testing.assert_array_equal(run_in_chunks(pool, arr, cuts), pool(arr))


@pytest.mark.parametrize("cutoff_hz", [0.0, 200.0])
def test_frames_session_emits_complete_frames_and_the_rest_at_flush(cutoff_hz, rng):
    arr, pool, expected = leaky_frames_case(rng, 400, 1000.0, cutoff_hz)
    session = pool.session()
    first = session(arr[:200])
    # Everything out so far belongs to frames before the chunk's last event (t_start + k ms).
    assert len(first) > 0 and first["t"].max() <= arr["t"][199]
    rest = session(arr[200:])
    tail = session.flush()
    assert len(tail) > 0  # the last frame waits for the end of the stream
    assert sorted(rows(np.concatenate([first, rest, tail]))) == expected
    assert session.flush().num_events == 0  # a flushed session starts afresh


@pytest.mark.parametrize("cutoff_hz", [0.0, 3000.0])
def test_frames_session_with_float_timestamps(cutoff_hz, rng):
    arr = random_stream(rng, 500, SENSOR, t_max=300)
    tensor = torch.as_tensor(np.stack([arr["x"], arr["y"], arr["t"] + 0.25, arr["p"]], axis=1)
                             .astype(np.float64))
    pool = PhotocurrentPooling(SENSOR, factor=2, contrast=0.3, threshold=0.1, fps=100_000.0,
                               cutoff_hz=cutoff_hz)
    session = pool.session()
    parts = [session(tensor[a:b]) for a, b in ((0, 120), (120, 121), (121, 121), (121, 500))]
    streamed = torch.cat([*parts, session.flush()])
    batch = pool(tensor)
    assert batch.shape[0] > 20
    assert torch.equal(streamed, batch)
