"""The one module that imports Numba: the decorator every compiled loop takes, and ``fma``.

Imported by the loop modules only, which the kernels import on their first compiled call
(:func:`~evdown_torch.transforms.functional.compiled.use_compiled`).

**Unsigned indices.** Numba lets a signed index count from the end (``a[-1]``), so each read
or write with a signed index it cannot prove non-negative (one read from a column, computed
from table values, or a loop variable that does not start at 0) carries a test and a fix-up.
Where a hot loop's index is non-negative by construction, the loops cast it to ``np.uint64``
(``a[np.uint64(i)]``, ``range(np.uint64(lo), np.uint64(hi))``), which has neither: 10 to 30 %
of EventCount's loop, the estimators' sums and LinearEstimation's ramps and sweep
(docs/benchmarks.md, "Third session of 2026-12-03"). Arithmetic stays in int64: NumPy's rules
make ``uint64`` mixed with ``int64`` a float64, so a cast is taken only where an index is used.

**No array assigned in a hot loop.** An array variable assigned inside a loop (two maps
swapped as windows start) made every read and write of it in that loop about twice as slow:
PoissonSubsampling's loop took 7.2-8.0 ms on a live chunk of 176,000 events, and 4.0-4.4 ms
once the events of each window went to a function of their own that takes the maps as
arguments (docs/benchmarks.md, "Session of 2026-12-04 (night)"). A swap outside the loop
that reads the arrays costs nothing measurable (the merge sort's passes).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numba
from numba.core import types
from numba.extending import intrinsic

__all__ = ["compiled_loop", "fma", "inlined_helper"]


def compiled_loop(function: Callable[..., Any]) -> Any:
    """``function`` compiled by Numba: nopython, cached on disk, releasing the GIL.

    The loops take NumPy arrays and numbers only (no Python object inside), and divide by
    positive integers only, so NumPy's error model (no zero-division check) changes nothing.
    """
    return numba.njit(cache=True, nogil=True, error_model="numpy")(function)


def inlined_helper(function: Callable[..., Any]) -> Any:
    """``function`` compiled as :func:`compiled_loop` compiles it, and inlined into each caller.

    Numba's ``inline="always"``: a small rule that a hot loop applies at every event (and other
    loops too) keeps its one home without costing a call each time.
    """
    return numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")(function)


@intrinsic
def _fma(typingctx: Any, a: Any, b: Any, c: Any) -> Any:  # pragma: no cover - compiled
    """``a * b + c`` rounded once (LLVM's ``fma``), for float64, inside a compiled loop.

    What ``torch.addcmul(c, a, b)`` computes where torch's CPU kernels fuse it (see
    :func:`~.cubic.addcmul_is_fused`); Numba itself never fuses ``a * b + c``.
    """
    signature = types.float64(types.float64, types.float64, types.float64)

    def codegen(context: Any, builder: Any, sig: Any, args: Any) -> Any:
        return builder.fma(*args)

    return signature, codegen


#: ``fma(a, b, c)``: ``a * b + c`` rounded once, callable inside a compiled loop only.
fma: Any = _fma
