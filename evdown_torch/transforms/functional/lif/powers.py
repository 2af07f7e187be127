"""The leak's powers ``beta ** g``: a function of ``beta`` and ``g`` alone, wherever ``g`` lies.

Used by :mod:`evdown_torch.transforms.functional.lif.rounds` (the decay over a gap) and
:mod:`evdown_torch.transforms.functional.lif.chains` (firing chains). torch's ``pow`` is no
such function: on the CPU its vectorised loop (SLEEF) and its scalar tail (the C library)
round some float32 and float64 powers one unit apart, and the split between them depends on
the tensor's length and the CPU, so a cell's decay, and then a spike, would depend on
unrelated cells of the call.

Here ``beta ** g`` (``g`` a whole number of steps, ``0 <= g < 2 ** 63``) is built from powers
precomputed once per ``beta`` in 256-bit binary arithmetic (Python integers): ``beta ** l`` for
every ``l < 2 ** LOW_BITS`` and ``beta ** (2 ** k)`` for ``k >= LOW_BITS``. The power of ``g``
is the first at ``g``'s low bits times the second at each of its higher set bits, in
ascending ``k``, in double-double arithmetic (pairs of float64 whose sum carries about 106
bits): only IEEE products and sums, each correctly rounded, so the same bits come out for an
element wherever it lies, on any CPU. The double-double product is within ``2 ** -97``
relative of ``beta ** g``; it is rounded once, to float64 (the chains' closed forms) or to
float32 (the decays; through round-to-odd float64, so without double rounding). Both are
therefore the correctly rounded power (and so non-increasing in ``g``) except where
``beta ** g`` lies within ``2 ** -97`` relative of a rounding boundary; the tests compare them
with the exact power on exponents up to ``2 ** 63 - 1``.
"""

from __future__ import annotations

import functools
from fractions import Fraction

import torch
from torch import Tensor

__all__ = ["LOW_BITS", "Powers", "powers_of"]

#: Exponents below ``2 ** LOW_BITS`` read their power from one table (a gather).
LOW_BITS = 10

#: Bits of the precomputed powers: 1023 products, or 62 squarings, keep far more than the 106
#: bits of a double-double.
_BITS = 256
_SPLIT = 134217729.0  # 2 ** 27 + 1: Dekker's split of a float64 into two 26-bit halves


class Powers:
    """``beta ** g`` for one ``beta`` in ``[0, 1]`` (module docstring), on one device.

    Args:
        beta: the decay per step (the float32 ``beta`` of the neurons, as a float).
        device: where the exponents lie.
    """

    def __init__(self, beta: float, device: torch.device) -> None:
        if not 0.0 <= beta <= 1.0:
            raise ValueError(f"beta must lie in [0, 1], got {beta}")
        self.beta = beta
        low_hi, low_lo, self._high = _binary_powers(beta)
        self._low_hi = torch.tensor(low_hi, dtype=torch.float64, device=device)
        self._low_lo = torch.tensor(low_lo, dtype=torch.float64, device=device)
        self._low32 = _to_float32(self._low_hi, self._low_lo)

    @property
    def small_float32(self) -> Tensor:
        """``(2 ** LOW_BITS,)`` float32 ``beta ** l`` for every ``l < 2 ** LOW_BITS``.

        What :meth:`float32` reads for such exponents (shared: never write to it).
        """
        return self._low32

    def float32(self, exponent: Tensor) -> Tensor:
        """``beta ** exponent`` rounded once to float32.

        Args:
            exponent: int64 tensor of whole numbers of steps, ``0 <= exponent < 2 ** 63``.

        Returns:
            float32 tensor of ``exponent``'s shape.
        """
        low = exponent.bitwise_and(_LOW_MASK)
        power = self._low32[low]
        big, hi, lo = self._high_part(exponent, low)
        if big is not None:
            power.view(-1)[big] = _to_float32(hi, lo)
        return power

    def float64(self, exponent: Tensor) -> Tensor:
        """``beta ** exponent`` rounded once to float64.

        Args:
            exponent: int64 tensor of whole numbers (or a float64 tensor of exact whole
                numbers), ``0 <= exponent < 2 ** 63``.

        Returns:
            float64 tensor of ``exponent``'s shape.
        """
        exponent = exponent.to(torch.int64)
        low = exponent.bitwise_and(_LOW_MASK)
        power = self._low_hi[low]
        big, hi, _ = self._high_part(exponent, low)
        if big is not None:
            power.view(-1)[big] = hi  # normalised: hi is hi + lo rounded to float64
        return power

    def _high_part(
        self, exponent: Tensor, low: Tensor
    ) -> tuple[Tensor | None, Tensor, Tensor]:
        """The flat positions of exponents of ``2 ** LOW_BITS`` or more, and their powers."""
        flat = exponent.reshape(-1)
        big = (flat >> LOW_BITS).nonzero().squeeze(1)
        if big.numel() == 0:
            return None, flat, flat
        high = flat[big] >> LOW_BITS
        low = low.reshape(-1)[big]
        hi, lo = self._low_hi[low], self._low_lo[low]
        for k in range(int(high.max()).bit_length()):
            factor_hi, factor_lo = self._high[k]
            new_hi, new_lo = _times(hi, lo, factor_hi, factor_lo)
            has_bit = high.bitwise_right_shift(k).bitwise_and_(1).bool()
            hi = torch.where(has_bit, new_hi, hi)
            lo = torch.where(has_bit, new_lo, lo)
        return big, hi, lo


_LOW_MASK = (1 << LOW_BITS) - 1


@functools.lru_cache(maxsize=16)
def powers_of(beta: float, device: torch.device) -> Powers:
    """The powers of ``beta`` on ``device``, built once per pair (tables of 1024 floats)."""
    return Powers(beta, device)


def _binary_powers(
    beta: float,
) -> tuple[list[float], list[float], list[tuple[float, float]]]:
    """``beta ** l`` (``l < 2 ** LOW_BITS``) and ``beta ** 2 ** k`` (``k >= LOW_BITS``).

    As double-double pairs, from products of :data:`_BITS`-bit binary numbers (Python
    integers): exact wherever the power fits in them (a power of two ``beta``, say).
    """
    mantissa, exponent = float(beta).as_integer_ratio()
    b = (mantissa, -(exponent.bit_length() - 1))  # beta = mantissa * 2 ** -log2(exponent)
    low = [(1, 0)]
    for _ in range(1, 1 << LOW_BITS):
        low.append(_multiply(low[-1], b))
    high = []
    square = _multiply(low[-1], b)  # beta ** 2 ** LOW_BITS
    for _ in range(LOW_BITS, 63):
        high.append(square)
        square = _multiply(square, square)
    low_pairs = [_double_double(x) for x in low]
    return [p[0] for p in low_pairs], [p[1] for p in low_pairs], [
        _double_double(x) for x in high]


def _multiply(a: tuple[int, int], b: tuple[int, int]) -> tuple[int, int]:
    """``a * b`` of binary numbers ``(m, e)`` (``m * 2 ** e``), ``m`` rounded to _BITS bits."""
    m, e = a[0] * b[0], a[1] + b[1]
    extra = m.bit_length() - _BITS
    if extra > 0:
        m, e = (m + (1 << (extra - 1))) >> extra, e + extra
    return m, e


def _double_double(x: tuple[int, int]) -> tuple[float, float]:
    """``m * 2 ** e`` as ``hi + lo``: ``hi`` the float64 nearest it, ``lo`` the rest rounded."""
    m, e = x
    if m == 0 or m.bit_length() + e < -1100:  # below every float64: 0
        return 0.0, 0.0
    exact = Fraction(m) * Fraction(2) ** e
    hi = float(exact)  # correctly rounded
    return hi, float(exact - Fraction(hi))


def _times(hi: Tensor, lo: Tensor, b_hi: float, b_lo: float) -> tuple[Tensor, Tensor]:
    """Double-double ``(hi + lo) * (b_hi + b_lo)``, normalised (Dekker's product)."""
    product = hi * b_hi
    a_big = hi * _SPLIT
    a_big = a_big - (a_big - hi)
    a_small = hi - a_big
    b_big = b_hi * _SPLIT
    b_big = b_big - (b_big - b_hi)
    b_small = b_hi - b_big
    error = (a_big * b_big - product) + a_big * b_small + a_small * b_big + a_small * b_small
    error = error + (hi * b_lo + lo * b_hi)
    total = product + error
    return total, error - (total - product)


def _to_float32(hi: Tensor, lo: Tensor) -> Tensor:
    """``hi + lo`` (normalised, non-negative) rounded once to float32.

    Round to odd in float64 first (``hi``, moved one unit towards ``lo`` where ``lo`` is not
    zero and ``hi``'s last bit is even), then to nearest in float32: 53 bits are at least two
    more than 24, so the two roundings give the correctly rounded ``hi + lo``.
    """
    bits = hi.view(torch.int64)  # positive floats: the next one up is the next integer
    inexact = (lo != 0) & (hi > 0) & (bits.bitwise_and(1) == 0)
    toward = torch.where(lo > 0, 1, -1)
    odd = torch.where(inexact, bits + toward, bits).view(torch.float64)
    return odd.to(torch.float32)

