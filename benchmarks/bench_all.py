"""Every method against its peers, scaling curves and peak memory, then the project's goals.

Run: ``python benchmarks/bench_all.py --out DIR [--short] [--input FILE.npy ...]``; it takes
the options of ``evdown bench`` (see ``evdown bench --help``), drives
:mod:`evdown_torch.bench` with the repository's N-MNIST sample added to the method table
(``shared/data/sample_nmnist.bin`` beside the repository, when present), and prints the goals
table of ``benchmarks/goals.py`` at the end.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from goals import goals_table  # noqa: E402 - the goals script beside this one

from evdown_torch import bench  # noqa: E402
from evdown_torch.bench.report import load_results  # noqa: E402
from evdown_torch.cli import build_parser  # noqa: E402

#: The real N-MNIST recording of the project's shared data, next to the repository.
NMNIST_FILE = Path(__file__).resolve().parents[2] / "shared" / "data" / "sample_nmnist.bin"


def run_bench(argv: list[str]) -> int:
    """``evdown bench ARGV`` with the N-MNIST sample (when present), then the goals table."""
    args = build_parser().parse_args(["bench", *argv])
    nmnist = NMNIST_FILE if NMNIST_FILE.is_file() else None
    if nmnist is None:
        print(f"{NMNIST_FILE} is absent: no real recording in the method table.",
              file=sys.stderr)
    try:
        code = bench.run_from_args(args, nmnist=nmnist)
    except (ValueError, TypeError) as error:
        print(f"bench_all: error: {error}", file=sys.stderr)
        return 2
    if code == 0:
        print("\n" + goals_table(load_results(Path(args.out) / "results.json")))
    return code


if __name__ == "__main__":
    sys.exit(run_bench(sys.argv[1:]))
