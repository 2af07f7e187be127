"""The benchmark report: Markdown tables, ``results.json`` and the plots."""

from __future__ import annotations

import json
import math
from dataclasses import asdict, fields
from pathlib import Path
from typing import Any, cast

from evdown_torch._text import format_factor
from evdown_torch.bench.inputs import EVENTS_SWEEP_RATE, BenchInput
from evdown_torch.bench.lineup import (
    PEER_DIFFERENTIATOR_BINS,
    PEER_DT_MS,
    PEER_MEMORY_BUDGET,
    PEER_NOISE_THRESHOLD,
    candidate,
    parse_spec,
)
from evdown_torch.bench.run import BenchResults, Measurement, Plan, log
from evdown_torch.transforms.registry import method_settings

__all__ = ["load_results", "method_table", "sweep_table", "write_report"]

def _num(value: float | None, digits: int = 3) -> str:
    """``digits`` significant digits (more for large numbers), no exponent; n/a for None."""
    if value is None:
        return "n/a"
    if not math.isfinite(value):
        return "inf"
    if value == 0:
        return "0"
    decimals = max(0, digits - 1 - math.floor(math.log10(abs(value))))
    return f"{value:.{decimals}f}"


def _mb(value: int | None) -> str:
    return "n/a" if value is None else _num(value / 1e6)


def method_table(results: BenchResults, input_name: str) -> str:
    """The Markdown table of every candidate on one input (all factors)."""
    peers = [(n, label) for n, label, is_peer in results.candidates if is_peer]
    head = ["method", "factor", "events in", "events out", "out / in", "median ms", "CPU ms",
            "runs", "M events/s", *[f"x {label}" for _, label in peers], "peak added MB",
            "peak process MB", "note"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    rows = [m for m in results.measurements if m.section == "methods" and m.input == input_name]
    for m in rows:
        ratios = []
        for peer, _ in peers:
            ref = results.find("methods", input_name, peer, m.factor)
            if ref is not None and ref.rate and m.rate:
                ratios.append(_num(m.rate / ref.rate))
            else:
                ratios.append("n/a")
        share = m.events_out / m.events_in if m.events_out is not None and m.events_in else None
        cells = [m.label, format_factor(m.factor), str(m.events_in),
                 "n/a" if m.events_out is None else str(m.events_out), _num(share),
                 _num(None if m.seconds is None else m.seconds * 1e3),
                 _num(None if m.cpu_seconds is None else m.cpu_seconds * 1e3), str(m.runs),
                 _num(None if m.rate is None else m.rate / 1e6), *ratios,
                 _mb(m.peak_added), _mb(m.peak_total), m.note.replace("|", "/")]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


_SWEEPS = {
    "events": ("Cost against the number of events", "events",
               f"128x128 sensor, {EVENTS_SWEEP_RATE / 1e3:.0f}k events/s (duration grows "
               "with the count), factor 4"),
    "sensor": ("Cost against the sensor size", "sensor pixels (W x H)",
               "fixed event count and duration (2 s), factor 4"),
    "duration": ("Cost against the recording duration", "duration (s)",
                 "fixed event count on 128x128; the events come in 10 bursts at a fixed rate "
                 "and the pauses between them grow; factor 4"),
}


def sweep_table(results: BenchResults, section: str, value: str) -> str:
    """Markdown table of one sweep: rows are candidates, columns the sweep's points.

    ``value`` is ``"rate"`` (M events/s) or ``"memory"`` (peak added MB).
    """
    swept = [m for m in results.measurements if m.section == section and m.x is not None]
    points = sorted({cast(float, m.x) for m in swept})
    names = {m.input: cast(float, m.x) for m in swept}
    by_x = {x: name for name, x in names.items()}
    labels = [_point_label(section, by_x[x], x) for x in points]
    lines = ["| method | " + " | ".join(labels) + " |", "|" + "---|" * (len(points) + 1)]
    for name, label, _ in results.candidates:
        cells = []
        for x in points:
            m = results.find(section, None, name, 4, x=x)
            if m is None:
                cells.append("n/a")
            elif value == "rate":
                cells.append("skipped" if m.note.startswith("skipped") else
                             _num(None if m.rate is None else m.rate / 1e6))
            else:
                cells.append("skipped" if m.note.startswith("skipped") else _mb(m.peak_added))
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _point_label(section: str, input_name: str, x: float) -> str:
    if section == "events":
        return f"{int(x):,}"
    if section == "sensor":
        return input_name.removeprefix("sensor-")
    return f"{x:g} s"


def write_report(results: BenchResults, out_dir: str | Path, *, command: str = "") -> list[Path]:
    """Write ``report.md``, ``results.json`` and the PNG plots to ``out_dir``.

    Returns:
        The paths written. Without matplotlib the plots are left out and the report says so.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = [out / "results.json"]
    (out / "results.json").write_text(json.dumps(_as_json(results), indent=1))
    plots: list[Path] = []
    notes = list(results.notes)
    try:
        plots = _plots(results, out)
    except ImportError:
        message = ("matplotlib is not installed: the report has no plots "
                   "(pip install 'evdown_torch[plot]' to get them).")
        log(message)
        notes.append(message)
    written += plots
    (out / "report.md").write_text(_markdown(results, plots, notes, command))
    written.insert(0, out / "report.md")
    return written


def _as_json(results: BenchResults) -> dict:
    return {
        "plan": asdict(results.plan), "machine": results.machine,
        "inputs": [asdict(i) for i in results.inputs],
        "candidates": [{"name": n, "label": label, "peer": p}
                       for n, label, p in results.candidates],
        "measurements": [{**asdict(m), "rate": m.rate} for m in results.measurements],
        "notes": results.notes,
        "elapsed_s": results.elapsed_s,
    }


def load_results(path: str | Path) -> BenchResults:
    """Read back the ``results.json`` that :func:`write_report` wrote (to re-render a report).

    Example:
        >>> import tempfile
        >>> from evdown_torch.bench.run import run_benchmark
        >>> r = run_benchmark(short=True, events=300, methods=["downsample"], scaling=False,
        ...                   memory=False)
        >>> with tempfile.TemporaryDirectory() as out:
        ...     _ = write_report(r, out)
        ...     again = load_results(Path(out) / "results.json")
        >>> again.measurements == r.measurements and again.plan == r.plan
        True
    """
    data = json.loads(Path(path).read_text())

    def tuples(value: Any) -> Any:
        return tuple(tuples(v) for v in value) if isinstance(value, list) else value

    plan = Plan(**{k: tuples(v) for k, v in data["plan"].items()})
    inputs = [BenchInput(**{**i, "sensor_size": tuple(i["sensor_size"])})
              for i in data["inputs"]]
    names = {f.name for f in fields(Measurement)}
    measurements = [Measurement(**{k: tuples(v) for k, v in m.items() if k in names})
                    for m in data["measurements"]]
    return BenchResults(plan, data["machine"], inputs, measurements,
                        [(c["name"], c["label"], c["peer"]) for c in data["candidates"]],
                        data["notes"], data["elapsed_s"])


def _markdown(results: BenchResults, plots: list[Path], notes: list[str], command: str) -> str:
    mc, plan = results.machine, results.plan
    lines = [
        "# evdown_torch benchmark report", "",
        f"Mode: {'short' if plan.short else 'full'}; {mc['date']}; took "
        f"{results.elapsed_s:.0f} s." + (f" Command: `{command}`." if command else ""), "",
        f"Machine: {mc['cpu']}, {mc['cores']} cores, {mc['memory']}; Python {mc['python']}, "
        f"torch {mc['torch']} ({mc['threads']} thread), NumPy {mc['numpy']}, "
        f"Tonic {mc['tonic']}.", "",
        "## What is measured", "",
        "- **Time**: wall-clock time of one call of the transform on a Tonic structured array "
        "(validation and conversions included), `torch.set_num_threads(1)`; median of "
        f"{plan.repeats} or more calls after one warm-up call (more until the calls add up to "
        f"{plan.min_seconds:g} s; {plan.scaling_repeats} or more in the scaling sweeps). "
        "*CPU ms* is the median process CPU time of the same calls: where it is well below the "
        "wall-clock time, the call waited for a core on a busy machine. Every candidate "
        "runs in this one process and run. **M events/s** is input events / median time; "
        "**x peer** is the candidate's throughput divided by the peer's (above 1: faster).",
        "- **Peak memory** (MB = 10^6 bytes), per measurement in a fresh process forked from a "
        "worker that has only imported the libraries: *added* is the peak resident set during "
        "the one call minus the resident set just before it (input loaded); *process* is the "
        "peak resident set of a fresh process that imports, loads the input and runs the "
        "method once (interpreter and libraries included; the worker imports torch and "
        "Tonic for every candidate, so a peer's figure includes torch too). Both are taken "
        "after a warm-up call on the first 1000 events, so one-time initialisation is not "
        "counted as the call's.",
        f"- **Peers**: `tonic.transforms.Downsample(spatial_factor=1/f)`; "
        f"`tonic.transforms.EventDownsampling(sensor_size, target_size=ceil(size/f), "
        f"dt={PEER_DT_MS:g} ms, noise_threshold={PEER_NOISE_THRESHOLD})`, integrator and "
        f"differentiator (differentiator_time_bins={PEER_DIFFERENTIATOR_BINS}). "
        "EventDownsampling builds dense frames of duration / dt steps; a run whose frames "
        f"would exceed {PEER_MEMORY_BUDGET / 1e9:.0f} GB is skipped.",
        "- **Method settings** (the defaults, except those in `BENCH_SETTINGS`): "
        + "; ".join(f"{name}: {text}" for name, text in _settings_text(results)) + ".",
    ]
    if notes:
        lines += ["", "Notes:", *[f"- {n}" for n in notes]]
    lines += ["", "## Inputs", "", "| input | sensor | events | duration s | source |",
              "|---|---|---|---|---|"]
    for i in results.inputs:
        lines.append(f"| {i.name} | {i.sensor_size[0]}x{i.sensor_size[1]} | {i.num_events} | "
                     f"{i.duration_s:.3f} | {i.source} |")
    lines += ["", "## Methods and peers"]
    for i in results.inputs:
        if any(m.section == "methods" and m.input == i.name for m in results.measurements):
            lines += ["", f"### {i.name}: {i.sensor_size[0]}x{i.sensor_size[1]}, "
                      f"{i.num_events:,} events, {i.duration_s:.2f} s", "",
                      method_table(results, i.name)]
            plot = next((p for p in plots if p.name == f"methods_{i.name}.png"), None)
            if plot is not None:
                lines += ["", f"![{i.name}: speed, memory and events kept]({plot.name})"]
    sections = [s for s in _SWEEPS if any(m.section == s for m in results.measurements)]
    if sections:
        lines += ["", "## Scaling"]
    for s in sections:
        title, _, setup = _SWEEPS[s]
        lines += ["", f"### {title}", "", f"{setup}.", "", "Throughput, M events/s:", "",
                  sweep_table(results, s, "rate"), "", "Peak added memory, MB:", "",
                  sweep_table(results, s, "memory")]
        plot = next((p for p in plots if p.name == f"scaling_{s}.png"), None)
        if plot is not None:
            lines += ["", f"![{title}]({plot.name})"]
    return "\n".join(lines) + "\n"


def _settings_text(results: BenchResults) -> list[tuple[str, str]]:
    out = []
    for name, _, peer in results.candidates:
        if peer:
            continue
        transform = candidate(name).build((128, 128, 2), 4)
        keys = method_settings(parse_spec(name)[0])
        values = [f"{key}={getattr(transform, key)!r}" for key in keys]
        out.append((name, ", ".join(values) or "no settings"))
    return out


def _kept(m: Measurement) -> float | None:
    """Output events per input event (``None`` when not measured)."""
    if m.events_out is None or not m.events_in:
        return None
    return m.events_out / m.events_in


def _plots(results: BenchResults, out: Path) -> list[Path]:
    """One figure per method table (at its largest factor) and per scaling sweep.

    Speed, peak memory and the share of events kept, side by side.
    """
    from matplotlib.figure import Figure

    panels = (("throughput (M events/s)", lambda m: None if m.rate is None else m.rate / 1e6),
              ("peak added memory (MB)",
               lambda m: None if m.peak_added is None else max(m.peak_added, 1e4) / 1e6),
              ("events kept (output / input)", _kept))
    paths = []
    for inp in results.inputs:
        rows = [m for m in results.measurements if m.section == "methods" and m.input == inp.name]
        if not rows:
            continue
        factor = max((m.factor for m in rows), key=lambda f: (f, f) if isinstance(f, int) else f)
        rows = [m for m in rows if m.factor == factor]
        fig = Figure(figsize=(13, 0.35 * len(rows) + 1.6), layout="constrained")
        axes = fig.subplots(1, 3, sharey=True)
        for ax, (xlabel, value) in zip(axes, panels, strict=True):
            bars = [(y, v, m.peer) for y, m in enumerate(rows)
                    if (v := value(m)) is not None and v > 0]
            if bars:
                ax.barh([y for y, _, _ in bars], [v for _, v, _ in bars],
                        color=["tab:gray" if peer else "tab:blue" for _, _, peer in bars])
                ax.set_xscale("log")
            else:
                ax.text(0.5, 0.5, "not measured", ha="center", va="center",
                        transform=ax.transAxes)
            ax.set_xlabel(xlabel)
            ax.grid(True, axis="x", which="both", alpha=0.3)
        axes[0].set_yticks(range(len(rows)), [m.label for m in rows])
        axes[0].set_ylim(len(rows) - 0.5, -0.5)
        fig.suptitle(f"{inp.name}: {inp.sensor_size[0]}x{inp.sensor_size[1]}, "
                     f"{inp.num_events:,} events, factor {format_factor(factor)} "
                     "(gray: other libraries)", fontsize=9)
        path = out / f"methods_{inp.name}.png"
        fig.savefig(path, dpi=100)
        paths.append(path)
    for s, (title, xlabel, setup) in _SWEEPS.items():
        rows = [m for m in results.measurements if m.section == s]
        if not rows:
            continue
        fig = Figure(figsize=(16, 4.2), layout="constrained")
        axes = fig.subplots(1, 3)
        plotted = [0, 0, 0]
        for name, label, peer in results.candidates:
            mine = sorted((m for m in rows if m.candidate == name), key=lambda m: cast(float, m.x))
            style = dict(marker="o", linestyle="--" if peer else "-", label=label)
            for k, (ax, (_, value)) in enumerate(zip(axes, panels, strict=True)):
                points = [(m.x, v) for m in mine if (v := value(m)) is not None and v > 0]
                ax.plot([x for x, _ in points], [v for _, v in points], **style)
                plotted[k] += len(points)
        for ax, (ylabel, _), count in zip(axes, panels, plotted, strict=True):
            ax.set_xscale("log")
            if count:
                ax.set_yscale("log")
            else:
                ax.text(0.5, 0.5, "not measured", ha="center", va="center",
                        transform=ax.transAxes)
            ax.set_xlabel(xlabel)
            ax.set_ylabel(ylabel)
            ax.grid(True, which="both", alpha=0.3)
        fig.legend(*axes[0].get_legend_handles_labels(), loc="outside right center", fontsize=8)
        fig.suptitle(f"{title} ({setup})", fontsize=9)
        path = out / f"scaling_{s}.png"
        fig.savefig(path, dpi=100)
        paths.append(path)
    return paths
