"""The first-call timing script (benchmarks/first_call.py): what it times and prints."""

from __future__ import annotations

import pytest

from benchmarks import first_call


def test_one_process_times_every_step_in_order():
    pytest.importorskip("numba")
    seconds = first_call.one_process()
    assert list(seconds) == first_call.STEPS
    assert all(value >= 0 for value in seconds.values())


@pytest.mark.slow
def test_the_table_has_a_cold_and_a_warm_range_per_step(capsys):
    pytest.importorskip("numba")
    assert first_call.main(["--runs", "1"]) == 0
    rows = [line.split(" | ") for line in capsys.readouterr().out.splitlines()
            if line.startswith("| ") and "---" not in line]
    assert [row[0].strip("| ") for row in rows[1:]] == [*first_call.STEPS,
                                                        "all but import numba"]
    assert all(row[1].endswith(" s") and row[2].endswith(" s |") for row in rows[1:])
