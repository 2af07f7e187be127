"""PhotocurrentPooling's events mode: the one-word running sums against the two-word ones.

The one-word path (:func:`~evdown_torch.transforms.functional.photocurrent.one_word.one_word_sums`)
must decide every event exactly as the two-word path (``running_sums``) does, bit for bit, and
hand a piece over to it wherever it cannot be sure.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from evdown_torch import PhotocurrentPooling
from evdown_torch.events import Events
from evdown_torch.transforms.functional.photocurrent import events_mode as kernel
from evdown_torch.transforms.functional.photocurrent import one_word, sums
from tests.helpers import DVS_DTYPE, photocurrent_events_reference, random_stream, rows, spy


@pytest.fixture(autouse=True)
def one_word_for_every_piece(monkeypatch, eager):
    """Short test streams take the one-word sums too (the kernel keeps them to long pieces);
    the eager kernel runs (the compiled loop has no pieces: test_compiled_photocurrent.py)."""
    monkeypatch.setattr(kernel, "ONE_WORD_MIN_EVENTS", 2)


def _one_word_calls(monkeypatch) -> list[bool]:
    """Spy on the one-word sums: a list that gets, per call, whether they could be used."""
    return spy(monkeypatch, one_word, "one_word_sums",
               lambda out: isinstance(out, one_word.OneWordSums))


def _two_word_only(monkeypatch) -> None:
    monkeypatch.setattr(one_word, "one_word_sums", lambda *args, **kwargs: None)


CASES = [
    ((10, 7, 2), 2, 0.2, None),
    ((10, 7, 2), (3, 2), 0.3, 0.1),
    ((16, 16, 2), 4, 0.2, 0.05),
    ((12, 9, 2), 4, 0.05, 0.05),
    ((8, 8, 2), 1, 0.3, 0.5),
    ((6, 4, 2), 2, math.log(2), None),  # sums land exactly on levels (powers of two)
    ((6, 4, 2), (2, 1), math.log(2), 2 * math.log(2)),
]


@pytest.mark.parametrize(("sensor", "factor", "contrast", "threshold"), CASES)
def test_one_word_sums_give_the_two_word_result(sensor, factor, contrast, threshold, rng,
                                                monkeypatch):
    arr = random_stream(rng, 3000, sensor, t_max=2000)
    pool = PhotocurrentPooling(sensor, factor=factor, contrast=contrast, threshold=threshold)
    calls = _one_word_calls(monkeypatch)
    out = pool(arr)
    assert any(calls)  # the one-word path decided at least one piece
    _two_word_only(monkeypatch)
    assert len(out) > 20
    assert rows(out) == rows(pool(arr))


@pytest.mark.parametrize(("factor", "contrast", "threshold"), [
    (2, 0.2, None), ((2, 3), 0.5, 0.3), ((10, 7), 0.01, 0.004), (3, 1.5, 0.7)])
def test_one_word_sums_match_the_reference(factor, contrast, threshold, rng, monkeypatch):
    sensor = (10, 7, 2)
    arr = random_stream(rng, 500, sensor, t_max=300, sort=False)
    pool = PhotocurrentPooling(sensor, factor=factor, contrast=contrast, threshold=threshold)
    calls = _one_word_calls(monkeypatch)
    out = rows(pool(arr))
    assert all(calls)
    assert out == photocurrent_events_reference(arr, sensor, factor, contrast, pool.threshold)


def _session_agrees(pool, arr: np.ndarray, chunks: int, monkeypatch) -> tuple[int, int]:
    """Replay ``arr`` in ``chunks`` chunks with both paths, check they agree bit for bit.

    Returns ``(output events, pieces the one-word sums decided)``.
    """

    def replay() -> list:
        session = pool.session()
        return [row for chunk in np.array_split(arr, chunks) for row in rows(session(chunk))]

    calls = _one_word_calls(monkeypatch)
    fast = replay()
    _two_word_only(monkeypatch)
    assert fast == replay()
    return len(fast), sum(calls)


def test_one_word_sums_in_a_session(rng, monkeypatch):
    # Chunks resume from a state whose levels and references are far from 0.
    sensor = (16, 12, 2)
    arr = random_stream(rng, 6000, sensor, t_max=6000)
    arr["p"] = (arr["x"] < 8) ^ (np.arange(6000) % 5 == 0)  # a drift: levels move far
    pool = PhotocurrentPooling(sensor, factor=4, contrast=0.2)
    emitted, decided = _session_agrees(pool, arr, 7, monkeypatch)
    assert emitted > 100 and decided > 3


def test_pixels_too_dark_to_count(rng, monkeypatch):
    # c = 5: a pixel 10 levels below its region's brightest has a one-word intensity of 0,
    # and the kernel clamps it there; short chunks keep each piece's rise below the cap.
    sensor = (4, 2, 2)
    arr = random_stream(rng, 2000, sensor, t_max=4000)
    arr["p"] = (arr["x"] % 2 == 0) | (np.arange(2000) % 7 == 0)  # odd columns mostly fall
    pool = PhotocurrentPooling(sensor, factor=2, contrast=5.0, threshold=2.0)
    emitted, decided = _session_agrees(pool, arr, 200, monkeypatch)
    assert emitted > 50 and decided > 50


def test_near_a_snap_bound_the_two_word_sums_decide(rng, monkeypatch):
    # With a huge error bound every event near a level is in doubt: the piece goes to the
    # two-word sums, whose result it is.
    sensor = (6, 4, 2)
    arr = random_stream(rng, 2000, sensor, t_max=2000)
    pool = PhotocurrentPooling(sensor, factor=2, contrast=math.log(2))
    expected = rows(pool(arr))
    monkeypatch.setattr(one_word, "EPS", 2.0**-30)
    declined = spy(monkeypatch, kernel, "one_word_moves", lambda out: out is None)
    assert rows(pool(arr)) == expected
    assert any(declined)


def test_one_word_totals_are_the_exact_integer_sums(rng):
    # Each total is the sum of the region's pixels' table intensities after the event,
    # recomputed here from the levels event by event.
    sensor, factor, contrast = (6, 4, 2), (3, 2), 0.3
    arr = random_stream(rng, 400, sensor, t_max=400)
    events = Events.from_columns(arr["x"].astype(np.int64), arr["y"].astype(np.int64),
                                 arr["t"], arr["p"])
    levels = torch.zeros(24, dtype=torch.int64)
    levels[5], levels[7] = 3, -2
    out_w, per_region = 2, 6
    region = (events.y // 2) * out_w + events.x // 3
    region, order = torch.sort(region, stable=True)
    pixel = (events.y * 6 + events.x)[order]
    step = torch.where(events.p[order], 1, -1)
    key = torch.empty_like(pixel)
    current = levels.clone()
    for i, (p, s) in enumerate(zip(pixel.tolist(), step.tolist(), strict=True)):
        key[i] = 2 * current[p] + (s > 0)
        current[p] += s
    touched, counts = torch.unique_consecutive(region, return_counts=True)
    firsts = torch.cumsum(counts, 0) - counts
    ids, inside = kernel.region_pixel_ids(touched, sensor, factor)
    got = one_word.one_word_sums(key, ids, inside, levels, current, firsts, counts, per_region,
                             contrast, contrast)
    assert got is not None
    scale = math.ldexp(1.0, got.bits)
    current = levels.clone()
    for i, (p, s) in enumerate(zip(pixel.tolist(), step.tolist(), strict=True)):
        current[p] += s
        segment = int(got.region[i])
        j = current[ids[segment]] - got.top[segment]
        if inside is not None:
            j = j[inside[segment]]
        intensities = sums.intensity_words(j, contrast, scale, 1.0)[0]
        assert int(got.total[i]) == int(intensities.sum())
        assert int(got.top[segment]) >= int(current[ids[segment]].max())


def test_a_fresh_rise_past_the_exponent_cap_takes_a_new_anchor(monkeypatch):
    # One pixel rising 200 levels (c = 0.2: 40 log units, above MAX_EXPONENT) in one piece:
    # the one-word sums decline and the two-word ones anchor the region again as it climbs.
    n = 200
    arr = np.zeros(n, dtype=DVS_DTYPE)
    arr["t"] = np.arange(n)
    arr["p"] = True
    pool = PhotocurrentPooling((2, 2, 2), factor=2, contrast=0.2)
    calls = _one_word_calls(monkeypatch)
    anchors = spy(monkeypatch, sums, "rising_anchors", lambda out: out.level.tolist())
    out = rows(pool(arr))
    assert calls[0] is False
    assert anchors == [[0, 160]]  # an anchor every 32 / 0.2 = 160 levels
    _two_word_only(monkeypatch)
    assert out == rows(pool(arr))
    assert sorted(out) == sorted(photocurrent_events_reference(arr, (2, 2, 2), 2, 0.2, 0.2))
    assert len(out) > 150


def test_regions_rising_too_far_take_two_words_while_the_others_take_one(rng, monkeypatch):
    # One region's pixel rises 200 levels (c = 0.2: past MAX_EXPONENT) among random events:
    # the one-word sums name that region (TooBright) and decide the others, and that region
    # goes to the two-word sums in the same piece; the result is the two-word path's, bit
    # for bit.
    hot = np.zeros(200, dtype=DVS_DTYPE)
    hot["t"] = np.arange(200) * 5
    hot["p"] = True
    rest = random_stream(rng, 3000, (8, 8, 2), t_max=1000)
    rest = rest[(rest["x"] >= 2) | (rest["y"] >= 2)]
    arr = np.sort(np.concatenate([hot, rest]), order="t", kind="stable")
    pool = PhotocurrentPooling((8, 8, 2), factor=2, contrast=0.2)
    answers = spy(monkeypatch, one_word, "one_word_sums", lambda out: type(out).__name__)
    out = rows(pool(arr))
    assert answers[:2] == ["TooBright", "OneWordSums"]
    _two_word_only(monkeypatch)
    assert out == rows(pool(arr))
    assert sorted(out) == sorted(photocurrent_events_reference(arr, (8, 8, 2), 2, 0.2, 0.2))


def test_a_piece_that_decides_nothing_still_moves_on(monkeypatch):
    # c = 50 at factor 1: pixel 0 rises two levels (TooBright, held back) and pixel 1's first
    # event is an OFF, a sum e^-50 of its anchor that the two words cannot hold: the kept
    # regions keep nothing. The piece's first event then goes alone and the rest follows
    # (with DENSE_VALUES = 0 the held-back rounds never go dense; a piece that decided
    # nothing would come back unchanged for ever).
    monkeypatch.setattr(kernel, "DENSE_VALUES", 0)
    calls, piece = [], kernel._events_piece

    def counted(*args, **kwargs):
        calls.append(1)
        if len(calls) > 50:
            raise RuntimeError("the pieces make no progress")
        return piece(*args, **kwargs)

    monkeypatch.setattr(kernel, "_events_piece", counted)
    arr = np.zeros(6, dtype=DVS_DTYPE)
    arr["x"] = [0, 0, 1, 1, 0, 1]
    arr["t"] = np.arange(6)
    arr["p"] = [1, 1, 0, 0, 0, 1]
    pool = PhotocurrentPooling((2, 1, 2), factor=1, contrast=50.0, threshold=50.0)
    out = rows(pool(arr))
    assert out == photocurrent_events_reference(arr, (2, 1, 2), 1, 50.0, 50.0)
    assert len(out) == 6
