"""Streaming sessions: any chunking gives the batch result; bad chunks are refused safely."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.interpolate import CubicHermiteSpline, PchipInterpolator

from evdown_torch import (
    Chain,
    CubicEstimation,
    Downsample,
    EventCount,
    EventFunnelling,
    Events,
    LinearEstimation,
    TemporalFunnelling,
    eager_kernels,
)
from evdown_torch.transforms import Session
from evdown_torch.transforms.thinning import ThinnedDownsample
from tests import helpers
from tests.helpers import DVS_DTYPE, chunkings, random_stream, run_in_chunks, streaming_cases

SENSOR = (9, 7, 2)

TRANSFORMS = {
    **streaming_cases(SENSOR, (3, 2), step=7),
    "temporal_then_count": Chain(
        TemporalFunnelling(dt=5), EventCount(SENSOR, factor=2, threshold=0.5)
    ),
    "funnelling_then_temporal": Chain(
        EventFunnelling(SENSOR, factor=2), TemporalFunnelling(dt=11)
    ),
}


def _chunked_stream(case, t_max: int) -> tuple[np.ndarray, list[int]]:
    """A :data:`~tests.helpers.chunkings` case as its random stream and its cut positions."""
    seed, n, fractions = case
    arr = random_stream(np.random.default_rng(seed), n, SENSOR, t_max=t_max)
    return arr, [int(f * n) for f in fractions]


@pytest.mark.parametrize("name", sorted(TRANSFORMS))
@settings(max_examples=25, deadline=None, derandomize=True)
@given(case=chunkings)
def test_any_chunking_gives_the_batch_result(name, case):
    arr, cuts = _chunked_stream(case, t_max=60)  # many equal timestamps and repeats
    transform = TRANSFORMS[name]
    np.testing.assert_array_equal(run_in_chunks(transform, arr, cuts), transform(arr))


def test_funnelling_drops_a_repeat_that_straddles_a_chunk_boundary():
    arr = np.array([(0, 0, True, 5), (1, 1, True, 5), (1, 0, True, 5)], dtype=DVS_DTYPE)
    session = EventFunnelling((4, 4, 2), factor=2).session()
    first = session(arr[:1])
    second = session(arr[1:])  # both repeat (0, 0, 5, ON) after downsampling
    assert first.tolist() == [(0, 0, True, 5)]
    assert second.tolist() == []


def test_temporal_session_bins_from_the_stream_start():
    # dt 10 from t_start 3: bins [3, 13) and [13, 23).
    session = TemporalFunnelling(dt=10).session()
    a = session(torch.tensor([[0, 0, 3, 1]]))
    b = session(torch.tensor([[0, 0, 12, 1], [0, 0, 13, 1], [1, 0, 14, 0]]))
    assert a.tolist() == [[0, 0, 3, 1]]
    assert b.tolist() == [[0, 0, 13, 1], [1, 0, 13, 0]]  # (0, 0, 12) repeats (0, 0, 3)


@pytest.mark.parametrize("name", sorted(TRANSFORMS))
def test_a_chunk_back_in_time_is_refused_and_the_session_stays_usable(name, rng):
    arr = random_stream(rng, 200, SENSOR, t_max=100)
    transform = TRANSFORMS[name]
    session = transform.session()
    head = session(arr[:120])
    late = arr[120:].copy()
    late["t"][-1] = arr["t"][119] - 1  # one event before the previous chunk's last one
    with pytest.raises(ValueError, match="follow each other in time"):
        session(late)
    # The refused chunk left nothing behind: the rest of the stream still gives the batch.
    out = np.concatenate([head, session(arr[120:]), session.flush()])
    np.testing.assert_array_equal(out, transform(arr))


def test_a_chunk_with_other_timestamps_or_outside_the_sensor_is_refused(rng):
    session = Downsample(SENSOR, factor=2).session()
    session(torch.tensor([[0, 0, 5, 1]]))
    with pytest.raises(ValueError, match="timestamps are torch.float64"):
        session(torch.tensor([[0.0, 0.0, 6.0, 1.0]], dtype=torch.float64))
    with pytest.raises(ValueError):
        session(torch.tensor([[SENSOR[0], 0, 7, 1]]))
    assert session(torch.tensor([[2, 3, 8, 1]])).tolist() == [[1, 1, 8, 1]]


def test_flush_ends_the_stream_and_keeps_the_kind(rng):
    arr = random_stream(rng, 50, SENSOR)
    session = EventCount(SENSOR, factor=2).session()
    assert isinstance(session.flush(), Events)  # nothing fed: empty Events
    session(arr)
    tail = session.flush()
    assert tail.dtype == DVS_DTYPE and len(tail) == 0  # causal: nothing left for the end
    assert session.state is None and session.last_t is None
    # A flushed session starts a new stream: earlier timestamps are fine again.
    np.testing.assert_array_equal(session(arr), EventCount(SENSOR, factor=2)(arr))


def test_empty_chunks_come_back_empty_in_their_own_kind():
    session = EventFunnelling(SENSOR, factor=2).session()
    out = session(torch.zeros((0, 4), dtype=torch.int32))
    assert out.shape == (0, 4) and out.dtype == torch.int32
    out = session(np.empty(0, dtype=DVS_DTYPE))
    assert out.dtype == DVS_DTYPE and len(out) == 0
    assert session.state is None


def test_every_session_is_the_common_session():
    for transform in TRANSFORMS.values():
        assert type(transform.session()) is Session


def test_chain_refuses_what_cannot_stream():
    with pytest.raises(ValueError, match="at least one"):
        Chain()
    with pytest.raises(TypeError, match="evdown_torch transforms"):
        Chain(lambda ev: ev)


@pytest.mark.parametrize("stage", [LinearEstimation(SENSOR, 4), CubicEstimation(SENSOR, 2),
                                   ThinnedDownsample(SENSOR, 2, keep=0.5)])
def test_a_chain_with_a_batch_only_stage_refuses_its_session_as_the_stage_does(stage):
    with pytest.raises((ValueError, NotImplementedError)) as own:
        stage.session()
    for chain in (Chain(TemporalFunnelling(dt=10), stage), Chain(stage),
                  Chain(Chain(stage), TemporalFunnelling(dt=10))):
        with pytest.raises(own.type) as chained:
            chain.session()
        assert str(chained.value) == str(own.value)
    # the batch call still works
    arr = random_stream(np.random.default_rng(0), 50, SENSOR)
    np.testing.assert_array_equal(Chain(TemporalFunnelling(dt=10), stage)(arr),
                                  stage(TemporalFunnelling(dt=10)(arr)))


# --- Bounded delay: LinearEstimation and CubicEstimation ------------------------------------

ESTIMATORS = {
    "linear": (LinearEstimation, 1),
    "cubic": (CubicEstimation, 2),
}


REFERENCE_KNOTS = helpers.reference_knots
REFERENCE_CURVE = helpers.reference_curve


def curve_at_rest(kind: str, knots: list) -> tuple:
    """The oracle's pixel curve with a bounded delay: the cubic slope at the first knot is 0
    (docs/semantics.md, "Bounded delay"), SciPy's PCHIP slopes at every other knot."""
    if kind != "cubic" or len(knots) < 2:
        return REFERENCE_CURVE(kind, knots)
    ts = np.array([k[0] for k in knots], dtype=np.float64)
    ls = np.array([k[1] for k in knots], dtype=np.float64)
    slopes = PchipInterpolator(ts, ls).derivative()(ts)
    slopes[0] = 0.0
    curve = CubicHermiteSpline(ts, ls, slopes)
    return curve, curve.derivative()


def delayed_knots(arr: np.ndarray, max_delay: int) -> tuple[dict, float, float]:
    """The oracle's knots with the contract's held knots ``(t_next - D, previous level)``."""
    knots, t_start, t_end = REFERENCE_KNOTS(arr)
    for pixel in knots.values():
        held = list(pixel[:1])
        for (t0, level0), (t1, level1) in zip(pixel[:-1], pixel[1:]):
            if t1 - t0 > max_delay and (t1, level1) != (t_end, level0):  # not the back knot
                held.append((t1 - max_delay, level0))
            held.append((t1, level1))
        pixel[:] = held
    return knots, t_start, t_end


@pytest.mark.parametrize("kind", sorted(ESTIMATORS))
@pytest.mark.parametrize(("factor", "threshold", "max_delay"),
                         [(2, 0.1, 40), ((3, 2), 0.5, 7), (3, 0.25, 1), (2, 0.2, 10**6)])
def test_bounded_delay_matches_the_slow_reference(kind, factor, threshold, max_delay, rng,
                                                  monkeypatch):
    cls, _ = ESTIMATORS[kind]
    arr = random_stream(rng, 300, SENSOR, t_max=3000)
    out = cls(SENSOR, factor=factor, threshold=threshold, max_delay=max_delay)(arr)
    monkeypatch.setattr(helpers, "reference_knots",
                        lambda a: delayed_knots(a, max_delay))
    monkeypatch.setattr(helpers, "reference_curve", curve_at_rest)
    fxy = (factor, factor) if isinstance(factor, int) else factor
    expected = helpers.reference(arr, SENSOR, fxy, threshold, kind)
    helpers.assert_matches_reference(out, expected, True)


def test_bounded_delay_hand_computed():
    # Pixel (0, 0): ON at 0, OFF at 30 -> held knot (27, 1). Pixel (1, 0): ON at 10 and 31
    # -> held knots (7, 0) and (28, 1). The mean rises from 0.5 to 1 on [7, 10] (0.75 at
    # 8.5, rounded to 9), dips to 5/6 on [28, 30] (no OFF at 0.75) and is 1 again at 31.
    ev = torch.tensor([[0, 0, 0, 1], [1, 0, 10, 1], [0, 0, 30, 0], [1, 0, 31, 1]])
    out = LinearEstimation((2, 1, 2), factor=(2, 1), threshold=0.25, max_delay=3)(ev)
    assert out.tolist() == [[0, 0, 0, 1], [0, 0, 0, 1], [0, 0, 9, 1], [0, 0, 10, 1]]


def test_a_delay_longer_than_the_stream_changes_nothing(rng):
    # Linear: the paper's method. Cubic: the paper's method but for the slope 0 at each
    # pixel's first knot, which the bounded-delay oracle (no knot held) checks.
    arr = random_stream(rng, 300, SENSOR, t_max=1000)
    np.testing.assert_array_equal(LinearEstimation(SENSOR, factor=2, max_delay=10**6)(arr),
                                  LinearEstimation(SENSOR, factor=2)(arr))
    assert delayed_knots(arr, 10**6) == REFERENCE_KNOTS(arr)


@pytest.mark.parametrize("kind", sorted(ESTIMATORS))
@pytest.mark.parametrize("dtype", [np.int64, np.float64])
@pytest.mark.parametrize("max_delay", [10**19, 1e300, 2**62])
def test_a_huge_delay_holds_nothing_in_batch_and_session(kind, dtype, max_delay, rng):
    # Longer than every gap: "never hold", as a delay just longer than the stream; the int64
    # arithmetic on it (t - D, tau - lag * D) must not overflow.
    cls, _ = ESTIMATORS[kind]
    arr = random_stream(rng, 200, SENSOR, t_max=1000).astype(
        [("x", "<i2"), ("y", "<i2"), ("p", "?"), ("t", dtype)])
    arr["t"] += 2**61 if dtype == np.int64 else 0
    long_enough = cls(SENSOR, factor=2, threshold=0.3, max_delay=2000)
    transform = cls(SENSOR, factor=2, threshold=0.3, max_delay=max_delay)
    batch = transform(arr)
    np.testing.assert_array_equal(batch, long_enough(arr))
    session = transform.session()
    parts = [session(chunk) for chunk in np.array_split(arr, 7)]
    assert sum(len(part) for part in parts) == 0  # nothing is decided before the end
    np.testing.assert_array_equal(np.concatenate([*parts, session.flush()]), batch)


@pytest.mark.parametrize("kind", sorted(ESTIMATORS))
@settings(max_examples=15, deadline=None, derandomize=True)
@given(case=chunkings, max_delay=st.sampled_from([1, 5, 30]))
def test_estimator_sessions_equal_the_batch_and_keep_the_delay_bound(kind, case, max_delay):
    cls, lag = ESTIMATORS[kind]
    arr, cuts = _chunked_stream(case, t_max=400)
    transform = cls(SENSOR, factor=(3, 2), threshold=0.3, max_delay=max_delay)
    batch = transform(arr)
    session = transform.session()
    parts = []
    for chunk in np.split(arr, sorted(cuts)):
        parts.append(session(chunk))
        if len(chunk):
            # Exactly the batch events earlier than tau - lag * D are out by now: each event
            # comes out with the first chunk that reaches past t + lag * D, and none sooner.
            horizon = chunk["t"][-1] - lag * max_delay
            np.testing.assert_array_equal(np.concatenate(parts), batch[batch["t"] < horizon])
    parts.append(session.flush())
    np.testing.assert_array_equal(np.concatenate(parts), batch)


@pytest.mark.parametrize("kind", sorted(ESTIMATORS))
def test_estimator_session_needs_a_finite_delay(kind):
    cls, _ = ESTIMATORS[kind]
    with pytest.raises(ValueError, match="needs a finite delay|max_delay=D"):
        cls(SENSOR, factor=2).session()


@pytest.mark.parametrize("max_delay", [0, -3, float("nan")])
def test_bad_max_delay_is_refused(max_delay):
    with pytest.raises(ValueError, match="max_delay"):
        LinearEstimation(SENSOR, factor=2, max_delay=max_delay)


def test_fractional_delay_is_refused_for_integer_timestamps():
    with pytest.raises(ValueError, match="whole number"):
        CubicEstimation(SENSOR, factor=2, max_delay=2.5)(torch.tensor([[0, 0, 1, 1]]))


@pytest.mark.parametrize("name", ["funnelling", "event_count", "temporal_then_count"])
def test_sessions_stay_on_the_chunks_device(name, device, rng):
    arr = random_stream(rng, 400, SENSOR, t_max=80)
    data = torch.tensor(np.stack([arr["x"], arr["y"], arr["t"], arr["p"]], 1).astype(np.int64),
                        device=device)
    transform = TRANSFORMS[name]
    session = transform.session()
    parts = [session(chunk) for chunk in torch.split(data, 70)] + [session.flush()]
    assert all(part.device == data.device for part in parts)
    assert torch.equal(torch.cat(parts), transform(data))


@pytest.mark.parametrize("kind", sorted(ESTIMATORS))
def test_estimator_sessions_on_float_timestamps_keep_the_stated_bound(kind):
    # docs/guide.md, "Streaming": with float timestamps CubicEstimation's session is the batch
    # bit for bit; LinearEstimation's gives the same events here, each time within two units
    # in the last place (its running remainder is summed from different starts; more where a
    # piece's level change is small, and a crossing at a chunk's horizon: the test below).
    cls, _ = ESTIMATORS[kind]
    rng = np.random.default_rng(0)
    events = random_stream(rng, 8000, (32, 24, 2), dtype=helpers.FLOAT_DTYPE)
    events["t"] = np.sort(rng.uniform(0.0, 3e5, len(events)))  # 0.3 s in float microseconds
    transform = cls((32, 24, 2), factor=4, threshold=0.3, max_delay=1000.0)
    batch = transform(events)
    for pieces in (7, 30):
        session = transform.session()
        out = np.concatenate([*(session(c) for c in np.array_split(events, pieces)),
                              session.flush()])
        np.testing.assert_array_equal(out[["x", "y", "p"]], batch[["x", "y", "p"]])
        if kind == "cubic":
            np.testing.assert_array_equal(out["t"], batch["t"])
        else:
            assert (np.abs(out["t"] - batch["t"]) <= 2 * np.spacing(batch["t"])).all()


def test_a_float_crossing_at_the_horizon_comes_out_once(kernels):
    # Found by a differential search, reduced to six events. The second chunk ends at 9.25, so
    # its horizon is 9.25 - 3 = 6.25, the time of a crossing of region (0, 7): the chunk
    # computes it at or after 6.25 (for the next chunk), the flush, from other knots, before
    # 6.25. When the flush decided by its own time, the crossing was lost; it now drops the
    # crossings the chunk returned by their count.
    arr = np.array([(2, 21, 1.75, False), (0, 23, 2.0, True), (0, 22, 2.0, True),
                    (0, 21, 2.0, True), (0, 22, 8.5, True), (18, 23, 9.25, True)],
                   dtype=[("x", "<i2"), ("y", "<i2"), ("t", "<f8"), ("p", "?")])
    transform = LinearEstimation((28, 39, 2), factor=3, threshold=0.05, max_delay=3)
    session = transform.session()
    parts = [session(arr[:4]), session(arr[4:]), session.flush()]
    # The flush computes the crossing just below the horizon 6.25 and raises it there: a
    # step's outputs never come before what the steps before returned.
    assert parts[1]["t"].max() < 6.25 <= parts[2]["t"].min()
    out, batch = np.concatenate(parts), transform(arr)
    assert len(out) == len(batch) == 12
    # Regions' crossings a few ulps apart may come out in either order: compared by region.
    out, batch = (a[np.lexsort((a["t"], a["y"], a["x"]))] for a in (out, batch))
    assert (out[["x", "y", "p"]] == batch[["x", "y", "p"]]).all()
    assert (np.abs(out["t"] - batch["t"]) <= 2 * np.spacing(batch["t"])).all()


@pytest.mark.parametrize("first", ["compiled", "eager"])
def test_the_crossings_returned_at_a_horizon_carry_over_to_the_other_path(first):
    # The same six events as above, the chunk on one path and the flush on the other: the
    # count of the crossings returned is the state's, which both paths read and write.
    pytest.importorskip("numba")
    arr = np.array([(2, 21, 1.75, False), (0, 23, 2.0, True), (0, 22, 2.0, True),
                    (0, 21, 2.0, True), (0, 22, 8.5, True), (18, 23, 9.25, True)],
                   dtype=[("x", "<i2"), ("y", "<i2"), ("t", "<f8"), ("p", "?")])
    transform = LinearEstimation((28, 39, 2), factor=3, threshold=0.05, max_delay=3)
    session = transform.session()
    with eager_kernels(first == "eager"):
        parts = [session(arr[:4]), session(arr[4:])]
    with eager_kernels(first != "eager"):
        parts.append(session.flush())
    assert len(np.concatenate(parts)) == len(transform(arr)) == 12
