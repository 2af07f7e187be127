"""Datasets of labelled recordings: synthetic gestures, Tonic's, or a folder of files.

A :class:`Source` (the package's one notion of a source) is a picklable object (worker
processes receive it) with ``len()``, ``sensor_size``, ``dtype``, ``classes``, ``describe()``
(JSON facts naming it) and ``load(i) -> (events, label)`` plus ``source_name(i)`` for
messages. :func:`open_source` builds one from ``evdown preprocess``'s ``--dataset`` choice;
:class:`TonicSource` is the one place DVS128 Gesture is opened and :class:`NMNISTSource` the one
place N-MNIST is (``evdown evaluate`` and ``evdown show`` read them through these too).
"""

from __future__ import annotations

import operator
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from evdown_torch._readers import NMNIST_SENSOR, check_nmnist_size
from evdown_torch.checks import check_choice, check_sensor_size
from evdown_torch.events import DVS_DTYPE, FIELDS
from evdown_torch.io import READ_EXTENSIONS, check_columns, read_microseconds
from evdown_torch.time_units import check_unit_name

__all__ = [
    "RECORDING_SUFFIXES",
    "FolderSource",
    "NMNISTSource",
    "Source",
    "SyntheticSource",
    "TonicSource",
    "check_label",
    "open_source",
    "read_recording",
]

#: File suffixes the folder source reads, with :func:`read_recording` (every format of
#: :mod:`evdown_torch.io`: NumPy, HDF5, AEDAT4, N-MNIST ``.bin``, Prophesee).
RECORDING_SUFFIXES = READ_EXTENSIONS


@runtime_checkable
class Source(Protocol):
    """A dataset of labelled recordings, read one by one (what :func:`open_source` returns).

    Attributes:
        name: the dataset's name (``"synthetic"``, ``"dvsgesture"``, ``"nmnist"``,
            ``"folder"``).
        sensor_size: ``(W, H, P)`` of every recording.
        dtype: the structured dtype of every recording's events.
        classes: the class names; labels index them.
    """

    name: str
    sensor_size: tuple[int, int, int]
    dtype: np.dtype
    classes: list[str]

    def __len__(self) -> int:
        """The number of recordings."""
        ...

    def describe(self) -> dict[str, Any]:
        """JSON-ready facts that name the dataset (kept in a cache's manifest)."""
        ...

    def source_name(self, index: int) -> str:
        """Where recording ``index`` comes from, for messages (a file, a split and index)."""
        ...

    def load(self, index: int) -> tuple[np.ndarray, int]:
        """Recording ``index``: ``(events, label)``, a Tonic structured array and a class."""
        ...


def read_recording(path: Path, sensor_size: tuple[int, int, int], *,
                   time_unit: str | None = None, columns: Any = FIELDS) -> np.ndarray:
    """Read one recording file of a folder dataset as a Tonic structured array.

    The one place a folder dataset reads files, through
    :func:`evdown_torch.io.read_microseconds` (the dataset's ``sensor_size`` stands for files
    that do not record one, ``time_unit`` and ``columns`` for files that do not say theirs).

    Raises:
        ValueError: if the file cannot be read as a structured event array.
    """
    return read_microseconds(path, sensor_size=sensor_size, time_unit=time_unit,
                             columns=columns).events


class SyntheticSource:
    """:class:`~evdown_torch.synthetic.SyntheticGestures` recordings (rendered, not read)."""

    name = "synthetic"

    def __init__(self, *, split: str, samples_per_class: int, duration_us: int, seed: int,
                 sensor_size: tuple[int, int, int]) -> None:
        from evdown_torch.synthetic import SyntheticGestures

        self.split = check_choice("split", split, ("train", "test"))
        self._data = SyntheticGestures(
            train=self.split == "train", samples_per_class=samples_per_class,
            duration_us=duration_us, seed=seed, sensor_size=sensor_size)
        self.sensor_size = self._data.sensor_size
        self.dtype = np.dtype(self._data.dtype)
        self.classes = list(self._data.classes)
        self._options = {"split": self.split, "samples_per_class": samples_per_class,
                         "duration_us": duration_us, "seed": seed}

    def __len__(self) -> int:
        return len(self._data)

    def describe(self) -> dict[str, Any]:
        """JSON-ready facts that name the dataset (kept in a cache's manifest)."""
        return {"name": self.name, "sensor_size": list(self.sensor_size), **self._options}

    def source_name(self, index: int) -> str:
        """Where recording ``index`` comes from, for messages."""
        return f"synthetic {self.split} recording {index}"

    def load(self, index: int) -> tuple[np.ndarray, int]:
        """Recording ``index``: ``(events, label)``."""
        return self._data[index]


_TONIC_CLASSES = {"dvsgesture": "DVSGesture"}

#: The suffix of each Tonic dataset's recording files, in its extracted folder.
_TONIC_RECORDINGS = {"DVSGesture": ".npy", "NMNIST": ".bin"}


class TonicSource:
    """A dataset of ``tonic.datasets`` (DVS128 Gesture) whose files are on disk.

    Args:
        name: ``"dvsgesture"``.
        root: the folder the dataset lives in (Tonic's ``save_to``).
        split: ``"train"`` or ``"test"``.
        download: let Tonic download absent files (default: refuse, saying where they go).

    Raises:
        ValueError: if the files are absent (and ``download`` is false), saying where they go.
    """

    def __init__(self, name: str, *, root: str | Path, split: str,
                 download: bool = False) -> None:
        self.name = check_choice("dataset", name, tuple(_TONIC_CLASSES))
        self.split = check_choice("split", split, ("train", "test"))
        self.root = str(Path(root).expanduser().resolve())
        self.download = bool(download)
        self._data: Any = None
        data = self._dataset()
        cls = _tonic_class(self.name)
        self.sensor_size = tuple(cls.sensor_size)
        self.dtype = np.dtype(cls.dtype)
        self.classes = list(cls.classes)
        self._length = len(data)
        self._files = list(data.data)

    def _dataset(self) -> Any:
        """The Tonic dataset, opened on first use (and again in each worker process)."""
        if self._data is None:
            cls = _tonic_class(self.name)
            opener = cls if self.download else _without_download(cls)
            self._data = opener(self.root, train=self.split == "train")
        return self._data

    def __getstate__(self) -> dict[str, Any]:
        return dict(self.__dict__, _data=None)

    def __len__(self) -> int:
        return self._length

    def describe(self) -> dict[str, Any]:
        """JSON-ready facts that name the dataset (kept in a cache's manifest)."""
        return {"name": self.name, "root": self.root, "split": self.split,
                "sensor_size": list(self.sensor_size)}

    def source_name(self, index: int) -> str:
        """Where recording ``index`` comes from, for messages."""
        return str(self._files[index])

    def load(self, index: int) -> tuple[np.ndarray, int]:
        """Recording ``index``: ``(events, label)``."""
        return self._dataset()[index]


def _tonic_class(name: str) -> Any:
    """The ``tonic.datasets`` class of dataset ``name``."""
    try:
        import tonic.datasets
    except ImportError:
        raise ValueError(
            f"--dataset {name} needs tonic: pip install 'evdown_torch[tonic]'"
        ) from None
    return getattr(tonic.datasets, _TONIC_CLASSES[name])


def _without_download(cls: Any) -> type:
    """A subclass of a Tonic dataset class that raises where Tonic would download.

    It also takes the extracted folder without its archive (Tonic wants both, as it checks
    the archive's presence to decide whether to download it): what it reads is the folder.
    """

    def extracted(self: Any) -> bool:
        folder = Path(self.location_on_system, self.folder_name)
        suffix = _TONIC_RECORDINGS[cls.__name__]
        return bool(cls._check_exists(self)) or (
            folder.is_dir() and any(p.is_file() for p in folder.rglob(f"*{suffix}")))

    def refuse(self: Any) -> None:
        folder = Path(self.location_on_system)
        raise ValueError(
            f"the {cls.__name__} files are absent: put the extracted folder "
            f"{self.folder_name}/ (from {self.filename}) in {folder} "
            f"(tonic.datasets.{cls.__name__}(save_to={str(folder.parent)!r}) downloads them "
            "there)"
        )

    return type(cls.__name__, (cls,), {"_check_exists": extracted, "download": refuse})


#: N-MNIST's split folders.
NMNIST_SPLITS = {"train": "Train", "test": "Test"}

#: Problems listed in full in a refusal; more are counted.
_SHOWN_PROBLEMS = 5


def nmnist_folder(root: str | Path, split: str) -> Path:
    """The folder of an N-MNIST split: ``ROOT/Train`` (``Test``), else ``ROOT/NMNIST/Train``.

    The second is where ``tonic.datasets.NMNIST(save_to=ROOT)`` extracts the dataset.

    Raises:
        ValueError: when neither exists, saying where the files go.
    """
    root = Path(root).expanduser().resolve()
    name = NMNIST_SPLITS[check_choice("split", split, tuple(NMNIST_SPLITS))]
    for folder in (root / name, root / "NMNIST" / name):
        if folder.is_dir():
            return folder
    raise ValueError(
        f"the N-MNIST files are absent: no {name}/ folder in {str(root)!r} nor in "
        f"{str(root / 'NMNIST')!r} (N-MNIST's layout is {name}/<digit>/<id>.bin, as "
        f"tonic.datasets.NMNIST(save_to={str(root)!r}) extracts it in {str(root / 'NMNIST')!r})"
    )


class NMNISTSource:
    """N-MNIST (Orchard et al. 2015) read from a folder in its own layout.

    ``ROOT/Train/<digit>/<id>.bin`` and ``ROOT/Test/<digit>/<id>.bin`` (or the same under
    ``ROOT/NMNIST/``, where Tonic puts it), any number of recordings per digit; the label is
    the digit of the folder. Files are read with ``tonic.io.read_mnist_file`` (through
    :func:`evdown_torch.io.read_events`) as :data:`~evdown_torch.events.DVS_DTYPE` arrays on
    the 34 x 34 ATIS crop, ``t`` in microseconds. The folder is checked when the source opens:
    every digit folder present and holding ``.bin`` files, and no file empty or truncated.

    Args:
        root: the folder holding ``Train/`` and ``Test/`` (or ``NMNIST/``).
        split: ``"train"`` or ``"test"``.

    Raises:
        ValueError: naming what is missing: the split folder, digit folders, recordings in a
            digit folder, or files that are empty or truncated (not whole 5-byte events).

    Example:
        >>> import tempfile
        >>> with tempfile.TemporaryDirectory() as root:
        ...     NMNISTSource(root, split="test")
        Traceback (most recent call last):
        ...
        ValueError: the N-MNIST files are absent: no Test/ folder in ...
    """

    name = "nmnist"

    def __init__(self, root: str | Path, *, split: str) -> None:
        self.split = check_choice("split", split, tuple(NMNIST_SPLITS))
        self.folder = nmnist_folder(root, self.split)
        self.sensor_size = NMNIST_SENSOR
        self.dtype = DVS_DTYPE
        self.classes = [str(digit) for digit in range(10)]
        missing = [c for c in self.classes if not (self.folder / c).is_dir()]
        if missing:
            raise ValueError(
                f"N-MNIST folder {str(self.folder)!r} lacks the class folder(s) "
                f"{', '.join(missing)}: it needs one folder per digit 0-9, each holding "
                "<id>.bin recordings"
            )
        self._items: list[tuple[str, int]] = []
        problems = []
        for label, digit in enumerate(self.classes):
            files = sorted(p for p in (self.folder / digit).iterdir()
                           if p.suffix == ".bin" and p.is_file())
            if not files:
                problems.append(f"class folder {digit}/ holds no .bin recording")
            for path in files:
                problems += self._check_file(path)
                self._items.append((f"{digit}/{path.name}", label))
        if problems:
            more = len(problems) - _SHOWN_PROBLEMS
            raise ValueError(
                f"N-MNIST folder {str(self.folder)!r} is incomplete: "
                + "; ".join(problems[:_SHOWN_PROBLEMS])
                + (f"; and {more} more" if more > 0 else "")
            )

    def _check_file(self, path: Path) -> list[str]:
        size = path.stat().st_size
        if size == 0:
            return [f"{path.parent.name}/{path.name} is empty"]
        try:
            check_nmnist_size(path, size)
        except ValueError:
            return [f"{path.parent.name}/{path.name} is truncated ({size} bytes, not whole "
                    "5-byte events)"]
        return []

    def __len__(self) -> int:
        return len(self._items)

    def describe(self) -> dict[str, Any]:
        """JSON-ready facts that name the dataset (kept in a cache's manifest)."""
        return {"name": self.name, "root": str(self.folder.parent), "split": self.split,
                "sensor_size": list(self.sensor_size), "files": len(self._items)}

    def source_name(self, index: int) -> str:
        """Where recording ``index`` comes from, for messages."""
        return str(self.folder / self._items[index][0])

    @property
    def labels(self) -> list[int]:
        """The label of every recording, in order (without reading the files)."""
        return [label for _, label in self._items]

    def load(self, index: int) -> tuple[np.ndarray, int]:
        """Recording ``index``: ``(events, label)``."""
        relative, label = self._items[index]
        return read_recording(self.folder / relative, self.sensor_size), label


class FolderSource:
    """Recording files under ``path/CLASS/...``, one recording per file, labels from folders.

    Class ``k`` is the ``k``-th subfolder of ``path`` in sorted order; each class folder is
    searched recursively for files with a suffix in :data:`RECORDING_SUFFIXES` (any case), in
    sorted order. Timestamps come in microseconds: a file's own unit is converted, and
    ``time_unit`` stands for files that state none. The dataset's dtype is that of the first
    file that reads; a file with another dtype is rejected like an unreadable one.

    Args:
        path: the dataset folder.
        sensor_size: ``(W, H, P)`` of files that do not record theirs.
        time_unit: the unit of ``t`` in files that do not state one (``"s"``, ``"ms"``,
            ``"us"``, ``"ns"``); ``None``: microseconds.
        columns: the column order of ``.npy`` files holding ``(N, 4)`` arrays.

    Raises:
        ValueError: if ``path`` is not a folder, has no class subfolders or no readable file.
    """

    name = "folder"

    def __init__(self, path: str | Path, *, sensor_size: tuple[int, int, int],
                 time_unit: str | None = None, columns: Any = FIELDS) -> None:
        self.path = Path(path).expanduser().resolve()
        if not self.path.is_dir():
            raise ValueError(f"dataset folder {str(self.path)!r} does not exist")
        self.sensor_size = check_sensor_size(sensor_size)
        self.time_unit = None if time_unit is None else check_unit_name(time_unit)
        self.columns = check_columns(columns)
        self.classes = sorted(p.name for p in self.path.iterdir() if p.is_dir())
        if not self.classes:
            raise ValueError(
                f"dataset folder {str(self.path)!r} has no class subfolders; expected "
                f"PATH/CLASS/FILE with FILE ending in {', '.join(RECORDING_SUFFIXES)}"
            )
        self._items: list[tuple[str, int]] = []
        for label, cls in enumerate(self.classes):
            files = sorted(p for p in (self.path / cls).rglob("*")
                           if p.suffix.lower() in RECORDING_SUFFIXES and p.is_file())
            self._items += [(p.relative_to(self.path).as_posix(), label) for p in files]
        if not self._items:
            raise ValueError(
                f"dataset folder {str(self.path)!r} holds no recording files "
                f"({', '.join(RECORDING_SUFFIXES)}) in its class subfolders"
            )
        self.dtype = self._first_dtype()

    def _first_dtype(self) -> np.dtype:
        for relative, _ in self._items:
            try:
                return self._read(relative).dtype
            except (OSError, ValueError):
                continue
        raise ValueError(f"no file under {str(self.path)!r} reads as a structured event array")

    def _read(self, relative: str) -> np.ndarray:
        return read_recording(self.path / relative, self.sensor_size, time_unit=self.time_unit,
                              columns=self.columns)

    def __len__(self) -> int:
        return len(self._items)

    def describe(self) -> dict[str, Any]:
        """JSON-ready facts that name the dataset (kept in a cache's manifest)."""
        reading = {"time_unit": self.time_unit} if self.time_unit is not None else {}
        if self.columns != FIELDS:
            reading["columns"] = ",".join(self.columns)
        return {"name": self.name, "path": str(self.path), "sensor_size": list(self.sensor_size),
                "files": len(self._items), **reading}

    def source_name(self, index: int) -> str:
        """Where recording ``index`` comes from, for messages."""
        return str(self.path / self._items[index][0])

    def load(self, index: int) -> tuple[np.ndarray, int]:
        """Recording ``index``: ``(events, label)``."""
        relative, label = self._items[index]
        events = self._read(relative)
        if events.dtype != self.dtype:
            raise ValueError(
                f"its dtype {events.dtype} differs from the dataset's {self.dtype} "
                "(the first readable file's)"
            )
        return events, label


def open_source(
    dataset: str,
    *,
    split: str = "train",
    root: str | Path | None = None,
    sensor_size: tuple[int, int, int] | None = None,
    samples_per_class: int | None = None,
    duration_us: int | None = None,
    seed: int | None = None,
    time_unit: str | None = None,
    columns: Any = None,
) -> SyntheticSource | TonicSource | NMNISTSource | FolderSource:
    """The source named by ``--dataset``.

    ``synthetic``, ``dvsgesture``, ``nmnist`` or ``folder:PATH``.

    Args:
        dataset: the source's name.
        split: ``"train"`` or ``"test"`` (synthetic and Tonic datasets).
        root: the folder Tonic's datasets live in (``save_to``; for N-MNIST, the folder
            holding ``Train/`` and ``Test/`` in its own layout also serves); required for them.
        sensor_size: ``(W, H, P)``; required for folders, the synthetic sensor (default
            ``(128, 128, 2)``), not accepted for Tonic datasets (theirs is fixed).
        samples_per_class: synthetic recordings per class (default 24).
        duration_us: synthetic recording length, microseconds (default 6 s).
        seed: synthetic dataset seed (default 0).
        time_unit: the unit of ``t`` in a folder's files that state none (folders only).
        columns: the column order of a folder's ``(N, 4)`` ``.npy`` files (folders only).

    Raises:
        ValueError: for an unknown dataset, a missing or foreign option, absent files.

    Example:
        >>> src = open_source("synthetic", samples_per_class=1, duration_us=100_000,
        ...                   sensor_size=(16, 16, 2))
        >>> len(src), src.sensor_size
        (11, (16, 16, 2))
    """
    if not isinstance(dataset, str):
        raise TypeError(f"dataset must be a string, got {dataset!r}")
    synthetic_options = {"samples_per_class": samples_per_class, "duration_us": duration_us,
                         "seed": seed}
    if dataset != "synthetic":
        given = [name for name, value in synthetic_options.items() if value is not None]
        if given:
            raise ValueError(f"{given[0]} is a setting of the synthetic dataset only")
    if dataset.startswith("folder:"):
        if root is not None:
            raise ValueError("--root is for Tonic datasets; a folder dataset is folder:PATH")
        if sensor_size is None:
            raise ValueError("a folder dataset needs --sensor-size W H P")
        return FolderSource(dataset[len("folder:"):], sensor_size=sensor_size,
                            time_unit=time_unit, columns=FIELDS if columns is None else columns)
    reading = [name for name, value in (("time_unit", time_unit), ("columns", columns))
               if value is not None]
    if reading:
        raise ValueError(f"{reading[0]} is a setting of folder datasets only (the other "
                         "datasets' timestamps are microseconds)")
    if dataset == "synthetic":
        if root is not None:
            raise ValueError("--root is for Tonic datasets, not synthetic")
        defaults = {"samples_per_class": 24, "duration_us": 6_000_000, "seed": 0}
        options = {k: defaults[k] if v is None else v for k, v in synthetic_options.items()}
        return SyntheticSource(split=split, sensor_size=sensor_size or (128, 128, 2), **options)
    if dataset in (*_TONIC_CLASSES, "nmnist"):
        if root is None:
            raise ValueError(f"--dataset {dataset} needs --root DIR, the folder its files are in")
        if sensor_size is not None:
            raise ValueError(f"{dataset} has a fixed sensor size; drop --sensor-size")
        if dataset == "nmnist":
            return NMNISTSource(root, split=split)
        return TonicSource(dataset, root=root, split=split)
    raise ValueError(
        f"unknown dataset {dataset!r}; expected synthetic, dvsgesture, nmnist or folder:PATH"
    )


def check_label(value: Any) -> int:
    """A recording's label as an int (the cache stores integer labels)."""
    try:
        return operator.index(value)
    except TypeError:
        raise TypeError(f"labels must be integers, got {value!r}") from None
