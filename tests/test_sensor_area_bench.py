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


def test_every_pixel_fires_once_in_time_order_before_the_bars():
    events = bench_sensor_area.every_pixel_fired((5, 3, 2))
    pixels = sorted(zip(events["x"].tolist(), events["y"].tolist()))
    assert pixels == [(x, y) for x in range(5) for y in range(3)]
    assert events["p"].all()
    t = events["t"]
    assert (t[:-1] <= t[1:]).all() and t.min() >= 0 and t.max() < bench_sensor_area.FIRED_US


def test_a_fired_session_reads_the_whole_sensor_before_the_bars():
    seconds, out = bench_sensor_area.session_run("downsample", (16, 16, 2), 50, 3, fired=True)
    assert len(seconds) == 3
    assert len(out) == 16 * 16 + 4 * 50  # Downsample keeps every event
    fired, bars = out[:256], out[256:]
    regions = fired["y"].astype(int) * 4 + fired["x"].astype(int)  # factor 4: a 4x4 grid
    assert sorted(regions.tolist()) == sorted(list(range(16)) * 16)
    assert bars["t"].min() >= bench_sensor_area.FIRED_US


def test_the_fired_mode_says_so_and_gives_the_eager_events(capsys):
    assert bench_sensor_area.main(["--chunk-events", "200", "--chunks", "2", "--runs", "1",
                                   "--fired", "--methods", "event_count"]) == 0
    out = capsys.readouterr().out
    assert "after every pixel fired once" in out.splitlines()[0]
    rows = [line for line in out.splitlines() if line.startswith("| event_count")]
    assert len(rows) == 1 and rows[0].rstrip(" |").endswith("yes")
