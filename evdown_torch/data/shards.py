"""The on-disk format of a preprocessed dataset: ``.npy`` shards and a JSON manifest.

A cache folder holds, for each shard ``k`` (``NAME = shard-{k:05d}``):

* ``NAME.events.npy``: the downscaled events of the shard's recordings, concatenated, as one
  structured array in the dataset's dtype (Tonic's format);
* ``NAME.index.npy``: one row per recording kept, a structured array of :data:`INDEX_DTYPE`
  (``index``: the recording's index in the source dataset, ``label``, and ``start``/``stop``:
  its slice of the events array);
* ``NAME.json``: the shard's record (counts, SHA-256 of both ``.npy`` files, the recordings
  skipped and why), written last, so that a shard without it is incomplete.

``job.json`` names the job (dataset, method, settings, shard size, package version); a folder
holds one job only. ``manifest.json``, written once every shard is done, gathers the job and
every shard's record. Every file is written under a temporary name and renamed into place, so
a file with its final name is never half written. Plain ``.npy`` (NumPy's documented format)
keeps the bytes a pure function of the data, so checksums agree between runs, ranks and
machines, and shards open memory-mapped in any number of ``DataLoader`` workers.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import socket
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

__all__ = [
    "FORMAT",
    "FORMAT_VERSION",
    "INDEX_DTYPE",
    "JOB",
    "MANIFEST",
    "dtype_from_json",
    "dtype_to_json",
    "file_sha256",
    "read_json",
    "read_shard_record",
    "remove_stale_temporaries",
    "shard_files",
    "shard_name",
    "shard_problem",
    "write_json",
    "write_shard",
]

FORMAT = "evdown-cache"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"
JOB = "job.json"

#: One row per recording of a shard: source index, label, and its slice of the events array.
INDEX_DTYPE = np.dtype([("index", "<i8"), ("label", "<i8"), ("start", "<i8"), ("stop", "<i8")])


def shard_name(shard: int) -> str:
    """``shard-{shard:05d}``, the stem of shard ``shard``'s files."""
    return f"shard-{shard:05d}"


def shard_files(shard: int) -> tuple[str, str, str]:
    """File names ``(events, index, record)`` of shard ``shard``."""
    name = shard_name(shard)
    return f"{name}.events.npy", f"{name}.index.npy", f"{name}.json"


def file_sha256(path: Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def dtype_to_json(dtype: np.dtype) -> list:
    """A structured dtype as JSON (NumPy's ``descr``, tuples as lists)."""
    return [list(item) for item in np.lib.format.dtype_to_descr(dtype)]


def dtype_from_json(descr: list) -> np.dtype:
    """The inverse of :func:`dtype_to_json`."""
    return np.lib.format.descr_to_dtype([tuple(item) for item in descr])


def _temporary(path: Path) -> Path:
    # Host and process in the name: ranks on several machines may share the folder.
    return path.with_name(f".{path.name}.tmp-{socket.gethostname()}-{os.getpid()}")


def _save_array(handle: BinaryIO, array: np.ndarray) -> None:
    np.save(handle, array, allow_pickle=False)


def _replace_atomically(path: Path, write: Callable[[BinaryIO], object]) -> None:
    temporary = _temporary(path)
    try:
        with open(temporary, "wb") as handle:
            write(handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(temporary, path)
    finally:
        if temporary.exists():
            temporary.unlink()


def write_json(path: Path, content: dict[str, Any]) -> None:
    """Write ``content`` as indented JSON under a temporary name, then rename it to ``path``."""
    text = json.dumps(content, indent=1, sort_keys=True) + "\n"
    _replace_atomically(Path(path), lambda handle: handle.write(text.encode()))


def read_json(path: Path) -> dict[str, Any]:
    """Read a JSON object written by :func:`write_json`.

    Raises:
        ValueError: if the file is not valid JSON holding an object.
    """
    try:
        content = json.loads(Path(path).read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"{str(path)!r} is not valid JSON: {error}") from None
    if not isinstance(content, dict):
        raise ValueError(f"{str(path)!r} does not hold a JSON object")
    return content


def remove_stale_temporaries(directory: Path, shard: int) -> None:
    """Delete temporary files a killed run left behind for shard ``shard``."""
    for name in shard_files(shard):
        for stale in Path(directory).glob(f".{name}.tmp-*"):
            stale.unlink(missing_ok=True)


def write_shard(
    directory: Path,
    shard: int,
    events: np.ndarray,
    index: np.ndarray,
    record: dict[str, Any],
) -> dict[str, Any]:
    """Write one shard: both arrays, then its record with their checksums.

    Args:
        directory: the cache folder.
        shard: shard number.
        events: ``(E,)`` structured events of the shard's recordings, concatenated.
        index: ``(R,)`` array of :data:`INDEX_DTYPE`.
        record: the shard's other facts (job id, counts, skipped recordings); JSON-able.

    Returns:
        The record as written: ``record`` plus ``shard``, ``files`` and ``sha256``.
    """
    directory = Path(directory)
    events_name, index_name, record_name = shard_files(shard)
    checksums = {}
    for name, array in ((events_name, events), (index_name, index)):
        _replace_atomically(directory / name, functools.partial(_save_array, array=array))
        checksums[name] = file_sha256(directory / name)
    full = dict(record, shard=shard, files={"events": events_name, "index": index_name},
                sha256=checksums)
    write_json(directory / record_name, full)
    return full


def shard_problem(directory: Path, record: dict[str, Any]) -> str | None:
    r"""Why shard ``record`` is not intact in ``directory`` (a missing or altered file), or None.

    Example:
        >>> import tempfile
        >>> folder = Path(tempfile.mkdtemp())
        >>> ev = np.zeros(3, dtype=[("x", "<i2"), ("y", "<i2"), ("p", "?"), ("t", "<i8")])
        >>> rec = write_shard(folder, 0, ev, np.zeros(1, dtype=INDEX_DTYPE), {"job": "j"})
        >>> shard_problem(folder, rec) is None
        True
        >>> with open(folder / rec["files"]["events"], "r+b") as f:
        ...     _ = f.seek(-1, 2); _ = f.write(b"\x01")
        >>> shard_problem(folder, rec).endswith("differs from its record (corrupt)")
        True
    """
    for name, expected in sorted(record.get("sha256", {}).items()):
        path = Path(directory) / name
        if not path.is_file():
            return f"{str(path)!r} is missing"
        if file_sha256(path) != expected:
            return f"the checksum of {str(path)!r} differs from its record (corrupt)"
    return None


def read_shard_record(directory: Path, shard: int, job_id: str) -> dict[str, Any] | None:
    """Shard ``shard``'s record if the shard is complete, intact and from job ``job_id``."""
    path = Path(directory) / shard_files(shard)[2]
    if not path.is_file():
        return None
    try:
        record = read_json(path)
    except (OSError, ValueError):
        return None
    if record.get("job") != job_id or record.get("shard") != shard:
        return None
    if set(record.get("sha256", {})) != set(shard_files(shard)[:2]):
        return None
    return None if shard_problem(directory, record) is not None else record
