"""The evdown command line on small files."""

from __future__ import annotations

import re
import subprocess
import sys
from dataclasses import fields

import numpy as np
import pytest

import evdown_torch
from evdown_torch import Downsample, EventCount, LinearEstimation
from evdown_torch.cli import main
from evdown_torch.io import read_events
from evdown_torch.transforms.registry import METHODS, method_settings
from tests.helpers import DVS_DTYPE, random_stream

SENSOR = (16, 12, 2)


@pytest.fixture
def npy(tmp_path, rng):
    path = tmp_path / "in.npy"
    np.save(path, random_stream(rng, 400, SENSOR, t_max=2000))
    return path


def _run(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "evdown_torch", *argv], capture_output=True,
                          text=True, check=False)


def test_downscale_writes_the_transform_output(npy, tmp_path, capsys):
    out_path = tmp_path / "out.npy"
    code = main(["downscale", str(npy), str(out_path), "--method", "event_count",
                 "--factor", "2", "--set", "threshold=0.5", "--sensor-size", "16", "12", "2"])
    assert code == 0
    expected = EventCount(SENSOR, factor=2, threshold=0.5)(np.load(npy))
    np.testing.assert_array_equal(np.load(out_path), expected)
    captured = capsys.readouterr()
    assert "400 events in" in captured.out and f"{len(expected)} events out" in captured.out
    assert f"wrote {out_path}" in captured.out and captured.err == ""


def test_class_names_are_method_names_too(npy, tmp_path):
    for name in ("LinearEstimation", "linear", "linear-estimation"):
        out_path = tmp_path / f"{name}.npy"
        assert main(["downscale", str(npy), str(out_path), "--method", name, "--factor", "2",
                     "--sensor-size", "16", "12", "2"]) == 0
        np.testing.assert_array_equal(np.load(out_path),
                                      LinearEstimation(SENSOR, 2)(np.load(npy)))


def test_factor_pair_and_a_loudly_guessed_sensor(npy, tmp_path, capsys):
    out_path = tmp_path / "out.npy"
    assert main(["downscale", str(npy), str(out_path), "--method", "downsample",
                 "--factor", "3,2"]) == 0
    out = np.load(out_path)
    assert out.dtype == DVS_DTYPE and len(out) == 400 and out["y"].max() < 6
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("evdown downscale: warning: ")
    assert "guessed" in err[0] and "--sensor-size" in err[0]


def test_bad_method_is_rejected(npy, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["downscale", str(npy), str(tmp_path / "o.npy"), "--method", "nope",
              "--factor", "2"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "unknown method 'nope'" in err and "event_count (EventCount)" in err


def test_bad_inputs_give_one_line_and_exit_2(tmp_path, npy, capsys):
    cases = [
        ([str(tmp_path / "absent.npy"), str(tmp_path / "o.npy")], "does not exist"),
        ([str(npy), str(tmp_path / "o.npy"), "--set", "tau=3"], "does not take setting"),
        ([str(npy), str(tmp_path / "o.npy"), "--factor", "40"], "larger than the sensor"),
        ([str(npy), str(tmp_path / "missing-dir" / "o.npy")], "does not exist"),
        ([str(npy), str(tmp_path / "out_noext")], "unknown extension ''"),
        ([str(npy), str(tmp_path / "o.csv")], "unknown extension '.csv'"),
        ([str(npy), str(npy)], "would overwrite its input"),
        ([str(npy), str(tmp_path / "o.npy"), "--threshold", "0.5"], "--set threshold=T"),
        ([str(npy)], "give the input file(s)"),
    ]
    (tmp_path / "notes.txt").write_text("not events")
    cases.append(([str(tmp_path / "notes.txt"), str(tmp_path / "o.npy")], "unknown extension"))
    (tmp_path / "broken.npz").write_bytes(b"not a zip")
    cases.append(([str(tmp_path / "broken.npz"), str(tmp_path / "o.npy")], "cannot read"))
    for paths, message in cases:
        argv = ["downscale", *paths, "--method", "downsample", "--sensor-size", "16", "12", "2"]
        if "--factor" not in paths:
            argv += ["--factor", "2"]
        assert main(argv) == 2, paths
        err = capsys.readouterr().err
        assert err.startswith("evdown downscale: error: ") and message in err, (paths, err)
        assert err.count("\n") == 1, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.npz", "in.npy", "notes.txt"]


def test_missing_output_folder_from_the_shell(npy, tmp_path):
    result = _run("downscale", str(npy), str(tmp_path / "missing-dir" / "o.npy"),
                  "--method", "downsample", "--factor", "2")
    assert result.returncode == 2
    assert result.stderr.startswith("evdown downscale: error: ")
    assert "Traceback" not in result.stderr and result.stderr.count("\n") == 1


@pytest.mark.parametrize("name", ["empty.npy", "empty.npz"])
def test_an_empty_file_is_one_error_line(tmp_path, capsys, name):
    empty = tmp_path / name
    empty.write_bytes(b"")
    argv = ["downscale", str(empty), str(tmp_path / "o.npy"), "--method", "downsample",
            "--factor", "2", "--sensor-size", "16", "12", "2"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("evdown downscale: error: cannot read ") and name in err, err
    assert err.count("\n") == 1, err
    result = _run(*argv)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]


def test_several_files_and_a_folder(tmp_path, rng, capsys):
    inputs = tmp_path / "recordings"
    inputs.mkdir()
    streams = {name: random_stream(rng, 300, SENSOR, t_max=5000) for name in ("a", "b", "c")}
    np.save(inputs / "a.npy", streams["a"])
    np.save(inputs / "b.npy", streams["b"])
    s = streams["c"]
    np.savez(inputs / "c.npz", x=s["x"], y=s["y"], t=s["t"], p=s["p"],
             sensor_size=np.array(SENSOR))
    (inputs / "README.txt").write_text("not events")
    expected = {n: EventCount(SENSOR, 2, threshold=0.5)(v) for n, v in streams.items()}
    common = ["--method", "EventCount", "--factor", "2", "--set", "threshold=0.5",
              "--sensor-size", "16", "12", "2"]

    assert main(["downscale", str(inputs), str(tmp_path / "out"), *common]) == 0
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["a.npy", "b.npy", "c.npy"]
    for name, events in expected.items():
        got = np.load(tmp_path / "out" / f"{name}.npy")
        assert [tuple(r) for r in got[["x", "y", "t"]]] == [
            tuple(r) for r in events[["x", "y", "t"]]]
    assert capsys.readouterr().out.count("wrote ") == 3

    assert main(["downscale", str(inputs / "a.npy"), str(inputs / "b.npy"),
                 str(tmp_path / "two"), *common, "--output-format", "h5"]) == 0
    assert sorted(p.name for p in (tmp_path / "two").iterdir()) == ["a.h5", "b.h5"]
    back = read_events(tmp_path / "two" / "b.h5")
    np.testing.assert_array_equal(back.events, expected["b"])
    assert back.sensor_size == (8, 6, 2) and not back.guessed

    np.save(tmp_path / "a.npy", streams["a"])
    assert main(["downscale", str(inputs / "a.npy"), str(tmp_path / "a.npy"),
                 str(tmp_path / "clash"), *common]) == 2
    assert "would both be written" in capsys.readouterr().err


def test_a_trailing_slash_names_an_output_folder(npy, tmp_path):
    argv = ["--method", "downsample", "--factor", "2", "--sensor-size", "16", "12", "2"]
    assert main(["downscale", str(npy), f"{tmp_path / 'made'}/", *argv]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "made" / "in.npy"),
                                  Downsample(SENSOR, 2)(np.load(npy)))
    assert [p.name for p in (tmp_path / "made").iterdir()] == ["in.npy"]
    assert main(["downscale", str(npy), f"{npy}/", *argv]) == 2


def test_version_and_help_list_every_setting_with_defaults(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.strip() == f"evdown {evdown_torch.__version__}"
    with pytest.raises(SystemExit):
        main(["downscale", "--help"])
    text = capsys.readouterr().out
    assert "event_count, EventCount: threshold=1.0" in text
    assert "downsample, Downsample: no settings" in text
    methods = text[text.index("methods (--method"):]
    entries = {e.split(":")[0]: " ".join(e.split())
               for e in re.split(r"\n  (?=\w+, \w+: )", methods)[1:]}
    assert len(entries) == len(METHODS)
    for name, cls in METHODS.items():
        entry = entries[f"{name}, {cls.__name__}"]
        for field in fields(cls):
            if field.name in method_settings(name):
                assert f"{field.name}={field.default!r}" in entry, (name, field.name)


def test_module_entry_point(npy, tmp_path):
    result = _run("downscale", str(npy), str(tmp_path / "o.npy"), "--method", "funnelling",
                  "--factor", "2", "--sensor-size", "16", "12", "2")
    assert result.returncode == 0, result.stderr
    assert "funnelling: 400 events in" in result.stdout and result.stderr == ""
    assert _run("--version").stdout.strip() == f"evdown {evdown_torch.__version__}"
