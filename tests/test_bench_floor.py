"""The live replay's floor benchmark (benchmarks/bench_realtime_floor.py) on a tiny replay."""

from __future__ import annotations

import pytest

from benchmarks import bench_realtime_floor as floor
from evdown_torch.bench.inputs import gesture_stream
from evdown_torch.bench.realtime import REALTIME_RATE, chunk_bounds_us, retime


@pytest.fixture(scope="module")
def tiny_replay():
    stream, _ = retime(gesture_stream(700_000, sensor_size=floor.SENSOR), REALTIME_RATE)
    return stream, chunk_bounds_us(stream["t"], 10_000)


@pytest.mark.parametrize("method", sorted(floor.GOALS))
def test_every_floor_part_is_reached_and_put_back(tiny_replay, method):
    # A part the kernel no longer calls by that name would read 0 and the benchmark would
    # understate the floor: every part must be timed, and the kernels left as they were.
    stream, bounds = tiny_replay
    before = [getattr(module, name) for module, name, _ in floor.FLOOR[method]]
    result = floor.replay(method, stream, bounds, chunks=2)
    assert len(result.chunks) >= 1
    assert set(result.parts) == {name for _, name, _ in floor.FLOOR[method]}
    assert all(spent > 0 for spent in result.parts.values()), result.parts
    assert sum(result.parts.values()) < result.total
    assert [getattr(module, name) for module, name, _ in floor.FLOOR[method]] == before


def test_measured_puts_the_functions_back_after_an_error():
    import types

    module = types.ModuleType("fake")
    module.f = lambda: 1 / 0  # type: ignore[attr-defined]
    original = module.f  # type: ignore[attr-defined]
    spent: dict[str, float] = {}
    with pytest.raises(ZeroDivisionError), floor.measured(((module, "f", False),), spent):
        module.f()  # type: ignore[attr-defined]
    assert module.f is original  # type: ignore[attr-defined]
    assert spent["f"] >= 0


def test_the_table_names_every_method(capsys):
    assert floor.main(["--events", "700000", "--chunks", "1", "--runs", "1"]) == 0
    out = capsys.readouterr().out
    rows = [line for line in out.splitlines() if line.startswith("| ") and "---" not in line]
    assert [row.split(" | ")[0].strip("| ") for row in rows[1:]] == list(floor.GOALS)
    for row in rows[1:]:
        assert row.rstrip(" |").endswith(("cheaper", "impossible"))
