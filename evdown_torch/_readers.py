"""The readers behind :func:`evdown_torch.io.read_events`, one per format (see its table).

Each takes the path and returns a :class:`Read`: the events as a structured array with fields
``x``, ``y``, ``t``, ``p``, the sensor size and time unit the file records (if it does), and a
better guess of the sensor size than the largest coordinates (N-MNIST's). Decoding is done by
maintained packages (NumPy, h5py, Tonic with aedat, faery), imported when a format needs them.
"""

from __future__ import annotations

import importlib
import json
import zipfile
from collections.abc import Callable
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


def _time_unit_attribute(attrs: Any, source: str) -> str | None:
    """A ``time_unit`` attribute or array, if present."""
    if "time_unit" not in attrs:
        return None
    value = attrs["time_unit"]
    value = value.item() if isinstance(value, np.ndarray) else value
    value = value.decode() if isinstance(value, bytes) else value
    try:
        return check_unit_name(value)
    except ValueError as error:
        raise ValueError(f"{source}: stored {error}") from None


def _sensor_attribute(attrs: Any, source: str) -> tuple[int, int, int] | None:
    """``sensor_size`` (W, H, P) or ``width``/``height`` attributes, if present."""
    if "sensor_size" in attrs:
        value = np.asarray(attrs["sensor_size"]).reshape(-1).tolist()
        try:
            return check_sensor_size(value)
        except (TypeError, ValueError) as error:
            raise ValueError(f"{source}: stored sensor_size is not valid: {error}") from None
    if "width" in attrs and "height" in attrs:
        return check_sensor_size((int(attrs["width"]), int(attrs["height"]), 2))
    return None


# ----------------------------------------------------------------------------- readers
# Each takes the path and returns a Read.


class Read(NamedTuple):
    events: np.ndarray
    recorded: tuple[int, int, int] | None  # the sensor size the file records
    guess: tuple[int, int, int] | None  # a better guess than the largest coordinates
    time_unit: str | None = None  # the one the format or the file states


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


def read_npy(path: Path, columns: Any = FIELDS) -> Read:
    source = str(path)
    try:
        data = np.load(path, allow_pickle=False)
    except (ValueError, EOFError) as error:  # EOFError: an empty file
        raise ValueError(f"cannot read {source!r} as a .npy array: {error}") from None
    names = data.dtype.names or ()
    if data.ndim == 1 and {"x", "y", "t", "p"} <= set(names):
        events = data
    elif data.ndim == 2 and data.shape[1] == 4 and not names:
        x, y, t, p = (data[:, check_columns(columns).index(f)] for f in FIELDS)
        if np.issubdtype(data.dtype, np.floating):  # one dtype for all: whole-number x, y
            if not all(np.isfinite(c).all() and (c == np.round(c)).all() for c in (x, y)):
                raise ValueError(f"{source}: coordinates x, y must be whole numbers")
            x, y = x.astype(np.int64), y.astype(np.int64)
        events = _columns(x, y, t, p, source)
    else:
        raise ValueError(
            f"{source!r} holds an array of dtype {data.dtype} and shape {data.shape}; "
            "expected a 1-D structured event array with fields x, y, t, p (Tonic's format) "
            "or an (N, 4) array of columns (x, y, t, p by default; see columns / --columns)"
        )
    meta = sidecar(path)
    if not meta.is_file():
        return Read(events, None, None)
    try:
        stored = json.loads(meta.read_text())
        if not isinstance(stored, dict):
            raise ValueError("not a JSON object")
    except (OSError, ValueError) as error:
        raise ValueError(f"cannot read {str(meta)!r}, the sidecar of {source!r}: {error}"
                         ) from None
    return Read(events, _sensor_attribute(stored, str(meta)),
                 None, _time_unit_attribute(stored, str(meta)))


def _read_npz(path: Path) -> Read:
    source = str(path)
    try:
        with np.load(path, allow_pickle=False) as archive:
            arrays = {key: archive[key] for key in archive.files}
    # EOFError: an empty file; BadZipFile: a truncated or damaged archive
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as error:
        raise ValueError(f"cannot read {source!r} as a .npz archive: {error}") from None
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
    except OSError as error:
        raise ValueError(f"cannot read {source!r} as HDF5: {error}") from None
    x, y, t, p = columns
    return Read(_columns(x, y, t, p, source), recorded, None, unit)


def _read_aedat4(path: Path) -> Read:
    require("tonic", ".aedat4")
    aedat = require("aedat", ".aedat4")
    import tonic.io

    source = str(path)
    try:
        streams = aedat.Decoder(source).id_to_stream()
    except Exception as error:  # the decoder raises plain exceptions for damaged files
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
    except Exception as error:  # as above
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
    except (RuntimeError, OSError) as error:  # faery reports damaged files as RuntimeError
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
