"""Reading and writing event recordings, whatever file they come in.

:func:`read_events` reads any of the formats below into a Tonic structured array (fields
``x``, ``y``, ``t``, ``p``) and tells the sensor size: the one the file records where it
records one, else the one the caller gives, else a guess that it says out loud (a
:class:`SensorSizeGuessWarning`). :func:`write_events` writes ``.npy`` and HDF5.

The decoding is done by maintained readers, never by parsers of our own:

=============  =====================================================  ========================
extension      reader                                                 sensor size, time unit
=============  =====================================================  ========================
``.npy``       NumPy: a structured array (Tonic's format) as stored,  the sidecar
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
=============  =====================================================  ========================

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

import json
import os
import threading
import warnings
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from evdown_torch._readers import (
    NMNIST_SENSOR,  # noqa: F401 - part of this module's API
    READERS,
    READERS_EXTRA,  # noqa: F401 - part of this module's API
    check_columns,
    load_npy,
    read_npy,
    require,
    sidecar,
)
from evdown_torch._text import WordedWarning
from evdown_torch.checks import check_sensor_size, swapped_sensor_hint
from evdown_torch.events import FIELDS
from evdown_torch.time_units import check_timing, check_unit_name, to_microseconds

__all__ = [
    "READ_EXTENSIONS",
    "WRITE_EXTENSIONS",
    "Recording",
    "SensorSizeGuessWarning",
    "check_columns",
    "check_readable",
    "check_writable",
    "event_files",
    "load_npy_events",
    "read_events",
    "read_microseconds",
    "sidecar",
    "write_events",
]

#: Extensions :func:`read_events` reads (lower case, with the dot).
READ_EXTENSIONS = (".npy", ".npz", ".h5", ".hdf5", ".aedat4", ".bin", ".raw", ".dat")

#: Extensions :func:`write_events` writes.
WRITE_EXTENSIONS = (".npy", ".h5", ".hdf5")

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
        """A recording; ``time_unit`` is ``None`` where the file does not say."""
        self = super().__new__(cls, events, sensor_size, guessed)
        self.time_unit = time_unit
        return self

    def _replace(self, **changes: Any) -> Recording:
        unit = changes.pop("time_unit", self.time_unit)
        return Recording(*super()._replace(**changes), time_unit=unit)

    def __repr__(self) -> str:
        return f"{super().__repr__()[:-1]}, time_unit={self.time_unit!r})"


class SensorSizeGuessWarning(WordedWarning):
    """The sensor size was guessed: the file does not record it and the caller gave none."""


# ----------------------------------------------------------------------------- public API


def _extent(events: np.ndarray) -> tuple[int, int]:
    return int(events["x"].max()) + 1, int(events["y"].max()) + 1


def _resolve_sensor_size(
    events: np.ndarray,
    given: Any,
    recorded: tuple[int, int, int] | None,
    guess: tuple[int, int, int] | None,
    source: str,
    hint: Callable[[], str] | None = None,
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
                f"{swapped_sensor_hint((w, h), size) or (hint() if hint else '')}"
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
    said = f"{source!r} does not record its sensor size; guessed {size} ({how}): "
    warnings.warn(SensorSizeGuessWarning(
        said + "give sensor_size=(W, H, P) to be sure",
        said + "give --sensor-size W H P to be sure",
    ), stacklevel=3)
    return size, True


def check_readable(path: str | Path) -> Path:
    """Check that ``path`` is an existing file with an extension :func:`read_events` reads.

    Raises:
        ValueError: naming the problem (unknown extension, missing file, not a file).
    """
    path = Path(path)
    if path.suffix.lower() not in READERS:
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
    """Check that :func:`write_events` can write ``path``.

    It needs a known extension and an existing folder (unless ``folder_may_be_missing``: the
    caller creates it).

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
    path: str | Path, *, sensor_size: Any = None, columns: Any = FIELDS,
    time_unit: str | None = None,
) -> Recording:
    """Read an event recording from any supported file (see the module's table).

    Args:
        path: the file; its extension chooses the reader (case-insensitive).
        sensor_size: ``(W, H, P)``, for files that do not record it; a size the file records
            wins (so that one value serves a folder of mixed files).
        columns: the column order of a ``.npy`` file holding an ``(N, 4)`` array, e.g.
            ``"t,x,y,p"`` (default ``x, y, t, p``, the order of ``(N, 4)`` tensors).
        time_unit: the unit of ``t`` (``"s"``, ``"ms"``, ``"us"`` or ``"ns"``) where the file
            states none (a unit the file states wins). Given, ``t`` comes back in
            microseconds, the unit of every time setting
            (:func:`~evdown_torch.time_units.to_microseconds`), and the recording's
            ``time_unit`` is ``"us"``; ``None`` (default): ``t`` as the file holds it.

    Returns:
        A :class:`Recording` ``(events, sensor_size, guessed)`` with the attribute
        ``time_unit``: a structured array with fields ``x``, ``y``, ``t``, ``p`` (``.npy`` and
        structured ``.npz`` arrays as stored, every other format as ``DVS_DTYPE``), the sensor
        size, and whether it was guessed (from the largest coordinates, or N-MNIST's 34 x 34
        for ``.bin``), which also warns with a :class:`SensorSizeGuessWarning`.

    Raises:
        ValueError: for a missing file, an unknown extension, a file the reader cannot read
            (or that is not what its extension says), bad ``columns``, or coordinates outside
            the sensor size.
        ImportError: when the format's optional reader is absent (naming the extra).

    Warns:
        TimeUnitWarning: when neither the file nor ``time_unit`` states the unit and the
            timestamps, read as microseconds, imply more events per second than any sensor
            makes (:func:`~evdown_torch.time_units.check_timing`): float seconds, most often.
        SensorSizeGuessWarning: when the sensor size was guessed.

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
    given_unit = None if time_unit is None else check_unit_name(time_unit)
    if path.suffix.lower() == ".npy":
        read = read_npy(path, columns)
    else:
        read = READERS[path.suffix.lower()](path)
    size, guessed = _resolve_sensor_size(read.events, sensor_size, read.recorded, read.guess,
                                         str(path), read.hint)
    unit = read.time_unit or given_unit
    if unit is None:  # microseconds, unconfirmed
        check_timing(read.events["t"], source=repr(str(path)))
        return Recording(read.events, size, guessed, None)
    if given_unit is None or unit == "us":
        return Recording(read.events, size, guessed, unit)
    return Recording(to_microseconds(read.events, unit), size, guessed, "us")


def read_microseconds(
    path: str | Path, *, sensor_size: Any = None, time_unit: str | None = None,
    columns: Any = FIELDS,
) -> Recording:
    """:func:`read_events` with ``t`` in microseconds wherever the unit is known.

    Unlike :func:`read_events` without ``time_unit``, a unit the file states is converted too.

    Args:
        path: the file, as for :func:`read_events`.
        sensor_size: as for :func:`read_events`.
        columns: as for :func:`read_events`.
        time_unit: the unit of ``t`` where the file states none (a file's own unit wins);
            ``None``: microseconds, unconfirmed (checked as :func:`read_events` checks).

    Returns:
        The :class:`Recording`, ``t`` in microseconds (see
        :func:`~evdown_torch.time_units.to_microseconds`); its ``time_unit`` is ``"us"``, or
        ``None`` where neither the file nor the caller said.
    """
    recording = read_events(path, sensor_size=sensor_size, columns=columns, time_unit=time_unit)
    if recording.time_unit in (None, "us"):
        return recording
    return recording._replace(events=to_microseconds(recording.events, recording.time_unit),
                              time_unit="us")


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
    path: str | Path, events: np.ndarray, *, sensor_size: Any = None, time_unit: str | None = None,
    metadata: Mapping[str, Any] | None = None,
) -> Path:
    """Write a structured event array to exactly ``path`` (``.npy``, ``.h5`` or ``.hdf5``).

    ``.npy`` stores the array as it is (NumPy's format), and the sensor size and time unit,
    when given, in the JSON sidecar ``FILE.npy.json`` (:func:`sidecar`; a stale one is
    removed). HDF5 stores one dataset per field under the group ``events`` (``events/x``,
    ...: DSEC's layout) and the sensor size and time unit as the file attributes
    ``sensor_size`` and ``time_unit``. :func:`read_events` gets both back.

    Everything is written under temporary names in the output's folder first and renamed into
    place last (the sidecar, then the file), so a write that fails leaves an existing file
    and its sidecar as they were.

    Args:
        path: the output file; its folder must exist. An existing file is replaced.
        events: ``(N,)`` structured array with fields ``x``, ``y``, ``t``, ``p``.
        sensor_size: ``(W, H, P)`` to store.
        time_unit: the unit of ``t`` to store (see :mod:`evdown_torch.time_units`).
        metadata: more to record beside them (e.g. how the file was made), each value
            JSON-serialisable: in the sidecar, or as HDF5 attributes holding JSON text.
            Readers ignore it.

    Returns:
        The path written (not the sidecar).

    Raises:
        ValueError: for an unknown extension, a missing folder, events without the fields or
            a sidecar path that is not a file.
        TypeError: if ``events`` is not a structured array.
        ImportError: for HDF5 without h5py (naming the extra).
        OSError: when the files cannot be written (nothing is replaced then).
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
    unit = None if time_unit is None else check_unit_name(time_unit)
    extra = dict(metadata or {})
    clash = sorted({"sensor_size", "time_unit"} & set(extra))
    if clash:
        raise ValueError(f"metadata may not hold {clash}: give them as their own arguments")
    json.dumps(extra)  # a TypeError naming the value that JSON cannot hold, before writing
    extension = path.suffix.lower()
    if extension == ".npy":
        meta_path = sidecar(path)
        if meta_path.exists() and not meta_path.is_file():
            raise ValueError(f"cannot write {str(path)!r}: its sidecar {str(meta_path)!r} is a "
                             "folder")
        meta = {k: v for k, v in (("sensor_size", size), ("time_unit", unit)) if v is not None}
        meta.update(extra)
        with _renamed_into_place(*((meta_path,) if meta else ()), path) as temporaries:
            with open(temporaries[-1], "wb") as file:  # np.save(name) would append ".npy"
                np.save(file, events, allow_pickle=False)
            if meta:
                temporaries[0].write_text(json.dumps(meta) + "\n")
        if not meta:
            meta_path.unlink(missing_ok=True)  # it would describe another file
        return path
    h5py = require("h5py", extension, "writing")
    with _renamed_into_place(path) as (temporary,), h5py.File(temporary, "w") as file:
        group = file.create_group("events")
        for name in events.dtype.names:
            group.create_dataset(name, data=np.ascontiguousarray(events[name]))
        if size is not None:
            file.attrs["sensor_size"] = np.asarray(size, dtype=np.int64)
        if unit is not None:
            file.attrs["time_unit"] = unit
        for key, value in extra.items():
            file.attrs[key] = json.dumps(value)
    return path


@contextmanager
def _renamed_into_place(*paths: Path) -> Iterator[tuple[Path, ...]]:
    """Temporary names beside ``paths`` for the block to write, renamed onto them at its end.

    The renames happen in the order given, once the block has succeeded; if the block or a
    rename fails, the temporaries are removed and the paths not yet renamed onto keep what
    they held.
    """
    tag = f"{os.getpid()}-{threading.get_ident()}"
    temporaries = tuple(p.with_name(f".{p.name}.{tag}.part") for p in paths)
    try:
        yield temporaries
        for temporary, path in zip(temporaries, paths, strict=True):
            os.replace(temporary, path)
    finally:
        for temporary in temporaries:
            temporary.unlink(missing_ok=True)


def load_npy_events(path: str | Path) -> np.ndarray:
    """Load a ``.npy`` structured event array (fields ``x``, ``y``, ``t``, ``p``).

    :func:`read_events` reads every event format (``(N, 4)`` arrays, other
    time units and files that record their sensor size included).

    Raises:
        ValueError: if the file is missing, unreadable, not a ``.npy`` file (whatever its
            name says) or not a structured event array.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"input file {str(path)!r} does not exist")
    events = load_npy(path)
    names = events.dtype.names or ()
    if events.ndim != 1 or not {"x", "y", "t", "p"} <= set(names):
        raise ValueError(
            f"{str(path)!r} holds an array of dtype {events.dtype} and shape {events.shape}; "
            "expected a 1-D structured event array with fields x, y, t, p (Tonic's format)"
        )
    return events
