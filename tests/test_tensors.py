"""The shared tensor helpers (``evdown_torch._tensors``) against plain torch."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evdown_torch import _tensors
from evdown_torch._tensors import (
    changes,
    correctly_rounded_sqrt,
    distinct_in_range,
    divide,
    note_time_order,
    run_max,
    runs_of,
    searchsorted_ascending,
    stable_sort_small,
    time_order,
    time_order_notes,
    where_true,
)


@pytest.mark.parametrize("numpy_on_cpu", [True, False])
@pytest.mark.parametrize("n", [0, 100, 4096, 8191, 8192, 9000, 32767, 40000])
@pytest.mark.parametrize("bound", [7, 256, 257, 1 << 15, 921_600])
def test_padded_sort_is_the_stable_sort(n, bound, numpy_on_cpu, rng, monkeypatch):
    # Keys padded to radix-sort length (ties with the padding key bound - 1 included), or
    # short keys through NumPy's radix sort, must sort exactly as torch's plain stable sort.
    monkeypatch.setattr(_tensors, "NUMPY_ON_CPU", numpy_on_cpu)
    keys = torch.as_tensor(rng.integers(0, bound, n))
    keys[: n // 3] = bound - 1
    values, order = stable_sort_small(keys, bound)
    expected = torch.sort(keys, stable=True)
    assert torch.equal(values, expected.values)
    assert torch.equal(order, expected.indices)


@pytest.mark.parametrize(
    ("bound", "dtype"),
    [(7, torch.int16), (256, torch.int16), (257, torch.int16), (1 << 15, torch.int16),
     ((1 << 15) + 1, torch.int32),
     (1 << 31, torch.int32), ((1 << 31) + 1, torch.int64)],
)
@pytest.mark.parametrize("n", [100, 9000, 40000])
def test_narrow_sort_returns_the_keys_in_the_dtype_they_were_sorted_as(bound, dtype, n, rng):
    keys = torch.as_tensor(rng.integers(0, bound, n))
    keys[: n // 4] = bound - 1
    values, order = stable_sort_small(keys, bound, narrow=True)
    expected = torch.sort(keys, stable=True)
    assert values.dtype == dtype and order.dtype == torch.int64
    assert torch.equal(values.to(torch.int64), expected.values)
    assert torch.equal(order, expected.indices)


@pytest.mark.parametrize("numpy_on_cpu", [True, False])
@pytest.mark.parametrize("runs", [1, 7, 300])
def test_run_helpers_against_a_python_loop(runs, numpy_on_cpu, rng, device, monkeypatch):
    # NumPy's primitives on the CPU, torch's elsewhere (and on the CPU with the switch off).
    monkeypatch.setattr(_tensors, "NUMPY_ON_CPU", numpy_on_cpu)
    monkeypatch.setattr(_tensors, "NUMPY_MIN_ELEMENTS", 0)
    lengths = rng.integers(1, 50, runs)
    n = int(lengths.sum())
    values = rng.integers(-10**12, 10**12, n)
    first_at = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    expected_ids = [i for i, length in enumerate(lengths) for _ in range(length)]
    expected_max = [int(values[a:a + length].max()) for a, length in zip(first_at, lengths,
                                                                         strict=True)]
    ids = runs_of(torch.tensor(lengths, device=device), n)
    assert ids.dtype == torch.int64 and ids.device == device and ids.tolist() == expected_ids
    for dtype in (torch.int64, torch.int32, torch.float64):
        column = torch.tensor(values, device=device)
        column = (column // 10**4 if dtype == torch.int32 else column).to(dtype)
        got = run_max(column, torch.tensor(first_at, device=device))
        want = [max(column[a:a + length].tolist()) for a, length in zip(first_at, lengths,
                                                                         strict=True)]
        assert got.dtype == dtype and got.device == device and got.tolist() == want
    assert run_max(torch.tensor(values), torch.tensor(first_at)).tolist() == expected_max
    mask = torch.tensor(rng.random(n) < 0.3, device=device)
    assert where_true(mask).tolist() == [i for i in range(n) if mask[i]]
    assert where_true(mask).dtype == torch.int64
    for dtype in (torch.int64, torch.int16, torch.float64, torch.bool, torch.bfloat16):
        column = torch.tensor(rng.integers(0, 2, n), device=device).to(dtype)
        plain = column.tolist()
        assert changes(column).tolist() == [i == 0 or plain[i] != plain[i - 1] for i in range(n)]
    ordered = np.sort(rng.integers(0, 50, n))
    keys = np.sort(rng.integers(-5, 55, 40))
    for right in (False, True):
        got = searchsorted_ascending(torch.tensor(ordered, device=device),
                                     torch.tensor(keys, device=device), right=right)
        want = [sum(int(v) < k or right and int(v) == k for v in ordered) for k in keys]
        assert got.dtype == torch.int64 and got.tolist() == want


@pytest.mark.parametrize("numpy_on_cpu", [True, False])
@pytest.mark.parametrize("dtype", [torch.int64, torch.int32, torch.int16])
def test_divide_floors_like_python(dtype, numpy_on_cpu, rng, device, monkeypatch):
    monkeypatch.setattr(_tensors, "NUMPY_ON_CPU", numpy_on_cpu)
    monkeypatch.setattr(_tensors, "NUMPY_MIN_ELEMENTS", 0)
    values = rng.integers(-30000, 30000, 500)
    column = torch.tensor(values, dtype=dtype, device=device)
    for divisor in (1, 2, 3, 9, 64, 87, 30001):
        got = divide(column, divisor)
        assert got.dtype == dtype and got.device == device
        assert got.tolist() == [int(v) // divisor for v in values]
    divisors = rng.integers(1, 100, 500)
    got = divide(column.long(), torch.tensor(divisors, device=device))
    assert got.tolist() == [int(v) // int(d) for v, d in zip(values, divisors, strict=True)]
    out = torch.empty_like(column)
    assert divide(column, 7, out=out) is out and out.tolist() == [int(v) // 7 for v in values]


@pytest.mark.parametrize("numpy_on_cpu", [True, False])
@pytest.mark.parametrize("dtype", [torch.int64, torch.float64, torch.float32])
@pytest.mark.parametrize("n", [0, 1, 100, 5000])
def test_time_order_is_none_exactly_for_a_sorted_stream(n, dtype, numpy_on_cpu, rng,
                                                          monkeypatch):
    # NumPy's comparison on CPU streams from NUMPY_MIN_ELEMENTS on, torch's otherwise: the
    # same answer, a stable order for an unsorted stream (ties, one step back, a NaN).
    monkeypatch.setattr(_tensors, "NUMPY_ON_CPU", numpy_on_cpu)
    t = torch.sort(torch.as_tensor(rng.integers(0, max(n // 4, 1), n)).to(dtype)).values
    assert time_order(t) is None
    if n < 2:
        return
    broken = t.clone()
    broken[n // 2] = broken[n // 2 - 1] - 1
    assert torch.equal(time_order(broken), torch.sort(broken, stable=True).indices)
    if dtype.is_floating_point:
        with_nan = t.clone()
        with_nan[n // 2] = float("nan")
        assert time_order(with_nan) is not None


def test_a_noted_tensor_is_taken_as_in_order_until_it_changes():
    # The note is trusted for that tensor object as it is (here on purpose an unsorted one, to
    # see it), and for nothing else: a change in place, a view or a copy is looked at again;
    # and only inside a span of notes (one transform's call).
    t = torch.tensor([5, 3, 4, 1])
    order = torch.sort(t, stable=True).indices
    note_time_order(t)  # outside every span: not taken
    assert torch.equal(time_order(t), order)
    with time_order_notes():
        note_time_order(t)
        assert time_order(t) is None
        assert torch.equal(time_order(t[:]), order) and torch.equal(time_order(t.clone()), order)
        t[0] = 5  # the same value, written in place
        assert torch.equal(time_order(t), order)
        note_time_order(t)
        note_time_order(torch.tensor([2, 1]))  # one tensor a thread: the last noted
        assert torch.equal(time_order(t), order)
        note_time_order(t)
        with torch.inference_mode():  # no version counter: never noted
            frozen = torch.tensor([2, 1])
            note_time_order(frozen)
            assert torch.equal(time_order(frozen), torch.tensor([1, 0]))
        assert time_order(t) is None
    assert torch.equal(time_order(t), order)  # the span's end drops the note


def test_the_compiled_read_notes_the_time_order_it_finds_inside_a_call(monkeypatch):
    pytest.importorskip("numba")
    from evdown_torch import EventCount, eager_kernels
    from evdown_torch.events import DVS_DTYPE, to_events

    arr = np.zeros(6, dtype=DVS_DTYPE)
    arr["x"], arr["t"], arr["p"] = [0, 1, 2, 3, 0, 1], [1, 2, 2, 5, 7, 9], True
    with eager_kernels(False):
        assert not _tensors._noted_in_order(to_events(arr)[0].t)  # a user's own read
        with time_order_notes():
            assert _tensors._noted_in_order(to_events(arr)[0].t)
            arr["t"][3] = 0
            events = to_events(arr)[0]
            assert not _tensors._noted_in_order(events.t) and time_order(events.t) is not None
        with torch.inference_mode():  # a transform's call there: read, not noted, the same
            out = EventCount((4, 2, 2), factor=2, threshold=0.5)(arr)
        arr.sort(order="t", kind="stable")
        answers = []
        noted = _tensors._noted_in_order
        monkeypatch.setattr(_tensors, "_noted_in_order",
                            lambda t: answers.append(noted(t)) or answers[-1])
        sorted_out = EventCount((4, 2, 2), factor=2, threshold=0.5)(arr)
        assert True in answers  # the kernel's check took the read's note
    assert out.tolist() == sorted_out.tolist() and len(out) > 0


@pytest.mark.parametrize("numpy_on_cpu", [True, False])
@pytest.mark.parametrize(("n", "low", "high"), [
    (0, 0, 0), (1, -3, -3), (50, -10, 10), (5000, 0, 999), (5000, -(1 << 40), -(1 << 40) + 99),
    (100, 0, 10**6), (2000, -5, 10**5)])  # (the last two: ranges longer than the values)
def test_distinct_in_range_is_torch_unique(n, low, high, numpy_on_cpu, rng, device, monkeypatch):
    # The table of marks (NumPy's assignment on the CPU from 1,024 values, torch's else; the
    # distinct values read from the table or put by their ranks) must give torch.unique's
    # sorted values and inverse, with the range's ends taken or not.
    monkeypatch.setattr(_tensors, "NUMPY_ON_CPU", numpy_on_cpu)
    values = torch.as_tensor(rng.integers(low, high + 1, n), dtype=torch.int64).to(device)
    if n > 2:
        values[:2] = torch.tensor([low, high])
    distinct, inverse = distinct_in_range(values, low, high)
    want, want_inverse = torch.unique(values, return_inverse=True)
    assert distinct.dtype == inverse.dtype == torch.int64
    assert torch.equal(distinct.cpu(), want.cpu())
    assert torch.equal(inverse.cpu(), want_inverse.cpu())
    assert torch.equal(distinct[inverse].cpu(), values.cpu())


def _nearest_to_sqrt(d: float, y: float) -> bool:
    """Whether ``y`` is the float nearest to ``sqrt(d)``: ``d`` lies between the squares of the
    midpoints to ``y``'s neighbours (exactly, in rationals; no float is a tie)."""
    from fractions import Fraction

    low = (Fraction(np.nextafter(y, 0.0)) + Fraction(y)) / 2 if y > 0 else Fraction(0)
    high = (Fraction(y) + Fraction(np.nextafter(y, np.inf))) / 2
    return low * low <= Fraction(d) <= high * high


def test_correctly_rounded_sqrt_gives_the_nearest_float(rng):
    values = np.concatenate([
        [6.167086359879541, 0.0, 1.0, 2.0, 5e-324, 1.7976931348623157e308],
        rng.uniform(0, 1000, 3000), np.exp(rng.uniform(-700, 700, 3000)),
    ])
    out = correctly_rounded_sqrt(torch.from_numpy(values))
    assert out.dtype == torch.float64 and out.shape == (values.size,)
    assert all(_nearest_to_sqrt(d, y) for d, y in zip(values.tolist(), out.tolist()))
    assert out[0].item() == 2.483361906746486  # torch 2.13.0's CPU sqrt: 2.4833619067464854
    negative = correctly_rounded_sqrt(torch.tensor([-1.0, -0.0], dtype=torch.float64))
    assert np.isnan(negative[0].item()) and negative[1].item() == 0.0
