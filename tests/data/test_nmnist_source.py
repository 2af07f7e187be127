"""N-MNIST in its own layout (Train/<digit>/<id>.bin): the real folder, read where it lies, and
small folders built here, complete or broken (missing class, empty file, truncated file)."""

from __future__ import annotations

import numpy as np
import pytest

from evdown_torch.cli import main
from evdown_torch.data import PreprocessedDataset
from evdown_torch.data.sources import NMNISTSource, Source, open_source
from evdown_torch.events import DVS_DTYPE
from evdown_torch.io import read_events
from evdown_torch.plot.recording import load_recording
from tests.conftest import SHARED_DATA

REAL = SHARED_DATA / "nmnist_small"

tonic = pytest.importorskip("tonic")


@pytest.fixture(scope="module")
def real():
    if not REAL.is_dir():
        pytest.skip(f"{REAL} is absent")
    return REAL


def encode(events: list[tuple[int, int, int, int]]) -> bytes:
    """N-MNIST's 40-bit events ``(x, y, p, t)``: x, y bytes, then p and 23 bits of time."""
    out = bytearray()
    for x, y, p, t in events:
        out += bytes([x, y, (p << 7) | (t >> 16), (t >> 8) & 0xFF, t & 0xFF])
    return bytes(out)


def build(root, split="Train", digits=range(10), per_digit=2):
    """A small folder in N-MNIST's layout; recording ``i`` of digit ``d`` has ``d + i + 1``
    events at ``x = d``."""
    for d in digits:
        folder = root / split / str(d)
        folder.mkdir(parents=True)
        for i in range(per_digit):
            events = [(d, k, k % 2, 100 * k + i) for k in range(d + i + 1)]
            (folder / f"{i:05d}.bin").write_bytes(encode(events))
    return root


def test_the_encoder_writes_what_tonic_reads(tmp_path):
    (tmp_path / "a.bin").write_bytes(encode([(3, 4, 1, 70_000), (33, 0, 0, 8_000_000)]))
    read = tonic.io.read_mnist_file(str(tmp_path / "a.bin"), dtype=tonic.datasets.NMNIST.dtype)
    assert read.tolist() == [(3, 4, 70_000, 1), (33, 0, 8_000_000, 0)]


def test_real_folder_labels_come_from_the_digit_folders(real):
    train, test = (NMNISTSource(real, split=s) for s in ("train", "test"))
    assert (len(train), len(test)) == (1000, 100)
    assert isinstance(train, Source) and train.sensor_size == (34, 34, 2)
    counts = np.bincount(train.labels, minlength=10)
    assert counts.sum() == 1000 and counts.min() >= 87 and counts.max() <= 117
    assert np.bincount(test.labels, minlength=10)[8] == 2
    for index in (0, 500, 999):
        events, label = train.load(index)
        path = train.source_name(index)
        assert str(label) == path.split("/")[-2] and events.dtype == DVS_DTYPE
        raw = tonic.io.read_mnist_file(path, dtype=tonic.datasets.NMNIST.dtype)
        np.testing.assert_array_equal(events["t"], raw["t"])
        np.testing.assert_array_equal(events["x"], raw["x"])
        np.testing.assert_array_equal(events["p"], raw["p"] > 0)
        assert 1_000 <= len(events) <= 7_000 and events["x"].max() < 34


def test_a_built_folder_and_tonics_layout(tmp_path):
    build(tmp_path / "NMNIST")  # where tonic.datasets.NMNIST(save_to=ROOT) puts it
    source = open_source("nmnist", root=tmp_path, split="train")
    assert isinstance(source, NMNISTSource) and len(source) == 20
    assert source.labels == [d for d in range(10) for _ in range(2)]
    events, label = source.load(7)  # digit 3, its second recording: 5 events
    assert label == 3 and len(events) == 5 and set(events["x"].tolist()) == {3}
    assert events["t"].tolist() == [1, 101, 201, 301, 401]


def test_an_absent_split_says_where_the_files_go(tmp_path):
    build(tmp_path)  # Train only
    with pytest.raises(ValueError, match=r"files are absent: no Test/ folder in .*NMNIST"):
        NMNISTSource(tmp_path, split="test")


def test_a_missing_class_is_named(tmp_path):
    build(tmp_path, digits=[d for d in range(10) if d not in (4, 7)])
    with pytest.raises(ValueError, match=r"lacks the class folder\(s\) 4, 7"):
        NMNISTSource(tmp_path, split="train")


def test_a_class_without_recordings_is_named(tmp_path):
    build(tmp_path, digits=range(9))
    (tmp_path / "Train" / "9").mkdir()
    (tmp_path / "Train" / "9" / "notes.txt").write_text("not a recording")
    with pytest.raises(ValueError, match=r"class folder 9/ holds no \.bin recording"):
        NMNISTSource(tmp_path, split="train")


def test_empty_and_truncated_files_are_named(tmp_path):
    build(tmp_path)
    (tmp_path / "Train" / "2" / "00001.bin").write_bytes(b"")
    whole = (tmp_path / "Train" / "6" / "00000.bin").read_bytes()
    (tmp_path / "Train" / "6" / "00000.bin").write_bytes(whole[:-2])
    with pytest.raises(ValueError) as caught:
        NMNISTSource(tmp_path, split="train")
    message = str(caught.value)
    assert "2/00001.bin is empty" in message
    assert f"6/00000.bin is truncated ({len(whole) - 2} bytes" in message
    assert "is incomplete" in message and str(tmp_path / "Train") in message


def test_many_problems_are_counted(tmp_path):
    build(tmp_path, per_digit=1)
    for d in range(10):
        (tmp_path / "Train" / str(d) / "00000.bin").write_bytes(b"")
    with pytest.raises(ValueError, match=r"0/00000.bin is empty; .*; and 5 more$"):
        NMNISTSource(tmp_path, split="train")


def test_reading_a_truncated_bin_file_names_it(tmp_path):
    (tmp_path / "cut.bin").write_bytes(encode([(1, 2, 1, 3)]) + b"\x01\x02")
    with pytest.raises(ValueError, match=r"cut.bin' is truncated: its 7 bytes are not a whole "
                                         r"number of 5-byte N-MNIST events"):
        read_events(tmp_path / "cut.bin")


def test_preprocess_reads_the_real_test_split(real, tmp_path, capsys):
    code = main(["preprocess", "--dataset", "nmnist", "--root", str(real), "--split", "test",
                 "--method", "density", "--factor", "2", "--set", "s=0.05",
                 "--out", str(tmp_path / "out"), "--workers", "1", "--no-progress"])
    assert code == 0, capsys.readouterr().err
    cache = PreprocessedDataset(tmp_path / "out")
    assert len(cache) == 100 and cache.targets == NMNISTSource(real, split="test").labels


def test_preprocess_refuses_a_broken_folder_in_one_line(tmp_path, capsys):
    build(tmp_path, digits=range(1, 10))
    code = main(["preprocess", "--dataset", "nmnist", "--root", str(tmp_path),
                 "--method", "downsample", "--factor", "2", "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2 and "lacks the class folder(s) 0" in err and err.count("\n") == 1
    assert not (tmp_path / "out").exists()


def test_show_reads_a_digit_of_the_folder(tmp_path):
    build(tmp_path, split="Test")
    shown = load_recording("nmnist:5:1", root=str(tmp_path), split="test")
    assert shown.label == 5 and shown.sensor_size == (34, 34, 2)
    assert shown.events.num_events == 7 and shown.name.endswith("Test/5/00001.bin")
    assert shown.ground_truth(2) is None
    with pytest.raises(ValueError, match="has 2 recordings of digit 5"):
        load_recording("nmnist:5:2", root=str(tmp_path), split="test")
    with pytest.raises(ValueError, match="needs --root"):
        load_recording("nmnist:5")
    with pytest.raises(ValueError, match="looks like nmnist:DIGIT"):
        load_recording("nmnist:12", root=str(tmp_path), split="test")
