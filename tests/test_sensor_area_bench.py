"""The sensor-area benchmark (benchmarks/bench_sensor_area.py) on tiny sessions."""

from __future__ import annotations

import pytest

from benchmarks import bench_sensor_area


def test_each_method_is_timed_on_both_sensors_and_gives_the_eager_events(capsys):
    assert bench_sensor_area.main(["--chunk-events", "300", "--chunks", "2", "--runs", "2",
                                   "--methods", "poisson", "event_count"]) == 0
    rows = [line.split(" | ") for line in capsys.readouterr().out.splitlines()
            if line.startswith("| ") and not line.startswith("| method")]
    assert [(row[0].strip("| "), row[1]) for row in rows] == [
        ("poisson", "1"), ("event_count", "1"), ("poisson", "2"), ("event_count", "2")]
    for row in rows:
        small, large, ratio = (float(value) for value in row[2:5])
        assert small > 0 and large > 0 and ratio == pytest.approx(large / small, rel=0.01,
                                                                   abs=0.01)
    assert [row[5].strip(" |") for row in rows] == ["yes", "yes", "", ""]


def test_a_session_returns_each_chunks_time_and_every_output_event():
    seconds, out = bench_sensor_area.session_run("downsample", (16, 16, 2), 50, 3)
    assert len(seconds) == 3 and min(seconds) > 0
    assert len(out) == 4 * 50  # Downsample keeps every event of the four chunks
