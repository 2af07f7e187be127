"""The package's random draws, seeded by the recording and a seed (one home for both kinds).

The thinning control (:class:`~evdown_torch.transforms.thinning.ThinnedDownsample`) seeds one
generator per recording from a digest of its whole content (:func:`recording_seed`); the
subsamplers, which must stream, draw one uniform per event from a hash of the event, its place
in the stream and the same mixed seed (:func:`event_uniforms`).
"""

from __future__ import annotations

import hashlib

import torch
from torch import Tensor

from evdown_torch.checks import check_non_negative_int
from evdown_torch.events import Events
from evdown_torch.transforms.functional.compiled import use_compiled

__all__ = ["chunk_uniforms", "content_digest", "event_uniforms", "mixed_seed", "recording_seed"]

_MASK32 = 0xFFFFFFFF


def content_digest(events: Events) -> bytes:
    """A digest of a stream's content (``x, y, t, p`` in order), whatever its container."""
    digest = hashlib.blake2b(digest_size=16)
    for column in events:
        digest.update(column.detach().cpu().contiguous().numpy().tobytes())
    return digest.digest()


def mixed_seed(content: bytes, seed: int) -> int:
    """A 63-bit seed from a content digest and ``seed``."""
    digest = hashlib.blake2b(content, digest_size=8)
    digest.update(int(seed).to_bytes(8, "little", signed=False))
    return int.from_bytes(digest.digest(), "little") >> 1


def recording_seed(events: Events, seed: int = 0) -> int:
    """A 63-bit seed derived from a stream's content and ``seed``.

    The same events (same ``x, y, t, p`` in the same order) always give the same seed,
    whatever container or device they came in; different recordings give different seeds.

    Example:
        >>> ev = Events.from_columns([0, 1], [0, 0], [5, 9], [1, 0])
        >>> recording_seed(ev) == recording_seed(Events.from_columns([0, 1], [0, 0], [5, 9],
        ...                                                          [True, False]))
        True
    """
    return mixed_seed(content_digest(events), seed)


def _mul32(values: Tensor, constant: int) -> Tensor:
    """``(values * constant) mod 2**32`` for int64 ``values`` in ``[0, 2**32)``, no overflow.

    The constant goes in two 16-bit halves, so that no product exceeds 2**48: exact on every
    device, without relying on int64 wrapping.
    """
    low = values * (constant & 0xFFFF)
    high = ((values * (constant >> 16)) & 0xFFFF) << 16
    return (low + high) & _MASK32


def _fmix32(h: Tensor) -> Tensor:
    """MurmurHash3's 32-bit finaliser on int64 ``h`` in ``[0, 2**32)`` (a bijection)."""
    h = h ^ (h >> 16)
    h = _mul32(h, 0x85EBCA6B)
    h = h ^ (h >> 13)
    h = _mul32(h, 0xC2B2AE35)
    return h ^ (h >> 16)


def event_uniforms(
    events: Events,
    seed: int,
    *,
    index: Tensor,
    origin: int | float | Tensor,
) -> Tensor:
    """One uniform draw in ``[0, 1)`` per event, a hash of the event and the seed.

    The subsamplers' draws (docs/semantics.md, "Subsamplers"): ``u_e`` depends on ``seed``
    (mixed as :func:`recording_seed` mixes it), on the event's position in its stream
    (``index``) and on its content (``x``, ``y``, ``p`` and ``t - origin``), and on nothing
    else. So a recording is drawn the same way whatever container, device, batch or process
    it comes in, a streaming session (which knows each event's position and the stream's
    first timestamp) draws what the whole-stream call draws, different recordings get
    different draws, and shifting the clock changes none. Two independent 32-bit hash chains
    (MurmurHash3's finaliser over 32-bit words, in int64 arithmetic that never overflows)
    give the 53 bits of each float64. On the CPU a compiled loop computes the same integers
    (:mod:`evdown_torch.transforms.functional.compiled.draws`).

    Args:
        events: ``N`` events.
        seed: non-negative integer.
        index: ``(N,)`` int64 position of each event in its stream (from 0, in stable time
            order).
        origin: the stream's first timestamp (a number, or an ``(N,)`` tensor of each
            event's stream's), of the events' ``t`` dtype.

    Returns:
        ``(N,)`` float64 in ``[0, 1)``, on the events' device.

    Example:
        >>> ev = Events.from_columns([0, 1, 1], [0, 0, 0], [5, 9, 9], [1, 0, 0])
        >>> u = event_uniforms(ev, 0, index=torch.arange(3), origin=5)
        >>> bool(((u >= 0) & (u < 1)).all()), bool(u[1] != u[2])
        (True, True)
        >>> shifted = Events.from_columns([0, 1, 1], [0, 0, 0], [105, 109, 109], [1, 0, 0])
        >>> bool(event_uniforms(shifted, 0, index=torch.arange(3), origin=105).equal(u))
        True
    """
    check_non_negative_int("seed", seed)
    key = mixed_seed(b"evdown_torch event uniforms", seed)
    offset = events.t - origin
    if offset.is_floating_point():
        offset = offset.to(torch.float64).view(torch.int64)
    if use_compiled(index):  # one compiled pass: the same draws
        from evdown_torch.transforms.functional.compiled import draws

        return draws.event_uniforms(events, key, index, offset)
    words = (index, index >> 32, events.x, (events.y << 1) | events.p.to(torch.int64),
             offset, offset >> 32)
    chains = []
    for start in (key & _MASK32, (key >> 32) & _MASK32):
        h = torch.full_like(index, start)
        for word in words:
            h = _fmix32(h ^ (word & _MASK32))
        chains.append(h)
    high, low = chains
    return ((high << 21) | (low >> 11)).to(torch.float64).mul_(2.0 ** -53)


def chunk_uniforms(events: Events, seed: int, *, seen: int, origin: int | float) -> Tensor:
    """:func:`event_uniforms` of a chunk whose first event is the stream's ``seen``-th.

    What a subsampler's step draws: its events sit at ``seen, seen + 1, ...`` in the stream
    that started at ``origin``.

    Example:
        >>> ev = Events.from_columns([0, 1, 1], [0, 0, 0], [5, 9, 9], [1, 0, 0])
        >>> whole = event_uniforms(ev, 3, index=torch.arange(3), origin=5)
        >>> bool(chunk_uniforms(ev.part(1, 3), 3, seen=1, origin=5).equal(whole[1:]))
        True
    """
    index = torch.arange(seen, seen + events.num_events, device=events.device)
    return event_uniforms(events, seed, index=index, origin=origin)
