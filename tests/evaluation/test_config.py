"""Evaluation configs: TOML to dataclasses, with every mistake named."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

import evdown_torch.evaluation.config as config_module
from evdown_torch.evaluation.config import EvaluationConfig, load_config, parse_config
from evdown_torch.transforms.registry import METHODS

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def test_defaults_and_conversion():
    config = parse_config({})
    assert config == EvaluationConfig()
    assert config.methods.names == tuple(METHODS)
    config = parse_config({
        "data": {"sensor_size": [32, 24], "time_bins": 4},
        "methods": {"factors": [2, [2, 3]], "include": ["downsample"]},
        "training": {"learning_rate": 1, "seeds": [3, 1]},
        "settings": {"event_count": {"threshold": 0.5}},
    }, name="x")
    assert config.data.sensor_size == (32, 24) and config.data.full_sensor_size == (32, 24, 2)
    assert config.methods.factors == (2, (2, 3)) and config.methods.names == ("downsample",)
    assert config.training.learning_rate == 1.0 and isinstance(config.training.learning_rate,
                                                                 float)
    assert config.method_settings("event_count") == {"threshold": 0.5}
    assert config.method_settings("downsample") == {} and config.name == "x"


def test_the_documented_example_is_valid(tmp_path):
    example = re.search(r"code-block:: toml\n\n(.*?)\n\"\"\"", config_module.__doc__ + '"""',
                        re.S).group(1)
    path = tmp_path / "example.toml"
    path.write_text("\n".join(line[4:] for line in example.splitlines()))
    config = load_config(path)
    assert config.methods.include == ("downsample", "event_count")
    assert config.settings == {"event_count": {"threshold": 1.0}}


@pytest.mark.parametrize("name", ["quick", "full", "tiny", "dvsgesture"])
def test_shipped_configs_load(name):
    config = load_config(CONFIGS / f"{name}.toml")
    assert config.name == name
    assert config.methods.names == (("event_count",) if name == "quick" else tuple(METHODS))
    if name == "quick":
        assert config.methods.peers == ("density", "poisson")


@pytest.mark.parametrize("name", ["quick", "full"])
def test_the_study_configs_meet_the_issue(name):
    config = load_config(CONFIGS / f"{name}.toml")
    m, t, d = config.methods, config.training, config.data
    assert d.full_sensor_size == (128, 128, 2) and d.test_samples >= 264
    # the primary family: at most about 10 one-sided comparisons, at the camera's rate
    assert m.primary == ("event_count", "linear", "cubic") and m.primary_factors == (4, 8)
    assert m.budget_reference == "camera" and m.primary_budget == 1.0
    assert len(m.primary) * len(m.primary_factors) <= 10 and m.sanity
    # seeds as the unit: 10 per primary cell, the same on the shared control (paired)
    assert t.primary_seeds >= 10 and t.control_seeds == t.primary_seeds
    assert config.statistics.resamples >= 50_000
    # each seed draws its own training set from a larger pool; the rate is chosen on
    # validation recordings of that pool
    assert 0 < d.train_per_seed < d.train_samples - d.validation_samples
    assert len(t.learning_rates) >= 2 and d.validation_samples >= 33
    # the classifier sees x4 and x8 whole (no stem) and inputs normalised per cell
    assert m.live_delay == 10_000 and config.model.grid >= 32 and t.normalise
    assert m.control and 0.25 in m.budgets and 4.0 in m.budgets
    if name == "full":
        assert (d.train_samples, d.test_samples) == (1077, 264) and d.duration_us == 6_000_000
        assert m.factors == (2, 4, 8) and len(t.seeds) >= 10 and m.names == tuple(METHODS)
        assert d.seed != load_config(CONFIGS / "quick.toml").data.seed  # a second data seed


def test_study_settings():
    config = parse_config({"training": {"seeds": [4, 5, 6], "full_resolution_seeds": 2},
                           "methods": {"budgets": [2.0, 0.5]}})
    assert config.training.baseline_seeds == (4, 5) and config.methods.budgets == (2.0, 0.5)
    assert parse_config({"training": {"full_resolution_seeds": 0}}).training.baseline_seeds \
        == config.training.seeds[:0] + (0, 1, 2, 3, 4)


@pytest.mark.parametrize(
    ("document", "error", "message"),
    [
        ({"data": {"sensor_sise": [8, 8]}}, ValueError, "unknown key data.sensor_sise"),
        ({"trainig": {}}, ValueError, r"unknown table \[trainig\]"),
        ({"training": {"epochs": 2.5}}, TypeError, r"training.epochs must be an integer, got a "
                                                   r"number \(2.5\)"),
        ({"training": {"epochs": True}}, TypeError, "training.epochs must be an integer, got a "
                                                    "boolean"),
        ({"training": {"learning_rate": "fast"}}, TypeError, "learning_rate must be a number"),
        ({"training": {"seeds": 0}}, TypeError, "training.seeds must be an array"),
        ({"training": {"seeds": [0, 0]}}, ValueError, "seeds must be distinct"),
        ({"training": {"encoding": "spikes"}}, ValueError, "training.encoding must be one of"),
        ({"training": {"epochs": 0}}, ValueError, "training.epochs must be a positive integer"),
        ({"model": {"channels": [8, "16"]}}, TypeError, r"model.channels\[1\] must be an integer"),
        ({"model": {"beta": 1.5}}, ValueError, r"model.beta must lie in \(0, 1\]"),
        ({"data": {"sensor_size": [8]}}, TypeError, "data.sensor_size must be an array of 2"),
        ({"data": {"dataset": "cifar10"}}, ValueError, "data.dataset must be one of"),
        ({"data": "synthetic"}, TypeError, r"\[data\] must be a table"),
        ({"methods": {"factors": [2.5]}}, TypeError, r"methods.factors\[0\] must be an integer "
                                                     "or an array of 2"),
        ({"methods": {"factors": []}}, ValueError, "at least one factor"),
        ({"methods": {"factors": [200]}}, ValueError, "methods.factors: factor 200 is larger"),
        ({"methods": {"include": ["nope"]}}, ValueError, r"unknown method\(s\) \['nope'\]"),
        ({"settings": {"nope": {}}}, ValueError, r"\[settings.nope\] names an unknown method"),
        ({"settings": {"event_count": {"thresh": 1}}}, ValueError,
         r"\[settings.event_count\]: method 'event_count' does not take setting\(s\) \['thresh'\]"),
        ({"settings": {"event_count": {"threshold": -1.0}}}, ValueError,
         r"\[settings.event_count\]: threshold must be a positive"),
        ({"settings": {"event_count": 1}}, TypeError, "one table per method"),
        ({"methods": {"budgets": [1.0, 1.0]}}, ValueError, "budgets must be distinct"),
        ({"methods": {"budgets": [0.0]}}, ValueError, "methods.budgets must be a positive"),
        ({"methods": {"budget_reference": "sensor"}}, ValueError, "budget_reference must be one"),
        ({"statistics": {"alpha": 1.5}}, ValueError, r"statistics.alpha must lie in \(0, 1\)"),
        ({"statistics": {"resamples": 0}}, ValueError, "statistics.resamples must be a positive"),
        ({"measures": {"consistency_bin_us": 0}}, ValueError, "consistency_bin_us must be a "),
        ({"model": {"grid": -1}}, ValueError, "model.grid must be a non-negative"),
        ({"training": {"workers": -2}}, ValueError, "training.workers must be a non-negative"),
        ({"training": {"num_threads": 10**20}}, ValueError,
         "training.num_threads must be at most 1024"),
        ({"output": {"cache": 3}}, TypeError, "output.cache must be a string"),
    ],
)
def test_mistakes_are_named(document, error, message):
    with pytest.raises(error, match=message):
        parse_config(document)


def test_file_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="config file .*absent.toml' does not exist"):
        load_config(tmp_path / "absent.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[data\nseed = 1\n")
    with pytest.raises(ValueError, match="bad.toml: invalid TOML"):
        load_config(bad)
    unknown = tmp_path / "unknown.toml"
    unknown.write_text("[training]\nepochs = 2\nepoch = 3\n")
    with pytest.raises(ValueError, match="unknown.toml: unknown key training.epoch;"):
        load_config(unknown)


def test_overrides_replace_one_setting_and_name_the_run(tmp_path):
    path = tmp_path / "study.toml"
    path.write_text('[data]\nseed = 0\ntrain_samples = 30\n[output]\ndirectory = "a"\n')
    config = load_config(path, ["data.seed=1", 'output.directory="b"', "training.epochs=2"])
    assert (config.data.seed, config.output.directory, config.training.epochs) == (1, "b", 2)
    assert config.data.train_samples == 30  # the rest of the file stays
    assert config.name == 'study (data.seed=1, output.directory="b", training.epochs=2)'
    assert load_config(path).name == "study"
    for bad, message in (("seed=1", "table.key=value"), ("data.seed", "table.key=value"),
                         ("data.seed=one", "not a TOML value"),
                         ("data.a.b=1", "table.key=value"),
                         ("data.nope=1", "nope")):
        with pytest.raises(ValueError, match=message) as error:
            load_config(path, [bad])
        assert str(path) in str(error.value)


def test_cli_set_reaches_the_config(tmp_path, capsys):
    from evdown_torch.cli import main

    path = tmp_path / "study.toml"
    path.write_text("[data]\nseed = 0\n")
    assert main(["evaluate", "--config", str(path), "--set", "data.seed=x"]) == 2
    assert "not a TOML value" in capsys.readouterr().err
