"""Torch's thread count, set for a while and put back: no call changes it behind a user's back.

Every kernel here is vectorised torch code; on the small tensors of one recording, torch's
intra-op threads cost more in hand-over than they save, and on a busy machine they wait for
cores (``docs/benchmarks.md``, "Threads"). The command line and the dataset preprocessing
therefore run one thread per process by default; library calls leave the caller's setting
alone, except inside :func:`torch_threads`.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch

from evdown_torch.checks import check_positive_int

__all__ = ["torch_threads"]


@contextmanager
def torch_threads(threads: int) -> Iterator[None]:
    """Run the ``with`` block with ``torch.set_num_threads(threads)``, then restore the count.

    Raises:
        ValueError: unless ``threads`` is a positive integer.

    Example:
        >>> import torch
        >>> before = torch.get_num_threads()
        >>> with torch_threads(1):
        ...     torch.get_num_threads()
        1
        >>> torch.get_num_threads() == before
        True
    """
    threads = check_positive_int("threads", threads)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        yield
    finally:
        torch.set_num_threads(before)
