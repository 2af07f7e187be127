"""The study end to end on configs/tiny.toml: cells, cache, workers, measures and the CLI."""

from __future__ import annotations

import csv
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from evdown_torch.cli import main
from evdown_torch.evaluation import (
    BASELINE,
    CONTROL,
    classifier,
    markdown_table,
    run_evaluation,
    write_report,
)
from evdown_torch.evaluation.config import load_config, parse_config
from evdown_torch.evaluation.data import StudyData, check_available
from evdown_torch.evaluation.metrics import optical_consistency
from evdown_torch.evaluation.report import primary_table, question
from evdown_torch.transforms import Downsample
from evdown_torch.transforms.registry import METHODS

CONFIGS = Path(__file__).resolve().parents[1] / "configs"
TIMES = ("throughput_events_per_s", "train_seconds", "cpu_us_per_recording")


def _tiny(tmp_path, **training):
    config = load_config(CONFIGS / "tiny.toml")
    return dataclasses.replace(
        config,
        output=dataclasses.replace(config.output, cache=str(tmp_path / "cache")),
        training=dataclasses.replace(config.training, **training),
    )


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    root = tmp_path_factory.mktemp("tiny")
    config = _tiny(root)
    return config, run_evaluation(config, log=None), root


def _rows(result, directory):
    paths = write_report(result, directory)
    with paths["csv"].open() as handle:
        rows = [{k: v for k, v in r.items() if k not in TIMES} for r in csv.DictReader(handle)]
    return rows, paths


def test_every_cell_is_planned(tiny):
    config, result, _ = tiny
    budgeted = [n for n, cls in METHODS.items() if cls.budget_setting is not None]
    plain = [n for n in METHODS if n not in budgeted]
    exploratory = [n for n in METHODS if n not in ("event_count", "downsample")]
    assert [(c.method, c.role) for c in result.cells] == [
        (BASELINE, "exploratory"), ("event_count", "primary"), (CONTROL, "control"),
        ("downsample", "sanity"), *[(n, "exploratory") for n in exploratory],
        ("linear", "exploratory"), ("cubic", "exploratory")]
    assert [dict(c.cell.settings).get("max_delay") for c in result.cells[-2:]] == [20_000] * 2
    for c in result.cells:
        assert (c.budget is None) == (c.method in (BASELINE, *plain))
        assert len(c.seeds) == (1 if c.method == BASELINE else 2)
        assert c.interval[0] <= c.accuracy <= c.interval[1]
        assert len(c.labels) == 6 and all(len(p) == 6 for p in c.predicted)
        if c.method in budgeted or c.role == "sanity":
            assert c.comparison is not None
        else:
            assert c.comparison is None
        if c.role == "primary":
            assert c.comparison.p_holm >= c.comparison.p_value
            assert c.comparison.paired  # the control trained on the same two seeds
        elif c.comparison is not None and c.role == "exploratory":
            assert c.comparison.p_value is None
        if c.method != BASELINE:
            assert c.output_size == (16, 16) and 0 <= c.consistency <= 1
            assert c.throughput is not None and c.throughput > 0
            assert c.cpu_us_per_recording > 0
    # the sanity check is the control against Downsample, on the same recordings
    sanity = result.sanity[(2, 2)]
    cells = {(c.method, c.role): c for c in result.cells}
    assert sanity.difference == pytest.approx(
        cells[(CONTROL, "control")].accuracy - cells[("downsample", "sanity")].accuracy)
    assert set(result.learning_rates[(2, 2)][1]) == {0.005, 0.01}
    assert result.generated == 22 + 6 + 3 + 6  # recordings, then camera renders at x2


def test_learning_rate_is_chosen_without_the_test_split(tiny, monkeypatch):
    # check (d): the selection trains and scores on the training pool only
    config, result, root = tiny
    source = StudyData(config.data, str(root / "cache"))
    read = []
    original = classifier.frames_of

    def spy(source, cell, split, *args, **kwargs):
        read.append(split)
        return original(source, cell, split, *args, **kwargs)

    monkeypatch.setattr(classifier, "frames_of", spy)
    control = next(c.cell for c in result.cells if c.role == "control")
    chunks = {"train": [list(range(22))], "test": [list(range(6))]}
    out = classifier.train_job(source, control, chunks, config, 1, "cpu", 0.003, True)
    assert read == ["train"] and len(out["correct"]) == config.data.validation_samples
    assert out["labels"] == [i % 11 for i in range(config.data.validation_samples)]


def test_measures_match_direct_computation(tiny):
    config, result, root = tiny
    source = StudyData(config.data, str(root / "cache"))
    test = [source.recording("test", i)[0] for i in range(6)]
    cells = {c.method: c for c in result.cells}
    sizes = [len(r) for r in test]
    assert cells[BASELINE].events_per_recording == pytest.approx(np.mean(sizes))
    assert cells["downsample"].events_per_recording == pytest.approx(np.mean(sizes))
    camera = [source.ground_truth("test", i, (2, 2)) for i in range(6)]
    assert cells["downsample"].rate_vs_camera == pytest.approx(
        sum(sizes) / sum(len(c) for c in camera))
    down = Downsample((32, 32, 2), 2)
    expected = np.mean([
        optical_consistency(down(r), c, (16, 16, 2), bin_width=10_000,
                            t_start=int(r["t"].min()), t_end=int(r["t"].max()))
        for r, c in zip(test, camera)])
    assert cells["downsample"].consistency == pytest.approx(expected)
    # LIFPooling's recordings go through its batched kernel: each as if alone
    lifs = [c for c in result.cells if c.method == "lif"]
    assert lifs
    for lif in lifs:
        pool = lif.cell.transform((32, 32, 2))
        assert lif.events_per_recording == pytest.approx(np.mean([len(pool(r)) for r in test]))
    # the control spends the budget that it was calibrated to on the training recordings
    control = cells[CONTROL]
    assert control.calibration["count"] == pytest.approx(control.calibration["target"], rel=0.05)
    assert 0 < dict(control.cell.settings)["keep"] < 1


def test_second_run_generates_nothing_and_gives_the_same_table(tiny, tmp_path):
    config, first, _ = tiny
    again = run_evaluation(config, log=None)
    assert again.generated == 0
    assert markdown_table(again) == markdown_table(first)
    assert _rows(again, tmp_path / "a")[0] == _rows(first, tmp_path / "b")[0]


@pytest.mark.slow
def test_worker_processes_without_cache_give_the_same_table(tiny, tmp_path):
    _, first, _ = tiny
    config = _tiny(tmp_path, workers=2)
    lines = []
    result = run_evaluation(config, log=lines.append, cache=False)
    assert result.generated == first.generated and result.workers == 2
    assert markdown_table(result) == markdown_table(first)
    assert not (tmp_path / "cache").exists()
    assert any("calibrated" in line for line in lines) and "done:" in lines[-1]


def test_report_files(tiny, tmp_path):
    _, result, _ = tiny
    rows, paths = _rows(result, tmp_path)
    assert len(rows) == len(result.cells)
    report = paths["markdown"].read_text()
    assert markdown_table(result) in report
    assert primary_table(result) in report and question(result.config) in report
    for check in ("(a) x2", "(b) ", "(c) ", "(d) learning rate chosen"):
        assert f"- {check}" in report
    assert [r["role"] for r in rows] == [c.role for c in result.cells]
    assert rows[1]["paired"] in ("true", "false")
    pytest.importorskip("matplotlib")
    assert paths["plot"].stat().st_size > 0


def test_the_tiny_report_says_it_is_a_smoke_test_and_explains_its_blanks(tiny, tmp_path):
    _, result, _ = tiny
    report = write_report(result, tmp_path)["markdown"].read_text()
    lines = report.splitlines()
    assert lines[2].startswith("**A smoke test, not a result.** 6 test recordings for 11 "
                               "classes (5 without one; fewer than 10 per class) and 1 epoch")
    assert "1 epoch, batch" in report and "1 epochs" not in report
    assert "nan" not in report
    assert "–: no test recording of class 6, 7, 8, 9, 10 (the test split has 6 recordings)." \
        in report
    every, cost = (_first_table(report.split(heading)[1])
                   for heading in ("**Every cell**", "**Cost**"))
    macs = [row[-3] for row in every[2:]]
    assert len(macs) == len(result.cells) and all(float(m) > 0 for m in macs)  # not 0.0
    assert macs[1] == f"{result.cells[1].macs_per_recording / 1e6:.4f}"  # 0.0270
    seconds = [row[-2] for row in cost[2:]]
    assert len(seconds) == len(result.cells)
    assert all(float(v) > 0 for v in seconds)  # training took under 0.05 s


def _first_table(text: str) -> list[list[str]]:
    """The cells of the first Markdown table in ``text``, row by row (heading included)."""
    rows = []
    for line in text.splitlines():
        if line.startswith("|"):
            rows.append([cell.strip() for cell in line.split("|")])
        elif rows:
            break
    return rows


def test_dvsgesture_absent_says_where_to_put_it(tmp_path):
    pytest.importorskip("tonic")
    config = parse_config({"data": {"dataset": "dvsgesture", "root": str(tmp_path)},
                           "methods": {"budget_reference": "input"}})
    with pytest.raises(FileNotFoundError, match=r"DVS128 Gesture was not found in .*DVSGesture"
                                                r".*ibmGestureTrain.tar.gz"):
        check_available(config.data)


def test_camera_budgets_need_ground_truth():
    with pytest.raises(ValueError, match="budget_reference = 'camera' needs the synthetic"):
        parse_config({"data": {"dataset": "dvsgesture"}})


def test_cli_evaluate_reports_a_missing_config(tmp_path, capsys):
    assert main(["evaluate", "--config", str(tmp_path / "absent.toml")]) == 2
    assert "evdown evaluate: error: config file" in capsys.readouterr().err


def test_cli_evaluate_reports_a_bad_config(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text("[training]\nepochs = 'many'\n")
    assert main(["evaluate", "--config", str(path)]) == 2
    assert "training.epochs must be an integer, got a string" in capsys.readouterr().err
    pytest.importorskip("tonic")
    path.write_text(f"[data]\ndataset = 'dvsgesture'\nroot = '{tmp_path}'\n"
                    "[methods]\nbudget_reference = 'input'\n")
    assert main(["evaluate", "--config", str(path)]) == 2
    assert "DVS128 Gesture was not found" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_evaluate_tiny_config(tmp_path, capsys):
    path = tmp_path / "tiny.toml"
    text = (CONFIGS / "tiny.toml").read_text()
    path.write_text(text.replace('cache = "results/tiny/cache"', f'cache = "{tmp_path}/c"'))
    assert main(["evaluate", "--config", str(path), "--output", str(tmp_path / "out")]) == 0
    captured = capsys.readouterr()
    report = (tmp_path / "out/report.md").read_text()
    assert "done:" in captured.err and "| p (Holm) |" in captured.out
    assert all(part in report for part in captured.out.split("\n\n"))
    assert (tmp_path / "c").is_dir()
    assert main(["evaluate", "--config", str(path), "--output", str(tmp_path / "o2"),
                 "--no-cache"]) == 0
    assert capsys.readouterr().out == captured.out


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
                n = 200
                t_ms = np.sort(rng.integers(0, 400, n))
                rows = np.stack([rng.integers(0, 128, n), rng.integers(0, 128, n),
                                 rng.integers(0, 2, n), t_ms], axis=1)
                np.save(directory / f"{label}.npy", rows)


def test_dvsgesture_subset_crop_and_input_budgets(tmp_path, rng):
    pytest.importorskip("tonic")
    _fake_dvsgesture(tmp_path, rng)
    config = parse_config({
        "data": {"dataset": "dvsgesture", "root": str(tmp_path), "train_samples": 11,
                 "test_samples": 5, "duration_us": 200_000, "time_bins": 2,
                 "calibration_samples": 4},
        "methods": {"factors": [8], "include": ["downsample", "event_count"],
                    "budget_reference": "input", "budgets": [0.2]},
        "model": {"channels": [2], "pool_size": 1, "grid": 8},
        "training": {"epochs": 1, "seeds": [0], "workers": 0, "device": "cpu"},
        "statistics": {"resamples": 50},
        "output": {"cache": str(tmp_path / "cache")},
    })
    source = StudyData(config.data, str(tmp_path / "cache"))
    events, label = source.recording("train", 0)
    assert 0 <= label < 11 and events["t"].max() - events["t"].min() < 200_000
    result = run_evaluation(config, log=None)
    assert [c.method for c in result.cells] == [BASELINE, "downsample", "event_count", CONTROL]
    assert [c.output_size for c in result.cells] == [(128, 128)] + [(16, 16)] * 3
    for c in result.cells:
        assert c.consistency is None and c.rate_vs_camera is None
    control = result.cells[-1].calibration
    assert control["count"] == pytest.approx(control["target"], rel=0.05)
    # uniform noise this sparse leaves EventCount a coarse staircase: the closest step is taken
    assert result.cells[2].calibration["count"] > 0


def test_consistency_on_the_first_test_recordings(tiny, tmp_path):
    config, first, root = tiny
    config = dataclasses.replace(
        config, measures=dataclasses.replace(config.measures, consistency_recordings=3),
        output=dataclasses.replace(config.output, cache=str(root / "cache")))
    result = run_evaluation(config, log=None)
    source = StudyData(config.data, str(root / "cache"))
    test = [source.recording("test", i)[0] for i in range(3)]
    camera = [source.ground_truth("test", i, (2, 2)) for i in range(3)]
    down = next(c for c in result.cells if c.method == "downsample")
    assert down.rate_vs_camera == pytest.approx(sum(len(r) for r in test)
                                                / sum(len(c) for c in camera))
    expected = np.mean([
        optical_consistency(Downsample((32, 32, 2), 2)(r), c, (16, 16, 2), bin_width=10_000,
                            t_start=int(r["t"].min()), t_end=int(r["t"].max()))
        for r, c in zip(test, camera)])
    assert down.consistency == pytest.approx(expected)
    # accuracy is still over every test recording
    assert all(len(row) == 6 for c in result.cells for row in c.correct)


def test_seeds_without_zero_measure_the_controls_first_draw(tmp_path):
    # exploratory cells only, on seeds 3 and 4: the control's measures come from its draw 3
    config = _tiny(tmp_path, seeds=(3, 4), learning_rates=())
    config = dataclasses.replace(config, methods=dataclasses.replace(
        config.methods, include=("event_count",), primary=(), primary_factors=(), sanity=False,
        live_delay=0, full_resolution=False))
    result = run_evaluation(config, log=None)
    assert [(c.method, c.seeds) for c in result.cells] == [("event_count", (3, 4)),
                                                           (CONTROL, (3, 4))]
    control = result.cells[1]
    source = StudyData(config.data, str(tmp_path / "cache"))
    thinned = control.cell.transform((32, 32, 2), draw=3)
    test = [source.recording("test", i)[0] for i in range(6)]
    assert control.events_per_recording == pytest.approx(np.mean([len(thinned(r)) for r in test]))
    assert 0 <= control.consistency <= 1 and result.cells[0].comparison is not None


def test_robustness_rows_train_a_stronger_classifier_on_the_same_frames(tmp_path):
    from evdown_torch.evaluation.config import RobustnessConfig

    config = _tiny(tmp_path, seeds=(0, 1))
    config = dataclasses.replace(
        config, methods=dataclasses.replace(config.methods, include=("event_count",),
                                            budgets=(), live_delay=0, full_resolution=False),
        robustness=RobustnessConfig(methods=("event_count",), factor=2, channels=(8, 8)))
    result = run_evaluation(config, log=None)
    rows = {c.cell.name: c for c in result.cells if c.budget is not None}
    wide = " (classifier channels 8-8)"
    method, control = rows["event_count" + wide], rows[CONTROL + wide]
    plain, plain_control = rows["event_count"], rows[CONTROL]  # the primary family's
    assert method.role == control.role == "exploratory" and method.seeds == (0, 1)
    assert (method.budget, method.factor) == (plain.budget, plain.factor) == (1.0, (2, 2))
    # the same frames and calibration as the study's own cells ...
    assert method.calibration == plain.calibration
    assert method.events_per_recording == plain.events_per_recording
    assert control.events_per_recording == plain_control.events_per_recording
    # ... through a wider classifier: [8, 8] blocks cost more than tiny.toml's [4, 4]
    assert method.macs_per_recording > 2 * plain.macs_per_recording
    # compared with the control trained the same way, not with the study's control
    assert method.comparison.difference == pytest.approx(method.accuracy - control.accuracy)
    assert plain.comparison.difference == pytest.approx(plain.accuracy - plain_control.accuracy)


def test_robustness_names_primary_methods_and_a_stronger_classifier():
    with pytest.raises(ValueError, match="robustness.methods must be primary methods"):
        parse_config({"methods": {"primary": ["event_count"], "primary_factors": [4]},
                      "robustness": {"methods": ["linear"], "channels": [8]}})
    with pytest.raises(ValueError, match="needs a stronger classifier"):
        parse_config({"robustness": {"methods": ["event_count"]}})
