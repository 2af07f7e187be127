"""The shape every downscaling transform shares, and the one streaming session of all."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields
from functools import cached_property
from typing import Any, ClassVar, overload

import torch

from evdown_torch._tensors import time_order_notes
from evdown_torch.checks import check_factor, check_output_count, check_sensor_size
from evdown_torch.collate import EventBatch, from_batch, to_batch
from evdown_torch.events import (
    EventFormat,
    Events,
    EventsLike,
    from_events,
    to_events,
)
from evdown_torch.threads import OneCallAtATime
from evdown_torch.time_units import check_first_call
from evdown_torch.transforms.functional.protocol import Method
from evdown_torch.transforms.functional.settings import RegionSettings, ThresholdSettings


class Streaming:
    """A transform built from a :class:`Method`: its settings and three kernels.

    A subclass names its method's bundle, defined beside the kernels
    (``method = EVENT_COUNT``, from ``transforms.functional.event_count``), its registry
    :attr:`name`, and its checked settings as :attr:`settings`; everything else is generic:
    :meth:`kernel` (the whole stream, through the method's ``whole`` fast path when it has
    one), :meth:`stream` / :meth:`stream_end` (the steps of a :class:`Session`),
    :meth:`__call__`, :meth:`batch` and :meth:`session`. The concatenation of every chunk's
    output and the end's equals the transform applied to the whole stream
    (docs/semantics.md, "Processing a stream in consecutive chunks"). A transform whose
    method cannot stream (its bundle's ``no_stream`` says why), or a ``session`` override
    refusing some settings, has no session.

    A class that names no ``method`` or no ``settings`` is refused when it is defined, but
    for bases and compositions, which say ``abstract=True`` in their class statement.
    """

    #: Every transform is a frozen dataclass whose fields are its settings as given.
    __dataclass_fields__: ClassVar[dict[str, Any]]
    sensor_size: tuple[int, int, int] | None
    #: The method's kernels, or ``None`` for an abstract base or a composition such as
    #: :class:`Chain`.
    method: ClassVar[Method[Any, Any] | None] = None
    #: The method's name in the registry (``transforms.registry.METHODS``), the command line
    #: and the study's configs; empty for a transform outside the registry.
    name: ClassVar[str] = ""
    #: Fields kept as given, and fields that stay ``None`` when left out, rather than taking
    #: the settings' normalised values and defaults (the copy-back of ``__post_init__``).
    as_given: ClassVar[tuple[str, ...]] = ()
    none_stays_none: ClassVar[tuple[str, ...]] = ()

    def __init_subclass__(cls, abstract: bool = False, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if abstract:
            return
        if cls.method is None and cls.kernels is Streaming.kernels:
            raise TypeError(f"{cls.__name__} names no method: set `method = <its bundle>`")
        if cls.settings is Streaming.settings:
            raise TypeError(f"{cls.__name__} has no settings: define its `settings` property")

    def __post_init__(self) -> None:
        """Check every setting once (:attr:`settings`); fields take its normalised values.

        A list ``sensor_size`` becomes a tuple; :attr:`as_given` fields, and a ``None`` in
        :attr:`none_stays_none`, stay as given.
        """
        settings = self.settings
        for name in (field.name for field in fields(self) if hasattr(settings, field.name)):
            if name not in self.as_given and not (name in self.none_stays_none
                                                  and getattr(self, name) is None):
                object.__setattr__(self, name, getattr(settings, name))

    @property
    def settings(self) -> Any:
        """The method's checked, normalised settings (what its kernels take)."""
        raise NotImplementedError(f"{type(self).__name__} has no settings")

    @property
    def kernels(self) -> Method[Any, Any]:
        """The bundle this transform runs, its class's :attr:`method`.

        A transform with several modes (PhotocurrentPooling) picks one from its settings.
        """
        if self.method is None:
            raise NotImplementedError(f"{type(self).__name__} has no method kernels")
        return self.method

    def algorithmic_delay(self) -> float:
        """How long after an input event, in stream time, its output can be final.

        0 for a causal method (the default); ``inf`` for one that needs the whole stream.
        """
        return 0.0

    def kernel(self, events: Events) -> Events:
        """The whole stream of validated events (any order), sorted by ``t``."""
        return self.kernels.run_whole(events, self.settings)

    def stream(self, events: Events, state: Any | None) -> tuple[Events, Any]:
        """One non-empty, time-sorted chunk through the method's ``step``.

        ``state`` is ``None`` for the first chunk of a stream. Returns ``(output, new state)``.
        """
        init_state, step = self.kernels.streaming()
        if state is None:
            state = init_state(self.settings, events)
        return step(events, state, self.settings)

    def stream_end(self, state: Any | None) -> Events | None:
        """The output only the end of the stream decides (``None``: nothing)."""
        if state is None:
            return None
        return self.kernels.finish(state, self.settings)

    def batch_kernel(self, batch: EventBatch) -> EventBatch | None:
        """A batch of validated recordings through the method's ``stacked`` fast path.

        ``None`` when it has none (:meth:`batch` then goes one recording at a time).
        """
        stacked = self.kernels.stacked
        return None if stacked is None else stacked(batch, self.settings)

    def __call__(self, events: EventsLike) -> EventsLike:
        """Downscale events of any accepted kind and return the same kind.

        Args:
            events: a Tonic structured array (fields x, y, t, p in any order), a tensor of
                shape ``(N, 4)`` with columns ``(x, y, t, p)``, or Events.

        Returns:
            The output events, sorted by ``t``, in the input's kind, dtype and polarity
            encoding.

        Warns:
            TimeUnitWarning: at most once per transform, when the first recording it is called
                on (of at least 100 events) looks like timestamps in another unit than the
                microseconds its time settings are in
                (:func:`~evdown_torch.time_units.check_first_call`).
        """
        with time_order_notes():  # the read's time order, for the kernel's (this call only)
            ev, fmt = to_events(events, self.sensor_size)
            check_first_call(self, ev.t)
            out = self.kernel(ev)
        return from_events(out, fmt)

    @overload
    def batch(self, recordings: EventBatch) -> EventBatch: ...

    @overload
    def batch(self, recordings: Sequence[EventsLike]) -> list[EventsLike]: ...

    def batch(
        self, recordings: EventBatch | Sequence[EventsLike]
    ) -> EventBatch | list[EventsLike]:
        """Downscale many recordings in one pass; each output equals the recording's own call.

        The recordings go through the kernel together (``docs/semantics.md``: processing
        several recordings in one batched call gives, for each, the same events as processing
        it alone), which costs much less than one call per recording when they are small.
        The frames mode of :class:`~evdown_torch.transforms.PhotocurrentPooling` and
        :class:`~evdown_torch.transforms.thinning.ThinnedDownsample` (random draws seeded by
        each recording) have no batched kernel and process the recordings one by one. The
        output limit (:func:`evdown_torch.max_output_events`) applies to the batch as a
        whole.

        Args:
            recordings: a sequence of recordings of any accepted kind (on one device, all
                with integer or all with float timestamps), or an
                :class:`~evdown_torch.collate.EventBatch`.

        Returns:
            A list with each recording's output in its own kind, dtype and polarity encoding;
            an :class:`~evdown_torch.collate.EventBatch` (on the input's device) for an
            :class:`~evdown_torch.collate.EventBatch`.

        Example:
            >>> import torch
            >>> from evdown_torch import Downsample
            >>> down = Downsample((4, 4, 2), factor=2)
            >>> a, b = torch.tensor([[3, 1, 0, 1]]), torch.tensor([[2, 2, 5, 0], [0, 0, 6, 1]])
            >>> [out.tolist() for out in down.batch([a, b])]
            [[[1, 0, 0, 1]], [[1, 1, 5, 0], [0, 0, 6, 1]]]
        """
        if isinstance(recordings, EventBatch):
            events, _ = to_events(recordings.events, self.sensor_size)
            return self._batch_events(EventBatch(events, recordings.lengths))
        batch, formats = to_batch(recordings, self.sensor_size)
        return from_batch(self._batch_events(batch), formats)

    def _batch_events(self, batch: EventBatch) -> EventBatch:
        """:meth:`batch` on validated events (the longest recording's timing checked once)."""
        if batch.lengths:
            longest = max(range(len(batch.lengths)), key=batch.lengths.__getitem__)
            start = sum(batch.lengths[:longest])
            check_first_call(self, batch.events.t[start:start + batch.lengths[longest]])
        out = self.batch_kernel(batch)
        if out is None:  # no batched kernel: one recording at a time, the limit on them all
            parts, emitted = [], 0
            for part in batch.unbind():
                parts.append(self.kernel(part))
                emitted += parts[-1].num_events
                check_output_count(emitted, detail=" in the batch")
            events = Events.cat(parts)
            out = EventBatch(events, tuple(part.num_events for part in parts))
        return out

    def session(self) -> Session:
        """Start a streaming session over consecutive chunks of one stream (see :class:`Session`).

        Raises:
            NotImplementedError: for a transform without method kernels, or whose method
                cannot stream (saying why).
        """
        try:
            self.kernels.streaming()
        except NotImplementedError as error:
            raise NotImplementedError(f"{type(self).__name__} has {error}") from None
        return Session(self)


class Session:
    """A live stream through a transform: feed consecutive chunks, get each chunk's events.

    ``session(chunk)`` returns the events that chunk decides, in the chunk's kind (structured
    array, ``(N, 4)`` tensor or Events); ``session.flush()`` returns what only the end of the
    stream decides and ends the stream; ``session.reset()`` forgets the stream. The
    concatenation of all outputs, flush included, equals the transform applied to the whole
    stream, whatever the chunk sizes (empty chunks included).

    Chunks must follow each other in time: a chunk may not hold a timestamp earlier than the
    previous chunks' last one (equal timestamps are fine and keep chunk order). A chunk that
    breaks this, or any other bad chunk (an empty one too), raises a ``ValueError`` and leaves
    the session as it was, so it stays usable. The method's own state is held explicitly in
    ``state`` (``None`` before the first event); the transform itself is never modified.

    A call, ``flush()`` or ``reset()`` made while another one runs (another thread) raises a
    ``RuntimeError`` and changes nothing: give each thread its own session (a copy,
    ``copy.deepcopy``, continues the stream on its own).

    Attributes:
        transform: the settings.
        state: the method's state after the last chunk (see its ``stream`` method).
        last_t: the latest input timestamp seen (a Python number), ``None`` before any event.

    Example:
        >>> import torch
        >>> from evdown_torch import EventCount
        >>> ev = torch.tensor([[0, 0, 10, 1], [1, 1, 20, 1], [0, 1, 30, -1], [1, 0, 40, -1]])
        >>> session = EventCount((2, 2, 2), factor=2, threshold=0.5).session()
        >>> [session(chunk).tolist() for chunk in (ev[:1], ev[1:3], ev[3:])]
        [[], [[0, 0, 20, 1]], [[0, 0, 40, -1]]]
        >>> session.flush().tolist()
        []
    """

    def __init__(self, transform: Streaming) -> None:
        self.transform = transform
        self._busy = OneCallAtATime("session",
                                    "give each thread its own session (transform.session())")
        self._forget()

    def reset(self) -> None:
        """Forget the stream: the next chunk starts a new one."""
        with self._busy:
            self._forget()

    def _forget(self) -> None:
        self.state: Any | None = None
        self.last_t: int | float | None = None
        self._fmt: EventFormat | None = None
        self._t_dtype: torch.dtype | None = None
        self._device: torch.device | None = None

    def __call__(self, chunk: EventsLike) -> EventsLike:
        """Process the next chunk; returns the events it decides, in the chunk's kind.

        Raises:
            ValueError: for a chunk (even an empty one) that starts before the previous
                chunk's last event, on another device or with another timestamp dtype than
                the stream's, or that fails the transform's input checks; the session is
                unchanged.
            RuntimeError: while another call of this session is running (another thread).
        """
        with self._busy:
            return self._next(chunk)

    def _next(self, chunk: EventsLike) -> EventsLike:
        events, fmt = to_events(chunk, self.transform.sensor_size, in_time_order=True)
        if self._device is not None:
            if events.device != self._device:
                raise ValueError(
                    f"chunk is on {events.device} but the stream so far is on {self._device}"
                )
            if events.t.dtype != self._t_dtype:
                raise ValueError(
                    f"chunk timestamps are {events.t.dtype} but the stream's are {self._t_dtype}"
                )
        if events.num_events == 0:
            self._fmt = fmt
            return from_events(Events.empty(events.t.dtype, events.device), fmt)
        first = events.t[0].item()
        if self.last_t is not None and first < self.last_t:
            raise ValueError(
                f"chunks must follow each other in time: this chunk holds t={first}, before "
                f"the previous chunks' last event at t={self.last_t}"
            )
        out, state = self.transform.stream(events, self.state)
        self.state = state
        self.last_t = events.t[-1].item()
        self._fmt, self._t_dtype, self._device = fmt, events.t.dtype, events.device
        return from_events(out, fmt)

    def flush(self) -> EventsLike:
        """End the stream: return what only its end decides and reset the session.

        Returns:
            The remaining events in the kind of the last chunk (empty Events when no chunk
            was fed).

        Raises:
            RuntimeError: while another call of this session is running (another thread).
        """
        with self._busy:
            return self._end()

    def _end(self) -> EventsLike:
        if self._fmt is None:
            self._forget()
            return Events.empty()
        out = self.transform.stream_end(self.state)
        if out is None:
            t_dtype = self._t_dtype if self._t_dtype is not None else torch.int64
            out = Events.empty(t_dtype, self._device)
        fmt = self._fmt
        self._forget()
        return from_events(out, fmt)


@dataclass(frozen=True)
class Downscaler(Streaming, abstract=True):
    """Base of the downscaling transforms: region settings, batches and the edge conversions.

    Subclasses are frozen dataclasses whose fields are the method's settings, built once
    into :attr:`settings` (checked and normalised there) and handed to the kernels of their
    :attr:`~Streaming.method`. ``__call__`` validates the events, converts them to
    :class:`~evdown_torch.events.Events`, runs the method and converts the result back to the
    caller's kind. Neither the input nor the transform is ever modified.

    Attributes:
        sensor_size: input sensor size ``(W, H, P)``.
        factor: a positive integer or a pair ``(fx, fy)``; pixel ``(x, y)`` goes to region
            ``(x // fx, y // fy)``.
    """

    #: The one setting that sets the output's event budget (see ``transforms.calibrate``);
    #: ``None`` for methods whose output count is fixed by the input.
    budget_setting: ClassVar[str | None] = None
    as_given = ("factor",)

    sensor_size: tuple[int, int, int]
    factor: int | tuple[int, int] = 2

    def region_geometry(self) -> tuple[tuple[int, int, int], tuple[int, int]]:
        """The checked ``(sensor_size, (fx, fy))`` every region method's settings start with."""
        sensor_size = check_sensor_size(self.sensor_size)
        return sensor_size, check_factor(self.factor, sensor_size)

    @cached_property
    def settings(self) -> RegionSettings:
        """The checked settings the kernels take (built once, in ``__post_init__``)."""
        return RegionSettings(*self.region_geometry())

    @property
    def factor_xy(self) -> tuple[int, int]:
        """The factor as a pair ``(fx, fy)``."""
        return self.settings.factor

    @property
    def output_sensor_size(self) -> tuple[int, int, int]:
        """Output sensor size ``(ceil(W / fx), ceil(H / fy), P)``, for the next transform."""
        return self.settings.output_sensor_size


@dataclass(frozen=True)
class ThresholdDownscaler(Downscaler, abstract=True):
    """Base of the log-luminance methods: a DVS reference rule at a contrast threshold.

    Attributes:
        threshold: contrast threshold on a region's mean level (in input events per pixel),
            > 0. It is used as the nearest fraction with denominator at most 10**6, so
            decimal thresholds such as 0.01 are exact.

    A call counts its output before building it and raises a ``ValueError`` naming the count
    when it would exceed the output limit (:func:`evdown_torch.max_output_events`, 100
    million events by default): a threshold far below the level steps of a region asks for
    that many. The linear and cubic estimators also refuse integer timestamps spanning 2**53
    or more, whose crossing times float64 cannot hold.
    """

    budget_setting: ClassVar[str | None] = "threshold"

    threshold: float = 1.0

    @cached_property
    def settings(self) -> ThresholdSettings:
        """The checked settings the kernels take (built once, in ``__post_init__``)."""
        return ThresholdSettings(*self.region_geometry(), self.threshold)


@dataclass(frozen=True, init=False)
class Chain(Streaming, abstract=True):
    """Transforms applied one after the other, as one transform with one session.

    ``tonic.transforms.Compose`` chains transforms for whole recordings; ``Chain`` does the
    same and also streams: its session feeds each chunk's output of one stage to the next
    stage's step, and its flush ends the stages in order, so a chained session equals the
    chained batch result too. Use it to compose :class:`~evdown_torch.TemporalFunnelling`
    with a spatial method.

    Args:
        *transforms: streaming transforms (at least one), first applied first.

    Example:
        >>> import torch
        >>> from evdown_torch import EventFunnelling, TemporalFunnelling
        >>> ev = torch.tensor([[0, 0, 0, 1], [1, 1, 3, 1], [2, 0, 12, 1]])
        >>> chain = Chain(TemporalFunnelling(dt=10), EventFunnelling((4, 4, 2), factor=2))
        >>> chain(ev).tolist()
        [[0, 0, 0, 1], [1, 0, 10, 1]]
    """

    transforms: tuple[Streaming, ...]

    def __init__(self, *transforms: Streaming) -> None:
        if not transforms:
            raise ValueError("Chain needs at least one transform")
        for transform in transforms:
            if not isinstance(transform, Streaming):
                raise TypeError(
                    f"Chain takes evdown_torch transforms, got {type(transform).__name__}"
                )
        object.__setattr__(self, "transforms", tuple(transforms))
        #: The first stage's input sensor size.
        object.__setattr__(self, "sensor_size", transforms[0].sensor_size)

    def batch_kernel(self, batch: EventBatch) -> EventBatch | None:
        """``None``: a chain's batch goes one recording at a time through every stage."""
        return None

    def algorithmic_delay(self) -> float:
        """The sum of the stages' delays."""
        return sum(stage.algorithmic_delay() for stage in self.transforms)

    def kernel(self, events: Events) -> Events:
        """Every stage's kernel in order; each stage checks its input as its call would."""
        for i, transform in enumerate(self.transforms):
            if i:
                events, _ = to_events(events, transform.sensor_size)
            events = transform.kernel(events)
        return events

    def __call__(self, events: EventsLike) -> EventsLike:
        """Apply every stage in order; returns the input's kind."""
        for transform in self.transforms:
            events = transform(events)
        return events

    def session(self) -> Session:
        """Start a streaming session through every stage (see :class:`Session`).

        Raises:
            ValueError, NotImplementedError: as the first stage that cannot stream raises
                from its own ``session()`` (e.g. an estimator without ``max_delay``), before
                any chunk.
        """
        for transform in self.transforms:
            transform.session()  # refuses as the stage itself would
        return Session(self)

    def stream(self, events: Events, state: Any | None) -> tuple[Events, Any]:
        """One chunk through every stage; the state is the tuple of the stages' states."""
        states = list(state) if state is not None else [None] * len(self.transforms)
        for i, transform in enumerate(self.transforms):
            if events.num_events == 0:
                break
            events, states[i] = transform.stream(events, states[i])
        return events, tuple(states)

    def stream_end(self, state: Any | None) -> Events | None:
        """End the stages in order, each one's end fed through the stages after it."""
        states = list(state) if state is not None else [None] * len(self.transforms)
        pieces: list[Events] = []
        for i, transform in enumerate(self.transforms):
            tail = transform.stream_end(states[i])
            for j in range(i + 1, len(self.transforms)):
                if tail is None or tail.num_events == 0:
                    break
                tail, states[j] = self.transforms[j].stream(tail, states[j])
            if tail is not None and tail.num_events:
                pieces.append(tail)
        if not pieces:
            return None
        return Events.cat(pieces)
