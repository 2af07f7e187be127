"""The method protocol: a method's settings, state and pure kernels, as one typed bundle.

Every method is a frozen settings dataclass ``S`` (checked and normalised once) and a state
``St`` threaded through its kernels. Its bundle, a :class:`Method` ``[S, St]``, is defined
beside those kernels (``EVENT_COUNT`` in :mod:`.event_count`, ``ESTIMATION`` in
:mod:`.estimation.method`, ...) and named by its transform class (``method = EVENT_COUNT``),
so a reader goes from the class to the kernel that runs in one hop. The kernels are named
``<method>_init``, ``<method>_step``, ``<method>_finish``, ``<method>_whole`` and
``<method>_stacked``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

from evdown_torch._tensors import chunk_bounds
from evdown_torch.collate import EventBatch
from evdown_torch.events import Events, sort_by_time

__all__ = ["Method", "finish_nothing", "run_protocol", "step_in_pieces"]

#: A method's settings type.
S = TypeVar("S")
#: A method's state type.
St = TypeVar("St")


def finish_nothing(state: object, settings: object) -> Events | None:
    """The ``finish`` kernel of a causal method: the end of a stream decides nothing."""
    return None


@dataclass(frozen=True)
class Method(Generic[S, St]):
    """A method's three pure kernels over its settings ``S`` and state ``St``, and fast paths.

    - ``init_state(settings, first_chunk) -> state``: the state of a fresh stream whose first
      non-empty, time-sorted chunk is ``first_chunk`` (its device, dtype and first timestamp
      are what a state may need from it; it is not consumed).
    - ``step(chunk, state, settings) -> (output, state)``: one non-empty, time-sorted chunk;
      the output is what the chunk *decides* (no later input can change it), sorted by ``t``
      and not earlier than any earlier output.
    - ``finish(state, settings) -> output``: what only the end of the stream decides
      (``None``: nothing; the default, for causal methods).

    :class:`~evdown_torch.transforms.Streaming` builds a transform's ``__call__``, ``batch``
    and ``session`` from these, so a stream cut in chunks equals the whole and a batch equals
    one call per recording by construction. Two optional fast paths give the same results
    faster and are tested equal to the protocol (``tests/transforms/test_streaming.py``):

    - ``whole(events, settings) -> output``: the whole stream in one call (events in any
      order).
    - ``stacked(batch, settings) -> EventBatch | None``: a batch of recordings in one call
      (``None``: this batch goes one recording at a time).

    Attributes:
        init_state: ``<method>_init``.
        step: ``<method>_step``.
        finish: ``<method>_finish``, or :func:`finish_nothing` for a causal method.
        whole: ``<method>_whole``, or ``None`` (the whole stream goes through the protocol).
        stacked: ``<method>_stacked``, or ``None`` (one recording at a time).
        no_stream: why the method has no ``init_state`` and ``step`` (it cannot stream: its
            transform has no session), or ``None``.
    """

    init_state: Callable[[S, Events], St] | None = None
    step: Callable[[Events, St, S], tuple[Events, St]] | None = None
    finish: Callable[[St, S], Events | None] = finish_nothing
    whole: Callable[[Events, S], Events] | None = None
    stacked: Callable[[EventBatch, S], EventBatch | None] | None = None
    no_stream: str | None = None

    def __post_init__(self) -> None:
        streams = self.init_state is not None and self.step is not None
        if streams == (self.no_stream is not None):
            raise TypeError("a Method has init_state and step, or says why not in no_stream")
        if not streams and self.whole is None:
            raise TypeError("a Method that cannot stream needs its whole-stream kernel")

    def streaming(self) -> tuple[Callable[[S, Events], St], Callable[[Events, St, S],
                                                                       tuple[Events, St]]]:
        """``(init_state, step)``.

        Raises:
            NotImplementedError: for a method that cannot stream, saying why.
        """
        if self.init_state is None or self.step is None:
            raise NotImplementedError(f"no streaming session: {self.no_stream}")
        return self.init_state, self.step

    def run_whole(self, events: Events, settings: S) -> Events:
        """The whole stream (any order): ``whole`` when the method has it, else the protocol."""
        if self.whole is not None:
            return self.whole(events, settings)
        return run_protocol(self, settings, events)


def run_protocol(method: Method[S, Any], settings: S, events: Events) -> Events:
    """The whole stream as one chunk through ``init_state``, ``step`` and ``finish``."""
    if events.num_events == 0:
        return Events.empty(events.t.dtype, events.device)
    events = sort_by_time(events)
    init_state, step = method.streaming()
    state = init_state(settings, events)
    out, state = step(events, state, settings)
    tail = method.finish(state, settings)
    if tail is None or tail.num_events == 0:
        return out
    return Events.cat([out, tail])


def step_in_pieces(
    events: Events, state: St, settings: S, step: Callable[[Events, St, S], tuple[Events, St]]
) -> tuple[Events, St]:
    """``step`` over the pieces of ``chunk_bounds`` of a time-sorted chunk, state carried.

    What a streaming session fed those pieces would give: a kernel's temporaries stay bounded
    on a long stream. Returns the pieces' outputs, concatenated, and the last state.
    """
    outputs = []
    bounds = chunk_bounds(events.t)
    for start, stop in zip(bounds[:-1], bounds[1:]):
        out, state = step(events.part(start, stop), state, settings)
        outputs.append(out)
    return (outputs[0] if len(outputs) == 1 else Events.cat(outputs)), state
