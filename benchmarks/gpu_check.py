"""The GPU check in one command: the CUDA tests and every method's batch on the GPU against the CPU.

``benchmarks/gpu_check.sh`` installs the package and calls this script; it can also run alone
(from the repository root, the package importable). In one run, within a time budget:

1. **Tests**: ``python -m pytest -m cuda tests`` in a subprocess, i.e. the tests that take the
   ``device`` fixture, on CUDA (``tests/conftest.py`` marks that parameter ``cuda``). Without
   CUDA they are all deselected and the report says so.
2. **Batched benchmark**: for every method of :data:`evdown_torch.transforms.registry.METHODS`
   (factor 4, the benchmark settings of :data:`evdown_torch.bench.lineup.BENCH_SETTINGS`), on
   two workloads (:data:`WORKLOADS`: N-MNIST-sized, 256 recordings of 4,300 events at 34x34,
   and DVS128-sized, 4 recordings of 200,000 events at 128x128), ``transform.batch`` of one
   :class:`~evdown_torch.collate.EventBatch` on the CPU (one thread) and of the same batch on
   the device, timed alternately (medians, after one warm-up call each, GPU work synchronised),
   and the outputs compared event for event. Methods in :data:`EXACT_METHODS` use integer
   arithmetic only and must give equal outputs; the others compute in floating point, whose
   last bits may differ between devices, so their equality is reported but not required.
3. **Report**: ``gpu_check.md`` and ``gpu_check.json`` in ``--out``.

The exit status is 0 when the tests passed (or none could run without CUDA) and every exact
method's outputs were equal, else 1. What the budget did not leave time for is listed as
skipped. Without CUDA the "device" side runs on the CPU as well (``--device cpu``): that checks
the harness, not a GPU; ``tests/test_gpu_check.py`` runs it so with tiny sizes.

Run: ``python benchmarks/gpu_check.py --out DIR [--device auto|cuda|cpu] [--budget-s 280]
[--repeats 3] [--tiny] [--skip-tests] [--pytest-args ARGS] [--methods ...]``.
"""

from __future__ import annotations

import argparse
import gc
import json
import platform
import re
import shlex
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from evdown_torch.bench.inputs import dvs_like_stream  # noqa: E402
from evdown_torch.bench.lineup import BENCH_SETTINGS  # noqa: E402
from evdown_torch.collate import EventBatch  # noqa: E402
from evdown_torch.transforms.registry import METHODS, make_method  # noqa: E402

FACTOR = 4
#: Methods whose kernels use integer arithmetic only: outputs must be equal on every device.
EXACT_METHODS = ("downsample", "funnelling", "event_count")
#: Seconds kept back from the budget for writing the report.
REPORT_RESERVE_S = 5.0


@dataclass(frozen=True)
class Workload:
    """A batch of synthetic recordings (:func:`~evdown_torch.bench.inputs.dvs_like_stream`).

    Attributes:
        name: the workload's label.
        sensor_size: ``(W, H, P)`` of every recording.
        recordings: number of recordings ``B`` in the batch.
        events: events per recording.
        duration_us: length of each recording (microseconds).
    """

    name: str
    sensor_size: tuple[int, int, int]
    recordings: int
    events: int
    duration_us: int

    def batch(self) -> EventBatch:
        """The recordings (seeds 0 to ``B - 1``) as one batch on the CPU."""
        return EventBatch.from_recordings([
            dvs_like_stream(self.events, self.sensor_size, duration_us=self.duration_us, seed=s)
            for s in range(self.recordings)
        ])


#: The two workloads of the check: N-MNIST-sized and DVS128-Gesture-sized batches.
WORKLOADS = (
    Workload("nmnist", (34, 34, 2), 256, 4_300, 300_000),
    Workload("dvs128", (128, 128, 2), 4, 200_000, 6_000_000),
)
#: The same shapes, tiny, for checking the harness (``--tiny``).
TINY_WORKLOADS = (
    Workload("nmnist", (34, 34, 2), 4, 1_000, 30_000),
    Workload("dvs128", (128, 128, 2), 2, 4_000, 20_000),
)


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def median_seconds(
    calls: Sequence[tuple[Callable[[], object], torch.device]], repeats: int
) -> list[float]:
    """Median wall-clock seconds of each call over ``repeats`` alternate rounds.

    Each call is warmed up once; its device is synchronised before its clock stops.
    """
    for call, device in calls:
        call()
        _synchronize(device)
    times: list[list[float]] = [[] for _ in calls]
    gc.collect()
    gc.disable()  # no collection pause inside a timed call
    try:
        for _ in range(repeats):
            for (call, device), record in zip(calls, times, strict=True):
                start = time.perf_counter()
                call()
                _synchronize(device)
                record.append(time.perf_counter() - start)
    finally:
        gc.enable()
    return [statistics.median(record) for record in times]


def same_batch(a: EventBatch, b: EventBatch) -> bool:
    """Whether two batches hold the same events (``b`` moved to ``a``'s device)."""
    if a.lengths != b.lengths:
        return False
    return all(torch.equal(u, v.to(u.device)) for u, v in zip(a.events, b.events, strict=True))


def bench_method(
    name: str, workload: Workload, batch: EventBatch, device: torch.device, repeats: int
) -> dict[str, Any]:
    """One method on one workload: CPU and device times, throughputs and equality."""
    transform = make_method(name, workload.sensor_size, FACTOR, **BENCH_SETTINGS.get(name, {}))
    on_device = batch.to(device)
    cpu_out, dev_out = transform.batch(batch), transform.batch(on_device)
    cpu_s, dev_s = median_seconds([(lambda: transform.batch(batch), torch.device("cpu")),
                                   (lambda: transform.batch(on_device), device)], repeats)
    n = batch.events.num_events
    return {
        "method": name, "workload": workload.name, "events_in": n,
        "events_out_cpu": cpu_out.events.num_events,
        "events_out_device": dev_out.events.num_events,
        "cpu_ms": cpu_s * 1e3, "device_ms": dev_s * 1e3,
        "cpu_mev_s": n / cpu_s / 1e6, "device_mev_s": n / dev_s / 1e6,
        "speedup": cpu_s / dev_s, "equal": same_batch(cpu_out, dev_out),
        "exact": name in EXACT_METHODS, "skipped": "",
    }


def run_benchmark(
    workloads: Sequence[Workload], methods: Sequence[str], device: torch.device, repeats: int,
    deadline: float,
) -> list[dict[str, Any]]:
    """:func:`bench_method` for every workload and method until ``deadline``.

    ``deadline`` is a ``time.perf_counter()`` reading; what would not fit is listed with
    ``skipped`` set.
    """
    rows: list[dict[str, Any]] = []
    for workload in workloads:
        batch = workload.batch()
        # A method's time on the last workload bounds the next one's (same sizes).
        last_s = 0.0
        for name in methods:
            if time.perf_counter() + 2 * last_s > deadline:
                rows.append({"method": name, "workload": workload.name,
                             "skipped": "time budget", "exact": name in EXACT_METHODS})
                continue
            start = time.perf_counter()
            try:
                rows.append(bench_method(name, workload, batch, device, repeats))
            except Exception as error:  # noqa: BLE001 - reported, the check goes on
                rows.append({"method": name, "workload": workload.name,
                             "skipped": f"error: {type(error).__name__}: {error}",
                             "exact": name in EXACT_METHODS})
            last_s = time.perf_counter() - start
    return rows


#: pytest's summary words, in the order the report lists them.
_SUMMARY_WORDS = ("passed", "failed", "skipped", "deselected", "xfailed", "xpassed", "errors",
                  "warnings")


def parse_pytest_summary(output: str) -> dict[str, int]:
    r"""Counts of pytest's last summary line (``3 passed, 1 skipped in 2.0s``).

    Example:
        >>> parse_pytest_summary("..\n2 failed, 14 passed, 1 error in 3.1s\n")
        {'passed': 14, 'failed': 2, 'errors': 1}
    """
    pattern = re.compile(r"(\d+) (passed|failed|skipped|deselected|xfailed|xpassed|error|"
                         r"errors|warning|warnings)\b")
    for line in reversed(output.strip().splitlines()):
        found = pattern.findall(line)
        if found:
            counts = {word + "s" if word in ("error", "warning") else word: int(n)
                      for n, word in found}
            return {word: counts[word] for word in _SUMMARY_WORDS if word in counts}
    return {}


def run_tests(pytest_args: Sequence[str], timeout_s: float) -> dict[str, Any]:
    """Run pytest in a subprocess (from the repository root) within ``timeout_s``."""
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:randomly", *pytest_args]
    start = time.perf_counter()
    try:
        done = subprocess.run(command, cwd=ROOT, capture_output=True, text=True,
                              timeout=max(timeout_s, 1.0), check=False)
        output, rc = done.stdout + done.stderr, done.returncode
    except subprocess.TimeoutExpired as expired:
        out = expired.stdout or ""
        output = (out.decode() if isinstance(out, bytes) else out) + "\n(timed out)"
        rc = None
    return {"command": shlex.join(command[2:]), "returncode": rc,
            "seconds": time.perf_counter() - start, "counts": parse_pytest_summary(output),
            "tail": "\n".join(output.strip().splitlines()[-15:])}


def tests_ok(tests: dict[str, Any], cuda: bool) -> bool:
    """Passed, or (without CUDA) none selected. pytest exits with 5 when it selected nothing."""
    if not tests:
        return True
    if tests["returncode"] == 0:
        return True
    return not cuda and tests["returncode"] == 5


def environment(device: torch.device) -> dict[str, Any]:
    """The machine and library versions, for the report."""
    import numpy

    info: dict[str, Any] = {
        "python": platform.python_version(), "torch": torch.__version__,
        "numpy": numpy.__version__, "cuda_available": torch.cuda.is_available(),
        "device": str(device), "cpu_threads": torch.get_num_threads(),
        "machine": platform.machine(), "processor": platform.processor() or "",
    }
    if device.type == "cuda":
        info["gpu"] = torch.cuda.get_device_name(device)
        info["cuda"] = torch.version.cuda
    return info


def report_markdown(report: dict[str, Any]) -> str:
    """The report as Markdown (times in ms, throughputs in M input events per second)."""
    env, lines = report["environment"], []
    gpu = env.get("gpu")
    lines.append("# GPU check\n")
    lines.append(f"Device: **{env['device']}**" + (f" ({gpu}, CUDA {env['cuda']})" if gpu else
                 " (no CUDA: the device side ran on the CPU, which checks the harness only)")
                 + f"; torch {env['torch']}, Python {env['python']}; CPU side on one thread. "
                 f"{report['elapsed_s']:.0f} s of a {report['budget_s']:.0f} s budget. "
                 f"Result: **{'pass' if report['ok'] else 'FAIL'}**.\n")
    tests = report["tests"]
    lines.append("## CUDA tests\n")
    if not tests:
        lines.append("Not run (`--skip-tests`).\n")
    else:
        counts = ", ".join(f"{v} {k}" for k, v in tests["counts"].items()) or "no summary"
        lines.append(f"`{tests['command']}`: exit status {tests['returncode']}, {counts}, "
                     f"{tests['seconds']:.0f} s.\n")
        if tests["returncode"] not in (0, 5):
            lines.append("```\n" + tests["tail"] + "\n```\n")
    lines.append("## Batched benchmark, device against CPU\n")
    lines.append(f"Factor {FACTOR}; `transform.batch` of one EventBatch; medians of "
                 f"{report['repeats']} alternate calls after a warm-up. *equal*: the device's "
                 "output equals the CPU's event for event (required for the exact methods).\n")
    for w in report["workloads"]:
        lines.append(f"- {w['name']}: {w['recordings']} recordings x {w['events']:,} events, "
                     f"{w['sensor_size'][0]}x{w['sensor_size'][1]}, {w['duration_us']:,} us each")
    lines.append("")
    lines.append("| workload | method | CPU ms | device ms | CPU M ev/s | device M ev/s | "
                 "speed-up | equal | exact |")
    lines.append("|---|---|---|---|---|---|---|---|---|")
    for r in report["benchmark"]:
        exact = "yes" if r["exact"] else "no"
        if r["skipped"]:
            lines.append(f"| {r['workload']} | {r['method']} | – | – | – | – | – | "
                         f"{r['skipped']} | {exact} |")
            continue
        lines.append(f"| {r['workload']} | {r['method']} | {r['cpu_ms']:.3g} | "
                     f"{r['device_ms']:.3g} | {r['cpu_mev_s']:.3g} | {r['device_mev_s']:.3g} | "
                     f"{r['speedup']:.3g} | {'yes' if r['equal'] else 'NO'} | {exact} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", required=True, help="folder for gpu_check.md and .json")
    parser.add_argument("--device", default="auto", help="auto (cuda if present), cuda or cpu")
    parser.add_argument("--budget-s", type=float, default=280.0,
                        help="seconds for the whole check (tests, benchmark, report)")
    parser.add_argument("--repeats", type=int, default=3, help="timed calls of each side")
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    parser.add_argument("--tiny", action="store_true", help="tiny batches, to check the harness")
    parser.add_argument("--skip-tests", action="store_true", help="no pytest run")
    parser.add_argument("--pytest-args", default="-m cuda --continue-on-collection-errors tests",
                        help="what pytest runs (default: the CUDA tests)")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    if args.budget_s <= REPORT_RESERVE_S or args.repeats < 1:
        parser.error(f"--budget-s must exceed {REPORT_RESERVE_S} and --repeats be positive")
    deadline = start + args.budget_s - REPORT_RESERVE_S
    if args.device == "auto":
        device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    else:
        device = torch.device(args.device)
        if device.type == "cuda" and not torch.cuda.is_available():
            parser.error("--device cuda, but torch sees no CUDA device")
    torch.set_num_threads(1)
    cuda = device.type == "cuda"
    tests: dict[str, Any] = {}
    if not args.skip_tests:
        # The tests get at most half of what is left; the benchmark skips what will not fit.
        tests = run_tests(shlex.split(args.pytest_args), (deadline - time.perf_counter()) / 2)
        print(f"tests: {tests['command']}: exit {tests['returncode']}, {tests['counts']}",
              flush=True)
    workloads = TINY_WORKLOADS if args.tiny else WORKLOADS
    rows = run_benchmark(workloads, args.methods, device, args.repeats, deadline)
    exact_equal = all(r.get("equal", True) for r in rows if r["exact"] and not r["skipped"])
    errors = [r for r in rows if r["skipped"].startswith("error")]
    report = {
        "environment": environment(device), "budget_s": args.budget_s,
        "elapsed_s": time.perf_counter() - start, "repeats": args.repeats,
        "ok": tests_ok(tests, cuda) and exact_equal and not errors,
        "tests": tests, "workloads": [asdict(w) for w in workloads], "benchmark": rows,
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    markdown = report_markdown(report)
    (out / "gpu_check.md").write_text(markdown)
    (out / "gpu_check.json").write_text(json.dumps(report, indent=1))
    print(markdown)
    print(f"gpu_check: wrote {out / 'gpu_check.md'} and {out / 'gpu_check.json'}")
    return 0 if report["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
