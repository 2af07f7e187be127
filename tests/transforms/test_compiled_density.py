"""DensitySubsampling's compiled loop (transforms/functional/compiled/density.py): the eager
kernel's events, counts against their definition, moves of the clock's origin, doubt."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from evdown_torch import DensitySubsampling, Events
from evdown_torch.events import sort_by_time, to_events
from evdown_torch.transforms.functional import density as density_kernel
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
from evdown_torch.transforms.functional.compiled import density as compiled  # noqa: E402

SENSOR = (9, 7, 2)


def _events(arr: np.ndarray) -> Events:
    return sort_by_time(to_events(arr, SENSOR)[0])


def _settings(tau: float, k: int, s: float, seed: int = 0) -> density_kernel.DensitySettings:
    return density_kernel.DensitySettings(SENSOR, (2, 3), tau, k, s, seed)


def _steps(events: Events, settings, cuts: list[int]):
    """The compiled step over ``events`` cut at ``cuts``: outputs and the last state."""
    state = density_kernel.density_init(settings, events)
    outputs = []
    for start, stop in zip([0, *cuts], [*cuts, events.num_events], strict=True):
        result = density_kernel._compiled_step(events.part(start, stop), state, settings)
        assert result is not None  # no event in doubt, no clock too wide
        out, state = result
        outputs.append(out)
    return Events.cat(outputs), state


def count_reference(events: Events, tau: float) -> dict[tuple[int, int, bool], tuple]:
    """Each pixel's decayed count after its last event, by the definition (a sum)."""
    by_pixel: dict[tuple[int, int, bool], list] = {}
    for x, y, t, p in zip(*(c.tolist() for c in events), strict=True):
        by_pixel.setdefault((x, y, p), []).append(t)
    return {key: (sum(math.exp(-(times[-1] - ti) / tau) for ti in times), times[-1])
            for key, times in by_pixel.items()}


CASES = [  # (t_max, t as float, tau, k, s)
    (300, False, 40.0, 3, 0.3),
    (5_000, False, 150.0, 5, 0.1),
    (400, True, 30.0, 7, 0.05),
    (10**6, False, 1.0, 5, 0.4),  # tau tiny against the span: the origin moves often
    (2_000, False, 2.0, 3, 0.2),  # events within and across 500 tau of each other
    (300, False, math.inf, 3, 0.02),  # no decay: counts of events
]


@pytest.mark.parametrize(("t_max", "float_t", "tau", "k", "s"), CASES)
def test_the_counts_after_a_chunk_are_their_definition(t_max, float_t, tau, k, s, rng):
    arr = random_stream(rng, 600, SENSOR, t_max=t_max, dtype=FLOAT_DTYPE if float_t else DVS_DTYPE)
    if float_t:
        arr["t"] = arr["t"] * 0.37
    events = _events(arr)
    settings = _settings(tau, k, s)
    _, state = _steps(events, settings, [250])
    width, height, r = density_kernel._padded(settings)
    expected = count_reference(events, tau)
    fired = np.flatnonzero(state.decayed.numpy())
    assert len(fired) == len(expected)
    for (x, y, p), (count, last) in expected.items():
        key = (int(p) * height + y + r) * width + x + r
        assert state.decayed[key].item() == pytest.approx(count, rel=1e-12)
        assert state.last_t[key].item() == last
    assert state.last_t.dtype == events.t.dtype and state.seen == events.num_events


@pytest.mark.parametrize(("t_max", "float_t", "tau", "k", "s"), CASES)
def test_every_chunking_keeps_the_eager_kernels_events(t_max, float_t, tau, k, s, rng):
    arr = random_stream(rng, 1_500, SENSOR, t_max=t_max,
                        dtype=FLOAT_DTYPE if float_t else DVS_DTYPE)
    if float_t:
        arr["t"] = arr["t"] * 0.37
    transform = DensitySubsampling(SENSOR, (2, 3), tau=tau, k=k, s=s, seed=5)
    whole = both_paths(lambda: transform(arr))
    assert_identical(*whole)
    assert 0 < len(whole[0]) < len(arr)
    for cuts in ([1, 2, 700, 701], list(range(0, 1_500, 97)), []):
        assert_identical(*both_paths(lambda cuts=cuts: run_in_chunks(transform, arr, cuts)))
    # The loop decided those chunks (it left none to the eager kernel).
    events = _events(arr)
    out, _ = _steps(events, _settings(tau, k, s, seed=5), [1, 2, 700, 701])
    assert_identical(out, to_events(whole[0], SENSOR)[0])


def test_a_state_moves_between_the_paths(rng):
    arr = random_stream(rng, 2_000, SENSOR, t_max=3_000)
    transform = DensitySubsampling(SENSOR, (2, 3), tau=200.0, k=5, s=0.1, seed=2)
    expected = both_paths(lambda: transform(arr))[1]
    for eager_first in (False, True):
        got = run_switching_paths(transform, arr, [500, 1_200, 1_600], eager_first=eager_first)
        np.testing.assert_array_equal(got, expected)


def test_a_draw_near_the_density_hands_the_call_to_the_eager_kernel(monkeypatch):
    """An event alone at its pixel (density 1) whose draw lies 1e-14 below ``s``: both paths
    keep it in exact arithmetic, but that is within their roundings, so the eager kernel
    decides the call."""
    events = Events.from_columns([3, 4], [2, 2], [10, 20], [1, 0])
    draws = event_uniforms(events, 0, index=torch.arange(2), origin=10)
    s = draws[1].item() * (1 + 1e-14)
    settings = _settings(100.0, 3, s)
    assert density_kernel._compiled_step(events, density_kernel.density_init(settings, events),
                                 settings) is None
    eager_steps = argument_spy(monkeypatch, density_kernel, "_step_sorted")
    transform = DensitySubsampling(SENSOR, (2, 3), tau=100.0, k=3, s=s)
    got = transform(events)
    assert len(eager_steps) == 1
    with eager_kernels():
        assert_identical(got, transform(events))
    assert 20 in got.t.tolist()


def test_an_event_outside_the_sensor_is_refused():
    events = Events.from_columns([3, 9], [2, 2], [10, 20], [1, 0])  # x = 9 on a 9-wide sensor
    settings = _settings(100.0, 3, 0.5)
    with pytest.raises(ValueError, match="x"):
        density_kernel._compiled_step(events, density_kernel.density_init(settings, events),
                                      settings)


def test_a_clock_near_the_int64_limits():
    """Timestamps near 2**62 go through the loop; a stream spanning 2**62 goes eagerly."""
    t = [2**62 + 7 * i for i in range(40)]
    events = Events.from_columns([i % 9 for i in range(40)], [i % 7 for i in range(40)], t,
                                 [i % 2 for i in range(40)])
    transform = DensitySubsampling(SENSOR, (2, 3), tau=20.0, k=5, s=0.3)
    assert_identical(*both_paths(lambda: transform(events)))
    settings = _settings(20.0, 5, 0.3)
    out, state = _steps(events, settings, [13])
    assert state.last_t.dtype == torch.int64 and int(state.last_t.max()) == t[-1]
    wide = Events.from_columns([1, 2], [1, 1], [-(2**61), 2**61 + 1], [1, 1])
    assert density_kernel._compiled_step(wide, density_kernel.density_init(settings, wide),
                                 settings) is None
    assert_identical(*both_paths(lambda: transform(wide)))


@pytest.mark.parametrize("by_rows", [False, True])
def test_the_doubt_bound_grows_with_the_call_and_stays_far_below_one_draw_in_a_million(by_rows):
    small = compiled._doubt_bound(10, 3, 1.0, by_rows)
    large = compiled._doubt_bound(250_000, 7, 1e4, by_rows)
    assert 0 < small < large < 1e-9


def test_a_chunk_is_summed_by_rows_where_making_every_row_sum_costs_less():
    # 2 k planes <= n (k^2 - 2 k): at k = 7, planes <= 2.5 n
    assert compiled._by_rows(1_000, 7, 2_500) and not compiled._by_rows(1_000, 7, 2_501)
    assert not compiled._by_rows(10**6, 1, 4)  # a 1 x 1 patch: nothing to save


LARGE = (60, 40, 2)
CUTS = [3, 40, 41, 300, 900]  # chunks of 1 to 600 events: patches from few to all


def _both_ways_alike(monkeypatch, rule, arr, settings):
    """The compiled steps of ``arr`` cut at CUTS with ``compiled.<rule>`` forced true, then
    false: the same events and the same states, bit for bit."""
    events = sort_by_time(to_events(arr, LARGE)[0])
    results = []
    for forced in (True, False):
        with monkeypatch.context() as patched:
            patched.setattr(compiled, rule, lambda *_, forced=forced: forced)
            state = density_kernel.density_init(settings, events)
            outputs = []
            for start, stop in zip([0, *CUTS], [*CUTS, events.num_events], strict=True):
                result = density_kernel._compiled_step(events.part(start, stop), state,
                                                       settings)
                assert result is not None
                outputs.append(result[0])
                state = result[1]
            results.append((Events.cat(outputs), state.decayed, state.last_t))
    assert_identical(results[0][0], results[1][0])
    assert torch.equal(results[0][1], results[1][1]) and torch.equal(results[0][2],
                                                                     results[1][2])


@pytest.mark.parametrize(("tau", "k"), [(150.0, 5), (1.0, 3), (math.inf, 7)])
def test_scaling_the_patches_only_gives_the_whole_sensors_steps_bit_for_bit(tau, k, rng,
                                                                           monkeypatch):
    """A chunk whose patches cover less than the sensor scales those pixels only: the same
    events and the same state as scaling every pixel, and the eager kernel's events."""
    arr = random_stream(rng, 1_200, LARGE, t_max=20_000)
    settings = density_kernel.DensitySettings(LARGE, (2, 3), tau, k, 0.3, 1)
    planes = density_kernel.density_init(settings, to_events(arr, LARGE)[0]).decayed.shape[0]
    assert compiled._patches_only(37, k * k, planes)  # the chunks take both ways
    assert not compiled._patches_only(600, k * k, planes)
    _both_ways_alike(monkeypatch, "_patches_only", arr, settings)
    transform = DensitySubsampling(LARGE, (2, 3), tau=tau, k=k, s=0.3, seed=1)
    assert_identical(*both_paths(lambda: run_in_chunks(transform, arr, CUTS)))


@pytest.mark.parametrize(("tau", "k"), [(150.0, 5), (1.0, 3), (math.inf, 7), (0.05, 5)])
def test_summing_by_rows_gives_the_neighbours_sums_steps_bit_for_bit(tau, k, rng, monkeypatch):
    """The patch summed by rows or by its k x k neighbours: the same events and states (the
    counts are the same; the densities round otherwise, within the doubt bound), and the
    eager kernel's events. tau = 0.05 moves the clock's origin often (the rows made again)."""
    arr = random_stream(rng, 1_200, LARGE, t_max=20_000)
    settings = density_kernel.DensitySettings(LARGE, (2, 3), tau, k, 0.3, 1)
    _both_ways_alike(monkeypatch, "_by_rows", arr, settings)
    transform = DensitySubsampling(LARGE, (2, 3), tau=tau, k=k, s=0.3, seed=1)
    for by_rows in (True, False):
        with monkeypatch.context() as patched:
            patched.setattr(compiled, "_by_rows", lambda *_, by_rows=by_rows: by_rows)
            assert_identical(*both_paths(lambda: run_in_chunks(transform, arr, CUTS)))


def test_sessions_alternating_in_a_thread_do_not_share_their_kept_maps(rng):
    streams = [random_stream(rng, 1_000, LARGE, t_max=30_000) for _ in range(2)]
    transforms = [DensitySubsampling(LARGE, (2, 3), tau=tau, k=5, s=0.2, seed=3)
                  for tau in (2.0, 400.0)]
    with eager_kernels():
        alone = [transform(arr) for transform, arr in zip(transforms, streams, strict=True)]
    sessions = [transform.session() for transform in transforms]
    outputs: list[list[np.ndarray]] = [[], []]
    for lo in range(0, 1_000, 50):  # 50-event chunks: the patches only
        for k in (0, 1):
            outputs[k].append(sessions[k](streams[k][lo:lo + 50]))
    for k in (0, 1):
        outputs[k].append(sessions[k].flush())
        np.testing.assert_array_equal(np.concatenate(outputs[k]), alone[k])


@pytest.mark.parametrize("patches_only", [True, False])
def test_a_count_from_the_state_shrinks_when_the_origin_moves(patches_only, monkeypatch):
    """tau = 1: pixel A fires at t = 0 in one chunk; the next chunk starts at t = 0 at its
    neighbour B, and A fires again at t = 600, after the origin moved (600 > 500 tau). A's
    count is then 1 + exp(-600), not 2: the count the state carried, scaled to the first
    origin, shrank at the move."""
    monkeypatch.setattr(compiled, "_patches_only", lambda *_: patches_only)
    settings = density_kernel.DensitySettings(LARGE, (2, 3), 1.0, 3, 0.5, 0)
    first = Events.from_columns([10], [10], [0], [1])
    state = density_kernel.density_init(settings, first)
    _, state = density_kernel._compiled_step(first, state, settings)
    second = Events.from_columns([11, 10], [10, 10], [0, 600], [1, 1])
    result = density_kernel._compiled_step(second, state, settings)
    assert result is not None
    width, height, r = density_kernel._padded(settings)
    key_a = (height + 10 + r) * width + 10 + r
    assert result[1].decayed[key_a].item() == pytest.approx(1.0, rel=1e-12)
    assert result[1].last_t[key_a].item() == 600
