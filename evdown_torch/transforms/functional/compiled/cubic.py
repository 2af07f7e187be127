"""CubicEstimation's compiled region solver: PCHIP slopes, the region's cubic pieces, roots.

One region at a time, what :mod:`~..estimation.cubic` computes over a chunk of regions, with
the same floats in the same order: :func:`pchip_slopes` (SciPy's rules), :func:`region_sums`
(the pixels strictly inside a segment, evaluated at every breakpoint inside it and added in
pixel order, then each knot's slope added at its breakpoint), :func:`monotone_moves` (each
piece's Hermite coefficients, the roots of its derivative, the moves between them) and
:func:`solve` (safeguarded Newton on a monotone move).

The eager solver evaluates its cubics with ``torch.addcmul``, which torch's CPU kernels
compute as one fused multiply-add (``fma``) where the CPU has one and as a product and a sum
elsewhere; :func:`addcmul_is_fused` asks this torch once, and the loops do the same
(``fused``). Where torch does neither exactly (:func:`addcmul_is_fused` is ``None``), the
cubic method keeps its eager path.
"""

from __future__ import annotations

import functools
import math

import numpy as np
import torch

from evdown_torch.transforms.functional.compiled._numba import compiled_loop, fma
from evdown_torch.transforms.functional.estimation.cubic import DOUBLE_ROOT, EDGE, MAX_ITERATIONS

__all__ = ["addcmul_is_fused", "monotone_moves", "pchip_slopes", "region_sums", "solve"]

#: ``1 - EDGE`` as the eager solver's Python expression computes it.
_HIGH_EDGE = 1 - EDGE


@compiled_loop
def _madd(a: float, b: float, c: float, fused: bool) -> float:  # pragma: no cover - compiled
    """``a * b + c`` as ``torch.addcmul(c, a, b)`` computes it here: one rounding or two."""
    if fused:
        return fma(a, b, c)
    return c + a * b


@compiled_loop
def _madd_all(a: np.ndarray, b: np.ndarray, c: np.ndarray,
              fused: bool) -> np.ndarray:  # pragma: no cover - compiled
    """:func:`_madd` of each value (the probe's)."""
    out = np.empty_like(a)
    for i in range(a.shape[0]):
        out[i] = _madd(a[i], b[i], c[i], fused)
    return out


@functools.cache
def addcmul_is_fused() -> bool | None:
    """How this torch's ``addcmul`` rounds on float64 CPU tensors: once, twice, or neither.

    ``True``: once (a fused multiply-add); ``False``: twice; ``None``: neither on every value
    of the probe (the cubic loop is then not used).

    ``torch.addcmul(c, a, b, value=v)`` is compared with ``fma(v * a, b, c)`` and with
    ``c + (v * a) * b`` on 4,099 random values (a vector's body and its tail).
    """
    generator = np.random.default_rng(20261202)
    a, b, c = (generator.standard_normal(4099) for _ in range(3))
    for value in (1.0, -3.0):
        got = torch.addcmul(*(torch.from_numpy(v) for v in (c, a, b)), value=value).numpy()
        fused = np.array_equal(got, _madd_all(value * a, b, c, True))
        if not fused and not np.array_equal(got, _madd_all(value * a, b, c, False)):
            return None
        if value == 1.0:
            answer = fused
        elif fused != answer:
            return None
    return answer


@compiled_loop
def _edge_slope(h0: float, h1: float, m0: float, m1: float) -> float:  # pragma: no cover
    """SciPy's one-sided three-point end slope (``estimation.cubic._edge_slope``)."""
    d = ((2.0 * h0 + h1) * m0 - h0 * m1) / (h0 + h1)
    if np.sign(d) != np.sign(m0):
        return 0.0
    if np.sign(m0) != np.sign(m1) and abs(d) > 3.0 * abs(m0):
        return 3.0 * m0
    return d


@compiled_loop
def pchip_slopes(
    k_t: np.ndarray, k_level: np.ndarray, k_first: np.ndarray, nk: int, front_at_rest: bool,
    slope: np.ndarray, width: np.ndarray, rise: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """Each knot's PCHIP slope, and its segment's width and rise (1 and 0 after a pixel's last)."""
    for k in range(nk):
        if k + 1 < nk and not k_first[k + 1]:
            width[k] = float(k_t[k + 1] - k_t[k])
            rise[k] = float(k_level[k + 1] - k_level[k])
        else:
            width[k], rise[k] = 1.0, 0.0
    for k in range(nk):
        m_next = rise[k] / width[k]
        w_prev, m_prev = (width[k - 1], rise[k - 1] / width[k - 1]) if k else (1.0, 0.0)
        if m_next * m_prev <= 0:
            slope[k] = 0.0
        else:
            w1 = w_prev + 2.0 * width[k]
            w2 = width[k] + 2.0 * w_prev
            slope[k] = (w1 + w2) / (w1 / m_prev + w2 / m_next)
    first = 0
    while first < nk:
        last = first
        while last + 1 < nk and not k_first[last + 1]:
            last += 1
        if last == first:  # one knot: a constant
            slope[first] = 0.0
        elif last == first + 1:  # two knots: a line
            slope[first] = 0.0 if front_at_rest else rise[first] / width[first]
            slope[last] = rise[first] / width[first]
        else:
            slope[first] = 0.0 if front_at_rest else _edge_slope(
                width[first], width[first + 1], rise[first] / width[first],
                rise[first + 1] / width[first + 1])
            slope[last] = _edge_slope(width[last - 1], width[last - 2],
                                      rise[last - 1] / width[last - 1],
                                      rise[last - 2] / width[last - 2])
        first = last + 1


@compiled_loop
def region_sums(
    k_t: np.ndarray, k_bp: np.ndarray, k_first: np.ndarray, nk: int, slope: np.ndarray,
    width: np.ndarray, rise: np.ndarray, bp_t: np.ndarray, nbp: int, integer_time: bool,
    origin: int, fused: bool, part: np.ndarray, derivative: np.ndarray,
) -> None:  # pragma: no cover - compiled
    """``part`` and ``derivative`` of ``n_r * M_r`` at each breakpoint (``_mid_segment_sums``).

    The pixels strictly inside a segment, evaluated in the segment's normalised time (integer
    times relative to ``origin``, the eager chunk's first knot time) and added in pixel order;
    then each knot's slope added to the derivative at its breakpoint.
    """
    part[:nbp] = 0.0
    derivative[:nbp] = 0.0
    for k in range(nk):
        last = k + 1 >= nk or k_first[k + 1]
        if last or k_bp[k + 1] - k_bp[k] <= 1:
            continue
        c1 = width[k] * slope[k]
        c2_end = slope[k + 1] * width[k]
        if c1 == 0 and c2_end == 0 and rise[k] == 0:
            continue
        c2 = (rise[k] * 3.0 - 2.0 * c1) - c2_end
        c3 = (c1 + c2_end) - 2.0 * rise[k]
        inv_w = 1.0 / width[k]
        start = float(k_t[k] - origin) if integer_time else float(k_t[k])
        # (An unsigned index: ``_numba``, "Unsigned indices".)
        for j in range(np.uint64(k_bp[k] + 1), np.uint64(k_bp[k + 1])):
            at = float(bp_t[j] - origin) if integer_time else float(bp_t[j])
            s = (at - start) * inv_w
            u = _madd(s, c3, c2, fused)
            part[j] += _madd(s, u, c1, fused) * s
            derivative[j] += _madd(s, c3 * s + 2.0 * u, c1, fused) * inv_w
    for k in range(nk):
        derivative[k_bp[k]] += slope[k]


@compiled_loop
def monotone_moves(
    bp_t: np.ndarray, nbp: int, whole: np.ndarray, part: np.ndarray, derivative: np.ndarray,
    fused: bool, c1: np.ndarray, c2: np.ndarray, c3: np.ndarray, move_bp: np.ndarray,
    move_s: np.ndarray, move_whole: np.ndarray, move_part: np.ndarray,
) -> int:  # pragma: no cover - compiled
    """Each piece's coefficients and its monotone moves (interior extrema, then its end).

    Returns the number of moves; move ``e`` ends at normalised time ``move_s[e]`` of the piece
    ending at breakpoint ``move_bp[e]``, where ``n_r * M_r`` is ``move_whole + move_part``.
    """
    moves = 0
    for j in range(nbp):
        prev = j - 1 if j else j
        if j == 0:
            c1[j], c2[j], c3[j] = 0.0, 0.0, 0.0
        else:
            gap = float(bp_t[j] - bp_t[prev])
            change = float(whole[j] - whole[prev]) + (part[j] - part[prev])
            m0, m1 = derivative[prev] * gap, derivative[j] * gap
            c1[j] = m0
            c2[j] = (change * 3.0 - 2.0 * m0) - m1
            c3[j] = (m0 + m1) - 2.0 * change
        low, high = _derivative_roots(c1[j], c2[j], c3[j], fused)
        for root in (low, high):
            if not np.isnan(root):
                value = _madd(root, _madd(root, c3[j], c2[j], fused), c1[j], fused) * root
                move_bp[moves], move_s[moves] = j, root
                move_whole[moves], move_part[moves] = whole[prev], value + part[prev]
                moves += 1
        move_bp[moves], move_s[moves] = j, 1.0
        move_whole[moves], move_part[moves] = whole[j], part[j]
        moves += 1
    return moves


@compiled_loop
def _derivative_roots(c1: float, c2: float, c3: float,
                      fused: bool) -> tuple[float, float]:  # pragma: no cover - compiled
    """The derivative's sign changes inside ``(EDGE, 1 - EDGE)``, ascending (NaN: none)."""
    square = c2 * c2
    disc = _madd(-3.0 * c1, c3, square, fused)
    q = -(math.copysign(np.sqrt(disc), c2) + c2)
    noise = abs(_madd(3.0 * c1, c3, square, fused)) * DOUBLE_ROOT
    if disc <= noise:
        q = np.nan
    r1 = q / (c3 * 3.0)
    r2 = c1 / q
    if not (r1 > EDGE and r1 < _HIGH_EDGE):
        r1 = np.nan
    if not (r2 > EDGE and r2 < _HIGH_EDGE):
        r2 = np.nan
    low, high = np.fmin(r1, r2), np.fmax(r1, r2)
    if not high > low:
        high = np.nan
    return low, high


@compiled_loop
def _poly(s: float, c1: float, c2: float, c3: float) -> float:  # pragma: no cover - compiled
    return s * (c1 + s * (c2 + s * c3))


@compiled_loop
def solve(c1: float, c2: float, c3: float, goal: float, low: float, high: float,
          rising: bool) -> float:  # pragma: no cover - compiled
    """The root of ``s (c1 + s (c2 + s c3)) = goal`` in ``[low, high]`` (``cubic._solve``)."""
    sign = 1.0 if rising else -1.0
    at_low, at_high = _poly(low, c1, c2, c3), _poly(high, c1, c2, c3)
    x = low + (goal - at_low) / (at_high - at_low) * (high - low)
    x = min(max(x, 0.0), 1.0) if np.isfinite(x) else 0.5 * (low + high)
    x = min(max(x, low), high)
    for _ in range(MAX_ITERATIONS):
        g = sign * (_poly(x, c1, c2, c3) - goal)
        if g < 0:
            low = x
        if g > 0:
            high = x
        newton = x - g / (sign * (c1 + x * (2.0 * c2 + 3.0 * c3 * x)))
        if g == 0:
            update = x
        elif newton > low and newton < high:
            update = newton
        else:
            update = 0.5 * (low + high)
        moving = abs(update - x) > 1e-15
        x = update
        if not moving:
            break
    return x
