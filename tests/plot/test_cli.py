"""``evdown show`` end to end on small inputs, its one-line errors, and lazy matplotlib."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from evdown_torch import EventCount, LIFPooling
from evdown_torch.cli import main
from evdown_torch.plot.command import build_transforms
from evdown_torch.plot.recording import load_recording
from evdown_torch.synthetic import render_gesture
from tests.helpers import random_stream, saved_stream
from tests.plot.images import big_blobs

SENSOR = (16, 12, 2)


@pytest.fixture
def npy(tmp_path, rng):
    return saved_stream(tmp_path / "in.npy", rng, 400, SENSOR, t_max=200_000)


@pytest.mark.slow
def test_gif_of_a_synthetic_gesture_has_its_ground_truth_panel(tmp_path, capsys):
    out = tmp_path / "g.gif"
    code = main(["show", "synthetic:right_arm_cw:2", "--factor", "4", "--sensor-size", "32",
                 "32", "2", "--duration", "120", "--methods", "event_count,cubic",
                 "--window", "40", "--out", str(out)])
    assert code == 0
    events = render_gesture(3, 2, sensor_size=(32, 32, 2), duration_us=120_000)
    frames = (events["t"].max() - events["t"].min()) // 40_000 + 1
    with Image.open(out) as gif:
        assert gif.n_frames == frames
        assert big_blobs(np.asarray(gif.convert("RGB"))) == 4  # input, 2 methods, truth
    assert f"{frames} frames of 40 ms x 4 panels" in capsys.readouterr().out


def test_png_contact_sheet_of_a_file(npy, tmp_path):
    out = tmp_path / "sheet.png"
    assert main(["show", str(npy), "--factor", "2", "--methods", "downsample,lif",
                 "--window", "20", "--windows", "3", "--out", str(out)]) == 0
    with Image.open(out) as png:
        assert big_blobs(np.asarray(png.convert("RGB"))) == 3 * 3


def test_curve_of_a_file_names_the_busiest_pixel(npy, tmp_path, capsys):
    out = tmp_path / "curve.svg"
    assert main(["show", str(npy), "--factor", "4", "--curve", "1,2", "--threshold", "0.25",
                 "--methods", "linear,cubic", "--out", str(out)]) == 0
    assert out.read_text().lstrip().startswith("<?xml")
    events = np.load(npy)
    counts = np.zeros((3, 4), dtype=int)  # 16 x 12 sensor, factor 4: 4 x 3 output
    np.add.at(counts, (events["y"] // 4, events["x"] // 4), 1)
    y, x = np.unravel_index(counts.argmax(), counts.shape)
    assert f"busiest output pixel is ({x}, {y}), with {counts.max()} input events" in (
        capsys.readouterr().out)


def test_synthetic_sheet_without_ground_truth(tmp_path):
    out = tmp_path / "sheet.png"
    assert main(["show", "synthetic:0", "--factor", "4", "--sensor-size", "32", "32", "2",
                 "--duration", "100", "--methods", "event_count", "--windows", "2",
                 "--no-ground-truth", "--out", str(out)]) == 0
    with Image.open(out) as png:
        assert big_blobs(np.asarray(png.convert("RGB"))) == 2 * 2


def test_a_file_that_records_its_sensor_size_is_shown_on_that_sensor(npy, tmp_path):
    from evdown_torch.io import write_events

    wide = (40, 30, 2)  # larger than the coordinates reach: a guess would be wrong
    path = write_events(tmp_path / "in.h5", np.load(npy), sensor_size=wide)
    recording = load_recording(str(path))
    assert recording.sensor_size == wide
    assert recording.events.num_events == len(np.load(npy))


def test_duration_keeps_the_first_milliseconds_of_a_file(npy):
    from evdown_torch.io import SensorSizeGuessWarning

    with pytest.warns(SensorSizeGuessWarning, match=r"guessed \(16, 12, 2\)"):
        whole = load_recording(str(npy))  # a .npy file does not record its sensor size
    first = load_recording(str(npy), duration_ms=50, sensor_size=SENSOR)
    t = whole.events.t
    assert first.events.num_events == int((t < t[0] + 50_000).sum()) < whole.events.num_events
    assert first.sensor_size == whole.sensor_size == (16, 12, 2)


@pytest.mark.parametrize(("argv", "message"), [
    (["--curve", "8,0"], "pixel (8, 0) is outside the 8x6 output sensor"),
    (["--out", "x.mp4"], "--out must end in .gif (animation) or .png (contact sheet)"),
    (["--curve", "1,1", "--out", "c.gif"], "--out for --curve must be an image"),
    (["--set", "weight=1", "--methods", "cubic"], "none of the chosen methods ['cubic'] takes"),
    (["--set", "lif.weight=1", "--methods", "cubic"], "'lif' is not one of the chosen methods"),
    (["--set", "cubic.dt=1"], "does not take setting(s) ['dt']"),
    (["--windows", "0"], "--windows must be a positive integer"),
])
def test_bad_arguments_give_one_line_errors(npy, tmp_path, capsys, argv, message):
    argv = [a if not a.endswith((".mp4", ".gif")) else str(tmp_path / a) for a in argv]
    size = [str(n) for n in SENSOR]  # a file that does not record its size warns without it
    assert main(["show", str(npy), "--factor", "2", "--sensor-size", *size, *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("evdown show: error: ") and message in err
    assert err.count("\n") == 1


@pytest.mark.parametrize(("spec", "message"), [
    ("synthetic:wave", "unknown synthetic class 'wave'"),
    ("synthetic:11", "unknown synthetic class '11'"),
    ("synthetic:1:x", "must be a non-negative integer"),
    ("synthetic:", "synthetic:CLASS[:SEED]"),
    ("absent.npy", "does not exist"),
])
def test_bad_inputs_give_one_line_errors(capsys, spec, message):
    assert main(["show", spec, "--factor", "2"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("evdown show: error: ") and message in err and err.count("\n") == 1


@pytest.mark.parametrize("name", ["empty.npy", "empty.npz"])
def test_an_empty_file_is_one_error_line(tmp_path, capsys, name):
    (tmp_path / name).write_bytes(b"")
    assert main(["show", str(tmp_path / name), "--factor", "2", "--sensor-size", "8", "6", "2",
                 "--out", str(tmp_path / "o.png")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("evdown show: error: cannot read ") and name in err, err
    assert err.count("\n") == 1 and not (tmp_path / "o.png").exists()


@pytest.mark.parametrize("argv", [["--curve", "1"], ["--methods", "cubic,nope"],
                                  ["--window", "0"], ["--factor", "0,x"]])
def test_malformed_values_are_refused_by_the_parser(npy, capsys, argv):
    with pytest.raises(SystemExit) as exit_info:
        main(["show", str(npy), "--factor", "2", *argv])
    assert exit_info.value.code == 2
    assert "evdown show: error: argument" in capsys.readouterr().err


def test_threshold_and_settings_reach_the_right_methods():
    a, b, c = build_transforms(["event_count", "lif", "linear"], SENSOR, 2, 0.5,
                               [("weight", 0.7), ("event_count.threshold", 2.0)])
    assert isinstance(a, EventCount) and a.threshold == 2.0
    assert isinstance(b, LIFPooling) and b.weight == 0.7 and b.threshold == 1.0
    assert c.threshold == 0.5


@pytest.mark.slow
def test_matplotlib_is_imported_only_to_draw_and_its_absence_names_the_extra(npy, tmp_path):
    # a fresh interpreter: this one has imported matplotlib already
    code = (
        "import sys, evdown_torch, evdown_torch.plot, evdown_torch.cli\n"
        "evdown_torch.cli.build_parser()\n"
        "print(sorted(m for m in sys.modules if m.startswith('matplotlib')))\n"
        "sys.modules['matplotlib'] = None  # as if it were not installed\n"
        f"sys.exit(evdown_torch.cli.main(['show', {str(npy)!r}, '--factor', '2',\n"
        f"                                '--out', {str(tmp_path / 'x.gif')!r}]))"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=120, check=False)
    assert result.stdout.strip() == "[]"
    assert result.returncode == 2
    assert result.stderr.startswith("evdown show: error: plots need matplotlib")
    assert result.stderr.count("\n") == 1 and "pip install evdown_torch[plot]" in result.stderr


def test_a_file_in_seconds_warns_until_its_unit_is_given(tmp_path, rng, capsys):
    stream = random_stream(rng, 400, SENSOR, t_max=200_000)
    seconds = np.empty(400, [("x", "<i2"), ("y", "<i2"), ("t", "<f8"), ("p", "?")])
    for name in ("x", "y", "p"):
        seconds[name] = stream[name]
    seconds["t"] = stream["t"] / 1e6
    np.save(tmp_path / "s.npy", seconds)
    argv = ["show", str(tmp_path / "s.npy"), "--factor", "2", "--methods", "downsample",
            "--sensor-size", "16", "12", "2", "--out", str(tmp_path / "sheet.png")]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "evdown show: warning: " in err and "--window=50000 us exceed" in err
    assert "--time-unit s" in err
    assert main([*argv, "--time-unit", "s", "--windows", "2"]) == 0
    captured = capsys.readouterr()
    assert "warning" not in captured.err and "2 windows of 50 ms" in captured.out
    assert load_recording(str(tmp_path / "s.npy"), sensor_size=SENSOR,
                       time_unit="s").events.t.tolist() == pytest.approx(
                           np.sort(stream["t"]).astype(float).tolist())
