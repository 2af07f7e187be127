"""A session refuses what would silently change its stream: chunks of another clock, even
empty ones, and a second call while one is still running (another thread)."""

from __future__ import annotations

import copy
import threading

import numpy as np
import pytest
import torch

from evdown_torch import (
    CubicEstimation,
    EventCount,
    LIFPooling,
    LinearEstimation,
    PhotocurrentPooling,
)
from evdown_torch.transforms._base import Streaming
from tests.helpers import DVS_DTYPE, FLOAT_DTYPE, random_stream

SENSOR = (6, 5, 2)

#: Methods whose flush can return events (the end decides them) and EventCount (causal).
WITH_AN_END = {
    "linear": LinearEstimation(SENSOR, 2, threshold=0.25, max_delay=5),
    "cubic": CubicEstimation(SENSOR, 2, threshold=0.25, max_delay=5),
    "lif": LIFPooling(SENSOR, 2, dt=5, weight=0.6),
    "photocurrent_frames": PhotocurrentPooling(SENSOR, 2, fps=1e5, cutoff_hz=10.0),
    "event_count": EventCount(SENSOR, 2, threshold=0.5),
}


@pytest.mark.parametrize("name", sorted(WITH_AN_END))
def test_an_empty_chunk_of_another_time_dtype_is_refused_and_changes_nothing(name, rng):
    transform = WITH_AN_END[name]
    ev = random_stream(rng, 60, SENSOR, t_max=200)
    session = transform.session()
    head = session(ev[:30])
    with pytest.raises(ValueError, match="timestamps are torch.float64 but the stream's are "
                                         "torch.int64"):
        session(ev.astype(FLOAT_DTYPE)[:0])
    with pytest.raises(ValueError, match="timestamps are torch.float64"):
        session(torch.zeros((0, 4), dtype=torch.float64))
    tail = session.flush()
    assert tail.dtype == DVS_DTYPE  # the stream's own kind, int64 timestamps
    rest = transform.session()
    whole = np.concatenate([head, tail])
    np.testing.assert_array_equal(
        whole, np.concatenate([rest(ev[:30]), rest.flush()]))


def test_an_empty_chunk_of_the_streams_own_kind_is_fine_and_one_before_any_event_too(rng):
    ev = random_stream(rng, 40, SENSOR, t_max=200)
    transform = WITH_AN_END["linear"]
    session = transform.session()
    assert len(session(ev.astype(FLOAT_DTYPE)[:0])) == 0  # no stream yet: nothing to break
    out = [session(ev[:20]), session(ev[:0]), session(ev[20:]), session.flush()]
    assert out[-1].dtype == DVS_DTYPE
    np.testing.assert_array_equal(np.concatenate(out), transform(ev))


def _blocking_stream(monkeypatch, entered: threading.Event, release: threading.Event) -> None:
    """Make every transform's ``stream`` wait for ``release`` once it has ``entered``."""
    real = Streaming.stream

    def stream(self, events, state):
        entered.set()
        assert release.wait(timeout=30)
        return real(self, events, state)

    monkeypatch.setattr(Streaming, "stream", stream)


@pytest.mark.parametrize("second", ["call", "flush", "reset"])
def test_a_second_thread_entering_a_busy_session_is_refused(second, monkeypatch, rng):
    transform = LIFPooling(SENSOR, 2, dt=5, weight=0.6)
    ev = random_stream(rng, 80, SENSOR, t_max=400)
    session = transform.session()
    session(ev[:10])
    entered, release = threading.Event(), threading.Event()
    _blocking_stream(monkeypatch, entered, release)
    first: dict[str, object] = {}
    worker = threading.Thread(target=lambda: first.setdefault("out", session(ev[10:50])))
    worker.start()
    try:
        assert entered.wait(timeout=30)  # the first call is inside the method's step
        action = {"call": lambda: session(ev[50:]), "flush": session.flush,
                  "reset": session.reset}[second]
        with pytest.raises(RuntimeError, match="session is already in use.*own session"):
            action()
    finally:
        release.set()
        worker.join(timeout=60)
    monkeypatch.undo()
    # The refused call changed nothing: the stream goes on as if it had never been made.
    out = np.concatenate([first["out"], session(ev[50:]), session.flush()])
    expected = transform.session()
    head = expected(ev[:10])
    np.testing.assert_array_equal(np.concatenate([head, out]), transform(ev))


def test_a_session_is_free_again_after_an_error_and_copies_have_their_own_guard(rng):
    transform = LinearEstimation(SENSOR, 2, threshold=0.25, max_delay=5)
    ev = random_stream(rng, 50, SENSOR, t_max=300)
    session = transform.session()
    head = session(ev[:25])
    with pytest.raises(ValueError):
        session(ev[:5])  # back in time: refused, and the guard is released
    twin = copy.deepcopy(session)  # a copy continues the stream on its own
    outputs = []
    for branch in (session, twin):
        outputs.append(np.concatenate([head, branch(ev[25:]), branch.flush()]))
    for out in outputs:
        np.testing.assert_array_equal(out, transform(ev))
