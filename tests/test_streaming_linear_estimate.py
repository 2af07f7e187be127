"""The streaming linear design's estimate (benchmarks/streaming_linear_estimate.py)."""

from __future__ import annotations

import re

import numpy as np
import pytest

from benchmarks import streaming_linear_estimate as estimate
from evdown_torch.events import DVS_DTYPE


def test_without_numba_it_says_so(monkeypatch, capsys):
    monkeypatch.setattr(estimate, "numba", None)
    assert estimate.main(["--events", "700000"]) == 2
    assert "needs numba" in capsys.readouterr().err


def test_the_design_hand_computed():
    # Region (0, 0) has 16 pixels and threshold 1/4: a level every 4 in the sum of levels S.
    # Six of its pixels go ON at 2000, each ramping over [2000 - D, 2000] = [1000, 2000]
    # (D = 1 ms, idle since t_start = 0): S = 6 (t - 1000) / 1000 reaches 4 at 1666.67,
    # rounded to 1667. They go OFF at 2600, ramping back over [2000, 2600]: S falls to 0 at
    # 2600, the level below q = 1 (S = 4 again on the way is no event: the full threshold).
    # Pixel (5, 5) (region (1, 1)) sets t_start with a jump at 0 to S = 1 and ends the
    # chunk at 4000 (S = 2 at 4000): no level. The horizon is 4000 - D = 3000.
    pytest.importorskip("numba")
    ev = np.zeros(14, dtype=DVS_DTYPE)
    ev["x"] = [5] + [0, 1, 2, 3, 0, 1] * 2 + [5]
    ev["y"] = [5] + [0, 0, 0, 0, 1, 1] * 2 + [5]
    ev["t"] = [0] + [2000] * 6 + [2600] * 6 + [4000]
    ev["p"] = [True] + [True] * 6 + [False] * 6 + [True]
    session = estimate.StreamingLinear(estimate.compile_loops(), 0, len(ev))
    out = session(ev)
    assert out["x"].tolist() == [0, 0] and out["y"].tolist() == [0, 0]
    assert out["t"].tolist() == [1667, 2600] and out["p"].tolist() == [True, False]
    assert session.horizon == 3000
    # The eager twin, the whole stream at once, gives the same events.
    whole = estimate.design_whole(ev, 3000)
    assert whole["t"].tolist() == [1667, 2600] and whole["p"].tolist() == [True, False]
    assert whole["x"].tolist() == [0, 0] and whole["y"].tolist() == [0, 0]
    # One doubt: S reaches the level 0 at 2600, the ramps' end, where the integers are a hair
    # off until the ends' jumps correct them; 1667 is far from a half tick.
    (regions, times), = session.doubts
    assert regions.tolist() == [0] and times.tolist() == [2600]


def test_a_crossing_on_a_half_tick_is_a_doubt():
    # Eight pixels of region (0, 0) go ON at 1000 (ramps over [0, 1000]: S = 4 at 500, 8 at
    # 1000) and again at 1999 (ramps over [1000, 1999]: S = 12 at 1499.5 exactly, 16 at
    # 1999). Rounded half up, 1499.5 is 1500; the fixed point's slope round(2**32 / 999) may
    # put it a hair either side, so the crossing must be recorded as a doubt (the design's
    # integers cannot tell) at its tick.
    pytest.importorskip("numba")
    pixels = [(x, y) for y in (0, 1) for x in range(4)]
    ev = np.zeros(18, dtype=DVS_DTYPE)
    ev["x"] = [5] + [x for x, _ in pixels] * 2 + [5]
    ev["y"] = [5] + [y for _, y in pixels] * 2 + [5]
    ev["t"] = [0] + [1000] * 8 + [1999] * 8 + [4000]
    ev["p"] = True
    session = estimate.StreamingLinear(estimate.compile_loops(), 0, len(ev))
    out = session(ev)
    assert out["t"].tolist()[:2] == [500, 1000] and out["t"].tolist()[3] == 1999
    assert out["t"][2] in (1499, 1500)
    regions, times = session.doubts[0]
    assert 0 in regions.tolist()
    assert set(times[regions == 0].tolist()) & {1499, 1500}


def test_on_a_tiny_replay_it_makes_the_package_events_but_a_few(capsys):
    # The design's fixed point may move an event on a half tick by one tick, or miss a touch
    # of a level: never more than a few in 10,000 (docs/benchmarks.md, sixth session).
    pytest.importorskip("numba")
    assert estimate.main(["--events", "700000", "--chunks", "1"]) == 0
    text = capsys.readouterr().out
    found = re.search(r"package ([\d,]+) events, design ([\d,]+); in one and not the other: "
                      r"([\d,]+) and ([\d,]+), of which ([\d,]+) pairs", text)
    assert found is not None, text
    package, design, only_package, only_design, pairs = (
        int(group.replace(",", "")) for group in found.groups())
    assert package > 1000
    assert abs(package - design) <= package // 10_000 + 1
    assert only_package - pairs <= package // 10_000 + 1
    assert only_design - pairs <= package // 10_000 + 1
    # Integers throughout: the eager twin on the whole stream is the session in its chunks.
    assert re.search(r"events before t = \d+, the same as the session's in \d+ chunks", text)


def test_a_replay_too_short_for_three_chunks_is_refused(capsys):
    with pytest.raises(SystemExit):
        estimate.main(["--events", "1000"])
    assert "at least three 10 ms chunks" in capsys.readouterr().err
