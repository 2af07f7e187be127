"""Shared fixtures: devices (absent ones skip) x timestamp dtypes, the kernel paths, seeded
generators, the real recording and LIF pooling's closed form forced on.

As in Kornia's test suite, ``device`` and ``dtype`` are separate parametrized fixtures: a test
that takes both runs on every available device for every dtype.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from evdown_torch import eager_kernels
from evdown_torch.transforms.functional.lif import closed_form as lif_closed_form
from evdown_torch.transforms.functional.lif import pooling as lif_kernel

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
NMNIST_FILE = SHARED_DATA / "sample_nmnist.bin"

#: The ``device`` fixture's parameters; the CUDA one is marked ``cuda`` (``pytest -m cuda``
#: runs the tests on CUDA alone: ``benchmarks/gpu_check.py``) and skips without CUDA.
DEVICES = [
    "cpu",
    pytest.param(
        "cuda",
        marks=[pytest.mark.cuda,
               pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")],
    ),
]


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    """Every available device; CUDA skips when absent."""
    return torch.device(request.param)


#: The dtypes of tensor events: integer timestamps (Tonic's microseconds) and float ones.
DTYPES = [torch.int64, torch.float64]


@pytest.fixture(params=DTYPES, ids=lambda dtype: str(dtype).removeprefix("torch."))
def dtype(request) -> torch.dtype:
    """Every dtype of ``(N, 4)`` event tensors: int64 and float64 timestamps."""
    return request.param


#: The two kernel paths on the CPU: Numba's compiled loops and eager torch.
KERNEL_PATHS = ["compiled", "eager"]


@pytest.fixture(params=KERNEL_PATHS)
def kernels(request) -> Iterator[str]:
    """Each kernel path in turn, the test running inside it (compiled: skips without numba)."""
    if request.param == "compiled":
        pytest.importorskip("numba")
    with eager_kernels(request.param == "eager"):
        yield request.param


@pytest.fixture
def eager() -> Iterator[None]:
    """The eager kernels, forced for the test (one that watches their internal steps)."""
    with eager_kernels():
        yield


@pytest.fixture
def rng() -> np.random.Generator:
    """A fresh, seeded NumPy generator for each test."""
    return np.random.default_rng(12345)


@pytest.fixture
def nmnist():
    """The real N-MNIST sample as a Tonic structured array (skips without tonic or file)."""
    tonic = pytest.importorskip("tonic")
    if not NMNIST_FILE.exists():
        pytest.skip(f"{NMNIST_FILE} is absent")
    return tonic.io.read_mnist_file(str(NMNIST_FILE), dtype=tonic.datasets.NMNIST.dtype)


@pytest.fixture
def lif_closed_form_answers(monkeypatch) -> Iterator[list[bool]]:
    """The closed form tried on every call (not only those of ``MIN_ROUNDS`` rounds or more);
    the list records, per call, whether it answered (``False``: left to the rounds). The test
    runs on the eager path, whose choice the closed form is (the compiled rounds cost less)."""
    calls: list[bool] = []

    def recording(*args, **kwargs):
        out = lif_closed_form.certain_spikes(*args, **kwargs)
        calls.append(out is not None)
        return out

    monkeypatch.setattr(lif_kernel, "MIN_ROUNDS", 1)
    monkeypatch.setattr(lif_kernel, "certain_spikes", recording)
    with eager_kernels():
        yield calls


@pytest.fixture(autouse=True)
def _doctest_seed(doctest_namespace):
    torch.manual_seed(0)
