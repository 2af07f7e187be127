"""``PreprocessedDataset``: a cache written by ``evdown preprocess``, read like a Tonic dataset."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from evdown_torch.checks import check_item_index
from evdown_torch.collate import apply_item_transforms
from evdown_torch.data import shards

__all__ = ["PreprocessedDataset", "verify_cache"]


def _read_manifest(root: Path) -> dict[str, Any]:
    path = root / shards.MANIFEST
    if not path.is_file():
        raise ValueError(
            f"{str(root)!r} has no {shards.MANIFEST}: not a finished evdown cache (an "
            "interrupted `evdown preprocess` finishes when rerun with the same arguments)"
        )
    manifest = shards.read_json(path)
    if manifest.get("format") != shards.FORMAT:
        raise ValueError(f"{str(path)!r} is not an {shards.FORMAT} manifest")
    if manifest.get("format_version") != shards.FORMAT_VERSION:
        raise ValueError(
            f"{str(path)!r} has format version {manifest.get('format_version')!r}; this "
            f"evdown_torch reads version {shards.FORMAT_VERSION}"
        )
    missing = [key for key in _MANIFEST_KEYS if key not in manifest]
    if missing:
        raise ValueError(f"{str(path)!r} lacks {', '.join(map(repr, missing))}: a damaged "
                         f"{shards.FORMAT} manifest; {_REDO}")
    records = manifest["shards"]
    if not isinstance(records, list) or not all(_is_record(r) for r in records):
        raise ValueError(f"{str(path)!r} has 'shards' that are not shard records (files and "
                         f"checksums): a damaged {shards.FORMAT} manifest; {_REDO}")
    return manifest


#: What a manifest must hold beside its format: what reading the cache uses.
_MANIFEST_KEYS = ("method", "factor", "output_sensor_size", "classes", "dtype", "shards")

_REDO = "rerun `evdown preprocess` with the same arguments to redo it"


def _is_record(record: Any) -> bool:
    """A shard record: its two files and their checksums."""
    return (isinstance(record, dict) and isinstance(record.get("files"), dict)
            and {"events", "index"} <= set(record["files"])
            and isinstance(record.get("sha256"), dict))


def verify_cache(root: str | Path) -> list[str]:
    """Check every shard of a cache against the checksums of its manifest.

    Args:
        root: the cache folder.

    Returns:
        One message per missing or corrupt file; empty when the cache is intact.

    Raises:
        ValueError: if ``root`` holds no readable manifest.
    """
    root = Path(root)
    manifest = _read_manifest(root)
    problems = (shards.shard_problem(root, record) for record in manifest["shards"])
    return [p for p in problems if p is not None]


class PreprocessedDataset:
    """Recordings downscaled by ``evdown preprocess``, with the interface of Tonic datasets.

    Items are ``(events, label)``: a structured array in the cache's dtype (the source
    dataset's, e.g. ``x``, ``y`` int16, ``p`` bool, ``t`` int64 microseconds for gestures),
    sorted by ``t``, on the downscaled sensor ``sensor_size``, after ``transform`` /
    ``target_transform`` / ``transforms`` as in Tonic. Each item is a fresh array (shards are
    memory-mapped and sliced), so transforms may modify it. Recordings the run skipped are
    absent; ``source_indices`` maps items to the source dataset's indices.

    Args:
        root: the cache folder (``--out`` of ``evdown preprocess``).
        transform: applied to the events.
        target_transform: applied to the label.
        transforms: applied to ``(events, label)`` together, last.
        verify: check every shard's SHA-256 against the manifest when opening (reads the
            whole cache once).

    Attributes:
        manifest: the manifest (method, settings, package version, counts, shards).
        sensor_size: the downscaled sensor ``(W', H', P)``.
        classes: class names of the source dataset.
        dtype: the event dtype; ``ordering``: its field names.
        targets: the label of every item.
        source_indices: the source dataset's index of every item.

    Raises:
        ValueError: if ``root`` is not a finished cache, its manifest is damaged (not
            JSON, another format or version, a key or a shard's record missing), or
            (``verify``) a shard is missing or corrupt, naming the file.

    Example:
        >>> import tempfile
        >>> from evdown_torch.data import open_source, preprocess
        >>> out = tempfile.mkdtemp()
        >>> src = open_source("synthetic", samples_per_class=1, duration_us=100_000,
        ...                   sensor_size=(16, 16, 2))
        >>> _ = preprocess(src, out, "event_count", 2, {"threshold": 0.5}, workers=1)
        >>> data = PreprocessedDataset(out)
        >>> events, label = data[3]
        >>> len(data), data.sensor_size, label, events.dtype == src.dtype
        (11, (8, 8, 2), 3, True)
    """

    def __init__(
        self,
        root: str | Path,
        transform: Callable | None = None,
        target_transform: Callable | None = None,
        transforms: Callable | None = None,
        *,
        verify: bool = True,
    ) -> None:
        for name, fn in (("transform", transform), ("target_transform", target_transform),
                         ("transforms", transforms)):
            if fn is not None and not callable(fn):
                raise TypeError(f"{name} must be callable or None, got {fn!r}")
        self.root = Path(root)
        self.transform = transform
        self.target_transform = target_transform
        self.transforms = transforms
        self.manifest = _read_manifest(self.root)
        if verify:
            problems = verify_cache(self.root)
            if problems:
                raise ValueError(
                    f"{problems[0]}; rerun `evdown preprocess` with the same arguments to "
                    f"redo it ({len(problems)} problem(s) in {str(self.root)!r})"
                )
        self.sensor_size = tuple(self.manifest["output_sensor_size"])
        self.classes = list(self.manifest["classes"])
        self.dtype = shards.dtype_from_json(self.manifest["dtype"])
        self.ordering = self.dtype.names
        records = self.manifest["shards"]
        indexes = [np.load(self.root / r["files"]["index"], allow_pickle=False) for r in records]
        self._events_files = [r["files"]["events"] for r in records]
        self._shard = np.concatenate(
            [np.full(len(ix), k, dtype=np.int64) for k, ix in enumerate(indexes)]
            or [np.empty(0, dtype=np.int64)])
        index = np.concatenate(indexes) if indexes else np.empty(0, dtype=shards.INDEX_DTYPE)
        self._start, self._stop = index["start"], index["stop"]
        self.targets = index["label"].tolist()
        self.source_indices = index["index"].tolist()
        self._events: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.targets)

    def _shard_events(self, shard: int) -> np.ndarray:
        if shard not in self._events:
            path = self.root / self._events_files[shard]
            events = np.load(path, allow_pickle=False, mmap_mode="r")
            if events.dtype != self.dtype:
                raise ValueError(f"{str(path)!r} holds dtype {events.dtype}, "
                                 f"the manifest says {self.dtype}")
            self._events[shard] = events
        return self._events[shard]

    def __getitem__(self, index: int) -> tuple[Any, Any]:
        """``(events, label)`` of item ``index``, after the transforms."""
        index = check_item_index(index, len(self), "recordings")
        shard_events = self._shard_events(int(self._shard[index]))
        events: Any = np.array(shard_events[self._start[index]:self._stop[index]])
        target: Any = self.targets[index]
        return apply_item_transforms(self, events, target)

    def __repr__(self) -> str:
        m = self.manifest
        return (f"PreprocessedDataset({str(self.root)!r}: {len(self)} recordings, "
                f"{m['method']} x{tuple(m['factor'])}, sensor {self.sensor_size})")
