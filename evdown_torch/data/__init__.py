"""Whole datasets, downscaled once: ``evdown preprocess`` and the dataset that reads its cache.

* :func:`open_source` names a dataset (synthetic gestures, Tonic's DVSGesture, N-MNIST in its
  own folder layout (:class:`NMNISTSource`), a folder of ``.npy`` recordings),
  :func:`preprocess` downscales it into ``.npy`` shards with a JSON manifest (worker processes
  on one machine, ranks under ``torchrun``; resumable);
* :class:`PreprocessedDataset` reads the cache back as Tonic structured arrays, with
  ``transform=`` like Tonic datasets; :func:`verify_cache` checks its checksums.
"""

from evdown_torch.data.dataset import PreprocessedDataset, verify_cache
from evdown_torch.data.preprocessing import PreprocessResult, RecordingError, preprocess
from evdown_torch.data.sources import NMNISTSource, open_source, read_recording

__all__ = [
    "NMNISTSource",
    "PreprocessResult",
    "PreprocessedDataset",
    "RecordingError",
    "open_source",
    "preprocess",
    "read_recording",
    "verify_cache",
]
