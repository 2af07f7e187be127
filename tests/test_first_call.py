"""The first-call timing script (benchmarks/first_call.py): what it times and prints."""

from __future__ import annotations

import pytest

from benchmarks import first_call


def test_one_process_times_every_step_in_order():
    pytest.importorskip("numba")
    seconds, copies = first_call.one_process()
    assert list(seconds) == first_call.STEPS
    assert all(value >= 0 for value in seconds.values())
    assert all(name.startswith("evdown_torch.") for name in copies)


class _Dispatcher:
    def __init__(self, function):
        self.py_func = function


class _Compile:
    def __init__(self, function, args, start=True):
        self.data = {"dispatcher": _Dispatcher(function), "args": args}
        self.is_start = start


def test_a_loop_compiled_for_a_constant_argument_is_named_once():
    numba = pytest.importorskip("numba")
    from evdown_torch.transforms.functional.compiled import sorting

    types = numba.core.types
    constant, counter = types.IntegerLiteral(0), types.int64
    events = [
        (0.0, _Compile(sorting.merge_order.py_func, (counter, constant))),  # a copy for 0
        (0.1, _Compile(sorting.merge_order.py_func, (counter, constant), start=False)),
        (0.2, _Compile(sorting.merge_order.py_func, (counter, constant))),  # again: once
        (0.3, _Compile(sorting.stable_order.py_func, (counter,))),  # no constant
        (0.4, _Compile(len, (constant,))),  # not the package's
    ]
    assert first_call._literal_copies(events, types.Literal) == {
        "evdown_torch.transforms.functional.compiled.sorting.merge_order"}


@pytest.mark.slow
def test_the_table_has_a_cold_and_a_warm_range_per_step(capsys):
    pytest.importorskip("numba")
    assert first_call.main(["--runs", "1"]) == 0
    out = capsys.readouterr().out
    rows = [line.split(" | ") for line in out.splitlines()
            if line.startswith("| ") and "---" not in line]
    assert [row[0].strip("| ") for row in rows[1:]] == [*first_call.STEPS,
                                                        "all but import numba"]
    assert all(row[1].endswith(" s") and row[2].endswith(" s |") for row in rows[1:])
    # A fresh cache: every loop compiled, none a second time for a constant argument.
    assert "loops compiled again for a constant argument: none" in out
