"""The compiled-loop estimate (benchmarks/compiled_loop_estimate.py) on a tiny replay."""

from __future__ import annotations

import pytest

from benchmarks import compiled_loop_estimate as estimate


def test_without_numba_it_says_so(monkeypatch, capsys):
    monkeypatch.setattr(estimate, "numba", None)
    assert estimate.main(["--events", "700000"]) == 2
    assert "needs numba" in capsys.readouterr().err


def test_its_event_count_loop_gives_the_package_output_count(capsys):
    # The compiled EventCount loop is exact at threshold 1: it must make exactly the events
    # the package's session makes on the same chunks, or it is not doing EventCount's work.
    pytest.importorskip("numba")
    assert estimate.main(["--events", "700000", "--chunks", "1"]) == 0
    rows = {line.split(" | ")[0].strip("| "): line.split(" | ")
            for line in capsys.readouterr().out.splitlines() if line.startswith("| ")}
    assert rows["compiled EventCount loop"][-1] == rows["EventCount session (package)"][-1]
    made = int(rows["EventCount session (package)"][-1].strip(" |").replace(",", ""))
    assert made > 0
    for name in ("compiled photocurrent loop, a logarithm per event",
                 "compiled photocurrent loop, sum against two levels"):
        loop = int(rows[name][-1].strip(" |").replace(",", ""))
        package = int(rows["PhotocurrentPooling session (package)"][-1].strip(" |")
                      .replace(",", ""))
        assert abs(loop - package) <= 0.01 * package
