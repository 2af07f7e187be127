"""Bounded-delay sessions without sorting: the window's merge, the next state's knots."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evdown_torch import CubicEstimation, Events, LinearEstimation
from evdown_torch.transforms.functional.estimation import delay, linear, stream
from tests.helpers import random_stream


def sorted_part(rng, n, t_max, dtype):
    """``n`` random knot events sorted by time (many ties) and their int64 window_change."""
    t = torch.sort(torch.from_numpy(rng.integers(0, t_max, n))).values.to(dtype)
    x, y = torch.from_numpy(rng.integers(0, 5, n)), torch.from_numpy(rng.integers(0, 4, n))
    change = torch.from_numpy(rng.integers(-2, 3, n))
    return Events(x, y, t, change > 0), change


@pytest.mark.parametrize("sizes", [(0, 0, 5), (7, 0, 40), (30, 3, 12), (1, 25, 0)])
@pytest.mark.parametrize("dtype", [torch.int64, torch.float64])
@pytest.mark.parametrize("offsets", [(0, 0, 0), (0, 19, 38), (38, 19, 0), (0, 40, 20)])
def test_merge_is_a_stable_time_sort_of_the_parts_in_turn(rng, sizes, dtype, offsets,
                                                         monkeypatch):
    # Overlapping parts, and parts one after another (touching at a tie, or not).
    monkeypatch.setattr(delay, "SMALL_WINDOW", 0)  # no sort, even of a few events
    parts = []
    for n, offset in zip(sizes, offsets, strict=True):
        events, change = sorted_part(rng, n, 20, dtype)
        parts.append((events._replace(t=events.t + offset), change))
    merged, change = delay.merge_by_time(parts)
    whole = Events(*(torch.cat([events[c] for events, _ in parts]) for c in range(4)))
    order = torch.sort(whole.t, stable=True).indices
    expected = whole.select(order)
    for got, want in zip(merged, expected, strict=True):
        assert torch.equal(got, want)
    assert torch.equal(change, torch.cat([s for _, s in parts])[order])


@pytest.mark.parametrize("keep", [1, 2])
@pytest.mark.parametrize("before", [0, 3, 11, 25])
def test_recent_knots_trim_as_the_whole_window(rng, keep, before, monkeypatch):
    monkeypatch.setattr(delay, "SMALL_WINDOW", 0)
    width, height = 5, 4
    window, change = sorted_part(rng, 200, 25, torch.int64)
    cut = torch.tensor(before)
    kwargs = {"before": cut, "keep": keep, "width": width}
    recent = stream._recent(window, change, pixels=width * height, t_start=window.t[0], **kwargs)
    assert recent[0].num_events <= window.num_events
    got, got_step = stream._trim(*recent, **kwargs)
    want, want_step = stream._trim(window, change, **kwargs)
    for a, b in zip((*got, got_step), (*want, want_step), strict=True):
        assert torch.equal(a, b)


def test_held_knots_are_those_hold_knots_adds(rng):
    ev = Events.from_columns(*(random_stream(rng, 300, (6, 5, 2), t_max=3000)[c]
                               for c in ("x", "y", "t", "p")))
    held = delay.held_knots(ev, max_delay=40, t_start=ev.t[0])
    merged, change = delay.hold_knots(ev, max_delay=40, t_start=ev.t[0])
    added = change == 0
    assert torch.equal(held.t, merged.t[added])
    assert sorted(zip(held.x.tolist(), held.y.tolist(), held.t.tolist(), strict=True)) == sorted(
        zip(merged.x[added].tolist(), merged.y[added].tolist(), merged.t[added].tolist(),
            strict=True))


@pytest.mark.parametrize("small_window", [0, delay.SMALL_WINDOW])
@pytest.mark.parametrize("cls", [LinearEstimation, CubicEstimation])
def test_the_state_keeps_its_knots_in_time_order(cls, rng, small_window, monkeypatch):
    monkeypatch.setattr(delay, "SMALL_WINDOW", small_window)
    sensor = (8, 6, 2)
    arr = random_stream(rng, 2000, sensor, t_max=5000)
    transform = cls(sensor, factor=2, threshold=0.5, max_delay=30)
    session = transform.session()
    parts = []
    for chunk in np.array_split(arr, 23):
        parts.append(session(chunk))
        t = session.state.knots.t
        assert torch.equal(t, torch.sort(t).values)
    parts.append(session.flush())
    np.testing.assert_array_equal(np.concatenate(parts), transform(arr))


@pytest.mark.parametrize("first_at", [[0, 1, 4, 5, 9, 40, 41], [0, *range(69_000, 70_000, 10)]])
def test_shared_rows_sum_each_segment_as_if_alone(rng, first_at):
    n = first_at[-1] + 3  # one group (small padding), or groups by length
    bounds = [*first_at, n]
    rows = linear.segment_rows(torch.tensor(first_at), n)
    for _ in range(2):  # the rows serve several sums
        values = torch.from_numpy(rng.standard_normal(n))
        alone = [torch.cumsum(values[a:b], 0) for a, b in zip(bounds[:-1], bounds[1:])]
        assert torch.equal(linear.rows_cumsum(values, rows), torch.cat(alone))
