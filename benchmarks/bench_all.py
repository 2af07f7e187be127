"""Every method against its peers, scaling curves and peak memory: ``evdown bench`` as a script.

Run: ``python benchmarks/bench_all.py --out DIR [--short] [--input FILE.npy ...]``; it takes
the options of ``evdown bench`` (see ``evdown bench --help``) and drives
:mod:`evdown_torch.bench`.
"""

from __future__ import annotations

import sys

from evdown_torch.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", *sys.argv[1:]]))
