"""LinearEstimation's compiled session step: the ramps (:mod:`.linear_ramps`) behind the protocol.

:func:`~..estimation.stream.estimation_step` hands a chunk here first. Where the ramps take
it (the linear curve, int64 timestamps, a compiled CPU call, settings whose integers fit:
:func:`ramps_step`), the step is two passes over the chunk, and the state it returns is the
package's :class:`~..estimation.stream.WindowState`, made from the ramps' session
(:func:`~.linear_ramps_state.window_state`): the eager path, the windowed compiled path and
``estimation_finish`` all resume from it. The ramps' session is kept beside that state (one
owner: the next step on that state takes it over), so a stream stepped chunk after chunk
converts one way only; a step on any other state (one stepped before, one from the other
path) seeds a session from the state's tensors (:func:`~.linear_ramps_state.ramp_session`).

Elsewhere it returns ``None`` and the windowed session runs. The ramps decide as the windowed
solver does except where an exact value lies within about ``1e-12`` fixed-point units of the
edge of its tolerances (docs/semantics.md, "Bounded delay").
"""

from __future__ import annotations

import functools
import threading
import weakref
from fractions import Fraction

import numpy as np
import torch

from evdown_torch.checks import check_output_count
from evdown_torch.events import Events
from evdown_torch.transforms.functional.compiled.linear_ramps import (
    LEVEL_BITS,
    RampSession,
    RampSettings,
)
from evdown_torch.transforms.functional.compiled.linear_ramps_state import (
    ramp_session,
    window_state,
)
from evdown_torch.transforms.functional.compiled.regions import outside_error
from evdown_torch.transforms.functional.estimation.delay import effective_delay
from evdown_torch.transforms.functional.estimation.settings import EstimationSettings
from evdown_torch.transforms.functional.estimation.window_state import WindowState
from evdown_torch.transforms.functional.reference import threshold_fraction

__all__ = ["MAX_RAMP_DELAY", "ramp_settings", "ramps_step"]

#: The longest ``max_delay`` (time units) the ramps take: their slope table has ``D + 1``
#: entries (16 bytes each). Longer delays take the windowed session.
MAX_RAMP_DELAY = 1 << 20

#: The largest ``a * n_r * 2**k`` (a level's spacing in fixed-point units) the ramps take:
#: the sweep compares values with ``(q + 1)`` spacings in int64.
_MAX_LEVEL = 1 << 58

#: Each state's ramps' session, by the id of the state's ``q`` (a tensor made for it alone):
#: ``(weak reference to q, session)``; an entry leaves when its ``q`` is collected.
_SESSIONS: dict[int, tuple[weakref.ref, RampSession]] = {}
_SESSIONS_LOCK = threading.Lock()


@functools.lru_cache(maxsize=16)
def ramp_settings(sensor_size: tuple[int, int, int], factor: tuple[int, int],
                  fraction: Fraction, delay: int) -> RampSettings | None:
    """The ramps' settings, or ``None`` where their integers cannot hold these settings.

    Example:
        >>> ramp_settings((128, 128, 2), (4, 4), Fraction(1, 4), 1000).k
        32
        >>> ramp_settings((128, 128, 2), (4, 4), Fraction(10**8), 1000) is None
        True
    """
    try:
        settings = RampSettings.of(sensor_size, factor,
                                   (fraction.numerator, fraction.denominator), delay)
    except ValueError:
        return None
    return settings if int(settings.levels.max()) < _MAX_LEVEL else None


def _taken(state: WindowState) -> RampSession | None:
    """The session kept beside ``state``, taken over (no longer kept), or ``None``."""
    with _SESSIONS_LOCK:
        entry = _SESSIONS.pop(id(state.q), None)
    if entry is None or entry[0]() is not state.q:
        return None
    session = entry[1]
    if session.horizon != state.horizon or session.t_last != int(state.t_last):
        return None
    return session


def _forget(key: int, _: weakref.ref) -> None:
    with _SESSIONS_LOCK:
        _SESSIONS.pop(key, None)


def _keep(state: WindowState, session: RampSession) -> None:
    key = id(state.q)
    with _SESSIONS_LOCK:
        _SESSIONS[key] = (weakref.ref(state.q, functools.partial(_forget, key)),
                          session)


def _levels_fit(x: np.ndarray, y: np.ndarray, state: WindowState, ramps: RampSettings) -> bool:
    """Whether no region's sum of levels can leave half the ramps' headroom in this chunk.

    A region's sum of levels, and every ramp's part of it, is at most the level changes its
    pixels carry: the state's knots (each fired pixel's first carries its whole level) and
    the chunk's events. Half the headroom (``n_r * 2**(LEVEL_BITS - 1)`` levels for the
    largest ``n_r``) leaves the fixed point's rounding room, and keeps every product of the
    sweep inside int64. Checked on the totals first, region by region only when they do not
    fit.
    """
    room = int(ramps.pixels.max()) << (LEVEL_BITS - 1)
    change = state.change.abs().numpy()
    if x.shape[0] + int(change.sum()) < room:
        return True
    regions = ramps.pixels.shape[0]
    knots = state.knots
    in_region = np.bincount(ramps.row[y] * ramps.out_w + ramps.column[x], minlength=regions)
    state_region = (ramps.row[knots.y.to(torch.int64).numpy()] * ramps.out_w
                    + ramps.column[knots.x.to(torch.int64).numpy()])
    in_region += np.bincount(state_region, weights=change, minlength=regions).astype(np.int64)
    return int(in_region.max()) < room


def ramps_step(events: Events, state: WindowState, settings: EstimationSettings,
               ) -> tuple[Events, WindowState] | None:
    """One chunk of a linear bounded-delay stream through the ramps, or ``None``.

    ``None`` (nothing done) where the ramps do not take the chunk: another curve, timestamps
    other than int64, a delay over :data:`MAX_RAMP_DELAY`, a threshold whose levels do not
    fit the fixed point, a region whose level changes (the state's and the chunk's) could leave
    half its headroom (:func:`_levels_fit`), a clock within ``2 D`` of the int64 limit.
    The caller has checked the chunk as for the windowed step (time order, the span).

    Args:
        events: ``N >= 1`` events in stable time order, none earlier than the previous
            chunk's last.
        state: the state after the previous chunk, or ``estimation_init``'s (no horizon
            yet) for the first.
        settings: the estimator's settings, ``max_delay`` set.

    Returns:
        ``(output, state)`` as the windowed step returns them, or ``None``.

    Raises:
        ValueError: for an event outside the sensor (the state given is left as it was).
        OutputLimitError: for more output events than the limit in force.
    """
    if settings.curve != "linear" or settings.max_delay is None or events.t.dtype != torch.int64:
        return None
    delay = effective_delay(settings.max_delay, events.t)
    if delay > MAX_RAMP_DELAY:
        return None
    ramps = ramp_settings(settings.sensor_size, settings.factor,
                          threshold_fraction(settings.threshold), int(delay))
    if ramps is None:
        return None
    t_start = int(state.t_start)
    if t_start < -(1 << 63) + 2 * delay + 1:
        return None
    x, y = events.x.to(torch.int64).numpy(), events.y.to(torch.int64).numpy()
    width, height, _ = settings.sensor_size
    if x.shape[0] and (x.min() < 0 or y.min() < 0 or x.max() >= width or y.max() >= height):
        bad = int(np.flatnonzero((x < 0) | (y < 0) | (x >= width) | (y >= height))[0])
        raise outside_error(bad, x, y, ramps.column, ramps.row)
    if not _levels_fit(x, y, state, ramps):
        return None
    first = state.horizon is None
    session = None if first else _taken(state)
    if session is None:
        session = (RampSession(t_start, events.num_events, ramps) if first
                   else ramp_session(state, ramps, events.num_events))
    decided = session(x, y, events.t.numpy(), events.p.numpy())
    if decided is None:  # more crossings than the ramps' buffer: the window solves the chunk
        return None  # (from ``state``, which the ramps never write; their session is dropped)
    out_x, out_y, out_t, out_on = decided
    check_output_count(out_t.shape[0])
    new_state = window_state(session)
    _keep(new_state, session)
    output = Events(torch.from_numpy(out_x), torch.from_numpy(out_y), torch.from_numpy(out_t),
                    torch.from_numpy(out_on))
    return output, new_state
