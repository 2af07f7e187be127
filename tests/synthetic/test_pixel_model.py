"""The DVS pixel model against hand-computed crossings, a slow reference and noise statistics."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from evdown_torch.synthetic import PixelModelConfig, noise_events, pixel_events, refractory_mask


def one_pixel(t, log_intensity, threshold, **kwargs):
    pixel = torch.zeros(len(t), dtype=torch.int64)
    _, times, on = pixel_events(pixel, torch.tensor(t), torch.tensor(log_intensity,
                                dtype=torch.float64), threshold=threshold, **kwargs)
    return list(zip(times.tolist(), on.tolist(), strict=True))


def test_ramp_up_then_down_hand_computed():
    # x = L / 0.2 goes 0 -> 2.5 over [0, 1000] us, then 2.5 -> -1.5 over [1000, 2000] us.
    # Up: levels 1, 2 at 400, 800 us (q = 2). Down: the reference is 2, so the first OFF is at
    # level 1 (x = 1 at 1375 us), then 0 (1625 us), then -1 (1875 us); -1.5 stops short of -2.
    events = one_pixel([0, 1000, 2000], [0.0, 0.5, -0.3], 0.2)
    assert events == [(400, True), (800, True), (1375, False), (1625, False), (1875, False)]


def test_refractory_drops_events_too_close_to_the_last_kept_one():
    events = one_pixel([0, 1000, 2000], [0.0, 0.5, -0.3], 0.2, refractory_us=300)
    # 1625 comes 250 us after 1375: dropped; 1875 comes 500 us after 1375: kept.
    assert events == [(400, True), (800, True), (1375, False), (1875, False)]
    events = one_pixel([0, 1000, 2000], [0.0, 0.5, -0.3], 0.2, refractory_us=450)
    # 800 is 400 after 400: dropped; 1375 is 975 after 400: kept; 1625 dropped; 1875 kept.
    assert events == [(400, True), (1375, False), (1875, False)]


def test_crossing_times_are_interpolated_and_rounded_half_up():
    # x: 0 -> 2.5 over 3 us: levels at 1.2 us and 2.4 us -> 1 and 2.
    assert one_pixel([0, 3], [0.0, 0.5], 0.2) == [(1, True), (2, True)]
    # x: 0 -> 2 over 1 us: level 1 at exactly 0.5 us rounds up to 1; level 2 at 1 us.
    assert one_pixel([0, 1], [0.0, 0.4], 0.2) == [(1, True), (1, True)]
    # several levels between two samples each get their own time
    assert one_pixel([100, 1100], [0.0, -1.0], 0.25) == [
        (350, False), (600, False), (850, False), (1100, False)
    ]


def test_reaching_a_level_counts_and_reversal_needs_a_full_threshold():
    # x = 0, 1, 0, 1: ON at 1, OFF on reaching 0 (= q - 1), ON again on reaching 1.
    events = one_pixel([0, 10, 20, 30], [0.0, 0.2, 0.0, 0.2], 0.2)
    assert events == [(10, True), (20, False), (30, True)]
    # x = 0, 1.5, 0.6, 1.9: after ON at 1 the dip to 0.6 is not a full threshold: no OFF;
    # rising to 1.9 does not reach 2: nothing.
    assert one_pixel([0, 10, 20, 30], [0.0, 0.3, 0.12, 0.38], 0.2) == [(7, True)]


def test_offset_moves_the_reference_within_the_window():
    # offset 0.5: x starts at 0.5, so x = 1 is reached a quarter of the way up to x = 2.5
    assert one_pixel([0, 1000], [0.0, 0.4], 0.2, offset=0.5) == [(250, True), (750, True)]
    assert one_pixel([0, 1000], [0.0, -0.1], 0.2, offset=-0.5) == [(1000, False)]


def test_per_pixel_thresholds_and_event_order():
    pixel = torch.tensor([0, 0, 2, 2])
    t = torch.tensor([0, 1000, 0, 1000])
    level = torch.tensor([0.0, 0.75, 0.0, 0.75], dtype=torch.float64)
    pix, times, on = pixel_events(pixel, t, level, threshold=torch.tensor([0.25, 9.0, 0.375]))
    # pixel 0: x = 0 -> 3, levels at 333.3, 666.7, 1000 us; pixel 2: x = 0 -> 2, 500, 1000 us;
    # ties in time are ordered by pixel
    assert list(zip(pix.tolist(), times.tolist(), strict=True)) == [
        (0, 333), (2, 500), (0, 667), (0, 1000), (2, 1000)
    ]
    assert bool(on.all())


def refractory_filtered(crossings, pixel, refractory):
    """``(t, pixel, on)`` of the time-ordered ``(t, on)`` crossings, times rounded to the
    nearest us, without those closer than ``refractory`` to the last one kept."""
    out, last_kept = [], None
    for time, on in crossings:
        time = math.floor(time + 0.5)
        if last_kept is None or time - last_kept >= refractory:
            out.append((time, pixel, on))
            last_kept = time
    return out


def slow_reference(pixel, t, level, theta, offset, refractory):
    """Obviously-correct per-pixel loop over segments and levels."""
    out = []
    for p in sorted(set(pixel)):
        idx = [i for i in range(len(pixel)) if pixel[i] == p]
        x = [(level[i] - level[idx[0]]) / theta[p] + offset[p] for i in idx]
        q, mine = 0, []
        for k in range(1, len(idx)):
            a, b = x[k - 1], x[k]
            t0, t1 = t[idx[k - 1]], t[idx[k]]
            while b > a and b >= q + 1:
                q += 1
                mine.append((t0 + (q - a) / (b - a) * (t1 - t0), True))
            while b < a and b <= q - 1:
                q -= 1
                mine.append((t0 + (q - a) / (b - a) * (t1 - t0), False))
        out += refractory_filtered(mine, p, refractory)
    return sorted(out, key=lambda e: (e[0], e[1]))


def slow_two_thresholds(pixel, t, level, theta_on, theta_off, offset, refractory):
    """Per-pixel loop of a DVS pixel with two comparators: a reference level moved by the
    threshold of each event; every level is ``start + a * theta_on - b * theta_off``."""
    out = []
    for p in sorted(set(pixel)):
        idx = [i for i in range(len(pixel)) if pixel[i] == p]
        on, off = theta_on[p], theta_off[p]
        start = level[idx[0]] - offset[p] * (on if offset[p] > 0 else off)
        a = b = 0
        mine = []
        for k in range(1, len(idx)):
            x0, x1 = level[idx[k - 1]], level[idx[k]]
            t0, t1 = t[idx[k - 1]], t[idx[k]]
            while x1 > x0 and start + (a + 1) * on - b * off <= x1:
                a += 1
                mine.append((t0 + (start + a * on - b * off - x0) / (x1 - x0) * (t1 - t0), True))
            while x1 < x0 and start + a * on - (b + 1) * off >= x1:
                b += 1
                mine.append((t0 + (start + a * on - b * off - x0) / (x1 - x0) * (t1 - t0),
                             False))
        out += refractory_filtered(mine, p, refractory)
    return sorted(out, key=lambda e: (e[0], e[1]))


def random_signals(rng, n_pixels, *, stride, per_pixel=30):
    """Random-walk levels at ``per_pixel`` increasing times for pixels ``0, stride, ...``:
    ``(pixel, t, level)`` arrays, pixel-major."""
    pixel = np.repeat(np.arange(n_pixels) * stride, per_pixel)
    t = np.concatenate([np.cumsum(rng.integers(1, 200, per_pixel)) for _ in range(n_pixels)])
    level = np.concatenate([np.cumsum(rng.normal(0, 0.3, per_pixel)) for _ in range(n_pixels)])
    return pixel, t, level


@pytest.mark.parametrize("refractory", [0, 300])
def test_two_thresholds_match_slow_reference(refractory, rng):
    n_pixels = 40
    pixel, t, level = random_signals(rng, n_pixels, stride=2)
    theta_on = rng.uniform(0.1, 0.4, 2 * n_pixels)
    theta_off = rng.uniform(0.1, 0.4, 2 * n_pixels)
    offset = rng.uniform(-0.99, 0.99, 2 * n_pixels)
    pix, times, on = pixel_events(
        torch.from_numpy(pixel), torch.from_numpy(t), torch.from_numpy(level),
        threshold=torch.from_numpy(theta_on), off_threshold=torch.from_numpy(theta_off),
        offset=torch.from_numpy(offset), refractory_us=refractory,
    )
    got = list(zip(times.tolist(), pix.tolist(), on.tolist(), strict=True))
    expected = slow_two_thresholds(pixel.tolist(), t.tolist(), level.tolist(), theta_on,
                                   theta_off, offset, refractory)
    assert len(expected) > 200
    assert got == expected


def test_on_share_follows_the_thresholds():
    """A bump up and back down: ON count ~ rise / theta_on, OFF count ~ fall / theta_off."""
    _, _, p = pixel_events(torch.zeros(3, dtype=torch.long), torch.tensor([0, 1000, 2000]),
                           torch.tensor([0.0, 3.05, 0.1], dtype=torch.float64),
                           threshold=0.1, off_threshold=0.3)
    # up: 30 ON (the reference ends at 3.0); down to 0.1: OFF at 2.7, 2.4, ..., 0.3 (9), the
    # next level 0.0 is not reached
    assert int(p.sum()) == 30 and int((~p).sum()) == 9


@pytest.mark.parametrize("refractory", [0, 40, 300])
def test_matches_slow_reference_on_random_signals(refractory, rng):
    n_pixels = 40
    pixel, t, level = random_signals(rng, n_pixels, stride=3)
    theta = rng.uniform(0.1, 0.4, 3 * n_pixels)
    offset = rng.uniform(-0.99, 0.99, 3 * n_pixels)
    pix, times, on = pixel_events(
        torch.from_numpy(pixel), torch.from_numpy(t), torch.from_numpy(level),
        threshold=torch.from_numpy(theta), offset=torch.from_numpy(offset),
        refractory_us=refractory,
    )
    got = list(zip(times.tolist(), pix.tolist(), on.tolist(), strict=True))
    expected = slow_reference(pixel.tolist(), t.tolist(), level.tolist(), theta, offset,
                              refractory)
    assert len(expected) > 200
    assert got == expected


def test_refractory_mask_matches_greedy_loop(rng):
    pixel = np.sort(rng.integers(0, 20, 3000))
    t = np.concatenate([np.sort(rng.integers(0, 20_000, int((pixel == p).sum())))
                        for p in range(20)])
    keep = refractory_mask(torch.from_numpy(pixel), torch.from_numpy(t), 700).numpy()
    expected, last = [], {}
    for p, time in zip(pixel.tolist(), t.tolist(), strict=True):
        ok = p not in last or time - last[p] >= 700
        expected.append(ok)
        if ok:
            last[p] = time
    assert keep.tolist() == expected


def test_empty_and_flat_inputs_give_no_events():
    empty = torch.empty(0, dtype=torch.int64)
    pix, t, p = pixel_events(empty, empty, torch.empty(0, dtype=torch.float64), threshold=0.2)
    assert pix.numel() == t.numel() == p.numel() == 0
    assert t.dtype == torch.int64 and p.dtype == torch.bool
    assert one_pixel([0, 10, 20], [0.3, 0.3, 0.3], 0.2) == []


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"threshold": 0.0}, ValueError, "threshold"),
        ({"threshold": 0.2, "offset": 1.0}, ValueError, "offset"),
        ({"threshold": 0.2, "refractory_us": -1}, ValueError, "refractory_us"),
        ({"threshold": torch.tensor([0.2, -1.0])}, ValueError, "threshold"),
        ({"threshold": torch.tensor([0.2])}, ValueError, "entries"),
    ],
)
def test_bad_settings_raise(kwargs, error, match):
    with pytest.raises(error, match=match):
        pixel_events(torch.tensor([0, 1]), torch.tensor([0, 1]),
                     torch.tensor([0.0, 1.0]), **kwargs)


def test_bad_samples_raise():
    level = torch.tensor([0.0, 1.0, 2.0])
    with pytest.raises(ValueError, match="sorted by pixel"):
        pixel_events(torch.tensor([1, 0, 1]), torch.tensor([0, 1, 2]), level, threshold=0.2)
    with pytest.raises(ValueError, match="increase strictly"):
        pixel_events(torch.tensor([0, 0, 0]), torch.tensor([0, 5, 5]), level, threshold=0.2)
    with pytest.raises(ValueError, match="1-D tensors of one length"):
        pixel_events(torch.tensor([0, 0]), torch.tensor([0, 5, 6]), level, threshold=0.2)
    with pytest.raises(TypeError, match="float"):
        pixel_events(torch.tensor([0, 0]), torch.tensor([0, 5]), torch.tensor([0, 1]),
                     threshold=0.2)


def test_noise_counts_follow_their_rates():
    g = torch.Generator().manual_seed(0)
    pix, t, p = noise_events(num_pixels=1000, duration_us=10_000_000, background_rate_hz=1.0,
                             hot_pixel_fraction=0.0, hot_pixel_rate_hz=50.0, generator=g)
    assert abs(pix.numel() - 10_000) < 500  # Poisson, sd 100
    assert bool((t >= 0).all() and (t < 10_000_000).all())
    assert bool((pix >= 0).all() and (pix < 1000).all())
    assert 0.45 < p.float().mean().item() < 0.55
    g = torch.Generator().manual_seed(1)
    pix, t, _ = noise_events(num_pixels=10_000, duration_us=1_000_000, background_rate_hz=0.0,
                             hot_pixel_fraction=0.01, hot_pixel_rate_hz=30.0, generator=g)
    hot = torch.unique(pix).numel()
    assert 60 < hot < 140  # binomial(10000, 0.01), sd 10
    assert 0.7 * hot * 30 < pix.numel() < 1.3 * hot * 30 + 200


def test_noise_is_deterministic_per_generator_seed():
    def draw(seed):
        return noise_events(num_pixels=500, duration_us=2_000_000, background_rate_hz=2.0,
                            hot_pixel_fraction=0.01, hot_pixel_rate_hz=10.0,
                            generator=torch.Generator().manual_seed(seed))

    a, b, c = draw(3), draw(3), draw(4)
    assert all(torch.equal(u, v) for u, v in zip(a, b, strict=True))
    assert not torch.equal(a[1], c[1])


@pytest.mark.parametrize(
    ("field", "value", "error"),
    [
        ("threshold", 0, ValueError),
        ("threshold", "0.2", TypeError),
        ("threshold_mismatch", -0.1, ValueError),
        ("refractory_us", 0.5, TypeError),
        ("refractory_us", -5, ValueError),
        ("background_rate_hz", float("nan"), ValueError),
        ("hot_pixel_fraction", 1.5, ValueError),
        ("max_step_px", 0.0, ValueError),
        ("max_step_us", 0, ValueError),
    ],
)
def test_config_validation(field, value, error):
    with pytest.raises(error, match=field):
        PixelModelConfig(**{field: value})


def test_config_is_frozen():
    config = PixelModelConfig()
    with pytest.raises(AttributeError):
        config.threshold = 0.3  # type: ignore[misc]
