"""The one event container the kernels see, and the conversions at the edge.

Kernels take and return :class:`Events`: four 1-D tensors of equal length on one device,

* ``x``, ``y``: ``torch.int64`` pixel coordinates, ``0 <= x < W``, ``0 <= y < H``;
* ``t``: timestamps, ``torch.int64`` (microseconds in Tonic datasets) or ``torch.float64``;
* ``p``: ``torch.bool`` polarity, ``True`` for ON.

Users hand transforms one of four kinds, and get the same kind back:

* a Tonic structured array with fields ``x``, ``y``, ``t``, ``p`` in any order (``x``/``y``
  any integer dtype, ``t`` integer or float, ``p`` bool, 0/1 or -1/+1): the result has the
  same dtype and field order, and polarity in the same encoding;
* a ``torch.Tensor`` of shape ``(N, 4)`` whose columns are ``(x, y, t, p)``: the result has
  the same dtype and device (an int64 tensor keeps exact int64 timestamps; a float32 tensor
  cannot hold microsecond timestamps past 2**24 us = 16.8 s, use int64 or float64 for long
  recordings: a :class:`TimestampPrecisionWarning` says when it happened);
* a plain NumPy array of shape ``(N, 4)``, columns ``(x, y, t, p)`` as for tensors: the result
  is a NumPy array of the same dtype (integer or float; bool, complex and object arrays are
  refused);
* an :class:`Events` tuple.

Tensors that require grad are read as values (detached): downscaling selects and moves
discrete events and is not differentiable, so results never require grad. Tensors on the
``meta`` device hold no values and are refused.

:func:`to_events` validates and converts the input (never modifying it), :func:`from_events`
converts a result back to the caller's kind.
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING, Literal, NamedTuple, cast

import numpy as np
import numpy.typing as npt
import torch
from torch import Tensor

from evdown_torch._tensors import note_time_order, time_order, where_true
from evdown_torch.checks import check_has_values, swapped_sensor_hint

if TYPE_CHECKING:
    from evdown_torch.transforms.functional.compiled.columns import ColumnFacts

__all__ = [
    "DVS_DTYPE",
    "Events",
    "EventFormat",
    "EventsLike",
    "TimestampPrecisionWarning",
    "from_events",
    "polarity_sign",
    "to_events",
]

#: Tonic's event dtype for DVS cameras (``tonic.datasets.DVSGesture.dtype``), fields ``x``,
#: ``y`` int16, ``p`` bool, ``t`` int64 microseconds, in that order.
DVS_DTYPE = np.dtype([("x", np.int16), ("y", np.int16), ("p", np.bool_), ("t", np.int64)])

FIELDS = ("x", "y", "t", "p")

def polarity_sign(p: Tensor, dtype: torch.dtype = torch.int8) -> Tensor:
    """``+1`` for ON and ``-1`` for OFF, as a new tensor of ``dtype``: a level's change.

    Args:
        p: ``(N,)`` bool polarity (True: ON), as :class:`Events` holds it.
        dtype: the result's dtype (any signed integer or float dtype).

    Example:
        >>> polarity_sign(torch.tensor([True, False])).tolist()
        [1, -1]
    """
    return p.to(dtype).mul_(2).sub_(1)


class TimestampPrecisionWarning(UserWarning):
    """Float timestamps too large for their dtype to tell consecutive microseconds apart."""


#: Exact integers in each float dtype reach 2 ** (significand bits).
_EXACT_INTEGER_BITS = {"float16": 11, "bfloat16": 8, "float32": 24}


def _warn_if_time_lost_precision(t: Tensor, dtype_name: str) -> None:
    """Warn (once per dtype and place) when float timestamps exceed their exact-integer range."""
    bits = _EXACT_INTEGER_BITS.get(dtype_name)
    if bits is None or t.numel() == 0:
        return
    largest = float(t.abs().max())
    if math.isfinite(largest) and largest > 2**bits:  # _validate reports NaN and infinities
        warnings.warn(  # one fixed text per dtype, so Python shows it once
            f"event timestamps are {dtype_name}, which holds whole numbers exactly only up to "
            f"2**{bits}; larger ones (epoch or long-recording microseconds) were rounded "
            "before evdown_torch saw them, so distinct events may "
            "now share a timestamp (EventFunnelling then drops them as duplicates). Keep "
            "timestamps int64 or float64, or subtract the first one before casting.",
            TimestampPrecisionWarning,
            stacklevel=4,
        )


class Events(NamedTuple):
    """A stream of events as four 1-D tensors of equal length ``N`` on one device.

    Attributes:
        x: ``(N,)`` int64 column index.
        y: ``(N,)`` int64 row index.
        t: ``(N,)`` int64 or float64 timestamps (microseconds for Tonic datasets).
        p: ``(N,)`` bool polarity, ``True`` for ON.

    Example:
        >>> import torch
        >>> ev = Events.from_columns([0, 1], [2, 3], [10, 20], [True, False])
        >>> ev.num_events, ev.t.dtype
        (2, torch.int64)
    """

    x: Tensor
    y: Tensor
    t: Tensor
    p: Tensor

    @property
    def num_events(self) -> int:
        """Number of events ``N``."""
        return int(self.t.shape[0])

    @property
    def device(self) -> torch.device:
        """Device the tensors live on."""
        return self.t.device

    def select(self, index: Tensor) -> Events:
        """Return the events picked (and ordered) by an index or boolean mask tensor.

        Args:
            index: ``(M,)`` integer positions (any order, repeats allowed) or an ``(N,)`` bool
                mask, on the events' device.

        Example:
            >>> ev = Events.from_columns([0, 1, 2], [0, 0, 0], [5, 6, 7], [True, False, True])
            >>> ev.select(torch.tensor([2, 0])).t.tolist(), ev.select(ev.p).x.tolist()
            ([7, 5], [0, 2])
        """
        if index.dtype == torch.bool:  # the positions once, not a mask per column
            index = where_true(index)
        if index.ndim == 1 and index.dtype in (torch.int64, torch.int32):
            # index_select: several times faster than advanced indexing on the CPU.
            return Events(*(column.index_select(0, index) for column in self))
        return Events(self.x[index], self.y[index], self.t[index], self.p[index])

    def part(self, start: int, stop: int | None = None) -> Events:
        """The events ``start:stop`` (views of the columns: nothing is copied)."""
        return Events(self.x[start:stop], self.y[start:stop], self.t[start:stop],
                      self.p[start:stop])

    @staticmethod
    def cat(parts: Sequence[Events]) -> Events:
        """The streams of ``parts`` (at least one) one after another, in new tensors.

        Example:
            >>> a = Events.from_columns([0], [0], [5], [True])
            >>> Events.cat([a, a.part(0, 0), a]).t.tolist()
            [5, 5]
        """
        return Events(*(torch.cat(columns) for columns in zip(*parts, strict=True)))

    @staticmethod
    def empty(
        t_dtype: torch.dtype = torch.int64, device: torch.device | str | None = None
    ) -> Events:
        """An empty stream with timestamps of ``t_dtype`` on ``device``."""
        i = torch.empty(0, dtype=torch.int64, device=device)
        return Events(i, i.clone(), torch.empty(0, dtype=t_dtype, device=device),
                      torch.empty(0, dtype=torch.bool, device=device))

    @staticmethod
    def from_columns(x: npt.ArrayLike | Tensor, y: npt.ArrayLike | Tensor,
                     t: npt.ArrayLike | Tensor, p: npt.ArrayLike | Tensor,
                     device: torch.device | str | None = None) -> Events:
        """Build events from tensors or array-likes.

        ``x`` and ``y`` become int64, ``t`` int64 when it holds integers and float64
        otherwise, and ``p`` is ON where it is ``> 0`` (or ``True``). Tensors stay on their
        device unless ``device`` is given. The result never shares memory with the inputs.
        """

        def column(values: npt.ArrayLike | Tensor) -> Tensor:
            if isinstance(values, Tensor):
                return values.to(device=device, copy=True).reshape(-1)
            # A copy, contiguous: field views of a structured array have odd strides.
            return torch.as_tensor(np.array(values), device=device).reshape(-1)

        t = column(t)
        return Events(
            column(x).to(torch.int64),
            column(y).to(torch.int64),
            t.to(torch.float64) if t.is_floating_point() else t.to(torch.int64),
            column(p) > 0,
        )


#: What transforms take and return (in the same kind), a structured or ``(N, 4)`` NumPy array,
#: an ``(N, 4)`` tensor, or :class:`Events`.
EventsLike = np.ndarray | Tensor | Events


@dataclass(frozen=True)
class EventFormat:
    """How the caller handed events over, so that results go back in the same form.

    Attributes:
        kind: ``"numpy"`` (structured array), ``"tensor"`` (``(N, 4)`` tensor), ``"array"``
            (``(N, 4)`` NumPy array) or ``"events"``.
        dtype: the structured, tensor or array dtype (``None`` for ``"events"``).
        polarity: ``"bool"``, ``"binary"`` (OFF 0, ON 1) or ``"signed"`` (OFF -1, ON +1).
        device: the device of a tensor input.
    """

    kind: Literal["numpy", "tensor", "array", "events"]
    dtype: np.dtype | torch.dtype | None
    polarity: Literal["bool", "binary", "signed"]
    device: torch.device


def sort_by_time(events: Events) -> Events:
    """Events in stable time order (the input itself when already sorted).

    Example:
        >>> sort_by_time(Events.from_columns([0, 1, 2], [0, 0, 0], [5, 3, 5], [1, 1, 0])).t.tolist()
        [3, 5, 5]
    """
    order = time_order(events.t)
    return events if order is None else events.select(order)


def _polarity_encoding(p: Tensor) -> Literal["bool", "binary", "signed"]:
    """Detect the polarity encoding of a numeric polarity column and validate its values."""
    if p.dtype == torch.bool:
        return "bool"
    if p.numel() == 0:
        return "binary"
    encoding: Literal["binary", "signed"]
    if bool((p < 0).any()):
        ok = bool(((p == 1) | (p == -1)).all())
        encoding = "signed"
    else:
        ok = bool(((p == 0) | (p == 1)).all())
        encoding = "binary"
    if not ok:
        values = torch.unique(p)
        shown = ", ".join(str(v) for v in values[:6].tolist())
        more = ", ..." if values.numel() > 6 else ""
        raise ValueError(
            "polarity p must take two values, as bool, 0/1 or -1/+1; "
            f"got values {{{shown}{more}}}"
        )
    return encoding


def _check_integral(name: str, column: Tensor) -> None:
    if column.is_floating_point() and not (
        bool(torch.isfinite(column).all()) and bool((column == column.round()).all())
    ):
        raise ValueError(f"event coordinate {name} must hold whole numbers")


def _validate(
    events: Events, sensor_size: tuple[int, int, int] | None, facts: ColumnFacts | None = None
) -> None:
    """Check timestamps are finite and coordinates lie inside the sensor.

    ``facts``: what the compiled reading of a structured array learnt of the same columns
    (:func:`_from_structured`), which spares the passes that would learn it again.
    """
    if events.num_events == 0:
        return
    finite = facts.t_finite if facts is not None else not events.t.is_floating_point() or bool(
        torch.isfinite(events.t).all())
    if not finite:
        raise ValueError("event timestamps t must be finite, got NaN or infinite values")
    if sensor_size is None:
        return
    w, h, _ = sensor_size
    ranges = [facts.x_range, facts.y_range] if facts is not None else [
        (int(lo), int(hi)) for lo, hi in (torch.aminmax(events.x), torch.aminmax(events.y))]
    for name, (lo, hi), size in zip("xy", ranges, (w, h)):
        if lo < 0 or hi >= size:
            hint = "" if lo < 0 else swapped_sensor_hint((ranges[0][1] + 1, ranges[1][1] + 1),
                                                         sensor_size)
            raise ValueError(
                f"event coordinate {name} must lie in [0, {size - 1}] for sensor_size "
                f"{tuple(sensor_size)}, got values from {lo} to {hi}{hint}"
            )


def _column_loops(dtype: np.dtype | None) -> ModuleType | None:
    """The compiled reading and writing of structured arrays of ``dtype``, where they run.

    On the CPU path of :func:`~evdown_torch.kernel_path` (Numba installed, eager kernels not
    forced) and for fields the loops take; ``None`` elsewhere (NumPy's copies run).
    """
    from evdown_torch.transforms.functional.compiled import kernel_path

    if dtype is None or kernel_path("cpu") != "compiled":
        return None
    from evdown_torch.transforms.functional.compiled import columns

    return columns if columns.compiled_fields(dtype) else None


# The checks of a structured array's dtype, made once per dtype (a live session's chunks share
# one): they took about 14 µs of each call's fixed cost (docs/benchmarks.md, "Session of
# 2026-12-05 (evening)"). Errors are not cached: a bad dtype raises at every call.
@functools.lru_cache(maxsize=64)
def _check_field_names(dtype: np.dtype) -> None:
    """Refuse a structured ``dtype`` without each of :data:`FIELDS`, or with another field."""
    names = dtype.names or ()
    missing = [f for f in FIELDS if f not in names]
    if missing:
        raise ValueError(
            f"events are missing field(s) {missing}; a structured array needs fields "
            f"{list(FIELDS)} in any order, got {list(names)}"
        )
    extra = [f for f in names if f not in FIELDS]
    if extra:
        raise ValueError(
            f"events have field(s) {extra} that a downscaler cannot carry over; "
            f"expected only {list(FIELDS)}"
        )


@functools.lru_cache(maxsize=64)
def _field_kinds(dtype: np.dtype) -> tuple[type[np.integer] | type[np.floating], str, bool]:
    """``(t's column dtype, t's field dtype name, p is bool)`` of a structured ``dtype``.

    Raises:
        TypeError: for a field whose dtype the events cannot take.
    """
    kinds = {f: dtype[f] for f in FIELDS}
    for f in ("x", "y"):
        if not np.issubdtype(kinds[f], np.integer):
            raise TypeError(f"event field {f} must have an integer dtype, got {kinds[f]}")
    if not (np.issubdtype(kinds["t"], np.integer) or np.issubdtype(kinds["t"], np.floating)):
        raise TypeError(f"event field t must have an integer or float dtype, got {kinds['t']}")
    if not (kinds["p"] == np.bool_ or np.issubdtype(kinds["p"], np.number)):
        raise TypeError(f"event field p must be bool, integer or float, got {kinds['p']}")
    t_dtype = np.float64 if np.issubdtype(kinds["t"], np.floating) else np.int64
    return t_dtype, kinds["t"].name, bool(kinds["p"] == np.bool_)


def _from_structured(data: np.ndarray) -> tuple[Events, EventFormat, ColumnFacts | None]:
    _check_field_names(data.dtype)
    if data.ndim != 1:
        raise ValueError(f"a structured event array must be 1-D, got shape {data.shape}")
    t_dtype, t_name, p_bool = _field_kinds(data.dtype)
    loops = _column_loops(data.dtype)
    if loops is not None:  # one compiled pass: the columns and what the checks need
        (x, y, t_values, p), facts = loops.read_columns(data, t_dtype)
        t = torch.from_numpy(t_values)
        _warn_if_time_lost_precision(t, t_name)
        encoding = _polarity_encoding_of(facts) if not p_bool else "bool"
        if encoding is None:  # the checks' own error, from the values
            encoding = _polarity_encoding(torch.from_numpy(np.array(data["p"])))
        events = Events(torch.from_numpy(x), torch.from_numpy(y), t, torch.from_numpy(p))
        return events, EventFormat("numpy", data.dtype, encoding, torch.device("cpu")), facts
    t = torch.from_numpy(np.array(data["t"], dtype=t_dtype))  # always a copy
    _warn_if_time_lost_precision(t, t_name)
    p_raw = torch.from_numpy(np.array(data["p"]))
    encoding = _polarity_encoding(p_raw)
    p = p_raw if encoding == "bool" else p_raw > 0
    events = Events(
        torch.from_numpy(data["x"].astype(np.int64)),
        torch.from_numpy(data["y"].astype(np.int64)),
        t,
        p,
    )
    return events, EventFormat("numpy", data.dtype, encoding, torch.device("cpu")), None


def _polarity_encoding_of(facts: ColumnFacts) -> Literal["binary", "signed"] | None:
    """:func:`_polarity_encoding` of a numeric field from its facts; ``None`` for bad values."""
    if facts.p_negative:
        return "signed" if facts.p_signed else None
    return "binary" if facts.p_binary else None


def _from_tensor(data: Tensor) -> tuple[Events, EventFormat]:
    if data.ndim != 2 or data.shape[1] != 4:
        raise ValueError(
            f"an event tensor must have shape (N, 4) with columns (x, y, t, p), "
            f"got shape {tuple(data.shape)}"
        )
    if data.dtype == torch.bool or data.is_complex():
        raise TypeError(f"an event tensor must be integer or float, got dtype {data.dtype}")
    check_has_values(data)
    data = data.detach()  # values only: downscaling is not differentiable
    x, y, t, p = data.unbind(1)
    _warn_if_time_lost_precision(t, str(data.dtype).removeprefix("torch."))
    _check_integral("x", x)
    _check_integral("y", y)
    encoding = _polarity_encoding(p)
    floating = data.is_floating_point()
    events = Events(
        x.to(torch.int64, copy=True),
        y.to(torch.int64, copy=True),
        t.to(torch.float64 if floating else torch.int64, copy=True),
        p > 0,
    )
    return events, EventFormat("tensor", data.dtype, encoding, data.device)


def _from_plain_array(data: np.ndarray) -> tuple[Events, EventFormat]:
    """An ``(N, 4)`` NumPy array, read as the same values in a tensor would be."""
    if data.ndim != 2 or data.shape[1] != 4:
        raise ValueError(
            f"a plain NumPy event array must have shape (N, 4) with columns (x, y, t, p), or be "
            f"structured with fields x, y, t, p (as Tonic's); got shape {data.shape}"
        )
    kind = data.dtype.kind
    if kind not in "iuf":
        raise TypeError(f"an (N, 4) event array must be integer or float, got dtype {data.dtype}")
    if kind == "u" and data.size and int(data.max()) > np.iinfo(np.int64).max:
        raise ValueError("an (N, 4) event array holds values beyond the int64 range")
    # Integers as int64, floats as they are: the tensor path's checks, exact values.
    values = np.array(data, dtype=np.int64 if kind in "iu" else data.dtype)  # always a copy
    events, fmt = _from_tensor(torch.from_numpy(values))
    return events, EventFormat("array", data.dtype, fmt.polarity, torch.device("cpu"))


def _from_events(data: Events) -> tuple[Events, EventFormat]:
    n = data.t.shape[0]
    for name, column in zip(FIELDS, data):
        if not isinstance(column, Tensor) or column.ndim != 1 or column.shape[0] != n:
            raise ValueError(f"Events.{name} must be a 1-D tensor of the same length as t")
        if column.device != data.t.device:
            raise ValueError("Events tensors must all be on one device")
    check_has_values(data.t)
    if data.x.dtype != torch.int64 or data.y.dtype != torch.int64:
        raise TypeError(f"Events.x and Events.y must be int64, got {data.x.dtype}, {data.y.dtype}")
    if data.t.dtype not in (torch.int64, torch.float64):
        raise TypeError(f"Events.t must be int64 or float64, got {data.t.dtype}")
    if data.p.dtype != torch.bool:
        raise TypeError(f"Events.p must be bool, got {data.p.dtype}")
    if data.t.requires_grad:  # float64 t only; values only, as for tensors
        data = data._replace(t=data.t.detach())
    return data, EventFormat("events", None, "bool", data.t.device)


def to_events(
    data: EventsLike, sensor_size: tuple[int, int, int] | None = None, *,
    in_time_order: bool = False,
) -> tuple[Events, EventFormat]:
    """Validate events of any accepted kind and convert them to :class:`Events`.

    The input is never modified: the returned tensors never share memory with it, except
    for an :class:`Events` input, which is returned as it is (kernels never write to it).

    Args:
        data: a Tonic structured array, an ``(N, 4)`` tensor or NumPy array ``(x, y, t, p)``,
            or Events.
        sensor_size: ``(W, H, P)``; when given, coordinates must lie inside it.
        in_time_order: return the events in stable time order (``sort_by_time``; a
            structured array read by the compiled loop says on the way whether it already is).

    Returns:
        The events and the :class:`EventFormat` that :func:`from_events` needs.

    Raises:
        TypeError: for an unsupported container or dtype.
        ValueError: for missing fields, a wrong shape, non-finite timestamps, coordinates
            outside the sensor or polarity values other than bool, 0/1 or -1/+1.

    Example:
        >>> import numpy as np
        >>> dtype = np.dtype([("t", "<i8"), ("x", "<i2"), ("y", "<i2"), ("p", "?")])
        >>> arr = np.array([(5, 1, 2, True)], dtype=dtype)
        >>> events, fmt = to_events(arr, (4, 4, 2))
        >>> events.x.tolist(), events.t.tolist(), fmt.kind
        ([1], [5], 'numpy')
    """
    facts = None
    if isinstance(data, Events):
        events, fmt = _from_events(data)
    elif isinstance(data, np.ndarray) and data.dtype.names is not None:
        events, fmt, facts = _from_structured(data)
    elif isinstance(data, Tensor):
        events, fmt = _from_tensor(data)
    elif isinstance(data, np.ndarray):
        events, fmt = _from_plain_array(data)
    else:
        raise TypeError(
            "events must be a Tonic structured array, a torch.Tensor or NumPy array of shape "
            f"(N, 4) or evdown_torch.Events, got {type(data).__name__}"
        )
    _validate(events, sensor_size, facts)
    if facts is not None and facts.t_sorted:
        note_time_order(events.t)  # (in a transform's call: its kernel's sort takes it as is)
    elif in_time_order:
        events = sort_by_time(events)
    return events, fmt


#: :func:`~evdown_torch.transforms.functional.compiled.columns.write_columns`'s code of each
#: polarity encoding.
_POLARITY_CODES = {"bool": 0, "binary": 1, "signed": 2}


def from_events(events: Events, fmt: EventFormat) -> EventsLike:
    """Convert kernel output back to the caller's kind, dtype, field order and polarity encoding.

    Args:
        events: the kernel's result.
        fmt: the format :func:`to_events` returned for the input.

    Returns:
        A structured array, an ``(N, 4)`` tensor or NumPy array, or Events, matching ``fmt``.
    """
    if fmt.kind == "events":
        return events
    loops = _column_loops(cast(np.dtype, fmt.dtype)) if fmt.kind == "numpy" else None
    if loops is not None:  # one compiled pass
        out = np.empty(events.num_events, dtype=cast(np.dtype, fmt.dtype))
        loops.write_columns(*(column.cpu().numpy() for column in events),
                            _POLARITY_CODES[fmt.polarity], out)
        return out
    if fmt.polarity == "bool":
        p = events.p
    elif fmt.polarity == "binary":
        p = events.p.to(torch.int8)
    else:
        p = polarity_sign(events.p)
    if fmt.kind == "tensor":
        columns = (events.x, events.y, events.t, p)
        dtype = cast(torch.dtype, fmt.dtype)
        return torch.stack([c.to(device=fmt.device, dtype=dtype) for c in columns], dim=1)
    if fmt.kind == "array":
        table = np.empty((events.num_events, 4), dtype=cast(np.dtype, fmt.dtype))
        for i, column in enumerate((events.x, events.y, events.t, p)):
            table[:, i] = column.cpu().numpy()
        return table
    out = np.empty(events.num_events, dtype=cast(np.dtype, fmt.dtype))
    for name, column in zip(FIELDS, (events.x, events.y, events.t, p)):
        out[name] = column.cpu().numpy()
    return out
