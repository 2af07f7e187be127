"""The streaming linear design's estimate (benchmarks/streaming_linear_estimate.py).

Its loops (evdown_torch/transforms/functional/compiled/linear_ramps.py) and eager twin
(benchmarks/streaming_linear_twin.py) are checked against the package's LinearEstimation
with the same ``max_delay``: hand-computed cases and random streams whose ramps often cross
a level exactly on a half tick or touch it (a fixed point alone misses some of those).
"""

from __future__ import annotations

import re

import numpy as np
import pytest

from benchmarks import streaming_linear_estimate as estimate
from benchmarks.streaming_linear_twin import FACTOR, SENSOR, THRESHOLD, RampArrays, design_whole
from evdown_torch.events import DVS_DTYPE
from evdown_torch.transforms.functional.compiled.linear_ramps import RampSettings
from evdown_torch.transforms.registry import make_method


def _events(rows: list[tuple[int, int, int, bool]]) -> np.ndarray:
    """A structured array from ``(x, y, t, p)`` rows, sorted by ``t`` (stable)."""
    rows = sorted(rows, key=lambda row: row[2])
    ev = np.zeros(len(rows), dtype=DVS_DTYPE)
    for name, k in (("x", 0), ("y", 1), ("t", 2), ("p", 3)):
        ev[name] = [row[k] for row in rows]
    return ev


def _rows(events: np.ndarray) -> list[tuple[int, int, int, bool]]:
    return sorted(map(tuple, events[["x", "y", "t", "p"]].tolist()))


def _package(events: np.ndarray, before: int) -> np.ndarray:
    a, b = THRESHOLD
    method = make_method("linear", SENSOR, FACTOR, threshold=a / b,
                         max_delay=estimate.REALTIME_MAX_DELAY_US)
    out = method(events)
    return out[out["t"] < before]


def test_without_numba_it_says_so(monkeypatch, capsys):
    monkeypatch.setattr(estimate, "numba_available", lambda: False)
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
    session = RampArrays(0, len(ev))
    out = session(ev)
    assert out["x"].tolist() == [0, 0] and out["y"].tolist() == [0, 0]
    assert out["t"].tolist() == [1667, 2600] and out["p"].tolist() == [True, False]
    assert session.horizon == 3000
    # The eager twin, the whole stream at once, gives the same events.
    whole = design_whole(ev, 3000)
    assert whole["t"].tolist() == [1667, 2600] and whole["p"].tolist() == [True, False]
    assert whole["x"].tolist() == [0, 0] and whole["y"].tolist() == [0, 0]
    # S reaches the level 0 at 2600, the ramps' end, where the integers are a hair off until
    # the ends' jumps correct them: decided on the corrected value (the twin: on the pixels'
    # segments). 1667 is far from a half tick.
    assert session.counts[0] >= 1 and session.counts[1] == 0
    assert _rows(_package(ev, 3000)) == _rows(out)


def test_a_crossing_on_a_half_tick_rounds_up():
    # Eight pixels of region (0, 0) go ON at 1000 (ramps over [0, 1000]: S = 4 at 500, 8 at
    # 1000) and again at 1999 (ramps over [1000, 1999]: S = 12 at 1499.5 exactly, 16 at
    # 1999). Rounded half up, 1499.5 is 1500; the fixed point's slope round(2**32 / 999)
    # puts it a hair below, so the crossing is decided on the corrected value.
    pytest.importorskip("numba")
    pixels = [(x, y) for y in (0, 1) for x in range(4)]
    ev = np.zeros(18, dtype=DVS_DTYPE)
    ev["x"] = [5] + [x for x, _ in pixels] * 2 + [5]
    ev["y"] = [5] + [y for _, y in pixels] * 2 + [5]
    ev["t"] = [0] + [1000] * 8 + [1999] * 8 + [4000]
    ev["p"] = True
    session = RampArrays(0, len(ev))
    out = session(ev)
    assert out["t"].tolist() == [500, 1000, 1500, 1999]
    assert session.counts[1] >= 1
    assert design_whole(ev, session.horizon)["t"].tolist() == [500, 1000, 1500, 1999]
    assert _rows(_package(ev, session.horizon)) == _rows(out)


def test_a_touch_of_a_level_between_knots_is_an_event():
    # Region (0, 0): pixels A = rows 0-1 go ON at 1000 (ramps [0, 1000]) and at 1998 (ramps
    # [1000, 1998]); pixels B = rows 2-3 go OFF at 1499 (ramps [499, 1499]) and at 1999
    # (ramps [1499, 1999]). S = 8 t / 1000 - 8 (t - 499) / 1000 = 3.992 on [499, 1000], then
    # 8 + 8 (t - 1000) / 998 - 8 (t - 499) / 1000, rising to exactly 12 - 8 = 4 (level 1) at
    # 1499, then falling (slope 8 / 998 - 16 / 1000) to 16 - 16 = 0 (level 0) at 1999. So one
    # ON event at 1499 (the touch, the rule's q goes to 1) and one OFF at 1999. The
    # fixed point's A slope round(2**32 / 998) is low, so A alone ends a hair under 4.
    pytest.importorskip("numba")
    a = [(x, y) for y in (0, 1) for x in range(4)]
    b = [(x, y) for y in (2, 3) for x in range(4)]
    ev = _events([(5, 5, 0, True), (5, 5, 5000, True)]
                 + [(x, y, t, True) for x, y in a for t in (1000, 1998)]
                 + [(x, y, t, False) for x, y in b for t in (1499, 1999)])
    session = RampArrays(0, len(ev))
    out = session(ev)
    assert _rows(out) == [(0, 0, 1499, True), (0, 0, 1999, False)]
    assert _rows(design_whole(ev, session.horizon)) == _rows(out)
    assert _rows(_package(ev, session.horizon)) == _rows(out)


def _random_stream(seed: int, n: int = 400) -> np.ndarray:
    # Two regions, times on a grid of 1, 2 or 250 us: many ramps of equal or related
    # lengths, so exact half ticks and exact touches of a level are common.
    rng = np.random.default_rng(seed)
    ev = np.zeros(n, DVS_DTYPE)
    ev["x"], ev["y"] = rng.integers(0, 8, n), rng.integers(0, 4, n)
    ev["t"] = np.sort(rng.choice(np.arange(0, 30_000, rng.choice([1, 2, 250])), n))
    ev["p"] = rng.random(n) < 0.5
    return ev


@pytest.mark.parametrize("seeds", [range(0, 20), range(20, 40)])
def test_random_streams_give_the_package_events_in_any_chunks(seeds):
    # The fixed point alone (no decision on a corrected value) differs from the package on 42 of
    # the first 300 seeds; this design on none. Each stream also goes through the session in
    # three chunks cut at random, empty ones included.
    pytest.importorskip("numba")
    for seed in seeds:
        ev = _random_stream(seed)
        whole_session = RampArrays(int(ev["t"][0]), len(ev))
        out = whole_session(ev)
        before = whole_session.horizon
        expected = _rows(_package(ev, before))
        assert _rows(out[out["t"] < before]) == expected, seed
        assert _rows(design_whole(ev, before)) == expected, seed
        cuts = np.sort(np.random.default_rng(seed).integers(0, len(ev), 2))
        chunked = RampArrays(int(ev["t"][0]), len(ev))
        parts = [chunked(ev[lo:hi]) for lo, hi in zip([0, *cuts], [*cuts, len(ev)])
                 if hi > lo]
        made = np.concatenate(parts)
        assert _rows(made[made["t"] < before]) == expected, seed


@pytest.mark.parametrize("case", range(12))
def test_other_settings_give_the_package_events(case):
    # Sensors the factor may not divide (smaller edge regions), non-square factors,
    # thresholds down to 0.05 and above 1, delays from 1 us, clocks near the int64 limit.
    pytest.importorskip("numba")
    rng = np.random.default_rng(1000 + case)
    width, height = (int(v) for v in rng.integers(3, 12, 2))
    factor = (min(int(rng.integers(1, 5)), width), min(int(rng.integers(1, 5)), height))
    threshold = [(1, 20), (1, 4), (3, 10), (1, 2), (1, 1), (3, 2)][case % 6]
    delay = [1, 7, 100, 1000][case % 4]
    n = 1000
    ev = np.zeros(n, DVS_DTYPE)
    ev["x"], ev["y"] = rng.integers(0, width, n), rng.integers(0, height, n)
    grid = int(rng.choice([1, 2, 5, 250]))
    ev["t"] = np.sort(rng.choice(np.arange(0, 20_000, grid), n)) + (2**62 if case % 3 == 0
                                                                      else 0)
    ev["p"] = rng.random(n) < 0.5
    settings = RampSettings.of((width, height, 2), factor, threshold, delay)
    session = RampArrays(int(ev["t"][0]), n, settings)
    out = session(ev)
    before = session.horizon
    method = make_method("linear", (width, height, 2), factor,
                         threshold=threshold[0] / threshold[1], max_delay=delay)
    expected = method(ev)
    expected = _rows(expected[expected["t"] < before])
    assert len(expected) >= 3  # (dozens to thousands but for thresholds above 1)
    assert _rows(out[out["t"] < before]) == expected
    assert _rows(design_whole(ev, before, settings)) == expected
    chunked = RampArrays(int(ev["t"][0]), n, settings)
    made = np.concatenate([chunked(ev[:100]), chunked(ev[100:100]), chunked(ev[100:])])
    assert _rows(made[made["t"] < before]) == expected


def test_ramps_longer_than_the_fixed_point_unit_give_the_package_events():
    # level_bits 40 leaves k = 14 bits: a ramp over more than 2**15 us rounds its slope to 0,
    # its whole rise coming as the end's jump (all of it error, corrected there).
    pytest.importorskip("numba")
    settings = RampSettings.of((8, 8, 2), (4, 4), (1, 4), 100_000, level_bits=40)
    assert settings.k == 14 and settings.slopes[40_000] == 0
    rng = np.random.default_rng(7)
    n = 400
    ev = np.zeros(n, DVS_DTYPE)
    ev["x"], ev["y"] = rng.integers(0, 8, n), rng.integers(0, 8, n)
    ev["t"] = np.sort(rng.choice(np.arange(0, 4_000_000, 250), n, replace=False))
    ev["p"] = rng.random(n) < 0.5
    session = RampArrays(int(ev["t"][0]), n, settings)
    out = session(ev)
    before = session.horizon
    method = make_method("linear", (8, 8, 2), 4, threshold=0.25, max_delay=100_000)
    expected = method(ev)
    expected = _rows(expected[expected["t"] < before])
    assert len(expected) > 10
    assert _rows(out[out["t"] < before]) == expected
    assert _rows(design_whole(ev, before, settings)) == expected


def test_settings_whose_integers_cannot_hold_are_refused():
    with pytest.raises(ValueError, match="under 8 bits"):
        RampSettings.of((128, 128, 2), (16, 16), (1, 10**9), 1000)


def test_rings_grow_to_a_chunk_and_a_level_beyond_the_headroom_raises():
    pytest.importorskip("numba")
    # 400 events within D of each other, in a session sized for 4 a chunk (rings of 16):
    # the rings grow to the chunk, unswept entries in place, and give the events of a session
    # sized for the whole stream.
    ev = _events([(x % 8, x % 3, 2 * x, x % 5 != 0) for x in range(400)] + [(0, 0, 5000, True)])
    small, whole = RampArrays(0, 4), RampArrays(0, len(ev))
    mask = small.session.mask
    made = np.concatenate([small(ev[:3]), small(ev[3:300]), small(ev[300:])])
    assert small.session.mask > mask
    assert _rows(made) == _rows(whole(ev)) and len(made) > 10
    # One pixel's level climbing to 9 where the headroom is 1 * 2**3 levels (factor 1).
    settings = RampSettings.of((4, 4, 2), (1, 1), (1, 1), 1000, level_bits=3)
    ev = _events([(0, 0, 3000 * k, True) for k in range(12)])
    session = RampArrays(0, len(ev), settings)
    with pytest.raises(ValueError, match="headroom"):
        session(ev)
    fine = RampArrays(0, len(ev), RampSettings.of(
        (4, 4, 2), (1, 1), (1, 1), 1000, level_bits=4))
    assert fine(ev)["t"].tolist() == [3000 * k for k in range(11)]


def test_on_a_tiny_replay_it_makes_the_package_events(capsys):
    pytest.importorskip("numba")
    assert estimate.main(["--events", "700000", "--chunks", "1"]) == 0
    text = capsys.readouterr().out
    found = re.search(r"package ([\d,]+) events, ramps alone ([\d,]+); in one and not the other: "
                      r"([\d,]+) and ([\d,]+), of which ([\d,]+) pairs", text)
    assert found is not None, text
    package, design, only_package, only_design, pairs = (
        int(group.replace(",", "")) for group in found.groups())
    assert package > 1000
    assert (design, only_package, only_design, pairs) == (package, 0, 0, 0)
    assert re.search(r"windowed session: [\d,]+ events, the same as its session through the "
                     r"ramps", text)
    # Integers throughout: the eager twin on the whole stream is the session in its chunks.
    assert re.search(r"events before t = \d+, the same as the session's in \d+ chunks", text)


def test_a_replay_too_short_for_three_chunks_is_refused(capsys):
    with pytest.raises(SystemExit):
        estimate.main(["--events", "1000"])
    assert "at least three 10 ms chunks" in capsys.readouterr().err
