"""Stream builders and slow, obviously-correct references for the tests."""

from __future__ import annotations

import numpy as np

from evdown_torch.events import DVS_DTYPE


def random_stream(
    rng: np.random.Generator,
    n: int,
    sensor_size: tuple[int, int, int],
    *,
    t_max: int = 10_000,
    dtype: np.dtype = DVS_DTYPE,
    sort: bool = True,
) -> np.ndarray:
    """``n`` random events on ``sensor_size`` with times in ``[0, t_max)`` (sorted by default)."""
    w, h, _ = sensor_size
    out = np.empty(n, dtype=dtype)
    out["x"] = rng.integers(0, w, n)
    out["y"] = rng.integers(0, h, n)
    t = rng.integers(0, t_max, n)
    out["t"] = np.sort(t) if sort else t
    on = rng.random(n) < 0.5
    p_kind = dtype["p"]
    if p_kind == np.bool_:
        out["p"] = on
    elif np.issubdtype(p_kind, np.unsignedinteger):
        out["p"] = on.astype(np.uint8)
    else:
        out["p"] = np.where(on, 1, -1) if np.issubdtype(p_kind, np.signedinteger) else on
    return out


def as_tuples(events: np.ndarray) -> list[tuple]:
    """Events as sorted ``(x, y, t, on)`` tuples, a multiset for comparisons."""
    return sorted(
        zip(
            events["x"].tolist(),
            events["y"].tolist(),
            events["t"].tolist(),
            (events["p"] > 0).tolist(),
        )
    )
