"""Tonic structured arrays read and written by the compiled loops: NumPy's values, NumPy's errors.

The compiled path (``transforms/functional/compiled/columns.py``) must give the same columns,
formats, arrays and errors as the NumPy copies it replaces (the eager path), on every field
dtype it takes, and leave every other dtype to NumPy.
"""

from __future__ import annotations

import itertools
import warnings

import numpy as np
import pytest

from evdown_torch import eager_kernels
from evdown_torch.events import TimestampPrecisionWarning, from_events, to_events
from tests.helpers import assert_identical, both_paths

pytest.importorskip("numba")

from evdown_torch.transforms.functional.compiled.columns import (  # noqa: E402
    compiled_fields,
    read_columns,
)

X_DTYPES = ["<i2", "<u2", "<i8", "<u1", "<i4"]
T_DTYPES = ["<i8", "<u4", "<i4", "<f8", "<f4"]
P_KINDS = [("?", "bool"), ("<i1", "binary"), ("<i1", "signed"), ("<f4", "signed"),
           ("<u1", "binary"), ("<f8", "binary")]


def _array(rng, x_dtype, t_dtype, p_dtype, encoding, n=300, order=("t", "x", "p", "y")):
    dtype = np.dtype([(name, {"x": x_dtype, "y": x_dtype, "t": t_dtype, "p": p_dtype}[name])
                      for name in order])
    data = np.zeros(n, dtype)
    data["x"] = rng.integers(0, 40, n)
    data["y"] = rng.integers(0, 30, n)
    data["t"] = np.sort(rng.integers(0, 100_000, n))
    on = rng.random(n) < 0.5
    data["p"] = on if encoding == "bool" else np.where(on, 1, 0 if encoding == "binary" else -1)
    return data


#: Each dtype of each field beside the others' usual ones (each combination compiles anew).
CASES = sorted({*((x, "<i8", P_KINDS[0]) for x in X_DTYPES),
                *(("<i2", t, P_KINDS[0]) for t in T_DTYPES),
                *(("<i2", "<i8", p) for p in P_KINDS),
                *itertools.product(["<u1"], ["<f4"], P_KINDS[-2:])})


@pytest.mark.parametrize(("x_dtype", "t_dtype", "p_kind"), CASES)
def test_every_field_dtype_reads_and_writes_as_numpy_does(rng, x_dtype, t_dtype, p_kind):
    p_dtype, encoding = p_kind
    data = _array(rng, x_dtype, t_dtype, p_dtype, encoding)
    assert compiled_fields(data.dtype)
    (events_c, fmt_c), (events_e, fmt_e) = both_paths(lambda: to_events(data, (40, 30, 2)))
    assert_identical(events_c, events_e)
    assert fmt_e == fmt_c
    assert fmt_c.polarity == encoding
    with eager_kernels():
        back_e = from_events(events_e, fmt_e)
    with eager_kernels(False):
        back_c = from_events(events_c, fmt_c)
    assert back_c.dtype == data.dtype
    assert back_c.tobytes() == back_e.tobytes() == data.tobytes()


def test_the_facts_are_the_hand_computed_ones():
    data = np.zeros(4, np.dtype([("x", "<i2"), ("y", "<i2"), ("t", "<f8"), ("p", "<i1")]))
    data["x"], data["y"], data["t"], data["p"] = [3, -2, 7, 0], [5, 5, 1, 9], [0, 1, np.inf, 2], \
        [1, -1, 1, -1]
    (x, y, t, p), facts = read_columns(data, np.float64)
    assert facts.x_range == (-2, 7) and facts.y_range == (1, 9)
    assert not facts.t_finite and not facts.t_sorted  # inf before 2
    assert facts.p_negative and facts.p_signed and not facts.p_binary
    assert x.tolist() == [3, -2, 7, 0] and p.tolist() == [True, False, True, False]
    _, empty = read_columns(data[:0], np.float64)
    assert empty.x_range == (0, -1) and empty.t_finite and not empty.p_negative
    assert empty.t_sorted
    data["t"] = [0, 1, 1, 2]
    assert read_columns(data, np.float64)[1].t_sorted
    data["t"] = [0, 1, 2, 1]
    assert not read_columns(data, np.float64)[1].t_sorted


@pytest.mark.parametrize("p_dtype", ["<i1", "<u1", "<i8", "<f4"])
def test_the_polarity_facts_name_each_encoding_and_no_other(p_dtype):
    # A fact read wrongly as "bad values" passes unseen through to_events, which then asks the
    # values again (slower): so each encoding's facts are checked here, hand-computed.
    data = np.zeros(5, np.dtype([("x", "<i2"), ("y", "<i2"), ("t", "<i8"), ("p", p_dtype)]))
    cases = {(0, 1, 1, 0, 1): (False, True, False), (1, 1, 1, 1, 1): (False, True, True),
             (0, 0, 0, 0, 0): (False, True, False), (2, 1, 0, 1, 0): (False, False, False)}
    if p_dtype != "<u1":
        cases[(1, -1, -1, 1, 1)] = (True, False, True)
        cases[(1, -1, 0, 1, 1)] = (True, False, False)
    for values, (negative, binary, signed) in cases.items():
        data["p"] = values
        facts = read_columns(data, np.int64)[1]
        assert (facts.p_negative, facts.p_binary, facts.p_signed) == (negative, binary, signed)


@pytest.mark.parametrize("eager", [True, False])
def test_in_time_order_sorts_stably_only_what_is_not_sorted(rng, eager):
    data = _array(rng, "<i2", "<i8", "?", "bool", n=500)
    data["t"] //= 1000  # many ties: a stable sort keeps their input order
    shuffled = data[rng.permutation(500)]
    with eager_kernels(eager):
        events, _ = to_events(shuffled, (40, 30, 2), in_time_order=True)
        kept, _ = to_events(data, (40, 30, 2), in_time_order=True)
    order = np.argsort(shuffled["t"], kind="stable")
    assert events.t.tolist() == shuffled["t"][order].tolist()
    assert events.x.tolist() == shuffled["x"][order].tolist()
    assert kept.x.tolist() == data["x"].tolist()


def test_a_session_fed_unsorted_chunks_gives_the_whole_streams_events(rng):
    from evdown_torch import EventCount

    data = _array(rng, "<i2", "<i8", "<i1", "binary", n=3000)
    data["t"] = np.arange(3000) * 7  # no ties: one time order, whatever the chunk's order
    transform = EventCount((40, 30, 2), 2, threshold=0.5)
    whole = transform(data)
    for eager in (True, False):
        with eager_kernels(eager):
            session = transform.session()
            parts = [session(data[cut:cut + 1000][::-1]) for cut in range(0, 3000, 1000)]
            parts.append(session.flush())
        assert np.concatenate(parts).tobytes() == whole.tobytes()


def test_results_of_a_kernel_come_back_alike(rng):
    from evdown_torch import EventCount, LinearEstimation

    data = _array(rng, "<i2", "<i8", "<i1", "signed", n=2000)
    for transform in (EventCount((40, 30, 2), 4, threshold=0.5),
                      LinearEstimation((40, 30, 2), 4, threshold=0.5)):
        compiled, eager = both_paths(lambda transform=transform: transform(data))
        assert_identical(compiled, eager)
        assert compiled.dtype == data.dtype
        assert set(np.unique(compiled["p"]).tolist()) <= {-1, 1}


@pytest.mark.parametrize(("field", "values", "match"), [
    ("x", [0, 40, 1], r"event coordinate x must lie in \[0, 39\].*from 0 to 40"),
    ("y", [0, -1, 1], r"event coordinate y must lie in \[0, 29\].*from -1 to 1"),
    ("p", [0, 1, 2], r"polarity p must take two values.*got values \{0, 1, 2\}"),
    ("p", [-1, 0, 1], r"polarity p must take two values.*got values \{-1, 0, 1\}"),
    ("t", [0.0, np.nan, 2.0], "event timestamps t must be finite"),
])
def test_bad_values_raise_the_same_error_on_both_paths(field, values, match):
    dtype = np.dtype([("x", "<i2"), ("y", "<i2"), ("t", "<f8"), ("p", "<i1")])
    data = np.zeros(3, dtype)
    data["p"] = 1
    data[field] = values
    messages = []
    for eager in (True, False):
        with eager_kernels(eager), pytest.raises(ValueError, match=match) as error:
            to_events(data, (40, 30, 2))
        messages.append(str(error.value))
    assert messages[0] == messages[1]


def test_swapped_sensor_hint_is_given_on_both_paths():
    data = np.zeros(2, np.dtype([("x", "<i2"), ("y", "<i2"), ("t", "<i8"), ("p", "?")]))
    data["x"], data["y"] = [0, 29], [0, 39]
    messages = []
    for eager in (True, False):
        with eager_kernels(eager), pytest.raises(ValueError) as error:
            to_events(data, (40, 30, 2))
        messages.append(str(error.value))
    assert messages[0] == messages[1]


@pytest.mark.parametrize("dtype", [
    [("x", ">i2"), ("y", ">i2"), ("t", ">i8"), ("p", "?")],  # not native
    [("x", "<i2"), ("y", "<i2"), ("t", "<f2"), ("p", "?")],  # float16
])
def test_fields_numba_cannot_read_take_numpys_copies(rng, dtype):
    dtype = np.dtype(dtype)
    assert not compiled_fields(dtype)
    data = np.zeros(50, dtype)
    data["x"], data["y"] = rng.integers(0, 40, 50), rng.integers(0, 30, 50)
    data["t"], data["p"] = np.arange(50), rng.random(50) < 0.5
    (events_c, fmt_c), (events_e, _) = both_paths(lambda: to_events(data, (40, 30, 2)))
    assert_identical(events_c, events_e)
    assert from_events(events_c, fmt_c).tobytes() == data.tobytes()


def test_float32_time_past_its_exact_range_warns_on_the_compiled_path():
    data = np.zeros(2, np.dtype([("x", "<i2"), ("y", "<i2"), ("t", "<f4"), ("p", "?")]))
    data["t"] = [2.0**25, 2.0**25 + 4]
    with eager_kernels(False), warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        to_events(data, (40, 30, 2))
    assert any(issubclass(w.category, TimestampPrecisionWarning) for w in caught)


def test_the_input_array_is_never_written_or_shared(rng):
    data = _array(rng, "<i2", "<i8", "?", "bool")
    before = data.copy()
    with eager_kernels(False):
        events, _ = to_events(data, (40, 30, 2))
    events.x.fill_(0)
    events.t.fill_(0)
    assert data.tobytes() == before.tobytes()
