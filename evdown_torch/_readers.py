"""The readers behind :func:`evdown_torch.io.read_events`, one per format (see its table).

Each takes the path and returns a :class:`Read`: the events as a structured array with fields
``x``, ``y``, ``t``, ``p``, the sensor size and time unit the file records (if it does), and a
better guess of the sensor size than the largest coordinates (N-MNIST's). Decoding is done by
maintained packages (NumPy, h5py, Tonic with aedat, faery), imported when a format needs them.
"""

from __future__ import annotations

import importlib
import json
import os
import zipfile
from collections.abc import Callable
from functools import partial
from pathlib import Path
from types import ModuleType
from typing import Any, NamedTuple

import numpy as np

from evdown_torch.checks import check_sensor_size
from evdown_torch.events import DVS_DTYPE, FIELDS
from evdown_torch.time_units import check_unit_name

#: The optional dependency group that installs every reader.
READERS_EXTRA = "readers"

#: N-MNIST's ATIS sensor crop, the usual content of a ``.bin`` file.
NMNIST_SENSOR = (34, 34, 2)

_INT16_MAX = int(np.iinfo(np.int16).max)


def require(module: str, extension: str, doing: str = "reading") -> ModuleType:
    try:
        return importlib.import_module(module)
    except ImportError:
        raise ImportError(
            f"{doing} {extension} files needs the optional package {module!r}: "
            f"pip install 'evdown_torch[{READERS_EXTRA}]'"
        ) from None


# ----------------------------------------------------------------------------- columns


def _columns(x: Any, y: Any, t: Any, p: Any, source: str) -> np.ndarray:
    """A DVS_DTYPE-like structured array from four columns, after checking their values."""
    x, y, t, p = (np.asarray(c).reshape(-1) for c in (x, y, t, p))
    if not len(x) == len(y) == len(t) == len(p):
        raise ValueError(
            f"{source}: columns x, y, t, p differ in length ({len(x)}, {len(y)}, {len(t)}, "
            f"{len(p)})"
        )
    for name, column in (("x", x), ("y", y)):
        if not np.issubdtype(column.dtype, np.integer):
            raise ValueError(f"{source}: coordinate {name} must be integers, got {column.dtype}")
        if len(column) and (int(column.min()) < 0 or int(column.max()) > _INT16_MAX):
            raise ValueError(
                f"{source}: coordinate {name} must lie in [0, {_INT16_MAX}], got values from "
                f"{int(column.min())} to {int(column.max())}"
            )
    t_dtype: type[np.number]
    if np.issubdtype(t.dtype, np.floating):
        t_dtype = np.float64
    elif np.issubdtype(t.dtype, np.integer):
        if len(t) and t.dtype == np.uint64 and int(t.max()) > np.iinfo(np.int64).max:
            raise ValueError(f"{source}: timestamps beyond the int64 range")
        t_dtype = np.int64
    else:
        raise ValueError(f"{source}: timestamps t must be integers or floats, got {t.dtype}")
    if p.dtype != np.bool_:
        if not np.issubdtype(p.dtype, np.number):
            raise ValueError(f"{source}: polarity p must be bool or numbers, got {p.dtype}")
        if not (np.isin(p, (0, 1)).all() or np.isin(p, (-1, 1)).all()):
            raise ValueError(f"{source}: polarity p must take two values, 0/1 or -1/+1")
        p = p > 0
    out = np.empty(len(x), dtype=np.dtype([*DVS_DTYPE.descr[:3], ("t", t_dtype)]))
    out["x"], out["y"], out["p"], out["t"] = x, y, p, t
    return out


def _one_value(attrs: Any, name: str) -> Any:
    """Attribute ``name`` as one Python value (bytes decoded), or the list it holds."""
    value = attrs[name]
    if isinstance(value, (np.ndarray, np.generic)):
        value = value.reshape(-1).tolist() if value.size != 1 else value.reshape(-1)[0].item()
    return value.decode() if isinstance(value, bytes) else value


def _time_unit_attribute(attrs: Any, source: str) -> str | None:
    """A ``time_unit`` attribute or array, if present."""
    if "time_unit" not in attrs:
        return None
    value = _one_value(attrs, "time_unit")
    if isinstance(value, list):
        raise ValueError(f"{source}: stored time_unit must be one unit name, got {value!r}")
    try:
        return check_unit_name(value)
    except ValueError as error:
        raise ValueError(f"{source}: stored {error}") from None


def _sensor_attribute(attrs: Any, source: str) -> tuple[int, int, int] | None:
    """``sensor_size`` (W, H, P) or ``width``/``height`` attributes, if present.

    Checked as a ``sensor_size`` argument is: whole numbers (not bools, floats or text).
    """
    if "sensor_size" in attrs:
        value = np.asarray(attrs["sensor_size"]).reshape(-1).tolist()
        try:
            return check_sensor_size(value)
        except (TypeError, ValueError) as error:
            raise ValueError(f"{source}: stored sensor_size is not valid: {error}") from None
    if "width" in attrs and "height" in attrs:
        sides = []
        for name in ("width", "height"):
            value = _one_value(attrs, name)
            if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
                raise ValueError(
                    f"{source}: stored {name} must be one positive integer, got {value!r}")
            sides.append(value)
        return check_sensor_size((*sides, 2))
    return None


# ----------------------------------------------------------------------------- readers
# Each takes the path and returns a Read.


class Read(NamedTuple):
    events: np.ndarray
    recorded: tuple[int, int, int] | None  # the sensor size the file records
    guess: tuple[int, int, int] | None  # a better guess than the largest coordinates
    time_unit: str | None = None  # the one the format or the file states
    # What an error about the coordinates adds (another column order?), made only then.
    hint: Callable[[], str] | None = None


def sidecar(path: str | Path) -> Path:
    """The JSON file next to a ``.npy`` file (``FILE.npy.json``): its sensor size, time unit."""
    path = Path(path)
    return path.with_name(path.name + ".json")


def check_columns(columns: Any) -> tuple[str, ...]:
    """Validate the column order of ``(N, 4)`` arrays: ``"t,x,y,p"`` or four names.

    Raises:
        ValueError: unless it names ``x``, ``y``, ``t`` and ``p`` once each.
    """
    names = tuple(c.strip() for c in columns.split(",")) if isinstance(columns, str) else (
        tuple(columns) if isinstance(columns, (tuple, list)) else ())
    if sorted(names) != sorted(FIELDS):
        raise ValueError(
            f"columns must name x, y, t and p once each, e.g. 't,x,y,p'; got {columns!r}")
    return names


#: The first bytes of NumPy's files (a ``.npz`` is a zip archive; an empty one starts PK\5\6).
_NUMPY_MAGIC = {".npy": (b"\x93NUMPY",), ".npz": (b"PK\x03\x04", b"PK\x05\x06")}


def _what_it_holds(path: Path) -> str:
    """``"text (a CSV file?)"`` or ``"binary data"``, from the first bytes of ``path``."""
    with open(path, "rb") as file:
        head = file.read(512)
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError:
        return "binary data of another format"
    first = text.splitlines()[0][:40] if text.strip() else ""
    return f"text ({first!r}...: a CSV file?)" if first else "blank text"


def _check_numpy_file(path: Path) -> None:
    """Refuse a file named ``.npy``/``.npz`` that is not one, before NumPy guesses at it.

    NumPy reads anything without its header as a pickle and advises ``allow_pickle``: never
    the advice for a text file with the wrong name, and unsafe for a file of unknown origin.

    Raises:
        ValueError: naming what the file holds instead (text, other binary data, nothing).
    """
    extension = path.suffix.lower()
    with open(path, "rb") as file:
        head = file.read(8)
    if not head:
        raise ValueError("the file is empty")
    if not head.startswith(_NUMPY_MAGIC[extension]):
        raise ValueError(
            f"it is not a NumPy {extension} file (no NumPy header) but {_what_it_holds(path)}; "
            "a text table can be read with numpy.loadtxt and saved with numpy.save"
        )


def _numpy_error(error: Exception) -> str:
    """NumPy's error, without its advice to load pickles (object arrays are refused)."""
    if "pickle" in str(error):
        return ("it holds Python objects (an object array), which are not loaded; save the "
                "events as a structured or (N, 4) numeric array")
    return str(error)


def _suggest_columns(data: np.ndarray) -> tuple[str, ...] | None:
    """The column order an ``(N, 4)`` array looks like, if only one fits; else ``None``.

    ``t`` is the one column sorted in time and not constant, ``p`` the one taking two
    values (0/1 or -1/+1), ``x`` and ``y`` the other two in their order.
    """
    if len(data) < 2 or not np.isfinite(data).all():
        return None
    columns = [data[:, i] for i in range(4)]
    polar = [i for i, c in enumerate(columns)
             if np.isin(c, (0, 1)).all() or np.isin(c, (-1, 1)).all()]
    if len(polar) != 1:
        return None
    sorted_ = [i for i, c in enumerate(columns)
               if i != polar[0] and c[0] < c[-1] and bool((np.diff(c) >= 0).all())]
    if len(sorted_) != 1:
        return None
    x, y = (i for i in range(4) if i not in (polar[0], sorted_[0]))
    names = [""] * 4
    names[x], names[y], names[sorted_[0]], names[polar[0]] = FIELDS
    return tuple(names)


def _columns_hint(data: np.ndarray, given: tuple[str, ...]) -> str:
    """What an error about an ``(N, 4)`` array's coordinates adds: another column order?"""
    found = _suggest_columns(data)
    if found is not None and found != given:
        order = ",".join(found)
        return (f"; its columns look like {order}, not {','.join(given)}: say so with "
                f"columns='{order}' (--columns {order})")
    return (f"; read as columns {','.join(given)}: if they come in another order, say so with "
            "columns, e.g. columns='t,x,y,p' (--columns t,x,y,p)")


def load_npy(path: Path) -> np.ndarray:
    """The array a ``.npy`` file holds, never a pickle.

    Raises:
        ValueError: naming the problem (not a ``.npy`` file whatever its name, an object
            array, a file cut short), never with NumPy's advice to load pickles.
    """
    try:
        _check_numpy_file(path)
        return np.load(path, allow_pickle=False)
    except (ValueError, EOFError) as error:  # EOFError: a file cut short
        raise ValueError(f"cannot read {str(path)!r} as a .npy array: {_numpy_error(error)}"
                         ) from None


def read_npy(path: Path, columns: Any = FIELDS) -> Read:
    source = str(path)
    data = load_npy(path)
    names = data.dtype.names or ()
    hint = None
    if data.ndim == 1 and {"x", "y", "t", "p"} <= set(names):
        events = data
    elif data.ndim == 2 and data.shape[1] == 4 and not names:
        order = check_columns(columns)
        hint = partial(_columns_hint, data, order)
        x, y, t, p = (data[:, order.index(f)] for f in FIELDS)
        try:
            if np.issubdtype(data.dtype, np.floating):  # one dtype for all: whole-number x, y
                if not all(np.isfinite(c).all() and (c == np.round(c)).all() for c in (x, y)):
                    raise ValueError(f"{source}: coordinates x, y must be whole numbers")
                x, y = x.astype(np.int64), y.astype(np.int64)
            events = _columns(x, y, t, p, source)
        except ValueError as error:
            raise ValueError(f"{error}{hint()}") from None
    else:
        raise ValueError(
            f"{source!r} holds an array of dtype {data.dtype} and shape {data.shape}; "
            "expected a 1-D structured event array with fields x, y, t, p (Tonic's format) "
            "or an (N, 4) array of columns (x, y, t, p by default; see columns / --columns)"
        )
    meta = sidecar(path)
    if not meta.is_file():
        return Read(events, None, None, hint=hint)
    try:
        stored = json.loads(meta.read_text())
        if not isinstance(stored, dict):
            raise ValueError("not a JSON object")
    except (OSError, ValueError) as error:
        raise ValueError(f"cannot read {str(meta)!r}, the sidecar of {source!r}: {error}"
                         ) from None
    return Read(events, _sensor_attribute(stored, str(meta)),
                 None, _time_unit_attribute(stored, str(meta)), hint)


def _read_npz(path: Path) -> Read:
    source = str(path)
    try:
        _check_numpy_file(path)
        with np.load(path, allow_pickle=False) as archive:
            arrays = {key: archive[key] for key in archive.files}
    # EOFError: an entry cut short; BadZipFile: a truncated or damaged archive
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:
        raise ValueError(f"cannot read {source!r} as a .npz archive: {_numpy_error(error)}"
                         ) from None
    recorded = _sensor_attribute(arrays, source) if "sensor_size" in arrays else None
    unit = _time_unit_attribute(arrays, source)
    if {"x", "y", "t", "p"} <= set(arrays):
        events = _columns(arrays["x"], arrays["y"], arrays["t"], arrays["p"], source)
        return Read(events, recorded, None, unit)
    structured = [key for key, array in arrays.items()
                  if array.dtype.names and {"x", "y", "t", "p"} <= set(array.dtype.names)]
    if len(structured) == 1 and arrays[structured[0]].ndim == 1:
        return Read(arrays[structured[0]], recorded, None, unit)
    raise ValueError(
        f"{source!r} holds arrays {sorted(arrays)}; expected arrays x, y, t, p or one 1-D "
        "structured array with fields x, y, t, p (and optionally sensor_size)"
    )


def _read_hdf5(path: Path) -> Read:
    h5py = require("h5py", path.suffix)
    source = str(path)
    try:
        with h5py.File(path, "r") as file:
            recorded = _sensor_attribute(file.attrs, source)
            unit = _time_unit_attribute(file.attrs, source)
            node = file.get("events")
            if isinstance(node, h5py.Group):
                recorded = recorded or _sensor_attribute(node.attrs, source)
                unit = unit or _time_unit_attribute(node.attrs, source)
                group = node
            elif isinstance(node, h5py.Dataset) and {"x", "y", "t", "p"} <= set(
                node.dtype.names or ()
            ):
                recorded = recorded or _sensor_attribute(node.attrs, source)
                unit = unit or _time_unit_attribute(node.attrs, source)
                data = node[()]
                events = _columns(data["x"], data["y"], data["t"], data["p"], source)
                return Read(events, recorded, None, unit)
            else:
                group = file
            if not all(isinstance(group.get(name), h5py.Dataset) for name in "xytp"):
                raise ValueError(
                    f"{source!r} holds {sorted(file.keys())}; expected datasets events/x, "
                    "events/y, events/t, events/p (or x, y, t, p), or a structured dataset "
                    "events"
                )
            columns = [group[name][()] for name in "xytp"]
    # h5py reports damage as OSError, RuntimeError ("bad local heap signature") or KeyError
    except (OSError, RuntimeError, KeyError) as error:
        raise ValueError(f"cannot read {source!r} as HDF5 (a damaged file?): {error}") from None
    x, y, t, p = columns
    return Read(_columns(x, y, t, p, source), recorded, None, unit)


def _native_failure(error: BaseException) -> bool:
    """Whether a native decoder's ``error`` means a damaged file.

    Any ``Exception``, and pyo3's ``PanicException`` (a Rust panic, which Python sees as a
    ``BaseException``); never an interrupt or an exit.
    """
    return isinstance(error, Exception) or type(error).__name__ == "PanicException"


#: An AEDAT4 file's first line.
_AEDAT4_MAGIC = b"#!AER-DAT4.0\r\n"

#: The fewest bytes of an AEDAT4 packet: a size-prefixed flatbuffer's size prefix, root
#: offset and file identifier (the aedat decoder panics on fewer).
_AEDAT4_MIN_PACKET = 12


def _short_aedat4_packet(path: Path) -> str | None:
    """What is wrong where the aedat decoder would panic: a packet too short to decode.

    Walks the packet headers (stream id, size) after the file's header without decoding
    anything; the decoder itself reports every other damage.
    """
    with open(path, "rb") as file:
        end = os.fstat(file.fileno()).st_size
        if file.read(len(_AEDAT4_MAGIC)) != _AEDAT4_MAGIC:
            return None
        prefix = file.read(4)
        if len(prefix) < 4:
            return None
        at = len(_AEDAT4_MAGIC) + 4 + int.from_bytes(prefix, "little")
        while at + 8 <= end:
            file.seek(at + 4)
            size = int.from_bytes(file.read(4), "little")
            if size < _AEDAT4_MIN_PACKET:
                return (f"the packet at byte {at} holds {size} bytes, fewer than the "
                        f"{_AEDAT4_MIN_PACKET} of any packet (a damaged or cut file)")
            at += 8 + size
    return None


def _read_aedat4(path: Path) -> Read:
    require("tonic", ".aedat4")
    aedat = require("aedat", ".aedat4")
    import tonic.io

    source = str(path)
    short = _short_aedat4_packet(path)
    if short is not None:
        raise ValueError(f"cannot read {source!r} as AEDAT4: {short}")
    try:
        streams = aedat.Decoder(source).id_to_stream()
    except BaseException as error:  # plain exceptions for damaged files, or a Rust panic
        if not _native_failure(error):
            raise
        raise ValueError(f"cannot read {source!r} as AEDAT4: {error}") from None
    ids = [i for i, stream in streams.items() if stream.get("type") == "events"]
    if not ids:
        raise ValueError(f"{source!r} has no event stream (streams: {streams})")
    stream = streams[min(ids)]  # the stream tonic.io.read_aedat4 reads
    recorded = check_sensor_size((int(stream["width"]), int(stream["height"]), 2))
    try:
        data = tonic.io.read_aedat4(source)
    except ValueError as error:
        if "need at least one array" not in str(error):  # no event packet at all
            raise ValueError(f"cannot read {source!r} as AEDAT4: {error}") from None
        return Read(np.empty(0, dtype=DVS_DTYPE), recorded, None, "us")
    except BaseException as error:  # as above
        if not _native_failure(error):
            raise
        raise ValueError(f"cannot read {source!r} as AEDAT4: {error}") from None
    return Read(_columns(data["x"], data["y"], data["t"], data["on"], source), recorded, None,
                 "us")


#: Bytes of one event of an N-MNIST ``.bin`` file (40 bits: x, y, polarity and time).
NMNIST_EVENT_BYTES = 5


def check_nmnist_size(path: Path, size: int) -> None:
    """Refuse an N-MNIST ``.bin`` file of ``size`` bytes that cannot hold whole events.

    Raises:
        ValueError: naming the file, when ``size`` is not a multiple of 5 (a truncated file).
    """
    if size % NMNIST_EVENT_BYTES:
        raise ValueError(
            f"{str(path)!r} is truncated: its {size} bytes are not a whole number of "
            f"{NMNIST_EVENT_BYTES}-byte N-MNIST events"
        )


def _read_bin(path: Path) -> Read:
    require("tonic", ".bin")
    import tonic.io

    check_nmnist_size(path, path.stat().st_size)
    dtype = np.dtype([("x", int), ("y", int), ("t", int), ("p", int)])  # Tonic's NMNIST.dtype
    size = path.stat().st_size
    if size % 5:
        raise ValueError(
            f"cannot read {str(path)!r} as an N-MNIST .bin file: its {size} bytes are not "
            f"5-byte events but {_what_it_holds(path)}")
    try:
        data = tonic.io.read_mnist_file(str(path), dtype=dtype)
    except (OSError, ValueError, IndexError) as error:
        raise ValueError(f"cannot read {str(path)!r} as an N-MNIST .bin file: {error}") from None
    events = _columns(data["x"], data["y"], data["t"], data["p"], str(path))
    return Read(events, None, NMNIST_SENSOR, "us")


_SIZE_FALLBACK = (65535, 65535)  # only where the header has no size; never reported as one


def _read_prophesee(path: Path) -> Read:
    require("faery", path.suffix)
    from faery import dat, evt

    source = str(path)
    dat_file = path.suffix.lower() == ".dat"

    def decode(fallback: tuple[int, int] | None) -> tuple[tuple[int, int], list[np.ndarray]]:
        if dat_file:
            with dat.Decoder(path, fallback, "dat2") as decoder:
                if decoder.event_type != "cd":
                    raise ValueError(f"{source!r} holds {decoder.event_type!r} events, not CD")
                return decoder.dimensions, [packet for packet in decoder]
        with evt.Decoder(path, fallback, None) as decoder:
            packets = [packet["events"] for packet in decoder if "events" in packet]
            return decoder.dimensions, packets

    try:
        try:
            (width, height), packets = decode(None)
            recorded = check_sensor_size((int(width), int(height), 2))
        except RuntimeError as error:
            if "no size information" not in str(error):
                raise
            _, packets = decode(_SIZE_FALLBACK)
            recorded = None
    except BaseException as error:  # faery reports damaged files as RuntimeError, or panics
        if not _native_failure(error) or isinstance(error, ValueError):
            raise
        raise ValueError(f"cannot read {source!r} as a Prophesee file: {error}") from None
    data = np.concatenate(packets) if packets else np.empty(0, DVS_DTYPE)
    p = data["payload"] if dat_file and len(packets) else data["p"]
    return Read(_columns(data["x"], data["y"], data["t"], p, source), recorded, None, "us")


READERS: dict[str, Callable[[Path], Read]] = {
    ".npy": read_npy,
    ".npz": _read_npz,
    ".h5": _read_hdf5,
    ".hdf5": _read_hdf5,
    ".aedat4": _read_aedat4,
    ".bin": _read_bin,
    ".raw": _read_prophesee,
    ".dat": _read_prophesee,
}
