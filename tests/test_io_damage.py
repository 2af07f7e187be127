"""Damaged files, odd metadata and failed writes: one ValueError naming the file, never a
traceback from a decoder, and nothing the user had is lost."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from evdown_torch.cli import main
from evdown_torch.io import read_events, sidecar, write_events
from tests.helpers import random_stream
from tests.test_io import write_aedat4

SENSOR = (64, 64, 2)


@pytest.fixture
def stream(rng) -> np.ndarray:
    return random_stream(rng, 200, SENSOR, t_max=10_000)


def _one_error_line(capsys, *needles: str) -> str:
    err = capsys.readouterr().err
    assert err.startswith("evdown downscale: error: ") and err.count("\n") == 1, err
    for needle in needles:
        assert needle in err, err
    return err


def _downscale(source, target) -> int:
    return main(["downscale", str(source), str(target), "--method", "downsample",
                 "--factor", "2", "--sensor-size", *map(str, SENSOR)])


# ----------------------------------------------------------------------------- AEDAT4


def _aedat4_header(path, stream) -> bytes:
    """The magic line and the header of an AEDAT4 file the tests write, no packet after it."""
    write_aedat4(path, stream, *SENSOR[:2], packets=1)
    data = path.read_bytes()
    header_size = struct.unpack("<I", data[14:18])[0]
    return data[:18 + header_size]


@pytest.mark.parametrize("tail", [bytes(8), bytes(100), struct.pack("<iI", 0, 11) + bytes(11)])
def test_an_aedat4_packet_too_short_to_decode_is_a_value_error(tmp_path, stream, tail, capsys):
    pytest.importorskip("tonic")
    pytest.importorskip("aedat")
    path = tmp_path / "damaged.aedat4"
    path.write_bytes(_aedat4_header(tmp_path / "whole.aedat4", stream) + tail)
    with pytest.raises(ValueError, match=r"cannot read .*damaged\.aedat4.* as AEDAT4: the "
                                         r"packet at byte \d+ holds \d+ bytes"):
        read_events(path)
    assert _downscale(path, tmp_path / "out.npy") == 2
    _one_error_line(capsys, "damaged.aedat4", "AEDAT4")
    assert not (tmp_path / "out.npy").exists()


def test_a_panic_in_a_native_decoder_becomes_a_value_error(tmp_path, stream, monkeypatch):
    aedat = pytest.importorskip("aedat")
    pytest.importorskip("tonic")

    class PanicException(BaseException):  # what pyo3 raises for a Rust panic
        pass

    class Panicking:
        def __init__(self, path: str) -> None:
            raise PanicException("assertion failed: data.len() >= SIZE_SIZEPREFIX")

    path = tmp_path / "rec.aedat4"
    write_aedat4(path, stream, *SENSOR[:2])
    monkeypatch.setattr(aedat, "Decoder", Panicking)
    with pytest.raises(ValueError, match="cannot read .*rec.aedat4.* as AEDAT4: assertion"):
        read_events(path)

    class Interrupting:
        def __init__(self, path: str) -> None:
            raise KeyboardInterrupt

    monkeypatch.setattr(aedat, "Decoder", Interrupting)
    with pytest.raises(KeyboardInterrupt):  # the user's interrupt is not a damaged file
        read_events(path)


# ----------------------------------------------------------------------------- HDF5


def test_a_damaged_hdf5_file_is_a_value_error_wherever_the_damage_lies(tmp_path, stream):
    pytest.importorskip("h5py")
    whole = write_events(tmp_path / "whole.h5", stream[:50], sensor_size=SENSOR).read_bytes()
    raised = 0
    for start in range(0, len(whole) - 400, len(whole) // 40):
        damaged = bytearray(whole)
        damaged[start:start + 400] = bytes(b ^ 0xFF for b in damaged[start:start + 400])
        path = tmp_path / "damaged.h5"
        path.write_bytes(bytes(damaged))
        try:
            read_events(path)  # damage inside the data reads back as other values
        except ValueError as error:
            assert "damaged.h5" in str(error)
            raised += 1
    assert raised > 5


def test_hdf5_errors_of_every_kind_name_the_file(tmp_path, stream, monkeypatch, capsys):
    h5py = pytest.importorskip("h5py")
    path = write_events(tmp_path / "rec.h5", stream, sensor_size=SENSOR)
    for error in (RuntimeError("Link iteration failed (bad local heap signature)"),
                  KeyError("Unable to synchronously open object (bad object header)"),
                  OSError("Unable to synchronously open file (truncated file)")):
        def broken(*args, error=error, **kwargs):
            raise error

        monkeypatch.setattr(h5py, "File", broken)
        with pytest.raises(ValueError, match=r"cannot read .*rec\.h5.* as HDF5"):
            read_events(path)
        assert _downscale(path, tmp_path / "out.npy") == 2
        _one_error_line(capsys, "rec.h5", "as HDF5")


# ----------------------------------------------------------------------------- metadata


def _hdf5_with(path, stream, **attrs):
    import h5py

    with h5py.File(path, "w") as file:
        group = file.create_group("events")
        for name in "xytp":
            group.create_dataset(name, data=stream[name])
        for key, value in attrs.items():
            file.attrs[key] = value
    return path


def _npy_with(path, stream, meta: dict):
    np.save(path, stream)
    sidecar(path).write_text(json.dumps(meta))
    return path


BAD_SIZES = [
    ({"width": [64, 64], "height": 64}, "stored width must be one positive integer, got"),
    ({"width": "abc", "height": 64}, r"stored width must be one positive integer, got 'abc'"),
    ({"width": 64.7, "height": 64}, r"stored width must be one positive integer, got 64\.7"),
    ({"width": 64, "height": 0}, r"stored height must be one positive integer, got 0"),
]


@pytest.mark.parametrize(("attrs", "message"), BAD_SIZES)
def test_hdf5_width_and_height_are_checked_as_sensor_size_is(tmp_path, stream, attrs, message):
    pytest.importorskip("h5py")
    path = _hdf5_with(tmp_path / "rec.h5", stream, **attrs)
    with pytest.raises(ValueError, match=rf"rec\.h5: {message}"):
        read_events(path)


@pytest.mark.parametrize(("meta", "message"), [
    *BAD_SIZES,
    ({"width": None, "height": 64}, "stored width must be one positive integer, got None"),
    ({"width": [64, 2], "height": 64}, r"stored width must be one positive integer, got \[64, 2\]"),
    ({"width": True, "height": 64}, "stored width must be one positive integer, got True"),
])
def test_sidecar_width_and_height_are_checked_as_sensor_size_is(tmp_path, stream, meta,
                                                                 message):
    path = _npy_with(tmp_path / "rec.npy", stream, meta)
    with pytest.raises(ValueError, match=rf"rec\.npy\.json: {message}"):
        read_events(path)


def test_good_width_and_height_attributes_still_read(tmp_path, stream):
    pytest.importorskip("h5py")
    for width in (64, np.int32(64), np.array([64])):
        path = _hdf5_with(tmp_path / "rec.h5", stream, width=width, height=np.uint16(64))
        assert read_events(path).sensor_size == SENSOR
    assert read_events(_npy_with(tmp_path / "rec.npy", stream, {"width": 64, "height": 64})
                       ).sensor_size == SENSOR


def test_a_time_unit_attribute_holding_several_names_is_refused(tmp_path, stream):
    pytest.importorskip("h5py")
    path = _hdf5_with(tmp_path / "rec.h5", stream, sensor_size=np.array(SENSOR),
                      time_unit=np.array(["us", "ms"], dtype="S2"))
    with pytest.raises(ValueError, match=r"rec\.h5: stored time_unit must be one unit name"):
        read_events(path)
    path = _hdf5_with(tmp_path / "one.h5", stream, sensor_size=np.array(SENSOR),
                      time_unit=np.array(["ms"], dtype="S2"))
    assert read_events(path).time_unit == "ms"  # one name in an array of one is fine


# ----------------------------------------------------------------------------- writing


def test_a_failed_sidecar_leaves_the_old_file_and_its_sidecar(tmp_path, stream, monkeypatch):
    path = write_events(tmp_path / "out.npy", stream[:10], sensor_size=SENSOR, time_unit="us")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    import evdown_torch.io as io

    real = io.json.dumps

    def failing(*args, **kwargs):
        real(*args, **kwargs)
        raise OSError("No space left on device")

    monkeypatch.setattr(io.json, "dumps", failing)
    with pytest.raises(OSError, match="No space left"):
        write_events(path, stream, sensor_size=SENSOR, time_unit="us")
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before  # no temporaries


def test_a_sidecar_path_in_the_way_keeps_the_old_output(tmp_path, stream, capsys):
    source = write_events(tmp_path / "good.npy", stream, sensor_size=SENSOR, time_unit="us")
    out = tmp_path / "out.npy"
    np.save(out, stream[:3])
    old = out.read_bytes()
    sidecar(out).mkdir()  # the sidecar cannot be written there
    with pytest.raises(ValueError, match=r"cannot write .*out\.npy.*sidecar .*is a folder"):
        write_events(out, stream, sensor_size=SENSOR, time_unit="us")
    assert _downscale(source, out) == 2
    _one_error_line(capsys, "out.npy.json")
    assert out.read_bytes() == old  # the user's file is untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["good.npy", "good.npy.json",
                                                           "out.npy", "out.npy.json"]


@pytest.mark.parametrize("suffix", [".npy", ".h5"])
def test_a_write_that_fails_midway_keeps_the_old_file(tmp_path, stream, monkeypatch, suffix):
    if suffix == ".h5":
        pytest.importorskip("h5py")
    path = write_events(tmp_path / f"out{suffix}", stream[:10], sensor_size=SENSOR)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    bad = stream.astype([("x", "<i2"), ("y", "<i2"), ("p", "?"), ("t", "O")])  # cannot save
    with pytest.raises((ValueError, TypeError)):
        write_events(path, bad, sensor_size=SENSOR)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
