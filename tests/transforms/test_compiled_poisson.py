"""PoissonSubsampling's compiled loop (transforms/functional/compiled/poisson.py): the eager
kernel's events and states, chunk by chunk, and its doubt."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evdown_torch import Events, PoissonSubsampling
from evdown_torch.events import sort_by_time, to_events
from evdown_torch.transforms.functional import poisson as poisson_kernel
from evdown_torch.transforms.functional.compiled import eager_kernels
from evdown_torch.transforms.functional.draws import event_uniforms
from tests.helpers import (
    DVS_DTYPE,
    FLOAT_DTYPE,
    argument_spy,
    assert_identical,
    both_paths,
    random_stream,
    run_in_chunks,
    run_switching_paths,
)

pytest.importorskip("numba")

SENSOR = (9, 7, 2)

CASES = [  # (t_max, t as float, window, alpha)
    (300, False, 13, 0.3),
    (5_000, False, 40, 0.05),
    (400, True, 7.5, 0.5),
    (2_000, False, 1_000, 0.2),  # one or two windows
    (3_000, False, 3, 1.0),  # windows without events between others
]


def _stream(rng, n: int, t_max: int, float_t: bool) -> np.ndarray:
    arr = random_stream(rng, n, SENSOR, t_max=t_max, dtype=FLOAT_DTYPE if float_t else DVS_DTYPE)
    if float_t:
        arr["t"] = arr["t"] * 0.37
    return arr


@pytest.mark.parametrize(("t_max", "float_t", "window", "alpha"), CASES)
def test_every_chunking_keeps_the_eager_kernels_events(t_max, float_t, window, alpha, rng,
                                                       monkeypatch):
    arr = _stream(rng, 1_500, t_max, float_t)
    transform = PoissonSubsampling(SENSOR, (2, 3), window=window, alpha=alpha, seed=4)
    steps = []
    real = poisson_kernel._compiled_step
    monkeypatch.setattr(poisson_kernel, "_compiled_step",
                        lambda *args: steps.append(real(*args)) or steps[-1])
    whole = both_paths(lambda: transform(arr))
    assert_identical(*whole)
    assert 0 < len(whole[0]) < len(arr)
    for cuts in ([1, 2, 700, 701], list(range(0, 1_500, 97)), []):
        assert_identical(*both_paths(lambda cuts=cuts: run_in_chunks(transform, arr, cuts)))
    assert steps and all(step is not None for step in steps)  # the loop decided every chunk


@pytest.mark.parametrize(("t_max", "float_t", "window", "alpha"), CASES)
def test_each_step_leaves_the_eager_kernels_state(t_max, float_t, window, alpha, rng):
    events = sort_by_time(to_events(_stream(rng, 1_200, t_max, float_t), SENSOR)[0])
    settings = poisson_kernel.PoissonSettings(SENSOR, (2, 3), window, alpha, 4)

    def steps():
        state = poisson_kernel.poisson_init(settings, events)
        outputs = []
        for start, stop in ((0, 1), (1, 400), (400, 401), (401, 1_200)):
            out, state = poisson_kernel.poisson_step(events.part(start, stop), state, settings)
            outputs.append((out, torch.tensor([state.seen, state.kept]), state.windows,
                            state.keys, state.counts))
        return outputs

    assert_identical(*both_paths(steps))


def test_a_state_moves_between_the_paths(rng):
    arr = random_stream(rng, 2_000, SENSOR, t_max=3_000)
    transform = PoissonSubsampling(SENSOR, (2, 3), window=50, alpha=0.2, seed=2)
    expected = both_paths(lambda: transform(arr))[1]
    for eager_first in (False, True):
        got = run_switching_paths(transform, arr, [500, 1_200, 1_600], eager_first=eager_first)
        np.testing.assert_array_equal(got, expected)


def test_a_draw_near_its_probability_hands_the_call_to_the_eager_kernel(monkeypatch):
    """In the first window P = alpha: an alpha 1e-14 above the first event's draw is within
    the paths' roundings, so the eager kernel decides the call."""
    events = Events.from_columns([3, 4, 5], [2, 2, 2], [10, 20, 30], [1, 0, 1])
    draws = event_uniforms(events, 0, index=torch.arange(3), origin=10)
    alpha = draws[0].item() * (1 + 1e-14)
    assert 1e-6 <= alpha <= 1
    settings = poisson_kernel.PoissonSettings(SENSOR, (2, 3), 1_000, alpha, 0)
    assert poisson_kernel._compiled_step(events, poisson_kernel.poisson_init(settings, events),
                                         settings) is None
    eager_steps = argument_spy(monkeypatch, poisson_kernel, "_step_sorted")
    transform = PoissonSubsampling(SENSOR, (2, 3), window=1_000, alpha=alpha)
    got = transform(events)
    assert len(eager_steps) == 1
    with eager_kernels():
        assert_identical(got, transform(events))


def test_an_event_outside_the_sensor_is_refused():
    events = Events.from_columns([3, 2], [2, 7], [10, 20], [1, 0])  # y = 7 on a 7-high sensor
    settings = poisson_kernel.PoissonSettings(SENSOR, (2, 3), 13, 0.5, 0)
    with pytest.raises(ValueError, match="y"):
        poisson_kernel._compiled_step(events, poisson_kernel.poisson_init(settings, events),
                                      settings)


def _poisson_maps() -> dict[str, np.ndarray]:
    from evdown_torch.transforms.functional.compiled import scratch

    return {slot[0]: column for slot, column in scratch._KEPT.columns.items()
            if slot[0].startswith("map poisson")}


def test_the_kept_maps_are_zeros_between_calls_and_sessions_do_not_share_them(rng):
    """Two sessions whose chunks alternate in one thread share the kept per-pixel maps: each
    gives what it gives alone (the eager kernel's events), and between calls the counts and
    the blur are zeros again."""
    streams = [random_stream(rng, 1_500, SENSOR, t_max=2_000) for _ in range(2)]
    transforms = [PoissonSubsampling(SENSOR, (2, 3), window=w, alpha=a, seed=s)
                  for w, a, s in ((40, 0.3, 1), (13, 0.5, 2))]
    with eager_kernels():
        alone = [transform(arr) for transform, arr in zip(transforms, streams, strict=True)]
    sessions = [transform.session() for transform in transforms]
    outputs: list[list[np.ndarray]] = [[], []]
    for lo in range(0, 1_500, 250):
        for k in (0, 1):
            outputs[k].append(sessions[k](streams[k][lo:lo + 250]))
            maps = _poisson_maps()
            for name in ("current", "previous", "rows"):
                assert not maps[f"map poisson {name}"].any(), name
            stamp = maps["map poisson stamp"]
            assert stamp[-1] == stamp.max() > 0  # the last window's number, the largest
    for k in (0, 1):
        outputs[k].append(sessions[k].flush())
        np.testing.assert_array_equal(np.concatenate(outputs[k]), alone[k])


def test_a_call_that_stops_early_leaves_the_maps_as_the_next_call_needs(rng, monkeypatch):
    from evdown_torch.transforms.functional.compiled import poisson as compiled

    arr = random_stream(rng, 600, SENSOR, t_max=400)
    events = sort_by_time(to_events(arr, SENSOR)[0])
    settings = poisson_kernel.PoissonSettings(SENSOR, (2, 3), 13, 0.4, 3)
    state = poisson_kernel.poisson_init(settings, events)
    _, state = poisson_kernel.poisson_step(events.part(0, 300), state, settings)
    assert state.keys.numel() > 0  # the next call seeds its maps from these entries
    with monkeypatch.context() as patched:  # every event in doubt: the loop stops at once
        patched.setattr(compiled, "_doubt_bound", lambda: 1.0)
        assert poisson_kernel._compiled_step(events.part(300, 600), state, settings) is None
    maps = _poisson_maps()
    for name in ("current", "previous", "rows"):
        assert not maps[f"map poisson {name}"].any(), name
    # A refused chunk (y = 7 on a 7-high sensor) leaves them zeros too, and the next call
    # still gives the eager kernel's step.
    outside = Events.from_columns([3, 2], [2, 7], [500, 501], [1, 0])
    with pytest.raises(ValueError, match="y"):
        poisson_kernel._compiled_step(outside, state, settings)
    maps = _poisson_maps()
    for name in ("current", "previous", "rows"):
        assert not maps[f"map poisson {name}"].any(), name
    steps = both_paths(lambda: poisson_kernel.poisson_step(events.part(300, 600), state,
                                                           settings))
    assert_identical(steps[0][0], steps[1][0])
    for got, want in zip(steps[0][1], steps[1][1], strict=True):
        if isinstance(got, torch.Tensor):
            assert torch.equal(got, want)
        else:
            assert got == want


def test_a_window_s_keys_sorted_from_an_ordered_head_are_the_sort_of_all(rng):
    from evdown_torch.transforms.functional.compiled import poisson as compiled

    for _ in range(30):
        keys = rng.permutation(200)[:rng.integers(0, 60)].astype(np.int64)
        head = int(rng.integers(0, keys.shape[0] + 1))
        keys[:head] = np.sort(keys[:head])
        assert np.array_equal(compiled._sorted_after(keys, head), np.sort(keys))
    # A head out of order (a state not in the state's order) is sorted with the rest.
    keys = np.array([5, 3, 9, 1, 4], dtype=np.int64)
    assert compiled._sorted_after(keys, 3).tolist() == [1, 3, 4, 5, 9]
    assert compiled._sorted_after(keys[:2], 2).tolist() == [3, 5]


def test_a_session_merges_each_window_s_ordered_keys_without_sorting_them_again(rng,
                                                                                monkeypatch):
    """Chunks inside a window and across one window's end: each window's state keys come first
    and in order, so the merge never finds them out of order (no full sort again)."""
    from evdown_torch.transforms.functional.compiled import poisson as compiled

    merges = []
    real = compiled._merge_loop
    monkeypatch.setattr(compiled, "_merge_loop",
                        lambda head, tail, out: merges.append((head.shape[0],
                                                               real(head, tail, out)))
                        or merges[-1][1])
    arr = random_stream(rng, 3_000, SENSOR, t_max=3_000)
    transform = PoissonSubsampling(SENSOR, (2, 3), window=400, alpha=0.3, seed=5)
    session = transform.session()
    got = [session(arr[lo:lo + 100]) for lo in range(0, 3_000, 100)] + [session.flush()]
    with eager_kernels():
        np.testing.assert_array_equal(np.concatenate(got), transform(arr))
    assert len(merges) > 30 and all(ordered for _, ordered in merges)
    assert max(head for head, _ in merges) > 10
