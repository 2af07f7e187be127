"""PhotocurrentPooling against slow float64 references of both modes, limits and invariants."""

from __future__ import annotations

import math
from collections import defaultdict
from fractions import Fraction

import numpy as np
import pytest
import torch

from evdown_torch import EventCount, PhotocurrentPooling
from evdown_torch.transforms.registry import make_method
from tests.helpers import (
    DVS_DTYPE,
    as_tuples,
    photocurrent_events_reference,
    random_stream,
    region_members,
    rows,
    spy,
)

SENSOR = (10, 7, 2)
SNAP = 1e-9


def test_hand_computed_region():
    # 2x1 region, c = theta = ln 2: intensities 1 -> (2 + 1) / 2 -> (2 + 2) / 2 = 2 (log 2, ON)
    # -> (4 + 2) / 2 = 3 (log2 3 = 1.58, no event) -> (4 + 4) / 2 = 4 (ON) -> (2 + 4) / 2 = 3
    # (inside (1, 2) from above: no event) -> (2 + 2) / 2 = 2 (level 1: OFF).
    ev = np.array([(0, 0, True, 1), (1, 0, True, 2), (0, 0, True, 3), (1, 0, True, 4),
                   (0, 0, False, 5), (1, 0, False, 6)], dtype=DVS_DTYPE)
    out = PhotocurrentPooling((2, 1, 2), factor=(2, 1), contrast=math.log(2))(ev)
    assert out.tolist() == [(0, 0, True, 2), (0, 0, True, 4), (0, 0, False, 6)]


def test_linear_intensity_averaging_favours_bright_pixels():
    # One pixel up two steps: (4 + 1) / 2 = 2.5, log2 2.5 = 1.32 -> one ON. Flipped: (1/4 + 1)
    # / 2 = 0.625, log2 0.625 = -0.68 -> nothing. Polarity flip is no invariant of method 7
    # (SEMANTICS.md keeps it for methods 3 to 5); it is for factor 1.
    ev = torch.tensor([[0, 0, 1, 1], [0, 0, 2, 1]])
    pool = PhotocurrentPooling((2, 1, 2), factor=(2, 1), contrast=math.log(2))
    assert pool(ev).tolist() == [[0, 0, 2, 1]]
    flipped = ev.clone()
    flipped[:, 3] = 0
    assert pool(flipped).tolist() == []


def test_polarity_flip_with_factor_one(rng):
    arr = random_stream(rng, 600, SENSOR, t_max=500)
    pool = PhotocurrentPooling(SENSOR, factor=1, contrast=0.3, threshold=0.5)
    flipped = arr.copy()
    flipped["p"] = ~arr["p"]
    expected = [(x, y, t, not on) for x, y, t, on in as_tuples(pool(arr))]
    assert as_tuples(pool(flipped)) == sorted(expected)


@pytest.mark.parametrize("factor", [2, 3, (2, 3), (10, 7)])
@pytest.mark.parametrize(("contrast", "threshold"), [(0.2, None), (0.2, 0.05), (0.5, 0.3),
                                                    (1.5, 0.7), (0.01, 0.004)])
def test_events_mode_matches_reference(factor, contrast, threshold, rng):
    arr = random_stream(rng, 500, SENSOR, t_max=300, sort=False)
    pool = PhotocurrentPooling(SENSOR, factor=factor, contrast=contrast, threshold=threshold)
    expected = photocurrent_events_reference(arr, SENSOR, factor, contrast, pool.threshold)
    assert rows(pool(arr)) == expected


def hot_pixel_stream(rng, n_hot, n_on, *, dt, n_rest):
    """A hot pixel (0, 0): ``n_hot`` events ``dt`` apart, the first ``n_on`` ON, mixed in time
    with ``n_rest`` random events on a (4, 4, 2) sensor over the same span."""
    hot = np.zeros(n_hot, dtype=DVS_DTYPE)
    hot["t"] = np.arange(n_hot) * dt
    hot["p"][:n_on] = True
    rest = random_stream(rng, n_rest, (4, 4, 2), t_max=n_hot * dt)
    return np.sort(np.concatenate([hot, rest]), order="t", kind="stable")


def test_hot_pixel_far_beyond_float_range(rng):
    # 4000 ON then 4000 OFF at one pixel: c * L reaches 1000 (exp overflows), so the kernel
    # must cut the stream and re-anchor; its neighbours keep moving meanwhile.
    arr = hot_pixel_stream(rng, 8000, 4000, dt=2, n_rest=3000)
    pool = PhotocurrentPooling((4, 4, 2), factor=2, contrast=0.25, threshold=0.4)
    expected = photocurrent_events_reference(arr, (4, 4, 2), 2, 0.25, 0.4)
    assert sorted(rows(pool(arr))) == sorted(expected)


def _spy_pieces(kernel, monkeypatch) -> list:
    """Per call of the events mode's ``_events_piece``: ``None`` when it held nothing back,
    else whether each held-back event lies in region (0, 0) of a factor 2."""
    held, piece = [], kernel._events_piece

    def spy(events, *args, **kwargs):
        out = piece(events, *args, **kwargs)
        held.append(None if out.rest is None else (events.x[out.rest] // 2 == 0)
                    & (events.y[out.rest] // 2 == 0))
        return out

    monkeypatch.setattr(kernel, "_events_piece", spy)
    return held


@pytest.mark.usefixtures("eager")  # its internal steps
def test_a_climbing_region_is_decided_in_its_piece(rng, monkeypatch):
    # 600 ON at pixel (0, 0) (c = 0.25: 150 log units) among random events elsewhere: the
    # one-word sums decide every other region, and the two-word sums the hot one in the same
    # piece, with anchors 32 / 0.25 = 128 levels apart.
    from evdown_torch.transforms.functional.photocurrent import events_mode as kernel
    from evdown_torch.transforms.functional.photocurrent import one_word as one_word_module
    from evdown_torch.transforms.functional.photocurrent import sums

    monkeypatch.setattr(kernel, "ONE_WORD_MIN_EVENTS", 256)
    anchors = spy(monkeypatch, sums, "rising_anchors", lambda out: out.level.tolist())
    one_word = spy(monkeypatch, one_word_module, "one_word_sums", lambda out: type(out).__name__)
    held = _spy_pieces(kernel, monkeypatch)
    arr = hot_pixel_stream(rng, 600, 600, dt=2, n_rest=1500)
    out = PhotocurrentPooling((4, 4, 2), factor=2, contrast=0.25, threshold=0.4)(arr)
    assert held == [None] and one_word == ["TooBright", "OneWordSums"]
    assert len(anchors) == 1 and anchors[0][:2] == [0, 128]
    assert np.all(np.diff(out["t"].astype(np.int64)) >= 0)
    expected = photocurrent_events_reference(arr, (4, 4, 2), 2, 0.25, 0.4)
    assert sorted(rows(out)) == sorted(expected)


@pytest.mark.usefixtures("eager")  # its internal steps
@pytest.mark.parametrize("dense_values", [0, None])
def test_a_falling_region_is_held_back_alone(dense_values, rng, monkeypatch):
    # 600 ON then 600 OFF at pixel (0, 0) (c = 0.25): after the climb, the region falls 150
    # log units below its anchor, where the two-word sums cannot hold it. Only that region
    # waits; its events follow in rounds re-anchored where it was cut (DENSE_VALUES = 0), or
    # in one dense round; either way the outputs come back in time order.
    from evdown_torch.transforms.functional.photocurrent import events_mode as kernel

    monkeypatch.setattr(kernel, "ONE_WORD_MIN_EVENTS", 256)
    if dense_values is not None:
        monkeypatch.setattr(kernel, "DENSE_VALUES", dense_values)
    held = _spy_pieces(kernel, monkeypatch)
    arr = hot_pixel_stream(rng, 1200, 600, dt=2, n_rest=1500)
    out = PhotocurrentPooling((4, 4, 2), factor=2, contrast=0.25, threshold=0.4)(arr)
    assert held[0] is not None and bool(held[0].all())  # only region (0, 0) waits
    if dense_values == 0:
        assert len(held) > 2 and held[-1] is None
    else:
        assert len(held) == 2 and held[1] is None
    assert np.all(np.diff(out["t"].astype(np.int64)) >= 0)
    expected = photocurrent_events_reference(arr, (4, 4, 2), 2, 0.25, 0.4)
    assert sorted(rows(out)) == sorted(expected)


@pytest.mark.parametrize("step", [1, 3, 128])
def test_rising_anchors_against_a_loop(step, rng):
    # Regions of 4 pixels, each event's level before it relative to its region's brightest
    # before the piece (0); the anchors replayed one event at a time.
    from evdown_torch.transforms.functional.photocurrent.sums import rising_anchors

    start = rng.integers(-6, 1, (5, 4))
    start[np.arange(5), rng.integers(0, 4, 5)] = 0  # each region's brightest is 0
    counts = rng.integers(1, 40, 5)
    keys, ranks, slots, expected = [], [], [], {"level": [], "region": [], "firsts": [],
                                                "anchor_of": [], "pixel_level": []}
    for r, count in enumerate(counts):
        level, reach, run_k = start[r].copy(), 0, None
        for _ in range(count):
            slot, on = int(rng.integers(0, 4)), int(rng.random() < 0.75)  # mostly climbing
            k = reach // step
            if k != run_k:  # a new anchor: the region's levels as they are now
                run_k = k
                expected["level"].append(k * step)
                expected["region"].append(r)
                expected["firsts"].append(len(keys))
                expected["pixel_level"].append(level.tolist())
            expected["anchor_of"].append(len(expected["level"]) - 1)
            keys.append(2 * int(level[slot]) + on)
            ranks.append(r)
            slots.append(slot)
            level[slot] += 1 if on else -1
            reach = max(reach, int(level[slot]))
    firsts = torch.tensor(np.concatenate([[0], np.cumsum(counts)[:-1]]))
    got = rising_anchors(torch.tensor(keys), torch.tensor(ranks), firsts, torch.tensor(start),
                         torch.tensor(slots), step)
    for name, values in expected.items():
        assert getattr(got, name).tolist() == values, name


@pytest.mark.parametrize(("sensor", "factor", "contrast"), [
    ((4, 4, 2), 2, 0.25), ((5, 4, 2), 2, 2.0), ((6, 4, 2), (3, 2), 40.0)])
def test_climbing_regions_match_the_reference_in_one_call_and_in_chunks(sensor, factor,
                                                                        contrast, rng):
    # Hot pixels in two regions climb far past MAX_EXPONENT at different times, then fall
    # back, among random events: the running sums take new anchors as they climb.
    hot = []
    for x, y, start in ((0, 0, 0), (sensor[0] - 1, sensor[1] - 1, 300)):
        part = np.zeros(400, dtype=DVS_DTYPE)
        part["x"], part["y"], part["t"] = x, y, start + np.arange(400)
        part["p"][:300] = True
        hot.append(part)
    arr = np.sort(np.concatenate([*hot, random_stream(rng, 600, sensor, t_max=700)]),
                  order="t", kind="stable")
    pool = PhotocurrentPooling(sensor, factor=factor, contrast=contrast, threshold=0.3)
    expected = photocurrent_events_reference(arr, sensor, factor, contrast, 0.3)
    assert sorted(rows(pool(arr))) == sorted(expected)
    session = pool.session()
    chunks = [session(arr[a:b]) for a, b in ((0, 250), (250, 900), (900, len(arr)))]
    assert sorted(rows(np.concatenate([*chunks, session.flush()]))) == sorted(expected)


@pytest.mark.parametrize("factor", [2, (3, 2)])
def test_a_batch_with_a_hot_recording_equals_one_by_one(factor, rng):
    # Stacked recordings (regions of several recordings in one piece): only the hot pixel's
    # region of the first recording is held back; every recording's output is its own.
    pool = PhotocurrentPooling((4, 4, 2), factor=factor, contrast=0.25, threshold=0.4)
    recordings = [hot_pixel_stream(rng, 600, 600, dt=2, n_rest=800),
                  random_stream(rng, 900, (4, 4, 2), t_max=1200),
                  hot_pixel_stream(rng, 300, 150, dt=3, n_rest=200)]
    for recording, output in zip(recordings, pool.batch(recordings), strict=True):
        assert output.tolist() == pool(recording).tolist()


@pytest.mark.parametrize(("sensor", "factor", "contrast"), [
    ((8, 8, 2), 2, 0.3), ((10, 7, 2), (3, 2), 0.2), ((6, 4, 2), 1, 0.5), ((8, 6, 2), 4, 37.0)])
def test_a_dense_piece_gives_the_running_sums_result(sensor, factor, contrast, rng):
    # Every event's sum from a row of its region's levels after it, against the kernel's
    # running sums on the same stream from the same state (partial edge regions, factor 1, a
    # contrast past MAX_EXPONENT, where the running sums hold regions back).
    from evdown_torch.events import Events
    from evdown_torch.transforms.functional.photocurrent import events_mode as kernel

    arr = random_stream(rng, 3000, sensor, t_max=2000)
    events = Events.from_columns(arr["x"].astype(np.int64), arr["y"].astype(np.int64),
                                 arr["t"], arr["p"])
    fx, fy = (factor, factor) if isinstance(factor, int) else factor
    state = kernel.initial_state(sensor, (fx, fy))
    state.level[::3] = 2
    settings_ = {"sensor_size": sensor, "factor": (fx, fy), "contrast": contrast,
                 "threshold": 0.3}
    dense = kernel._events_piece(events, dense=True, state=state, **settings_)
    assert dense.rest is None
    assert dense.out.num_events > 100
    summed, summed_state = kernel.photocurrent_sorted(events, state=state, **settings_)
    assert all(torch.equal(a, b) for a, b in zip(dense.out, summed, strict=True))
    assert torch.equal(dense.state.level, summed_state.level)
    assert torch.equal(dense.state.reference, summed_state.reference)


@pytest.mark.parametrize("contrast", [0.2, 1e-4, 37.3, 50.0])
@pytest.mark.parametrize("spread", [3, 5000, 10**6])
def test_log_mean_exp_is_the_direct_sum_bit_for_bit(contrast, spread):
    # The table of exp(c * j) against each entry's own exp, with and without an edge mask,
    # levels spanning more than the table (10**6) and intensities that underflow (c = 50).
    from evdown_torch.transforms.functional.photocurrent.levels import log_mean_exp

    gen = torch.Generator().manual_seed(spread)
    levels = torch.randint(-spread, spread + 1, (500, 12), generator=gen)
    inside = torch.rand(500, 12, generator=gen) > 0.3
    inside[:, 3] = True
    for mask in (None, inside):
        ok = torch.ones_like(levels, dtype=torch.bool) if mask is None else mask
        m = torch.where(ok, levels, torch.iinfo(torch.int64).min).amax(1)
        direct = torch.where(ok, torch.exp((levels - m[:, None]).to(torch.float64) * contrast),
                             0.0).sum(1)
        got_m, got = log_mean_exp(levels, mask, contrast)
        assert torch.equal(got_m, m)
        assert torch.equal(got, direct)


def test_region_levels_after_each_event(rng):
    # Against replaying the events one by one on a copy of the levels.
    from evdown_torch.events import Events
    from evdown_torch.transforms.functional.photocurrent.levels import (
        region_levels_after,
        region_pixel_ids,
    )

    sensor, factor = (6, 4, 2), (3, 2)
    arr = random_stream(rng, 500, sensor, t_max=500)
    events = Events.from_columns(arr["x"].astype(np.int64), arr["y"].astype(np.int64),
                                 arr["t"], arr["p"])
    region = (events.y // 2) * 2 + events.x // 3
    region, order = torch.sort(region, stable=True)
    grouped = events.select(order)
    touched, counts = torch.unique_consecutive(region, return_counts=True)
    firsts = torch.cumsum(counts, 0) - counts
    segment = torch.repeat_interleave(torch.arange(touched.shape[0]), counts)
    levels = torch.from_numpy(rng.integers(-5, 5, 24))
    ids, _ = region_pixel_ids(touched, sensor, factor)
    got = region_levels_after(grouped, factor, segment, firsts, levels[ids])
    current = levels.clone()
    for i in range(events.num_events):
        x, y, on = int(grouped.x[i]), int(grouped.y[i]), bool(grouped.p[i])
        current[y * 6 + x] += 1 if on else -1
        assert got[i].tolist() == current[ids[segment[i]]].tolist()


def test_factor_one_threshold_contrast_returns_input(rng):
    arr = random_stream(rng, 2000, SENSOR, t_max=1000)  # many same-pixel same-time events too
    for contrast in (0.2, 0.15, 1.0, 3.7):
        out = PhotocurrentPooling(SENSOR, factor=1, contrast=contrast)(arr)
        assert as_tuples(out) == as_tuples(arr)


def _mean_on_level(arr, sensor, factor, threshold):
    """Regions whose mean level ever lies exactly on a level of EventCount(threshold)."""
    fx, fy, _, _, members = region_members(sensor, factor)
    theta = Fraction(threshold)
    total, hit = defaultdict(int), set()
    for i in np.argsort(arr["t"], kind="stable"):
        r = (int(arr["x"][i]) // fx, int(arr["y"][i]) // fy)
        total[r] += 1 if arr["p"][i] > 0 else -1
        if (Fraction(total[r], len(members[r])) / theta).denominator == 1:
            hit.add(r)
    return hit


@pytest.mark.parametrize("factor", [2, (3, 2)])
def test_small_contrast_limit_is_event_count(factor, rng):
    threshold = 0.37
    arr = random_stream(rng, 3000, SENSOR, t_max=2000)
    on_level = _mean_on_level(arr, SENSOR, factor, threshold)
    c = 1e-4
    pool = PhotocurrentPooling(SENSOR, factor=factor, contrast=c, threshold=c * threshold)
    got = [e for e in rows(pool(arr)) if e[:2] not in on_level]
    expected = [e for e in rows(EventCount(SENSOR, factor=factor, threshold=threshold)(arr))
                if e[:2] not in on_level]
    assert len(expected) > 100  # plenty of regions never sit on a level
    assert got == expected


@pytest.mark.parametrize("fps", [None, 1000.0])
def test_clock_shift_at_unix_epoch_magnitude(fps, rng):
    arr = random_stream(rng, 800, SENSOR, t_max=50_000)
    pool = PhotocurrentPooling(SENSOR, factor=2, contrast=0.3, threshold=0.2, fps=fps)
    shift = 1_700_000_000_000_000  # 1.7e15 us
    shifted = arr.copy()
    shifted["t"] += shift
    base = pool(arr)
    assert len(base) > 50
    expected = [(x, y, t + shift, on) for x, y, t, on in as_tuples(base)]
    assert as_tuples(pool(shifted)) == expected


@pytest.mark.parametrize("seed", range(4))
def test_streaming_equals_batch(seed):
    rng = np.random.default_rng(seed)
    arr = random_stream(rng, 3000, SENSOR, t_max=3000)
    pool = PhotocurrentPooling(SENSOR, factor=(3, 2), contrast=0.25, threshold=0.3)
    cuts = np.sort(rng.integers(0, len(arr) + 1, 12))
    cuts = np.concatenate([[0], cuts, cuts[:3], [len(arr)]])  # repeated cuts: empty chunks
    cuts.sort()
    session = pool.session()
    pieces = [session(arr[a:b]) for a, b in zip(cuts[:-1], cuts[1:], strict=True)]
    assert rows(np.concatenate(pieces)) == rows(pool(arr))


@pytest.mark.parametrize("fps", [None, 100.0])
def test_session_rejects_out_of_order_chunks(fps):
    session = PhotocurrentPooling(SENSOR, fps=fps).session()
    session(torch.tensor([[0, 0, 10, 1]]))
    with pytest.raises(ValueError, match="follow each other in time"):
        session(torch.tensor([[0, 0, 5, 1]]))


@pytest.mark.parametrize("fps", [None, 500.0])
def test_empty_and_single_event(fps):
    pool = PhotocurrentPooling(SENSOR, factor=2, contrast=0.2, fps=fps)
    empty = np.zeros(0, dtype=DVS_DTYPE)
    out = pool(empty)
    assert out.dtype == DVS_DTYPE and len(out) == 0
    assert pool(torch.zeros((0, 4), dtype=torch.int64)).shape == (0, 4)
    single = np.array([(3, 4, True, 77)], dtype=DVS_DTYPE)
    # One ON in a 2x2 region: (e^0.2 + 3) / 4 is far below the level e^0.2: nothing.
    assert len(pool(single)) == 0
    one = PhotocurrentPooling(SENSOR, factor=1, contrast=0.2, fps=fps)(single)
    assert one.tolist() == [(3, 4, True, 77)]


def test_kinds_in_kinds_out_input_untouched(rng):
    arr = random_stream(rng, 400, SENSOR, t_max=1000)
    before = arr.copy()
    pool = PhotocurrentPooling(SENSOR, factor=2, contrast=0.3, threshold=0.15)
    out_arr = pool(arr)
    assert out_arr.dtype == DVS_DTYPE and np.array_equal(arr, before)
    tensor = torch.as_tensor(np.stack([arr["x"], arr["y"], arr["t"],
                                       np.where(arr["p"], 1, -1)], axis=1).astype(np.int64))
    tensor_before = tensor.clone()
    out_tensor = pool(tensor)
    assert torch.equal(tensor, tensor_before)
    assert out_tensor.dtype == torch.int64 and out_tensor.shape[1] == 4
    assert set(out_tensor[:, 3].tolist()) <= {-1, 1}
    assert out_tensor[:, :3].tolist() == [list(r[:2]) + [r[3]] for r in out_arr.tolist()]
    assert (out_tensor[:, 0] < 5).all() and (out_tensor[:, 1] < 4).all()
    assert (out_tensor[1:, 2] >= out_tensor[:-1, 2]).all()


def test_device(device, dtype, rng):
    arr = random_stream(rng, 500, SENSOR, t_max=1000)
    tensor = torch.as_tensor(np.stack([arr["x"], arr["y"], arr["t"], arr["p"]], axis=1)
                             .astype(np.int64))
    for fps in (None, 2000.0):
        pool = PhotocurrentPooling(SENSOR, factor=2, contrast=0.3, fps=fps)
        out = pool(tensor.to(device, dtype))
        assert out.device.type == device.type and out.dtype == dtype
        if fps is None:  # against the reference: events at their triggering input's time
            got = [(int(x), int(y), t, p > 0) for x, y, t, p in out.cpu().tolist()]
            assert sorted(got) == sorted(photocurrent_events_reference(arr, SENSOR, 2, 0.3, 0.3))
        assert out.cpu().tolist() == pool(tensor.to(dtype)).tolist()


@pytest.mark.parametrize(("settings", "message"), [
    ({"contrast": 0.0}, "contrast"), ({"contrast": -0.2}, "contrast"),
    ({"contrast": math.nan}, "contrast"), ({"contrast": math.inf}, "contrast"),
    ({"contrast": 100.0}, "contrast"), ({"threshold": 0.0}, "threshold"),
    ({"threshold": math.inf}, "threshold"), ({"fps": 0.0}, "fps"), ({"fps": -5.0}, "fps"),
    ({"fps": math.nan}, "fps"), ({"fps": 100.0, "cutoff_hz": -1.0}, "cutoff_hz"),
    ({"cutoff_hz": 3.0}, "cutoff_hz"),
])
def test_bad_settings_are_refused(settings, message):
    with pytest.raises(ValueError, match=message):
        PhotocurrentPooling(SENSOR, **settings)


def test_registry_and_budget_setting():
    pool = make_method("photocurrent", SENSOR, 2, contrast=0.3, threshold=0.1)
    assert isinstance(pool, PhotocurrentPooling)
    assert pool.output_sensor_size == (5, 4, 2)
    assert PhotocurrentPooling.budget_setting == "threshold"
    assert PhotocurrentPooling(SENSOR).threshold == 0.2


def test_streaming_equals_batch_across_cuts(rng):
    # A hot pixel forces the kernel to cut pieces and re-anchor; a session must agree.
    arr = hot_pixel_stream(rng, 3000, 2000, dt=3, n_rest=2000)
    pool = PhotocurrentPooling((4, 4, 2), factor=2, contrast=0.3, threshold=0.2)
    session = pool.session()
    cuts = np.concatenate([[0], np.sort(rng.integers(0, len(arr), 9)), [len(arr)]])
    pieces = [session(arr[a:b]) for a, b in zip(cuts[:-1], cuts[1:], strict=True)]
    batch = pool(arr)
    assert rows(np.concatenate(pieces)) == rows(batch)
    assert sorted(rows(batch)) == sorted(photocurrent_events_reference(arr, (4, 4, 2), 2, 0.3, 0.2))


# --- Paths of the events-mode kernel chosen by size (table, place keys, anchors, cuts) ------


def _pieces(monkeypatch):
    """Spy on the kernel's pieces: a list that gets the number of events it decided in each."""
    from evdown_torch.transforms.functional.photocurrent import events_mode as kernel

    used, piece = [], kernel._events_piece

    def spy(events, *args, **kwargs):
        out = piece(events, *args, **kwargs)
        used.append(events.num_events - (0 if out.rest is None else out.rest.shape[0]))
        return out

    monkeypatch.setattr(kernel, "_events_piece", spy)
    return used


@pytest.mark.parametrize(("sensor", "factor", "threshold"), [
    ((40, 40, 2), 2, 0.1), ((48, 36, 2), (4, 3), 0.1), ((40, 30, 2), (20, 15), 0.004),
    ((40, 40, 2), 1, 0.1), ((512, 300, 2), 2, 0.1), ((256, 256, 2), 1, 0.1)])
def test_events_mode_matches_reference_on_wider_sensors(sensor, factor, threshold, rng):
    # More regions than the one-byte place key's region bits (40x40 / 2: 400 > 64), whole
    # regions (no edge mask), 300 pixels a region (a two-byte place key), factor 1, and more
    # than 2**15 regions (int32 region ids).
    arr = random_stream(rng, 4000, sensor, t_max=3000)
    pool = PhotocurrentPooling(sensor, factor=factor, contrast=0.3, threshold=threshold)
    expected = photocurrent_events_reference(arr, sensor, factor, 0.3, threshold)
    assert len(expected) > 100
    assert rows(pool(arr)) == expected


@pytest.mark.usefixtures("eager")  # its internal steps
def test_levels_spanning_more_than_the_table(monkeypatch):
    # 70,000 ON at one pixel of a 2x1 region (c * L reaches 7): a piece's levels span more
    # than TABLE_SIZE, so the intensities are computed per event instead of looked up.
    from evdown_torch.transforms.functional.photocurrent.sums import TABLE_SIZE

    n = 70_000
    arr = np.zeros(n + 2, dtype=DVS_DTYPE)
    arr["t"] = np.arange(n + 2)
    arr["p"][:n] = True
    arr["x"][n:] = 1  # then the other pixel goes down twice
    pool = PhotocurrentPooling((2, 1, 2), factor=(2, 1), contrast=1e-4, threshold=1e-3)
    pieces = _pieces(monkeypatch)
    out = rows(pool(arr))
    assert max(pieces) > TABLE_SIZE - 3
    expected = photocurrent_events_reference(arr, (2, 1, 2), (2, 1), 1e-4, 1e-3)
    assert len(expected) > 500
    assert out == expected


@pytest.mark.usefixtures("eager")  # its internal steps
def test_region_far_below_its_anchor_is_reanchored(monkeypatch, rng):
    # Every pixel of a 2x2 region falls 130 levels (c = 0.5: a photocurrent e^-65 of its
    # anchor's) within one piece: the fixed-point sums lose their precision there, so the
    # kernel cuts the piece and re-anchors; the result still equals the reference.
    fall = np.zeros(520, dtype=DVS_DTYPE)
    fall["x"], fall["y"] = np.tile([0, 1, 0, 1], 130), np.tile([0, 0, 1, 1], 130)
    fall["t"] = np.arange(520) * 2
    rest = random_stream(rng, 300, (4, 4, 2), t_max=1040)
    arr = np.sort(np.concatenate([fall, rest]), order="t", kind="stable")
    pool = PhotocurrentPooling((4, 4, 2), factor=2, contrast=0.5, threshold=0.3)
    pieces = _pieces(monkeypatch)
    out = rows(pool(arr))
    assert len(pieces) > 1  # cut at least once
    assert sorted(out) == sorted(photocurrent_events_reference(arr, (4, 4, 2), 2, 0.5, 0.3))


@pytest.mark.parametrize(("contrast", "threshold"), [(45.0, 20.0), (33.0, 50.0)])
def test_contrasts_above_the_exponent_cap(contrast, threshold, rng):
    # One level is more than MAX_EXPONENT (32) in log units: every piece is cut at a pixel
    # rising twice above its anchor, and a lone event must still be exact.
    arr = random_stream(rng, 300, (4, 2, 2), t_max=1000)
    pool = PhotocurrentPooling((4, 2, 2), factor=2, contrast=contrast, threshold=threshold)
    expected = photocurrent_events_reference(arr, (4, 2, 2), 2, contrast, threshold)
    assert len(expected) > 20
    assert rows(pool(arr)) == expected


def test_pixels_too_dark_to_count(rng):
    # c = 20: exp(c * j) underflows to 0 for pixels 40 levels below their region's brightest,
    # which the kernel clamps there; regions with such pixels still match the reference.
    arr = random_stream(rng, 1000, (4, 2, 2), t_max=3000)
    arr["p"] = (arr["x"] % 2 == 0) | (np.arange(1000) % 7 == 0)  # odd columns mostly fall
    pool = PhotocurrentPooling((4, 2, 2), factor=2, contrast=20.0, threshold=5.0)
    expected = photocurrent_events_reference(arr, (4, 2, 2), 2, 20.0, 5.0)
    assert len(expected) > 50
    assert rows(pool(arr)) == expected


@pytest.mark.parametrize("contrast", [0.2, 1e-4, 37.3])
def test_fixed_point_intensities_are_within_a_few_ulps(contrast):
    # exp(c * j) however large |c * j| is (the float product c * j alone would be off by
    # |c * j| / 2 ulps): against exact decimal arithmetic.
    from decimal import Decimal, localcontext

    from evdown_torch.transforms.functional.photocurrent.sums import intensity_words

    scale, fine = 2.0**10, 2.0**40
    js = sorted(j for j in {0, 1, -1, 7, -7, 150, -3000, -int(700 / contrast),
                            int(30 / contrast)} if -700 <= contrast * j <= 30)
    high, low = intensity_words(torch.tensor(js), contrast, scale, fine)
    with localcontext() as context:
        context.prec = 60
        for j, h, lo in zip(js, high.tolist(), low.tolist(), strict=True):
            exact = (Decimal(contrast) * j).exp() * Decimal(scale)
            got = Decimal(h) + Decimal(lo) / Decimal(fine)
            assert abs(got - exact) <= exact * Decimal(4 * 2.0**-53) + Decimal(0.5 / fine)


def test_levels_beyond_float_resolution_are_refused():
    # contrast / threshold = 1e6 output levels per input level: a pixel 2**40 levels up would
    # put u beyond 2**50, where float64 cannot tell levels apart.
    from evdown_torch.events import Events
    from evdown_torch.transforms.functional.photocurrent.events_mode import (
        initial_state,
        photocurrent_sorted,
    )

    state = initial_state(SENSOR, (2, 2))
    state.level[3 * SENSOR[0] + 4] = 2**40
    ev = Events.from_columns([4], [3], [10], [1])
    with pytest.raises(ValueError, match="2\\*\\*50"):
        photocurrent_sorted(ev, SENSOR, (2, 2), 1.0, 1e-6, state)


def test_int64_levels_give_the_int32_result(rng):
    # Levels beyond 2**28 switch the kernel's level arithmetic from int32 to int64.
    from evdown_torch.events import Events
    from evdown_torch.transforms.functional.photocurrent import events_mode as kernel

    arr = random_stream(rng, 2000, SENSOR, t_max=1000)
    events = Events.from_columns(arr["x"].astype(np.int64), arr["y"].astype(np.int64),
                                 arr["t"], arr["p"])
    state = kernel.initial_state(SENSOR, (2, 2))
    settings_ = {"sensor_size": SENSOR, "factor": (2, 2), "contrast": 0.3, "threshold": 0.1}
    narrow = kernel._events_piece(events, state=state, level_bound=2000, **settings_).out
    wide = kernel._events_piece(events, state=state, level_bound=2**40, **settings_).out
    assert narrow.num_events > 100
    assert all(torch.equal(a, b) for a, b in zip(narrow, wide, strict=True))
