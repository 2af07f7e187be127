"""``evdown preprocess`` and ``PreprocessedDataset``: the cache against the transform, ranks,
resuming, corruption, bad files."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from evdown_torch.cli import main
from evdown_torch.data import (
    PreprocessedDataset,
    RecordingError,
    open_source,
    preprocess,
    shards,
    verify_cache,
)
from evdown_torch.synthetic import SyntheticGestures
from evdown_torch.transforms.registry import make_method
from tests.helpers import DVS_DTYPE, random_stream

REPO = Path(__file__).resolve().parents[2]
SYNTHETIC = {"samples_per_class": 1, "duration_us": 200_000, "sensor_size": (24, 20, 2)}
SYNTHETIC_ARGS = ["--dataset", "synthetic", "--samples-per-class", "1", "--duration-us",
                  "200000", "--sensor-size", "24", "20", "2"]
METHOD_ARGS = ["--method", "event_count", "--factor", "2", "--set", "threshold=0.5"]


def _digests(folder: Path) -> dict[str, str]:
    """SHA-256 of every shard array, computed here, independently of the package."""
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.glob("shard-*.npy"))}


def _shards_of(folder: Path) -> list:
    return json.loads((folder / "manifest.json").read_text())["shards"]


def _command(*args: str) -> list[str]:
    return [sys.executable, "-m", "evdown_torch", "preprocess", *args]


def _env() -> dict[str, str]:
    return dict(os.environ, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")


@pytest.fixture(scope="module")
def reference(tmp_path_factory) -> Path:
    """The synthetic cache written by one process, in-process, shards of 3 recordings."""
    out = tmp_path_factory.mktemp("reference")
    source = open_source("synthetic", **SYNTHETIC)
    preprocess(source, out, "event_count", 2, {"threshold": 0.5}, shard_size=3, workers=1)
    return out


@pytest.mark.slow
def test_cache_equals_the_transform_recording_by_recording(reference):
    data = PreprocessedDataset(reference)
    truth = SyntheticGestures(samples_per_class=1, duration_us=200_000,
                              sensor_size=(24, 20, 2))
    transform = make_method("event_count", (24, 20, 2), 2, threshold=0.5)
    assert len(data) == len(truth) == 11
    assert data.sensor_size == (12, 10, 2) and data.classes == truth.classes
    events_in = 0
    for i in range(len(truth)):
        events, label = truth[i]
        events_in += len(events)
        cached, cached_label = data[i]
        expected = transform(events)
        assert cached.dtype == expected.dtype == DVS_DTYPE
        np.testing.assert_array_equal(cached, expected)
        assert cached_label == label == i % 11
    assert data.source_indices == list(range(11))
    manifest = data.manifest
    assert manifest["method"] == "event_count" and manifest["factor"] == [2, 2]
    assert manifest["settings"]["threshold"] == 0.5
    assert manifest["counts"] == {"shards": 4, "recordings": 11, "skipped": 0,
                                  "events_in": events_in,
                                  "events_out": sum(len(data[i][0]) for i in range(11))}
    for record in manifest["shards"]:
        for name, digest in record["sha256"].items():
            assert hashlib.sha256((reference / name).read_bytes()).hexdigest() == digest


def test_dataset_applies_transforms_like_tonic(reference):
    tonic = pytest.importorskip("tonic")
    frames = tonic.transforms.ToFrame(sensor_size=(12, 10, 2), n_time_bins=3)
    data = PreprocessedDataset(reference, transform=frames, target_transform=lambda y: y + 100)
    plain = PreprocessedDataset(reference, verify=False)
    out, label = data[5]
    assert label == 105 and out.shape == (3, 2, 10, 12)
    np.testing.assert_array_equal(out, frames(plain[5][0]))
    assert int(out.sum()) > 0
    events, _ = plain[-1]
    events["x"][:] = 0  # items are copies: the cache is untouched
    assert plain[-1][0]["x"].max() > 0


class WaitingSynthetic:
    """The synthetic source, whose loads in the creating process wait until another process
    has loaded a recording (so that a spawned worker surely gets some work); ``log`` notes
    which process loaded each recording."""

    def __init__(self, log: Path) -> None:
        self.inner = open_source("synthetic", **SYNTHETIC)
        self.log, self.creator = log, os.getpid()
        self.sensor_size, self.dtype = self.inner.sensor_size, self.inner.dtype
        self.classes = self.inner.classes

    def __len__(self) -> int:
        return len(self.inner)

    def describe(self) -> dict:
        return self.inner.describe()

    def source_name(self, index: int) -> str:
        return self.inner.source_name(index)

    def load(self, index: int):
        deadline = time.monotonic() + 120
        while os.getpid() == self.creator and not any(
                not name.endswith(f"-{self.creator}") for name in os.listdir(self.log)):
            assert time.monotonic() < deadline, "no worker process loaded anything"
            time.sleep(0.01)
        (self.log / f"{index}-{os.getpid()}").touch()
        return self.inner.load(index)


@pytest.mark.slow
def test_two_worker_processes_write_the_same_bytes(reference, tmp_path):
    log = tmp_path / "log"
    log.mkdir()
    out = tmp_path / "cache"
    result = preprocess(WaitingSynthetic(log), out, "event_count", 2, {"threshold": 0.5},
                        shard_size=3, workers=2)
    assert result.written == (0, 1, 2, 3) and result.kept == () and result.recordings == 11
    assert _digests(out) == _digests(reference)
    assert (out / "manifest.json").read_text() == (reference / "manifest.json").read_text()
    loads = [name.split("-") for name in os.listdir(log)]
    assert sorted(int(i) for i, _ in loads) == list(range(11))  # each recording once
    assert len({pid for _, pid in loads}) == 2  # both processes worked


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_torchrun_two_ranks_write_the_same_cache(reference, tmp_path):
    command = [sys.executable, "-m", "torch.distributed.run", "--nnodes", "1",
               "--nproc-per-node", "2", "--master-addr", "127.0.0.1", "--master-port",
               str(_free_port()), "-m", "evdown_torch", "preprocess", *SYNTHETIC_ARGS,
               *METHOD_ARGS, "--shard-size", "3", "--out", str(tmp_path)]
    done = subprocess.run(command, cwd=REPO, env=_env(), capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert _digests(tmp_path) == _digests(reference)
    assert (tmp_path / "manifest.json").read_text() == (reference / "manifest.json").read_text()
    assert done.stdout.count("wrote") == 1  # rank 0 alone reports


def _folder_dataset(root: Path, rng: np.random.Generator, big: int = 0) -> Path:
    """PATH/CLASS/*.npy: classes "a" and "b"; recording 1 has ``big`` events if given."""
    sizes = [300, big or 200, 250, 150]
    for i, n in enumerate(sizes):
        folder = root / ("a" if i < 2 else "b")
        folder.mkdir(parents=True, exist_ok=True)
        np.save(folder / f"rec{i}.npy", random_stream(rng, n, (64, 48, 2), t_max=10_000 * n))
    return root


@pytest.mark.slow
def test_interrupted_run_resumes_to_the_same_cache(tmp_path, rng):
    data = _folder_dataset(tmp_path / "data", rng, big=3_000_000)
    args = ["--dataset", f"folder:{data}", "--sensor-size", "64", "48", "2", "--method",
            "linear", "--factor", "4", "--shard-size", "1", "--workers", "1"]
    out = tmp_path / "out"
    run = subprocess.Popen(_command(*args, "--out", str(out)), cwd=REPO, env=_env(),
                           stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while not (out / "shard-00000.json").exists() and run.poll() is None:
        assert time.monotonic() < deadline, "the first shard never appeared"
        time.sleep(0.002)
    run.send_signal(signal.SIGKILL)
    run.communicate()
    assert run.returncode == -signal.SIGKILL, "the run ended before it could be interrupted"
    assert not (out / "shard-00003.json").exists() and not (out / "manifest.json").exists()
    with pytest.raises(ValueError, match="no manifest.json"):
        PreprocessedDataset(out)

    assert main(["preprocess", *args, "--out", str(out), "--no-progress"]) == 0
    whole = tmp_path / "whole"
    assert main(["preprocess", *args, "--out", str(whole), "--no-progress"]) == 0
    assert _digests(out) == _digests(whole)
    assert _shards_of(out) == _shards_of(whole)
    assert not list(out.glob(".*"))  # no temporary file left
    assert verify_cache(out) == []


def test_partial_shard_is_redone_and_complete_ones_kept(reference, tmp_path):
    out = tmp_path / "cache"
    source = open_source("synthetic", **SYNTHETIC)
    preprocess(source, out, "event_count", 2, {"threshold": 0.5}, shard_size=3, workers=1)
    # A run killed while writing shard 2: its record never written, a truncated array and
    # a temporary file left behind; the manifest not yet written.
    (out / "shard-00002.json").unlink()
    events = out / "shard-00002.events.npy"
    events.write_bytes(events.read_bytes()[:100])
    (out / ".shard-00002.events.npy.tmp-12345").write_bytes(b"partial")
    (out / "manifest.json").unlink()
    result = preprocess(source, out, "event_count", 2, {"threshold": 0.5}, shard_size=3,
                        workers=1)
    assert result.written == (2,) and result.kept == (0, 1, 3) and result.recordings == 3
    assert _digests(out) == _digests(reference)
    assert (out / "manifest.json").read_text() == (reference / "manifest.json").read_text()
    assert not list(out.glob(".*"))


def test_corrupt_shard_is_detected_and_redone(reference, tmp_path):
    out = tmp_path / "cache"
    source = open_source("synthetic", **SYNTHETIC)
    preprocess(source, out, "event_count", 2, {"threshold": 0.5}, shard_size=3, workers=1)
    path = out / "shard-00001.events.npy"
    raw = bytearray(path.read_bytes())
    raw[-5] ^= 0xFF  # one flipped byte in the events, same size
    path.write_bytes(bytes(raw))
    problems = verify_cache(out)
    assert len(problems) == 1 and "shard-00001.events.npy" in problems[0]
    with pytest.raises(ValueError, match=r"shard-00001\.events\.npy.*corrupt"):
        PreprocessedDataset(out)
    (out / "shard-00003.index.npy").unlink()
    assert any("shard-00003.index.npy' is missing" in p for p in verify_cache(out))
    result = preprocess(source, out, "event_count", 2, {"threshold": 0.5}, shard_size=3,
                        workers=1)
    assert result.written == (1, 3)
    assert _digests(out) == _digests(reference) and verify_cache(out) == []


def test_damaged_manifests_are_refused_clearly(reference, tmp_path):
    out = tmp_path / "cache"
    shutil.copytree(reference, out)
    good = json.loads((out / "manifest.json").read_text())
    no_checksums = dict(good, shards=[{k: v for k, v in r.items() if k != "sha256"}
                                      for r in good["shards"]])
    damaged = [
        ({k: v for k, v in good.items() if k != "shards"}, r"lacks 'shards'"),
        ({k: v for k, v in good.items() if k not in ("dtype", "classes")},
         r"lacks 'classes', 'dtype'"),
        (dict(good, shards={"0": good["shards"][0]}), "not shard records"),
        (no_checksums, "not shard records"),
        (dict(good, format_version=99), "format version 99"),
    ]
    for manifest, message in damaged:
        (out / "manifest.json").write_text(json.dumps(manifest))
        for open_cache in (PreprocessedDataset, verify_cache):
            with pytest.raises(ValueError, match=message):
                open_cache(out)
    (out / "manifest.json").write_text(json.dumps(damaged[0][0]))
    # the rerun the message asks for puts the cache back
    preprocess(open_source("synthetic", **SYNTHETIC), out, "event_count", 2,
               {"threshold": 0.5}, shard_size=3, workers=1)
    assert len(PreprocessedDataset(out)) == len(PreprocessedDataset(reference))


def test_folder_labels_and_unreadable_file(tmp_path, rng, capsys):
    data = _folder_dataset(tmp_path / "data", rng)
    (data / "b" / "broken.npy").write_bytes(b"not an array")
    (data / "b" / "notes.txt").write_text("ignored: not a recording suffix")
    args = ["preprocess", "--dataset", f"folder:{data}", "--sensor-size", "64", "48", "2",
            "--method", "downsample", "--factor", "2", "--shard-size", "2", "--workers", "1"]
    assert main([*args, "--out", str(tmp_path / "skip")]) == 0
    assert f"skipped {data / 'b' / 'broken.npy'}" in capsys.readouterr().err
    cache = PreprocessedDataset(tmp_path / "skip")
    assert cache.classes == ["a", "b"] and cache.targets == [0, 0, 1, 1]
    # Sorted within class b: broken.npy (index 2, skipped), rec2.npy, rec3.npy.
    assert cache.source_indices == [0, 1, 3, 4]
    transform = make_method("downsample", (64, 48, 2), 2)
    np.testing.assert_array_equal(cache[2][0], transform(np.load(data / "b" / "rec2.npy")))
    skipped = cache.manifest["shards"][1]["skipped"]
    assert [s["index"] for s in skipped] == [2] and "broken.npy" in skipped[0]["source"]
    assert cache.manifest["counts"]["skipped"] == 1

    assert main([*args, "--out", str(tmp_path / "stop"), "--on-error", "stop"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("evdown preprocess: error: cannot preprocess ")
    assert "broken.npy" in err and err.count("\n") == 1
    kept = tmp_path / "stop"
    assert (kept / "shard-00000.json").is_file() and not (kept / "manifest.json").exists()
    np.testing.assert_array_equal(np.load(kept / "shard-00000.events.npy"),
                                  np.load(tmp_path / "skip" / "shard-00000.events.npy"))


def test_an_empty_first_file_is_skipped_like_any_other(tmp_path, rng, capsys):
    data = _folder_dataset(tmp_path / "data", rng)
    (data / "a" / "empty.npy").write_bytes(b"")  # sorts first: the file that sets the dtype
    args = ["preprocess", "--dataset", f"folder:{data}", "--sensor-size", "64", "48", "2",
            "--method", "downsample", "--factor", "2", "--workers", "1", "--no-progress"]
    assert main([*args, "--out", str(tmp_path / "skip")]) == 0
    assert f"skipped {data / 'a' / 'empty.npy'}" in capsys.readouterr().err
    cache = PreprocessedDataset(tmp_path / "skip")
    assert cache.source_indices == [1, 2, 3, 4] and cache.targets == [0, 0, 1, 1]
    assert main([*args, "--out", str(tmp_path / "stop"), "--on-error", "stop"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("evdown preprocess: error: cannot preprocess ")
    assert "empty.npy" in err and err.count("\n") == 1


@pytest.mark.slow
def test_recording_error_in_the_api(tmp_path, rng):
    data = _folder_dataset(tmp_path / "data", rng)
    bad = random_stream(rng, 10, (64, 48, 2))
    bad["x"][3] = 64  # outside the sensor
    np.save(data / "a" / "rec1.npy", bad)
    source = open_source(f"folder:{data}", sensor_size=(64, 48, 2))
    with pytest.raises(RecordingError, match=r"rec1\.npy: ValueError: .*x"):
        preprocess(source, tmp_path / "out", "downsample", 2, on_error="stop", workers=1)
    out = tmp_path / "two"
    with pytest.raises(RecordingError, match=r"rec1\.npy"):
        preprocess(source, out, "downsample", 2, shard_size=1, on_error="stop", workers=2)
    assert not (out / "manifest.json").exists() and not list(out.glob(".*"))
    for record in out.glob("shard-*.json"):  # whatever finished is complete and intact
        assert shards.shard_problem(out, json.loads(record.read_text())) is None


def test_progress_bar_with_rate_only_when_asked(tmp_path, capsys):
    source = open_source("synthetic", **SYNTHETIC)
    preprocess(source, tmp_path / "a", "downsample", 2, workers=1)  # stderr is no terminal
    assert capsys.readouterr().err == ""
    preprocess(source, tmp_path / "b", "downsample", 2, workers=1, progress=True)
    err = capsys.readouterr().err
    assert "11/11" in err and "rec/s" in err


def test_nmnist_in_its_own_layout(tmp_path):
    """The real N-MNIST test folder, read where it lies: labels from the digit folders."""
    tonic = pytest.importorskip("tonic")
    from tests.conftest import SHARED_DATA

    root = SHARED_DATA / "nmnist_small"
    if not root.is_dir():
        pytest.skip(f"{root} is absent")
    source = open_source("nmnist", root=root, split="test")
    assert len(source) == 100 and source.sensor_size == (34, 34, 2)
    assert sorted(set(source.labels)) == list(range(10))
    preprocess(source, tmp_path / "out", "event_count", 2, {"threshold": 1}, workers=1)
    cache = PreprocessedDataset(tmp_path / "out")
    assert cache.targets == source.labels
    for index in (0, 57, 99):
        path = source.source_name(index)
        assert Path(path).parent.name == str(source.labels[index])
        raw = tonic.io.read_mnist_file(path, dtype=tonic.datasets.NMNIST.dtype)
        expected = make_method("event_count", (34, 34, 2), 2, threshold=1)(raw)
        got = cache[index][0]
        assert len(got) == len(expected) > 0
        for name in ("x", "y", "t"):
            np.testing.assert_array_equal(got[name], expected[name])
        np.testing.assert_array_equal(got["p"], expected["p"] > 0)


@pytest.mark.parametrize("dataset", ["dvsgesture", "nmnist"])
def test_absent_tonic_files_say_where_they_go(tmp_path, capsys, dataset):
    pytest.importorskip("tonic")
    code = main(["preprocess", "--dataset", dataset, "--root", str(tmp_path), *METHOD_ARGS,
                 "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    folder = "DVSGesture" if dataset == "dvsgesture" else "NMNIST"
    assert code == 2 and "files are absent" in err and str(tmp_path / folder) in err
    assert err.count("\n") == 1 and not list(tmp_path.glob("*/*.gz"))


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--dataset", "folder:/nonexistent", "--sensor-size", "4", "4", "2"], "does not exist"),
        (["--dataset", "nmnist"], "needs --root"),
        (["--dataset", "synthetic", "--root", "x"], "--root is for Tonic"),
        (["--dataset", "nmnist", "--root", "x", "--seed", "3"], "seed is a setting of the"),
        (["--dataset", "synthetic", "--shard-size", "0"], "shard_size must be"),
        (["--dataset", "synthetic", "--set", "dt=3"], "does not take setting"),
        (["--dataset", "synthetic", "--threshold", "0.5"], "--threshold is gone"),
    ],
)
def test_bad_arguments_get_one_line(tmp_path, capsys, extra, message):
    args = ["preprocess", *METHOD_ARGS, "--out", str(tmp_path / "o"), *extra]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("evdown preprocess: error: ") and message in err
    assert err.count("\n") == 1


def test_another_job_in_the_same_folder_is_refused(reference, tmp_path):
    source = open_source("synthetic", **SYNTHETIC)
    out = tmp_path / "cache"
    preprocess(source, out, "event_count", 2, {"threshold": 0.5}, shard_size=3, workers=1)
    before = _digests(out)
    with pytest.raises(ValueError, match="another job.*settings"):
        preprocess(source, out, "event_count", 2, {"threshold": 0.25}, shard_size=3, workers=1)
    assert _digests(out) == before


def test_dvsgesture_through_tonic(tmp_path, monkeypatch, rng):
    tonic = pytest.importorskip("tonic")
    folder = tmp_path / "DVSGesture" / "ibmGestureTest" / "user01_led"
    folder.mkdir(parents=True)
    recordings = {}
    for label in (2, 9):  # DVSGesture's files: (N, 4) arrays x, y, p, t in ms, named LABEL.npy
        ev = random_stream(rng, 500, (128, 128, 2), t_max=3000)
        recordings[label] = ev
        raw = np.stack([ev["x"], ev["y"], ev["p"], ev["t"]], axis=1).astype(np.int64)
        np.save(folder / f"{label}.npy", raw)
    monkeypatch.setattr(tonic.datasets.DVSGesture, "_check_exists", lambda self: True)
    source = open_source("dvsgesture", root=tmp_path, split="test")
    preprocess(source, tmp_path / "out", "funnelling", 4, workers=1)
    cache = PreprocessedDataset(tmp_path / "out")
    assert cache.sensor_size == (32, 32, 2) and sorted(cache.targets) == [2, 9]
    transform = make_method("funnelling", (128, 128, 2), 4)
    for events, label in (cache[0], cache[1]):
        expected = recordings[label].copy()
        expected["t"] *= 1000  # Tonic's DVSGesture reads milliseconds as microseconds
        np.testing.assert_array_equal(events, transform(expected))


def test_threads_apply_while_working_and_the_callers_count_is_restored(reference, tmp_path,
                                                                      monkeypatch):
    from evdown_torch.data import preprocessing

    seen = []
    real = preprocessing._write_one_shard

    def spy(state, shard):
        seen.append(torch.get_num_threads())
        return real(state, shard)

    monkeypatch.setattr(preprocessing, "_write_one_shard", spy)
    source = open_source("synthetic", **SYNTHETIC)
    before = torch.get_num_threads()
    preprocess(source, tmp_path / "two", "event_count", 2, {"threshold": 0.5}, shard_size=3,
               workers=1, threads=2)
    assert seen and set(seen) == {2} and torch.get_num_threads() == before
    assert _digests(tmp_path / "two") == _digests(reference)  # threads change no result
    with pytest.raises(ValueError, match="threads must be a positive integer"):
        preprocess(source, tmp_path / "zero", "downsample", 2, workers=1, threads=0)


def test_a_folder_of_float_seconds_with_time_unit_and_columns(tmp_path, rng, capsys):
    # The same recordings as (N, 4) float arrays of t in seconds, x, y, p: with --time-unit s
    # and --columns t,x,y,p the cache equals the one of the microsecond files; without the
    # unit, one warning names the fix (the run's first recording), in the command's words.
    micro = _folder_dataset(tmp_path / "micro", rng)
    seconds = tmp_path / "seconds"
    for path in sorted(micro.glob("*/*.npy")):
        events = np.load(path)
        (seconds / path.parent.name).mkdir(parents=True, exist_ok=True)
        np.save(seconds / path.parent.name / path.name, np.stack(
            [events["t"] / 1e6, events["x"], events["y"], events["p"]], axis=1))
    common = ["preprocess", "--sensor-size", "64", "48", "2", "--method", "lif", "--factor",
              "4", "--workers", "1", "--no-progress"]
    assert main([*common, "--dataset", f"folder:{micro}", "--out", str(tmp_path / "a")]) == 0
    assert main([*common, "--dataset", f"folder:{seconds}", "--out", str(tmp_path / "b"),
                 "--time-unit", "s", "--columns", "t,x,y,p"]) == 0
    assert "warning" not in capsys.readouterr().err
    a, b = PreprocessedDataset(tmp_path / "a"), PreprocessedDataset(tmp_path / "b")
    assert len(a) == len(b) == 4
    for i in range(4):
        np.testing.assert_array_equal(a[i][0]["t"], b[i][0]["t"])
    assert main([*common, "--dataset", f"folder:{seconds}", "--out", str(tmp_path / "c"),
                 "--columns", "t,x,y,p"]) == 0
    (warning,) = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
    assert "rec0.npy" in warning and "--time-unit s" in warning and "time_unit=" not in warning


def test_help_names_every_format_a_folder_may_hold(capsys):
    with pytest.raises(SystemExit):
        main(["preprocess", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "PATH/CLASS/FILE" in text and ".bin" in text and ".aedat4" in text
    assert "--time-unit" in text and "--columns" in text and "Train/" in text
