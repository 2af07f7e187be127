"""The subsamplers (docs/semantics.md, methods 9 and 10): each against a slow per-event loop
of its rule with the same draws, hand-computed values, sessions, batches and seeding."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from scipy.ndimage import gaussian_filter

from evdown_torch import DensitySubsampling, Events, PoissonSubsampling, _tensors
from evdown_torch.events import DVS_DTYPE, sort_by_time, to_events
from evdown_torch.transforms.functional import density as density_kernel
from evdown_torch.transforms.functional.density import event_density, patch_offsets
from evdown_torch.transforms.functional.draws import event_uniforms
from evdown_torch.transforms.functional.poisson import _capped
from tests.helpers import FLOAT_DTYPE, chunkings, random_stream, run_in_chunks

SENSOR = (9, 7, 2)
REPO = Path(__file__).resolve().parents[2]


def _sorted_draws(arr: np.ndarray, seed: int) -> tuple[Events, np.ndarray]:
    """The stream in stable time order and its draws ``u_e``, as the transforms take them."""
    events, _ = to_events(arr, SENSOR)
    events = sort_by_time(events)
    draws = event_uniforms(events, seed, index=torch.arange(events.num_events),
                           origin=events.t[0].item())
    return events, draws.numpy()


def _rows(events: Events, factor: tuple[int, int], keep) -> list[tuple]:
    fx, fy = factor
    return [(int(x) // fx, int(y) // fy, float(t), bool(p))
            for x, y, t, p, k in zip(*(c.tolist() for c in events), keep, strict=True) if k]


def _out_rows(out: np.ndarray) -> list[tuple]:
    return [(int(e["x"]), int(e["y"]), float(e["t"]), bool(e["p"])) for e in out]


# --- DensitySubsampling -----------------------------------------------------------------------


def density_reference(events: Events, tau: float, k: int) -> list[float]:
    """Method 9's density of each event by its definition: a loop over earlier events."""
    r, sigma = k // 2, k / 5
    x, y, t, p = (c.tolist() for c in events)
    out = []
    for e in range(len(t)):
        total = 0.0
        for i in range(e + 1):  # up to and including e in stream order
            dx, dy = x[i] - x[e], y[i] - y[e]
            if p[i] == p[e] and abs(dx) <= r and abs(dy) <= r:
                total += math.exp(-(dx * dx + dy * dy) / (2 * sigma**2)) * math.exp(
                    -(t[e] - t[i]) / tau)
        out.append(total)
    return out


def test_density_by_hand():
    """k = 3 (sigma 0.6): side weight exp(-1 / 0.72), tau = 10 us."""
    ev = Events.from_columns([1, 2, 1, 1], [1, 1, 1, 1], [0, 10, 10, 20], [1, 1, 0, 1])
    side = math.exp(-1 / 0.72)
    expected = [1.0, 1 + side * math.exp(-1), 1.0,
                1 + math.exp(-2) + side * math.exp(-1)]
    got = event_density(ev, sensor_size=(4, 3, 2), tau=10.0, k=3).tolist()
    assert got == pytest.approx(expected, rel=1e-14)
    assert [round(w, 6) for _, _, w in patch_offsets(3)][4] == 1.0  # the centre


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("t_dtype", ["int", "float"])
def test_density_matches_the_per_event_loop(seed, t_dtype):
    rng = np.random.default_rng(seed)
    dtype = FLOAT_DTYPE if t_dtype == "float" else None
    arr = random_stream(rng, int(rng.integers(1, 160)), SENSOR, t_max=300,
                        **({"dtype": dtype} if dtype else {}))
    if t_dtype == "float":
        arr["t"] = arr["t"] * 0.37
    tau, k, s = [(40.0, 3, 0.3), (150.0, 5, 0.1), (1e9, 7, 0.05)][seed % 3]
    events, draws = _sorted_draws(arr, seed)
    reference = density_reference(events, tau, k)
    assert event_density(events, sensor_size=SENSOR, tau=tau, k=k).tolist() == pytest.approx(
        reference, rel=1e-12)
    factor = (2, 3)
    out = DensitySubsampling(SENSOR, factor, tau=tau, k=k, s=s, seed=seed)(arr)
    keep = [u < s * d for u, d in zip(draws, reference, strict=True)]
    assert _out_rows(out) == _rows(events, factor, keep)
    assert len(out) > 0 or not any(keep)


def test_density_keeps_everything_at_s_one_and_fewer_as_s_falls(rng):
    arr = random_stream(rng, 400, SENSOR, t_max=5_000)
    counts = [len(DensitySubsampling(SENSOR, 1, s=s)(arr)) for s in (1.0, 0.3, 0.1, 0.03, 0.01)]
    assert counts[0] == 400
    assert counts == sorted(counts, reverse=True) and counts[-1] < counts[1]


def test_density_pieces_of_a_long_stream_equal_one_pass(rng, monkeypatch):
    """A stream longer than a kernel's piece goes through with the per-pixel state."""
    arr = random_stream(rng, 300, SENSOR, t_max=900)
    whole = DensitySubsampling(SENSOR, 2, tau=200.0, s=0.1)(arr)
    events = sort_by_time(to_events(arr, SENSOR)[0])
    densities = event_density(events, sensor_size=SENSOR, tau=200.0)
    monkeypatch.setattr(_tensors, "CHUNK_EVENTS", 37)
    assert len(_tensors.chunk_bounds(events.t)) > 3
    np.testing.assert_array_equal(DensitySubsampling(SENSOR, 2, tau=200.0, s=0.1)(arr), whole)
    np.testing.assert_allclose(event_density(events, sensor_size=SENSOR, tau=200.0),
                               densities, rtol=1e-13)


def test_density_counts_decay_without_overflow_over_long_clocks():
    """Events 10**6 tau apart on an int64 clock near 2**62: each density is 1 (no NaN)."""
    t = [2**62 + i * 10**11 for i in range(5)]
    ev = Events.from_columns([3] * 5, [3] * 5, t, [1] * 5)
    assert event_density(ev, sensor_size=SENSOR, tau=1e5).tolist() == [1.0] * 5


def test_density_doubling_scan_covers_long_runs_at_one_pixel():
    """200 events at one pixel (8 doubling passes): S_k = sum_i exp(-(t_k - t_i) / tau)."""
    n = 200
    ev = Events.from_columns([4] * n, [2] * n, list(range(0, 3 * n, 3)), [0] * n)
    got = event_density(ev, sensor_size=SENSOR, tau=25.0, k=1)
    expected = [sum(math.exp(-3 * (k - i) / 25.0) for i in range(k + 1)) for k in range(n)]
    assert got.tolist() == pytest.approx(expected, rel=1e-13)


# --- PoissonSubsampling -----------------------------------------------------------------------


def blur_reference(value: np.ndarray) -> np.ndarray:
    """The Gaussian blur of method 10 by its definition (sigma 2, 13 x 13, renormalised)."""
    h, w = value.shape
    out = np.zeros_like(value)
    for jy in range(h):
        for jx in range(w):
            num = den = 0.0
            for iy in range(max(0, jy - 6), min(h, jy + 7)):
                for ix in range(max(0, jx - 6), min(w, jx + 7)):
                    g = math.exp(-((ix - jx) ** 2 + (iy - jy) ** 2) / 8.0)
                    num += g * value[iy, ix]
                    den += g
            out[jy, jx] = num / den
    return out


def test_the_reference_blur_is_scipys_normalised_gaussian(rng):
    value = rng.random((7, 9))
    ones = np.ones_like(value)
    scipy = (gaussian_filter(value, 2.0, mode="constant", truncate=3.0)
             / gaussian_filter(ones, 2.0, mode="constant", truncate=3.0))
    np.testing.assert_allclose(blur_reference(value), scipy, rtol=1e-12)


def poisson_reference(events: Events, draws, sensor, window: float, alpha: float) -> list[bool]:
    """Method 10 by its rule: a loop over events, dense maps of the previous window."""
    w, h, _ = sensor
    x, y, t, p = (c.tolist() for c in events)
    t0 = t[0]
    counts: dict[tuple[int, int], np.ndarray] = {}
    budget = Fraction(str(alpha))
    kept = 0
    keep = []
    for seen, e in enumerate(range(len(t)), start=1):
        m = math.floor((t[e] - t0) / window)
        grid = counts.setdefault((m, p[e]), np.zeros((h, w)))
        grid[y[e], x[e]] += 1
        previous = counts.get((m - 1, p[e]))
        chance = alpha
        if previous is not None:
            blurred = blur_reference(1 - np.exp(-previous))
            if blurred.mean() > 0:
                chance = min(1.0, alpha * blurred[y[e], x[e]] / blurred.mean())
        take = bool(draws[e] < chance) and kept + 1 <= budget * seen
        kept += take
        keep.append(take)
    return keep


def test_the_cap_by_hand():
    """alpha = 1/2: at most floor(seen / 2) kept; every event a candidate."""
    keep = _capped(torch.ones(6, dtype=torch.bool), 0, 0, Fraction(1, 2))
    assert keep.tolist() == [False, True, False, True, False, True]
    # 3 seen and 1 kept before; limits floor(seen / 2) after each event: 2, 2, 3, 3
    keep = _capped(torch.ones(4, dtype=torch.bool), 3, 1, Fraction(1, 2))
    assert keep.tolist() == [True, False, True, False]
    # candidates late: the allowance saved up lets two through in a row
    keep = _capped(torch.tensor([False, False, True, True]), 3, 1, Fraction(1, 2))
    assert keep.tolist() == [False, False, True, True]


@pytest.mark.parametrize("seed", range(6))
def test_poisson_matches_the_per_event_loop(seed):
    rng = np.random.default_rng(100 + seed)
    arr = random_stream(rng, int(rng.integers(1, 200)), SENSOR, t_max=400)
    window, alpha = [(50, 0.3), (17, 0.05), (120, 0.8)][seed % 3]
    events, draws = _sorted_draws(arr, seed)
    keep = poisson_reference(events, draws, SENSOR, window, alpha)
    factor = (3, 2)
    out = PoissonSubsampling(SENSOR, factor, window=window, alpha=alpha, seed=seed)(arr)
    assert _out_rows(out) == _rows(events, factor, keep)


def test_poisson_on_float_timestamps_matches_the_loop(rng):
    arr = random_stream(rng, 150, SENSOR, t_max=400, dtype=FLOAT_DTYPE)
    arr["t"] = arr["t"] * 1e-3 + 0.25  # seconds
    events, draws = _sorted_draws(arr, 3)
    keep = poisson_reference(events, draws, SENSOR, 0.04, 0.25)
    out = PoissonSubsampling(SENSOR, 1, window=0.04, alpha=0.25, seed=3)(arr)
    assert _out_rows(out) == _rows(events, (1, 1), keep)


def test_poisson_never_keeps_more_than_alpha_of_the_events_seen(rng):
    arr = random_stream(rng, 500, SENSOR, t_max=2_000)
    for alpha in (0.05, 0.2, 0.5):
        out = PoissonSubsampling(SENSOR, 1, window=100, alpha=alpha)(arr)
        kept_t = out["t"]
        seen = np.searchsorted(arr["t"], kept_t, side="right")  # an upper bound on seen
        assert np.all(np.arange(1, len(out) + 1) <= alpha * seen + 1e-9)


def test_poisson_refuses_a_fractional_window_for_integer_time(rng):
    arr = random_stream(rng, 20, SENSOR)
    with pytest.raises(ValueError, match="whole number"):
        PoissonSubsampling(SENSOR, 1, window=2.5, alpha=0.5)(arr)


# --- both: sessions, batches, seeds, settings --------------------------------------------------

SUBSAMPLERS = {
    "density": DensitySubsampling(SENSOR, factor=2, tau=60.0, k=5, s=0.08, seed=1),
    "poisson": PoissonSubsampling(SENSOR, factor=(3, 2), window=13, alpha=0.3, seed=2),
}


@pytest.mark.parametrize("name", sorted(SUBSAMPLERS))
@settings(max_examples=30, deadline=None, derandomize=True)
@given(case=chunkings)
def test_any_chunking_gives_the_batch_result(name, case):
    seed, n, fractions = case
    arr = random_stream(np.random.default_rng(seed), n, SENSOR, t_max=120)
    transform = SUBSAMPLERS[name]
    cuts = [int(f * n) for f in fractions]
    np.testing.assert_array_equal(run_in_chunks(transform, arr, cuts), transform(arr))


@pytest.mark.parametrize("name", sorted(SUBSAMPLERS))
def test_odd_chunkings_of_a_longer_stream(name, rng):
    arr = random_stream(rng, 3_000, SENSOR, t_max=20_000)
    transform = SUBSAMPLERS[name]
    whole = transform(arr)
    assert 0 < len(whole) < len(arr)
    for cuts in ([1, 2, 3, 997, 998, 2999], list(range(0, 3000, 7)), [1500, 1500, 1501]):
        np.testing.assert_array_equal(run_in_chunks(transform, arr, cuts), whole)


@pytest.mark.parametrize("name", sorted(SUBSAMPLERS))
def test_a_batch_equals_each_recording_alone(name, rng):
    transform = SUBSAMPLERS[name]
    recordings = [random_stream(rng, n, SENSOR, t_max=300) for n in (40, 0, 250, 1)]
    recordings.append(recordings[2].copy())
    for got, arr in zip(transform.batch(recordings), recordings, strict=True):
        np.testing.assert_array_equal(got, transform(arr))


@pytest.mark.parametrize("name", sorted(SUBSAMPLERS))
def test_draws_follow_the_recording_and_the_seed_not_the_container(name, rng):
    arr = random_stream(rng, 500, SENSOR, t_max=3_000)
    transform = SUBSAMPLERS[name]
    out = transform(arr)
    tensor = torch.tensor(np.stack([arr["x"], arr["y"], arr["t"], arr["p"]], 1).astype(np.int64))
    np.testing.assert_array_equal(transform(tensor).numpy(),
                                  np.stack([out["x"], out["y"], out["t"], out["p"]], 1))
    other = dataclasses.replace(transform, seed=transform.seed + 1)
    assert not np.array_equal(other(arr), out)
    shifted = arr.copy()
    shifted["t"] += 10**12  # the clock's origin changes no draw
    moved = transform(shifted)
    np.testing.assert_array_equal(moved["t"] - 10**12, out["t"])
    np.testing.assert_array_equal(moved[["x", "y", "p"]], out[["x", "y", "p"]])


def test_seeded_draws_are_the_same_in_another_process(rng, tmp_path):
    arr = random_stream(rng, 400, SENSOR, t_max=3_000)
    np.save(here := tmp_path / "stream.npy", arr)
    script = (
        "import numpy as np; from evdown_torch import DensitySubsampling, PoissonSubsampling; "
        f"a = np.load({str(here)!r}); s = {SENSOR!r}; "
        "d = DensitySubsampling(s, 2, tau=60.0, k=5, s=0.08, seed=1)(a); "
        "p = PoissonSubsampling(s, (3, 2), window=13, alpha=0.3, seed=2)(a); "
        "print(d['t'].tolist(), p['t'].tolist())"
    )
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          cwd=REPO, env={"PYTHONPATH": str(REPO), "PATH": ""}, check=True)
    expected = (f"{SUBSAMPLERS['density'](arr)['t'].tolist()} "
                f"{SUBSAMPLERS['poisson'](arr)['t'].tolist()}")
    assert done.stdout.strip() == expected


def test_an_empty_stream_gives_an_empty_stream():
    for transform in SUBSAMPLERS.values():
        empty = np.empty(0, dtype=random_stream(np.random.default_rng(0), 1, SENSOR).dtype)
        assert len(transform(empty)) == 0
        assert transform(torch.empty(0, 4, dtype=torch.int64)).shape == (0, 4)


@pytest.mark.parametrize(("cls", "settings_", "match"), [
    (DensitySubsampling, {"k": 4}, "odd"),
    (DensitySubsampling, {"k": 0}, "k must be a positive integer"),
    (DensitySubsampling, {"tau": 0.0}, "tau"),
    (DensitySubsampling, {"s": 0.0}, "s must be a positive"),
    (DensitySubsampling, {"seed": -1}, "seed"),
    (PoissonSubsampling, {"alpha": 1.5}, r"alpha must lie in \[1e-6, 1\]"),
    (PoissonSubsampling, {"alpha": 0.0}, "alpha"),
    (PoissonSubsampling, {"window": -3}, "window"),
    (PoissonSubsampling, {"seed": 1.5}, "seed"),
])
def test_bad_settings_are_refused(cls, settings_, match):
    with pytest.raises((ValueError, TypeError), match=match):
        cls(SENSOR, 2, **settings_)


def test_kernel_pieces_use_the_lookup_groups(rng, monkeypatch):
    """Neighbour lookups in groups smaller than the patch give the same densities."""
    arr = random_stream(rng, 200, SENSOR, t_max=700)
    events = sort_by_time(to_events(arr, SENSOR)[0])
    whole = event_density(events, sensor_size=SENSOR, tau=90.0, k=5)
    monkeypatch.setattr(density_kernel, "LOOKUP_ELEMENTS", 450)  # 2 offsets a group
    np.testing.assert_array_equal(event_density(events, sensor_size=SENSOR, tau=90.0, k=5),
                                  whole)


def test_the_kernels_run_where_the_events_are(device, rng):
    arr = random_stream(rng, 600, SENSOR, t_max=4_000)
    columns = np.stack([arr["x"], arr["y"], arr["t"], arr["p"]], 1).astype(np.int64)
    for transform in SUBSAMPLERS.values():
        on_cpu = transform(torch.tensor(columns))
        out = transform(torch.tensor(columns, device=device))
        assert out.device.type == device.type
        torch.testing.assert_close(out.cpu(), on_cpu, rtol=0, atol=0)


@pytest.mark.parametrize("span", [50, 10**5, 2**40])
def test_distinct_keys_by_marks_are_torch_unique(span, rng):
    # PoissonSubsampling's distinct keys: by a table of marks (small ranges, negative values
    # too) or by the sort (a wide range), torch.unique's sorted values and inverse.
    from evdown_torch.transforms.functional import poisson as poisson_kernel

    values = torch.from_numpy(rng.integers(-span // 2, span // 2, 20_000))
    distinct, inverse = poisson_kernel._distinct(values)
    want, want_inverse = torch.unique(values, return_inverse=True)
    assert torch.equal(distinct, want) and torch.equal(inverse, want_inverse)
    empty = poisson_kernel._distinct(torch.empty(0, dtype=torch.int64))
    assert all(part.shape == (0,) and part.dtype == torch.int64 for part in empty)


def test_poisson_blur_finds_its_rows_by_table_as_by_search(monkeypatch, rng):
    # The blur's lookups of its targets: by the table of places or by binary search (a table
    # refused), the same kept events.
    from evdown_torch.transforms.functional import poisson as poisson_kernel

    arr = random_stream(rng, 6_000, SENSOR, t_max=3_000)
    transform = SUBSAMPLERS["poisson"]
    by_table = transform(arr)
    monkeypatch.setattr(poisson_kernel, "_places", lambda ordered: (0, None))
    np.testing.assert_array_equal(transform(arr), by_table)
    assert 0 < len(by_table) < len(arr)


@pytest.mark.parametrize("t_dtype", [DVS_DTYPE, FLOAT_DTYPE])
def test_density_neighbour_sweep_equals_the_search_bit_for_bit(t_dtype, rng):
    # The compiled sweep finds each neighbour's last event as the eager binary search does:
    # the same densities and touched pixels, bit for bit, in one pass and continuing a
    # state (pixels whose last event came in an earlier chunk), with ties and both polarities.
    from tests.helpers import assert_identical, both_paths

    arr = random_stream(rng, 3_000, SENSOR, t_max=400, dtype=t_dtype)
    events = sort_by_time(to_events(arr, SENSOR)[0])
    settings_ = density_kernel.DensitySettings(SENSOR, (1, 1), 40.0, 5)
    first = events.select(torch.arange(1_200))
    rest = events.select(torch.arange(1_200, events.num_events))
    state = density_kernel.density_step(first, density_kernel.density_init(settings_, first),
                                        settings_)[1]
    assert state.seen == 1_200

    def densities():
        return (density_kernel._density_sorted(events, settings_, None),
                density_kernel._density_sorted(rest, settings_, state))

    compiled, eager = both_paths(densities)
    assert_identical(compiled, eager)
    assert bool((compiled[1][0] >= 1.0).all())
    kept = both_paths(lambda: run_in_chunks(SUBSAMPLERS["density"], arr, [0, 700, 1_900]))
    assert_identical(*kept)
