"""Benchmarks: every downscaler against its peers, scaling curves and peak memory.

``evdown bench --out DIR [--short]`` (or :func:`run_benchmark` then :func:`write_report`)
measures, in one process and one run, every method of
:data:`~evdown_torch.transforms.registry.METHODS` and the peers a user would otherwise pick,
``tonic.transforms.Downsample`` and ``tonic.transforms.EventDownsampling`` (integrator and
differentiator; only when Tonic is installed), and writes ``report.md``, ``results.json`` and
PNG plots (when matplotlib is installed) to ``DIR``.

What is measured:

* **Time**: wall-clock time of one call of the transform on a Tonic structured array in
  memory (validation, conversion to tensors and back included, as a user calls it), with
  ``torch.set_num_threads(1)``; the median of at least ``repeats`` calls after one warm-up call
  (more calls for inputs that take only milliseconds), with the median CPU time of the same
  calls beside it. **Throughput** is input events divided by the median wall-clock time.
* **Peak memory**, per method and input, in a fresh process: one worker process imports
  everything (interpreter, NumPy, torch, evdown_torch, Tonic) and, for every measurement,
  forks a child that loads the input, builds the transform, warms it up on 1000 events and
  calls it once. *Added* is the child's peak resident set (``VmHWM``) during the call minus
  its resident set just before (the input loaded); *process* is the worker's resident set
  after imports plus the child's growth up to its peak, i.e. the peak of a fresh process
  that imports, loads the input and runs the method once. Without ``fork`` or ``/proc`` (not
  Linux), each measurement runs in its own fresh interpreter and *added* is the growth of the
  peak resident set (``ru_maxrss``) over the call.
* **Scaling curves** (factor 4) of throughput and added peak memory against the number of
  events at a fixed event rate, the sensor size at a fixed count and duration, and the
  recording duration at a fixed count (events arrive in bursts at a fixed rate; the pauses
  between bursts grow), so the curves show what the cost follows.

Inputs: synthetic DVS128-Gesture-like recordings (:func:`gesture_stream`, from
:mod:`evdown_torch.synthetic`) for the headline method table; streams of moving bar edges
(:func:`dvs_like_stream`, whose count, sensor and duration are set exactly) for the large
1280x720 input and the sweeps; an N-MNIST recording when one is given
(``benchmarks/bench_all.py`` gives the repository's sample); and any ``.npy`` structured
arrays named.

The modules: :mod:`~evdown_torch.bench.inputs` (streams), :mod:`~evdown_torch.bench.lineup`
(methods and peers), :mod:`~evdown_torch.bench.measure` (timing, peak memory),
:mod:`~evdown_torch.bench.run` (plan and run), :mod:`~evdown_torch.bench.report` (tables,
JSON, plots) and :mod:`~evdown_torch.bench.command` (``evdown bench``). The project's speed
and memory goals are checked against a run's ``results.json`` by ``benchmarks/goals.py``.
"""

from evdown_torch.bench.command import run_from_args
from evdown_torch.bench.inputs import (
    BenchInput,
    dvs_like_stream,
    gesture_stream,
    read_nmnist,
    with_pauses,
)
from evdown_torch.bench.lineup import (
    BENCH_SETTINGS,
    PEERS,
    Candidate,
    candidate,
    candidate_job,
    candidates,
    fresh_call,
    fresh_call_summary,
    parse_spec,
    prepare_candidate_call,
    tonic_available,
)
from evdown_torch.bench.measure import MemoryJob, Timing, measure_memory, time_call
from evdown_torch.bench.report import load_results, method_table, sweep_table, write_report
from evdown_torch.bench.run import BenchResults, Measurement, Plan, make_plan, run_benchmark

__all__ = [
    "BENCH_SETTINGS",
    "PEERS",
    "BenchInput",
    "BenchResults",
    "Candidate",
    "Measurement",
    "MemoryJob",
    "Plan",
    "Timing",
    "candidate",
    "candidate_job",
    "candidates",
    "fresh_call",
    "fresh_call_summary",
    "dvs_like_stream",
    "gesture_stream",
    "load_results",
    "make_plan",
    "measure_memory",
    "method_table",
    "parse_spec",
    "prepare_candidate_call",
    "read_nmnist",
    "run_benchmark",
    "run_from_args",
    "sweep_table",
    "time_call",
    "tonic_available",
    "with_pauses",
    "write_report",
]
