"""The study's disk cache: files named by a hash of the settings that made them.

A recording, a low-resolution render, a cell's frames, a calibration or a trained seed's
predictions is stored under ``ROOT/KIND/HASH.EXT``, where ``HASH`` digests a JSON document of
every setting that determines it, including a fingerprint of the source code that computes it
(so editing the generator or a kernel invalidates what they produced). A second run with the
same settings reads instead of computing; ``evdown evaluate --no-cache`` runs in a fresh
temporary directory that is removed afterwards. Files are written to a temporary name and
renamed, so an interrupted run never leaves half a file under a valid name.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["Cache", "code_fingerprint"]

_PACKAGE = Path(__file__).resolve().parents[1]


@functools.cache
def code_fingerprint(*parts: str) -> str:
    """A digest of the package's source files under ``parts`` (paths relative to the package).

    Example:
        >>> len(code_fingerprint("synthetic")), code_fingerprint("frames.py") != ""
        (16, True)
    """
    digest = hashlib.blake2b(digest_size=8)
    for part in parts:
        path = _PACKAGE / part
        files = sorted(path.rglob("*.py")) if path.is_dir() else [path]
        for file in files:
            digest.update(str(file.relative_to(_PACKAGE)).encode())
            digest.update(file.read_bytes())
    return digest.hexdigest()


class Cache:
    """Files keyed by settings under one root directory.

    Args:
        root: the directory (created when needed); ``None`` for a temporary directory that
            :meth:`close` removes.
    """

    def __init__(self, root: str | Path | None) -> None:
        self.temporary = root is None
        self.root = Path(tempfile.mkdtemp(prefix="evdown-cache-")) if root is None else Path(root)

    def close(self) -> None:
        """Remove a temporary cache; a persistent one stays."""
        if self.temporary:
            shutil.rmtree(self.root, ignore_errors=True)

    def path(self, kind: str, key: dict[str, Any], suffix: str) -> Path:
        """Where the item of ``kind`` with settings ``key`` lives."""
        text = json.dumps(key, sort_keys=True, default=str)
        name = hashlib.blake2b(text.encode(), digest_size=12).hexdigest()
        return self.root / kind / f"{name}{suffix}"

    @staticmethod
    def _replace(path: Path, write: Callable[[str], object]) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".part")
        os.close(handle)
        try:
            write(temporary)
            os.replace(temporary, path)
        finally:
            if os.path.exists(temporary):
                os.remove(temporary)

    def save_array(self, path: Path, array: np.ndarray) -> None:
        """Store a NumPy array (``np.save``)."""

        def write(name: str) -> None:
            with open(name, "wb") as handle:
                np.save(handle, array, allow_pickle=False)

        self._replace(path, write)

    @staticmethod
    def load_array(path: Path) -> np.ndarray:
        """A NumPy array saved by :meth:`save_array` (no pickles)."""
        return np.load(path, allow_pickle=False)

    def save_tensors(self, path: Path, tensors: dict[str, torch.Tensor]) -> None:
        """Store a dict of tensors (``torch.save``)."""
        self._replace(path, lambda name: torch.save(tensors, name))

    @staticmethod
    def load_tensors(path: Path) -> dict[str, torch.Tensor]:
        """Tensors saved by :meth:`save_tensors` (weights only)."""
        return torch.load(path, weights_only=True)

    def save_json(self, path: Path, value: Any) -> None:
        """Store a JSON document."""
        self._replace(path, lambda name: Path(name).write_text(json.dumps(value),
                                                               encoding="utf-8"))

    @staticmethod
    def load_json(path: Path) -> Any:
        """A JSON document saved by :meth:`save_json`."""
        return json.loads(path.read_text(encoding="utf-8"))
