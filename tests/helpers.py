"""Stream builders and slow, obviously-correct references for the tests."""

from __future__ import annotations

import math
import threading
from collections import defaultdict
from fractions import Fraction

import numpy as np
import pytest
import torch
from hypothesis import strategies as st

from evdown_torch import (
    CubicEstimation,
    DensitySubsampling,
    Downsample,
    EventCount,
    EventFunnelling,
    LIFPooling,
    LinearEstimation,
    PhotocurrentPooling,
    PoissonSubsampling,
    RateLimiter,
    TemporalFunnelling,
    eager_kernels,
    max_output_events,
)
from evdown_torch.events import DVS_DTYPE, Events
from evdown_torch.models import SpikingPooling
from evdown_torch.transforms import Streaming
from evdown_torch.transforms.thinning import ThinnedDownsample
from evdown_torch.transforms.tonic_peers import TonicDecimation, TonicRefractoryPeriod

#: The estimators, and the three log-luminance methods (EventCount and the estimators).
ESTIMATORS = [LinearEstimation, CubicEstimation]
LOG_LUMINANCE = [EventCount, LinearEstimation, CubicEstimation]

#: DVS_DTYPE with float64 timestamps (seconds or any float unit).
FLOAT_DTYPE = np.dtype([("x", np.int16), ("y", np.int16), ("p", bool), ("t", np.float64)])


def transform_cases(
    sensor_size: tuple[int, int, int], factor: int | tuple[int, int], *, step: int
) -> dict[str, Streaming]:
    """Every transform of the package, once per method and mode: the one table of instances.

    The protocol, streaming and batch tests all run over it, and ``test_registry`` checks that
    it holds every method of the registry. Its keys are the registry names, plus the variants
    of a method (``linear_delay``, ``photocurrent_frames``) and the transforms outside the
    registry (``temporal``, ``thinned``, ``rate_limit``). ``step`` is the time scale of the
    test's streams (in their ticks): LIF's ``dt``, the estimators' ``max_delay``, two frames,
    one temporal bin, one limiter window.
    """
    return {
        "downsample": Downsample(sensor_size, factor),
        "funnelling": EventFunnelling(sensor_size, factor),
        "event_count": EventCount(sensor_size, factor, threshold=0.3),
        "linear": LinearEstimation(sensor_size, factor, threshold=0.25),
        "cubic": CubicEstimation(sensor_size, factor, threshold=0.25),
        "linear_delay": LinearEstimation(sensor_size, factor, threshold=0.25, max_delay=step),
        "cubic_delay": CubicEstimation(sensor_size, factor, threshold=0.25, max_delay=step),
        "lif": LIFPooling(sensor_size, factor, dt=step, tau=3.0 * step, weight=0.6),
        "photocurrent": PhotocurrentPooling(sensor_size, factor, contrast=0.3, threshold=0.2),
        "photocurrent_frames": PhotocurrentPooling(sensor_size, factor, contrast=0.3,
                                                   threshold=0.2, fps=1e6 / (2 * step)),
        "temporal": TemporalFunnelling(dt=step, sensor_size=sensor_size),
        "thinned": ThinnedDownsample(sensor_size, factor, keep=0.5, seed=3),
        "rate_limit": RateLimiter(max_events=3, window=step, sensor_size=sensor_size),
        "density": DensitySubsampling(sensor_size, factor, tau=4.0 * step, k=5, s=0.2),
        "poisson": PoissonSubsampling(sensor_size, factor, window=step, alpha=0.4),
        "refractory": TonicRefractoryPeriod(sensor_size, factor, delta=step),
        "decimation": TonicDecimation(sensor_size, factor, n=2),
    }


def streaming_cases(
    sensor_size: tuple[int, int, int], factor: int | tuple[int, int], *, step: int
) -> dict[str, Streaming]:
    """:func:`transform_cases` whose ``session()`` starts (the estimators need a delay)."""
    return {name: transform
            for name, transform in transform_cases(sensor_size, factor, step=step).items()
            if _has_session(transform)}


def _has_session(transform: Streaming) -> bool:
    try:
        transform.session()
    except (ValueError, NotImplementedError):
        return False
    return True


def argument_spy(monkeypatch, module, name: str) -> list[tuple]:
    """Wrap ``module.name`` for the test: the list returned gets each call's arguments."""
    calls, real = [], getattr(module, name)

    def wrapper(*args):
        calls.append(args)
        return real(*args)

    monkeypatch.setattr(module, name, wrapper)
    return calls


def spy(monkeypatch, module, name: str, record=lambda out: out) -> list:
    """Wrap ``module.name`` for the test: the list returned gets ``record(output)`` per call."""
    seen, real = [], getattr(module, name)

    def wrapper(*args, **kwargs):
        out = real(*args, **kwargs)
        seen.append(record(out))
        return out

    monkeypatch.setattr(module, name, wrapper)
    return seen


def random_stream(
    rng: np.random.Generator,
    n: int,
    sensor_size: tuple[int, int, int],
    *,
    t_max: int = 10_000,
    dtype: np.dtype = DVS_DTYPE,
    sort: bool = True,
) -> np.ndarray:
    """``n`` random events on ``sensor_size`` with times in ``[0, t_max)`` (sorted by default)."""
    w, h, _ = sensor_size
    out = np.empty(n, dtype=dtype)
    out["x"] = rng.integers(0, w, n)
    out["y"] = rng.integers(0, h, n)
    t = rng.integers(0, t_max, n)
    out["t"] = np.sort(t) if sort else t
    on = rng.random(n) < 0.5
    p_kind = dtype["p"]
    if p_kind == np.bool_:
        out["p"] = on
    elif np.issubdtype(p_kind, np.unsignedinteger):
        out["p"] = on.astype(np.uint8)
    else:
        out["p"] = np.where(on, 1, -1) if np.issubdtype(p_kind, np.signedinteger) else on
    return out


def saved_stream(path, rng: np.random.Generator, n: int, sensor_size: tuple[int, int, int],
                 **kwargs):
    """Save :func:`random_stream` ``(rng, n, sensor_size, **kwargs)`` as ``.npy`` at ``path``
    and return ``path``."""
    np.save(path, random_stream(rng, n, sensor_size, **kwargs))
    return path


def assert_shift_equivariant(transform, events: np.ndarray, out: np.ndarray, shifts) -> None:
    """``transform`` of ``events`` with every time plus ``shift`` is ``out`` (the output of
    ``events``) with every time plus ``shift``, for each of ``shifts`` (structured arrays)."""
    for shift in shifts:
        shifted = events.copy()
        shifted["t"] += shift
        out_shifted = transform(shifted)
        np.testing.assert_array_equal(out_shifted["t"] - out["t"], shift)
        np.testing.assert_array_equal(out_shifted[["x", "y", "p"]], out[["x", "y", "p"]])


def as_tuples(events: np.ndarray) -> list[tuple]:
    """Events as sorted ``(x, y, t, on)`` tuples, a multiset for comparisons."""
    return sorted(
        zip(
            events["x"].tolist(),
            events["y"].tolist(),
            events["t"].tolist(),
            (events["p"] > 0).tolist(),
        )
    )


def rows(events: np.ndarray) -> list[tuple]:
    """Events as ``(x, y, t, on)`` tuples in their order (see :func:`as_tuples` for a multiset)."""
    return list(zip(events["x"].tolist(), events["y"].tolist(), events["t"].tolist(),
                    (events["p"] > 0).tolist(), strict=True))


def run_in_threads(*targets, timeout: float = 60) -> None:
    """Run each function in a thread of its own, all at once, and wait for them all."""
    threads = [threading.Thread(target=target) for target in targets]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=timeout)


# --- the two kernel paths ------------------------------------------------------------------


def both_paths(call):
    """``call()`` through the compiled CPU kernels, then through the eager ones (skips without
    numba): ``(compiled output, eager output)``."""
    pytest.importorskip("numba")
    with eager_kernels(False):
        compiled = call()
    with eager_kernels(True):
        eager = call()
    return compiled, eager


def assert_identical(a, b) -> None:
    """Two outputs equal bit for bit: same kind, same dtypes, same bytes (Events, tensors,
    structured arrays, or tuples of them)."""
    assert type(a) is type(b)
    if isinstance(a, (tuple, list)) and not isinstance(a, Events):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            assert_identical(x, y)
        return
    if isinstance(a, Events):
        for x, y in zip(a, b):
            assert_identical(x, y)
        return
    if isinstance(a, torch.Tensor):
        assert a.dtype == b.dtype and a.shape == b.shape
        a, b = a.contiguous().numpy(), b.contiguous().numpy()
    assert a.dtype == b.dtype and a.shape == b.shape
    assert a.tobytes() == b.tobytes()


def near_their_limits(arr: np.ndarray, dtype, t_max: int) -> torch.Tensor:
    """``arr`` (times below ``t_max``) as an ``(N, 4)`` tensor ``[x, y, t, p = +-1]`` of
    ``dtype``: int64 times moved up to just below ``2**63`` (from ``2**63 - t_max - 10``),
    float times quartered and moved to ``1e6`` (a few units in the last place of float32)."""
    if dtype == np.int64:
        t = arr["t"] + (2**63 - t_max - 10)
    else:
        t = arr["t"].astype(dtype) * dtype(0.25) + dtype(1e6)
    return torch.tensor(np.stack([arr["x"], arr["y"], t, np.where(arr["p"], 1, -1)], 1)
                        .astype(dtype))


#: Cuts of a 1,500-event stream into empty chunks, one-event chunks and long ones.
ODD_CUTS = [0, 0, 1, 2, 2, 3, 40, 41, 700, 1100, 1101, 1499]


def assert_compiled_then_eager(monkeypatch, compiled: tuple, eager: tuple, call) -> None:
    """``call()`` runs ``compiled`` (a ``(module, name)``) once and not ``eager``, and under
    ``eager_kernels()`` runs ``eager`` once and not ``compiled`` again."""
    compiled_calls, eager_calls = spy(monkeypatch, *compiled), spy(monkeypatch, *eager)
    call()
    assert (len(compiled_calls), len(eager_calls)) == (1, 0)
    with eager_kernels():
        call()
    assert (len(compiled_calls), len(eager_calls)) == (1, 1)


def assert_sessions_on_both_paths(transform, arr: np.ndarray, whole: np.ndarray,
                                  cuts=ODD_CUTS) -> None:
    """``transform``'s session over ``arr`` cut at ``cuts`` equals ``whole`` bit for bit, with
    every chunk on the compiled path, on the eager one, and the paths alternating."""
    chunks = np.split(arr, cuts)
    for paths in (["compiled"], ["eager"], ["compiled", "eager"], ["eager", "eager", "compiled"]):
        session, parts = transform.session(), []
        for i, chunk in enumerate(chunks):
            with eager_kernels(paths[i % len(paths)] == "eager"):
                parts.append(session(chunk))
        parts.append(session.flush())
        assert_identical(np.concatenate(parts), whole)


def assert_output_limit_on_both_paths(transform, arr: np.ndarray, limit: int, total: int) -> str:
    """On each path, a session over ``arr[:10]`` then ``arr[10:]`` (``total`` events) under
    ``max_output_events(limit)`` raises the same error, keeps its state, and then gives the
    ``total`` events under a larger limit: the error's message."""
    messages = []
    for path in ("compiled", "eager"):
        with eager_kernels(path == "eager"):
            session = transform.session()
            session(arr[:10])
            state = [column.clone() for column in session.state[:2]]
            with max_output_events(limit), pytest.raises(ValueError) as error:
                session(arr[10:])
            messages.append(str(error.value))
            assert_identical(list(session.state[:2]), state)
            with max_output_events(total + 200):
                assert len(session(arr[10:])) == total
    assert messages[0] == messages[1]
    return messages[0]
def assert_batches_on_both_paths(transform, rng, sensor, t_max: int, check) -> None:
    """``transform.batch`` of sorted recordings and of unsorted ones (empty and one-event
    recordings among them) is the same on both paths, and ``check(recording, output)`` holds
    for each recording."""
    recordings = [random_stream(rng, n, sensor, t_max=t_max) for n in (50, 0, 300, 1, 120)]
    unsorted = [random_stream(rng, n, sensor, t_max=t_max, sort=False) for n in (80, 0, 200)]
    for batch in (recordings, unsorted):
        compiled, eager = both_paths(lambda batch=batch: transform.batch(batch))
        assert_identical(compiled, eager)
        for recording, out in zip(batch, compiled, strict=True):
            check(recording, out)


# --- the DVS reference rule, one level at a time --------------------------------------------


def reference_index(q: int, u) -> int:
    """The reference index after a value moves monotonely to ``u`` (levels in threshold
    units, a float or a Fraction) from index ``q``: ``floor(u)`` once ``u >= q + 1``,
    ``ceil(u)`` once ``u <= q - 1``, else ``q``."""
    if u >= q + 1:
        return math.floor(u)
    if u <= q - 1:
        return math.ceil(u)
    return q


def crossed_levels(q: int, new_q: int) -> list[tuple[int, bool]]:
    """The levels passed going from index ``q`` to ``new_q``, in order, each with ``on``."""
    up = new_q > q
    levels = range(q + 1, new_q + 1) if up else range(q - 1, new_q - 1, -1)
    return [(level, up) for level in levels]


def walk(q: int, u) -> tuple[int, list[tuple[int, bool]]]:
    """The reference rule from index ``q`` to value ``u``: ``(new q, [(level, on), ...])``."""
    new_q = reference_index(q, u)
    return new_q, crossed_levels(q, new_q)


def event_count_reference(arr: np.ndarray, sensor, factor, threshold) -> list[tuple]:
    """Event by event, in Fractions: the reference rule on each region's mean level."""
    theta = Fraction(threshold).limit_denominator(10**6)
    w, h, _ = sensor
    fx, fy = (factor, factor) if isinstance(factor, int) else factor
    level_sum, q, out = defaultdict(int), defaultdict(int), []
    for i in np.argsort(arr["t"], kind="stable"):
        rx, ry = int(arr["x"][i]) // fx, int(arr["y"][i]) // fy
        n_r = min(fx, w - rx * fx) * min(fy, h - ry * fy)
        level_sum[rx, ry] += 1 if arr["p"][i] > 0 else -1
        q[rx, ry], crossed = walk(q[rx, ry], Fraction(level_sum[rx, ry], n_r) / theta)
        out += [(rx, ry, arr["t"][i].item(), on) for _, on in crossed]
    return out


# --- funnelling: keep the first of each repeat ---------------------------------------------


def funnel_reference(arr: np.ndarray, fx: int, fy: int) -> list[tuple]:
    """Slow reference: stable time order, then keep the first of each (x', y', t, p)."""
    seen, out = set(), []
    for i in np.argsort(arr["t"], kind="stable"):
        key = (int(arr["x"][i]) // fx, int(arr["y"][i]) // fy, int(arr["t"][i]), bool(arr["p"][i]))
        if key not in seen:
            seen.add(key)
            out.append(key)
    return out


def temporal_reference(arr: np.ndarray, dt) -> list[tuple]:
    """Event by event in stable time order: bin start from the first t, keep first repeats."""
    order = np.argsort(arr["t"], kind="stable")
    if len(order) == 0:
        return []
    t0 = arr["t"][order[0]].item()
    seen, out = set(), []
    for i in order:
        t = arr["t"][i].item()
        key = (int(arr["x"][i]), int(arr["y"][i]), t0 + math.floor((t - t0) / dt) * dt,
               bool(arr["p"][i] > 0))
        if key not in seen:
            seen.add(key)
            out.append(key)
    return out


# --- streaming ----------------------------------------------------------------------------


def run_switching_paths(transform, arr: np.ndarray, cuts: list[int], *,
                        eager_first: bool) -> np.ndarray:
    """Feed ``arr`` split at ``cuts`` to one session whose chunks alternate between the eager
    and the compiled kernels (eager first, or compiled first), then flush."""
    pytest.importorskip("numba")
    session, parts = transform.session(), []
    for k, chunk in enumerate(np.split(arr, sorted(cuts))):
        with eager_kernels((k % 2 == 0) == eager_first):
            parts.append(session(chunk))
    parts.append(session.flush())
    return np.concatenate(parts)


def run_in_chunks(transform, arr: np.ndarray, cuts: list[int]) -> np.ndarray:
    """Feed ``arr`` split at ``cuts`` (repeated cuts make empty chunks), then flush."""
    session = transform.session()
    parts = [session(chunk) for chunk in np.split(arr, sorted(cuts))]
    parts.append(session.flush())
    return np.concatenate(parts)


#: Hypothesis cases of a stream cut into chunks: ``(seed, events, cut fractions)``.
chunkings = st.tuples(
    st.integers(0, 2**32 - 1),  # stream seed
    st.integers(0, 300),  # number of events
    st.lists(st.floats(0, 1), max_size=12),  # cut positions as fractions of the stream
)


# --- photocurrent pooling (method 7): slow float64 references -------------------------------


def region_members(sensor, factor):
    w, h, _ = sensor
    fx, fy = (factor, factor) if isinstance(factor, int) else factor
    out_w, out_h = -(-w // fx), -(-h // fy)
    members = defaultdict(list)
    for y in range(h):
        for x in range(w):
            members[x // fx, y // fy].append((x, y))
    return fx, fy, out_w, out_h, members


def log_mean_level(log_values, theta, snap=1e-9):
    """log(mean(exp(values))) / theta in float64 (log-sum-exp), snapped to a level."""
    top = max(log_values)
    u = (top + math.log(math.fsum(math.exp(v - top) for v in log_values))
         - math.log(len(log_values))) / theta
    return float(round(u)) if abs(u - round(u)) <= snap else u


def photocurrent_events_reference(arr, sensor, factor, contrast, threshold):
    """Event by event: recompute each region's mean photocurrent from scratch."""
    fx, fy, _, _, members = region_members(sensor, factor)
    level, q, out = defaultdict(int), defaultdict(int), []
    for i in np.argsort(arr["t"], kind="stable"):
        x, y = int(arr["x"][i]), int(arr["y"][i])
        level[x, y] += 1 if arr["p"][i] > 0 else -1
        r = (x // fx, y // fy)
        u = log_mean_level([contrast * level[p] for p in members[r]], threshold)
        q[r], crossed = walk(q[r], u)
        out += [(r[0], r[1], arr["t"][i].item(), on) for _, on in crossed]
    return out


def photocurrent_frames_reference(arr, sensor, factor, contrast, threshold, fps, cutoff_hz=0.0,
                                  ticks_per_second=10**6):
    """Dense frames at t_start + k / fps (last clipped to t_end), linear ramps in log I_r;
    integer timestamps of ``1 / ticks_per_second`` seconds."""
    fx, fy, _, _, members = region_members(sensor, factor)
    order = np.argsort(arr["t"], kind="stable")
    t = [arr["t"][i].item() for i in order]
    t0, duration = t[0], t[-1] - t[0]
    period = Fraction(ticks_per_second) / Fraction(fps).limit_denominator(10**6)
    last = math.ceil(Fraction(duration) / period)
    times = [float(min(k * period, duration)) for k in range(last + 1)]
    omega = 2 * math.pi * cutoff_hz / ticks_per_second
    q, u_prev, out = defaultdict(int), defaultdict(float), []
    for k, tk in enumerate(times):
        ell = defaultdict(float)
        for i, ti in zip(order, t, strict=True):
            if ti - t0 <= k * period:
                step = contrast if arr["p"][i] > 0 else -contrast
                decay = math.exp(-omega * (tk - (ti - t0)))
                ell[int(arr["x"][i]), int(arr["y"][i])] += step * decay
        t_before = times[k - 1] if k else 0.0
        for r, pixels in members.items():
            u = log_mean_level([ell[p] for p in pixels], threshold)
            q[r], crossed = walk(q[r], u)
            for j, on in crossed:
                ratio = 1.0 if j == u else (j - u_prev[r]) / (u - u_prev[r])
                at = t_before + ratio * (tk - t_before)
                out.append((r[0], r[1], t0 + math.floor(at + 0.5 + 1e-9), on))
            u_prev[r] = u
    return sorted(out)


# --- LIF pooling (method 6): the module stepped through dense frames -----------------------


def lif_dense_reference(arr: np.ndarray, pool) -> list[tuple]:
    """Slow oracle: bin into dense (T, 1, 2, H, W) frames, run the module through every step,
    turn spikes of step k into events at t_start + (k + 1) * dt clipped to t_end."""
    w, h, _ = pool.sensor_size
    t = arr["t"].astype(np.int64)
    t0, t1 = int(t.min()), int(t.max())
    dt = int(pool.dt)
    k = (t - t0) // dt
    frames = np.zeros((int(k.max()) + 1, 1, 2, h, w), dtype=np.float32)
    np.add.at(frames, (k, 0, (arr["p"] > 0).astype(int), arr["y"], arr["x"]), 1)
    spikes, _ = SpikingPooling.from_transform(pool)(torch.from_numpy(frames))
    step, _, p, y, x = (c.tolist() for c in spikes.nonzero(as_tuple=True))
    times = [min(t0 + (s + 1) * dt, t1) for s in step]
    return sorted(zip(x, y, times, [bool(v) for v in p], strict=True))


def bursty_stream(rng, n_bursts: int, sensor, *, gap_max: int, burst: int = 30) -> np.ndarray:
    """Dense bursts of events separated by long random silences (many empty steps)."""
    parts, start = [], 0
    for _ in range(n_bursts):
        part = random_stream(rng, int(rng.integers(1, burst)), sensor, t_max=40)
        part["t"] += start
        parts.append(part)
        start += 40 + int(rng.integers(0, gap_max))
    return np.concatenate(parts)


LIF_SETTINGS = [
    {"tau": math.inf, "weight": 0.25},
    {"tau": 30.0, "weight": 0.3, "mutual_inhibition": 0.125},
    {"tau": 10.0, "weight": 1.5, "threshold": 1.0},  # strong input: firing through empty steps
    {"tau": 50.0, "weight": 0.9, "reset_mechanism": "zero"},
    {"tau": 25.0, "weight": 0.6, "reset_mechanism": "none", "mutual_inhibition": 0.5},
    {"tau": math.inf, "weight": 0.7, "reset_mechanism": "none"},
    {"tau": 1e-3, "weight": 1.2},  # beta = 0
]


#: Hypothesis strategies of a small LIF case: events ``(x, y, t, on)`` on a 7x5 sensor and
#: the transform's settings (see :func:`lif_case`); ``beta`` is drawn by each test.
LIF_CASES = {
    "events": st.lists(
        st.tuples(st.integers(0, 6), st.integers(0, 4), st.integers(0, 400), st.booleans()),
        min_size=1,
        max_size=80,
    ),
    "dt": st.integers(1, 50),
    "weight": st.sampled_from([0.3, 0.5, 1.0, 2.5]),
    "inhibition": st.sampled_from([0.0, 0.25, 0.5]),
    "reset": st.sampled_from(["subtract", "zero", "none"]),
    "factor": st.sampled_from([1, 2, 3, (2, 5)]),
}


def lif_case(events, dt, beta, weight, inhibition, reset, factor):
    """A drawn :data:`LIF_CASES` case as ``(stream, LIFPooling)``; ``beta`` 0 is a tiny tau."""
    from evdown_torch import LIFPooling

    arr = np.array([(x, y, p, t) for x, y, t, p in events], dtype=DVS_DTYPE)
    tau = math.inf if beta == 1.0 else (1e-9 if beta == 0.0 else -dt / math.log(beta))
    return arr, LIFPooling((7, 5, 2), factor, dt=dt, tau=tau, weight=weight,
                           mutual_inhibition=inhibition, reset_mechanism=reset)


def unique_pixel_times(arr: np.ndarray) -> np.ndarray:
    """``arr`` without events repeating an earlier (x, y, t)."""
    _, keep = np.unique(np.stack([arr["x"], arr["y"], arr["t"]], 1), axis=0, return_index=True)
    return arr[np.sort(keep)]


# --- slow oracles of the linear and cubic estimators (docs/semantics.md, methods 4 and 5) -----

ESTIMATION_SNAP = 1e-9  # the kernels' tolerance for "on a level", in thresholds
HALF_TICK = 1e-6  # an oracle time this close to a half tick may round either way


def reference_knots(arr: np.ndarray) -> tuple[dict, float, float]:
    """Knots of every pixel with events: ``{(x, y): [(t, level), ...]}``, t_start, t_end."""
    order = np.argsort(arr["t"], kind="stable")
    t_start, t_end = arr["t"][order[0]], arr["t"][order[-1]]
    levels: dict = {}
    knots: dict = {}
    for i in order:
        key = (int(arr["x"][i]), int(arr["y"][i]))
        t = arr["t"][i]
        levels[key] = levels.get(key, 0) + (1 if arr["p"][i] > 0 else -1)
        pixel = knots.setdefault(key, [])
        if pixel and pixel[-1][0] == t:
            pixel[-1] = (t, levels[key])  # several events at one time: one knot
        else:
            pixel.append((t, levels[key]))
    for pixel in knots.values():
        if pixel[0][0] > t_start:
            pixel.insert(0, (t_start, 0))
        if pixel[-1][0] < t_end:
            pixel.append((t_end, pixel[-1][1]))
    return knots, t_start, t_end


def reference_curve(kind: str, knots: list) -> tuple:
    """``(f, df)`` of one pixel, in time relative to t_start."""
    from scipy.interpolate import PchipInterpolator

    ts = np.array([k[0] for k in knots], dtype=np.float64)
    ls = np.array([k[1] for k in knots], dtype=np.float64)
    if len(knots) == 1:
        return (lambda t: np.full(np.shape(t), ls[0])), (lambda t: np.zeros(np.shape(t)))
    if kind == "linear":
        slopes = np.diff(ls) / np.diff(ts)
        return (lambda t: np.interp(t, ts, ls)), (
            lambda t: slopes[np.clip(np.searchsorted(ts, t, side="right") - 1, 0, len(slopes) - 1)]
        )
    curve = PchipInterpolator(ts, ls)
    return curve, curve.derivative()


def reference_rule(q: int, u: float) -> tuple[int, bool]:
    """The reference index after a monotone step ending at ``u = M / theta``."""
    nearest = round(u)
    if abs(u - nearest) <= ESTIMATION_SNAP:
        return nearest, True
    return reference_index(q, u), False


def reference(arr: np.ndarray, sensor, factor, threshold: float, kind: str) -> dict:
    """Per output pixel, the list of ``(t, on)`` events in time order (t unrounded)."""
    from scipy.optimize import brentq

    fx, fy = factor
    w, h, _ = sensor
    knots, t_start, t_end = reference_knots(arr)
    t0 = float(t_start)
    regions: dict = {}
    for (x, y), pixel in knots.items():
        regions.setdefault((x // fx, y // fy), []).append(pixel)
    out = {}
    for (rx, ry), pixels in regions.items():
        n_r = min(fx, w - rx * fx) * min(fy, h - ry * fy)
        curves = [reference_curve(kind, [(float(t) - t0, lev) for t, lev in p]) for p in pixels]

        def u(t, curves=curves, n_r=n_r):
            return sum(c[0](t) for c in curves) / n_r / threshold

        def du(t, curves=curves, n_r=n_r):
            return sum(c[1](t) for c in curves) / n_r / threshold

        breakpoints = sorted({float(t) - t0 for p in pixels for t, _ in p})
        steps = []
        for ta, tb in zip(breakpoints[:-1], breakpoints[1:], strict=True):
            cuts = [ta]
            if kind == "cubic":  # split at the extrema: sign changes of M' on a fine grid
                grid = np.linspace(ta, tb, 201)
                d = du(grid)
                nonzero = [i for i in range(201) if d[i] != 0]
                for i, j in zip(nonzero[:-1], nonzero[1:], strict=True):
                    if d[i] * d[j] < 0:
                        root = brentq(du, grid[i], grid[j], xtol=1e-13 * (tb - ta))
                        if 1e-9 < (root - ta) / (tb - ta) < 1 - 1e-9:
                            cuts.append(root)
            cuts.append(tb)
            steps.extend(zip(cuts[:-1], cuts[1:], strict=True))
        events = []
        q, _ = reference_rule(0, u(0.0))  # the jump at t_start from level 0
        events += [(t0, q > 0)] * abs(q)
        for ta, tb in steps:
            ua, ub = u(ta), u(tb)
            new_q, on_level = reference_rule(q, ub)
            for level, up in crossed_levels(q, new_q):
                if on_level and level == new_q:
                    tc = tb
                elif kind == "linear":
                    tc = ta + (level - ua) / (ub - ua) * (tb - ta)
                else:
                    fa, fb = u(ta) - level, u(tb) - level
                    tc = tb if fa * fb > 0 else brentq(
                        lambda t, level=level: u(t) - level, ta, tb, xtol=1e-12 * (tb - ta)
                    )
                events.append((t0 + tc, up))
            q = new_q
        out[(rx, ry)] = events
    return {key: value for key, value in out.items() if value}


def by_output_pixel(out: np.ndarray) -> dict:
    """Output events grouped by output pixel, in output (time) order."""
    got: dict = {}
    for x, y, t, p in zip(out["x"], out["y"], out["t"], out["p"], strict=True):
        got.setdefault((int(x), int(y)), []).append((t.item(), bool(p > 0)))
    return got


def assert_rounded(t: int, t_ref: float | Fraction, key) -> None:
    """``t`` is ``t_ref`` rounded half up, or either neighbour within HALF_TICK of a half."""
    rounded = math.floor(t_ref + Fraction(1, 2))
    if abs((t_ref - math.floor(t_ref)) - Fraction(1, 2)) <= HALF_TICK:
        assert t in (math.floor(t_ref), math.ceil(t_ref)), (key, t, t_ref)
    else:
        assert t == rounded, (key, t, t_ref)


def assert_matches_reference(out: np.ndarray, expected: dict, integer_time: bool) -> None:
    """Same events per output pixel: count, polarity order, and times (rounded half up)."""
    got = by_output_pixel(out)
    assert got.keys() == expected.keys()
    for key, ref in expected.items():
        mine = got[key]
        assert len(mine) == len(ref), key
        assert [p for _, p in mine] == [p for _, p in ref], key
        for (t, _), (t_ref, _) in zip(mine, ref, strict=True):
            if integer_time:
                assert_rounded(t, Fraction(t_ref), key)
            else:
                assert t == pytest.approx(t_ref, rel=1e-12, abs=1e-6), (key, t, t_ref)


def exact_linear_reference(arr: np.ndarray, sensor, factor, threshold: float) -> dict:
    """The linear method in exact rationals: per output pixel, ``(t, on)`` with t a Fraction.

    Each pixel's polyline is evaluated at every breakpoint of its region as a Fraction; the
    region's sum is linear between breakpoints, so each crossing time is the exact rational
    ``ta + (level - ua) / (ub - ua) * (tb - ta)``. A value is on a level only when it equals it.
    """
    theta = Fraction(threshold).limit_denominator(10**6)
    fx, fy = factor
    w, h, _ = sensor
    knots, t_start, _ = reference_knots(arr)
    regions: dict = {}
    for (x, y), pixel in knots.items():
        regions.setdefault((x // fx, y // fy), []).append(
            [(int(t), level) for t, level in pixel])

    def value(pixel: list, t: int) -> Fraction:
        for (ta, la), (tb, lb) in zip(pixel[:-1], pixel[1:], strict=True):
            if ta <= t <= tb:
                return la + Fraction(lb - la, tb - ta) * (t - ta)
        return Fraction(pixel[0][1])  # one knot: t_start == t_end

    def rule(q: int, u: Fraction) -> int:
        return int(u) if u.denominator == 1 else reference_index(q, u)

    out = {}
    for (rx, ry), pixels in regions.items():
        n_r = min(fx, w - rx * fx) * min(fy, h - ry * fy)
        times = sorted({t for p in pixels for t, _ in p})
        us = [sum(value(p, t) for p in pixels) / (n_r * theta) for t in times]
        q = rule(0, us[0])
        events = [(Fraction(int(t_start)), q > 0)] * abs(q)
        for ta, tb, ua, ub in zip(times[:-1], times[1:], us[:-1], us[1:], strict=True):
            new_q = rule(q, ub)
            for level, up in crossed_levels(q, new_q):
                events.append((ta + (level - ua) / (ub - ua) * (tb - ta), up))
            q = new_q
        if events:
            out[(rx, ry)] = events
    return out
