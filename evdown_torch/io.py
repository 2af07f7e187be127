"""Reading and writing event recordings, whatever file they come in.

:func:`read_events` reads any of the formats below into a Tonic structured array (fields
``x``, ``y``, ``t``, ``p``) and tells the sensor size: the one the file records where it
records one, else the one the caller gives, else a guess that it says out loud (a
:class:`SensorSizeGuessWarning`). :func:`write_events` writes ``.npy`` and HDF5.

The decoding is done by maintained readers, never by parsers of our own:

=============  =====================================================  =====================
extension      reader                                                 sensor size, time unit
=============  =====================================================  =====================
``.npy``       NumPy: a structured array (Tonic's format), as stored, the sidecar
               or an ``(N, 4)`` array (columns ``x, y, t, p`` unless  ``FILE.npy.json``, if
               ``columns`` says otherwise)                            there
``.npz``       NumPy: arrays ``x, y, t, p`` or one structured array   ``sensor_size``,
                                                                      ``time_unit`` arrays
``.h5/.hdf5``  h5py: datasets ``events/x, y, t, p`` (DSEC's layout,   ``sensor_size`` (or
               and what :func:`write_events` writes), a structured    ``width``/``height``),
               dataset ``events``, or datasets ``x, y, t, p``         ``time_unit`` attrs
``.aedat4``    ``tonic.io.read_aedat4`` (the ``aedat`` package)       the header; us
``.bin``       ``tonic.io.read_mnist_file`` (N-MNIST, N-Caltech101)   not recorded; us
``.raw``       faery (Prophesee EVT 2.0, 2.1 and 3.0)                 the header, if there; us
``.dat``       faery (Prophesee DAT, CD events)                       the header, if there; us
=============  =====================================================  =====================

A file's own sensor size wins; the one the caller gives fills in where the file records none
(so that one setting serves a folder of mixed files); a guess comes last. The time unit is the
format's (microseconds for camera formats) or the one recorded in the file, else ``None``
(unknown: the package reads timestamps as microseconds, and
:func:`~evdown_torch.time_units.check_timing` warns when that looks wrong).

Tonic, aedat, faery and h5py are optional: ``pip install 'evdown_torch[readers]'``.
Prophesee files go through faery (an 8 MB Rust extension needing only NumPy). expelliarmus,
smaller (50 kB) and installed with Tonic, misreads EVT 3.0 time: it counts a TIME_LOW wrap
on top of the TIME_HIGH word that follows it (an event at 4095 us then one at 4097 us come
back as 4095 and 8193), so timestamps gain 4.1 ms at every wrap of the 4.1 ms low clock.
It is 5 to 30 times faster on EVT 2.0 and DAT, but faery's 11 to 13 M events/s (one thread,
``benchmarks/bench_readers.py``) already outpaces the downscalers, and one reader that is right
on every Prophesee format is worth more. evlib reads the same formats but weighs 17 MB plus
Polars and PyArrow.

Files other than ``.npy``/``.npz`` come back with :data:`~evdown_torch.events.DVS_DTYPE`
(``x``, ``y`` int16, ``p`` bool, ``t`` int64, or float64 for float timestamps).
"""

from __future__ import annotations

import importlib
import json
import warnings
import zipfile
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any, NamedTuple

import numpy as np

from evdown_torch.checks import check_sensor_size
from evdown_torch.events import DVS_DTYPE, FIELDS
from evdown_torch.time_units import check_time_unit, to_microseconds

__all__ = [
    "READ_EXTENSIONS",
    "WRITE_EXTENSIONS",
    "Recording",
    "SensorSizeGuessWarning",
    "check_columns",
    "check_readable",
    "check_writable",
    "event_files",
    "read_events",
    "read_microseconds",
    "sidecar",
    "write_events",
]

#: The optional dependency group that installs every reader.
READERS_EXTRA = "readers"

#: Extensions :func:`read_events` reads (lower case, with the dot).
READ_EXTENSIONS = (".npy", ".npz", ".h5", ".hdf5", ".aedat4", ".bin", ".raw", ".dat")

#: Extensions :func:`write_events` writes.
WRITE_EXTENSIONS = (".npy", ".h5", ".hdf5")

#: N-MNIST's ATIS sensor crop, the usual content of a ``.bin`` file.
NMNIST_SENSOR = (34, 34, 2)

_INT16_MAX = int(np.iinfo(np.int16).max)


class _RecordingFields(NamedTuple):
    events: np.ndarray
    sensor_size: tuple[int, int, int]
    guessed: bool


class Recording(_RecordingFields):
    """What :func:`read_events` returns; unpacks as ``events, sensor_size, guessed``.

    Attributes:
        events: ``(N,)`` structured array with fields ``x``, ``y``, ``t``, ``p``.
        sensor_size: ``(W, H, P)`` of the recording.
        guessed: ``True`` when the file did not record the sensor size, none was given, and
            it was guessed (a :class:`SensorSizeGuessWarning` said so).
        time_unit: the unit of ``t`` (``"s"``, ``"ms"``, ``"us"`` or ``"ns"``: see
            :mod:`evdown_torch.time_units`) that the format or the file states; ``None`` when
            neither says (read as microseconds). An attribute, not unpacked.
    """

    time_unit: str | None

    def __new__(cls, events: np.ndarray, sensor_size: tuple[int, int, int], guessed: bool,
                time_unit: str | None = None) -> Recording:
        self = super().__new__(cls, events, sensor_size, guessed)
        self.time_unit = time_unit
        return self

    def _replace(self, **changes: Any) -> Recording:
        unit = changes.pop("time_unit", self.time_unit)
        return Recording(*super()._replace(**changes), time_unit=unit)

    def __repr__(self) -> str:
        return f"{super().__repr__()[:-1]}, time_unit={self.time_unit!r})"


class SensorSizeGuessWarning(UserWarning):
    """The sensor size was guessed: the file does not record it and the caller gave none."""


def _require(module: str, extension: str, doing: str = "reading") -> ModuleType:
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
        return check_time_unit(value)
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
# Each takes the path and returns a _Read.


class _Read(NamedTuple):
    events: np.ndarray
    recorded: tuple[int, int, int] | None  # the sensor size the file records
    guess: tuple[int, int, int] | None  # a better guess than the largest coordinates
    time_unit: str | None = None  # the one the format or the file states


def sidecar(path: str | Path) -> Path:
    """The JSON file next to a ``.npy`` file that holds its sensor size and time unit
    (``FILE.npy.json``)."""
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


def _read_npy(path: Path, columns: Any = FIELDS) -> _Read:
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
        return _Read(events, None, None)
    try:
        stored = json.loads(meta.read_text())
        if not isinstance(stored, dict):
            raise ValueError("not a JSON object")
    except (OSError, ValueError) as error:
        raise ValueError(f"cannot read {str(meta)!r}, the sidecar of {source!r}: {error}"
                         ) from None
    return _Read(events, _sensor_attribute(stored, str(meta)),
                 None, _time_unit_attribute(stored, str(meta)))


def _read_npz(path: Path) -> _Read:
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
        return _Read(events, recorded, None, unit)
    structured = [key for key, array in arrays.items()
                  if array.dtype.names and {"x", "y", "t", "p"} <= set(array.dtype.names)]
    if len(structured) == 1 and arrays[structured[0]].ndim == 1:
        return _Read(arrays[structured[0]], recorded, None, unit)
    raise ValueError(
        f"{source!r} holds arrays {sorted(arrays)}; expected arrays x, y, t, p or one 1-D "
        "structured array with fields x, y, t, p (and optionally sensor_size)"
    )


def _read_hdf5(path: Path) -> _Read:
    h5py = _require("h5py", path.suffix)
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
                return _Read(events, recorded, None, unit)
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
    return _Read(_columns(*columns, source), recorded, None, unit)


def _read_aedat4(path: Path) -> _Read:
    _require("tonic", ".aedat4")
    aedat = _require("aedat", ".aedat4")
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
        return _Read(np.empty(0, dtype=DVS_DTYPE), recorded, None, "us")
    except Exception as error:  # as above
        raise ValueError(f"cannot read {source!r} as AEDAT4: {error}") from None
    return _Read(_columns(data["x"], data["y"], data["t"], data["on"], source), recorded, None,
                 "us")


def _read_bin(path: Path) -> _Read:
    _require("tonic", ".bin")
    import tonic.io

    dtype = np.dtype([("x", int), ("y", int), ("t", int), ("p", int)])  # Tonic's NMNIST.dtype
    try:
        data = tonic.io.read_mnist_file(str(path), dtype=dtype)
    except (OSError, ValueError, IndexError) as error:
        raise ValueError(f"cannot read {str(path)!r} as an N-MNIST .bin file: {error}") from None
    events = _columns(data["x"], data["y"], data["t"], data["p"], str(path))
    return _Read(events, None, NMNIST_SENSOR, "us")


_SIZE_FALLBACK = (65535, 65535)  # only where the header has no size; never reported as one


def _read_prophesee(path: Path) -> _Read:
    _require("faery", path.suffix)
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
    return _Read(_columns(data["x"], data["y"], data["t"], p, source), recorded, None, "us")


_READERS: dict[str, Callable[[Path], _Read]] = {
    ".npy": _read_npy,
    ".npz": _read_npz,
    ".h5": _read_hdf5,
    ".hdf5": _read_hdf5,
    ".aedat4": _read_aedat4,
    ".bin": _read_bin,
    ".raw": _read_prophesee,
    ".dat": _read_prophesee,
}


# ----------------------------------------------------------------------------- public API


def _extent(events: np.ndarray) -> tuple[int, int]:
    return int(events["x"].max()) + 1, int(events["y"].max()) + 1


def _resolve_sensor_size(
    events: np.ndarray,
    given: Any,
    recorded: tuple[int, int, int] | None,
    guess: tuple[int, int, int] | None,
    source: str,
) -> tuple[tuple[int, int, int], bool]:
    n = len(events)
    if n and (int(events["x"].min()) < 0 or int(events["y"].min()) < 0):
        raise ValueError(f"{source!r} holds negative pixel coordinates")
    if given is not None or recorded is not None:
        size = recorded if recorded is not None else check_sensor_size(given)
        if n and (events["x"].max() >= size[0] or events["y"].max() >= size[1]):
            w, h = _extent(events)
            where = "recorded in the file" if recorded is not None else "given"
            raise ValueError(
                f"{source!r} holds coordinates up to x={w - 1}, y={h - 1}, outside the sensor "
                f"size {size} {where}"
            )
        return size, False
    if not n:
        raise ValueError(
            f"{source!r} holds no events and does not record its sensor size: give sensor_size"
        )
    w, h = _extent(events)
    if guess is not None and w <= guess[0] and h <= guess[1]:
        size, how = guess, "N-MNIST's sensor, as its coordinates fit in it"
    else:
        size, how = (w, h, 2), "the largest coordinates, too small if the edge pixels were quiet"
    warnings.warn(
        f"{source!r} does not record its sensor size; guessed {size} ({how}): give the "
        "sensor size (--sensor-size W H P) to be sure",
        SensorSizeGuessWarning,
        stacklevel=3,
    )
    return size, True


def check_readable(path: str | Path) -> Path:
    """Check that ``path`` is an existing file with an extension :func:`read_events` reads.

    Raises:
        ValueError: naming the problem (unknown extension, missing file, not a file).
    """
    path = Path(path)
    if path.suffix.lower() not in _READERS:
        raise ValueError(
            f"cannot read {str(path)!r}: unknown extension {path.suffix!r}; "
            f"readable: {', '.join(READ_EXTENSIONS)}"
        )
    if not path.exists():
        raise ValueError(f"input file {str(path)!r} does not exist")
    if not path.is_file():
        raise ValueError(f"input {str(path)!r} is not a file")
    return path


def check_writable(path: str | Path, *, folder_may_be_missing: bool = False) -> Path:
    """Check that :func:`write_events` can write ``path``: a known extension, an existing folder
    (unless ``folder_may_be_missing``: the caller creates it).

    Raises:
        ValueError: naming the problem.
    """
    path = Path(path)
    if path.suffix.lower() not in WRITE_EXTENSIONS:
        raise ValueError(
            f"cannot write {str(path)!r}: unknown extension {path.suffix!r}; "
            f"writable: {', '.join(WRITE_EXTENSIONS)}"
        )
    if not folder_may_be_missing and not path.parent.is_dir():
        raise ValueError(
            f"cannot write {str(path)!r}: folder {str(path.parent)!r} does not exist"
        )
    return path


def read_events(
    path: str | Path, *, sensor_size: Any = None, columns: Any = FIELDS
) -> Recording:
    """Read an event recording from any supported file (see the module's table).

    Args:
        path: the file; its extension chooses the reader (case-insensitive).
        sensor_size: ``(W, H, P)``, for files that do not record it; a size the file records
            wins (so that one value serves a folder of mixed files).
        columns: the column order of a ``.npy`` file holding an ``(N, 4)`` array, e.g.
            ``"t,x,y,p"`` (default ``x, y, t, p``, the order of ``(N, 4)`` tensors).

    Returns:
        A :class:`Recording` ``(events, sensor_size, guessed)`` with the attribute
        ``time_unit``: a structured array with fields ``x``, ``y``, ``t``, ``p`` (``.npy`` and
        structured ``.npz`` arrays as stored, every other format as ``DVS_DTYPE``), the sensor
        size, and whether it was guessed (from the largest coordinates, or N-MNIST's 34 x 34
        for ``.bin``), which also warns with a :class:`SensorSizeGuessWarning`.

    Raises:
        ValueError: for a missing file, an unknown extension, a file the reader cannot read,
            bad ``columns``, or coordinates outside the sensor size.
        ImportError: when the format's optional reader is absent (naming the extra).

    Example:
        >>> import tempfile, numpy as np
        >>> from evdown_torch.events import DVS_DTYPE
        >>> folder = tempfile.mkdtemp()
        >>> path = write_events(f"{folder}/rec.npy", np.zeros(3, DVS_DTYPE),
        ...                     sensor_size=(8, 6, 2), time_unit="us")
        >>> events, size, guessed = read_events(path)
        >>> len(events), size, guessed, read_events(path).time_unit
        (3, (8, 6, 2), False, 'us')
    """
    path = check_readable(path)
    if path.suffix.lower() == ".npy":
        read = _read_npy(path, columns)
    else:
        read = _READERS[path.suffix.lower()](path)
    size, guessed = _resolve_sensor_size(read.events, sensor_size, read.recorded, read.guess,
                                         str(path))
    return Recording(read.events, size, guessed, read.time_unit)


def read_microseconds(
    path: str | Path, *, sensor_size: Any = None, time_unit: str | None = None,
    columns: Any = FIELDS,
) -> Recording:
    """:func:`read_events`, with ``t`` converted to microseconds (the unit of every time setting).

    Args:
        path, sensor_size, columns: as for :func:`read_events`.
        time_unit: the unit of ``t`` where the file states none (a file's own unit wins);
            ``None``: microseconds, unconfirmed.

    Returns:
        The :class:`Recording`, ``t`` in microseconds (see
        :func:`~evdown_torch.time_units.to_microseconds`); its ``time_unit`` is ``"us"``, or
        ``None`` where neither the file nor the caller said.
    """
    recording = read_events(path, sensor_size=sensor_size, columns=columns)
    unit = recording.time_unit or (None if time_unit is None else check_time_unit(time_unit))
    if unit is None:
        return recording
    return recording._replace(events=to_microseconds(recording.events, unit), time_unit="us")


def event_files(folder: str | Path) -> list[Path]:
    """The files directly inside ``folder`` that :func:`read_events` reads, sorted by name.

    Raises:
        ValueError: if ``folder`` is not a folder.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{str(folder)!r} is not a folder")
    return sorted(
        p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in READ_EXTENSIONS
    )


def write_events(
    path: str | Path, events: np.ndarray, *, sensor_size: Any = None, time_unit: str | None = None
) -> Path:
    """Write a structured event array to exactly ``path`` (``.npy``, ``.h5`` or ``.hdf5``).

    ``.npy`` stores the array as it is (NumPy's format), and the sensor size and time unit,
    when given, in the JSON sidecar ``FILE.npy.json`` (:func:`sidecar`; a stale one is
    removed). HDF5 stores one dataset per field under the group ``events`` (``events/x``,
    ...: DSEC's layout) and the sensor size and time unit as the file attributes
    ``sensor_size`` and ``time_unit``. :func:`read_events` gets both back.

    Args:
        path: the output file; its folder must exist. An existing file is replaced.
        events: ``(N,)`` structured array with fields ``x``, ``y``, ``t``, ``p``.
        sensor_size: ``(W, H, P)`` to store.
        time_unit: the unit of ``t`` to store (see :mod:`evdown_torch.time_units`).

    Returns:
        The path written (not the sidecar).

    Raises:
        ValueError: for an unknown extension, a missing folder or events without the fields.
        TypeError: if ``events`` is not a structured array.
        ImportError: for HDF5 without h5py (naming the extra).
    """
    path = check_writable(path)
    if not isinstance(events, np.ndarray) or events.dtype.names is None:
        raise TypeError(
            f"events to write must be a structured array, got {type(events).__name__}"
        )
    if events.ndim != 1 or not {"x", "y", "t", "p"} <= set(events.dtype.names):
        raise ValueError(
            f"events to write must be a 1-D structured array with fields x, y, t, p, got "
            f"dtype {events.dtype} and shape {events.shape}"
        )
    size = None if sensor_size is None else check_sensor_size(sensor_size)
    unit = None if time_unit is None else check_time_unit(time_unit)
    extension = path.suffix.lower()
    if extension == ".npy":
        with open(path, "wb") as file:  # np.save(path) would append ".npy" to other names
            np.save(file, events, allow_pickle=False)
        meta = {k: v for k, v in (("sensor_size", size), ("time_unit", unit)) if v is not None}
        if meta:
            sidecar(path).write_text(json.dumps(meta) + "\n")
        else:
            sidecar(path).unlink(missing_ok=True)
        return path
    h5py = _require("h5py", extension, "writing")
    with h5py.File(path, "w") as file:
        group = file.create_group("events")
        for name in events.dtype.names:
            group.create_dataset(name, data=np.ascontiguousarray(events[name]))
        if size is not None:
            file.attrs["sensor_size"] = np.asarray(size, dtype=np.int64)
        if unit is not None:
            file.attrs["time_unit"] = unit
    return path
