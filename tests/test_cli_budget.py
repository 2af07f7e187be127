"""``evdown downscale --budget``: calibrated on the inputs, printed, recorded; bad budgets."""

from __future__ import annotations

import json

import numpy as np
import pytest

from evdown_torch import EventCount
from evdown_torch.cli import main
from evdown_torch.io import read_events, write_events
from evdown_torch.transforms.calibrate import BudgetTarget, calibrate
from evdown_torch.transforms.window_rates import window_rates
from tests.helpers import random_stream

SENSOR = (16, 12, 2)


@pytest.fixture
def two_files(tmp_path, rng):
    paths = []
    for i, n in enumerate((3000, 2000)):
        path = tmp_path / f"rec{i}.npy"
        np.save(path, random_stream(rng, n, SENSOR, t_max=200_000))
        paths.append(path)
    return paths


def _downscale(*paths, budget: str, method: str = "event_count", extra=()) -> int:
    return main(["downscale", *map(str, paths), "--method", method, "--factor", "2",
                 "--sensor-size", "16", "12", "2", "--budget", budget, *extra])


def test_a_ratio_budget_is_calibrated_on_all_inputs(two_files, tmp_path, capsys):
    out = tmp_path / "out"
    assert _downscale(*two_files, out, budget="ratio=0.1") == 0
    recordings = [np.load(p) for p in two_files]
    expected = calibrate(EventCount(SENSOR, 2), recordings, BudgetTarget.ratio(0.1))
    for path, recording in zip(two_files, recordings, strict=True):
        written = out / path.name
        np.testing.assert_array_equal(np.load(written), expected(recording))
        meta = json.loads((out / f"{path.name}.json").read_text())
        assert meta["calibration"]["threshold"] == expected.threshold
        assert meta["calibration"]["budget"] == "ratio=0.1"
        assert set(meta["calibration"]["rates_per_second"]) == {"window_us", "mean", "p99",
                                                                "peak"}
        assert read_events(written).sensor_size == (8, 6, 2)  # the sidecar still reads
    said = capsys.readouterr().out
    assert f"calibrated threshold={expected.threshold:.6g} on 2 file(s)" in said
    assert "events/s in windows of 1 ms" in said


def test_a_peak_budget_caps_the_busiest_window_of_every_output(two_files, tmp_path, capsys):
    out = tmp_path / "out"
    assert _downscale(*two_files, out, budget="peak=40000/1ms") == 0  # 40 per ms
    for path in two_files:
        t = np.load(out / path.name)["t"]
        busiest = max(int(((t >= s) & (t < s + 1000)).sum()) for s in t)
        assert busiest <= 40
        meta = json.loads((out / f"{path.name}.json").read_text())["calibration"]
        assert meta["rates_per_second"]["peak"] <= 40_000
    said = capsys.readouterr().out
    assert "(at most 40)" in said and "peak" in said


def test_hdf5_outputs_record_the_calibration(two_files, tmp_path):
    h5py = pytest.importorskip("h5py")
    out = tmp_path / "out.h5"
    assert _downscale(two_files[0], out, budget="rate=5000") == 0
    with h5py.File(out) as file:
        record = json.loads(file.attrs["calibration"])
    found = calibrate(EventCount(SENSOR, 2), [np.load(two_files[0])], BudgetTarget.rate(5000.0))
    assert record["threshold"] == found.threshold
    rates = window_rates([found(np.load(two_files[0]))], 1000)
    assert record["rates_per_second"]["peak"] == pytest.approx(rates.per_second(rates.peak))


@pytest.mark.parametrize(("budget", "said"), [
    ("ratio", "a budget must be ratio=R"), ("peak=500000", "a budget must be ratio=R"),
    ("peak=1500/1ms", "1.5 events per window"), ("peak=9/1 parsec", "a number and a unit"),
    ("ratio=-0.1", "positive"),
])
def test_a_malformed_budget_is_one_error_line_and_exit_2(two_files, tmp_path, capsys, budget,
                                                         said):
    with pytest.raises(SystemExit) as stop:
        _downscale(two_files[0], tmp_path / "out.npy", budget=budget)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("evdown downscale: error: argument --budget:") and said in err[-1]
    assert not (tmp_path / "out.npy").exists()


@pytest.mark.parametrize(("method", "extra", "said"), [
    ("downsample", (), "has no budget setting"),
    ("event_count", ("--set", "threshold=0.3"), "not both"),
])
def test_a_budget_the_method_cannot_take(two_files, tmp_path, capsys, method, extra, said):
    assert _downscale(two_files[0], tmp_path / "out.npy", budget="ratio=0.1", method=method,
                      extra=extra) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("evdown downscale: error:") and said in err[0]
    assert not (tmp_path / "out.npy").exists()


def test_a_budget_needs_one_sensor_for_all_inputs(tmp_path, rng, capsys):
    a, b = tmp_path / "a.npy", tmp_path / "b.npy"
    np.save(a, random_stream(rng, 500, SENSOR))
    np.save(b, random_stream(rng, 500, SENSOR))
    b.with_name("b.npy.json").write_text(json.dumps({"sensor_size": [20, 12, 2]}))
    assert _downscale(a, b, tmp_path / "out", budget="ratio=0.1") == 2
    assert "share one sensor size" in capsys.readouterr().err


def test_metadata_cannot_stand_in_for_the_sensor_size_or_time_unit(tmp_path, rng):
    events = random_stream(rng, 10, SENSOR)
    with pytest.raises(ValueError, match="sensor_size"):
        write_events(tmp_path / "x.npy", events, metadata={"sensor_size": [1, 1, 2]})
    with pytest.raises(TypeError):
        write_events(tmp_path / "x.npy", events, metadata={"when": object()})
    assert not (tmp_path / "x.npy").exists()
