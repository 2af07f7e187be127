"""What a user's own files meet: wrong names, bad files in a folder, swapped sizes, column
orders, time units in ``evdown bench --input``, and the hints each error or warning gives."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from evdown_torch import Downsample
from evdown_torch.bench import run
from evdown_torch.cli import main
from evdown_torch.io import SensorSizeGuessWarning, load_npy_events, read_events
from tests.helpers import random_stream

SENSOR = (16, 12, 2)
ARGS = ["--method", "downsample", "--factor", "2", "--sensor-size", "16", "12", "2"]


def _text_named_npy(path):
    path.write_text("t,x,y,p\n0.001,3,4,1\n0.002,5,6,0\n")
    return path


@pytest.mark.parametrize("name", ["table.npy", "table.npz"])
def test_a_text_file_named_npy_is_called_text_never_a_pickle(tmp_path, name):
    path = _text_named_npy(tmp_path / name)
    with pytest.raises(ValueError) as caught:
        read_events(path, sensor_size=SENSOR)
    message = str(caught.value)
    assert f"is not a NumPy {path.suffix} file" in message and "'t,x,y,p'" in message
    assert "pickle" not in message and "numpy.loadtxt" in message


def test_an_object_array_is_refused_without_the_pickle_advice(tmp_path):
    path = tmp_path / "objects.npy"
    np.save(path, np.array([{"x": 1}, None], dtype=object), allow_pickle=True)
    for read in (lambda: read_events(path, sensor_size=SENSOR), lambda: load_npy_events(path)):
        with pytest.raises(ValueError, match="Python objects") as caught:
            read()
        assert "allow_pickle" not in str(caught.value)


def test_bench_input_names_a_text_file_for_what_it_is(tmp_path, capsys):
    path = _text_named_npy(tmp_path / "table.npy")
    assert main(["bench", "--out", str(tmp_path / "o"), "--input", str(path), "--short"]) == 2
    err = capsys.readouterr().err
    assert "is not a NumPy .npy file" in err and "allow_pickle" not in err
    assert err.count("\n") == 1 and not (tmp_path / "o").exists()


def test_bench_input_reads_float_seconds_in_any_column_order(tmp_path):
    rng = np.random.default_rng(3)
    events = random_stream(rng, 400, SENSOR, t_max=300_000)
    table = np.stack([events["t"] / 1e6, events["x"], events["y"], events["p"]], axis=1)
    np.save(tmp_path / "seconds.npy", table)
    results = run.run_benchmark(short=True, events=300, methods=["downsample"], scaling=False,
                                memory=False, inputs=[tmp_path / "seconds.npy"],
                                sensor_size=SENSOR, time_unit="s", columns="t,x,y,p")
    read = results.input("seconds")
    assert read.sensor_size == SENSOR and read.num_events == 400
    assert read.duration_s == pytest.approx((events["t"][-1] - events["t"][0]) / 1e6)


def test_downscale_on_error_skip_does_the_rest_and_says_which_failed(tmp_path, capsys):
    rng = np.random.default_rng(4)
    folder = tmp_path / "in"
    folder.mkdir()
    for name in ("a", "c"):
        np.save(folder / f"{name}.npy", random_stream(rng, 50, SENSOR, t_max=5000))
    _text_named_npy(folder / "b.npy")  # sorts between them
    out = tmp_path / "out"
    assert main(["downscale", str(folder), str(out), *ARGS]) == 2  # stops at b (the default)
    err = capsys.readouterr().err
    assert "b.npy" in err and "1 file(s) after it not done; --on-error skip" in err
    assert main(["downscale", str(folder), str(out), *ARGS, "--on-error", "skip"]) == 1
    captured = capsys.readouterr()
    assert sorted(p.name for p in out.iterdir()) == ["a.npy", "a.npy.json", "c.npy",
                                                     "c.npy.json"]
    np.testing.assert_array_equal(np.load(out / "c.npy"),
                                  Downsample(SENSOR, 2)(np.load(folder / "c.npy")))
    lines = captured.err.strip().splitlines()
    assert lines[0].startswith(f"evdown downscale: error: {folder / 'b.npy'}: ")
    assert lines[0].endswith("(skipped)") and "not a NumPy .npy file" in lines[0]
    assert lines[-1] == (f"evdown downscale: 1 of 3 files failed (skipped: {folder / 'b.npy'});"
                         " the others were written")


def test_a_swapped_sensor_size_asks_width_first(tmp_path):
    rng = np.random.default_rng(5)
    events = random_stream(rng, 300, (320, 240, 2))
    events["x"][0], events["y"][0] = 319, 239
    with pytest.raises(ValueError, match=r"width first, \(W, H, P\): \(320, 240, 2\)\?"):
        Downsample((240, 320, 2), 2)(events)
    path = tmp_path / "r.npy"
    np.save(path, events)
    with pytest.raises(ValueError, match=r"width first, \(W, H, P\): \(320, 240, 2\)\?"):
        read_events(path, sensor_size=(240, 320, 2))
    with pytest.raises(ValueError) as caught:  # too small either way: no such hint
        Downsample((100, 100, 2), 2)(torch.tensor([[319, 239, 5, 1]]))
    assert "width first" not in str(caught.value)


def test_an_n_by_4_file_in_t_x_y_p_order_points_to_columns(tmp_path):
    rng = np.random.default_rng(6)
    events = random_stream(rng, 200, SENSOR, t_max=300_000)
    floats = np.stack([events["t"] / 1e6, events["x"], events["y"], events["p"]], axis=1)
    np.save(tmp_path / "floats.npy", floats)
    with pytest.raises(ValueError, match="whole numbers") as caught:
        read_events(tmp_path / "floats.npy", sensor_size=SENSOR)
    assert "columns look like t,x,y,p" in str(caught.value)
    assert "columns='t,x,y,p' (--columns t,x,y,p)" in str(caught.value)
    ints = np.stack([events["t"], events["x"], events["y"], events["p"]], axis=1)
    np.save(tmp_path / "ints.npy", ints)
    with pytest.raises(ValueError, match="columns look like t,x,y,p"):
        read_events(tmp_path / "ints.npy", sensor_size=SENSOR)  # t read as x: out of range
    np.save(tmp_path / "short.npy", ints[ints[:, 0] < 32_000])  # t read as x: off the sensor
    with pytest.raises(ValueError, match="outside the sensor size .* columns look like t,x,y,p"):
        read_events(tmp_path / "short.npy", sensor_size=SENSOR)
    got = read_events(tmp_path / "ints.npy", sensor_size=SENSOR, columns="t,x,y,p").events
    assert got["t"].tolist() == events["t"].tolist()


def test_the_guessed_sensor_size_tells_python_and_the_command_line_each_their_way(tmp_path,
                                                                                    capsys):
    rng = np.random.default_rng(7)
    path = tmp_path / "r.npy"
    np.save(path, random_stream(rng, 100, SENSOR, t_max=5000))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read_events(path)
    (warning,) = [w.message for w in caught if w.category is SensorSizeGuessWarning]
    assert "sensor_size=(W, H, P)" in str(warning) and "--" not in str(warning)
    assert main(["downscale", str(path), str(tmp_path / "o.npy"), "--method", "downsample",
                 "--factor", "2"]) == 0
    err = capsys.readouterr().err
    assert "--sensor-size W H P" in err and "sensor_size=" not in err
