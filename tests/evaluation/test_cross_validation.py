"""Repeated stratified k-fold cross-validation of the pooled N-MNIST recordings."""

from __future__ import annotations

import csv
import dataclasses
import math
from collections import Counter
from pathlib import Path

import pytest

from evdown_torch.evaluation import data, run_evaluation, write_report
from evdown_torch.evaluation.config import load_config, parse_config
from evdown_torch.evaluation.data import StudyData, fold_assignment
from tests.conftest import SHARED_DATA

REAL = SHARED_DATA / "nmnist_small"


def _config(cache, **data):
    document = _document(cache)
    document["data"].update(data)
    return parse_config(document)


def _document(cache):
    return {
        "data": {"dataset": "nmnist", "root": str(REAL), "train_samples": 24,
                 "test_samples": 12, "calibration_samples": 6, "time_bins": 2,
                 "duration_us": 0, "folds": 3, "repeats": 2, "validation_samples": 6},
        "methods": {"factors": [4], "include": ["downsample", "event_count"],
                    "budget_reference": "input", "budgets": [0.25], "primary": ["event_count"],
                    "primary_factors": [4], "primary_budget": 0.25, "sanity": False,
                    "full_resolution": False},
        "model": {"channels": [2], "pool_size": 1, "grid": 8},
        "training": {"epochs": 1, "seeds": [0, 1], "workers": 0, "device": "cpu",
                     "primary_seeds": 2, "control_seeds": 2, "learning_rates": [0.005, 0.01],
                     "selection_seeds": 1},
        "statistics": {"resamples": 50},
        "output": {"cache": str(cache)},
    }


@pytest.mark.parametrize("folds", [2, 3, 5])
def test_folds_are_stratified_balanced_and_partition_the_recordings(folds):
    labels = [0] * 7 + [1] * 4 + [2] * 9 + [3] * 1
    order, fold_of = fold_assignment(labels, folds, seed=3)
    assert sorted(order) == list(range(len(labels)))
    sizes = Counter(fold_of)
    assert max(sizes.values()) - min(sizes.values()) <= 1
    for label in set(labels):
        per_fold = Counter(f for f, y in zip(fold_of, labels) if y == label)
        counts = [per_fold.get(f, 0) for f in range(folds)]
        assert max(counts) - min(counts) <= 1, (label, counts)
    assert fold_assignment(labels, folds, seed=3) == (order, fold_of)
    assert fold_assignment(labels, folds, seed=4)[0] != order


@pytest.mark.parametrize(("data", "message"), [
    ({"folds": 1}, "at least 2, got 1"),
    ({"folds": 0, "repeats": 2}, "needs data.folds >= 2"),
    ({"dataset": "synthetic", "folds": 3}, "keeps its own train and test split"),
])
def test_bad_fold_settings_are_refused(tmp_path, data, message):
    with pytest.raises(ValueError, match=message):
        _config(tmp_path, **data)


def test_each_repeat_tests_every_recording_once_on_folds_it_did_not_train_on(tmp_path):
    pytest.importorskip("tonic")
    if not REAL.is_dir():
        pytest.skip(f"{REAL} is absent")
    config = _config(tmp_path)
    pooled = StudyData(config.data, str(tmp_path), (0, 0)).pooled_size
    assert pooled == 36
    for repeat in range(2):
        tested = []
        for fold in range(3):
            source = StudyData(config.data, str(tmp_path), (repeat, fold))
            train, test = source._fold_split("train"), source.test_positions
            assert not set(train) & set(test) and len(train) + len(test) == pooled
            tested += test
        assert sorted(tested) == list(range(pooled))
    a, b = (StudyData(config.data, str(tmp_path), (r, 0)).test_positions for r in (0, 1))
    assert a != b  # each repeat deals its own folds
    with pytest.raises(ValueError, match="needs a fold exactly when"):
        StudyData(config.data, str(tmp_path))


@pytest.mark.parametrize(("data", "message"), [
    ({"calibration": "held_out", "train_samples": 0}, "needs recordings of Train left out"),
    ({"calibration": "held_out", "dataset": "synthetic", "folds": 0, "repeats": 1},
     "calibrates on its training"),
    ({"calibration": "first"}, "data.calibration must be one of"),
])
def test_bad_calibration_settings_are_refused(tmp_path, data, message):
    with pytest.raises(ValueError, match=message):
        _config(tmp_path, **data)


def test_held_out_calibration_recordings_are_outside_every_fold(tmp_path):
    pytest.importorskip("tonic")
    if not REAL.is_dir():
        pytest.skip(f"{REAL} is absent")
    config = _config(tmp_path, calibration="held_out")
    sources = [StudyData(config.data, str(tmp_path), unit) for unit in config.data.fold_units]
    held = sources[0]
    assert held.calibration_split == "calibration" and held.size("calibration") == 6
    in_study = {data._pooled(config.data)[p] for p in range(held.pooled_size)}
    taken = {(True, i) for i in data._held_out(config.data)}
    assert len(taken) == 6 and not taken & in_study  # never a training or test recording
    assert all(s.key("calibration") == held.key("calibration") for s in sources)  # one for all
    assert held.key("calibration") != held.key("train")
    first = [held.recording("calibration", i)[1] for i in range(6)]
    assert len(set(first)) > 1  # a mix of classes
    too_many = _config(tmp_path, calibration="held_out", calibration_samples=977)
    with pytest.raises(ValueError, match="needs 977 recordings of Train outside"):
        data.check_available(too_many.data)


def test_held_out_calibration_runs_once_for_every_fold(tmp_path):
    pytest.importorskip("tonic")
    if not REAL.is_dir():
        pytest.skip(f"{REAL} is absent")
    config = _config(tmp_path / "cache", calibration="held_out")
    messages: list[str] = []
    result = run_evaluation(config, log=messages.append)
    budgeted = [c for c in result.cells if c.calibration is not None]
    assert budgeted and all(c.calibration["target"] > 0 for c in budgeted)
    calibrations = list((tmp_path / "cache").rglob("calibrations/*.json"))
    assert len(calibrations) == len(budgeted)  # not one per fold
    assert sum("6 held-out recordings" in m for m in messages) == 6  # every fold reads them
    # each cell's frames are made once, over the 36 pooled recordings (2 chunks), for all folds
    units = sum(len(c.seeds) if c.method == "control" else 1 for c in result.cells)
    assert len(list((tmp_path / "cache").rglob("frames/*.pt"))) == units * 2


def test_cross_validated_study_end_to_end(tmp_path):
    pytest.importorskip("tonic")
    if not REAL.is_dir():
        pytest.skip(f"{REAL} is absent")
    config = _config(tmp_path / "cache")
    result = run_evaluation(config, log=None)
    assert [c.method for c in result.cells] == ["event_count", "control", "downsample"]
    labels = result.cells[0].labels
    for cell in result.cells:
        assert len(cell.correct) == 2 * 2 and all(len(row) == 36 for row in cell.correct)
        assert cell.labels == labels  # one pooled order for every cell: paired
        assert sorted((r, f, s) for r, f, s, _, _ in cell.units) == [
            (r, f, s) for r in range(2) for f in range(3) for s in (0, 1)]
        # a (repeat, seed) row is the concatenation of that repeat's three folds
        for r in range(2):
            for i, s in enumerate((0, 1)):
                folds = [a for rr, _, ss, a, _ in cell.units if rr == r and ss == s]
                row = cell.correct[2 * r + i]
                assert sum(row) == pytest.approx(sum(a * 12 for a in folds))
    paths = write_report(result, tmp_path / "out")
    with paths["csv"].open() as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows[0]["fold_accuracies"].split(";")) == 12


def test_primary_family_against_control_and_peer_with_the_corrected_t(tmp_path):
    pytest.importorskip("tonic")
    if not REAL.is_dir():
        pytest.skip(f"{REAL} is absent")
    config = parse_config({
        **_document(tmp_path / "cache"),
        "methods": {"factors": [2, 4], "include": ["downsample"],
                    "budget_reference": "input", "budgets": [], "control": False,
                    "primary": ["event_count"], "primary_factors": [2, 4],
                    "primary_budgets": [0.25, 0.05], "primary_peer": "density",
                    "noninferiority": ["event_count", "density"], "noninferiority_margin": 0.05,
                    "sanity": True, "full_resolution": False},
    })
    result = run_evaluation(config, log=None)
    by = {(c.method, c.factor, c.budget): c for c in result.cells}
    for factor, budget in (((2, 2), 0.25), ((4, 4), 0.05)):
        assert by[("density", factor, budget)].role == "control"
        assert by[("control", factor, budget)].role == "control"
    family = result.primary()
    assert len(family) == 2
    p_values = []
    for c in family:
        for k, reference in ((c.comparison, by[("control", c.factor, c.budget)]),
                             (c.peer_comparison, by[("density", c.factor, c.budget)])):
            # by hand: per (repeat, fold), the mean over seeds; differences paired by split
            d = [_split_mean(c, u) - _split_mean(reference, u)
                 for u in config.data.fold_units]
            mean = sum(d) / 6
            variance = sum((x - mean) ** 2 for x in d) / 5
            assert k.difference == pytest.approx(mean, abs=1e-12)
            assert k.standard_error == pytest.approx(
                math.sqrt((1 / 6 + 1 / 2) * variance), abs=1e-12)
            assert k.paired
            p_values.append(k.p_value)
    adjusted = sorted(k.p_holm for c in family for k in (c.comparison, c.peer_comparison))
    # Holm over the whole family of 4: the smallest p-value is multiplied by 4
    assert adjusted[0] == pytest.approx(min(1.0, 4 * min(p_values)))
    assert set(result.noninferiority) == {(2, 2), (4, 4)}
    assert set(result.sanity) == {(2, 2), (4, 4)}
    paths = write_report(result, tmp_path / "out")
    text = paths["markdown"].read_text()
    assert "Non-inferiority" in text and "corrected resampled t" in text
    with paths["csv"].open() as handle:
        rows = [r for r in csv.DictReader(handle) if r["role"] == "primary"]
    assert all(r["difference_vs_peer"] and r["p_holm_vs_peer"] for r in rows)


def _split_mean(cell, unit):
    values = [a for r, f, _, a, _ in cell.units if (r, f) == unit]
    return sum(values) / len(values)


CONFIGS = Path(__file__).resolve().parents[2] / "configs"


@pytest.mark.parametrize("name", ["nmnist.toml", "nmnist_full.toml", "nmnist_tiny.toml"])
def test_the_nmnist_configs_state_the_question_and_load(name):
    config = load_config(CONFIGS / name)
    m = config.methods
    assert config.data.folds == 5 or name == "nmnist_tiny.toml"
    assert m.budget_at(2) == 0.25 and m.budget_at(4) == 0.05
    assert m.primary_peer == "density" and m.tonic_peer
    if name != "nmnist_tiny.toml":
        assert m.primary == ("event_count", "linear", "cubic")
        assert m.noninferiority == ("event_count", "cubic") and len(m.budgets) >= 4
        assert {"poisson", "refractory", "decimation", "downsample"} <= set(m.names)
        text = (CONFIGS / name).read_text()
        assert "Primary question" in text or "primary question" in text


def test_the_tiny_nmnist_config_end_to_end(tmp_path, monkeypatch):
    pytest.importorskip("tonic")
    if not REAL.is_dir():
        pytest.skip(f"{REAL} is absent")
    monkeypatch.chdir(CONFIGS.parent)  # its root is relative to the repository's root
    config = load_config(CONFIGS / "nmnist_tiny.toml")
    config = dataclasses.replace(config, output=dataclasses.replace(
        config.output, directory=str(tmp_path / "out"), cache=str(tmp_path / "cache")))
    result = run_evaluation(config, log=None)
    assert len(result.primary()) == 2 and set(result.noninferiority) == {(2, 2), (4, 4)}
    assert all(c.peer_comparison is not None for c in result.primary())
    assert all(len(c.labels) == 24 for c in result.cells)
    paths = write_report(result, tmp_path / "out")
    report = paths["markdown"].read_text()
    assert "corrected resampled t" in report
    # Tonic's peer, at its own rate, against the control thinned to its output count
    assert "| tonic integrator | exploratory | 4 |" in report
    assert "| matched control " in report.split("| tonic integrator |")[1].splitlines()[0]
    # without a camera, the figure's second row is accuracy against CPU time per recording
    matplotlib = pytest.importorskip("matplotlib")
    from evdown_torch.evaluation.figure import plot_tradeoff

    drawn = []
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig",
                        lambda figure, *args, **kwargs: drawn.append(figure))
    assert plot_tradeoff(result, tmp_path / "figure.png")
    axes = drawn[0].axes
    assert axes[0].get_xlabel() == "output events per second"
    assert axes[-1].get_xlabel().startswith("CPU microseconds per recording")
    timed = [c for c in result.cells if c.cpu_us_per_recording]
    assert timed and sum(len(line.get_xdata()) for line in axes[-1].lines) >= len(timed)
    labels = [t.get_text() for t in drawn[0].legends[0].get_texts()]
    assert any(label.startswith("event_count (delay 0)") for label in labels)
