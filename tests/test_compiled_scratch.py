"""The scratch columns the compiled edge reuses: reused only where nothing else holds them."""

from __future__ import annotations

import threading
import weakref
from fractions import Fraction
from unittest import mock

import numpy as np
import pytest
import torch

import evdown_torch
from evdown_torch import Downsample, eager_kernels
from evdown_torch.events import Events, to_events
from evdown_torch.transforms.functional.compiled import numba_available, scratch
from evdown_torch.transforms.functional.compiled.scratch import LARGEST_KEPT, scratch_column
from evdown_torch.transforms.registry import make_method
from tests.helpers import random_stream

SENSOR = (34, 34, 2)


def _address(column: np.ndarray) -> int:
    return column.__array_interface__["data"][0]


def test_a_column_no_one_holds_is_reused() -> None:
    first = scratch_column("test reuse", 1000, np.int64)
    address = _address(first)
    del first
    again = scratch_column("test reuse", 600, np.int64)
    assert _address(again) == address and again.shape == (600,) and again.dtype == np.int64
    del again
    # Longer than the kept one: new memory.
    assert scratch_column("test reuse", 2000, np.int64).shape == (2000,)


@pytest.mark.parametrize("holder", ["view", "tensor", "tensor view", "list"])
def test_a_held_column_is_never_overwritten(holder: str) -> None:
    column = scratch_column(f"test held {holder}", 100, np.int64)
    column[:] = np.arange(100)
    held: object
    if holder == "view":
        held = column[10:20]
    elif holder == "tensor":
        held = torch.from_numpy(column)
    elif holder == "tensor view":
        held = torch.from_numpy(column)[::3]
    else:
        held = [column]

    def values() -> np.ndarray:
        if isinstance(held, torch.Tensor):
            return held.numpy().copy()
        return np.array(held[0] if isinstance(held, list) else held)

    expected = values()
    del column
    for _ in range(3):  # each call must take other memory while ``held`` lives
        other = scratch_column(f"test held {holder}", 100, np.int64)
        other[:] = -1
    np.testing.assert_array_equal(values(), expected)


def test_slots_and_dtypes_do_not_share() -> None:
    a = scratch_column("test slot a", 50, np.int64)
    b = scratch_column("test slot b", 50, np.int64)
    c = scratch_column("test slot a", 50, np.float64)
    assert not np.shares_memory(a, b) and not np.shares_memory(a, c)


def test_large_columns_are_not_kept() -> None:
    small = scratch_column("test large", 10, np.int64)
    address = _address(small)
    del small
    large = scratch_column("test large", LARGEST_KEPT // 8 + 1, np.int64)
    assert _address(large) != address  # the small one is not long enough
    del large
    # The large one neither replaced the kept one nor is kept itself.
    assert _address(scratch_column("test large", 10, np.int64)) == address


def test_each_thread_keeps_its_own() -> None:
    mine = scratch_column("test thread", 64, np.int64)
    address = _address(mine)
    del mine  # kept by this thread, held by no one
    theirs: list[int] = []
    thread = threading.Thread(
        target=lambda: theirs.append(_address(scratch_column("test thread", 64, np.int64))))
    thread.start()
    thread.join()
    assert theirs[0] != address
    assert _address(scratch_column("test thread", 64, np.int64)) == address


@pytest.mark.skipif(not numba_available(), reason="the compiled edge needs numba")
def test_events_read_from_arrays_stay_intact_while_held() -> None:
    """Events a user keeps from ``to_events`` are not overwritten by later reads."""
    chunks = [random_stream(np.random.default_rng(seed), 5000, SENSOR, t_max=10**6)
              for seed in range(6)]
    kept = [to_events(chunk, SENSOR)[0] for chunk in chunks]
    for chunk, events in zip(chunks, kept, strict=True):
        np.testing.assert_array_equal(events.x.numpy(), chunk["x"].astype(np.int64))
        np.testing.assert_array_equal(events.y.numpy(), chunk["y"].astype(np.int64))
        np.testing.assert_array_equal(events.t.numpy(), chunk["t"])
        np.testing.assert_array_equal(events.p.numpy(), chunk["p"])


def _event_chunks(seed: int, chunks: int = 6, n: int = 3000) -> list[Events]:
    """``Events`` chunks of one time-ordered stream on 34 x 34 (returned as ``Events``)."""
    stream = random_stream(np.random.default_rng(seed), chunks * n, SENSOR, t_max=10**6)
    return [to_events(stream[k * n:(k + 1) * n])[0] for k in range(chunks)]


def _columns(events: Events) -> list[np.ndarray]:
    return [column.numpy().copy() for column in (events.x, events.y, events.t, events.p)]


@pytest.mark.skipif(not numba_available(), reason="the compiled kernels need numba")
def test_downsample_outputs_held_by_the_caller_stay_intact() -> None:
    # With Events chunks, Downsample's output columns are scratch columns handed to the
    # caller: each held output must still be its own chunk divided by the factor.
    chunks = _event_chunks(1)
    session = Downsample(SENSOR, 4).session()
    held = [session(chunk) for chunk in chunks]
    for chunk, out in zip(chunks, held, strict=True):
        assert isinstance(out, Events)
        x, y, t, p = _columns(chunk)
        for got, want in zip(_columns(out), (x // 4, y // 4, t, p), strict=True):
            np.testing.assert_array_equal(got, want)


@pytest.mark.skipif(not numba_available(), reason="the compiled kernels need numba")
@pytest.mark.parametrize("method", ["event_count", "funnelling", "photocurrent"])
def test_outputs_held_by_the_caller_match_the_eager_session(method: str) -> None:
    # Their outputs (crossings, kept events) come from scratch columns too: held chunk after
    # chunk, they must equal the eager kernels' session, which takes none.
    chunks = _event_chunks(2)
    compiled = make_method(method, SENSOR, 4).session()
    held = [compiled(chunk) for chunk in chunks]
    with eager_kernels():
        eager = make_method(method, SENSOR, 4).session()
        expected = [eager(chunk) for chunk in chunks]
    assert sum(out.num_events for out in held if isinstance(out, Events)) > 0
    for out, want in zip(held, expected, strict=True):
        assert isinstance(out, Events) and isinstance(want, Events)
        for got, column in zip(_columns(out), _columns(want), strict=True):
            np.testing.assert_array_equal(got, column)


def _window(seed: int, n: int = 4000) -> tuple[Events, torch.Tensor]:
    """Knot events of a window on 34 x 34 in time order, and their level changes."""
    events = to_events(random_stream(np.random.default_rng(seed), n, SENSOR, t_max=10**6))[0]
    change = torch.where(events.p, 1, -1).to(torch.int64)
    return events, change


def _solve_window(events: Events, change: torch.Tensor,
                  cubic: bool) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    from evdown_torch.transforms.functional.compiled.estimation import estimation_window

    found = estimation_window(
        events.x, events.y, events.t, change, t_start=events.t[0], t_end=events.t[-1],
        sensor_size=SENSOR, factor=(4, 4), out_size=(9, 9), fraction=Fraction(1, 2),
        resume_cut=None, resume_q=None, resume_returned=None, next_cut=None,
        chunk_events=1 << 17, cubic=cubic, front_at_rest=False)
    assert found is not None
    region, t, on, _, _ = found
    return region, t, on


def _kept(slot: str, dtype: type) -> np.ndarray:
    return scratch._KEPT.columns[(slot, np.dtype(dtype))]


@pytest.mark.skipif(not numba_available(), reason="the compiled kernels need numba")
@pytest.mark.parametrize("cubic", [False, True])
def test_window_outputs_held_stay_intact_and_equal_fresh_memory(cubic: bool) -> None:
    # The window loop's grouping and outputs are scratch columns: outputs a caller holds
    # must survive later windows, and every window must give what it gives in fresh memory.
    from evdown_torch.transforms.functional.compiled.cubic import addcmul_is_fused

    if cubic and addcmul_is_fused() is None:
        pytest.skip("this torch's addcmul rounds neither way: no compiled cubic loop")
    windows = [_window(seed) for seed in range(4)]
    with mock.patch.object(scratch, "LARGEST_KEPT", -1):  # every column new
        expected = [[c.clone() for c in _solve_window(*w, cubic)] for w in windows]
    held = [_solve_window(*w, cubic) for w in windows]
    assert sum(out[0].shape[0] for out in expected) > 0
    for got, want in zip(held, expected, strict=True):
        for column, reference in zip(got, want, strict=True):
            assert torch.equal(column, reference)


@pytest.mark.skipif(not numba_available(), reason="the compiled kernels need numba")
def test_a_window_reuses_the_last_windows_memory_once_dropped() -> None:
    events, change = _window(7)
    for _ in range(2):  # outputs dropped at once (the first call may compile the loop, and
        _solve_window(events, change, cubic=False)  # Numba may hold its arguments a while)
    grouping, outputs = _address(_kept("window 0", np.int64)), _address(_kept("window 4", np.int64))
    region, _, _ = _solve_window(events, change, cubic=False)
    assert _address(_kept("window 0", np.int64)) == grouping
    assert _address(region.numpy()) == outputs
    held = region.clone()
    _solve_window(*_window(8), cubic=False)  # ``region`` is held: new outputs' memory
    assert torch.equal(region, held)


@pytest.mark.skipif(not numba_available(), reason="the compiled kernels need numba")
def test_next_knots_held_stay_intact_and_reuse_the_loop_columns() -> None:
    from evdown_torch.transforms.functional.compiled.estimation_window import next_knots

    def knots(seed: int) -> tuple[Events, torch.Tensor]:
        events, change = _window(seed)
        return next_knots(events, change, before=events.t[events.num_events // 2], keep=2,
                          width=SENSOR[0])

    first, first_change = knots(1)
    expected = _columns(first) + [first_change.numpy().copy()]
    knots(2)  # (the first call may compile the loop, and Numba may hold its arguments a while)
    loop_columns = _address(_kept("next knots 0", np.int64))
    for seed in range(3, 6):
        knots(seed)
        assert _address(_kept("next knots 0", np.int64)) == loop_columns  # the same memory
    for got, want in zip(_columns(first) + [first_change.numpy()], expected, strict=True):
        np.testing.assert_array_equal(got, want)


def test_a_thread_keeps_at_most_most_kept_bytes() -> None:
    before = scratch.kept_bytes()
    with mock.patch.object(scratch, "MOST_KEPT", before + 3 * 8000):
        for k in range(3):  # three new slots of 8,000 bytes: kept
            scratch_column(f"test most kept {k}", 1000, np.int64)
        assert scratch.kept_bytes() == before + 24_000
        # A fourth slot would go past the limit: new memory every call, nothing kept.
        assert scratch_column("test most kept 3", 1000, np.int64).shape == (1000,)
        assert ("test most kept 3", np.dtype(np.int64)) not in scratch._KEPT.columns
        assert scratch.kept_bytes() == before + 24_000
        # A kept slot asked for a longer column than the limit allows keeps its last one.
        kept = _address(_kept("test most kept 0", np.int64))
        longer = scratch_column("test most kept 0", 2000, np.int64)
        assert longer.shape == (2000,) and _address(longer) != kept
        assert _address(_kept("test most kept 0", np.int64)) == kept
        assert scratch.kept_bytes() == before + 24_000
        del longer
        # Still reused where it is long enough.
        assert _address(scratch_column("test most kept 0", 500, np.int64)) == kept


def test_release_scratch_frees_the_threads_columns_and_keeps_held_ones() -> None:
    # Two kept columns: one that no one holds, one a caller still holds a view of.
    free = scratch_column("test release free", 1000, np.int64)
    held = scratch_column("test release held", 1000, np.int64)
    held[:] = np.arange(1000)
    view = held[5:10]
    del free, held
    free_ref = weakref.ref(_kept("test release free", np.int64))
    held_ref = weakref.ref(_kept("test release held", np.int64))
    before = scratch.kept_bytes()
    assert before >= 16_000
    assert evdown_torch.release_scratch() == before
    assert scratch.kept_bytes() == 0 and not scratch._KEPT.columns
    assert free_ref() is None  # its memory is gone
    assert held_ref() is not None  # still held through the view: alive and intact
    assert view.tolist() == [5, 6, 7, 8, 9]
    # The slot takes a new column; the held one is never handed out again.
    again = scratch_column("test release held", 1000, np.int64)
    again[:] = -1
    assert not np.shares_memory(again, view) and view.tolist() == [5, 6, 7, 8, 9]
    assert scratch.kept_bytes() == 8000
    del view
    assert held_ref() is None
    assert evdown_torch.release_scratch() == 8000


def test_release_scratch_leaves_other_threads_columns() -> None:
    mine = scratch_column("test release thread", 64, np.int64)
    address = _address(mine)
    del mine
    released: list[int] = []

    def other() -> None:
        scratch_column("test release other", 32, np.int64)
        released.append(evdown_torch.release_scratch())

    thread = threading.Thread(target=other)
    thread.start()
    thread.join()
    assert released == [256]  # only the other thread's own column
    assert _address(scratch_column("test release thread", 64, np.int64)) == address


@pytest.mark.skipif(not numba_available(), reason="the compiled kernels need numba")
def test_outputs_held_across_release_scratch_stay_intact() -> None:
    chunks = _event_chunks(3)
    session = Downsample(SENSOR, 4).session()
    held = []
    for chunk in chunks:
        held.append(session(chunk))
        evdown_torch.release_scratch()  # between every two chunks
    for chunk, out in zip(chunks, held, strict=True):
        assert isinstance(out, Events)
        x, y, t, p = _columns(chunk)
        for got, want in zip(_columns(out), (x // 4, y // 4, t, p), strict=True):
            np.testing.assert_array_equal(got, want)


def test_a_kept_map_comes_back_as_the_last_call_left_it() -> None:
    with scratch.kept_map("test map", 6, np.int64) as first:
        assert first.tolist() == [0] * 6  # a new map is zeros
        first[[1, 4]] = [3, 5]
        address = _address(first)
    with scratch.kept_map("test map", 6, np.int64) as again:
        assert _address(again) == address and again.tolist() == [0, 3, 0, 0, 5, 0]
        # Nested, the slot's map is the outer body's alone: the inner one is new, zeros.
        with scratch.kept_map("test map", 6, np.int64) as inner:
            assert not np.shares_memory(inner, again) and not inner.any()
    # Another length or dtype is another map; the dtype is part of the slot.
    with scratch.kept_map("test map", 7, np.int64) as longer:
        assert not longer.any()
    with scratch.kept_map("test map", 6, np.float64) as floats:
        assert not floats.any()


def test_a_kept_map_whose_body_raised_is_not_handed_out_again() -> None:
    with scratch.kept_map("test map raised", 4, np.int64) as kept:
        kept[0] = 9
    with (pytest.raises(RuntimeError, match="half-way"),
          scratch.kept_map("test map raised", 4, np.int64) as broken):
        broken[2] = 1
        raise RuntimeError("half-way")
    with scratch.kept_map("test map raised", 4, np.int64) as fresh:
        assert not np.shares_memory(fresh, broken) and not fresh.any()


def test_kept_maps_count_in_the_threads_bytes_and_go_with_release_scratch() -> None:
    evdown_torch.release_scratch()
    large = (LARGEST_KEPT // 8) + 1  # kept, unlike a scratch column of this size
    with scratch.kept_map("test map bytes", large, np.int64):
        assert scratch.kept_bytes() == 0  # the body's, not the table's, meanwhile
    assert scratch.kept_bytes() == 8 * large
    with mock.patch.object(scratch, "MOST_KEPT", 8 * large + 100):
        with scratch.kept_map("test map other", 20, np.int64):
            pass  # 160 bytes more would pass the limit: not kept
        assert scratch.kept_bytes() == 8 * large
    assert evdown_torch.release_scratch() == 8 * large
    with scratch.kept_map("test map bytes", large, np.int64) as again:
        assert not again.any()


def test_each_thread_keeps_its_own_maps() -> None:
    with scratch.kept_map("test map thread", 3, np.int64) as mine:
        mine[0] = 1
    seen: list[list[int]] = []

    def other() -> None:
        for _ in range(2):
            with scratch.kept_map("test map thread", 3, np.int64) as theirs:
                seen.append(theirs.tolist())
                theirs[1] += 5

    thread = threading.Thread(target=other)
    thread.start()
    thread.join()
    assert seen == [[0, 0, 0], [0, 5, 0]]  # a new map in that thread, kept there
    with scratch.kept_map("test map thread", 3, np.int64) as again:
        assert again.tolist() == [1, 0, 0]  # this thread's, untouched
