"""The file readers and writers on small files the tests write, and the real N-MNIST sample."""

from __future__ import annotations

import contextlib
import importlib.util
import json
import struct
import sys
import warnings

import numpy as np
import pytest

from evdown_torch.events import DVS_DTYPE
from evdown_torch.io import (
    READ_EXTENSIONS,
    SensorSizeGuessWarning,
    event_files,
    read_events,
    write_events,
)
from tests.conftest import NMNIST_FILE
from tests.helpers import random_stream


@pytest.fixture
def stream(rng) -> np.ndarray:
    return random_stream(rng, 300, (40, 30, 2), t_max=50_000)


@contextlib.contextmanager
def _no_guess_warning():
    """Fail if the sensor size is guessed."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", SensorSizeGuessWarning)
        yield


def _values(events: np.ndarray) -> list[tuple]:
    """Events as (x, y, t, on) tuples in file order, whatever the dtype."""
    return list(zip(events["x"].tolist(), events["y"].tolist(), events["t"].tolist(),
                    (events["p"] > 0).tolist()))


# ----------------------------------------------------------------------------- AEDAT4 fixture
# A minimal AEDAT4 file (the format's documented layout: magic line, a size-prefixed
# flatbuffer IOHeader whose XML names each stream and its sizeX/sizeY, then packets of
# stream id, size and a size-prefixed EventPacket flatbuffer of 16-byte Event structs).

_AEDAT4_EVENT = np.dtype({"names": ["t", "x", "y", "on"], "formats": ["<i8", "<i2", "<i2", "?"],
                          "offsets": [0, 8, 10, 12], "itemsize": 16})


def _flatbuffer(identifier: bytes, slot: int, payload: bytes, align: int) -> bytes:
    """A size-prefixed flatbuffer: one table whose field ``slot`` points to ``payload``."""
    buf = bytearray(12)  # size prefix, root offset, file identifier
    vtable_at = len(buf)
    buf += struct.pack("<HH", 4 + 2 * (slot + 1), 8) + b"\0\0" * slot + struct.pack("<H", 4)
    while len(buf) % 4:
        buf += b"\0"
    table_at = len(buf)
    buf += struct.pack("<i", table_at - vtable_at)
    field_at = len(buf)
    buf += bytes(4)
    while (len(buf) + 4) % align:  # the vector's elements follow its 4-byte length
        buf += b"\0"
    struct.pack_into("<I", buf, field_at, len(buf) - field_at)
    buf += payload
    while len(buf) % 8:
        buf += b"\0"
    struct.pack_into("<I", buf, 4, table_at - 4)
    buf[8:12] = identifier
    struct.pack_into("<I", buf, 0, len(buf) - 4)
    return bytes(buf)


def write_aedat4(path, events: np.ndarray, width: int, height: int, packets: int = 3) -> None:
    xml = (
        '<dv version="2.0"><node name="outInfo" path="/outInfo/"><node name="0" path="/outInfo/0/">'
        '<attr key="typeIdentifier" type="string">EVTS</attr>'
        '<node name="info" path="/outInfo/0/info/">'
        f'<attr key="sizeX" type="int">{width}</attr><attr key="sizeY" type="int">{height}</attr>'
        "</node></node></node></dv>"
    ).encode()
    header = _flatbuffer(b"IOHE", 2, struct.pack("<I", len(xml)) + xml + b"\0", 4)
    out = b"#!AER-DAT4.0\r\n" + header
    for part in np.array_split(events, packets):
        records = np.zeros(len(part), _AEDAT4_EVENT)
        records["t"], records["x"], records["y"], records["on"] = (
            part["t"], part["x"], part["y"], part["p"] > 0)
        body = _flatbuffer(b"EVTS", 0, struct.pack("<I", len(records)) + records.tobytes(), 8)
        out += struct.pack("<II", 0, len(body)) + body
    path.write_bytes(out)


def test_aedat4_events_and_the_header_sensor_size(tmp_path, rng):
    pytest.importorskip("tonic")
    pytest.importorskip("aedat")
    events = random_stream(rng, 200, (320, 240, 2), t_max=10**6)
    path = tmp_path / "davis.aedat4"
    write_aedat4(path, events, 320, 240)
    with _no_guess_warning():
        got, size, guessed = read_events(path)
    assert size == (320, 240, 2) and not guessed
    assert got.dtype == DVS_DTYPE and _values(got) == _values(events)


# ----------------------------------------------------------------------------- each reader


def test_nmnist_bin_matches_tonic_and_guesses_the_nmnist_sensor_loudly():
    tonic = pytest.importorskip("tonic")
    if not NMNIST_FILE.exists():
        pytest.skip(f"{NMNIST_FILE} is absent")
    reference = tonic.io.read_mnist_file(str(NMNIST_FILE), dtype=tonic.datasets.NMNIST.dtype)
    with pytest.warns(SensorSizeGuessWarning, match=r"guessed \(34, 34, 2\).*N-MNIST"):
        events, size, guessed = read_events(NMNIST_FILE)
    assert len(events) == 4325 and size == (34, 34, 2) and guessed
    assert _values(events) == _values(reference)
    with _no_guess_warning():
        assert read_events(NMNIST_FILE, sensor_size=(40, 40, 2)).sensor_size == (40, 40, 2)


# Prophesee files written word by word from the formats' documentation (EVT 3.0: 16-bit words
# TIME_HIGH 0x8, TIME_LOW 0x6, ADDR_Y 0x0, ADDR_X 0x2 with the polarity in bit 11; EVT 2.0:
# 32-bit words, TIME_HIGH 0x8 with t >> 6, CD_OFF 0x0 / CD_ON 0x1 with t & 63, x, y; DAT: a
# type/size byte pair, then per event a 32-bit t and a word with x, y and p in bits 0, 14, 28).


def _evt3(events: np.ndarray) -> bytes:
    """As a camera writes it: a TIME_HIGH word for every 4096 us period, then the events."""
    words, high = [], -1
    for t, x, y, p in _rows(events):
        while high < t >> 12:
            high += 1
            words.append(0x8000 | high & 0xFFF)
        words += [0x6000 | t & 0xFFF, y, 0x2000 | p << 11 | x]
    return np.array(words, "<u2").tobytes()


def _rows(events: np.ndarray) -> list[tuple[int, int, int, int]]:
    return list(zip(*(events[f].astype(np.int64).tolist() for f in ("t", "x", "y", "p"))))


def _evt2(events: np.ndarray) -> bytes:
    t, x, y, p = (events[f].astype(np.int64) for f in ("t", "x", "y", "p"))
    words = np.stack([0x8 << 28 | t >> 6, (p > 0).astype(np.int64) << 28 | (t & 63) << 22
                      | x << 11 | y], axis=1)
    return words.astype("<u4").tobytes()


def _dat(events: np.ndarray) -> bytes:
    t, x, y, p = (events[f].astype(np.int64) for f in ("t", "x", "y", "p"))
    words = np.stack([t, x | y << 14 | (p > 0).astype(np.int64) << 28], axis=1)
    return bytes([0x0C, 8]) + words.astype("<u4").tobytes()


@pytest.mark.parametrize(
    ("suffix", "header", "encode", "recorded"),
    [
        (".raw", "% evt 3.0\n% geometry 640x480\n% end\n", _evt3, (640, 480, 2)),
        (".raw", "% format EVT3;height=720;width=1280\n% end\n", _evt3, (1280, 720, 2)),
        (".raw", "% evt 2.0\n% end\n", _evt2, None),
        (".dat", "% Data file containing CD events\n% Version 2\n% Width 640\n% Height 480\n",
         _dat, (640, 480, 2)),
        (".dat", "% Data file containing CD events\n", _dat, None),
    ],
)
def test_prophesee_files(tmp_path, rng, suffix, header, encode, recorded):
    pytest.importorskip("faery")
    events = random_stream(rng, 150, (640, 480, 2), t_max=10**6)
    path = tmp_path / f"rec{suffix}"
    path.write_bytes(header.encode() + encode(events))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got, size, guessed = read_events(path)
    assert _values(got) == _values(events)
    if recorded is None:  # no geometry in the header: guessed, loudly
        assert guessed and size == (int(events["x"].max()) + 1, int(events["y"].max()) + 1, 2)
        assert [w.category for w in caught] == [SensorSizeGuessWarning]
    else:
        assert not guessed and size == recorded and not caught


def test_prophesee_raw_of_an_unknown_format_is_refused(tmp_path):
    pytest.importorskip("faery")
    path = tmp_path / "rec.raw"
    path.write_bytes(b"% evt 9.9\n% geometry 640x480\n% end\n" + bytes(16))
    with pytest.raises(ValueError, match="cannot read .* as a Prophesee file"):
        read_events(path)


def test_npz_columns_and_structured(tmp_path, stream):
    columns = tmp_path / "columns.npz"
    np.savez(columns, x=stream["x"], y=stream["y"], t=stream["t"], p=stream["p"],
             sensor_size=np.array([40, 30, 2]))
    events, size, guessed = read_events(columns)
    assert _values(events) == _values(stream) and size == (40, 30, 2) and not guessed
    structured = tmp_path / "structured.npz"
    np.savez(structured, events=stream)
    with pytest.warns(SensorSizeGuessWarning, match="largest coordinates"):
        events, size, guessed = read_events(structured)
    assert events.dtype == stream.dtype and np.array_equal(events, stream) and guessed
    other = tmp_path / "other.npz"
    np.savez(other, a=np.arange(3))
    with pytest.raises(ValueError, match="expected arrays x, y, t, p"):
        read_events(other)


def test_hdf5_layouts(tmp_path, stream):
    h5py = pytest.importorskip("h5py")
    compound = tmp_path / "compound.h5"
    with h5py.File(compound, "w") as file:
        file.create_dataset("events", data=stream)
        file["events"].attrs["width"], file["events"].attrs["height"] = 64, 48
    events, size, _ = read_events(compound)
    assert _values(events) == _values(stream) and size == (64, 48, 2)
    flat = tmp_path / "flat.hdf5"
    with h5py.File(flat, "w") as file:
        for name in "xytp":
            file.create_dataset(name, data=stream[name].astype(np.int32))
    with pytest.warns(SensorSizeGuessWarning):
        assert _values(read_events(flat).events) == _values(stream)
    empty = tmp_path / "nothing.h5"
    h5py.File(empty, "w").close()
    with pytest.raises(ValueError, match="expected datasets events/x"):
        read_events(empty)


# ----------------------------------------------------------------------------- writers


@pytest.mark.parametrize("suffix", [".npy", ".h5", ".hdf5"])
def test_round_trip_through_each_writer(tmp_path, stream, suffix):
    if suffix != ".npy":
        pytest.importorskip("h5py")
    path = write_events(tmp_path / f"out{suffix}", stream, sensor_size=(40, 30, 2))
    assert path == tmp_path / f"out{suffix}" and path.is_file()
    if suffix == ".npy":
        events, size, guessed = read_events(path, sensor_size=(40, 30, 2))
    else:
        events, size, guessed = read_events(path)
    assert events.dtype == stream.dtype and np.array_equal(events, stream)
    assert size == (40, 30, 2) and not guessed


def test_write_refuses_what_it_cannot_write_exactly(tmp_path, stream):
    with pytest.raises(ValueError, match="unknown extension ''"):
        write_events(tmp_path / "out_noext", stream)
    with pytest.raises(ValueError, match="folder .* does not exist"):
        write_events(tmp_path / "missing" / "o.npy", stream)
    with pytest.raises(TypeError, match="structured array"):
        write_events(tmp_path / "o.npy", np.zeros((3, 4)))
    assert sorted(p.name for p in tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- sensor and errors


def test_sensor_size_given_recorded_and_checked(tmp_path, stream):
    path = write_events(tmp_path / "s.npy", stream)
    with _no_guess_warning():
        assert read_events(path, sensor_size=(50, 50, 2)).sensor_size == (50, 50, 2)
    with pytest.raises(ValueError, match="outside the sensor size .* given"):
        read_events(path, sensor_size=(10, 10, 2))
    empty = write_events(tmp_path / "e.npy", stream[:0])
    with pytest.raises(ValueError, match="holds no events"):
        read_events(empty)
    assert len(read_events(empty, sensor_size=(4, 4, 2)).events) == 0


def test_bad_paths_and_extensions(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        read_events(tmp_path / "absent.npy")
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(ValueError, match=r"unknown extension '.txt'; readable: \.npy"):
        read_events(tmp_path / "notes.txt")
    (tmp_path / "broken.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="cannot read .* as a .npz archive"):
        read_events(tmp_path / "broken.npz")


def test_empty_and_truncated_numpy_files_are_value_errors(tmp_path, stream):
    """A 0-byte .npy/.npz or a cut-off .npz archive is unreadable input, not an EOFError."""
    (tmp_path / "empty.npy").write_bytes(b"")
    (tmp_path / "empty.npz").write_bytes(b"")
    np.savez(tmp_path / "whole.npz", x=stream["x"], y=stream["y"], t=stream["t"], p=stream["p"])
    (tmp_path / "cut.npz").write_bytes((tmp_path / "whole.npz").read_bytes()[:-40])
    with pytest.raises(ValueError, match=r"cannot read .*empty\.npy.* as a \.npy array"):
        read_events(tmp_path / "empty.npy", sensor_size=(4, 4, 2))
    for name in ("empty.npz", "cut.npz"):
        with pytest.raises(ValueError, match=rf"cannot read .*{name}.* as a \.npz archive"):
            read_events(tmp_path / name, sensor_size=(4, 4, 2))


def test_missing_optional_reader_names_the_extra(tmp_path, monkeypatch):
    (tmp_path / "rec.raw").write_bytes(b"% evt 3.0\n")
    monkeypatch.setitem(sys.modules, "faery", None)  # as if not installed
    with pytest.raises(ImportError, match=r"'faery'.*pip install 'evdown_torch\[readers\]'"):
        read_events(tmp_path / "rec.raw")


def test_event_files_lists_readable_files(tmp_path, stream):
    for name in ("b.npy", "a.NPZ", "c.txt"):
        (tmp_path / name).write_bytes(b"")
    (tmp_path / "sub.npy").mkdir()
    assert [p.name for p in event_files(tmp_path)] == ["a.NPZ", "b.npy"]
    assert ".aedat4" in READ_EXTENSIONS
    with pytest.raises(ValueError, match="not a folder"):
        event_files(tmp_path / "b.npy")


# ----------------------------------------------------------------------------- time units, metadata


def test_each_reader_reports_its_time_unit(tmp_path, stream, rng):
    columns = tmp_path / "c.npz"
    np.savez(columns, x=stream["x"], y=stream["y"], t=stream["t"], p=stream["p"],
             sensor_size=np.array([40, 30, 2]), time_unit=np.array("ms"))
    assert read_events(columns).time_unit == "ms"
    np.savez(columns, events=stream, sensor_size=np.array([40, 30, 2]))
    assert read_events(columns).time_unit is None  # the file does not say
    np.savez(columns, events=stream, sensor_size=np.array([40, 30, 2]), time_unit=np.array("h"))
    with pytest.raises(ValueError, match="stored time unit must be one of s, ms, us, ns"):
        read_events(columns)
    if NMNIST_FILE.exists() and importlib.util.find_spec("tonic"):
        with pytest.warns(SensorSizeGuessWarning):
            assert read_events(NMNIST_FILE).time_unit == "us"  # N-MNIST's format
    pytest.importorskip("h5py")
    path = write_events(tmp_path / "o.h5", stream, sensor_size=(40, 30, 2), time_unit="us")
    assert read_events(path).time_unit == "us"


def test_npy_sidecar_round_trips_and_a_stale_one_is_removed(tmp_path, stream):
    path = write_events(tmp_path / "o.npy", stream, sensor_size=(40, 30, 2), time_unit="ns")
    meta = tmp_path / "o.npy.json"
    assert json.loads(meta.read_text()) == {"sensor_size": [40, 30, 2], "time_unit": "ns"}
    with _no_guess_warning():
        back = read_events(path, sensor_size=(99, 99, 2))  # the file's own size wins
    assert back.sensor_size == (40, 30, 2) and back.time_unit == "ns" and not back.guessed
    assert np.array_equal(back.events, stream)
    assert back._replace(guessed=True).time_unit == "ns" and "time_unit='ns'" in repr(back)
    write_events(path, stream)  # no metadata now: the old sidecar would lie
    assert not meta.exists()
    meta.write_text("[1, 2")
    with pytest.raises(ValueError, match="cannot read .*o.npy.json.*sidecar"):
        read_events(path)
    meta.write_text('{"sensor_size": [10, 10, 2]}')
    with pytest.raises(ValueError, match="outside the sensor size .* recorded in the file"):
        read_events(path)


def test_recorded_sensor_size_wins_over_the_given_one(tmp_path, stream):
    columns = tmp_path / "c.npz"
    np.savez(columns, events=stream, sensor_size=np.array([40, 30, 2]))
    assert read_events(columns, sensor_size=(64, 64, 2)).sensor_size == (40, 30, 2)


def test_npy_of_n_by_4_columns(tmp_path, stream):
    plain = np.stack([stream["t"], stream["x"], stream["y"], stream["p"]], axis=1)
    path = tmp_path / "plain.npy"
    np.save(path, plain.astype(np.float64))
    events, size, _ = read_events(path, sensor_size=(40, 30, 2), columns="t,x,y,p")
    assert _values(events) == _values(stream) and events["t"].dtype == np.float64
    np.save(path, plain[:, [1, 2, 0, 3]])  # x, y, t, p: the default order
    assert _values(read_events(path, sensor_size=(40, 30, 2)).events) == _values(stream)
    for bad in ("x,y,t", "x,y,t,t", ["x", "y", "t", "q"], 4):
        with pytest.raises(ValueError, match="columns must name x, y, t and p once each"):
            read_events(path, sensor_size=(40, 30, 2), columns=bad)
    np.save(path, plain[:, :3])
    with pytest.raises(ValueError, match=r"or an \(N, 4\) array of columns"):
        read_events(path, sensor_size=(40, 30, 2))
