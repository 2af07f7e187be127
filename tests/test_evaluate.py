"""The evaluation end to end on a tiny seeded stand-in, its measures, and the CLI."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch

from evdown_torch import EventFunnelling
from evdown_torch.cli import main
from evdown_torch.config import load_config, parse_config
from evdown_torch.evaluate import (
    BASELINE,
    EvaluationData,
    _cosine,
    load_data,
    markdown_table,
    run_evaluation,
    write_report,
)
from evdown_torch.transforms.registry import METHODS
from tests.stand_in import SENSOR, stand_in_data

CONFIGS = Path(__file__).resolve().parents[1] / "configs"

DOCUMENT = {
    "data": {"sensor_size": [16, 16], "time_bins": 5},
    "methods": {"factors": [2, 4]},
    "model": {"channels": [4], "pool_size": 2},
    "training": {"epochs": 2, "batch_size": 4, "seeds": [0, 1], "learning_rate": 0.01,
                 "num_threads": 1},
}


@pytest.fixture(scope="module")
def stand_in():
    return stand_in_data()


@pytest.fixture(scope="module")
def result(stand_in):
    return run_evaluation(parse_config(DOCUMENT, name="stand-in"), data=stand_in, log=None)


def _measures(result):
    """Everything but the measured times."""
    return [dataclasses.replace(c, throughput=None, downscale_seconds=0, train_seconds=0)
            for c in result.cells]


def test_every_cell_is_reported(result, tmp_path):
    names = [c.method for c in result.cells]
    assert names == [BASELINE] + [m for m in METHODS for _ in (2, 4)]
    assert [c.factor for c in result.cells[1:3]] == [(2, 2), (4, 4)]
    for c in result.cells:
        assert len(c.accuracies) == 2 and all(0 <= a <= 1 for a in c.accuracies)
        assert (c.throughput is None) == (c.method == BASELINE)
        assert c.consistency is not None and 0 <= c.consistency <= 1 + 1e-12
    baseline = result.cells[0]
    assert baseline.reduction == 1 and baseline.consistency == 1 and baseline.output_size == (16,
                                                                                              16)
    paths = write_report(result, tmp_path / "out", log=None)
    assert {p.name for p in paths.values()} >= {"results.csv", "report.md"}
    with paths["csv"].open() as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == len(result.cells)
    assert all(0 <= float(r["accuracy_mean"]) <= 1 for r in rows)
    table = paths["markdown"].read_text()
    for c in result.cells:
        label = f"| {c.method} | {c.factor[0]} | {c.output_size[0]}x{c.output_size[1]} |"
        assert label in table
    assert markdown_table(result) in table


def test_stream_measures_match_direct_computation(result, stand_in):
    items = list(stand_in.train) + list(stand_in.test)
    total = sum(len(ev) for ev, _ in items)
    downsample, funnelling = result.cells[1], result.cells[3]
    assert downsample.method == "downsample" and downsample.reduction == 1
    assert downsample.events_per_sample == total / len(items)
    out = sum(len(EventFunnelling(SENSOR, 2)(ev)) for ev, _ in items)
    assert funnelling.method == "funnelling" and funnelling.factor == (2, 2)
    assert funnelling.events_per_sample == out / len(items)
    assert funnelling.reduction == pytest.approx(total / out)
    # the baseline's density: events per pixel per microsecond, over each recording's span
    densities = [len(ev) / (16 * 16 * float(ev["t"].max() - ev["t"].min())) for ev, _ in items]
    assert result.cells[0].density == pytest.approx(np.mean(densities))


def test_same_seed_same_results(result, stand_in):
    again = run_evaluation(parse_config(DOCUMENT, name="stand-in"), data=stand_in, log=None)
    assert _measures(again) == _measures(result)


def test_cosine_consistency():
    a = torch.tensor([[1.0, 0.0], [2.0, 0.0]])
    assert _cosine(a, 3 * a) == pytest.approx(1.0)
    assert _cosine(a, torch.tensor([[0.0, 1.0], [0.0, 1.0]])) == 0.0
    assert _cosine(a, torch.tensor([[1.0, 0.0], [0.0, 0.0]])) == pytest.approx(1 / 5**0.5)
    assert _cosine(torch.zeros(3), torch.zeros(3)) == 1.0
    assert _cosine(a, torch.zeros(2, 2)) == 0.0


def test_without_ground_truth_consistency_is_na(stand_in, tmp_path):
    data = dataclasses.replace(stand_in, ground_truth=None, train=stand_in.train[:6],
                               test=stand_in.test[:3])
    document = {**DOCUMENT, "methods": {"factors": [2], "include": ["downsample"]},
                "training": {**DOCUMENT["training"], "epochs": 1, "seeds": [0]}}
    result = run_evaluation(parse_config(document), data=data, log=None)
    assert [c.consistency for c in result.cells] == [None, None]
    table = markdown_table(result)
    assert table.count("| n/a |") == 2


def test_progress_lines(stand_in):
    lines = []
    data = dataclasses.replace(stand_in, train=stand_in.train[:3], test=stand_in.test[:3])
    document = {**DOCUMENT, "methods": {"factors": [2], "include": ["event_count"]},
                "training": {**DOCUMENT["training"], "epochs": 1, "seeds": [0]}}
    run_evaluation(parse_config(document), data=data, log=lines.append)
    assert lines[0].startswith("[") and " s] data: stand-in sweeps" in lines[0]
    assert any("event_count x2, seed 0: accuracy" in line for line in lines)
    assert "done: 2 cells in" in lines[-1]


def test_empty_split_is_an_error(stand_in):
    data = EvaluationData("empty", SENSOR, 3, stand_in.train, [])
    with pytest.raises(ValueError, match="the test split has no recordings"):
        run_evaluation(parse_config(DOCUMENT), data=data, log=None)


def test_dvsgesture_absent_says_where_to_put_it(tmp_path):
    pytest.importorskip("tonic")
    config = parse_config({"data": {"dataset": "dvsgesture", "root": str(tmp_path)}})
    with pytest.raises(FileNotFoundError, match=r"DVS128 Gesture was not found in .*DVSGesture"
                                                r".*ibmGestureTrain.tar.gz"):
        load_data(config.data)


def test_cli_evaluate_reports_a_missing_config(tmp_path, capsys):
    assert main(["evaluate", "--config", str(tmp_path / "absent.toml")]) == 2
    assert "evdown evaluate: error: config file" in capsys.readouterr().err


def test_cli_evaluate_reports_a_bad_config(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text("[training]\nepochs = 'many'\n")
    assert main(["evaluate", "--config", str(path)]) == 2
    assert "training.epochs must be an integer, got a string" in capsys.readouterr().err
    pytest.importorskip("tonic")
    path.write_text(f"[data]\ndataset = 'dvsgesture'\nroot = '{tmp_path}'\n")
    assert load_config(path).data.root == str(tmp_path)
    assert main(["evaluate", "--config", str(path)]) == 2
    assert "DVS128 Gesture was not found" in capsys.readouterr().err


def test_cli_evaluate_tiny_config_end_to_end(tmp_path, capsys):
    """configs/tiny.toml on real synthetic gestures: every cell, every file."""
    config = CONFIGS / "tiny.toml"
    assert main(["evaluate", "--config", str(config), "--output", str(tmp_path)]) == 0
    captured = capsys.readouterr()
    assert "ground truth x2" in captured.err and "done:" in captured.err
    with (tmp_path / "results.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    assert [r["method"] for r in rows] == [BASELINE, *METHODS]
    for row in rows:
        assert 0 <= float(row["accuracy_mean"]) <= 1
        assert 0 <= float(row["consistency"]) <= 1 + 1e-9
        assert float(row["events_per_sample"]) >= 0
    assert all(row["width"] == "16" for row in rows[1:])
    report = (tmp_path / "report.md").read_text()
    assert report.count("\n| ") == len(rows) + 1  # header and one row per cell
    assert captured.out in report
    pytest.importorskip("matplotlib")
    assert (tmp_path / "tradeoff.png").stat().st_size > 0


def _fake_dvsgesture(root, rng):
    """Tonic's DVSGesture layout: archives, and user folders of ``<label>.npy`` (x, y, p, t_ms)."""
    location = root / "DVSGesture"
    for folder in ("ibmGestureTrain", "ibmGestureTest"):
        (location / f"{folder}.tar.gz").parent.mkdir(parents=True, exist_ok=True)
        (location / f"{folder}.tar.gz").write_bytes(b"")
        for user in range(1, 11):
            directory = location / folder / f"user{user:02d}_led"
            directory.mkdir(parents=True)
            for label in range(11):
                n = 60
                t_ms = np.sort(rng.integers(0, 400, n))
                rows = np.stack([rng.integers(0, 128, n), rng.integers(0, 128, n),
                                 rng.integers(0, 2, n), t_ms], axis=1)
                np.save(directory / f"{label}.npy", rows)


def test_dvsgesture_subset_and_crop(tmp_path, rng):
    pytest.importorskip("tonic")
    _fake_dvsgesture(tmp_path, rng)
    config = parse_config({
        "data": {"dataset": "dvsgesture", "root": str(tmp_path), "train_samples": 22,
                 "test_samples": 11, "duration_us": 200_000, "time_bins": 2},
        "methods": {"factors": [8], "include": ["downsample"]},
        "model": {"channels": [2], "pool_size": 1},
        "training": {"epochs": 1, "num_threads": 1},
    })
    data = load_data(config.data)
    assert data.sensor_size == (128, 128, 2) and data.num_classes == 11
    assert (len(data.train), len(data.test)) == (22, 11) and data.ground_truth is None
    events, label = data.train[0]
    assert 0 <= label < 11 and events["t"].max() - events["t"].min() < 200_000
    assert data.train[0][0].tolist() == events.tolist()  # the same recording every time
    result = run_evaluation(config, data=data, log=None)
    assert [c.output_size for c in result.cells] == [(128, 128), (16, 16)]
    assert all(c.consistency is None and 0 <= c.accuracy_mean <= 1 for c in result.cells)
