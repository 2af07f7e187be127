"""``evdown evaluate`` on real N-MNIST recordings in their own layout (a few of them)."""

from __future__ import annotations

import pytest

from evdown_torch.evaluation import BASELINE, CONTROL, run_evaluation
from evdown_torch.evaluation.config import parse_config
from evdown_torch.evaluation.data import StudyData, check_available
from evdown_torch.evaluation.report import per_class_table
from tests.conftest import SHARED_DATA

REAL = SHARED_DATA / "nmnist_small"


def _config(root, cache, methods=None, **data):
    return parse_config({
        "data": {"dataset": "nmnist", "root": str(root), "train_samples": 20,
                 "test_samples": 10, "calibration_samples": 6, "time_bins": 2,
                 "duration_us": 0, **data},
        "methods": {"factors": [4], "include": ["downsample", "density", "poisson"],
                    "budget_reference": "input", "budgets": [0.25], "primary": ["density"],
                    "primary_factors": [4], "primary_budget": 0.25, "sanity": False,
                    } if methods is None else methods,
        "model": {"channels": [2], "pool_size": 1, "grid": 8},
        "training": {"epochs": 1, "seeds": [0], "workers": 0, "device": "cpu",
                     "primary_seeds": 1, "control_seeds": 1},
        "statistics": {"resamples": 50},
        "output": {"cache": str(cache)},
    })


def test_evaluate_reads_the_real_folder_and_spends_the_budget(tmp_path):
    pytest.importorskip("tonic")
    if not REAL.is_dir():
        pytest.skip(f"{REAL} is absent")
    config = _config(REAL, tmp_path / "cache")
    assert config.data.full_sensor_size == (34, 34, 2) and config.data.num_classes == 10
    source = StudyData(config.data, str(tmp_path / "cache"))
    assert source.size("train") == 20 and source.size("test") == 10
    assert "N-MNIST" in source.description()
    events, label = source.recording("test", 3)
    assert 0 <= label < 10 and len(events) > 500
    result = run_evaluation(config, log=None)
    methods = [c.method for c in result.cells]
    assert methods[0] == BASELINE and sorted(methods[1:]) == sorted(
        ["density", CONTROL, "downsample", "poisson"])
    for cell in result.cells:
        if cell.method in ("density", "poisson", CONTROL):
            found = cell.calibration
            assert found["count"] == pytest.approx(found["target"], rel=0.05), cell.method
        if cell.method != BASELINE:
            assert cell.output_size == (9, 9)
    header = per_class_table(result).splitlines()[0]
    assert header.endswith("| 8 | 9 |")  # ten digits


def test_a_broken_folder_is_refused_before_any_work(tmp_path):
    (tmp_path / "Train" / "0").mkdir(parents=True)
    config = _config(tmp_path, tmp_path / "cache")
    with pytest.raises(ValueError, match=r"lacks the class folder\(s\) 1, 2, 3"):
        check_available(config.data)
    with pytest.raises(ValueError, match="lacks the class folder"):
        run_evaluation(config, log=None)
    assert not (tmp_path / "cache").exists()


def test_tonics_peer_is_compared_with_a_control_thinned_to_its_own_output_count(tmp_path):
    tonic = pytest.importorskip("tonic")
    if not REAL.is_dir():
        pytest.skip(f"{REAL} is absent")
    import numpy as np

    from evdown_torch.evaluation.cells import TONIC

    config = _config(REAL, tmp_path / "cache", methods={
        "factors": [4], "include": ["downsample"], "budgets": [], "primary": [],
        "tonic_peer": True, "control": False, "sanity": False, "full_resolution": False})
    result = run_evaluation(config, log=None)
    by_name = {c.cell.name: c for c in result.cells}
    peer, matched = by_name[TONIC], by_name[f"{CONTROL} (matched to {TONIC})"]
    assert matched.cell.matches == TONIC and matched.budget is None
    # the target is what Tonic itself outputs on the calibration recordings
    source = StudyData(config.data, str(tmp_path / "cache"))
    integrator = tonic.transforms.EventDownsampling(
        sensor_size=(34, 34, 2), target_size=(9, 9), dt=1.0,
        downsampling_method="integrator", noise_threshold=1)
    expected = sum(len(integrator(source.recording("train", i)[0]))
                   for i in range(config.data.calibration_samples))
    assert matched.calibration["target"] == expected > 0
    assert matched.calibration["count"] == pytest.approx(expected, rel=0.05)
    # the peer's comparison is against that control, on the same recordings
    difference = peer.accuracy - matched.accuracy
    assert peer.comparison is not None
    assert peer.comparison.difference == pytest.approx(difference, abs=1e-9)
    assert np.isclose(matched.events_per_recording, peer.events_per_recording, rtol=0.25)
