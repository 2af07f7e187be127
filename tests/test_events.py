"""The event container and the conversions at the edge."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from evdown_torch import CubicEstimation, EventCount, EventFunnelling
from evdown_torch.events import Events, TimestampPrecisionWarning, from_events, to_events
from evdown_torch.transforms.registry import make_method
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
        (np.zeros((3, 3)), ValueError, r"shape \(N, 4\) with columns \(x, y, t, p\), or be "
         "structured"),
        (np.zeros((3, 4), dtype=bool), TypeError, "integer or float, got dtype bool"),
        (np.zeros((3, 4), dtype=object), TypeError, "integer or float, got dtype object"),
        (np.full((1, 4), 2**63, dtype=np.uint64), ValueError, "beyond the int64 range"),
        (np.array([[0.5, 0.0, 1.0, 1.0]]), ValueError, "whole numbers"),
        (np.array([[0, 0, 1, 2]]), ValueError, "two values"),
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
        (np.zeros((2, 2), dtype=[("x", "<i2"), ("y", "<i2"), ("t", "<i8"), ("p", "?")]),
         ValueError, r"must be 1-D, got shape \(2, 2\)"),
    ],
)
def test_bad_events_raise_clear_errors(data, error, match):
    for _ in range(2):  # at every call: a structured dtype's checks are made once, not its errors
        with pytest.raises(error, match=match):
            to_events(data, SENSOR)


def test_events_container_checks_its_tensors():
    good = Events.from_columns([0], [0], [0], [1])
    with pytest.raises(TypeError, match="x and Events.y must be int64"):
        to_events(Events(good.x.int(), good.y, good.t, good.p))
    with pytest.raises(ValueError, match="same length"):
        to_events(Events(good.x, good.y, torch.zeros(2, dtype=torch.int64), good.p))


@pytest.mark.parametrize("kind", ["int64", "int32", "mask", "empty", "rows"])
def test_select_picks_the_same_events_as_a_python_loop(kind, rng, device):
    n = 3000  # past NUMPY_MIN_ELEMENTS: a mask takes NumPy's positions on the CPU
    columns = [rng.integers(0, 9, n), rng.integers(0, 9, n), rng.integers(0, 99, n),
               rng.random(n) < 0.5]
    ev = Events.from_columns(*(torch.from_numpy(c).to(device) for c in columns))
    if kind == "mask":
        mask = rng.random(n) < 0.3
        picked = [i for i in range(n) if mask[i]]
        index = torch.from_numpy(mask).to(device)
    elif kind == "rows":  # a 2-D index keeps advanced indexing's shape
        picked = None
        index = torch.tensor([[3, 1], [0, 3]], device=device)
    else:
        picked = [] if kind == "empty" else rng.integers(0, n, 60).tolist()  # repeats
        index = torch.tensor(picked, dtype=getattr(torch, "int32" if kind == "int32" else "int64"),
                             device=device)
    out = ev.select(index)
    if picked is None:
        assert out.t.tolist() == [[int(columns[2][i]) for i in row] for row in [[3, 1], [0, 3]]]
        return
    for column, got in zip(columns, out, strict=True):
        assert got.tolist() == [column[i].item() for i in picked]
        assert got.device == ev.device
    assert out.p.dtype == torch.bool and out.t.dtype == torch.int64


def test_from_columns_accepts_structured_field_views_and_tensors(device):
    arr = np.array([(1, 2, True, 7)], dtype=[("x", "<i2"), ("y", "<i2"), ("p", "?"), ("t", "<i8")])
    ev = Events.from_columns(arr["x"], arr["y"], arr["t"], arr["p"])
    assert (ev.x.tolist(), ev.y.tolist(), ev.t.tolist(), ev.p.tolist()) == ([1], [2], [7], [True])
    t = torch.tensor([5], device=device)
    ev = Events.from_columns(t, t, t, t)
    assert ev.device == t.device and ev.p.tolist() == [True]
    ev.t.add_(1)
    assert t.tolist() == [5]


# ------------------------------------------------------------------ float time, meta, grad


def _epoch_stream(rng, n=2000):
    """A DAVIS-like stream on an epoch clock (microseconds since 1970): beyond 2**24."""
    t = np.sort(rng.integers(0, 200_000, n)) + 1_600_000_000_000_000
    return torch.stack([torch.as_tensor(rng.integers(0, 16, n)),
                        torch.as_tensor(rng.integers(0, 16, n)), torch.as_tensor(t),
                        torch.as_tensor(rng.integers(0, 2, n))], dim=1)


def test_float32_epoch_time_warns_once_naming_the_cause(rng, device):
    ev = _epoch_stream(rng).to(device)
    funnel = EventFunnelling((346, 260, 2), 2)
    exact = funnel(ev)
    assert len(exact) > 1900  # int64: distinct events stay distinct
    # A compile inside the block (a cold Numba cache) changes the warning filters, which
    # clears Python's record of warnings shown: the float path compiles here first.
    funnel(ev.double())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        for _ in range(3):
            rounded = funnel(ev.float())
    assert len(rounded) < len(exact) / 2  # float32 merged microseconds into duplicates
    assert [w.category for w in caught] == [TimestampPrecisionWarning]
    message = str(caught[0].message)
    assert "float32" in message and "2**24" in message and "int64 or float64" in message


@pytest.mark.parametrize(
    ("make", "dtype_name"),
    [
        (lambda t: torch.tensor([[0, 0, t, 1]], dtype=torch.float32), "float32"),
        (lambda t: torch.tensor([[0, 0, t / 1000, 1]], dtype=torch.float16), "float16"),
        (lambda t: np.array([(0, 0, t, True)], dtype=[("x", "<i2"), ("y", "<i2"),
                                                     ("t", "<f4"), ("p", "?")]), "float32"),
    ],
)
def test_each_short_float_warns_past_its_exact_range(make, dtype_name):
    with pytest.warns(TimestampPrecisionWarning, match=dtype_name):
        to_events(make(2**24 + 8))
    with warnings.catch_warnings():
        warnings.simplefilter("error", TimestampPrecisionWarning)
        to_events(make(2000))  # in range: silent
        to_events(torch.tensor([[0, 0, 2**40, 1]], dtype=torch.int64))
        to_events(torch.tensor([[0, 0, 2**40, 1]], dtype=torch.float64))


def test_meta_tensors_are_refused_clearly():
    data = torch.zeros(5, 4, device="meta")
    for transform in (EventCount(SENSOR, 2), CubicEstimation(SENSOR, 2)):
        with pytest.raises(ValueError, match="'meta' device.*no values"):
            transform(data)
    meta = Events(*(torch.zeros(3, dtype=d, device="meta")
                    for d in (torch.int64, torch.int64, torch.int64, torch.bool)))
    with pytest.raises(ValueError, match="'meta' device"):
        to_events(meta)


@pytest.mark.parametrize("method", ["event_count", "linear", "cubic", "lif", "funnelling"])
def test_tensors_that_require_grad_are_read_as_values(rng, method, device):
    arr = random_stream(rng, 300, SENSOR, t_max=5000)
    data = torch.tensor(np.stack([arr["x"], arr["y"], arr["t"], arr["p"]], 1),
                        dtype=torch.float64, device=device)
    transform = make_method(method, SENSOR, 2, **({"dt": 100} if method == "lif" else {}))
    leaf = data.clone().requires_grad_(True)
    out = transform(leaf)
    assert not out.requires_grad and leaf.requires_grad and leaf.grad is None
    torch.testing.assert_close(out, transform(data), rtol=0, atol=0)
    events = Events(*to_events(data)[0][:2], to_events(data)[0].t.requires_grad_(True),
                    to_events(data)[0].p)
    assert not transform(events).t.requires_grad


@pytest.mark.parametrize("dtype", [np.int64, np.int32, np.float64, np.float32])
@pytest.mark.parametrize("method", ["downsample", "event_count", "cubic", "lif"])
def test_plain_numpy_arrays_act_as_tensors_and_come_back_as_arrays(rng, dtype, method):
    stream = random_stream(rng, 400, SENSOR, t_max=60_000)
    plain = np.stack([stream["x"], stream["y"], stream["t"], stream["p"] * 2 - 1],
                     axis=1).astype(dtype)  # signed polarity, x y t p columns
    before = plain.copy()
    transform = make_method(method, SENSOR, 2)
    out = transform(plain)
    expected = transform(torch.from_numpy(plain)).numpy()  # the same data as a tensor
    assert isinstance(out, np.ndarray) and out.dtype == dtype and out.shape[1] == 4
    np.testing.assert_array_equal(out, expected)
    assert set(np.unique(out[:, 3]).tolist()) <= {-1, 1}  # the polarity encoding kept
    np.testing.assert_array_equal(plain, before)  # the input is not modified
    assert [o.dtype for o in transform.batch([plain, plain[:0]])] == [dtype, dtype]
    np.testing.assert_array_equal(transform.batch([plain, plain[:0]])[0], out)


def test_plain_arrays_stream_through_a_session(rng):
    stream = random_stream(rng, 300, SENSOR, t_max=30_000)
    plain = np.stack([stream["x"], stream["y"], stream["t"], stream["p"]], axis=1)
    transform = EventCount(SENSOR, 2, threshold=0.5)
    session = transform.session()
    parts = [session(plain[:100]), session(plain[100:]), session.flush()]
    assert all(isinstance(part, np.ndarray) and part.dtype == plain.dtype for part in parts)
    np.testing.assert_array_equal(np.concatenate(parts), transform(plain))
