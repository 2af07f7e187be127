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

**One cache per version of the sources.** Numba's disk cache knows a loop is stale only when
the file that defines it changes, not when a function it calls, or a constant it folds in,
changes in another file (Numba's documentation, "Cache limitations"; numba/numba#1833): an
edit to ``knots.py`` alone left the window loop of ``estimation.py`` running the old code
from the cache. So each loop's cache name carries :data:`SOURCES_DIGEST`, a digest of every
module of this package and of each package module they import from: any change to them
compiles every loop again, and the process that first sees a new digest removes the other
digests' files from this package's own ``__pycache__`` (files under ``NUMBA_CACHE_DIR`` stay).
"""

from __future__ import annotations

import contextlib
import hashlib
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numba
from numba.core import types
from numba.extending import intrinsic

__all__ = ["SOURCES_DIGEST", "compiled_loop", "fma", "inlined_helper", "written_name"]

#: This package's directory, and the directory of ``evdown_torch``.
_HERE = Path(__file__).resolve().parent
_ROOT = _HERE.parents[2]

#: ``from evdown_torch... import``, at any indentation: a module the loops may take from.
_IMPORT = re.compile(r"^\s*from (evdown_torch(?:\.\w+)*) import", re.MULTILINE)


def _module_file(module: str) -> Path | None:
    """The source file of a module of ``evdown_torch`` (``None`` where there is none)."""
    path = _ROOT.joinpath(*module.split(".")[1:])
    for candidate in (path.with_suffix(".py"), path / "__init__.py"):
        if candidate.is_file():
            return candidate
    return None


def _sources_digest() -> str:
    """Eight hex digits of the sources of this package's modules and those they import from."""
    files = set(_HERE.glob("*.py"))
    for source in sorted(_HERE.glob("*.py")):
        for module in _IMPORT.findall(source.read_text(encoding="utf-8")):
            found = _module_file(module)
            if found is not None:
                files.add(found)
    digest = hashlib.blake2b(digest_size=4)
    for path in sorted(files):
        digest.update(path.relative_to(_ROOT).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


#: The digest of the loops' sources that every loop's cache name carries (module docstring).
SOURCES_DIGEST = _sources_digest()


def _remove_other_digests() -> None:
    """Remove the cache files of other digests from this package's ``__pycache__``."""
    mark = f"__{SOURCES_DIGEST}-"
    for path in (_HERE / "__pycache__").glob("*.nb[ic]"):
        if mark not in path.name:
            path.unlink(missing_ok=True)  # (another process may have removed it first)


# (OSError: a directory this process may not write, where Numba caches elsewhere.)
with contextlib.suppress(OSError):
    _remove_other_digests()


def _named_for_sources(function: Callable[..., Any]) -> Callable[..., Any]:
    """``function``, its qualified name (the cache files' name) ending in the digest."""
    function.__qualname__ = f"{function.__qualname__}__{SOURCES_DIGEST}"
    return function


def written_name(function: Callable[..., Any]) -> str:
    """A loop's qualified name as its module writes it (without the digest)."""
    return function.__qualname__.removesuffix(f"__{SOURCES_DIGEST}")


def compiled_loop(function: Callable[..., Any]) -> Any:
    """``function`` compiled by Numba: nopython, cached on disk, releasing the GIL.

    The loops take NumPy arrays and numbers only (no Python object inside), and divide by
    positive integers only, so NumPy's error model (no zero-division check) changes nothing.
    Cached under a name of this version of the sources (module docstring).
    """
    return numba.njit(cache=True, nogil=True, error_model="numpy")(_named_for_sources(function))


def inlined_helper(function: Callable[..., Any]) -> Any:
    """``function`` compiled as :func:`compiled_loop` compiles it, and inlined into each caller.

    Numba's ``inline="always"``: a small rule that a hot loop applies at every event (and other
    loops too) keeps its one home without costing a call each time.
    """
    return numba.njit(cache=True, nogil=True, error_model="numpy",
                      inline="always")(_named_for_sources(function))


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
