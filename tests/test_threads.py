"""torch_threads sets torch's thread count for a block only; library calls leave it alone."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from evdown_torch.threads import torch_threads


def test_the_count_is_restored_even_after_an_error():
    before = torch.get_num_threads()
    with pytest.raises(RuntimeError), torch_threads(1):
        assert torch.get_num_threads() == 1
        raise RuntimeError("inside")
    assert torch.get_num_threads() == before
    with pytest.raises(ValueError, match="threads must be a positive integer"), torch_threads(0):
        pass


def test_realtime_replay_leaves_the_callers_thread_count(rng):
    from evdown_torch.bench.realtime import realtime_benchmark
    from tests.helpers import random_stream

    events = np.sort(random_stream(rng, 300, (16, 16, 2), t_max=20_000), order="t")
    before = torch.get_num_threads()
    with torch_threads(2):  # a setting of the caller's that is not 1
        realtime_benchmark(events, (16, 16, 2), factor=2, methods=["downsample"],
                           chunks_us=(5000,),
                           rates=(None,), max_chunks=2)
        assert torch.get_num_threads() == 2
    assert torch.get_num_threads() == before


@pytest.mark.parametrize("threads", [10**30, 2**63, 100_000])
def test_thread_counts_are_bounded_with_a_message_naming_them(threads):
    before = torch.get_num_threads()
    with pytest.raises(ValueError, match=r"threads must be at most 1024 \(this machine has"), \
            torch_threads(threads):
        pass
    assert torch.get_num_threads() == before


@pytest.fixture
def npy(tmp_path, rng):
    from tests.helpers import saved_stream

    return saved_stream(tmp_path / "in.npy", rng, 50, (8, 8, 2))


def _downscale(npy, *options: str) -> int:
    from evdown_torch.cli import main

    return main(["downscale", str(npy), str(npy.with_name("out.npy")), "--method",
                 "downsample", "--factor", "2", "--sensor-size", "8", "8", "2", *options])


@pytest.mark.parametrize("text", ["99999999999999999999", "100000", "1025"])
def test_a_huge_threads_option_is_one_error_line_before_any_work(npy, text, capsys):
    with pytest.raises(SystemExit) as exit_info:
        _downscale(npy, "--threads", text)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("evdown downscale: error: argument --threads: ")
    assert "--threads must be at most 1024" in err[-1] and text in err[-1]
    assert not npy.with_name("out.npy").exists()


@pytest.fixture
def set_threads(monkeypatch) -> list[int]:
    """What the command sets torch's thread count to (this process's count is left alone)."""
    calls: list[int] = []
    monkeypatch.setattr(torch, "set_num_threads", calls.append)
    return calls


def _machine(monkeypatch, cores: int, omp_num_threads: str | None) -> None:
    """A machine of ``cores`` cores, ``OMP_NUM_THREADS`` set to ``omp_num_threads`` (or unset)."""
    monkeypatch.setattr("evdown_torch.threads.available_cores", lambda: cores, raising=False)
    if omp_num_threads is None:
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    else:
        monkeypatch.setenv("OMP_NUM_THREADS", omp_num_threads)


@pytest.mark.parametrize(("environment", "option", "expected"), [
    (None, (), 1),  # neither: one thread
    ("3", (), 3),  # OMP_NUM_THREADS when --threads is not given
    ("3,1", (), 3),  # OpenMP's nested form: the first level
    ("3", ("--threads", "2"), 2),  # --threads wins
])
def test_omp_num_threads_is_the_default_of_threads(npy, monkeypatch, set_threads, capsys,
                                                   environment, option, expected):
    _machine(monkeypatch, cores=64, omp_num_threads=environment)
    assert _downscale(npy, *option) == 0
    assert set_threads == [expected]
    assert capsys.readouterr().err == ""


def test_a_bad_omp_num_threads_warns_and_uses_one(npy, monkeypatch, set_threads, capsys):
    monkeypatch.setenv("OMP_NUM_THREADS", "many")
    assert _downscale(npy) == 0
    assert set_threads == [1]
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("evdown downscale: warning: ")
    assert "OMP_NUM_THREADS" in err[0] and "'many'" in err[0] and "using 1 thread" in err[0]


@pytest.mark.parametrize(("environment", "option", "said"), [
    (None, ("--threads", "4"), "--threads 4"),
    ("4", (), "OMP_NUM_THREADS=4"),
])
def test_more_threads_than_cores_warn_once(npy, monkeypatch, set_threads, capsys,
                                           environment, option, said):
    _machine(monkeypatch, cores=2, omp_num_threads=environment)
    assert _downscale(npy, *option) == 0
    assert set_threads == [4]
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"evdown downscale: warning: {said} asks for "
                                               "more threads than the 2 cores available")


def test_show_and_preprocess_take_the_same_threads(monkeypatch):
    """Every command with --threads resolves it the same way (one parser type, one default)."""
    from evdown_torch.cli import build_parser

    parser = build_parser()
    for command in ("downscale", "show", "preprocess"):
        argv = {"downscale": ["downscale", "a.npy", "b.npy", "--method", "downsample",
                              "--factor", "2"],
                "show": ["show", "a.npy", "--factor", "2"],
                "preprocess": ["preprocess", "--dataset", "nmnist", "--method", "downsample",
                               "--factor", "2", "--out", "o"]}[command]
        assert parser.parse_args(argv).threads is None  # resolved at run time
        with pytest.raises(SystemExit):
            parser.parse_args([*argv, "--threads", "5000"])
