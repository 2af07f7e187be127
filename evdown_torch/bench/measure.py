"""How the benchmark measures: timed calls, and peak memory in fresh processes."""

from __future__ import annotations

import gc
import importlib
import importlib.util
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import torch

from evdown_torch.checks import check_positive_int

__all__ = ["MemoryJob", "Timing", "measure_memory", "memory_worker", "time_call"]

@dataclass(frozen=True)
class Timing:
    """Timed calls: the median wall-clock and process CPU seconds, and how many calls.

    On a shared machine the wall clock also counts waiting for a core; the CPU time does
    not, so the two agree when the machine was quiet.
    """

    seconds: float
    cpu_seconds: float
    runs: int


def time_call(
    fn: Callable[..., Any],
    *args: Any,
    repeats: int = 5,
    min_seconds: float = 0.0,
    max_repeats: int = 1000,
) -> tuple[Timing, Any]:
    """Time ``fn(*args)``: one warm-up call, then at least ``repeats`` timed calls.

    More calls (up to ``max_repeats``) are made until the timed ones add up to
    ``min_seconds`` of wall-clock time.

    Returns:
        ``(timing, result of the warm-up call)``.

    Example:
        >>> timing, result = time_call(sum, [1, 2, 3], repeats=5)
        >>> timing.runs, result, timing.seconds >= 0
        (5, 6, True)
    """
    repeats = check_positive_int("repeats", repeats)
    result = fn(*args)
    wall: list[float] = []
    cpu: list[float] = []
    while len(wall) < repeats or (sum(wall) < min_seconds and len(wall) < max_repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn(*args)
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return Timing(statistics.median(wall), statistics.median(cpu), len(wall)), result

@dataclass(frozen=True)
class MemoryJob:
    """One peak-memory measurement, run in a fresh process by :func:`measure_memory`.

    Attributes:
        target: ``"package.module:function"`` or ``"path/to/file.py:function"``;
            ``function(**kwargs)`` prepares everything (loads, builds, warms up) and returns
            the zero-argument callable whose peak is measured (its return value comes back
            when it is a number or a string).
        kwargs: JSON-serialisable keyword arguments of ``function``.
    """

    target: str
    kwargs: dict[str, Any]

def _resolve(target: str) -> Callable[..., Callable[[], Any]]:
    where, sep, function = target.rpartition(":")
    if not sep or not where or not function:
        raise ValueError(f"target must look like MODULE:FUNCTION or FILE.py:FUNCTION, got "
                         f"{target!r}")
    if where.endswith(".py"):
        spec = importlib.util.spec_from_file_location(f"_bench_{Path(where).stem}", where)
        if spec is None or spec.loader is None:
            raise ValueError(f"cannot import {where!r}")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    else:
        module = importlib.import_module(where)
    return getattr(module, function)


def _proc_status_kib() -> dict[str, int]:
    values = {}
    with open("/proc/self/status") as status:
        for line in status:
            key, _, rest = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                values[key] = int(rest.split()[0])
    return values


def _reset_peak() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as refs:
            refs.write("5")
    except OSError:
        return False
    return True


def _peak_bytes() -> int:
    """Peak resident set of this process so far, in bytes.

    ``VmHWM`` where ``/proc`` exists (it starts afresh at ``exec``, and
    :func:`_reset_peak` resets it); else ``ru_maxrss``, which on Linux would also carry the
    peak of the process that spawned this one.
    """
    if Path("/proc/self/status").exists():
        return _proc_status_kib()["VmHWM"] * 1024
    import resource

    value = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(value) if sys.platform == "darwin" else int(value) * 1024


def _measure_here(job: MemoryJob, prepare: Callable[..., Callable[[], Any]]) -> dict[str, Any]:
    """Prepare the job, then measure the peak of its call in this process."""
    call = prepare(**job.kwargs)
    _reset_peak()
    before = _peak_bytes()
    start, start_cpu = time.perf_counter(), time.process_time()
    value = call()
    seconds, cpu = time.perf_counter() - start, time.process_time() - start_cpu
    # The kernel updates VmHWM from per-thread RSS counters it syncs lazily, so a call that
    # allocates (almost) nothing can read a few pages below the value before it: at least 0.
    out: dict[str, Any] = {"added": max(_peak_bytes() - before, 0), "peak": _peak_bytes(),
                           "seconds": seconds, "cpu_seconds": cpu}
    if isinstance(value, (bool, int, float, str)):
        out["result"] = value
    return out


def _forked_measurement(job: MemoryJob, prepare: Callable[..., Callable[[], Any]],
                        base_rss: int) -> dict[str, Any]:
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # the child: prepare, measure one call, report, exit
        os.close(read_end)
        try:
            at_fork = _proc_status_kib()["VmRSS"] * 1024
            message = _measure_here(job, prepare)
            message["total"] = base_rss + message.pop("peak") - at_fork
        except BaseException as error:  # noqa: BLE001 - reported to the parent
            message = {"error": f"{type(error).__name__}: {error}"}
        os.write(write_end, json.dumps(message).encode())
        os._exit(0)
    os.close(write_end)
    chunks = []
    while chunk := os.read(read_end, 65536):
        chunks.append(chunk)
    os.close(read_end)
    _, status = os.waitpid(pid, 0)
    if not chunks:
        return {"error": f"the measuring process died (wait status {status})"}
    return json.loads(b"".join(chunks))


def memory_worker(spec_path: str) -> None:
    """Entry point of the measuring process: runs the jobs of a JSON spec, prints results."""
    spec = json.loads(Path(spec_path).read_text())
    torch.set_num_threads(1)
    jobs = [MemoryJob(j["target"], j["kwargs"]) for j in spec["jobs"]]
    prepares: dict[str, Any] = {}  # imported before the baseline; an exception if it fails
    for job in jobs:
        if job.target not in prepares:
            try:
                prepares[job.target] = _resolve(job.target)
            except Exception as error:  # noqa: BLE001 - reported for the jobs that need it
                prepares[job.target] = error
    if any(str(job.kwargs.get("spec", "")).startswith("tonic_") for job in jobs):
        import tonic  # noqa: F401 - the peers' library, imported before the baseline
    gc.collect()
    gc.freeze()  # forked children then never touch (copy) the imported objects
    fork = spec["fork"]
    base_rss = _proc_status_kib()["VmRSS"] * 1024 if fork else 0
    for job in jobs:
        prepared = prepares[job.target]
        if isinstance(prepared, Exception):
            result = {"error": f"{type(prepared).__name__}: {prepared}"}
        elif fork:
            result = _forked_measurement(job, prepares[job.target], base_rss)
        else:
            try:
                result = _measure_here(job, prepares[job.target])
                result["total"] = result.pop("peak")
            except Exception as error:  # noqa: BLE001 - reported to the parent
                result = {"error": f"{type(error).__name__}: {error}"}
        print("EVDOWN-MEM " + json.dumps(result), flush=True)


def _can_fork_measure() -> bool:
    return hasattr(os, "fork") and Path("/proc/self/status").exists()


def measure_memory(jobs: Sequence[MemoryJob], *, fork: bool | None = None) -> list[dict]:
    """Peak memory of each job's call, each measured in a fresh process.

    With ``fork`` (Linux; the default where possible) one fresh worker interpreter imports
    the jobs' modules, then forks one child per job: the child prepares the job, resets its
    peak resident set (``VmHWM``) and runs the call. Without it, every job runs in its own
    fresh interpreter.

    Args:
        jobs: the measurements to make.
        fork: see above (default: where possible).

    Returns:
        One dict per job: ``{"added": bytes, "total": bytes, "seconds": s,
        "cpu_seconds": s}`` or ``{"error": message}``. *added* is the peak resident set
        during the call minus the resident set just before it; *total* is the peak of a
        fresh process that imports, prepares and calls (the worker's resident set after
        imports plus the child's growth up to its peak); *seconds* and *cpu_seconds* are the
        call's wall-clock and CPU time; *result* is the call's return value when it is a
        number or a string.
    """
    if not jobs:
        return []
    fork = _can_fork_measure() if fork is None else fork
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[2])  # where evdown_torch is imported from
    env["PYTHONPATH"] = os.pathsep.join([root, *filter(None, [env.get("PYTHONPATH")])])
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        env[var] = "1"
    groups = [list(jobs)] if fork else [[job] for job in jobs]
    results: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="evdown-mem-") as tmp:
        for i, group in enumerate(groups):
            spec = Path(tmp) / f"spec{i}.json"
            spec.write_text(json.dumps({"fork": fork, "jobs": [asdict(j) for j in group]}))
            code = ("import sys; from evdown_torch.bench.measure import memory_worker; "
                    "memory_worker(sys.argv[1])")
            done = subprocess.run([sys.executable, "-c", code, str(spec)], env=env,
                                  capture_output=True, text=True, check=False)
            lines = [json.loads(line[len("EVDOWN-MEM "):]) for line in done.stdout.splitlines()
                     if line.startswith("EVDOWN-MEM ")]
            if len(lines) < len(group):
                tail = done.stderr.strip().splitlines()[-1:] or [f"exit status {done.returncode}"]
                lines += [{"error": f"memory worker failed: {tail[0]}"}] * (len(group) - len(lines))
            results.extend(lines)
    return results
