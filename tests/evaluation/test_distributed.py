"""``evdown evaluate`` under ``torchrun``: the one-process report from two ranks, with and
without a shared cache; a rank killed mid-run and the rerun; ranks that disagree; devices."""

from __future__ import annotations

import csv
import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from evdown_torch.cli import main
from evdown_torch.distributed import balance, folder_groups
from evdown_torch.evaluation import study
from evdown_torch.evaluation.config import load_config, parse_config
from evdown_torch.evaluation.ranks import Ranks, check_agreement, study_settings

REPO = Path(__file__).resolve().parents[2]
RANK_MAIN = Path(__file__).with_name("rank_main.py")
TIMES = ("throughput_events_per_s", "train_seconds", "cpu_us_per_recording")
#: Every training job of the tiny config: 2 learning rates x 2 factors, and 29 seeds of cells
#: (every registry method, the subsampler peers included, at 2 seeds; the control; the rest).
TRAININGS = 33


def _config(folder: Path, out: Path, epochs: int = 1) -> Path:
    """configs/tiny.toml as ``folder/tiny.toml``, its report and cache under ``out``."""
    text = (REPO / "configs" / "tiny.toml").read_text()
    text = text.replace('directory = "results/tiny"', f'directory = "{out / "report"}"')
    text = text.replace('cache = "results/tiny/cache"', f'cache = "{out / "cache"}"')
    assert text.count(str(out)) == 2 and "epochs = 1\n" in text
    text = text.replace("epochs = 1\n", f"epochs = {epochs}\n")
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "tiny.toml").write_text(text)
    return folder / "tiny.toml"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _torchrun(*args: str, ranks: int = 2) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "torch.distributed.run", "--nnodes", "1",
               "--nproc-per-node", str(ranks), "--master-addr", "127.0.0.1", "--master-port",
               str(_free_port()), str(RANK_MAIN), *args]
    env = dict(os.environ, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")
    return subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True,
                          timeout=600)


def _report(folder: Path) -> str:
    """report.md without what differs between runs: the run's paragraph (wall time, CPU
    seconds, ranks) and the cost table (measured times)."""
    text = (folder / "report.md").read_text()
    before, rest = text.split("**Run.**")
    return before + rest[rest.index("**Every cell**"):rest.index("**Cost**")]


def _rows(folder: Path) -> list[dict[str, str]]:
    with (folder / "results.csv").open() as handle:
        return [{k: v for k, v in row.items() if k not in TIMES} for row in csv.DictReader(handle)]


def _assert_same_report(folder: Path, reference: Path) -> None:
    assert _report(folder) == _report(reference)
    assert _rows(folder) == _rows(reference)
    if (reference / "tradeoff.png").exists():
        assert (folder / "tradeoff.png").read_bytes() == (reference / "tradeoff.png").read_bytes()


def _files(cache: Path, kind: str) -> set[str]:
    return {p.name for p in (cache / kind).glob("*") if not p.name.endswith(".part")}


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """The tiny study in one process: its output folder (report and cache)."""
    out = tmp_path_factory.mktemp("one")
    assert main(["evaluate", "--config", str(_config(out / "config", out))]) == 0
    return out


@pytest.mark.slow
def test_two_ranks_sharing_the_cache_give_the_one_process_report(reference, tmp_path):
    done = _torchrun("evaluate", "--config", str(_config(tmp_path / "config", tmp_path)))
    assert done.returncode == 0, done.stderr[-3000:]
    _assert_same_report(tmp_path / "report", reference / "report")
    report = (tmp_path / "report" / "report.md").read_text()
    assert "2 ranks (torchrun)" in report and "through the shared cache folder" in report
    assert "trained on cpu" in report and report.count("| cpu |") == 2  # no CUDA here
    assert done.stdout.count("| method |") == 2  # rank 0 alone prints the two tables
    # the same per-seed files as one process's (named by their settings), made once
    assert _files(tmp_path / "cache", "predictions") == _files(reference / "cache",
                                                               "predictions")
    assert len(_files(tmp_path / "cache", "predictions")) == TRAININGS
    assert not (tmp_path / "cache" / "runs" / "tiny.json").exists()  # finished


@pytest.mark.slow
def test_ranks_without_a_shared_cache_send_results_through_the_process_group(reference,
                                                                             tmp_path):
    done = _torchrun("--private-cache", "evaluate", "--config",
                     str(_config(tmp_path / "config", tmp_path)))
    assert done.returncode == 0, done.stderr[-3000:]
    _assert_same_report(tmp_path / "report", reference / "report")
    assert "through the process group" in (tmp_path / "report" / "report.md").read_text()
    caches = [tmp_path / "cache" / f"rank-{r}" for r in (0, 1)]
    # each rank made its own recordings; each cell's frames and seeds went to one rank only
    for cache in caches:
        assert _files(cache, "recordings") == _files(reference / "cache", "recordings")
    for kind in ("frames", "predictions"):
        made = [_files(cache, kind) for cache in caches]
        assert made[0] and made[1] and not made[0] & made[1]
        assert made[0] | made[1] == _files(reference / "cache", kind)


@pytest.mark.slow
def test_a_rank_killed_mid_run_leaves_its_jobs_and_the_rerun_does_the_rest(reference,
                                                                          tmp_path):
    config = _config(tmp_path / "config", tmp_path)
    cache = tmp_path / "cache"
    killed = _torchrun("--exit-after-training", "1", "evaluate", "--config", str(config))
    assert killed.returncode != 0 and not (tmp_path / "report").exists()
    kept = {p: p.stat().st_mtime_ns for p in (cache / "predictions").glob("*.json")}
    assert 0 < len(kept) < TRAININGS
    assert (cache / "runs" / "tiny.json").is_file()  # the unfinished run's record

    # another config is refused, before any work
    other = _config(tmp_path / "other", tmp_path, epochs=2)
    assert main(["evaluate", "--config", str(other)]) == 2
    assert set((cache / "predictions").glob("*.json")) == set(kept)

    # the same config, on one rank this time, does what is missing and nothing else
    assert main(["evaluate", "--config", str(config)]) == 0
    _assert_same_report(tmp_path / "report", reference / "report")
    assert {p: p.stat().st_mtime_ns for p in kept} == kept
    assert len(_files(cache, "predictions")) == TRAININGS
    assert not (cache / "runs" / "tiny.json").exists()


@pytest.mark.slow
def test_frames_stored_without_their_measures_are_made_again(reference, tmp_path):
    # a run killed after a unit's frames were stored and before its measures were
    shutil.copytree(reference / "cache", tmp_path / "cache")
    measures = sorted((tmp_path / "cache" / "frames").glob("*.json"))[0]
    measures.unlink()
    assert main(["evaluate", "--config", str(_config(tmp_path / "config", tmp_path))]) == 0
    _assert_same_report(tmp_path / "report", reference / "report")
    assert measures.is_file()


def test_another_config_than_the_unfinished_runs_is_refused_by_name(tmp_path, capsys):
    config = _config(tmp_path / "config", tmp_path)
    record = tmp_path / "cache" / "runs" / "tiny.json"
    record.parent.mkdir(parents=True)
    settings = study_settings(load_config(_config(tmp_path / "other", tmp_path, epochs=2)))
    record.write_text(json.dumps({"settings": settings}))
    assert main(["evaluate", "--config", str(config)]) == 2
    err = capsys.readouterr().err
    assert "holds an unfinished run of study 'tiny' with another configuration" in err
    assert "training.epochs" in err and str(record) in err
    assert sorted(p.name for p in (tmp_path / "cache").iterdir()) == ["runs"]  # no work


@pytest.mark.slow
def test_ranks_with_different_configs_are_refused_before_any_work(tmp_path):
    config = _config(tmp_path / "config", tmp_path)
    other = _config(tmp_path / "other", tmp_path, epochs=2)
    done = _torchrun("--config-of", "1", str(other), "evaluate", "--config", str(config))
    assert done.returncode != 0
    assert ("the ranks disagree on the config (compared by a hash of its settings, [output] "
            "aside): rank 1 in training.epochs differ from rank 0") in done.stderr
    assert not (tmp_path / "cache").exists() and not (tmp_path / "report").exists()


def test_one_process_is_one_rank_of_its_own(tmp_path):
    config = parse_config({})
    check_agreement(config)  # nothing to compare with
    assert folder_groups(tmp_path) == [(0,)]
    ranks = Ranks(tmp_path)
    assert (ranks.rank, ranks.world, ranks.gathered_through) == (0, 1, "")
    assert ranks.runners([5.0, 1.0, 3.0]) == [(0,), (0,), (0,)]
    assert not list(tmp_path.iterdir())  # no probe file in a single process


def test_study_settings_leave_out_the_places():
    a = parse_config({"output": {"cache": "a", "directory": "x"}}, name="a")
    b = parse_config({"output": {"cache": "b", "directory": "y"}}, name="b")
    assert study_settings(a) == study_settings(b)
    assert study_settings(a) != study_settings(parse_config({"data": {"seed": 1}}))


def test_balance_gives_the_longest_jobs_first_to_the_least_loaded():
    costs = [1, 7, 3, 5, 2, 2, 4]
    bins = balance(costs, [1, 1, 1])
    loads = [sum(c for c, b in zip(costs, bins) if b == k) for k in range(3)]
    assert bins == [1, 0, 2, 1, 1, 0, 2] and loads == [9, 8, 7]
    # within 4/3 of the best (here 8: {7, 1}, {5, 3}, {4, 2, 2}) as Graham's bound says
    assert max(loads) <= 4 / 3 * 8


@pytest.mark.parametrize("available", [False, True])
def test_each_rank_trains_on_its_own_gpu_or_on_the_cpu_without_cuda(monkeypatch, available):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: available)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    monkeypatch.setenv("LOCAL_RANK", "3")
    if not available:
        assert study._resolve_device("auto", 4) == torch.device("cpu")
        assert study._resolve_device("cpu", 4) == torch.device("cpu")
        with pytest.raises(ValueError, match="CUDA is not available here"):
            study._resolve_device("cuda", 4)
        return
    assert study._resolve_device("auto", 4) == torch.device("cuda", 1)  # 3 mod 2 GPUs
    assert study._resolve_device("cuda", 4) == torch.device("cuda", 1)
    assert study._resolve_device("cuda:0", 4) == torch.device("cuda", 0)  # as configured
    assert study._resolve_device("auto", 1) == torch.device("cuda")  # one process: as before
