"""Downscale every recording of a dataset once, into a sharded cache (``evdown preprocess``).

Recordings ``[k * S, (k + 1) * S)`` form shard ``k`` (``S``: the shard size); a shard's bytes
depend only on its recordings, so the cache is the same whoever writes it. On one machine the
shards are shared by worker processes (this one and spawned ones, one torch thread each);
under ``torchrun`` rank ``r`` of ``W`` takes shards ``r, r + W, r + 2W, ...`` (each rank may
use workers too), and after a collective rank 0 writes the manifest. Complete shards whose
checksums verify are kept on a rerun, anything else is redone. The format is described in
:mod:`evdown_torch.data.shards`, the command line in :mod:`evdown_torch.data.command`.
"""

from __future__ import annotations

import hashlib
import json
import math
import multiprocessing
import sys
import threading
import time
import warnings
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass
from pathlib import Path
from queue import Empty
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

import evdown_torch
from evdown_torch.checks import check_choice, check_factor, check_positive_int
from evdown_torch.data import shards
from evdown_torch.data.sources import check_label
from evdown_torch.distributed import all_gather, rank_and_world
from evdown_torch.threads import available_cores, check_threads, torch_threads
from evdown_torch.time_units import (
    TimeUnitWarning,
    time_settings,
    timing_checked_by_caller,
    timing_warning,
)
from evdown_torch.transforms import Downscaler
from evdown_torch.transforms.registry import make_method, method_settings

#: A timing warning from a shard, ``(text, command line's text)``, or ``None``.
_Warning = tuple[str, str] | None

if TYPE_CHECKING:
    from multiprocessing.queues import Queue

    from tqdm.auto import tqdm

    from evdown_torch.data.sources import Source

    _Done = Callable[[dict[str, Any], Sequence[float], _Warning], None]

__all__ = ["PreprocessResult", "RecordingError", "preprocess"]


class RecordingError(Exception):
    """A recording could not be read or downscaled, and the run was told to stop there."""


@dataclass(frozen=True)
class PreprocessResult:
    """What a preprocessing run did (on rank 0: all ranks; on other ranks: their share).

    Attributes:
        out: the cache folder.
        manifest: the manifest written (rank 0), else None.
        shards: number of shards of the whole cache.
        written: shards written in this run.
        kept: complete shards found from an earlier run and kept.
        recordings: recordings downscaled (or skipped) in this run.
        seconds: wall time of this process, seconds.
        read_seconds: time this process's workers spent reading (or rendering) recordings,
            summed.
        transform_seconds: time they spent downscaling, summed.
        write_seconds: time they spent writing and checksumming shards, summed.
    """

    out: Path
    manifest: dict[str, Any] | None
    shards: int
    written: tuple[int, ...]
    kept: tuple[int, ...]
    recordings: int
    seconds: float
    read_seconds: float
    transform_seconds: float
    write_seconds: float


# Worker side ---------------------------------------------------------------------------------

_STATE: dict[str, Any] = {}


def _init_worker(state: dict[str, Any], queue: Queue[int]) -> None:
    torch.set_num_threads(state["threads"])
    _STATE.clear()
    _STATE.update(state, tick=lambda: queue.put(1))


def _ready() -> bool:
    return True


def _worker_shard(shard: int) -> tuple[dict[str, Any], tuple[float, float, float], _Warning]:
    return _write_one_shard(_STATE, shard)


def _write_one_shard(
    state: dict[str, Any], shard: int
) -> tuple[dict[str, Any], tuple[float, float, float], _Warning]:
    """Downscale shard ``shard``'s recordings and write it.

    Returns:
        Its record, its timings, and the timing warning of its first recording
        (:func:`_timing_warning`), which the run gives once: the readers' and transforms'
        own checks are silent here, or every file and process would repeat it.
    """
    with timing_checked_by_caller():
        return _write_shard(state, shard)


def _timing_warning(events: np.ndarray, transform: Downscaler, source: str) -> _Warning:
    """What :func:`~evdown_torch.time_units.timing_warning` says of a recording, if anything."""
    said = timing_warning(events["t"], time_settings(transform), source=source)
    return None if said is None else (str(said), said.command_line)


def _write_shard(
    state: dict[str, Any], shard: int
) -> tuple[dict[str, Any], tuple[float, float, float], _Warning]:
    source, transform, size = state["source"], state["transform"], state["shard_size"]
    first, stop = shard * size, min((shard + 1) * size, len(source))
    shards.remove_stale_temporaries(state["out"], shard)
    loaded, skipped = [], []
    read_s = transform_s = 0.0

    def skip(index: int, error: Exception) -> None:
        reason = f"{type(error).__name__}: {error}"
        if state["on_error"] == "stop":
            raise RecordingError(
                f"cannot preprocess {source.source_name(index)}: {reason}") from None
        skipped.append({"index": index, "source": source.source_name(index), "error": reason})

    for index in range(first, stop):
        start = time.perf_counter()
        try:
            events, label = source.load(index)
            loaded.append((index, check_label(label), events))
        except (OSError, EOFError, ValueError, TypeError) as error:
            skip(index, error)
            state["tick"]()
        read_s += time.perf_counter() - start
    said = None if not loaded else _timing_warning(loaded[0][2], transform,
                                                   source.source_name(loaded[0][0]))
    start = time.perf_counter()
    try:  # the whole shard in one batched pass of the transform
        outputs = transform.batch([events for _, _, events in loaded])
    except (ValueError, TypeError):  # one recording is bad: find it, keep the others
        outputs = []
        for index, _, events in loaded:
            try:
                outputs.append(transform(events))
            except (ValueError, TypeError) as error:
                skip(index, error)
                outputs.append(None)
    transform_s += time.perf_counter() - start
    chunks, rows = [], []
    events_in = events_out = 0
    for (index, label, events), out in zip(loaded, outputs):
        if out is not None:
            offset = events_out
            chunks.append(out)
            events_in += len(events)
            events_out += len(out)
            rows.append((index, label, offset, events_out))
        state["tick"]()
    start = time.perf_counter()
    events = np.concatenate(chunks) if chunks else np.empty(0, dtype=source.dtype)
    record = shards.write_shard(
        state["out"], shard, events, np.array(rows, dtype=shards.INDEX_DTYPE),
        {"job": state["job_id"], "first": first, "stop": stop, "recordings": len(rows),
         "events_in": events_in, "events_out": events_out, "skipped": skipped})
    return record, (read_s, transform_s, time.perf_counter() - start), said


# Driver side ---------------------------------------------------------------------------------


def _job(source: Source, method: str, factor: tuple[int, int], transform: Downscaler,
         shard_size: int) -> dict[str, Any]:
    settings = {name: getattr(transform, name) for name in method_settings(method)}
    job = {"format": shards.FORMAT, "format_version": shards.FORMAT_VERSION,
           "package": "evdown_torch", "version": evdown_torch.__version__,
           "dataset": source.describe(), "num_recordings": len(source),
           "method": method, "factor": list(factor), "settings": settings,
           "shard_size": shard_size}
    return json.loads(json.dumps(job))  # as it reads back from job.json


def _claim_folder(out: Path, job: dict[str, Any]) -> None:
    out.mkdir(parents=True, exist_ok=True)
    path = out / shards.JOB
    if path.is_file():
        previous = shards.read_json(path)
        if previous != job:
            differing = sorted(k for k in set(job) | set(previous)
                               if job.get(k) != previous.get(k))
            raise ValueError(
                f"{str(out)!r} holds a cache of another job (differs in {', '.join(differing)}); "
                "choose another --out or delete that folder"
            )
    else:
        shards.write_json(path, job)


def _run_shards(state: dict[str, Any], todo: list[int], workers: int, bar: tqdm) -> tuple[
        list[dict[str, Any]], list[float]]:
    """Write the shards ``todo`` with ``workers`` processes.

    Each process uses ``state["threads"]`` torch threads (this one's setting is restored
    afterwards).

    This process works too (in a thread, from the back of the list) while ``workers - 1``
    spawned processes start; each gets one shard at a time from the front once it has
    started, so nobody waits for work and the end waits for at most one shard.
    """
    records: list[dict[str, Any]] = []
    timings = [0.0, 0.0, 0.0]

    warned = False

    def done(record: dict[str, Any], timing: Sequence[float], said: _Warning) -> None:
        nonlocal warned
        if said is not None and not warned:  # once a run, naming the recording
            warned = True
            warnings.warn(TimeUnitWarning(*said), stacklevel=2)
        records.append(record)
        for i, value in enumerate(timing):
            timings[i] += value
        for skip in record["skipped"]:
            bar.write(f"evdown preprocess: warning: skipped {skip['source']}: {skip['error']}",
                      file=sys.stderr)

    local = dict(state, tick=lambda: bar.update(1))
    with torch_threads(state["threads"]):
        if workers <= 1:
            for shard in todo:
                done(*_write_one_shard(local, shard))
            return records, timings
        _run_with_pool(state, deque(todo), workers - 1, bar, done)
        return records, timings


def _run_with_pool(state: dict[str, Any], waiting: deque[int], spawned: int, bar: tqdm,
                   done: _Done) -> None:
    context = multiprocessing.get_context("spawn")
    queue = context.Queue()  # progress ticks from every process, shown by this thread
    local = dict(state, tick=lambda: queue.put(1))
    stop = threading.Event()
    here: list = []  # (record, timing, warning) or an exception, from the thread working here

    def work_here() -> None:
        try:
            while not stop.is_set():
                try:
                    shard = waiting.pop()
                except IndexError:
                    return
                here.append(_write_one_shard(local, shard))
        except BaseException as error:  # handed to the main thread
            here.append(error)

    def collect_here() -> None:
        while here:
            item = here.pop(0)
            if isinstance(item, BaseException):
                raise item
            done(*item)

    thread = threading.Thread(target=work_here, name="evdown-preprocess", daemon=True)
    with ProcessPoolExecutor(spawned, mp_context=context, initializer=_init_worker,
                             initargs=(state, queue)) as pool:
        pings = {pool.submit(_ready) for _ in range(spawned)}
        pending: set = set()
        thread.start()
        try:
            while True:
                started = sum(ping.done() for ping in pings)
                while not stop.is_set() and waiting and len(pending) < started:
                    try:
                        shard = waiting.popleft()
                    except IndexError:
                        break
                    pending.add(pool.submit(_worker_shard, shard))
                watched = pending | {ping for ping in pings if not ping.done()}
                if watched:
                    finished, _ = wait(watched, timeout=0.1, return_when=FIRST_COMPLETED)
                else:  # only this process is busy
                    finished = set()
                    thread.join(timeout=0.1)
                _drain(queue, bar)
                for future in finished & pending:
                    pending.discard(future)
                    done(*future.result())
                collect_here()
                if not pending and not thread.is_alive() and not here:
                    break
        except BaseException:
            stop.set()
            thread.join()  # the shard it is writing finishes and stays
            pool.shutdown(wait=True, cancel_futures=True)
            raise
        _drain(queue, bar)


def _drain(queue: Queue[int], bar: tqdm) -> None:
    while True:
        try:
            bar.update(queue.get_nowait())
        except Empty:
            return


def _manifest(job: dict[str, Any], job_id: str, source: Source, transform: Downscaler,
              records: list[dict[str, Any]]) -> dict[str, Any]:
    records = sorted(records, key=lambda r: r["shard"])
    return dict(
        job, job=job_id, classes=source.classes,
        output_sensor_size=list(transform.output_sensor_size),
        dtype=shards.dtype_to_json(source.dtype),
        counts={"shards": len(records),
                "recordings": sum(r["recordings"] for r in records),
                "skipped": sum(len(r["skipped"]) for r in records),
                "events_in": sum(r["events_in"] for r in records),
                "events_out": sum(r["events_out"] for r in records)},
        shards=records,
    )


def preprocess(
    source: Source,
    out: str | Path,
    method: str,
    factor: int | tuple[int, int],
    settings: dict[str, Any] | None = None,
    *,
    shard_size: int = 32,
    workers: int | None = None,
    on_error: str = "skip",
    progress: bool | None = None,
    threads: int = 1,
) -> PreprocessResult:
    """Downscale every recording of ``source`` once and write the cache to ``out``.

    Under an initialised ``torch.distributed`` process group, this process does its rank's
    share and rank 0 writes the manifest once every rank is done; otherwise it does all.
    Scripts that call this with ``workers > 1`` need the ``if __name__ == "__main__":``
    guard (worker processes are spawned).

    Args:
        source: a dataset source (:func:`~evdown_torch.data.sources.open_source`).
        out: the cache folder (created; a rerun with the same job resumes in it).
        method: a name of :data:`~evdown_torch.transforms.registry.METHODS`.
        factor: ``f`` or ``(fx, fy)``.
        settings: the method's other settings (e.g. ``{"threshold": 0.5}``).
        shard_size: recordings per shard.
        workers: processes working, this one included (default: one per available core,
            or 1 per rank under ``torch.distributed``); ``workers - 1`` are spawned.
        on_error: ``"skip"`` a recording that cannot be read or downscaled (reported by name
            on stderr and in the manifest; retried by a rerun), or ``"stop"`` the run there,
            keeping the shards already complete.
        progress: show a progress bar (default: when stderr is a terminal; rank 0 only).
        threads: torch threads of each working process while it works (this process's own
            setting is restored afterwards). One is never much slower per process and leaves
            the other cores to the other workers (docs/benchmarks.md, "Threads").

    Returns:
        What this process did; ``manifest`` on rank 0.

    Raises:
        ValueError: for bad settings or an ``out`` folder holding another job.
        RecordingError: with ``on_error="stop"``, naming the recording.
    """
    from tqdm.auto import tqdm  # a core dependency, imported when a run starts
    start_time = time.perf_counter()
    check_choice("on_error", on_error, ("skip", "stop"))
    shard_size = check_positive_int("shard_size", shard_size)
    if workers is not None:
        workers = check_positive_int("workers", workers)
    threads = check_threads(threads)
    fxy = check_factor(factor, source.sensor_size)
    transform = make_method(method, source.sensor_size, factor, **(settings or {}))
    rank, world = rank_and_world()
    out = Path(out)
    job = _job(source, method, fxy, transform, shard_size)
    job_id = hashlib.sha256(json.dumps(job, sort_keys=True).encode()).hexdigest()[:16]
    _claim_folder(out, job)

    num_shards = math.ceil(len(source) / shard_size)
    records, todo = [], []
    for shard in range(rank, num_shards, world):
        record = shards.read_shard_record(out, shard, job_id)
        if record is not None and not record["skipped"]:
            records.append(record)
        else:
            todo.append(shard)
    kept = tuple(r["shard"] for r in records)
    if todo:
        (out / shards.MANIFEST).unlink(missing_ok=True)
    if workers is None:
        workers = 1 if world > 1 else available_cores()
    workers = min(workers, max(len(todo), 1))
    state = {"source": source, "transform": transform, "shard_size": shard_size, "out": out,
             "job_id": job_id, "on_error": on_error, "threads": threads}
    total = sum(min((s + 1) * shard_size, len(source)) - s * shard_size for s in todo)
    show = (sys.stderr.isatty() if progress is None else progress) and rank == 0
    label = f"rank 0 of {world}" if world > 1 else "preprocess"
    error, timings = None, [0.0, 0.0, 0.0]
    with tqdm(total=total, unit="rec", desc=label, disable=not show, file=sys.stderr) as bar:
        try:
            written, timings = _run_shards(state, todo, workers, bar)
            records += written
        except Exception as caught:  # every rank must reach the collective below
            error = caught
    mine: dict[str, Any] = {"records": records, "kept": kept, "recordings": total,
                            "error": None if error is None else str(error)}
    gathered = all_gather(mine)
    if error is not None:
        raise error
    failed = [g["error"] for g in gathered if g["error"] is not None]
    if failed:
        raise RecordingError(f"another rank stopped: {failed[0]}")
    manifest = None
    if rank == 0:
        manifest = _manifest(job, job_id, source, transform,
                             [r for g in gathered for r in g["records"]])
        shards.write_json(out / shards.MANIFEST, manifest)
        mine = {"kept": tuple(sorted(s for g in gathered for s in g["kept"])),
                "recordings": sum(g["recordings"] for g in gathered)}
        every = range(num_shards)
    else:
        every = range(rank, num_shards, world)
    return PreprocessResult(
        out=out, manifest=manifest, shards=num_shards,
        written=tuple(sorted(set(every) - set(mine["kept"]))), kept=tuple(mine["kept"]),
        recordings=mine["recordings"], seconds=time.perf_counter() - start_time,
        read_seconds=timings[0], transform_seconds=timings[1], write_seconds=timings[2])
