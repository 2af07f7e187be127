"""``evdown evaluate`` checks every path it will write before any work."""

from __future__ import annotations

from pathlib import Path

import pytest

from evdown_torch.cli import main

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


@pytest.fixture
def runs(monkeypatch) -> list[object]:
    """The studies started (none should be: the run is stubbed to record, not to train)."""
    started: list[object] = []

    def run_evaluation(config, **kwargs):
        started.append(config)
        raise AssertionError("the study started")

    monkeypatch.setattr("evdown_torch.evaluation.study.run_evaluation", run_evaluation)
    return started


def _config(tmp_path, directory: str | None = None, cache: str | None = None) -> Path:
    text = (CONFIGS / "tiny.toml").read_text()
    text = text.replace('directory = "results/tiny"',
                        f'directory = "{directory or tmp_path / "results"}"')
    text = text.replace('cache = "results/tiny/cache"', f'cache = "{cache or tmp_path / "c"}"')
    path = tmp_path / "study.toml"
    path.write_text(text)
    return path


def _one_error_line(capsys, *needles: str) -> None:
    err = capsys.readouterr().err
    assert err.startswith("evdown evaluate: error: ") and err.count("\n") == 1, err
    for needle in needles:
        assert needle in err, err


def test_an_output_folder_under_a_file_is_refused_before_the_study(tmp_path, runs, capsys):
    afile = tmp_path / "afile"
    afile.write_text("mine")
    config = _config(tmp_path)
    assert main(["evaluate", "--config", str(config), "--output", str(afile / "out")]) == 2
    _one_error_line(capsys, "cannot create the output folder", f"{str(afile)!r} is a file")
    assert runs == [] and afile.read_text() == "mine"


def test_a_config_output_directory_under_a_file_is_refused_too(tmp_path, runs, capsys):
    afile = tmp_path / "afile"
    afile.write_text("mine")
    assert main(["evaluate", "--config", str(_config(tmp_path, directory=str(afile / "r")))]
                ) == 2
    _one_error_line(capsys, "cannot create the output folder", "is a file")
    assert runs == []


def test_a_cache_folder_under_a_file_is_refused_before_the_study(tmp_path, runs, capsys):
    afile = tmp_path / "afile"
    afile.write_text("mine")
    config = _config(tmp_path, cache=str(afile / "cache"))
    assert main(["evaluate", "--config", str(config)]) == 2
    _one_error_line(capsys, "cannot create the cache folder", "is a file")
    assert runs == []
    # Without the cache the cache folder is never made, so it is not in the way.
    with pytest.raises(AssertionError, match="the study started"):
        main(["evaluate", "--config", str(config), "--no-cache"])
    assert len(runs) == 1 and not (tmp_path / "results").exists()  # made with the report
