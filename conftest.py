"""Collection across the repository: the doctests of modules that import Numba need Numba.

The compiled loops (``evdown_torch/transforms/functional/compiled/``, all but its switch and
tables) import Numba when imported; without it (an optional dependency: the ``compiled``
extra) their doctests, and the floor's (:mod:`evdown_torch.bench.floor`), are not collected.
The tests of the compiled paths skip themselves (``pytest.importorskip("numba")``).
"""

import importlib.util

collect_ignore_glob: list[str] = []
if importlib.util.find_spec("numba") is None:
    collect_ignore_glob += [
        "evdown_torch/transforms/functional/compiled/[!_r]*.py",  # not __init__, regions
        "evdown_torch/transforms/functional/compiled/_numba.py",
        "evdown_torch/bench/floor.py",
    ]
