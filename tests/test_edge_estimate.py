"""The edge estimate (benchmarks/edge_estimate.py) on a tiny replay."""

from __future__ import annotations

import pytest

from benchmarks import edge_estimate as estimate


def test_without_numba_it_says_so(monkeypatch, capsys):
    monkeypatch.setattr(estimate, "numba", None)
    assert estimate.main(["--events", "700000"]) == 2
    assert "needs numba" in capsys.readouterr().err


def _rows(text: str) -> dict[str, list[str]]:
    return {cells[0]: cells[1:] for line in text.splitlines() if line.startswith("| ")
            for cells in [[cell.strip() for cell in line.strip("|").split("|")]]}


def test_each_variant_makes_its_package_sessions_events(capsys):
    # The script compares every variant's output with its package session's byte for byte
    # and stops otherwise; the table's counts agree, and are not empty.
    pytest.importorskip("numba")
    assert estimate.main(["--events", "700000", "--chunks", "1"]) == 0
    rows = _rows(capsys.readouterr().out)
    downsample = rows["Downsample session (package)"][-1]
    assert int(downsample.replace(",", "")) > 0
    assert rows["records Downsample"][-1] == rows["int32 columns Downsample"][-1] == downsample
    event_count = rows["EventCount session (package)"][-1]
    assert int(event_count.replace(",", "")) > 0
    assert rows["records EventCount"][-1] == event_count
    funnelled = rows["EventFunnelling session (package)"][-1]
    assert int(funnelled.replace(",", "")) > 0
    assert rows["records EventFunnelling"][-1] == funnelled
    assert float(rows["floor"][2]) == 1.0


def test_a_variant_that_differs_from_its_session_stops_the_script(monkeypatch):
    # The check is what makes the timings comparable: a variant writing every polarity
    # flipped must be caught on the first chunk.
    pytest.importorskip("numba")
    compile_loops = estimate.compile_loops

    def flipping_loops() -> dict:
        loops = compile_loops()
        downsample = loops["records_downsample"]

        def flipped(*args):
            found = downsample(*args)
            args[-1][:] = ~args[-1]  # the output's polarity field
            return found

        return {**loops, "records_downsample": flipped}

    monkeypatch.setattr(estimate, "compile_loops", flipping_loops)
    with pytest.raises(RuntimeError, match="records Downsample differs from"):
        estimate.main(["--events", "700000", "--chunks", "1"])
