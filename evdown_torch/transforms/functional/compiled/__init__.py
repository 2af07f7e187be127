"""Compiled CPU kernels (Numba) and the one switch between them and the eager torch kernels.

On the CPU a per-event loop compiled by Numba runs several times faster than vectorised
eager torch for the causal methods, whose outputs follow from each event in turn. The
kernels in ``transforms/functional/`` take such a loop when their input is on the CPU and
this switch allows it; every other device, and the CPU when it does not, takes the eager
kernel. Both paths give the same events (tested event for event) and take and return the
same state, so a stream may move from one to the other between chunks.

The loops live in this package's modules (one per family) and import Numba; nothing here
does until a kernel first needs a loop, so ``import evdown_torch`` costs no Numba import and
no compilation. Each loop is compiled on its first call (nopython mode) and cached on disk
(``cache=True``: next to the module, or under ``NUMBA_CACHE_DIR``), so later processes load it.

The switch:

* Numba absent: eager kernels everywhere (Numba is an optional dependency: the ``compiled``
  extra, which ``all`` includes).
* ``EVDOWN_EAGER=1`` in the environment: eager kernels by default in this process.
* ``with evdown_torch.eager_kernels():`` forces the eager kernels inside the block (this
  thread or asyncio task only, as :func:`~evdown_torch.max_output_events`);
  ``eager_kernels(False)`` allows the compiled ones again inside it, ``EVDOWN_EAGER``
  notwithstanding.

:func:`kernel_path` says which path a call would take.
"""

from __future__ import annotations

import functools
import os
import warnings
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from contextvars import ContextVar
from typing import Literal

import torch
from torch import Tensor

__all__ = [
    "EAGER_VARIABLE",
    "eager_kernels",
    "kernel_path",
    "numba_available",
    "use_compiled",
]

#: The environment variable that makes the eager kernels the default (``1``; ``0`` or unset:
#: compiled kernels on the CPU where Numba is installed).
EAGER_VARIABLE = "EVDOWN_EAGER"

_TRUE = ("1", "true", "yes", "on")
_FALSE = ("", "0", "false", "no", "off")

#: ``True``: eager kernels forced in this thread (or asyncio task); ``False``: compiled kernels
#: allowed; ``None``: as the environment says.
_EAGER: ContextVar[bool | None] = ContextVar("evdown_torch_eager_kernels", default=None)


def eager_kernels(eager: bool = True) -> AbstractContextManager[bool]:
    """A block in which the kernels take their eager torch path (or, with ``False``, not).

    The compiled CPU kernels and the eager ones give the same events; this block is for
    cross-checks, for timing the two, and for a machine where a compiled kernel must not run.
    The setting lives in a context variable, as :func:`~evdown_torch.max_output_events`: it
    holds for the calls made inside the ``with`` block, in this thread (or asyncio task)
    only, and the previous setting comes back when the block ends, however it ends. Blocks
    nest; ``eager_kernels(False)`` inside allows the compiled kernels again, even under
    ``EVDOWN_EAGER=1``. The object is also a decorator.

    Args:
        eager: ``True`` to force the eager kernels, ``False`` to allow the compiled ones.

    Returns:
        A context manager; ``with eager_kernels() as eager:`` binds ``eager``.

    Raises:
        TypeError: for an ``eager`` that is not a bool.

    Example:
        >>> with eager_kernels():
        ...     kernel_path("cpu")
        'eager'
    """
    if not isinstance(eager, bool):
        raise TypeError(f"eager must be True or False, got {eager!r}")
    return _eager_block(eager)


@contextmanager
def _eager_block(eager: bool) -> Iterator[bool]:
    token = _EAGER.set(eager)
    try:
        yield eager
    finally:
        _EAGER.reset(token)


def _eager_forced() -> bool:
    """Whether the eager kernels are forced here: by a block, else by the environment."""
    eager = _EAGER.get()
    if eager is not None:
        return eager
    value = os.environ.get(EAGER_VARIABLE, "").strip().lower()
    if value in _FALSE:
        return False
    if value in _TRUE:
        return True
    raise ValueError(
        f"{EAGER_VARIABLE} must be 1 (eager kernels only) or 0 (compiled kernels on the CPU), "
        f"got {os.environ[EAGER_VARIABLE]!r}"
    )


@functools.cache
def numba_available() -> bool:
    """Whether Numba can be imported here (imported once, on the first question).

    A Numba that is installed but fails to import (e.g. a NumPy newer than it supports) is
    reported by a ``RuntimeWarning``, and the eager kernels run.
    """
    try:
        import numba  # noqa: F401
    except ModuleNotFoundError as error:
        if error.name != "numba":
            _warn_broken(error)
        return False
    except ImportError as error:
        _warn_broken(error)
        return False
    return True


def _warn_broken(error: ImportError) -> None:
    warnings.warn(
        f"numba is installed but cannot be imported ({error}); the eager kernels run instead",
        RuntimeWarning,
        stacklevel=3,
    )


def use_compiled(tensor: Tensor) -> bool:
    """Whether a kernel given ``tensor`` (one of its input's columns) takes its compiled loop.

    True on the CPU where Numba is installed and the eager kernels are not forced.
    """
    return _compiled_on(tensor.device.type)


def kernel_path(device: torch.device | str = "cpu") -> Literal["compiled", "eager"]:
    """The path a kernel on ``device`` takes here: ``"compiled"`` or ``"eager"``.

    ``"compiled"`` on the CPU where Numba is installed and neither ``EVDOWN_EAGER=1`` nor an
    :func:`eager_kernels` block forces the eager kernels; ``"eager"`` elsewhere (every other
    device). Methods without a compiled loop run eagerly everywhere.

    Raises:
        ValueError: for an ``EVDOWN_EAGER`` value other than 1/0 (true/false, yes/no, on/off).

    Example:
        >>> kernel_path("meta")
        'eager'
    """
    return "compiled" if _compiled_on(torch.device(device).type) else "eager"


def _compiled_on(device_type: str) -> bool:
    return device_type == "cpu" and not _eager_forced() and numba_available()
