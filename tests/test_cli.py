"""The evdown command line on small files."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from evdown_torch import EventCount
from evdown_torch.cli import main
from tests.helpers import DVS_DTYPE, random_stream


@pytest.fixture
def npy(tmp_path, rng):
    path = tmp_path / "in.npy"
    np.save(path, random_stream(rng, 400, (16, 12, 2), t_max=2000))
    return path


def test_downscale_writes_the_transform_output(npy, tmp_path, capsys):
    out_path = tmp_path / "out.npy"
    code = main(["downscale", str(npy), str(out_path), "--method", "event_count",
                 "--factor", "2", "--threshold", "0.5", "--sensor-size", "16", "12", "2"])
    assert code == 0
    expected = EventCount((16, 12, 2), factor=2, threshold=0.5)(np.load(npy))
    np.testing.assert_array_equal(np.load(out_path), expected)
    printed = capsys.readouterr().out
    assert "400 events in" in printed and f"{len(expected)} events out" in printed


def test_factor_pair_and_inferred_sensor(npy, tmp_path):
    out_path = tmp_path / "out.npy"
    assert main(["downscale", str(npy), str(out_path), "--method", "downsample",
                 "--factor", "3,2"]) == 0
    out = np.load(out_path)
    assert out.dtype == DVS_DTYPE and len(out) == 400 and out["y"].max() < 6


def test_bad_method_is_rejected(npy, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["downscale", str(npy), str(tmp_path / "o.npy"), "--method", "nope",
              "--factor", "2"])
    assert exit_info.value.code == 2
    assert "invalid choice: 'nope'" in capsys.readouterr().err


def test_missing_file_and_bad_setting(tmp_path, npy, capsys):
    assert main(["downscale", str(tmp_path / "absent.npy"), str(tmp_path / "o.npy"),
                 "--method", "downsample", "--factor", "2"]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["downscale", str(npy), str(tmp_path / "o.npy"), "--method", "downsample",
                 "--factor", "2", "--threshold", "1"]) == 2
    assert "does not take setting" in capsys.readouterr().err
    assert main(["downscale", str(npy), str(tmp_path / "o.npy"), "--method", "downsample",
                 "--factor", "40"]) == 2
    assert "larger than the sensor" in capsys.readouterr().err


def test_module_entry_point(npy, tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "evdown_torch", "downscale", str(npy), str(tmp_path / "o.npy"),
         "--method", "funnelling", "--factor", "2"],
        capture_output=True, text=True, check=False,
    )
    assert result.returncode == 0, result.stderr
    assert "funnelling: 400 events in" in result.stdout
