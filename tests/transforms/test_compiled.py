"""The switch between the compiled CPU kernels and the eager ones; Numba absent, broken, cold."""

from __future__ import annotations

import importlib.abc
import json
import os
import shutil
import subprocess
import sys
import threading
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from evdown_torch import EventCount, eager_kernels, kernel_path
from evdown_torch.transforms.functional.compiled import EAGER_VARIABLE, numba_available
from evdown_torch.transforms.registry import make_method
from tests.helpers import random_stream, run_in_threads

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def with_numba():
    pytest.importorskip("numba")


@pytest.fixture(autouse=True)
def _no_variable(monkeypatch):
    monkeypatch.delenv(EAGER_VARIABLE, raising=False)


def test_the_cpu_takes_the_compiled_path_and_other_devices_the_eager_one(with_numba):
    assert kernel_path() == kernel_path("cpu") == "compiled"
    assert kernel_path("meta") == kernel_path(torch.device("meta")) == "eager"


def test_blocks_force_the_eager_path_nest_and_restore_however_they_end(with_numba):
    with eager_kernels() as eager:
        assert eager is True and kernel_path() == "eager"
        with eager_kernels(False):
            assert kernel_path() == "compiled"
        assert kernel_path() == "eager"
        with pytest.raises(RuntimeError), eager_kernels(False):
            raise RuntimeError("leaves the block")
        assert kernel_path() == "eager"
    assert kernel_path() == "compiled"

    @eager_kernels()
    def inside() -> str:
        return kernel_path()

    assert inside() == "eager" and kernel_path() == "compiled"


def test_the_environment_variable_sets_the_default_and_a_block_overrides_it(
    with_numba, monkeypatch
):
    for value in ("1", "true", " YES ", "on"):
        monkeypatch.setenv(EAGER_VARIABLE, value)
        assert kernel_path() == "eager"
        with eager_kernels(False):
            assert kernel_path() == "compiled"
    for value in ("0", "", "false", "off"):
        monkeypatch.setenv(EAGER_VARIABLE, value)
        assert kernel_path() == "compiled"


def test_a_bad_variable_or_setting_is_an_error_naming_it(monkeypatch):
    monkeypatch.setenv(EAGER_VARIABLE, "sometimes")
    with pytest.raises(ValueError, match="EVDOWN_EAGER must be 1 .* or 0 .*, got 'sometimes'"):
        kernel_path()
    with pytest.raises(TypeError, match="eager must be True or False, got 'yes'"):
        eager_kernels("yes")  # type: ignore[arg-type]


def test_a_block_in_one_thread_does_not_apply_in_another(with_numba):
    seen, entered, checked = {}, threading.Event(), threading.Event()

    def forcing() -> None:
        with eager_kernels():
            entered.set()
            checked.wait(timeout=30)
            seen["inside"] = kernel_path()

    def other() -> None:
        entered.wait(timeout=30)
        seen["other"] = kernel_path()
        checked.set()

    run_in_threads(forcing, other)
    assert seen == {"inside": "eager", "other": "compiled"}


class _BrokenNumba(importlib.abc.MetaPathFinder):
    """Finds ``numba`` and fails to import it, as a Numba built for another NumPy does."""

    def find_spec(self, name, path=None, target=None):
        if name == "numba":
            raise ImportError("Numba needs NumPy 2.2 or less")
        return None


@pytest.mark.parametrize("how", ["absent", "broken"])
def test_without_a_working_numba_the_eager_kernels_run(how, monkeypatch, rng):
    arr = random_stream(rng, 300, (8, 8, 2))
    with eager_kernels():
        expected = EventCount((8, 8, 2), factor=2, threshold=0.25)(arr)
    monkeypatch.delitem(sys.modules, "numba", raising=False)
    if how == "absent":
        monkeypatch.setitem(sys.modules, "numba", None)
    else:
        monkeypatch.setattr(sys, "meta_path", [_BrokenNumba(), *sys.meta_path])
    numba_available.cache_clear()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            assert kernel_path() == "eager"
            out = EventCount((8, 8, 2), factor=2, threshold=0.25)(arr)
        np.testing.assert_array_equal(out, expected)
        messages = [str(w.message) for w in caught if w.category is RuntimeWarning]
        if how == "absent":
            assert messages == []
        else:
            assert messages == ["numba is installed but cannot be imported (Numba needs NumPy "
                                "2.2 or less); the eager kernels run instead"]
    finally:
        numba_available.cache_clear()


def test_importing_the_package_imports_no_numba():
    code = "import sys, evdown_torch; print(sorted(m for m in sys.modules if 'numba' in m))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=ROOT, check=True)
    assert out.stdout.strip() == "[]"


#: Every compiled method on a fixed stream, printed as JSON (run in a fresh process).
COLD_SCRIPT = """
import json, sys
import numpy as np
import evdown_torch
from evdown_torch.transforms.registry import make_method
from tests.helpers import random_stream

arr = random_stream(np.random.default_rng(7), 2000, (12, 9, 2), t_max=400)
out = {"path": evdown_torch.kernel_path()}
settings = json.loads(sys.argv[1])
for name in sys.argv[2:]:
    result = make_method(name, (12, 9, 2), (3, 2), **settings.get(name, {}))(arr)
    out[name] = [list(map(int, row)) for row in result.tolist()]
print(json.dumps(out))
"""

#: The methods with a compiled loop, and settings that make each run it (LIF pooling: steps
#: of 10 us, so that regions have many cells; the subsamplers: budgets that drop events).
#: The two estimators share one process: their window loops are two closures of one
#: function, which Numba's cache must keep apart.
COMPILED_METHODS = ["downsample", "funnelling", "event_count", "photocurrent", "lif", "linear",
                    "cubic", "density", "poisson"]
COLD_SETTINGS = {"lif": {"dt": 10, "tau": 40.0}, "density": {"tau": 40.0, "s": 0.2},
                 "poisson": {"window": 40, "alpha": 0.3}}


#: Both estimators on a fixed stream of int64 (or, with ``float``, float64) timestamps, as
#: JSON (a fresh process; the package from the ``PYTHONPATH`` the test gives).
ESTIMATORS_SCRIPT = """
import json, sys
import numpy as np
from evdown_torch.transforms.registry import make_method

rng = np.random.default_rng(3)
arr = np.zeros(3000, [("x", "<i2"), ("y", "<i2"), ("t", "<i8"), ("p", "?")])
arr["x"], arr["y"] = rng.integers(0, 12, 3000), rng.integers(0, 9, 3000)
arr["t"], arr["p"] = np.sort(rng.integers(0, 5000, 3000)), rng.random(3000) < 0.5
out = {}
for kind in sys.argv[1].split(","):
    stream = arr.astype([("x", "<i2"), ("y", "<i2"), ("t", "<f8"), ("p", "?")]) \\
        if kind == "float" else arr
    for name in sys.argv[2:]:
        result = make_method(name, (12, 9, 2), (3, 2), max_delay=50)(stream)
        out[f"{name} {kind}"] = [list(map(float, row)) for row in result.tolist()]
print(json.dumps(out))
"""


@pytest.mark.slow
def test_the_estimators_cached_by_other_processes_load_together(with_numba, tmp_path):
    # The sequence that failed, on a copy of the package: both window loops cached for int64
    # and float64 times by one process; the loops' source changed (an upgrade, an edit);
    # LinearEstimation's loop compiled again by a process, CubicEstimation's by one that read
    # the first from the cache; a fourth process that read both failed on the second (a
    # SystemError from the dispatcher, "NRT_adapt_ndarray_to_python: descr is NULL"). Both
    # loops had one qualified name; each has its own now.
    shutil.copytree(ROOT / "evdown_torch", tmp_path / "evdown_torch",
                    ignore=shutil.ignore_patterns("__pycache__"))
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"),
           "PYTHONPATH": str(tmp_path)}
    env.pop(EAGER_VARIABLE, None)

    def run(kinds: str, *names: str) -> dict:
        done = subprocess.run([sys.executable, "-c", ESTIMATORS_SCRIPT, kinds, *names],
                              capture_output=True, text=True, cwd=tmp_path, env=env)
        assert done.returncode == 0, done.stderr[-2000:]
        return json.loads(done.stdout)

    before = run("int,float", "linear", "cubic")
    loops = tmp_path / "evdown_torch" / "transforms" / "functional" / "compiled" / "estimation.py"
    with loops.open("a", encoding="utf-8") as source:
        source.write("# changed\n")
    run("int", "linear")
    run("int", "linear", "cubic")
    after = run("int", "linear", "cubic")
    assert after == {key: before[key] for key in after}
    assert after["linear int"] and after["cubic int"]


@pytest.mark.slow
def test_a_change_to_a_function_a_loop_calls_from_another_file_reaches_the_cached_loop(
        with_numba, tmp_path):
    # Numba's cache checks only the file that defines a loop: LinearEstimation's window loop
    # (estimation.py) cached, then a function it calls changed in knots.py alone (every level
    # change read as 0: no crossings), ran the old code from the cache. On a copy of the
    # package, with its own in-tree cache (the default place).
    shutil.copytree(ROOT / "evdown_torch", tmp_path / "evdown_torch",
                    ignore=shutil.ignore_patterns("__pycache__"))
    env = {**os.environ, "PYTHONPATH": str(tmp_path)}
    env.pop(EAGER_VARIABLE, None)
    env.pop("NUMBA_CACHE_DIR", None)
    compiled = tmp_path / "evdown_torch" / "transforms" / "functional" / "compiled"

    def run() -> list:
        done = subprocess.run([sys.executable, "-c", ESTIMATORS_SCRIPT, "float", "linear"],
                              capture_output=True, text=True, cwd=tmp_path, env=env)
        assert done.returncode == 0, done.stderr[-2000:]
        return json.loads(done.stdout)["linear float"]

    def cached() -> set[str]:
        return {path.name for path in (compiled / "__pycache__").glob("*.nb[ic]")}

    assert run()  # crossings, and the window loop cached
    first = cached()
    assert any("window_loop_linear" in name for name in first)
    knots = compiled / "knots.py"
    source = knots.read_text(encoding="utf-8")
    changed = source.replace("    return (packed << 32) >> 32\n", "    return 0 * packed\n")
    assert changed != source
    knots.write_text(changed, encoding="utf-8")
    assert run() == []
    assert not first & cached()  # the files of the sources before were removed


@pytest.mark.slow
def test_a_fresh_process_with_a_cold_cache_gives_the_same_events(with_numba, tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"),
           "PYTHONPATH": str(ROOT)}
    env.pop(EAGER_VARIABLE, None)
    runs = []
    for _ in range(2):  # cold, then from the cache the first run wrote
        done = subprocess.run([sys.executable, "-c", COLD_SCRIPT, json.dumps(COLD_SETTINGS),
                               *COMPILED_METHODS],
                              capture_output=True, text=True, cwd=ROOT, env=env, check=True)
        runs.append(json.loads(done.stdout))
    assert list((tmp_path / "cache").rglob("*.nbi"))  # the loops were cached there
    arr = random_stream(np.random.default_rng(7), 2000, (12, 9, 2), t_max=400)
    with eager_kernels():
        eager = {name: [list(map(int, row)) for row in
                        make_method(name, (12, 9, 2), (3, 2),
                                    **COLD_SETTINGS.get(name, {}))(arr).tolist()]
                 for name in COMPILED_METHODS}
    for run in runs:
        assert run.pop("path") == "compiled"
        assert run == eager
        assert all(run[name] for name in COMPILED_METHODS)
