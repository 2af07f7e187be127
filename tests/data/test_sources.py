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
