"""The one notion of a dataset source, and the one opener of Tonic's datasets."""

from __future__ import annotations

import numpy as np
import pytest

from evdown_torch.data.sources import Source, TonicSource, open_source
from tests.helpers import random_stream


def test_every_opened_dataset_is_a_source(tmp_path, rng):
    synthetic = open_source("synthetic", samples_per_class=1, duration_us=50_000,
                            sensor_size=(16, 12, 2))
    (tmp_path / "a").mkdir()
    np.save(tmp_path / "a" / "r.npy", random_stream(rng, 20, (16, 12, 2), t_max=1000))
    folder = open_source(f"folder:{tmp_path}", sensor_size=(16, 12, 2))
    for source in (synthetic, folder):
        assert isinstance(source, Source)
        events, label = source.load(len(source) - 1)
        assert events.dtype == source.dtype and 0 <= label < len(source.classes)
    assert not isinstance(object(), Source)


def test_tonic_source_downloads_only_when_asked(tmp_path, monkeypatch):
    tonic = pytest.importorskip("tonic")
    calls = []
    monkeypatch.setattr(tonic.datasets.DVSGesture, "_check_exists", lambda self: False)
    monkeypatch.setattr(tonic.datasets.DVSGesture, "download", lambda self: calls.append(1))
    with pytest.raises(ValueError, match="DVSGesture files are absent"):
        TonicSource("dvsgesture", root=tmp_path, split="test")
    assert calls == []
    source = TonicSource("dvsgesture", root=tmp_path, split="test", download=True)
    assert calls == [1] and len(source) == 0 and source.sensor_size == (128, 128, 2)
    assert isinstance(source, Source)


def test_a_folder_reads_every_format_in_any_case_and_its_time_unit(tmp_path, rng):
    from tests.conftest import NMNIST_FILE

    pytest.importorskip("tonic")
    if not NMNIST_FILE.exists():
        pytest.skip("the N-MNIST sample is absent")
    (tmp_path / "3").mkdir()
    (tmp_path / "3" / "a.bin").write_bytes(NMNIST_FILE.read_bytes())
    events = random_stream(rng, 20, (34, 34, 2), t_max=300)  # t in milliseconds
    table = np.stack([events["t"], events["x"], events["y"], events["p"]], axis=1)
    np.save(tmp_path / "3" / "b.NPY", table)  # int64 (N, 4): t, x, y, p
    source = open_source(f"folder:{tmp_path}", sensor_size=(34, 34, 2), time_unit="ms",
                         columns="t,x,y,p")
    assert len(source) == 2 and source.describe()["time_unit"] == "ms"
    assert source.load(1)[0]["t"].tolist() == (events["t"] * 1000).tolist()  # exact, int64
    assert len(source.load(0)[0]) == 4325  # the .bin, in its own microseconds
    with pytest.raises(ValueError, match="time_unit is a setting of folder datasets only"):
        open_source("synthetic", time_unit="s")


def test_nmnist_takes_its_extracted_folder_without_the_archive(tmp_path):
    from tests.conftest import NMNIST_FILE

    pytest.importorskip("tonic")
    if not NMNIST_FILE.exists():
        pytest.skip("the N-MNIST sample is absent")
    for digit in range(10):  # Train/ as train.zip extracts, the archive itself gone
        (tmp_path / "NMNIST" / "Train" / str(digit)).mkdir(parents=True)
        (tmp_path / "NMNIST" / "Train" / str(digit) / "1.bin").write_bytes(
            NMNIST_FILE.read_bytes())
    source = open_source("nmnist", root=tmp_path)
    assert len(source) == 10 and [source.load(i)[1] for i in (3, 7)] == [3, 7]
    with pytest.raises(ValueError, match=r"no Test/ folder in"):
        open_source("nmnist", root=tmp_path, split="test")
