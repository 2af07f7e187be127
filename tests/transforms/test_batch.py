"""transform.batch: each recording's output equals processing it alone (docs/semantics.md)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import evdown_torch as ev
from evdown_torch import _tensors as tensors
from evdown_torch.collate import EventBatch
from evdown_torch.events import DVS_DTYPE
from evdown_torch.transforms import Streaming
from evdown_torch.transforms.functional.reference import region_dtype
from tests.helpers import random_stream, transform_cases

SENSOR = (7, 5, 2)  # not a multiple of the factors: edge regions have fewer pixels

#: The table of instances (tests/helpers.py), every method and mode.
NAMES = sorted(transform_cases(SENSOR, 2, step=50))


def _case(name: str, factor: int | tuple[int, int]) -> Streaming:
    return transform_cases(SENSOR, factor, step=50)[name]


def _recordings(rng: np.random.Generator, t_max: int = 400) -> list[np.ndarray]:
    """Recordings of various lengths: empty, one event, ties inside and across recordings,
    different clocks (one starts late, one far in the epoch), one out of time order."""
    sizes = [0, 1, 37, 5, 120, 0, 64, 2]
    recordings = [random_stream(rng, n, SENSOR, t_max=t_max) for n in sizes]
    recordings[3]["t"] = 100  # all at one timestamp, equal to times of other recordings
    recordings[4]["t"] += 1_000_000
    recordings[6]["t"] += 1_700_000_000_000_000  # epoch microseconds
    recordings[7] = random_stream(rng, 30, SENSOR, t_max=t_max, sort=False)
    return recordings


def _assert_same(got: np.ndarray, want: np.ndarray) -> None:
    assert got.dtype == want.dtype
    assert got.tolist() == want.tolist()  # same events in the same order


@pytest.mark.parametrize("factor", [2, (3, 2)])
@pytest.mark.parametrize("name", NAMES)
def test_batch_equals_one_by_one(name, factor, rng):
    transform = _case(name, factor)
    recordings = _recordings(rng)
    originals = [r.copy() for r in recordings]
    outputs = transform.batch(recordings)
    assert len(outputs) == len(recordings)
    for recording, output in zip(recordings, outputs, strict=True):
        _assert_same(output, transform(recording))
    for recording, original in zip(recordings, originals, strict=True):
        assert recording.tolist() == original.tolist()  # input untouched


@pytest.mark.parametrize("name", NAMES)
def test_batch_float_times_and_tensors(name, rng):
    """Float timestamps are not shifted (the kernel sorts the batch); tensors come back."""
    transform = _case(name, 2)
    recordings = []
    for n in (25, 0, 1, 40):
        stream = random_stream(rng, n, SENSOR, t_max=300)
        recordings.append(torch.tensor(
            np.stack([stream["x"], stream["y"], stream["t"] + 0.25, stream["p"]], 1),
            dtype=torch.float64))
    for recording, output in zip(recordings, transform.batch(recordings), strict=True):
        assert torch.equal(output, transform(recording))


def test_batch_signed_polarity_per_recording(rng):
    """Each recording keeps the polarity encoding it has alone (all-ON reads as 0/1)."""
    dtype = np.dtype([("x", "<i2"), ("y", "<i2"), ("t", "<i8"), ("p", "<i1")])
    signed = random_stream(rng, 30, SENSOR, dtype=dtype)
    all_on = signed[signed["p"] > 0]
    transform = ev.EventCount(SENSOR, factor=2, threshold=0.25)
    for recording, output in zip([signed, all_on], transform.batch([signed, all_on]),
                                 strict=True):
        _assert_same(output, transform(recording))


def test_batch_mixed_kinds(rng):
    """Recordings of different kinds each come back in their own kind."""
    stream = random_stream(rng, 50, SENSOR)
    as_tensor = torch.tensor(np.stack([stream["x"], stream["y"], stream["t"], stream["p"]], 1),
                             dtype=torch.int64)
    as_events = ev.Events.from_columns(stream["x"], stream["y"], stream["t"], stream["p"])
    transform = ev.LinearEstimation(SENSOR, factor=2, threshold=0.5)
    got = transform.batch([stream, as_tensor, as_events])
    _assert_same(got[0], transform(stream))
    assert torch.equal(got[1], transform(as_tensor))
    want = transform(as_events)
    assert all(torch.equal(a, b) for a, b in zip(got[2], want, strict=True))


@pytest.mark.parametrize("name", ["event_count", "cubic"])
def test_event_batch_keeps_device(name, device, rng):
    transform = _case(name, 2)
    recordings = [torch.from_numpy(np.stack(
        [r["x"].astype(np.int64), r["y"], r["t"], r["p"]], 1)).to(device)
        for r in _recordings(rng)]
    batch = EventBatch.from_recordings(recordings)
    out = transform.batch(batch)
    assert isinstance(out, EventBatch) and out.device == device
    for recording, part in zip(recordings, out.unbind(), strict=True):
        want = transform(recording)
        assert torch.equal(torch.stack([part.x, part.y, part.t, part.p.long()], 1), want)


def test_batch_errors_name_the_recording(rng):
    good = random_stream(rng, 5, SENSOR)
    bad = random_stream(rng, 5, (20, 20, 2))
    bad["x"][0] = 15
    with pytest.raises(ValueError, match="recording 1 of the batch: event coordinate x"):
        ev.Downsample(SENSOR, factor=2).batch([good, bad])
    with pytest.raises(ValueError, match="at least one recording"):
        ev.Downsample(SENSOR, factor=2).batch([])
    floats = good.astype([("x", "<i2"), ("y", "<i2"), ("p", "?"), ("t", "<f8")])
    with pytest.raises(ValueError, match="all have integer or all float timestamps"):
        ev.Downsample(SENSOR, factor=2).batch([good, floats])


def test_batch_of_real_recording_copies(nmnist):
    """The N-MNIST sample and shifted, cut copies of it: each as alone."""
    sensor = (34, 34, 2)
    recordings = [nmnist, nmnist[:1000].copy(), nmnist[2000:].copy(), nmnist[:0]]
    recordings[1]["t"] += 123
    for transform in (ev.EventFunnelling(sensor, factor=4), ev.CubicEstimation(sensor, factor=4)):
        for recording, output in zip(recordings, transform.batch(recordings), strict=True):
            _assert_same(output, transform(recording))


def test_dvs_dtype_round_trip(rng):
    recordings = [random_stream(rng, n, SENSOR, dtype=DVS_DTYPE) for n in (3, 9)]
    outputs = ev.EventFunnelling(SENSOR, factor=2).batch(recordings)
    assert all(o.dtype == DVS_DTYPE for o in outputs)


@pytest.mark.parametrize("reset", ["subtract", "zero", "none"])
@pytest.mark.parametrize("dt", [7, 12.5, 10_000])
def test_lif_batch_with_firing_chains(reset, dt, rng):
    """Strong weights and slow leaks: neurons keep firing through silent steps up to their own
    recording's end (tails), inhibition, a fractional dt, a dt longer than every recording."""
    transform = ev.LIFPooling(SENSOR, factor=2, dt=dt, tau=500, threshold=0.5, weight=2.0,
                           mutual_inhibition=0.5, reset_mechanism=reset)
    recordings = _recordings(rng, t_max=150)
    outputs = transform.batch(recordings)
    assert sum(len(o) for o in outputs) > 50
    for recording, output in zip(recordings, outputs, strict=True):
        _assert_same(output, transform(recording))


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.usefixtures("kernels")
def test_batch_of_empty_recordings_and_of_one(name, rng):
    transform = _case(name, 2)
    empty = random_stream(rng, 0, SENSOR)
    assert [len(out) for out in transform.batch([empty, empty.copy()])] == [0, 0]
    recording = random_stream(rng, 30, SENSOR)
    _assert_same(transform.batch([recording])[0], transform(recording))


def _sorted_recordings(rng: np.random.Generator) -> list[np.ndarray]:
    """Recordings each in time order (the batched kernels' path without stacking): empty ones,
    one event, all at one time, a recording that starts with the pixel, time and polarity its
    predecessor ends with (a repeat only if recordings were mixed), epoch clocks."""
    recordings = [random_stream(rng, n, SENSOR, t_max=60) for n in (0, 1, 90, 7, 0, 150, 40)]
    recordings[3]["t"] = 20
    recordings[6]["t"] += 1_700_000_000_000_000
    recordings[2][-1] = recordings[1][0]
    recordings[3][0] = recordings[2][-1]
    recordings[3][0]["t"] = 20
    recordings[2][-1]["t"] = 20
    recordings[2]["t"] = np.minimum(recordings[2]["t"], 20)
    recordings[2].sort(order="t", kind="stable")
    return recordings


def _funnelled(recording: np.ndarray, factor: tuple[int, int]) -> list[tuple[int, ...]]:
    """Slow reference: the first event of each distinct (x', y', t, p), in stable time order."""
    seen, out = set(), []
    for i in np.argsort(recording["t"], kind="stable"):
        x, y, t, p = (int(recording[i][k]) for k in ("x", "y", "t", "p"))
        key = (x // factor[0], y // factor[1], t, p)
        if key not in seen:
            seen.add(key)
            out.append(key)
    return out


@pytest.mark.parametrize("chunk", [None, 16])
@pytest.mark.parametrize("factor", [(2, 2), (3, 1), (1, 1)])
@pytest.mark.usefixtures("kernels")
def test_funnelling_batch_of_sorted_recordings(factor, chunk, rng, monkeypatch):
    """Recordings in time order: against a slow reference and each recording alone (small
    chunks: the pieces never split a recording's run of equal timestamps)."""
    if chunk is not None:
        monkeypatch.setattr(tensors, "CHUNK_EVENTS", chunk)
    recordings = _sorted_recordings(rng)
    assert all(bool(np.all(np.diff(r["t"]) >= 0)) for r in recordings)
    transform = ev.EventFunnelling(SENSOR, factor=factor)
    outputs = transform.batch(recordings)
    for recording, output in zip(recordings, outputs, strict=True):
        want = _funnelled(recording, factor)
        assert [(int(e["x"]), int(e["y"]), int(e["t"]), int(e["p"])) for e in output] == want
        _assert_same(output, transform(recording))
    assert sum(len(o) for o in outputs) < sum(len(r) for r in recordings)  # repeats dropped


@pytest.mark.parametrize("chunk", [None, 16])
@pytest.mark.usefixtures("kernels")
def test_event_count_batch_of_sorted_recordings(chunk, rng, monkeypatch):
    if chunk is not None:
        monkeypatch.setattr(tensors, "CHUNK_EVENTS", chunk)
    recordings = _sorted_recordings(rng)
    for factor in (2, (3, 2)):
        transform = ev.EventCount(SENSOR, factor=factor, threshold=0.25)
        outputs = transform.batch(recordings)
        assert sum(len(o) for o in outputs) > 20
        for recording, output in zip(recordings, outputs, strict=True):
            _assert_same(output, transform(recording))


@pytest.mark.usefixtures("kernels")
def test_event_count_batch_with_int32_region_ids(rng):
    """More regions in the batch than int16 holds: the region ids go to int32."""
    sensor = (64, 64, 2)  # 4,096 regions at factor 1: nine recordings need 36,864 ids
    assert region_dtype(sensor, (1, 1), 9 * 64 * 64) == torch.int32
    recordings = [random_stream(rng, 300, sensor, t_max=500) for _ in range(9)]
    recordings[8]["x"], recordings[8]["y"] = 63, 63  # the batch's last region id
    transform = ev.EventCount(sensor, factor=1, threshold=0.5)
    outputs = transform.batch(recordings)
    assert len(outputs[8]) > 0
    for recording, output in zip(recordings, outputs, strict=True):
        _assert_same(output, transform(recording))
