"""The one module that imports Numba: the decorator every compiled loop takes.

Imported by the loop modules only, which the kernels import on their first compiled call
(:func:`~evdown_torch.transforms.functional.compiled.use_compiled`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numba

__all__ = ["compiled_loop"]


def compiled_loop(function: Callable[..., Any]) -> Any:
    """``function`` compiled by Numba: nopython, cached on disk, releasing the GIL.

    The loops take NumPy arrays and numbers only (no Python object inside), and divide by
    positive integers only, so NumPy's error model (no zero-division check) changes nothing.
    """
    return numba.njit(cache=True, nogil=True, error_model="numpy")(function)
