"""Many recordings through one kernel call: stacking them on one virtual sensor and back.

A batch of ``B`` recordings becomes one stream on which no region mixes recordings and no
kernel needs a loop over them (``docs/semantics.md``: each recording's output equals the
output of processing it alone):

* **Space.** Recording ``b``'s pixel ``(x, y)`` becomes ``(x, y + b * Ho * fy)``: the
  recordings are stacked vertically, each padded to a whole number of region rows, so
  recording ``b`` owns the block of region ids ``[b * Ho * Wo, (b + 1) * Ho * Wo)``.
  :func:`~evdown_torch._regions.region_pixel_count` gives those regions the ``n_r`` of their
  own recording's regions.
* **Time.** With integer timestamps each recording is shifted (exactly, in int64) into its own
  window ``[base_b, base_b + span_b]``, the windows one after the other. A batch of recordings
  that are each in time order is then one stream in time order, which the kernels take without
  sorting, and their output comes back grouped by recording. Float timestamps are not shifted
  (a shift would round them): the kernels then sort the whole batch by ``t``, which keeps each
  recording's own order, and the output is grouped by a stable sort on the recording.
* **Bounds.** Methods that depend on a stream's ``t_start``/``t_end`` (the estimators' front
  and back knots) get each recording's own bounds (:attr:`Stacked.starts`, :attr:`Stacked.ends`).

Every method is invariant under shifting the clock (exactly for integer ``t``) and treats
regions independently, so each recording's output is the one it gets alone.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import torch
from torch import Tensor

from evdown_torch._tensors import divide, runs_of, stable_sort_small, take, where_true
from evdown_torch.checks import output_size
from evdown_torch.collate import EventBatch
from evdown_torch.events import Events

__all__ = ["Stacked", "recording_index", "run_stacked", "sorted_within", "stack", "unstack"]

#: Largest total of the shifted time windows: int64 arithmetic on shifted times stays exact.
MAX_SHIFTED_SPAN = 1 << 62


class Stacked(NamedTuple):
    """A batch of recordings as one stream on a virtual sensor (see the module's docstring).

    Attributes:
        events: ``N`` events in virtual coordinates (and shifted time when :attr:`shift` is
            not ``None``), recording after recording.
        recordings: ``B``, the number of recordings.
        starts: ``(B,)`` each recording's first timestamp, in the events' clock (0 when empty).
        ends: ``(B,)`` each recording's last timestamp, in the events' clock (0 when empty).
        shift: ``(B,)`` int64 added to each recording's timestamps, or ``None`` (float ``t``).
        out_height: ``Ho``, the output height of one recording.
    """

    events: Events
    recordings: int
    starts: Tensor
    ends: Tensor
    shift: Tensor | None
    out_height: int


def recording_index(lengths: tuple[int, ...], device: torch.device) -> Tensor:
    """``(N,)`` int64 recording of each event of recordings of ``lengths`` concatenated."""
    return runs_of(torch.tensor(lengths, dtype=torch.int64, device=device), sum(lengths))


def sorted_within(t: Tensor, lengths: tuple[int, ...]) -> bool:
    """Whether each recording of ``t`` (recordings of ``lengths`` concatenated) is in time order.

    Example:
        >>> sorted_within(torch.tensor([5, 9, 1, 2]), (2, 2))
        True
        >>> sorted_within(torch.tensor([5, 1]), (2,))
        False
    """
    if t.shape[0] < 2:
        return True
    ordered = t[1:] >= t[:-1]
    starts = torch.tensor(lengths[:-1], dtype=torch.int64).cumsum(0)
    starts = starts[(starts > 0) & (starts < t.shape[0])].to(t.device)
    ordered.index_fill_(0, starts - 1, True)  # a recording may start before the last ended
    return bool(ordered.all())


def stack(
    events: Events,
    lengths: tuple[int, ...],
    *,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
) -> Stacked:
    """Place concatenated recordings on one virtual sensor and, for integer ``t``, clock.

    Args:
        events: the recordings' events concatenated, recording 0 first (each recording in
            any order, coordinates inside ``sensor_size``).
        lengths: number of events of each recording, ``sum(lengths) == N``.
        sensor_size: one recording's ``(W, H, P)``.
        factor: ``(fx, fy)``.

    Returns:
        The :class:`Stacked` batch.

    Example:
        >>> ev = Events.from_columns([1, 0, 3], [1, 0, 3], [500, 7, 9], [1, 1, 0])
        >>> s = stack(ev, (1, 2), sensor_size=(4, 4, 2), factor=(2, 2))
        >>> s.events.y.tolist(), s.events.t.tolist(), s.starts.tolist(), s.ends.tolist()
        ([1, 4, 7], [0, 1, 3], [0, 1], [0, 3])
    """
    device = events.device
    b = len(lengths)
    out_h = output_size(sensor_size, factor)[1]
    recording = recording_index(lengths, device)
    y = recording * (out_h * factor[1])
    y += events.y
    t = events.t
    counts = torch.tensor(lengths, dtype=torch.int64)
    present = where_true(counts > 0)
    last = (counts.cumsum(0) - 1)[present].to(device)
    first = last - (counts[present].to(device) - 1)
    present = present.to(device)
    starts = torch.zeros(b, dtype=t.dtype, device=device)
    ends = torch.zeros(b, dtype=t.dtype, device=device)
    if sorted_within(t, lengths):
        starts[present] = take(t, first)
        ends[present] = take(t, last)
    else:
        starts.scatter_reduce_(0, recording, t, "amin", include_self=False)
        ends.scatter_reduce_(0, recording, t, "amax", include_self=False)
    shift = None
    if not t.is_floating_point() and b > 1:
        spans = ends - starts  # negative where a span of 2**63 or more wrapped
        if int(spans.min()) >= 0 and int(spans.max()) < MAX_SHIFTED_SPAN // b:  # fits in int64
            base = torch.cumsum(spans + 1, 0) - (spans + 1)
            shift = base - starts
            t = t + take(shift, recording)
            starts, ends = base, base + spans
    stacked = Events(events.x, y, t, events.p)
    return Stacked(stacked, b, starts, ends, shift, out_h)


def unstack(out: Events, stacked: Stacked) -> tuple[Events, tuple[int, ...]]:
    """Map a kernel's output on the virtual sensor back to each recording.

    Args:
        out: the kernel's output for :attr:`Stacked.events`, sorted by ``t``; with a shifted
            clock, each recording's output lies in its window ``[starts, ends]``. Its ``y``
            and (shifted) ``t`` are rewritten in place: they must be new tensors (or the
            stacked ones), never the caller's.
        stacked: the :class:`Stacked` batch it came from.

    Returns:
        ``(events, lengths)``: the outputs of the recordings concatenated, recording 0 first,
        each sorted by ``t`` in its own coordinates and clock, and their lengths.
    """
    b = stacked.recordings
    if stacked.shift is None:
        recording = divide(out.y, stacked.out_height)
        recording, order = stable_sort_small(recording, b)
        out = out.select(order)
        counts = tuple(torch.bincount(recording, minlength=b).tolist())
        t = out.t
    else:  # sorted by t: the recordings' windows follow each other
        edges = torch.searchsorted(out.t, stacked.starts).tolist() + [out.num_events]
        counts = tuple(hi - lo for lo, hi in zip(edges[:-1], edges[1:]))
        recording = recording_index(counts, out.device)
        t = out.t.sub_(take(stacked.shift, recording))  # the kernel's own new tensors
    y = out.y.sub_(recording, alpha=stacked.out_height)
    return Events(out.x, y, t, out.p), counts


def run_stacked(
    batch: EventBatch,
    kernel: Callable[[Stacked], Events],
    *,
    sensor_size: tuple[int, int, int],
    factor: tuple[int, int],
) -> EventBatch:
    """Stack a batch, run ``kernel`` on it once, and give each recording its output back."""
    stacked = stack(batch.events, batch.lengths, sensor_size=sensor_size, factor=factor)
    return EventBatch(*unstack(kernel(stacked), stacked))
