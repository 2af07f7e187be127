"""The scratch-columns benchmark (benchmarks/scratch_columns.py) on a tiny replay."""

from __future__ import annotations

import pytest

from benchmarks import scratch_columns


@pytest.mark.slow
def test_sessions_with_and_without_scratch_columns_give_the_same_events(capsys):
    # The scratch columns change no output event: sessions with and without them, in fresh
    # processes and in this one, give the same events (each held to the end, in order).
    pytest.importorskip("numba")
    assert scratch_columns.main(["--events", "700000", "--chunks", "2", "--laps", "2",
                                 "--runs", "1", "--methods", "event_count", "downsample",
                                 "funnelling", "photocurrent"]) == 0
    rows = [line.split(" | ") for line in capsys.readouterr().out.splitlines()
            if line.startswith("| ") and not line.startswith("| method")]
    assert len(rows) == 8
    assert {(row[0].strip("| "), row[1]) for row in rows} == {
        (method, process) for method in ("event_count", "downsample", "funnelling",
                                         "photocurrent")
        for process in ("fresh", "after the replay's set-up")}
    assert all(row[-1].strip(" |") == "yes" for row in rows)
