"""The evdown command line on small files."""

from __future__ import annotations

import re
import subprocess
import sys
from dataclasses import fields

import numpy as np
import pytest

import evdown_torch
from evdown_torch import Downsample, EventCount, LIFPooling, LinearEstimation
from evdown_torch.cli import main
from evdown_torch.io import read_events
from evdown_torch.transforms.registry import METHODS, method_settings
from tests.helpers import DVS_DTYPE, random_stream, saved_stream

SENSOR = (16, 12, 2)


@pytest.fixture
def npy(tmp_path, rng):
    return saved_stream(tmp_path / "in.npy", rng, 400, SENSOR, t_max=2000)


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
        ([str(npy), str(npy / "o.npy")], "is a file"),
        ([str(npy), str(tmp_path / "missing-dir" / "o.csv")], "unknown extension '.csv'"),
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


def test_a_file_in_the_way_from_the_shell(npy, tmp_path):
    result = _run("downscale", str(npy), str(npy / "sub" / "o.npy"),
                  "--method", "downsample", "--factor", "2", "--sensor-size", "16", "12", "2")
    assert result.returncode == 2
    assert result.stderr.startswith("evdown downscale: error: ") and "is a file" in result.stderr
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


def test_missing_output_folders_are_made_alike_for_one_file_or_many(npy, tmp_path):
    argv = ["--method", "downsample", "--factor", "2", "--sensor-size", "16", "12", "2"]
    one = tmp_path / "new" / "deeper" / "o.npy"
    assert main(["downscale", str(npy), str(one), *argv]) == 0
    many = tmp_path / "new2" / "deeper"
    assert main(["downscale", str(npy), str(npy), str(many), *argv]) == 2  # same name twice
    assert not (tmp_path / "new2").exists()  # nothing made when the plan fails
    assert main(["downscale", str(npy), f"{many}/", *argv]) == 0
    expected = Downsample(SENSOR, 2)(np.load(npy))
    np.testing.assert_array_equal(np.load(one), expected)
    np.testing.assert_array_equal(np.load(many / "in.npy"), expected)


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
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "a.npy", "a.npy.json", "b.npy", "b.npy.json", "c.npy", "c.npy.json"]
    for name, events in expected.items():
        back = read_events(tmp_path / "out" / f"{name}.npy")  # the sidecar gives the size
        assert back.sensor_size == (8, 6, 2) and not back.guessed and back.time_unit is None
        assert [tuple(r) for r in back.events[["x", "y", "t"]]] == [
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
    assert sorted(p.name for p in (tmp_path / "made").iterdir()) == ["in.npy", "in.npy.json"]
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


@pytest.mark.slow
def test_module_entry_point(npy, tmp_path):
    result = _run("downscale", str(npy), str(tmp_path / "o.npy"), "--method", "funnelling",
                  "--factor", "2", "--sensor-size", "16", "12", "2")
    assert result.returncode == 0, result.stderr
    assert "funnelling: 400 events in" in result.stdout and result.stderr == ""
    assert _run("--version").stdout.strip() == f"evdown {evdown_torch.__version__}"


def test_time_unit_converts_to_microseconds_and_round_trips(tmp_path, rng):
    stream = random_stream(rng, 2000, SENSOR, t_max=200_000)  # microseconds, up to 0.2 s
    seconds = np.empty(2000, [("x", "<i2"), ("y", "<i2"), ("t", "<f8"), ("p", "?")])
    for name in ("x", "y", "p"):
        seconds[name] = stream[name]
    seconds["t"] = stream["t"] / 1e6
    np.save(tmp_path / "s.npy", seconds)
    out = tmp_path / "out.npy"
    argv = ["downscale", str(tmp_path / "s.npy"), str(out), "--method", "lif", "--factor", "2",
            "--sensor-size", "16", "12", "2"]
    assert main([*argv, "--time-unit", "s"]) == 0
    expected = LIFPooling(SENSOR, 2)(_as_microseconds(seconds))
    back = read_events(out)
    assert back.time_unit == "us" and back.sensor_size == (8, 6, 2) and not back.guessed
    np.testing.assert_array_equal(back.events, expected)
    assert len(expected) > 1 and np.unique(expected["t"]).size > 1  # steps of 1 ms, not one


def _as_microseconds(seconds: np.ndarray) -> np.ndarray:
    """An independent conversion: seconds times a million, as float64."""
    out = seconds.copy()
    out["t"] = seconds["t"] * 1_000_000.0
    return out


def test_seconds_read_as_microseconds_warn(tmp_path, rng, capsys):
    seconds = np.empty(400, [("x", "<i2"), ("y", "<i2"), ("t", "<f8"), ("p", "?")])
    seconds["x"], seconds["y"] = rng.integers(0, 16, 400), rng.integers(0, 12, 400)
    seconds["t"], seconds["p"] = np.sort(rng.random(400)) * 0.3, rng.random(400) < 0.5
    np.save(tmp_path / "s.npy", seconds)
    assert main(["downscale", str(tmp_path / "s.npy"), str(tmp_path / "o.npy"), "--method",
                 "lif", "--factor", "2", "--sensor-size", "16", "12", "2"]) == 0
    err = capsys.readouterr().err
    assert err.startswith("evdown downscale: warning: ") and err.count("\n") == 1
    assert "events/s" in err and "dt=1000 us, tau=10000 us exceed" in err
    assert "--time-unit s" in err
    assert read_events(tmp_path / "o.npy").time_unit is None  # unknown: none is claimed


def test_header_wins_over_sensor_size_and_columns_name_an_n_by_4_file(tmp_path, rng, capsys):
    stream = random_stream(rng, 300, (40, 30, 2), t_max=50_000)
    np.savez(tmp_path / "a.npz", events=stream, sensor_size=np.array([40, 30, 2]))
    plain = np.stack([stream["t"], stream["x"], stream["y"], stream["p"]], axis=1)
    np.save(tmp_path / "b.npy", plain)
    argv = ["--method", "downsample", "--factor", "2", "--sensor-size", "48", "32", "2",
            "--columns", "t,x,y,p", "--threads", "2"]
    assert main(["downscale", str(tmp_path / "a.npz"), str(tmp_path / "b.npy"),
                 str(tmp_path / "out"), *argv]) == 0
    assert read_events(tmp_path / "out" / "a.npy").sensor_size == (20, 15, 2)  # the header's
    assert read_events(tmp_path / "out" / "b.npy").sensor_size == (24, 16, 2)  # the flag's
    back = read_events(tmp_path / "out" / "b.npy").events
    np.testing.assert_array_equal(back, Downsample((48, 32, 2), 2)(
        read_events(tmp_path / "b.npy", sensor_size=(48, 32, 2), columns="t,x,y,p").events))
    assert "warning" not in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["downscale", str(tmp_path / "b.npy"), str(tmp_path / "o.npy"), "--method",
              "downsample", "--factor", "2", "--threads", "0"])
    assert "threads must be a positive integer" in capsys.readouterr().err


def test_each_subcommand_registers_itself_from_its_package_without_importing_the_cli():
    import ast
    import inspect

    from evdown_torch.cli import SUBCOMMANDS, build_parser

    names = []
    for module in SUBCOMMANDS:
        tree = ast.parse(inspect.getsource(module))
        imported = {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}
        imported |= {alias.name for node in ast.walk(tree) if isinstance(node, ast.Import)
                     for alias in node.names}
        assert "evdown_torch.cli" not in imported, module.__name__  # no cycle
        assert callable(module.add_command), module.__name__
        names.append(module.__name__)
    assert names == ["evdown_torch.downscale", "evdown_torch.data.command",
                     "evdown_torch.bench.command", "evdown_torch.evaluation.command",
                     "evdown_torch.plot.command"]
    choices = build_parser()._subparsers._group_actions[0].choices
    assert list(choices) == ["downscale", "preprocess", "bench", "evaluate", "show"]
