"""The study's report: ``results.csv``, ``report.md`` and ``tradeoff.png``."""

from __future__ import annotations

import csv
import math
from collections.abc import Callable
from pathlib import Path

from evdown_torch.evaluation.cells import BASELINE, CONTROL
from evdown_torch.evaluation.config import EvaluationConfig
from evdown_torch.evaluation.figure import pareto_front, plot_tradeoff
from evdown_torch.evaluation.plan import CONTROL_ROLE, PRIMARY, SANITY, pair
from evdown_torch.evaluation.statistics import dunnett_seeds
from evdown_torch.evaluation.study import CellResult, EvaluationResult
from evdown_torch.evaluation.verdicts import control_of
from evdown_torch.transforms.registry import METHODS

__all__ = [
    "CSV_COLUMNS", "markdown_table", "pareto_front", "primary_table", "question",
    "smoke_test_line", "write_report",
]

Log = Callable[[str], None]

#: Gesture classes of the study's datasets (DVS128 Gesture's 11).
NUM_CLASSES = 11

#: A run with fewer test recordings per class than this, or fewer epochs, is a smoke test: its
#: accuracies and differences say nothing about the methods (configs/tiny.toml is one).
SMOKE_TEST_PER_CLASS = 10
SMOKE_TEST_EPOCHS = 5

CSV_COLUMNS = (
    "method", "role", "factor_x", "factor_y", "budget", "setting", "width", "height", "seeds",
    "learning_rate", "accuracy", "ci_low", "ci_high", "accuracies", "fold_accuracies",
    "events_per_recording",
    "events_per_second", "reduction", "rate_vs_camera", "consistency", "control_consistency",
    "difference_vs_control", "difference_low", "difference_high", "p_value", "p_holm",
    "significant", "equivalence_p", "detectable_difference", "difference_vs_peer",
    "p_holm_vs_peer", "paired",
    "delay", "density", "entropy", "macs_per_recording", "synops_per_recording",
    "cpu_us_per_recording", "throughput_events_per_s", "train_seconds",
)


def _setting(c: CellResult) -> str:
    """The calibrated budget setting, e.g. ``threshold=0.31``."""
    if c.calibration is None:
        return ""
    name = "keep" if c.method == CONTROL else METHODS[c.method].budget_setting
    return f"{name}={c.calibration['value']:.4g}"


def _factor(c: CellResult) -> str:
    f = c.factor
    return str(f[0]) if f[0] == f[1] else f"{f[0]}x{f[1]}"


def _peer(result: EvaluationResult, c: CellResult) -> CellResult | None:
    peer = result.config.methods.primary_peer
    return next((o for o in result.cells if o.method == peer and o.factor == c.factor
                 and o.budget == c.budget and o.cell.classifier == c.cell.classifier), None)


def noninferiority_lines(result: EvaluationResult) -> str:
    """The non-inferiority test of ``methods.noninferiority``, one line per primary factor."""
    m = result.config.methods
    if not result.noninferiority:
        return ""
    tested, reference = m.noninferiority
    return f"**Non-inferiority** of {tested} to {reference} (margin {m.noninferiority_margin:g}" \
        ", one-sided, Holm over the factors):\n\n" + "".join(
            f"- x{f[0]}: difference {k.difference:+.3f} {_ci(*k.interval)}, p {k.p_value:.2g} "
            f"(Holm {k.p_holm:.2g}): {'non-inferior' if k.significant else 'not shown'}\n"
            for f, k in result.noninferiority.items()) + "\n"


def _number(value: float | None, fmt: str) -> str:
    return "" if value is None else format(value, fmt)


def _significant(value: float, digits: int = 3) -> str:
    """``value`` to ``digits`` significant digits in plain notation: 0.0270, 15.3, 1,204.

    Example:
        >>> _significant(0.027012), _significant(15.31), _significant(1204.4), _significant(0.0)
        ('0.0270', '15.3', '1,204', '0')
    """
    if value == 0 or not math.isfinite(value):
        return f"{value:g}"
    decimals = max(0, digits - 1 - math.floor(math.log10(abs(value))))
    return f"{value:,.{decimals}f}"


def _plural(count: int, noun: str) -> str:
    return f"{count} {noun}{'' if count == 1 else 's'}"


def _csv_rows(result: EvaluationResult) -> list[dict[str, str]]:
    rows = []
    for c in result.cells:
        control = control_of(result.cells, c)
        k, peer = c.comparison, c.peer_comparison
        rows.append({
            "method": c.cell.name, "role": c.role, "factor_x": str(c.factor[0]),
            "factor_y": str(c.factor[1]),
            "budget": _number(c.budget, "g"), "setting": _setting(c),
            "width": str(c.output_size[0]), "height": str(c.output_size[1]),
            "seeds": ";".join(map(str, c.seeds)), "learning_rate": f"{c.learning_rate:g}",
            "accuracy": f"{c.accuracy:.4f}", "ci_low": f"{c.interval[0]:.4f}",
            "ci_high": f"{c.interval[1]:.4f}",
            "accuracies": ";".join(f"{a:.4f}" for a in c.accuracies),
            "fold_accuracies": ";".join(f"{r}:{f}:{s}={a:.4f}@{lr:g}"
                                        for r, f, s, a, lr in c.units),
            "events_per_recording": f"{c.events_per_recording:.1f}",
            "events_per_second": f"{c.events_per_second:.1f}",
            "reduction": f"{c.reduction:.4f}",
            "rate_vs_camera": _number(c.rate_vs_camera, ".4f"),
            "consistency": _number(c.consistency, ".4f"),
            "control_consistency": _number(control.consistency if control else None, ".4f"),
            "difference_vs_control": _number(k.difference if k else None, ".4f"),
            "difference_low": _number(k.interval[0] if k else None, ".4f"),
            "difference_high": _number(k.interval[1] if k else None, ".4f"),
            "p_value": _number(k.p_value if k else None, ".4g"),
            "p_holm": _number(k.p_holm if k else None, ".4g"),
            "significant": "" if k is None or k.significant is None
            else str(k.significant).lower(),
            "equivalence_p": _number(k.equivalence_p if k else None, ".4g"),
            "detectable_difference": _number(k.detectable if k else None, ".4f"),
            "difference_vs_peer": _number(peer.difference if peer else None, ".4f"),
            "p_holm_vs_peer": _number(peer.p_holm if peer else None, ".4g"),
            "paired": "" if k is None else str(k.paired).lower(),
            "delay": c.delay,
            "density": f"{c.density:.6g}", "entropy": f"{c.entropy:.6g}",
            "macs_per_recording": str(c.macs_per_recording),
            "synops_per_recording": f"{c.synops_per_recording:.0f}",
            "cpu_us_per_recording": _number(c.cpu_us_per_recording, ".0f"),
            "throughput_events_per_s": _number(c.throughput, ".0f"),
            "train_seconds": f"{c.train_seconds:.4g}",
        })
    return rows


def _ci(low: float, high: float) -> str:
    return f"[{low:+.3f}, {high:+.3f}]"


def question(config: EvaluationConfig) -> str:
    """The primary question of ``config``, in words (stated before the run)."""
    m, t = config.methods, config.training
    if not m.primary:
        return "No primary question: every comparison is exploratory."
    reference = ("the low-resolution camera's event count" if m.budget_reference == "camera"
                 else "the input's event count")
    factors = ", ".join(f"x{pair(f)[0]}" for f in m.primary_factors)
    control = t.control_seeds or dunnett_seeds(t.primary_seeds, len(m.primary))
    budgets = (f"a budget of {m.primary_budget:g}" if not m.primary_budgets else "budgets of "
               + ", ".join(f"{b:g} (x{pair(f)[0]})"
                           for f, b in zip(m.primary_factors, m.primary_budgets)))
    peers = 2 if m.primary_peer else 1
    peer = f" and than {m.primary_peer} at the same budget" if m.primary_peer else ""
    d = config.data
    unit = (f"the {d.repeats} x {d.folds} train/test splits of repeated stratified "
            "cross-validation are the unit (seeds averaged within each), paired, tested with "
            "Nadeau and Bengio's corrected resampled t" if d.folds else
            "seeds are the unit of replication (hierarchical bootstrap, seeds outer, test "
            f"recordings inner, {config.statistics.resamples:,} resamples)")
    tested = ""
    if m.noninferiority:
        tested = (f" Beside it: is {m.noninferiority[0]} non-inferior to {m.noninferiority[1]} "
                  f"within {m.noninferiority_margin:g} accuracy at each primary factor?")
    return (
        f"At {budgets} x {reference}, at factors {factors}, does each "
        f"of {', '.join(m.primary)} keep more accuracy than random thinning of Downsample to "
        f"the same budget{peer}? {len(m.primary) * len(m.primary_factors) * peers} one-sided "
        f"comparisons, Holm-corrected within this family at alpha = "
        f"{config.statistics.alpha:g}; {_plural(t.primary_seeds, 'training seed')} per method "
        "cell, "
        f"{control} on the shared control{' and the peer' if peers == 2 else ''}; "
        f"{unit}.{tested}"
    )


def primary_table(result: EvaluationResult) -> str:
    """The primary family: each verdict, its interval, how the seeds were paired, the power."""
    lines = ["| method | factor | accuracy | reference | difference [95% CI] | p (Holm) | "
             "seeds | detectable at 80 % |",
             "|---|---|---|---|---|---|---|---|"]
    primary = result.primary()
    for c, k, control in [(c, c.comparison, control_of(result.cells, c)) for c in primary] + [
            (c, c.peer_comparison, _peer(result, c)) for c in primary]:
        if k is None or control is None:
            continue
        seeds = (f"paired ({len(c.seeds)})" if k.paired
                 else f"{len(c.seeds)} vs {len(control.seeds)}")
        lines.append(
            f"| {c.method} | {_factor(c)} | {c.accuracy:.3f} | {control.method} "
            f"{control.accuracy:.3f} "
            f"| {k.difference:+.3f} {_ci(*k.interval)} | {k.p_value:.2g} ({k.p_holm:.2g})"
            f"{' *' if k.significant else ''} | {seeds} | {k.detectable:.3f} |")
    return "\n".join(lines) + "\n"


def markdown_table(result: EvaluationResult) -> str:
    """Every cell as a Markdown table (no measured times, so equal settings give equal tables).

    Differences from the control carry their interval; only the primary family has p-values (in
    :func:`primary_table`).
    """
    lines = [
        "| method | role | factor | budget | setting | events/rec | x camera | seeds | "
        "accuracy [95% CI] | vs control [95% CI] | equivalent (TOST p) | delay | "
        "consistency (control) | MMACs/rec | synops/rec |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    margin = result.config.methods.equivalence_margin
    alpha = result.config.statistics.alpha
    for c in result.cells:
        control = control_of(result.cells, c)
        k = c.comparison
        versus = "–" if k is None else f"{k.difference:+.3f} {_ci(*k.interval)}"
        if c.role == SANITY and k is not None:
            versus = f"control {versus}"
        elif k is not None and control is not None and control.cell.matches is not None:
            versus = f"matched control {versus}"
        equivalent = "–" if k is None else (
            f"{'yes' if k.equivalence_p < alpha else 'no'} ({k.equivalence_p:.2g})")
        consistency = _number(c.consistency, ".3f")
        if control is not None and c.method != CONTROL and control.consistency is not None:
            consistency += f" ({control.consistency:.3f})"
        lines.append(
            f"| {c.cell.name} | {c.role} | {_factor(c) if c.method != BASELINE else 1} "
            f"| {_number(c.budget, 'g') or '–'} | {_setting(c) or '–'} "
            f"| {c.events_per_recording:,.0f} | {_number(c.rate_vs_camera, '.2f') or 'n/a'} "
            f"| {len(c.seeds)} | {c.accuracy:.3f} [{c.interval[0]:.3f}, {c.interval[1]:.3f}] "
            f"| {versus} | {equivalent} | {c.delay} | {consistency or '–'} "
            f"| {_significant(c.macs_per_recording / 1e6)} | {c.synops_per_recording:,.0f} |"
        )
    return "\n".join(lines) + f"\n\nequivalent: TOST within +-{margin:g} at {alpha:g}.\n"


def sanity_lines(result: EvaluationResult) -> str:
    """The classifier's sanity checks (a) to (d), one line each."""
    config = result.config
    lines = []
    for factor, k in result.sanity.items():
        verdict = "FAILS" if k.significant else "passes"
        lines.append(
            f"- (a) x{factor[0]}: every event of Downsample against its random subset (the "
            f"control): control - Downsample {k.difference:+.3f} {_ci(*k.interval)}, one-sided "
            f"p {k.p_value:.2g}: {verdict} (a superset must not score significantly lower).")
    if not result.sanity:
        lines.append("- (a) not run (no sanity rows or no control at the primary budget).")
    grid = config.model.grid
    pooled = sorted({c.output_size for c in result.cells if c.method != BASELINE
                     and grid and max(c.output_size) > grid})
    lines.append(
        "- (b) " + ("every downscaled cell reaches the first spiking layer at its full output "
                    f"resolution (grid {grid})." if not pooled else
                    f"cells of output size {', '.join(f'{w}x{h}' for w, h in pooled)} are pooled "
                    f"to at most {grid}x{grid} by the stem before the first spiking layer."))
    lines.append(
        "- (c) " + ("the count channels are divided by their RMS over each seed's training "
                    "frames, so dense and sparse cells feed inputs of the same energy."
                    if config.training.normalise else
                    "the count channels are not normalised: dense cells feed larger inputs."))
    if result.learning_rates and any(means for _, means in result.learning_rates.values()):
        chosen = "; ".join(
            f"x{f[0]}: {rate:g} (" + ", ".join(f"{r:g}: {m:.3f}" for r, m in means.items())
            + ")" for f, (rate, means) in result.learning_rates.items())
        lines.append(f"- (d) learning rate chosen per factor on {config.data.validation_samples} "
                     f"validation recordings of the training pool, never the test set: {chosen}.")
    else:
        lines.append(f"- (d) learning rate fixed at {config.training.learning_rate:g} (no "
                     "candidates configured).")
    return "\n".join(lines) + "\n"


def per_class_table(result: EvaluationResult, num_classes: int | None = None) -> str:
    """Accuracy per class of the primary cells and their controls (over all seeds).

    ``num_classes`` defaults to the dataset's. A class without test recordings shows ``–``,
    and a line below the table says which.
    """
    if num_classes is None:
        num_classes = result.config.data.num_classes
    cells = [c for c in result.cells if c.role in (PRIMARY, CONTROL_ROLE, SANITY)]
    if not cells:
        return ""
    head = "| cell | " + " | ".join(str(k) for k in range(num_classes)) + " |"
    lines = [head, "|---|" + "---|" * num_classes]
    for c in cells:
        values = " | ".join("–" if math.isnan(v) else f"{v:.2f}"
                            for v in c.per_class(num_classes))
        lines.append(f"| {c.cell.label} | {values} |")
    untested = _untested_classes(result, num_classes)
    if untested:
        lines.append(f"\n–: no test recording of class {', '.join(map(str, untested))} (the "
                     f"test split has {_plural(len(cells[0].labels), 'recording')}).")
    return "\n".join(lines) + "\n"


def _run_lines(result: EvaluationResult) -> str:
    """How the run went: its wall time and CPU seconds, in all and per ``torchrun`` rank.

    The only part of the report besides the cost table that differs between runs.
    """
    if not result.ranks:
        return (f"**Run.** Wall time {result.wall_seconds:.0f} s, {result.cpu_seconds:.0f} CPU "
                f"s, with {result.workers} worker process(es); {result.generated} recordings "
                "or renders generated.\n")
    lines = [
        f"**Run.** {len(result.ranks)} ranks (torchrun), {result.workers} worker process(es) "
        f"each; results gathered through {result.gathered_through}. Wall time "
        f"{result.wall_seconds:.0f} s (rank 0, from start to report), {result.cpu_seconds:.0f} "
        f"CPU s in total (every rank and its workers); {result.generated} recordings or "
        "renders generated.\n",
        "| rank | host | device | jobs | generated | wall s | CPU s |",
        "|---|---|---|---|---|---|---|"]
    for r in result.ranks:
        lines.append(f"| {r.rank} | {r.host} | {r.device} | {r.jobs} | {r.generated} "
                     f"| {r.wall_seconds:.0f} | {r.cpu_seconds:.0f} |")
    return "\n".join(lines) + "\n"


def _untested_classes(result: EvaluationResult, num_classes: int) -> list[int]:
    labels = set(result.cells[0].labels) if result.cells else set()
    return [k for k in range(num_classes) if k not in labels]


def smoke_test_line(result: EvaluationResult, num_classes: int = NUM_CLASSES) -> str:
    """A line saying the run is too small for its accuracies to mean anything, or ``""``.

    Too small: fewer than :data:`SMOKE_TEST_PER_CLASS` test recordings per class, or fewer
    than :data:`SMOKE_TEST_EPOCHS` training epochs.
    """
    tested = len(result.cells[0].labels) if result.cells else 0
    epochs = result.config.training.epochs
    if tested >= SMOKE_TEST_PER_CLASS * num_classes and epochs >= SMOKE_TEST_EPOCHS:
        return ""
    untested = len(_untested_classes(result, num_classes))
    return (
        f"**A smoke test, not a result.** {_plural(tested, 'test recording')} for "
        f"{num_classes} classes ({f'{untested} without one; ' if untested else ''}fewer than "
        f"{SMOKE_TEST_PER_CLASS} per class) and {_plural(epochs, 'epoch')} of training: the "
        "accuracies and differences below mean nothing about the methods. configs/quick.toml "
        "is the smallest run that answers the primary question.\n\n"
    )


def _speed_table(result: EvaluationResult) -> str:
    lines = ["| cell | CPU us/recording | throughput (M ev/s, 1 thread) | delay | "
             "training s/seed |", "|---|---|---|---|---|"]
    for c in result.cells:
        speed = "–" if c.throughput is None else f"{c.throughput / 1e6:.2f}"
        lines.append(f"| {c.cell.label} | {_number(c.cpu_us_per_recording, ',.0f') or '–'} "
                     f"| {speed} | {c.delay} | {_significant(c.train_seconds)} |")
    return "\n".join(lines) + "\n"


def _markdown(result: EvaluationResult) -> str:
    config = result.config
    m, t, s = config.model, config.training, config.statistics
    reference = ("the low-resolution camera's event count (the generator's ground truth)"
                 if config.methods.budget_reference == "camera" else "the input's event count")
    per_seed = (f"{config.data.train_per_seed} recordings drawn per seed from a pool of "
                f"{config.data.train_samples}" if config.data.train_per_seed
                else f"all {config.data.train_samples} training recordings")
    return (
        f"# evdown evaluate: {config.name}\n\n"
        + smoke_test_line(result)
        + f"**Primary question.** {question(config)}\n\n"
        + primary_table(result) + "\n" + noninferiority_lines(result)
        + "\nseeds: paired where both cells trained on the same seeds (resampled as pairs), "
        "else each cell's count; * significant after Holm. A claim replicates only if it holds "
        "on another run on other data (another data.seed); detectable at 80 %: the smallest "
        "true gap this design detects with probability 0.8 at Holm's strictest step ("
        + ("Student's t on the splits' degrees of freedom" if config.data.folds
           else "normal approximation") + ").\n\n"
        "**Sanity checks of the classifier.**\n\n" + sanity_lines(result)
        + f"\n**Data.** {result.description}; {config.data.time_bins} time bins per recording"
        f"{', with mean-time channels' if config.data.mean_time else ''}. Training: {per_seed}. "
        f"Budgets: multiples of {reference}, calibrated on "
        + (f"{config.data.calibration_samples} recordings of Train held out of the study "
           "(once, for every fold). " if config.data.calibration == "held_out" else
           f"the first {config.data.calibration_samples} training recordings. ")
        + f"Classifier: SpikingClassifier(channels={list(m.channels)}, grid={m.grid}, "
        f"stem_channels={m.stem_channels}, pool_size={m.pool_size}), "
        f"{_plural(t.epochs, 'epoch')}, "
        f"batch {t.batch_size}, {t.encoding} input, trained on {result.device}.\n\n"
        + _run_lines(result)
        + "\n**Every cell** (exploratory rows carry no p-value):\n\n"
        + markdown_table(result)
        + f"\nevents/rec: mean output events per test recording; x camera: output events / "
        "the low-resolution camera's events; accuracy: mean over seeds and test recordings, "
        f"{s.confidence:.0%} hierarchical bootstrap interval; vs control: accuracy minus the "
        "thinning control's at the same factor and budget (for the sanity rows, the control "
        "minus Downsample); delay: how long after an event the method's output is final; "
        f"consistency: 1 - normalised L1 distance of counts in "
        f"{config.measures.consistency_bin_us / 1000:g} ms bins to the camera's recording (the "
        "control's in brackets); MMACs/rec: the classifier's multiply-accumulates per "
        "recording, in millions (dense); synops/rec: output events times the first layer's "
        "fan-out.\n\n"
        "**Accuracy per class** (primary, control and sanity cells, all seeds):\n\n"
        + per_class_table(result)
        + "\n**Cost** (each transform timed alone on one thread; training time per seed):\n\n"
        + _speed_table(result)
    )


def write_report(
    result: EvaluationResult, directory: str | Path, log: Log | None = None
) -> dict[str, Path]:
    """Write ``results.csv``, ``report.md`` and ``tradeoff.png`` into ``directory``.

    Args:
        result: what :func:`~evdown_torch.evaluation.run_evaluation` returned.
        directory: created if needed; existing files of these names are replaced.
        log: told where the files went, and when the plot is skipped for want of matplotlib.

    Returns:
        ``{"csv": ..., "markdown": ..., "plot": ...}`` for the files written (no ``"plot"``
        without matplotlib).
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    paths = {"csv": directory / "results.csv", "markdown": directory / "report.md"}
    with paths["csv"].open("w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        writer.writerows(_csv_rows(result))
    paths["markdown"].write_text(_markdown(result), encoding="utf-8")
    plot = directory / "tradeoff.png"
    if plot_tradeoff(result, plot):
        paths["plot"] = plot
    elif log is not None:
        log("matplotlib is not installed: skipped tradeoff.png "
            "(pip install matplotlib, or evdown_torch[plot])")
    if log is not None:
        log("wrote " + ", ".join(str(p) for p in paths.values()))
    return paths
