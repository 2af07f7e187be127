"""The event container and the conversions at the edge."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evdown_torch.events import Events, from_events, to_events
from tests.helpers import random_stream

SENSOR = (8, 6, 2)


@pytest.mark.parametrize(
    "fields",
    [
        [("x", "<i2"), ("y", "<i2"), ("p", "?"), ("t", "<i8")],
        [("t", "<u8"), ("p", "<i1"), ("y", "<u2"), ("x", "<i4")],
        [("p", "<f4"), ("x", "<u1"), ("t", "<f8"), ("y", "<i8")],
    ],
)
def test_structured_round_trip_keeps_dtype_and_order(fields, rng):
    dtype = np.dtype(fields)
    arr = random_stream(rng, 50, SENSOR, dtype=dtype)
    if np.issubdtype(dtype["p"], np.signedinteger):
        arr["p"] = np.where(arr["p"] > 0, 1, -1)
    before = arr.copy()
    events, fmt = to_events(arr, SENSOR)
    back = from_events(events, fmt)
    assert back.dtype == arr.dtype and back.dtype.names == arr.dtype.names
    np.testing.assert_array_equal(back, arr)
    np.testing.assert_array_equal(arr, before)
    assert events.x.dtype == torch.int64 and events.p.dtype == torch.bool
    assert events.t.dtype == (torch.float64 if dtype["t"].kind == "f" else torch.int64)


def test_signed_and_binary_polarity_are_detected():
    dtype = np.dtype([("x", "<i2"), ("y", "<i2"), ("t", "<i8"), ("p", "<i1")])
    signed = np.array([(0, 0, 1, -1), (1, 1, 2, 1)], dtype=dtype)
    binary = np.array([(0, 0, 1, 0), (1, 1, 2, 1)], dtype=dtype)
    ev_s, fmt_s = to_events(signed, SENSOR)
    ev_b, fmt_b = to_events(binary, SENSOR)
    assert (fmt_s.polarity, fmt_b.polarity) == ("signed", "binary")
    assert ev_s.p.tolist() == ev_b.p.tolist() == [False, True]


def test_tensor_round_trip_keeps_int64_time_exactly(device):
    t = 1_700_000_000_000_000 + torch.arange(3, device=device)
    data = torch.stack(
        [torch.tensor([1, 2, 3], device=device), torch.tensor([0, 1, 2], device=device), t,
         torch.tensor([1, 0, 1], device=device)], dim=1
    )
    events, fmt = to_events(data, SENSOR)
    assert events.t.tolist() == t.tolist()
    back = from_events(events, fmt)
    assert back.dtype == torch.int64 and back.device == data.device
    assert torch.equal(back, data)


def test_tensor_input_is_never_aliased():
    data = torch.tensor([[1, 2, 3, 1]])
    events, _ = to_events(data, SENSOR)
    events.x.add_(1)
    events.t.add_(1)
    assert data.tolist() == [[1, 2, 3, 1]]


def test_events_input_returns_events():
    ev = Events.from_columns([1], [2], [3.5], [0])
    out, fmt = to_events(ev, SENSOR)
    assert fmt.kind == "events" and from_events(out, fmt) is out
    assert ev.t.dtype == torch.float64 and ev.p.tolist() == [False]


@pytest.mark.parametrize(
    ("data", "error", "match"),
    [
        (np.zeros(3, dtype=[("x", "<i2"), ("y", "<i2"), ("t", "<i8")]), ValueError,
         r"missing.*'p'"),
        (np.zeros(3, dtype=[("x", "<f4"), ("y", "<i2"), ("t", "<i8"), ("p", "?")]), TypeError,
         "field x must have an integer dtype"),
        (np.zeros((3, 4)), TypeError, "structured"),
        (torch.zeros(3, 3), ValueError, r"shape \(N, 4\)"),
        (torch.zeros(4), ValueError, r"shape \(N, 4\)"),
        (torch.zeros(2, 4, dtype=torch.bool), TypeError, "integer or float"),
        ([1, 2, 3, 4], TypeError, "events must be"),
        (torch.tensor([[0.0, 0.0, float("nan"), 1.0]]), ValueError, "finite"),
        (torch.tensor([[0.0, 0.0, float("inf"), 1.0]]), ValueError, "finite"),
        (torch.tensor([[0.5, 0.0, 1.0, 1.0]]), ValueError, "whole numbers"),
        (torch.tensor([[8, 0, 1, 1]]), ValueError, r"x must lie in \[0, 7\]"),
        (torch.tensor([[0, -1, 1, 1]]), ValueError, r"y must lie in \[0, 5\]"),
        (torch.tensor([[0, 0, 1, 1], [0, 0, 2, 0], [0, 0, 3, 2]]), ValueError, "two values"),
        (torch.tensor([[0, 0, 1, -1], [0, 0, 2, 0]]), ValueError, "two values"),
        (np.zeros(2, dtype=[("x", "<i2"), ("y", "<i2"), ("t", "<i8"), ("p", "?"), ("z", "<i2")]),
         ValueError, "cannot carry"),
    ],
)
def test_bad_events_raise_clear_errors(data, error, match):
    with pytest.raises(error, match=match):
        to_events(data, SENSOR)


def test_events_container_checks_its_tensors():
    good = Events.from_columns([0], [0], [0], [1])
    with pytest.raises(TypeError, match="x and Events.y must be int64"):
        to_events(Events(good.x.int(), good.y, good.t, good.p))
    with pytest.raises(ValueError, match="same length"):
        to_events(Events(good.x, good.y, torch.zeros(2, dtype=torch.int64), good.p))


def test_from_columns_accepts_structured_field_views_and_tensors(device):
    arr = np.array([(1, 2, True, 7)], dtype=[("x", "<i2"), ("y", "<i2"), ("p", "?"), ("t", "<i8")])
    ev = Events.from_columns(arr["x"], arr["y"], arr["t"], arr["p"])
    assert (ev.x.tolist(), ev.y.tolist(), ev.t.tolist(), ev.p.tolist()) == ([1], [2], [7], [True])
    t = torch.tensor([5], device=device)
    ev = Events.from_columns(t, t, t, t)
    assert ev.device == t.device and ev.p.tolist() == [True]
    ev.t.add_(1)
    assert t.tolist() == [5]
