"""The bounded-delay window's compiled upkeep against the eager functions, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("numba")

from evdown_torch._tensors import take  # noqa: E402
from evdown_torch.events import Events, polarity_sign  # noqa: E402
from evdown_torch.transforms.functional.compiled import (  # noqa: E402
    estimation_window as compiled,
)
from evdown_torch.transforms.functional.estimation import delay, stream  # noqa: E402
from tests.helpers import assert_identical, random_stream  # noqa: E402

TIME_KINDS = ["int64", "int64_near_2_62", "float64", "float32"]
Sensor = tuple[int, int, int]
SENSORS: list[Sensor] = [(7, 5, 2), (34, 34, 2)]


def _times(raw: np.ndarray, kind: str) -> torch.Tensor:
    """Integer times ``raw`` (ascending keeps ascending, ties stay ties) in a time kind."""
    if kind == "int64":
        return torch.from_numpy(raw.astype(np.int64))
    if kind == "int64_near_2_62":
        return torch.from_numpy(raw.astype(np.int64) + 2**62)
    if kind == "float64":
        return torch.from_numpy(raw * 0.37 + 1234.5)
    # Near 1e6 float32 steps by 1/16: a tenth of a tick rounds, some distinct times collide.
    return torch.from_numpy((raw * 0.1 + 1e6).astype(np.float32))


def _stream(rng: np.random.Generator, n: int, sensor: Sensor, kind: str, *, t_max: int = 2000,
            sort: bool = True) -> Events:
    arr = random_stream(rng, n, sensor, t_max=t_max, sort=sort)
    return Events(torch.from_numpy(arr["x"].astype(np.int64)),
                  torch.from_numpy(arr["y"].astype(np.int64)), _times(arr["t"], kind),
                  torch.from_numpy(arr["p"].copy()))


def _delays(kind: str) -> list[float]:
    if kind.startswith("int"):
        return [1, 3, 37, 2**60]
    return [0.1, 2.7, 33.3, 1e300]  # 0.1, 2.7, 33.3 are not float32 numbers


def _per_event_start(rng: np.random.Generator, t: torch.Tensor, span: float) -> torch.Tensor:
    """A time at or before each event's (its pixel's last knot time, in a session)."""
    back = rng.random(t.shape[0]) * span
    if t.is_floating_point():
        return t - torch.from_numpy(back).to(t.dtype)
    return t - torch.from_numpy(back.astype(np.int64))


def _eager_next(window: Events, change: torch.Tensor, *, before: torch.Tensor, keep: int,
                width: int, pixels: int, t_start: torch.Tensor) -> tuple[Events, torch.Tensor]:
    """The next state's knots as ``estimation_step`` computes them."""
    recent, recent_change = stream._recent(window, change, before=before, keep=keep,
                                           pixels=pixels, width=width, t_start=t_start)
    kept, kept_change = stream._trim(recent, recent_change, before=before, keep=keep,
                                     width=width)
    by_time = torch.sort(kept.t, stable=True).indices
    return kept.select(by_time), take(kept_change, by_time)


# --- held_knots ---------------------------------------------------------------------------


@pytest.mark.parametrize("kind", TIME_KINDS)
@pytest.mark.parametrize("sensor", SENSORS)
def test_held_knots_equal_eager(kind: str, sensor: Sensor) -> None:
    held_total = 0
    for seed in range(6):
        rng = np.random.default_rng(seed)
        n = int(rng.choice([1, 2, 30, 700, 5000]))
        events = _stream(rng, n, sensor, kind, t_max=int(rng.choice([50, 2000, 10**6])))
        t0 = events.t[0]
        for max_delay in _delays(kind):
            for t_start in (t0, t0 - (7 if kind.startswith("int") else 7.5),
                            _per_event_start(rng, events.t, 3 * min(max_delay, 1000))):
                got = compiled.held_knots(events, max_delay=max_delay, t_start=t_start)
                assert_identical(got, delay.held_knots(events, max_delay=max_delay,
                                                       t_start=t_start))
                held_total += got.num_events
    assert held_total > 1000  # knots were held


@pytest.mark.parametrize("kind", TIME_KINDS)
def test_held_knots_of_unsorted_events_equal_eager(kind: str, rng: np.random.Generator) -> None:
    for _ in range(5):
        events = _stream(rng, 600, (9, 4, 2), kind, t_max=300, sort=False)
        for t_start in (events.t.min(), _per_event_start(rng, events.t, 20)):
            got = compiled.held_knots(events, max_delay=_delays(kind)[1], t_start=t_start)
            want = delay.held_knots(events, max_delay=_delays(kind)[1], t_start=t_start)
            assert_identical(got, want)
            assert bool((got.t[1:] < got.t[:-1]).any()) is False


def test_held_knots_tied_times_go_in_pixel_order_not_input_order(
    rng: np.random.Generator,
) -> None:
    # float32 times near -3.3e7 are 4 apart: held times of nearby events collide, and the
    # eager kernel orders each tie by pixel.
    events = _stream(rng, 3000, (34, 34, 2), "float64", t_max=200)
    events = events._replace(t=(events.t - 1234.5).to(torch.float32))
    t_start = torch.tensor(-1e8, dtype=torch.float32)
    got = compiled.held_knots(events, max_delay=3.3e7, t_start=t_start)
    assert_identical(got, delay.held_knots(events, max_delay=3.3e7, t_start=t_start))
    pixel = got.y * 34 + got.x
    ties = got.t[1:] == got.t[:-1]
    assert bool(ties.any()) and bool((pixel[1:][ties] >= pixel[:-1][ties]).all())
    # In input order the ties would not be in pixel order: the test tells them apart.
    first = torch.ones(events.num_events, dtype=torch.bool)
    seen: set[int] = set()
    for i, p in enumerate((events.y * 34 + events.x).tolist()):
        first[i] = p not in seen
        seen.add(p)
    in_input_order = (events.y * 34 + events.x)[first]
    assert not torch.equal(in_input_order, pixel)


@pytest.mark.parametrize("max_delay", [0.1, 0.3, 0.7])
def test_held_knots_round_a_float32_delay_as_torch_does(
    max_delay: float, rng: np.random.Generator
) -> None:
    # Multiples of float32(0.1): many gaps are float32(max_delay) exactly, which is more
    # than max_delay itself (0.1, 0.3) or less (0.7): the delay must be rounded first.
    ticks = np.sort(rng.integers(0, 600, 4000))
    events = _stream(rng, 4000, (5, 4, 2), "int64")._replace(
        t=torch.from_numpy(ticks.astype(np.float32) * np.float32(0.1)))
    by_pixel = torch.sort(events.y * 5 + events.x, stable=True)
    t = events.t[by_pixel.indices]
    gaps = (t[1:] - t[:-1])[by_pixel.values[1:] == by_pixel.values[:-1]]
    assert bool((gaps == torch.tensor(max_delay, dtype=torch.float32)).any())
    for t_start in (events.t[0], _per_event_start(rng, events.t, 0.5).to(torch.float32)):
        got = compiled.held_knots(events, max_delay=max_delay, t_start=t_start)
        assert_identical(got, delay.held_knots(events, max_delay=max_delay, t_start=t_start))


def test_held_knots_empty_one_event_and_refusals() -> None:
    for kind in TIME_KINDS:
        empty = Events(torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.int64),
                       _times(np.zeros(0, dtype=np.int64), kind), torch.zeros(0, dtype=torch.bool))
        start = torch.zeros((), dtype=empty.t.dtype)
        assert_identical(compiled.held_knots(empty, max_delay=3, t_start=start),
                         delay.held_knots(empty, max_delay=3, t_start=start))
        one = Events(torch.tensor([4]), torch.tensor([2]), _times(np.array([40]), kind),
                     torch.tensor([True]))
        for t_start in (one.t[0], one.t[0] - 9, one.t - 2):
            got = compiled.held_knots(one, max_delay=3, t_start=t_start)
            assert_identical(got, delay.held_knots(one, max_delay=3, t_start=t_start))
        assert compiled.held_knots(one, max_delay=3, t_start=one.t[0] - 9).num_events == 1
    ints = Events(torch.tensor([0]), torch.tensor([0]), torch.tensor([5]), torch.tensor([True]))
    with pytest.raises(ValueError, match="whole number"):
        compiled.held_knots(ints, max_delay=2.5, t_start=ints.t[0])
    with pytest.raises(ValueError, match="non-negative"):
        compiled.held_knots(ints._replace(x=torch.tensor([-1])), max_delay=2, t_start=ints.t[0])


def test_other_timestamp_dtypes_take_the_eager_kernels(rng: np.random.Generator) -> None:
    events = _stream(rng, 500, (7, 5, 2), "int64", t_max=300)
    for dtype in (torch.int32, torch.float16):
        other = events._replace(t=events.t.to(dtype))
        assert_identical(compiled.held_knots(other, max_delay=7, t_start=other.t[0]),
                         delay.held_knots(other, max_delay=7, t_start=other.t[0]))
        parts = [(other.part(0, 200), torch.ones(200, dtype=torch.int64)),
                 (other.part(200), torch.ones(300, dtype=torch.int64))]
        assert_identical(compiled.merge_by_time(parts), delay.merge_by_time(parts))
        with pytest.raises(TypeError, match="int64, float64 or float32"):
            compiled.next_knots(other, torch.ones(500, dtype=torch.int64), before=other.t[9],
                                keep=1, width=7)


# --- merge_by_time ------------------------------------------------------------------------


def _parts(rng: np.random.Generator, sizes: list[int], kind: str,
           change_dtype: torch.dtype) -> list[tuple[Events, torch.Tensor]]:
    """Time-sorted parts sharing many times, polarity unrelated to the changes."""
    parts = []
    for size in sizes:
        events = _stream(rng, size, (34, 34, 2), kind, t_max=int(rng.choice([20, 5000])))
        change = torch.from_numpy(rng.integers(-3, 4, size)).to(change_dtype)
        parts.append((events, change))
    return parts


@pytest.mark.parametrize("kind", TIME_KINDS)
@pytest.mark.parametrize("change_dtype", [torch.int64, torch.int8])
def test_merge_by_time_equals_eager(kind: str, change_dtype: torch.dtype,
                                    rng: np.random.Generator) -> None:
    paths = set()
    for sizes in ([0], [5], [3, 0, 4], [100, 2000], [1500, 10, 3000], [20000, 7, 300],
                  [0, 6000], [50, 60, 70, 80], [4095, 1], [4095, 0]):
        parts = _parts(rng, sizes, kind, change_dtype)
        got = compiled.merge_by_time(parts)
        assert_identical(got, delay.merge_by_time(parts))
        merged, change = got
        paths.add(torch.equal(merged.p, change > 0))
        # The merge is a stable time sort of the concatenation.
        whole = Events.cat([events for events, _ in parts])
        order = torch.sort(whole.t, stable=True).indices
        assert_identical(merged.t, whole.t[order])
    assert paths == {True, False}  # the small path keeps the parts' polarity


def test_merge_by_time_of_parts_of_different_dtypes_equals_eager(
    rng: np.random.Generator,
) -> None:
    parts = _parts(rng, [30, 40], "int64", torch.int64)
    parts[1] = (parts[1][0], parts[1][1].to(torch.int8))
    assert_identical(compiled.merge_by_time(parts), delay.merge_by_time(parts))


# --- next_knots ---------------------------------------------------------------------------


def _window(rng: np.random.Generator, n: int, sensor: Sensor, kind: str,
            t_max: int) -> tuple[Events, torch.Tensor]:
    """A time-sorted window whose changes include whole levels (|change| > 1)."""
    events = _stream(rng, n, sensor, kind, t_max=t_max)
    change = polarity_sign(events.p, torch.int64)
    big = torch.from_numpy(rng.random(n) < 0.05)
    change[big] = torch.from_numpy(rng.integers(-9, 10, int(big.sum())))
    return events._replace(p=change > 0), change


def _befores(t: torch.Tensor) -> list[torch.Tensor]:
    """Before all, after all, in the middle, on an event's time, between two times."""
    lo, hi = t[0], t[-1]
    mid = t[t.shape[0] // 2]
    one = 1 if not t.is_floating_point() else 0.5
    return [lo - one, lo, hi + one, hi, mid, (mid + one).to(t.dtype)]


@pytest.mark.parametrize("kind", TIME_KINDS)
@pytest.mark.parametrize("sensor", SENSORS)
@pytest.mark.parametrize("keep", [1, 2])
def test_next_knots_equal_eager(kind: str, sensor: Sensor, keep: int) -> None:
    pruned = 0
    width, height, _ = sensor
    for seed in range(4):
        rng = np.random.default_rng(seed)
        n = int(rng.choice([1, 3, 200, 5000, 9000]))
        window, change = _window(rng, n, sensor, kind, t_max=int(rng.choice([30, 3000])))
        for before in _befores(window.t):
            got = compiled.next_knots(window, change, before=before, keep=keep, width=width)
            want = _eager_next(window, change, before=before, keep=keep, width=width,
                               pixels=width * height, t_start=window.t[0])
            assert_identical(got, want)
            recent, _ = stream._recent(window, change, before=before, keep=keep,
                                       pixels=width * height, width=width, t_start=window.t[0])
            pruned += recent.num_events < window.num_events
            # _recent prunes only what _trim drops: the whole window's _trim, sorted.
            kept, kept_change = stream._trim(window, change, before=before, keep=keep,
                                             width=width)
            by_time = torch.sort(kept.t, stable=True).indices
            assert_identical(got, (kept.select(by_time), take(kept_change, by_time)))
    assert pruned  # _recent took its pruning branch


def test_next_knots_keep_other_than_the_lags_equals_eager_trim(
    rng: np.random.Generator,
) -> None:
    window, change = _window(rng, 3000, (7, 5, 2), "int64", t_max=400)
    for keep in (0, 3, 10):
        for before in _befores(window.t):
            kept, kept_change = stream._trim(window, change, before=before, keep=keep, width=7)
            by_time = torch.sort(kept.t, stable=True).indices
            assert_identical(compiled.next_knots(window, change, before=before, keep=keep,
                                                 width=7),
                             (kept.select(by_time), take(kept_change, by_time)))


def test_signed_zero_times_equal_eager(rng: np.random.Generator) -> None:
    """A knot keeps the time of its run's last event: -0.0 or 0.0, as the eager kernels."""
    signs = 0
    for n in (300, 6000):
        window, change = _window(rng, n, (7, 5, 2), "int64", t_max=40)
        t = window.t.to(torch.float64)
        zero = t == t[n // 3]
        t = t - t[n // 3]
        t[zero] = torch.from_numpy(np.where(rng.random(int(zero.sum())) < 0.5, -0.0, 0.0))
        window = window._replace(t=t)
        for before in (torch.tensor(0.0), torch.tensor(-0.0), t[-1]):
            for keep in (1, 2):
                got = compiled.next_knots(window, change, before=before, keep=keep, width=7)
                assert_identical(got, _eager_next(window, change, before=before, keep=keep,
                                                  width=7, pixels=35, t_start=t[0]))
                signs += int(torch.signbit(got[0].t[got[0].t == 0]).sum())
        for t_start in (t[0], torch.zeros((), dtype=t.dtype), -torch.zeros((), dtype=t.dtype)):
            assert_identical(compiled.held_knots(window, max_delay=0.5, t_start=t_start),
                             delay.held_knots(window, max_delay=0.5, t_start=t_start))
        parts = [(window.part(0, n // 2), change[: n // 2]), (window.part(n // 2), change[n // 2:])]
        assert_identical(compiled.merge_by_time(parts), delay.merge_by_time(parts))
    assert signs  # knots at -0.0 were kept


def test_next_knots_of_nothing_and_refusals() -> None:
    for kind in TIME_KINDS:
        t = _times(np.zeros(0, dtype=np.int64), kind)
        empty = Events(torch.zeros(0, dtype=torch.int64), torch.zeros(0, dtype=torch.int64), t,
                       torch.zeros(0, dtype=torch.bool))
        knots, change = compiled.next_knots(empty, torch.zeros(0, dtype=torch.int64),
                                            before=torch.zeros((), dtype=t.dtype), keep=1,
                                            width=3)
        assert_identical((knots, change), (empty, torch.zeros(0, dtype=torch.int64)))
    one = Events(torch.tensor([-1]), torch.tensor([0]), torch.tensor([5]), torch.tensor([True]))
    with pytest.raises(ValueError, match="non-negative"):
        compiled.next_knots(one, torch.tensor([1]), before=torch.tensor(9), keep=1, width=3)


# --- a session's windows, step by step ------------------------------------------------------


@pytest.mark.parametrize("kind", TIME_KINDS)
@pytest.mark.parametrize("sensor", SENSORS)
@pytest.mark.parametrize("lag", [1, 2])
def test_a_sessions_window_upkeep_equals_eager_chunk_by_chunk(
    kind: str, sensor: Sensor, lag: int, rng: np.random.Generator
) -> None:
    """The step's held knots, window merge and next knots, on the state the eager path keeps."""
    width, height, _ = sensor
    events = _stream(rng, 30000, sensor, kind, t_max=60000)
    max_delay = _delays(kind)[2]
    d = delay.effective_delay(max_delay, events.t)
    bounds = sorted({0, events.num_events, *rng.integers(0, events.num_events, 12).tolist()})
    t_start = events.t[0]
    pixel_t = torch.full((width * height,), t_start.item(), dtype=events.t.dtype)
    knots, knot_change = Events.empty(events.t.dtype), torch.zeros(0, dtype=torch.int64)
    horizon = None
    big_windows, whole_levels = 0, 0
    for a, b in zip(bounds[:-1], bounds[1:]):
        chunk = events.part(a, b)
        pixel = chunk.y * width + chunk.x
        starts = take(pixel_t, pixel)
        held = delay.held_knots(chunk, max_delay=max_delay, t_start=starts)
        assert_identical(compiled.held_knots(chunk, max_delay=max_delay, t_start=starts), held)
        pixel_t.scatter_reduce_(0, pixel, chunk.t, "amax")
        parts = [(knots, knot_change),
                 (held, torch.zeros(held.num_events, dtype=torch.int64)),
                 (chunk, polarity_sign(chunk.p, torch.int64))]
        window, change = delay.merge_by_time(parts)
        assert_identical(compiled.merge_by_time(parts), (window, change))
        big_windows += window.num_events >= delay.SMALL_WINDOW
        horizon = max(chunk.t[-1].item() - lag * d, t_start.item(),
                      *(() if horizon is None else (horizon,)))
        before = torch.tensor(horizon, dtype=events.t.dtype)
        knots, knot_change = _eager_next(window, change, before=before, keep=lag, width=width,
                                         pixels=width * height, t_start=t_start)
        assert_identical(compiled.next_knots(window, change, before=before, keep=lag,
                                             width=width), (knots, knot_change))
        whole_levels += int((knot_change.abs() > 1).sum())
    assert big_windows and whole_levels
