"""The one output limit: a context variable, so a limit is per thread, nests and restores."""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

import evdown_torch
from evdown_torch import (
    Chain,
    Downsample,
    EventCount,
    EventFunnelling,
    LIFPooling,
    TemporalFunnelling,
    max_output_events,
    output_limit,
)
from evdown_torch.checks import DEFAULT_MAX_OUTPUT_EVENTS
from evdown_torch.transforms.thinning import ThinnedDownsample
from tests.helpers import DVS_DTYPE, random_stream, run_in_threads

# Factor 1 at threshold 1: EventCount copies its input, so the output count is the input's.
COPY = EventCount((8, 8, 2), 1, threshold=1.0)


def test_the_default_holds_outside_any_block():
    assert output_limit() == DEFAULT_MAX_OUTPUT_EVENTS == 100_000_000


def test_blocks_nest_and_restore_the_previous_limit_however_they_end():
    with max_output_events(500) as limit:
        assert limit == output_limit() == 500
        with max_output_events(None):
            assert output_limit() is None
            with max_output_events(7):
                assert output_limit() == 7
            assert output_limit() is None
        assert output_limit() == 500
        with pytest.raises(RuntimeError), max_output_events(3):
            raise RuntimeError("leaves the block")
        assert output_limit() == 500
    assert output_limit() == DEFAULT_MAX_OUTPUT_EVENTS


def test_the_limit_is_enforced_with_an_error_naming_the_count_and_the_limit():
    ev = random_stream(np.random.default_rng(0), 300, (8, 8, 2))
    with max_output_events(299), pytest.raises(
        ValueError, match=r"at least 300 events, more than the limit of 299.*max_output_events"
    ):
        COPY(ev)
    with max_output_events(300):
        assert len(COPY(ev)) == 300


def test_a_limit_set_in_one_thread_does_not_apply_in_another():
    ev = random_stream(np.random.default_rng(1), 200, (8, 8, 2))
    inside, entered, checked = {}, threading.Event(), threading.Event()

    def strict() -> None:  # holds a limit of 10 while the other thread runs
        with max_output_events(10):
            entered.set()
            checked.wait(timeout=30)
            inside["limit"] = output_limit()
            try:
                COPY(ev)
            except ValueError as error:
                inside["error"] = str(error)

    def free() -> None:  # runs while the strict thread is inside its block
        entered.wait(timeout=30)
        inside["other_limit"] = output_limit()
        inside["other_count"] = len(COPY(ev))
        checked.set()

    run_in_threads(strict, free)
    assert inside["other_limit"] == DEFAULT_MAX_OUTPUT_EVENTS
    assert inside["other_count"] == 200
    assert inside["limit"] == 10
    assert "at least 200 events, more than the limit of 10" in inside["error"]
    assert output_limit() == DEFAULT_MAX_OUTPUT_EVENTS  # this thread: untouched


def test_the_limit_counts_a_batch_as_a_whole_and_a_session_chunk_by_chunk():
    a, b = (random_stream(np.random.default_rng(s), 60, (8, 8, 2)) for s in (2, 3))
    with max_output_events(100):
        assert [len(out) for out in COPY.batch([a[:50], b[:50]])] == [50, 50]
        with pytest.raises(ValueError, match="at least 120 events"):
            COPY.batch([a, b])
        whole = random_stream(np.random.default_rng(4), 120, (8, 8, 2))
        session = COPY.session()
        assert [len(session(chunk)) for chunk in (whole[:60], whole[60:])] == [60, 60]


def test_lif_pooling_obeys_the_same_limit_in_calls_and_sessions():
    # No leak, reset "none", weight above threshold: the neuron fires at every step of the
    # 1000-step silence (1001 spikes in all, counted before they are built).
    arr = np.array([(0, 0, True, 0), (0, 0, True, 1000)], dtype=DVS_DTYPE)
    pool = LIFPooling((4, 4, 2), 2, dt=1, tau=math.inf, weight=1.5, reset_mechanism="none")
    assert len(pool(arr)) == 1001
    with max_output_events(1000):
        with pytest.raises(ValueError, match="at least 1,001 events"):
            pool(arr)
        session = pool.session()
        assert len(session(arr[:1])) == 0
        with max_output_events(999), pytest.raises(ValueError, match="at least 1,000 events"):
            session(arr[1:])
        assert len(session(arr[1:])) == 1000  # the session is unchanged by the refusal
        assert len(session.flush()) == 1


@pytest.mark.parametrize(("limit", "error"), [(0, ValueError), (-5, ValueError),
                                              (1.5, TypeError), ("10", TypeError)])
def test_a_bad_limit_is_refused_before_the_block(limit, error):
    with pytest.raises(error, match="max_output_events must be a positive integer"):
        max_output_events(limit)
    assert output_limit() == DEFAULT_MAX_OUTPUT_EVENTS


def test_the_old_setter_warns_and_sets_this_threads_limit_only():
    def run() -> None:
        with pytest.warns(DeprecationWarning, match="max_output_events"):
            assert evdown_torch.set_max_output_events(42) == DEFAULT_MAX_OUTPUT_EVENTS
        seen.append(output_limit())

    seen: list[int | None] = []
    thread = threading.Thread(target=run)
    thread.start()
    thread.join(timeout=60)
    assert seen == [42]
    assert output_limit() == DEFAULT_MAX_OUTPUT_EVENTS


def test_the_old_setters_return_value_restores_no_limit_too():
    with max_output_events(None), pytest.warns(DeprecationWarning):
        previous = evdown_torch.set_max_output_events(5)
        assert previous is None and output_limit() == 5
        assert evdown_torch.set_max_output_events(previous) == 5
        assert output_limit() is None  # "no limit" back, not the default


# Methods whose output is at most their input: with 40 distinct events (no repeats, one per
# time bin) each keeps every one, so a limit of 39 must refuse every way of calling them.
KEEP_ALL = {
    "downsample": Downsample((8, 8, 2), 2),
    "funnelling": EventFunnelling((8, 8, 2), 2),
    "temporal": TemporalFunnelling(dt=1, sensor_size=(8, 8, 2)),
    "thinned": ThinnedDownsample((8, 8, 2), 2, keep=0.999999, seed=3),
    "chain": Chain(TemporalFunnelling(dt=1), Downsample((8, 8, 2), 2)),
}


def _distinct(n: int, seed: int, shuffled: bool = False) -> np.ndarray:
    events = np.zeros(n, DVS_DTYPE)
    generator = np.random.default_rng(seed)
    events["x"], events["y"] = generator.integers(0, 8, n), generator.integers(0, 8, n)
    events["p"], events["t"] = generator.random(n) < 0.5, np.arange(n) * 10
    return generator.permutation(events) if shuffled else events


@pytest.mark.parametrize("name", sorted(KEEP_ALL))
def test_methods_that_keep_their_input_obey_the_limit_too(name):
    transform = KEEP_ALL[name]
    one, other = _distinct(40, 1), _distinct(40, 2, shuffled=True)
    assert len(transform(one)) == 40  # what the limits below are measured against
    with max_output_events(40):
        assert len(transform(one)) == 40
    with max_output_events(39):
        for call in (lambda: transform(one), lambda: transform(other)):
            with pytest.raises(ValueError, match="at least 40 events, more than the limit of 39"):
                call()
    with max_output_events(79):  # a batch counts as a whole, in order or not
        for batch in ([one, one], [one, other]):
            with pytest.raises(ValueError, match="at least 80 events"):
                transform.batch(batch)
    if name == "thinned":
        return  # no session: its draws are seeded by the whole recording
    session = transform.session()
    later = _distinct(40, 3)
    later["t"] += 1000  # after the first chunk
    with max_output_events(39):
        assert len(session(one[:39])) == 39
        with pytest.raises(ValueError, match="at least 40 events"):
            session(later)
        assert len(session(later[:39])) == 39  # the refused chunk changed nothing
