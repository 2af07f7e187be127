"""LIFPooling's streaming session: any chunking gives exactly the batch events."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from evdown_torch import Events, LIFPooling
from tests.helpers import DVS_DTYPE, LIF_SETTINGS, bursty_stream, random_stream

SENSOR = (9, 7, 2)


def run_in_chunks(pool: LIFPooling, events, cuts: list[int]) -> list:
    """Outputs of a session fed ``events`` split at ``cuts`` (repeats: empty chunks), flush last."""
    session = pool.session()
    n = events.num_events if isinstance(events, Events) else len(events)
    bounds = [0, *sorted(cuts), n]
    if isinstance(events, Events):
        chunks = [events.select(torch.arange(a, b)) for a, b in zip(bounds, bounds[1:])]
    else:
        chunks = [events[a:b] for a, b in zip(bounds, bounds[1:])]
    return [session(chunk) for chunk in chunks] + [session.flush()]


def concat_events(parts: list[Events]) -> Events:
    return Events(*(torch.cat(column) for column in zip(*parts)))


def assert_same_events(got: Events, expected: Events) -> None:
    for name, a, b in zip(Events._fields, got, expected):
        assert torch.equal(a, b), name


cases = st.tuples(
    st.integers(0, len(LIF_SETTINGS) - 1),  # neuron settings
    st.integers(0, 2**32 - 1),  # stream seed
    st.integers(0, 250),  # number of events
    st.lists(st.floats(0, 1), max_size=12),  # cut positions as fractions of the stream
    st.booleans(),  # bursts with long silences (firing chains) or a dense stream
)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(case=cases, dt=st.sampled_from([1, 2.4, 4, 7.5, 30]), offset=st.sampled_from([0, 2**50]))
def test_any_chunking_of_integer_times_gives_the_batch_result(case, dt, offset):
    which, seed, n, fractions, bursty = case
    rng = np.random.default_rng(seed)
    if bursty:
        arr = bursty_stream(rng, max(1, n // 20), SENSOR, gap_max=120)
    else:
        arr = random_stream(rng, n, SENSOR, t_max=80)  # chunk boundaries inside steps
    arr["t"] += offset
    pool = LIFPooling(SENSOR, factor=(2, 3), dt=dt, **LIF_SETTINGS[which])
    cuts = [int(f * len(arr)) for f in fractions]
    got = np.concatenate(run_in_chunks(pool, arr, cuts))
    np.testing.assert_array_equal(got, pool(arr))


@settings(max_examples=60, deadline=None, derandomize=True)
@given(case=cases, dt=st.sampled_from([0.1, 0.37, 1.0, 2.5]), origin=st.sampled_from([0, 1e6]))
def test_any_chunking_of_float_times_gives_the_batch_result(case, dt, origin):
    which, seed, n, fractions, _ = case
    rng = np.random.default_rng(seed)
    t = np.sort(rng.random(n) * 20.0) + origin
    if seed % 3 == 0:
        t = np.round(t, 1)  # equal timestamps across chunk boundaries
    events = Events.from_columns(
        rng.integers(0, SENSOR[0], n), rng.integers(0, SENSOR[1], n), t, rng.random(n) < 0.5
    )
    pool = LIFPooling(SENSOR, factor=2, dt=dt, **LIF_SETTINGS[which])
    cuts = [int(f * n) for f in fractions]
    assert_same_events(concat_events(run_in_chunks(pool, events, cuts)), pool(events))


def test_hand_computed_session():
    # dt 10 from t = 0, no leak, weight 2.5, threshold 1, subtract reset: an input makes the
    # membrane 2.5 (spike), then 1.5 (spike, through an empty step), then 0.5.
    pool = LIFPooling((4, 4, 2), factor=2, dt=10, tau=math.inf, weight=2.5)
    a = np.array([(0, 0, True, 0)], dtype=DVS_DTYPE)  # block (0, 0), ON, step 0
    b = np.array([(2, 2, False, 15)], dtype=DVS_DTYPE)  # block (1, 1), OFF, step 1
    c = np.array([(3, 2, False, 31)], dtype=DVS_DTYPE)  # block (1, 1), OFF, step 3
    session = pool.session()
    assert session(a).tolist() == []  # step 0 still open
    assert session(b).tolist() == [(0, 0, True, 10)]  # step 0 closed at t = 15 >= 10
    assert session(b[:0]).tolist() == []
    # Steps 1 and 2 (their ends 20 and 30 <= 31): the chain of block (0, 0), block (1, 1)'s
    # spike at its input and one through the empty step 2; OFF before ON within a step.
    assert session(c).tolist() == [(1, 1, False, 20), (0, 0, True, 20), (1, 1, False, 30)]
    # Step 3 at the flush: 1.5 - 1 + 2.5 = 3 > 1, at min(40, t_end = 31).
    assert session.flush().tolist() == [(1, 1, False, 31)]
    assert pool(np.concatenate([a, b, c])).tolist() == [
        (0, 0, True, 10), (1, 1, False, 20), (0, 0, True, 20), (1, 1, False, 30),
        (1, 1, False, 31),
    ]


def test_a_chunk_returns_the_steps_it_closes():
    # One block, no leak, weight 0.6: two ON events in step 0 make 1.2 > 1.
    pool = LIFPooling((2, 2, 2), factor=2, dt=10, tau=math.inf, weight=0.6)
    session = pool.session()
    assert session(np.array([(0, 0, True, 3)], dtype=DVS_DTYPE)).tolist() == []  # t_start 3
    # t = 12 is still in step 0 ([3, 13)): the step may yet get input.
    assert session(np.array([(1, 1, True, 12)], dtype=DVS_DTYPE)).tolist() == []
    # t = 13 opens step 1: step 0 is closed, its spike at 3 + 10.
    assert session(np.array([(1, 0, False, 13)], dtype=DVS_DTYPE)).tolist() == [
        (0, 0, True, 13)
    ]
    assert session.flush().tolist() == []  # step 1: ON 1.2 - 1 = 0.2, OFF 0.6


def test_a_step_whose_rounded_end_is_reached_stays_open_until_it_closes():
    # Integer t, dt 2.4: step 0 is [0, 2.4) and its end rounds to t = 2, so a chunk ending
    # at t = 2 has reached the step's output time while the step can still get events at 2.
    pool = LIFPooling((2, 2, 2), factor=2, dt=2.4, tau=math.inf, weight=0.4)
    arr = np.array([(0, 0, True, 0), (1, 0, True, 2), (0, 1, True, 2)], dtype=DVS_DTYPE)
    session = pool.session()
    assert session(arr[:2]).tolist() == []
    assert session(arr[2:]).tolist() == []
    assert session.flush().tolist() == [(0, 0, True, 2)]  # 3 * 0.4 > 1 in step 0
    assert pool(arr).tolist() == [(0, 0, True, 2)]


def test_going_back_in_time_is_refused_and_the_session_stays_usable():
    rng = np.random.default_rng(5)
    arr = random_stream(rng, 120, SENSOR, t_max=90)
    pool = LIFPooling(SENSOR, factor=2, dt=6, tau=20.0, weight=0.7)
    session = pool.session()
    parts = [session(arr[:60])]
    with pytest.raises(ValueError, match="follow each other in time"):
        session(arr[:10])  # earlier than the first chunk's last event
    parts += [session(arr[60:]), session.flush()]
    np.testing.assert_array_equal(np.concatenate(parts), pool(arr))


def test_a_stream_is_a_pure_function_of_its_state():
    rng = np.random.default_rng(6)
    arr = random_stream(rng, 80, SENSOR, t_max=50)
    pool = LIFPooling(SENSOR, factor=2, dt=4, tau=30.0, weight=0.8)
    session = pool.session()
    session(arr[:40])
    state = session.state
    again = pool.session()
    again.state, again.last_t, again._fmt = state, session.last_t, session._fmt
    np.testing.assert_array_equal(session(arr[40:]), again(arr[40:]))  # state not modified
    np.testing.assert_array_equal(session.flush(), again.flush())


def test_flush_without_events_is_empty():
    pool = LIFPooling(SENSOR, factor=2)
    session = pool.session()
    assert session.flush().num_events == 0
    empty = np.zeros(0, dtype=DVS_DTYPE)
    assert len(session(empty)) == 0
    assert len(session.flush()) == 0
    # A session is reusable after a flush: the next chunk starts a new stream.
    rng = np.random.default_rng(7)
    arr = random_stream(rng, 50, SENSOR, t_max=40)
    np.testing.assert_array_equal(np.concatenate(run_in_chunks(pool, arr, [25])), pool(arr))


def test_one_step_streams_emit_at_the_end_only():
    # dt longer than the stream: every spike is in step 0, at t_end, decided by the flush.
    pool = LIFPooling(SENSOR, factor=2, dt=10**18, tau=math.inf, weight=1.5)
    rng = np.random.default_rng(8)
    arr = random_stream(rng, 40, SENSOR, t_max=1000)
    parts = run_in_chunks(pool, arr, [10, 20, 30])
    assert all(len(part) == 0 for part in parts[:-1])
    np.testing.assert_array_equal(parts[-1], pool(arr))


def test_a_session_stays_on_the_chunks_device(device):
    rng = np.random.default_rng(9)
    arr = random_stream(rng, 300, SENSOR, t_max=120)
    columns = [arr["x"], arr["y"], arr["t"], np.where(arr["p"], 1, -1)]
    data = torch.tensor(np.stack(columns, 1).astype(np.int64), device=device)
    pool = LIFPooling(SENSOR, factor=2, dt=5, tau=40.0, weight=0.5)
    session = pool.session()
    parts = [session(chunk) for chunk in torch.split(data, 45)] + [session.flush()]
    assert all(part.device == data.device for part in parts)
    assert torch.equal(torch.cat(parts), pool(data))


def test_a_chunk_the_steps_cannot_index_is_refused_and_the_session_stays_usable():
    pool = LIFPooling((2, 2, 2), factor=2, dt=1, tau=math.inf, weight=0.6)
    arr = np.array([(0, 0, True, 0), (1, 1, True, 0), (0, 1, True, 5)], dtype=DVS_DTYPE)
    far = np.array([(0, 0, True, 2**62)], dtype=DVS_DTYPE)
    session = pool.session()
    parts = [session(arr[:2])]
    with pytest.raises(ValueError, match="2\\*\\*62"):
        session(far)
    parts += [session(arr[2:]), session.flush()]
    assert np.concatenate(parts).tolist() == pool(arr).tolist() == [(0, 0, True, 1)]
