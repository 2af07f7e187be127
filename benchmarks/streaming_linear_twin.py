"""The streaming LinearEstimation design's eager twin: the whole stream at once, in torch.

:func:`design_whole` gives the events of LinearEstimation's compiled ramps
(:class:`~evdown_torch.transforms.functional.compiled.linear_ramps.RampSession`, chunk by chunk)
from vectorised torch, with no loop over events, regions or moves: the same fixed-point integers and
the same doubts, decided by the same rules on a value found another way: the region's pixels'
segments evaluated at the doubt's time (exact integer parts, a float remainder:
:class:`PixelSegments`, :func:`exact_levels`), where the loop corrects its integers by the error it
tracks. Both are within float error of the exact value, so the two agree event for event whatever
the chunks, except where an exact value lies within that error of the edge of the package's
tolerances.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from evdown_torch._tensors import changes, run_index, segmented_cumsum, take, where_true
from evdown_torch.bench.realtime import REALTIME_MAX_DELAY_US
from evdown_torch.events import DVS_DTYPE
from evdown_torch.transforms.functional.compiled.linear_ramps import _HALF, RampSession
from evdown_torch.transforms.functional.compiled.linear_ramps import RampSettings as Settings
from evdown_torch.transforms.functional.estimation.knots import HALF_TOLERANCE, RELATIVE_ERROR
from evdown_torch.transforms.functional.reference import SNAP, move_crossings

#: The live replay's settings (``evdown bench --realtime``): sensor, factor, threshold a / b.
SENSOR = (128, 128, 2)
FACTOR = 4
THRESHOLD = (1, 4)


def replay_settings() -> Settings:
    """The ramps' settings of the live replay (``D`` = ``REALTIME_MAX_DELAY_US``)."""
    return Settings.of(SENSOR, (FACTOR, FACTOR), THRESHOLD, REALTIME_MAX_DELAY_US)


class RampArrays:
    """The ramps' session on structured arrays (the replay's settings by default).

    ``__call__(chunk)`` returns the decided events as an array of the chunk's dtype.
    """

    def __init__(self, t_start: int, max_events: int, settings: Settings | None = None,
                 session: RampSession | None = None) -> None:
        self.session = session or RampSession(t_start, max_events,
                                              settings or replay_settings())

    @classmethod
    def resumed(cls, session: RampSession) -> RampArrays:
        """The arrays' face of a session made already (e.g. from the package's state)."""
        return cls(session.t_start, 0, session.settings, session)

    @property
    def horizon(self) -> int:
        return self.session.horizon

    @property
    def counts(self) -> np.ndarray:
        return self.session.counts

    def __call__(self, chunk: np.ndarray) -> np.ndarray:
        decided = self.session(chunk["x"], chunk["y"], chunk["t"], chunk["p"])
        if decided is None:
            raise RuntimeError("the ramps' outputs outgrew their buffer (the package's session "
                               "solves such a chunk as a window; this twin does not)")
        x, y, t, on = decided
        out = np.empty(len(t), chunk.dtype if chunk.dtype.names else DVS_DTYPE)
        out["x"], out["y"], out["t"], out["p"] = x, y, t, on
        return out


def region_members(settings: Settings) -> np.ndarray:
    """``(R, max n_r)`` int64: each region's pixels (``y * W + x``), ascending, then ``W * H``.

    ``W * H`` (a pixel no event has) pads the smaller edge regions.
    """
    width, height = settings.width, settings.row.shape[0]
    pixel_y, pixel_x = np.divmod(np.arange(width * height), width)
    region = settings.row[pixel_y] * settings.out_w + settings.column[pixel_x]
    order = np.argsort(region, kind="stable")
    rank = np.arange(width * height) - np.repeat(np.cumsum(settings.pixels) - settings.pixels,
                                                 settings.pixels)
    members = np.full((settings.pixels.shape[0], int(settings.pixels.max())), width * height)
    members[region[order], rank] = order
    return members


class PixelSegments:
    """Each pixel's knots, to evaluate regions' sums of levels at given times.

    Args:
        pixel: ``(N,)`` int64 pixel (``y * W + x``) of each event, ascending (stable).
        t: ``(N,)`` int64 time of each event (ascending inside a pixel).
        c: ``(N,)`` int64 change of each event (+1 or -1).
        h: ``(N,)`` int64 start of each event's ramp (its knot's held or previous knot).
        t_start: the stream's first time.
        settings: the design's.
    """

    def __init__(self, pixel: Tensor, t: Tensor, c: Tensor, h: Tensor, t_start: int,
                 settings: Settings) -> None:
        new_knot = changes(pixel) | changes(t)
        first_at = where_true(new_knot)
        # Times from t_start: a clock near the int64 limit leaves no room above it.
        self.pixel = take(pixel, first_at)
        self.t, self.h = take(t, first_at) - t_start, take(h, first_at) - t_start
        self.rise = torch.zeros(first_at.shape[0], dtype=torch.int64).index_add_(
            0, run_index(new_knot), c)
        first_of_pixel = changes(self.pixel)
        # Each pixel's level after each of its knots.
        self.level = segmented_cumsum(self.rise, where_true(first_of_pixel),
                                      run_index(first_of_pixel))
        self.t_start, self.span = t_start, int(t.max()) - t_start + 2
        self.key = self.pixel * self.span + self.t
        self.members = torch.from_numpy(region_members(settings))

    def at(self, region: Tensor, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """The sums at ``(region, x)``, ``x`` int64 times: ``(whole, rest, slope)``.

        ``whole`` is the exact integer part, ``rest`` the remainder (float64, 0.0 exactly where
        the sum is an integer), ``slope`` the sum's slope (levels per tick) from ``x`` on.
        """
        x = x - self.t_start
        n = self.key.shape[0]
        whole = torch.zeros(region.shape[0], dtype=torch.int64)
        rest = torch.zeros(region.shape[0], dtype=torch.float64)
        slope = torch.zeros(region.shape[0], dtype=torch.float64)
        for position in range(self.members.shape[1]):  # the region's pixels, not events
            pixel = take(self.members[:, position], region)
            # The pixel's first knot after x (its segment's end) and the one before.
            after = torch.searchsorted(self.key, pixel * self.span + x, right=True)
            ahead = after.clamp(max=n - 1)
            has_next = (after < n) & (take(self.pixel, ahead) == pixel)
            behind = (after - 1).clamp(min=0)
            has_last = (after > 0) & (take(self.pixel, behind) == pixel)
            whole += torch.where(has_last, take(self.level, behind), 0)
            start, end, rise = take(self.h, ahead), take(self.t, ahead), take(self.rise, ahead)
            ramping = has_next & (start <= x) & (rise != 0)
            span = (end - start).clamp(min=1)
            num, den = rise * (x - start), span
            part = torch.div(num, den, rounding_mode="floor")
            whole += torch.where(ramping, part, 0)
            rest += torch.where(ramping, (num - part * den).double() / den.double(), 0.0)
            slope += torch.where(ramping, rise.double() / span.double(), 0.0)
        return whole, rest, slope


def exact_levels(whole: Tensor, rest: Tensor, pixels: Tensor, a: int,
                 b: int) -> tuple[Tensor, Tensor]:
    """``floor(u)`` and ``u is on a level`` from the segments' sums, by the package's rules.

    The package's rule (:func:`~evdown_torch.transforms.functional.reference.level_index`):
    an integer sum is tested exactly, any other is on a level within ``SNAP``. ``pixels``:
    each sum's ``n_r``.
    """
    u = (whole.double() + rest) * b / (pixels * a).double()
    nearest = torch.floor(u + 0.5)
    on = (u - nearest).abs() <= SNAP
    floor_u = torch.where(on, nearest, torch.floor(u)).to(torch.int64)
    integer = rest == 0.0
    exact_floor = torch.div(whole * b, pixels * a, rounding_mode="floor")
    floor_u = torch.where(integer, exact_floor, floor_u)
    on = torch.where(integer, exact_floor * (pixels * a) == whole * b, on)
    return floor_u, on


def design_whole(events: np.ndarray, before: int,
                 settings: Settings | None = None) -> np.ndarray:
    """The design's events earlier than ``before``, the whole stream at once: its eager twin.

    Vectorised torch, no loop over events or regions: each event's ramp (its pixel's previous
    knot from a stable sort by pixel), the slope changes and jumps summed per region and time
    (one sort), the region's slope and value at each breakpoint as integer cumulative sums,
    then the package's reference rule over the moves (each breakpoint's ramp, then its jump,
    :func:`~evdown_torch.transforms.functional.reference.move_crossings`) and the loop's
    rounded crossing times. Integers throughout, so it must give the loop's session's events,
    whatever the chunks.

    Args:
        events: a time-sorted Tonic structured array (``t`` integer microseconds).
        before: the cut (the session's last horizon).
        settings: the design's (the replay's by default).

    Returns:
        The events earlier than ``before``, sorted by ``t`` (stable), of the input's dtype.
    """
    settings = settings or replay_settings()
    width, out_w, a, b = settings.width, settings.out_w, settings.a, settings.b
    one, delay = settings.one, settings.delay
    levels, pixels = torch.from_numpy(settings.levels), torch.from_numpy(settings.pixels)
    x = torch.from_numpy(events["x"].astype(np.int64))
    y = torch.from_numpy(events["y"].astype(np.int64))
    t = torch.from_numpy(events["t"].astype(np.int64))
    c = torch.from_numpy(np.where(events["p"], 1, -1).astype(np.int64))
    t_start = int(t[0])
    pixel, order = torch.sort(y * width + x, stable=True)  # time order inside a pixel
    t, c, x, y = t[order], c[order], x[order], y[order]
    first_of_pixel = changes(pixel)
    new_knot = first_of_pixel | changes(t)
    previous = torch.where(first_of_pixel, t_start, torch.roll(t, 1))  # read at new knots
    t0 = take(take(previous, where_true(new_knot)), run_index(new_knot))
    h = torch.maximum(t0, t - delay)
    length = t - h
    slope = c * torch.where(length > 0, (one + length // 2) // length.clamp(min=1), 0)
    region = (take(torch.from_numpy(settings.row), y) * out_w
              + take(torch.from_numpy(settings.column), x))
    ramp = where_true(length > 0)
    at = torch.cat([take(h, ramp), t])
    where = torch.cat([take(region, ramp), region])
    d_slope = torch.cat([take(slope, ramp), -slope])
    d_jump = torch.cat([torch.zeros_like(ramp), c * one - slope * length])
    # Per (region, time): one breakpoint, its slope change and jump.
    span = int(t.max()) - t_start + 1
    key, by_key = torch.sort(where * span + (at - t_start), stable=True)
    new_point = changes(key)
    point = run_index(new_point)
    n_points = int(point[-1]) + 1
    slope_change = torch.zeros(n_points, dtype=torch.int64).index_add_(0, point, d_slope[by_key])
    jump = torch.zeros(n_points, dtype=torch.int64).index_add_(0, point, d_jump[by_key])
    first_point = where_true(new_point)
    point_t = t_start + take(key, first_point) % span
    point_region = take(key, first_point) // span
    first = changes(point_region)
    starts, run = where_true(first), run_index(first)
    slope_after = segmented_cumsum(slope_change, starts, run)
    slope_before = torch.where(first, 0, torch.roll(slope_after, 1))
    gap = torch.where(first, 0, point_t - torch.roll(point_t, 1))
    value = segmented_cumsum(slope_before * gap + jump, starts, run)  # after the jumps
    value_before_jump = value - jump
    start_value = torch.where(first, 0, torch.roll(value, 1))  # the ramp's start
    # Moves: each point's ramp, then its jump, decided as the loop decides them: in integers
    # unless within their error bound of a level (then on the pixels' segments' values).
    d_active = torch.cat([torch.ones_like(ramp), -(length > 0).to(torch.int64)])
    active = segmented_cumsum(torch.zeros(n_points, dtype=torch.int64).index_add_(
        0, point, d_active[by_key]), starts, run)  # after each point
    active_before = torch.where(first, 0, torch.roll(active, 1))
    move_value = torch.stack([value_before_jump, value], 1).reshape(-1)
    move_first = torch.stack([first, torch.zeros_like(first)], 1).reshape(-1)
    move_active = torch.stack([active_before, active], 1).reshape(-1)
    move_t = torch.repeat_interleave(point_t, 2)
    move_region = torch.repeat_interleave(point_region, 2)
    scaled = b * move_value
    level = take(levels, move_region)
    floor_u = torch.div(scaled, level, rounding_mode="floor")
    off = scaled - floor_u * level
    on_level = off == 0
    near = b * (move_active * delay // 2 + 1) + ((SNAP * level).to(torch.int64) + 2)
    doubt = where_true((move_active > 0) & (torch.minimum(off, level - off) <= near))
    exact = PixelSegments(pixel, t, c, h, t_start, settings)
    whole, rest, _ = exact.at(take(move_region, doubt), take(move_t, doubt))
    exact_floor, exact_on = exact_levels(whole, rest, take(pixels, take(move_region, doubt)),
                                         a, b)
    floor_u.index_copy_(0, doubt, exact_floor)
    on_level.index_copy_(0, doubt, exact_on)
    cross = move_crossings(floor_u, on_level, move_first)
    k, is_jump = cross.move // 2, cross.move % 2 == 1
    sl = take(slope_before, k)
    crossing_region = take(point_region, k)
    num = cross.level * take(levels, crossing_region) - b * take(start_value, k)
    den = b * sl
    # (a flat fixed slope is decided on the segments below: spare <= 0)
    on_ramp = torch.div(2 * num + den, torch.where(is_jump | (den == 0), 1, 2 * den),
                        rounding_mode="floor")
    t_prev = take(torch.where(first, point_t, torch.roll(point_t, 1)), k)
    piece = take(point_t, k) - t_prev
    # A crossing within the integers' error bound of a half tick: on the pixels' segments.
    # (float64 throughout: torch divides integers into its default float32)
    n_active, piece_f = take(active_before, k).double(), piece.double()
    spare = sl.abs().double() - n_active / 2
    half = ((num.double() / torch.where(den == 0, 1, den).double()) % 1.0 - 0.5).abs()
    tolerance = HALF_TOLERANCE + RELATIVE_ERROR * piece_f + 1e-9
    at_end = is_jump | (take(on_level, cross.move) & (cross.level == take(floor_u, cross.move)))
    bound = torch.floor(n_active * delay / 2) + 1  # the loop's E
    near_half = where_true(~at_end & ((spare <= 0) | (half <= bound / spare + tolerance)))
    whole, rest, slope = exact.at(take(crossing_region, near_half), take(t_prev, near_half))
    target = (take(cross.level, near_half) * take(pixels, take(crossing_region, near_half))
              * a).to(torch.float64) / b
    flat = slope == 0.0  # a flat piece: at the move's end, as the loop
    ratio = ((target - whole) - rest) / torch.where(flat, 1.0, slope)
    near_piece = take(piece, near_half)
    on_ramp.index_copy_(0, near_half, torch.where(flat, near_piece, torch.floor(
        ratio + _HALF + RELATIVE_ERROR * near_piece.double()).to(torch.int64)))
    on_ramp = torch.minimum(on_ramp.clamp(min=0), piece)
    out_t = torch.where(at_end, take(point_t, k), t_prev + on_ramp)
    out_region = take(point_region, k)
    keep = where_true(out_t < before)
    out_t, out_region, on = take(out_t, keep), take(out_region, keep), take(cross.on, keep)
    out_t, order = torch.sort(out_t, stable=True)
    result = np.empty(out_t.shape[0], events.dtype)
    region_sorted = take(out_region, order).numpy()
    result["x"], result["y"] = region_sorted % out_w, region_sorted // out_w
    result["t"], result["p"] = out_t.numpy(), take(on, order).numpy()
    return result
