"""The shape every downscaling transform shares, and the one streaming session of all."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any, ClassVar, overload

import torch

from evdown_torch._tensors import sort_by_time
from evdown_torch.collate import EventBatch, from_batch, to_batch
from evdown_torch.events import EventFormat, Events, EventsLike, from_events, to_events
from evdown_torch.time_units import check_first_call
from evdown_torch.transforms.functional.settings import RegionSettings, ThresholdSettings


def finish_nothing(state: Any, settings: Any) -> Events | None:
    """The ``finish`` kernel of a causal method: the end of a stream decides nothing."""
    return None


@dataclass(frozen=True)
class Method:
    """A method's three pure kernels over its settings, and optional fast paths.

    Every method is a frozen settings dataclass ``S`` (checked and normalised once) plus:

    - ``init_state(settings, first_chunk) -> state``: the state of a fresh stream whose first
      non-empty, time-sorted chunk is ``first_chunk`` (its device, dtype and first timestamp
      are what a state may need from it; it is not consumed).
    - ``step(chunk, state, settings) -> (output, state)``: one non-empty, time-sorted chunk;
      the output is what the chunk *decides* (no later input can change it), sorted by
      ``t`` and not earlier than any earlier output.
    - ``finish(state, settings) -> output``: what only the end of the stream decides
      (``None``: nothing; the default, for causal methods).

    :class:`Streaming` builds a transform's ``__call__``, ``batch`` and ``session`` from
    these, so a stream cut in chunks equals the whole and a batch equals one call per
    recording by construction. Two optional fast paths give the same results faster and are
    tested equal to the protocol (``tests/transforms/test_streaming.py``):

    - ``whole(events, settings) -> output``: the whole stream in one call (events in any order).
    - ``stacked(batch, settings) -> EventBatch | None``: a batch of recordings in one call
      (``None``: this batch goes one recording at a time).
    """

    init_state: Callable[[Any, Events], Any]
    step: Callable[[Events, Any, Any], tuple[Events, Any]]
    finish: Callable[[Any, Any], Events | None] = finish_nothing
    whole: Callable[[Events, Any], Events] | None = None
    stacked: Callable[[EventBatch, Any], EventBatch | None] | None = None


def run_protocol(method: Method, settings: Any, events: Events) -> Events:
    """The whole stream as one chunk through ``init_state``, ``step`` and ``finish``."""
    if events.num_events == 0:
        return Events.empty(events.t.dtype, events.device)
    events = sort_by_time(events)
    state = method.init_state(settings, events)
    out, state = method.step(events, state, settings)
    tail = method.finish(state, settings)
    if tail is None or tail.num_events == 0:
        return out
    return Events.cat([out, tail])


class Streaming:
    """A transform built from a :class:`Method`: its settings and three kernels.

    Subclasses set the class attribute :attr:`method` and expose their checked settings as
    :attr:`settings`; everything else is generic: :meth:`kernel` (the whole stream, through
    the method's ``whole`` fast path when it has one), :meth:`stream` / :meth:`stream_end`
    (the steps of a :class:`Session`), :meth:`__call__`, :meth:`batch` and :meth:`session`.
    The concatenation of every chunk's output and the end's equals the transform applied to
    the whole stream (docs/semantics.md, "Processing a stream in consecutive chunks").
    A method that cannot stream (:attr:`method` ``None``, or a ``session`` override saying
    why) has no session.
    """

    sensor_size: tuple[int, int, int] | None
    #: The method's kernels, or ``None`` for a composition such as :class:`Chain`.
    method: ClassVar[Method | None] = None

    @property
    def settings(self) -> Any:
        """The method's checked, normalised settings (what its kernels take)."""
        raise NotImplementedError(f"{type(self).__name__} has no settings")

    @property
    def method_settings(self) -> Any:
        """The settings the method's kernels take.

        That is :attr:`settings`, except where the public settings are a part of them (LIF:
        the neuron's ``LIFSettings``, shared with the ``nn.Module``, inside the region's
        ``LIFPoolingSettings``).
        """
        return self.settings

    def kernel(self, events: Events) -> Events:
        """The whole stream of validated events (any order), sorted by ``t``."""
        method = self._method()
        if method.whole is not None:
            return method.whole(events, self.method_settings)
        return run_protocol(method, self.method_settings, events)

    def stream(self, events: Events, state: Any | None) -> tuple[Events, Any]:
        """One non-empty, time-sorted chunk through the method's ``step``.

        ``state`` is ``None`` for the first chunk of a stream. Returns ``(output, new state)``.
        """
        method = self._method()
        if state is None:
            state = method.init_state(self.method_settings, events)
        return method.step(events, state, self.method_settings)

    def stream_end(self, state: Any | None) -> Events | None:
        """The output only the end of the stream decides (``None``: nothing)."""
        if state is None:
            return None
        return self._method().finish(state, self.method_settings)

    def batch_kernel(self, batch: EventBatch) -> EventBatch | None:
        """A batch of validated recordings through the method's ``stacked`` fast path.

        ``None`` when it has none (:meth:`batch` then goes one recording at a time).
        """
        if self.method is None or self.method.stacked is None:
            return None
        return self.method.stacked(batch, self.method_settings)

    def _method(self) -> Method:
        if self.method is None:
            raise NotImplementedError(f"{type(self).__name__} has no method kernels")
        return self.method

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
        ev, fmt = to_events(events, self.sensor_size)
        check_first_call(self, ev.t)
        return from_events(self.kernel(ev), fmt)

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
        if out is None:  # no batched kernel: one recording at a time
            parts = [self.kernel(part) for part in batch.unbind()]
            events = Events.cat(parts)
            out = EventBatch(events, tuple(part.num_events for part in parts))
        return out

    def session(self) -> Session:
        """Start a streaming session over consecutive chunks of one stream (see :class:`Session`).

        Raises:
            NotImplementedError: for a transform without method kernels.
        """
        self._method()
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
    breaks this, or any other bad chunk, raises a ``ValueError`` and leaves the session as it
    was, so it stays usable. The method's own state is held explicitly in ``state``
    (``None`` before the first event); the transform itself is never modified.

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
        self.reset()

    def reset(self) -> None:
        """Forget the stream: the next chunk starts a new one."""
        self.state: Any | None = None
        self.last_t: int | float | None = None
        self._fmt: EventFormat | None = None
        self._t_dtype: torch.dtype | None = None
        self._device: torch.device | None = None

    def __call__(self, chunk: EventsLike) -> EventsLike:
        """Process the next chunk; returns the events it decides, in the chunk's kind.

        Raises:
            ValueError: for a chunk that starts before the previous chunk's last event, on
                another device or with another timestamp dtype than the stream's, or that
                fails the transform's input checks; the session is unchanged.
        """
        events, fmt = to_events(chunk, self.transform.sensor_size)
        if events.num_events == 0:
            self._fmt = fmt
            return from_events(Events.empty(events.t.dtype, events.device), fmt)
        if self._device is not None:
            if events.device != self._device:
                raise ValueError(
                    f"chunk is on {events.device} but the stream so far is on {self._device}"
                )
            if events.t.dtype != self._t_dtype:
                raise ValueError(
                    f"chunk timestamps are {events.t.dtype} but the stream's are {self._t_dtype}"
                )
        events = sort_by_time(events)
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
        """
        if self._fmt is None:
            self.reset()
            return Events.empty()
        out = self.transform.stream_end(self.state)
        if out is None:
            t_dtype = self._t_dtype if self._t_dtype is not None else torch.int64
            out = Events.empty(t_dtype, self._device)
        fmt = self._fmt
        self.reset()
        return from_events(out, fmt)


@dataclass(frozen=True)
class Downscaler(Streaming):
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

    sensor_size: tuple[int, int, int]
    factor: int | tuple[int, int] = 2

    def __post_init__(self) -> None:
        object.__setattr__(self, "sensor_size", self.method_settings.sensor_size)

    @cached_property
    def settings(self) -> RegionSettings:
        """The checked settings the kernels take (built once, in ``__post_init__``)."""
        return RegionSettings(self.sensor_size, self.factor)  # type: ignore[arg-type]

    @property
    def factor_xy(self) -> tuple[int, int]:
        """The factor as a pair ``(fx, fy)``."""
        return self.method_settings.factor

    @property
    def output_sensor_size(self) -> tuple[int, int, int]:
        """Output sensor size ``(ceil(W / fx), ceil(H / fy), P)``, for the next transform."""
        return self.method_settings.output_sensor_size


@dataclass(frozen=True)
class ThresholdDownscaler(Downscaler):
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

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "threshold", self.settings.threshold)

    @cached_property
    def settings(self) -> ThresholdSettings:
        """The checked settings the kernels take (built once, in ``__post_init__``)."""
        return ThresholdSettings(self.sensor_size, self.factor,  # type: ignore[arg-type]
                                 self.threshold)


@dataclass(frozen=True, init=False)
class Chain(Streaming):
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

    @property
    def sensor_size(self) -> tuple[int, int, int] | None:  # type: ignore[override]
        """The first stage's input sensor size."""
        return self.transforms[0].sensor_size

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
