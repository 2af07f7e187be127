"""The line-up: the package's methods and the peers a user would pick instead (candidates).

A candidate is named by a spec, ``"NAME"`` or ``"NAME:KEY=VALUE,..."`` (:func:`parse_spec`):
a method of :data:`~evdown_torch.transforms.registry.METHODS` with optional settings, or a
peer of :data:`PEERS` (Tonic's transforms, when Tonic is installed).
"""

from __future__ import annotations

import contextlib
import tempfile
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from evdown_torch._text import parse_settings
from evdown_torch.bench.measure import MemoryJob, measure_memory
from evdown_torch.checks import check_factor, check_sensor_size, output_size
from evdown_torch.transforms.registry import METHODS, make_method

__all__ = [
    "BENCH_SETTINGS",
    "PEERS",
    "PEER_MEMORY_BUDGET",
    "Candidate",
    "candidate",
    "candidate_job",
    "candidates",
    "fresh_call",
    "fresh_call_summary",
    "parse_spec",
    "prepare_candidate_call",
    "tonic_available",
]

#: Benchmark settings of the methods that need some, by method name (checked by the tests
#: against :func:`~evdown_torch.transforms.registry.method_settings`). Methods not named here
#: run with their defaults. Times are in the stream's unit (microseconds).
BENCH_SETTINGS: dict[str, dict[str, Any]] = {
    "lif": {"dt": 1000},
}

#: Peer settings: ``EventDownsampling`` time step in milliseconds, its noise threshold (with 0
#: every output pixel spikes at every step, so 1 is the smallest useful one) and its
#: differentiator time bins (Tonic's documented default).
PEER_DT_MS = 1.0
PEER_NOISE_THRESHOLD = 1
PEER_DIFFERENTIATOR_BINS = 2

#: Peers skip a measurement whose dense frames would need more than this (bytes).
PEER_MEMORY_BUDGET = 3_000_000_000

@dataclass(frozen=True)
class Candidate:
    """Something to benchmark: a method of this package or a peer.

    Attributes:
        name: the spec it was made from: a method's registry name, optionally with settings
            (``"lif:weight=1.5,reset_mechanism=zero"``), or a peer's name (see :data:`PEERS`).
        label: what the report calls it.
        peer: whether it is a peer (another library's transform).
        build: ``build(sensor_size, factor)`` returns a callable taking and returning a
            structured event array.
        dense_cost: for peers that build dense frames, ``dense_cost(sensor_size, factor,
            duration_us)`` estimates their ``(bytes, seconds per call)``, so that runs over
            the plan's budgets are skipped.
    """

    name: str
    label: str
    peer: bool
    build: Builder
    dense_cost: DenseCost | None = None


def parse_spec(spec: str) -> tuple[str, dict[str, Any]]:
    """Split ``"NAME[:KEY=VALUE,KEY=VALUE...]"`` into the name and its settings.

    The settings follow the command line's syntax (:func:`evdown_torch._text.parse_settings`):
    Python literals where they parse as one, else strings; a comma starts a new setting only
    where ``KEY=`` follows it, so tuples are fine (``factor=(1, 2)``).

    Example:
        >>> parse_spec("lif:weight=1.5,reset_mechanism=zero")
        ('lif', {'weight': 1.5, 'reset_mechanism': 'zero'})
    """
    name, _, rest = spec.partition(":")
    try:
        return name.strip(), parse_settings(rest)
    except ValueError as error:
        raise ValueError(f"{error} (in {spec!r})") from None


Sensor = tuple[int, int, int]
#: ``build(sensor_size, factor)``: the callable to time (a structured array in and out).
Builder = Callable[[Sensor, Any], Callable[[np.ndarray], Any]]
#: ``estimate(sensor_size, factor, duration_us)``: ``(bytes, seconds)`` of a dense peer.
DenseCost = Callable[[Sensor, Any, float], tuple[float, float]]


def _method_builder(name: str, settings: dict[str, Any]) -> Builder:
    def build(sensor_size: Sensor, factor: Any) -> Callable[[np.ndarray], Any]:
        return make_method(name, sensor_size, factor, **settings)

    return build


def _tonic_downsample(sensor_size: Sensor, factor: Any) -> Callable[[np.ndarray], Any]:
    import tonic

    fx, fy = check_factor(factor)
    return tonic.transforms.Downsample(spatial_factor=(1 / fx, 1 / fy))


def _tonic_event_downsampling(method: str) -> Builder:
    def build(sensor_size: Sensor, factor: Any) -> Callable[[np.ndarray], Any]:
        import tonic

        target = output_size(check_sensor_size(sensor_size), check_factor(factor))[:2]
        settings: dict[str, Any] = {"noise_threshold": PEER_NOISE_THRESHOLD}
        if method == "differentiator":
            settings["differentiator_time_bins"] = PEER_DIFFERENTIATOR_BINS
        return tonic.transforms.EventDownsampling(
            sensor_size=tuple(sensor_size), target_size=target, dt=PEER_DT_MS,
            downsampling_method=method, **settings,
        )

    return build


def _tonic_dense_cost(method: str) -> DenseCost:
    """Estimated (bytes, seconds per call) of Tonic's EventDownsampling on a stream.

    It builds dense frames of ``duration / dt`` steps over the output sensor and loops over
    them in Python, so its cost follows duration x area. The per-frame constants were
    measured on the development machine (Tonic 1.7): integrator about 14 bytes and
    100 us + 90 ns per output pixel and step, the differentiator about 64 bytes and three
    times the integrator's time.
    """

    def estimate(sensor_size: Sensor, factor: Any, duration_us: float) -> tuple[float, float]:
        w, h, _ = output_size(check_sensor_size(sensor_size), check_factor(factor))
        frames = duration_us / (PEER_DT_MS * 1000) + 1
        seconds = frames * (100e-6 + 90e-9 * w * h)
        if method == "integrator":
            return frames * w * h * 14, seconds
        return frames * w * h * 64, 3 * seconds

    return estimate


#: Peer name -> label.
PEERS: dict[str, str] = {
    "tonic_downsample": "tonic Downsample",
    "tonic_integrator": "tonic EventDownsampling (integrator)",
    "tonic_differentiator": "tonic EventDownsampling (differentiator)",
}

_PEER_BUILDERS = {
    "tonic_downsample": (_tonic_downsample, None),
    "tonic_integrator": (_tonic_event_downsampling("integrator"),
                         _tonic_dense_cost("integrator")),
    "tonic_differentiator": (_tonic_event_downsampling("differentiator"),
                             _tonic_dense_cost("differentiator")),
}


def tonic_available() -> bool:
    """Whether Tonic (the peers' library) can be imported."""
    try:
        import tonic  # noqa: F401
    except ImportError:
        return False
    return True


def candidate(spec: str) -> Candidate:
    """The candidate a spec names: ``"NAME"`` or ``"NAME:KEY=VALUE,..."`` (see :func:`parse_spec`).

    A method runs with :data:`BENCH_SETTINGS` updated by the spec's settings; a peer takes
    no settings.

    Raises:
        ValueError: for an unknown name, settings given to a peer, a setting the method does
            not take, or a peer while Tonic is not installed.

    Example:
        >>> candidate("event_count:threshold=0.5").label
        'EventCount (threshold=0.5)'
    """
    name, settings = parse_spec(spec)
    if name in PEERS:
        if settings:
            raise ValueError(f"peer {name!r} takes no settings, got {spec!r}")
        if not tonic_available():
            raise ValueError(f"peer {name!r} needs Tonic, which is not installed")
        build, dense = _PEER_BUILDERS[name]
        return Candidate(name, PEERS[name], True, build, dense)
    if name not in METHODS:
        raise ValueError(
            f"unknown method or peer {name!r}; expected one of {[*METHODS, *PEERS]}"
        )
    build = _method_builder(name, {**BENCH_SETTINGS.get(name, {}), **settings})
    build((8, 8, 2), 1)  # a setting the method does not take fails here
    text = ", ".join(f"{k}={v!r}" for k, v in settings.items())
    return Candidate(spec, METHODS[name].__name__ + (f" ({text})" if text else ""), False, build)


def candidates(names: Iterable[str] | None = None, *, peers: bool = True) -> list[Candidate]:
    """The candidates to benchmark: every method in ``METHODS``, then the peers.

    Args:
        names: specs of a subset of methods and peers, in this order (default: every method
            in ``METHODS``, then every peer); see :func:`candidate`.
        peers: with ``names=None``, include the Tonic peers (when Tonic is importable).

    Raises:
        ValueError: for a spec :func:`candidate` rejects.

    Example:
        >>> [c.name for c in candidates(["downsample", "funnelling"])]
        ['downsample', 'funnelling']
    """
    if names is None:
        names = [*METHODS, *(PEERS if peers and tonic_available() else ())]
    return [candidate(spec) for spec in names]


def candidate_job(spec: str, path: str, sensor_size: Sequence[int], factor: Any) -> MemoryJob:
    """The memory job of a candidate (see :func:`candidate`) once on a ``.npy`` stream."""
    return MemoryJob("evdown_torch.bench.lineup:prepare_candidate_call",
                     {"spec": spec, "path": str(path), "sensor_size": list(sensor_size),
                      "factor": factor})


def fresh_call(spec: str, events: np.ndarray, sensor_size: Sequence[int],
               factor: Any) -> dict[str, Any]:
    """One call of a candidate on ``events`` in a fresh process: time and peak memory.

    The stream is saved to a temporary ``.npy`` file for the measuring process
    (:func:`~evdown_torch.bench.measure.measure_memory`, which returns the dict).

    Raises:
        RuntimeError: the measuring process failed (its message).
    """
    with tempfile.TemporaryDirectory(prefix="evdown-fresh-") as tmp:
        path = Path(tmp) / "events.npy"
        np.save(path, events)
        [result] = measure_memory([candidate_job(spec, str(path), sensor_size, factor)])
    if "error" in result:
        raise RuntimeError(f"{spec}, one call in a fresh process: {result['error']}")
    return result


def fresh_call_summary(result: dict[str, Any], num_events: int) -> str:
    """One line of a :func:`fresh_call` result: times, rate and peak memory (MiB).

    Example:
        >>> line = fresh_call_summary({"seconds": 2.0, "cpu_seconds": 1.9, "added": 2**30,
        ...                            "total": 2**31}, 10_000_000)
        >>> line.split("; ")[0]
        '2.0 s (1.9 s CPU, 5.00 M events/s)'
        >>> line.split("; ")[1]  # doctest: +NORMALIZE_WHITESPACE
        'peak memory +1,024 MiB during the call (107.4 bytes per input event),
         process peak 2,048 MiB'
    """
    mib = 2**20
    return (f"{result['seconds']:.1f} s ({result['cpu_seconds']:.1f} s CPU, "
            f"{num_events / result['seconds'] / 1e6:.2f} M events/s); peak memory "
            f"+{result['added'] / mib:,.0f} MiB during the call "
            f"({result['added'] / num_events:.1f} bytes per input event), process peak "
            f"{result['total'] / mib:,.0f} MiB")


def prepare_candidate_call(spec: str, path: str, sensor_size: Sequence[int],
                           factor: Any) -> Callable[[], Any]:
    """Load a stream, build the candidate, warm it up; return the call to measure.

    The warm-up is one call on the first 1000 events, so that one-time costs (lazy
    initialisation) are not counted as the call's.
    """
    events = np.load(path)
    w, h, p = sensor_size
    fn = candidate(spec).build((w, h, p),
                               factor if isinstance(factor, int) else tuple(factor))
    with contextlib.suppress(Exception):  # a peer may reject a short slice; the call reports
        fn(events[:1000])
    return lambda: fn(events)
