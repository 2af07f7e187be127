"""The benchmark harness: its inputs, timing, memory measurement and the report's structure.

Speed is not tested here (the numbers only have to be there and parse); one short run with
tiny streams exercises ``evdown bench`` end to end.
"""

from __future__ import annotations

import json
import math
import os
import re
import time

import numpy as np
import pytest

from benchmarks.goals import GOALS, evaluate_goals, goals_table
from evdown_torch.bench import inputs, lineup, measure, run
from evdown_torch.bench import report as report_module
from evdown_torch.cli import main
from evdown_torch.events import DVS_DTYPE
from evdown_torch.io import load_npy_events
from evdown_torch.transforms.registry import METHODS, make_method
from tests.conftest import NMNIST_FILE
from tests.helpers import random_stream

TONIC = lineup.tonic_available()
PEER_LABELS = list(lineup.PEERS.values()) if TONIC else []


def _tables(markdown: str) -> dict[str, list[list[dict[str, str]]]]:
    """Markdown tables by the heading above them: a list of tables of row dicts."""
    tables: dict[str, list[list[dict[str, str]]]] = {}
    heading, lines = "", markdown.splitlines()
    i = 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("#"):
            heading = line.lstrip("#").strip()
        if line.startswith("|") and i + 1 < len(lines) and lines[i + 1].startswith("|---"):
            head = [c.strip() for c in line.strip("|").split("|")]
            rows = []
            i += 2
            while i < len(lines) and lines[i].startswith("|"):
                cells = [c.strip() for c in lines[i].strip("|").split("|")]
                assert len(cells) == len(head), lines[i]
                rows.append(dict(zip(head, cells)))
                i += 1
            tables.setdefault(heading, []).append(rows)
            continue
        i += 1
    return tables


def _number(cell: str) -> float | None:
    """A numeric cell: a float, or None for the words that mark a missing figure."""
    if cell in ("n/a", "skipped"):
        return None
    return float(cell)


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    """One short benchmark run with tiny streams and one user file, through the CLI."""
    root = tmp_path_factory.mktemp("bench")
    user = root / "mine.npy"
    np.save(user, random_stream(np.random.default_rng(7), 600, (20, 10, 2), t_max=50_000))
    out = root / "out"
    code = main(["bench", "--out", str(out), "--short", "--events", "3000", "--input",
                 str(user), "--sensor-size", "20", "10", "2"])
    assert code == 0
    return out


@pytest.mark.slow
def test_report_files_are_written(report):
    assert (report / "report.md").is_file()
    data = json.loads((report / "results.json").read_text())
    assert {"plan", "machine", "inputs", "measurements"} <= set(data)
    pytest.importorskip("matplotlib")
    names = [f"scaling_{sweep}.png" for sweep in ("events", "sensor", "duration")]
    names += [f"methods_{name}.png" for name in ("gesture", "mine", "large")]
    for name in names:
        png = report / name
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert f"]({png.name})" in (report / "report.md").read_text()


@pytest.mark.slow
def test_report_speaks_the_users_language(report):
    # No issue numbers or project goals in what a user reads: those live in benchmarks/.
    text = (report / "report.md").read_text()
    assert not re.search(r"\bissues?\b", text, re.IGNORECASE)
    assert "## Goals" not in text
    assert "issue" not in (report / "results.json").read_text()


@pytest.mark.slow
def test_method_tables_have_every_method_and_peer_at_every_factor(report):
    tables = _tables((report / "report.md").read_text())
    labels = [cls.__name__ for cls in METHODS.values()] + PEER_LABELS
    expected_inputs = {"gesture": (2, 4), "mine": (2, 4), "large": (4,)}
    for name, factors in expected_inputs.items():
        [heading] = [h for h in tables if h.startswith(f"{name}:")]
        [rows] = tables[heading]
        assert sorted((r["method"], int(r["factor"])) for r in rows) == sorted(
            (label, f) for label in labels for f in factors)
        for row in rows:
            assert int(row["events in"]) > 0
            timed = _number(row["M events/s"])
            if timed is None:  # only a peer may be skipped, and it says why
                assert row["method"] in PEER_LABELS and row["note"].startswith("skipped")
                continue
            assert int(row["runs"]) >= 5
            assert _number(row["median ms"]) > 0
            assert int(row["events out"]) >= 0 and _number(row["out / in"]) >= 0
            added, total = _number(row["peak added MB"]), _number(row["peak process MB"])
            assert 0 <= added < total, row
            for label in PEER_LABELS:
                ratio = _number(row[f"x {label}"])
                assert ratio is None or ratio > 0
            if row["method"] in PEER_LABELS:  # a peer against itself
                assert _number(row[f"x {row['method']}"]) == pytest.approx(1.0)


@pytest.mark.slow
def test_sweep_tables_cover_every_candidate_and_point(report):
    tables = _tables((report / "report.md").read_text())
    labels = [cls.__name__ for cls in METHODS.values()] + PEER_LABELS
    for title in ("Cost against the number of events", "Cost against the sensor size",
                  "Cost against the recording duration"):
        rate, memory = tables[title]
        for table in (rate, memory):
            assert [r["method"] for r in table] == labels
            points = [k for k in table[0] if k != "method"]
            assert len(points) == 2
            for row in table:
                values = [_number(row[p]) for p in points]
                if row["method"] not in PEER_LABELS:
                    assert all(v is not None and v >= 0 for v in values), row


@pytest.mark.slow
def test_goals_table_names_every_measured_method_with_a_goal(report):
    results = report_module.load_results(report / "results.json")
    tables = _tables("## Goals\n\n" + goals_table(results))
    [rows] = tables["Goals"]
    assert rows == [{"issue": g["issue"], "method": g["method"], "goal": g["goal"],
                     "measured": g["measured"], "status": g["status"]}
                    for g in evaluate_goals(results)]
    goals = {(g.method, g.kind) for g in GOALS if g.method in METHODS}
    if not TONIC:
        goals.discard(("downsample", "peer"))
    assert len(rows) == len(goals)
    for row in rows:
        assert row["method"] in METHODS
        assert re.match(r"(met|missed by \d+%)", row["status"]), row
        assert "indicative" in row["status"]  # 3,000 events are not the goal's stream
        assert re.match(r"[\d.]+ (M events/s|GB)|[\d.]+x", row["measured"])


def test_an_nmnist_recording_joins_the_method_table(tmp_path):
    if not NMNIST_FILE.exists():
        pytest.skip("the N-MNIST sample is absent")
    results = run.run_benchmark(short=True, events=300, methods=["downsample"], scaling=False,
                                memory=False, nmnist=NMNIST_FILE)
    nmnist = results.input("nmnist")
    assert nmnist.sensor_size == (34, 34, 2) and nmnist.num_events == 4325
    [m2, m4] = [m for m in results.measurements if m.input == "nmnist"]
    assert (m2.factor, m4.factor) == (2, 4) and m2.events_out == m4.events_out == 4325
    with pytest.raises(ValueError, match="does not exist"):
        run.run_benchmark(short=True, nmnist=tmp_path / "none.bin")


@pytest.mark.slow
def test_inputs_table_lists_the_streams(report):
    tables = _tables((report / "report.md").read_text())
    [rows] = tables["Inputs"]
    names = {r["input"]: r for r in rows}
    assert int(names["gesture"]["events"]) == 3000 and names["gesture"]["sensor"] == "128x128"
    assert names["mine"]["sensor"] == "20x10" and int(names["mine"]["events"]) == 600
    assert names["large"]["sensor"] == "1280x720"
    assert {n.split("-")[0] for n in names} >= {"events", "sensor", "duration"}


def test_bench_settings_are_settings_of_their_methods():
    for name, settings in lineup.BENCH_SETTINGS.items():
        if name in METHODS:
            make_method(name, (34, 34, 2), 2, **settings)


def test_dvs_like_stream_is_seeded_sorted_and_inside_the_sensor():
    a = inputs.dvs_like_stream(5000, (40, 30, 2), duration_us=20_000, seed=3)
    b = inputs.dvs_like_stream(5000, (40, 30, 2), duration_us=20_000, seed=3)
    c = inputs.dvs_like_stream(5000, (40, 30, 2), duration_us=20_000, seed=4)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert a.dtype == DVS_DTYPE and len(a) == 5000
    assert (np.diff(a["t"]) >= 0).all() and a["t"].min() >= 0 and a["t"].max() < 20_000
    assert a["x"].min() >= 0 and a["x"].max() < 40 and a["y"].min() >= 0 and a["y"].max() < 30
    assert 0.3 < a["p"].mean() < 0.7
    # moving edges, not noise: events pile up on a small share of the pixels
    counts = np.bincount(a["y"].astype(int) * 40 + a["x"], minlength=1200)
    assert np.sort(counts)[::-1][:300].sum() > 0.7 * 5000
    assert len(inputs.dvs_like_stream(0, (4, 4, 2))) == 0
    later = inputs.dvs_like_stream(5000, (40, 30, 2), duration_us=20_000, seed=3, start_us=20_000)
    assert later["t"].min() >= 20_000 and later["t"].max() < 40_000
    with pytest.raises(ValueError, match="noise"):
        inputs.dvs_like_stream(10, (4, 4, 2), noise=2.0)


def test_with_pauses_keeps_order_and_bursts():
    ev = inputs.dvs_like_stream(2000, (32, 32, 2), duration_us=1000, seed=0)
    out = inputs.with_pauses(ev, 100_000, bursts=10)
    np.testing.assert_array_equal(out[["x", "y", "p"]], ev[["x", "y", "p"]])
    assert (np.diff(out["t"]) >= 0).all() and out["t"].max() < 100_000
    gaps = np.diff(out["t"])
    assert (gaps > 9000).sum() == 9  # nine pauses between ten bursts
    np.testing.assert_array_equal(gaps[gaps <= 9000], np.diff(ev["t"])[gaps <= 9000])
    with pytest.raises(ValueError, match="span"):
        inputs.with_pauses(ev, 10)


def test_read_nmnist_matches_tonic_and_handles_overflow(tmp_path):
    # two events, an overflow marker between them: the second gains 2**13 us
    raw = bytes([3, 4, 0x80 | 0x01, 0x02, 0x03, 0, 240, 0, 0, 0, 5, 6, 0x00, 0x00, 0x10])
    path = tmp_path / "two.bin"
    path.write_bytes(raw)
    ev = inputs.read_nmnist(path)
    assert ev.tolist() == [(3, 4, True, 0x010203), (5, 6, False, 0x10 + 2**13)]
    if not NMNIST_FILE.exists():
        pytest.skip("the N-MNIST sample is absent")
    ours = inputs.read_nmnist(NMNIST_FILE)
    assert len(ours) == 4325
    tonic = pytest.importorskip("tonic")
    theirs = tonic.io.read_mnist_file(str(NMNIST_FILE), dtype=tonic.datasets.NMNIST.dtype)
    for name in ("x", "y", "t", "p"):
        np.testing.assert_array_equal(ours[name].astype(np.int64), theirs[name].astype(np.int64))
    (tmp_path / "bad.bin").write_bytes(b"1234")
    with pytest.raises(ValueError, match="not an N-MNIST file"):
        inputs.read_nmnist(tmp_path / "bad.bin")


def test_load_npy_events_rejects_what_is_not_an_event_array(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        load_npy_events(tmp_path / "nope.npy")
    np.save(tmp_path / "plain.npy", np.zeros((3, 4)))
    with pytest.raises(ValueError, match="fields x, y, t, p"):
        load_npy_events(tmp_path / "plain.npy")


def test_cli_reports_a_missing_input_without_running(tmp_path, capsys):
    code = main(["bench", "--out", str(tmp_path / "o"), "--input", str(tmp_path / "no.npy")])
    assert code == 2
    assert "does not exist" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_time_call_counts_runs_and_returns_the_warm_up_result():
    calls = []
    timing, result = measure.time_call(lambda v: calls.append(v) or v * 2, 21, repeats=5)
    assert (timing.runs, result, len(calls)) == (5, 42, 6)
    assert timing.seconds >= 0 and timing.cpu_seconds >= 0
    timing, _ = measure.time_call(lambda: None, repeats=5, min_seconds=1.0, max_repeats=50)
    assert timing.runs == 50
    busy, _ = measure.time_call(lambda: sum(range(200_000)), repeats=3)
    idle, _ = measure.time_call(time.sleep, 0.02, repeats=3)
    # The loop runs on the CPU, sleeping does not. On a machine busy with other work the loop
    # gets only a share of a core, so its CPU share is compared with the sleep's, not with 1.
    assert busy.cpu_seconds > 0 and idle.seconds >= 0.02
    assert idle.cpu_seconds < 0.5 * idle.seconds
    assert busy.cpu_seconds / busy.seconds > 10 * idle.cpu_seconds / idle.seconds


def test_plan_caps_and_candidates():
    plan = run.make_plan(short=True, events=3000, repeats=7)
    assert plan.headline_events == plan.large_events == plan.sweep_events == 3000
    assert plan.events_sweep == (300, 3000) and plan.repeats == 7
    full = run.make_plan()
    assert full.events_sweep == (10_000, 100_000, 1_000_000, 10_000_000)
    assert full.large_events == 10_000_000 and full.repeats >= 5
    assert [c.name for c in lineup.candidates()][: len(METHODS)] == list(METHODS)
    with pytest.raises(ValueError, match="unknown method or peer"):
        lineup.candidates(["nope"])


def test_candidate_specs_carry_settings():
    cand = lineup.candidate("event_count:threshold=0.5")
    assert cand.name == "event_count:threshold=0.5" and not cand.peer
    assert cand.label == "EventCount (threshold=0.5)"
    assert cand.build((8, 8, 2), 2).threshold == 0.5
    assert lineup.parse_spec("a:b=x, c=(1, 2)") == ("a", {"b": "x", "c": (1, 2)})
    with pytest.raises(ValueError, match="KEY=VALUE"):
        lineup.candidate("event_count:threshold")
    with pytest.raises(ValueError, match="does not take"):
        lineup.candidate("downsample:threshold=1")
    if TONIC:
        assert lineup.candidate("tonic_integrator").peer
        with pytest.raises(ValueError, match="takes no settings"):
            lineup.candidate("tonic_downsample:x=1")


def _allocate(megabytes: int):
    """A memory job's preparation (used through its file path): the call fills an array."""
    return lambda: float(np.ones(megabytes * 125_000).sum())


@pytest.mark.slow
def test_memory_measurement_sees_the_call(tmp_path):
    n = 1_000_000
    path = tmp_path / "big.npy"
    np.save(path, inputs.dvs_like_stream(n, (128, 128, 2), duration_us=1_000_000, seed=1))
    job = lineup.candidate_job("downsample", str(path), (128, 128, 2), 4)
    jobs = [
        job,
        lineup.candidate_job("downsample", str(path), (8, 8, 2), 4),  # events outside the sensor
        measure.MemoryJob(f"{__file__}:_allocate", {"megabytes": 200}),
        measure.MemoryJob(f"{__file__}:_allocate", {"megabytes": 20}),
        measure.MemoryJob("no_colon", {}),
    ]
    forked, bad, big, little, unknown = measure.measure_memory(jobs)
    [inline] = measure.measure_memory([job], fork=False) if hasattr(os, "fork") else [forked]
    output_bytes = n * DVS_DTYPE.itemsize  # the call returns a new array this size
    for result in (forked, inline):
        assert output_bytes < result["added"] < 40 * output_bytes, result
        assert result["total"] > result["added"] + 50e6  # interpreter, torch and the input
        assert math.isfinite(result["total"]) and result["seconds"] > 0
    assert "ValueError" in bad["error"]
    assert 195e6 < big["added"] < 230e6, big
    assert big["result"] == 25_000_000.0
    assert 19e6 < little["added"] < 40e6, little
    assert "MODULE:FUNCTION" in unknown["error"]


def test_new_methods_in_the_registry_are_benchmarked(monkeypatch):
    from evdown_torch.transforms import registry
    from evdown_torch.transforms.downsample import Downsample

    monkeypatch.setitem(registry.METHODS, "zz_copy", Downsample)
    names = [c.name for c in lineup.candidates(peers=False)]
    assert names == [*METHODS]  # the same dict object, now with the new entry
    assert names[-1] == "zz_copy"
    [cand] = lineup.candidates(["zz_copy"])
    assert cand.build((8, 8, 2), 2).output_sensor_size == (4, 4, 2)


def test_cli_rejects_a_bad_method_spec(tmp_path, capsys):
    code = main(["bench", "--out", str(tmp_path / "o"), "--methods", "nope"])
    assert code == 2
    assert "unknown method or peer 'nope'" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


# --- Real-time replay (evdown bench --realtime): structure, not timing ------------------------


def test_retime_compresses_time_and_keeps_the_order(rng):
    from evdown_torch.bench import realtime

    arr = random_stream(rng, 1000, (16, 16, 2), t_max=1_000_000)
    arr["t"][0] = 0
    fast, rate = realtime.retime(arr, 25e6)
    assert rate == 25e6
    assert (np.diff(fast["t"]) >= 0).all() and fast["t"][0] == arr["t"][0]
    own = len(arr) / ((arr["t"][-1] - arr["t"][0]) * 1e-6)
    assert fast["t"][-1] == math.floor(arr["t"][-1] * own / 25e6)
    same, own_rate = realtime.retime(arr, None)
    assert same is arr and own_rate == pytest.approx(own)


def test_chunk_bounds_follow_stream_time():
    from evdown_torch.bench.realtime import chunk_bounds_us

    t = np.array([100, 150, 1099, 1100, 3200])
    # Chunks [100, 1100), [1100, 2100), [2100, 3100), [3100, 4100).
    assert chunk_bounds_us(t, 1000).tolist() == [0, 3, 4, 4, 5]


def test_replay_gives_the_batch_output_and_bounded_delays(rng):
    from evdown_torch import LinearEstimation
    from evdown_torch.bench.realtime import replay

    sensor = (16, 16, 2)
    arr = random_stream(rng, 3000, sensor, t_max=20_000)
    transform = LinearEstimation(sensor, factor=4, threshold=0.5, max_delay=300)
    result = replay(transform, arr, chunk_us=1000, label="linear", rate=1.0, lagging=True)
    chunks = math.ceil((arr["t"][-1] - arr["t"][0] + 1) / 1000)
    first_chunk = int((arr["t"] < arr["t"][0] + 1000).sum())
    last_chunk = int((arr["t"] >= arr["t"][0] + (chunks - 1) * 1000).sum())
    # Neither the warm-up chunk nor the stream's last (partial) chunk is timed.
    assert result.chunks == len(result.seconds) == chunks - 2
    assert result.events_in == len(arr) - first_chunk - last_chunk
    assert result.events_out == len(transform(arr))
    tail = int((transform(arr)["t"] >= arr["t"][-1] - 300).sum())  # left for the flush
    assert len(transform(arr)) - tail <= len(result.delays_us) <= result.events_out
    # Out with the first chunk whose last event is later than t + D (test_streaming checks
    # that exactly); measured from the end of the chunk's window, at most D plus two chunks.
    assert min(result.delays_us) >= 300 and max(result.delays_us) <= 300 + 2 * 1000
    summary = result.summary()
    assert summary["keeps_up"] == (summary["p99_s"] < 1e-3)
    assert summary["delay_us"]["max"] == max(result.delays_us)
    # Page faults are counted for each timed chunk (never negative).
    assert len(result.faults) == result.chunks and min(result.faults) >= 0
    assert min(result.faults) <= summary["median_faults"] <= max(result.faults)


def test_realtime_command_writes_a_table_for_every_method_rate_and_chunk(tmp_path, capsys):
    from evdown_torch.bench.realtime import FLOOR, REALTIME_METHODS
    from evdown_torch.transforms.functional.compiled import numba_available

    out = tmp_path / "rt"
    # 80,000 events last 3.2 ms at 25 M events/s: two timed 1 ms chunks, no 2 or 10 ms one.
    code = main(["bench", "--realtime", "--short", "--events", "80000", "--out", str(out)])
    assert code == 0
    table = (out / "realtime.md").read_text()
    rows = [line for line in table.splitlines() if line.startswith("| ") and "---" not in line]
    # The floor and the methods x rates x chunk sizes.
    assert len(rows) - 1 == (1 + len(REALTIME_METHODS)) * 2 * 3
    assert "latency budget (ms): delay + chunk + p99" in rows[0]
    data = json.loads((out / "realtime.json").read_text())
    assert {(d["method"], d["chunk_us"]) for d in data} == {
        (m, c) for m in [FLOOR, *REALTIME_METHODS] for c in (1000, 2000, 10_000)}
    fast = [d for d in data if d["rate"] == 25e6 and d["chunk_us"] == 1000 and not d["note"]]
    assert fast and all(d["chunks"] >= 1 and d["sustained_rate"] > 0 for d in fast)
    for d in fast:  # where it keeps up: the method's delay + the chunk + the p99
        if d["keeps_up"]:
            expected = (d["algorithmic_delay_us"] + 1000) * 1e-6 + d["p99_s"]
            assert d["latency_budget_s"] == pytest.approx(expected)
        else:
            assert d["latency_budget_s"] is None
    slow = [d for d in data if d["rate"] == 25e6 and d["chunk_us"] == 10_000 and not d["note"]]
    assert all(d["chunks"] == 0 and d["p99_s"] is None for d in slow)
    # Delays only for the lagging methods, and never below their max_delay (1 ms).
    assert all(d["method"] in ("linear", "cubic") and d["delay_us"]["median"] >= 1000
               for d in data if "delay_us" in d)
    skipped = {d["method"] for d in data if d["note"]}
    # Only methods without the common session (and the floor, without numba).
    assert skipped <= {"lif", "photocurrent"} | (set() if numba_available() else {FLOOR})
    printed = capsys.readouterr().out
    assert "realtime.md" in printed and "Memory allocator: " in printed


def test_the_latency_budget_is_delay_plus_chunk_plus_p99():
    from evdown_torch.bench.realtime import ReplayResult, realtime_markdown

    # p99 of [0.4, 0.5, 0.6] ms: 0.5 + 0.98 * 0.1 = 0.598 ms; + 1 ms delay + 2 ms chunk.
    kept = ReplayResult("linear", 25e6, 2000, seconds=[0.0004, 0.0005, 0.0006],
                        algorithmic_delay_us=1000.0)
    assert kept.latency_budget_s == pytest.approx(0.003598)
    behind = ReplayResult("cubic", 25e6, 1000, seconds=[0.002], algorithmic_delay_us=2000.0)
    assert behind.keeps_up is False and behind.latency_budget_s is None
    rows = [line.split(" | ") for line in realtime_markdown([kept, behind]).splitlines()[2:]]
    assert [(r[12], r[13]) for r in rows] == [("1", "3.6 |"), ("2", "falls behind |")]


def test_each_method_of_the_replay_has_the_delay_its_definition_asks():
    from evdown_torch import LinearEstimation, PhotocurrentPooling
    from evdown_torch.bench.realtime import REALTIME_METHODS, _transform

    delays = {label: _transform(label, (32, 32, 2), 4).algorithmic_delay()
              for label in REALTIME_METHODS}
    assert delays == {"downsample": 0, "funnelling": 0, "event_count": 0, "temporal": 0,
                      "linear": 1000, "cubic": 2000, "lif": 1000, "photocurrent": 0,
                      "density": 0, "poisson": 0}
    assert LinearEstimation((8, 8, 2), 2).algorithmic_delay() == math.inf
    framed = PhotocurrentPooling((8, 8, 2), 2, fps=500.0)
    assert framed.algorithmic_delay() == pytest.approx(2000)


def test_sustained_rate_scales_the_replayed_rate_to_the_p99():
    from evdown_torch.bench.realtime import ReplayResult

    r = ReplayResult("m", 2e6, 1000, seconds=[0.0001, 0.0002, 0.0004])
    # p99 by linear interpolation: 0.0002 + 0.98 * 0.0002 = 0.000396 s of a 1 ms chunk.
    assert r.sustained_rate == pytest.approx(2e6 * 1e-3 / 0.000396)
    assert r.keeps_up is True
    assert ReplayResult("m", 1e6, 1000).sustained_rate is None


def test_the_table_gives_each_rate_over_event_counts_in_the_same_run():
    from evdown_torch.bench.realtime import ReplayResult, realtime_markdown

    results = [ReplayResult("event_count", 25e6, 10_000, chunks=1, seconds=[0.008]),
               ReplayResult("linear", 25e6, 10_000, chunks=1, seconds=[0.08]),
               ReplayResult("linear", 25e6, 1000, chunks=1, seconds=[0.002]),  # no peer row
               ReplayResult("lif", 25e6, 10_000, note="no session")]
    rows = [line.split(" | ") for line in realtime_markdown(results).splitlines()[2:]]
    ratio = {(r[0].strip("| "), r[2]): r[9] for r in rows}
    assert ratio[("event_count", "10")] == "1"
    assert ratio[("linear", "10")] == "0.1"  # 10x EventCount's p99
    assert ratio[("linear", "1")] == "–"
    assert ratio[("lif", "10")] == "–"


def test_the_floor_counts_every_event_in_its_region_and_gives_the_x_floor_column(rng):
    pytest.importorskip("numba")
    from evdown_torch.bench.floor import RegionFloor
    from evdown_torch.bench.realtime import realtime_benchmark, realtime_markdown, replay

    sensor = (16, 12, 2)
    arr = random_stream(rng, 4000, sensor, t_max=20_000)
    floor = RegionFloor(sensor, (4, 3))
    session = floor.session()
    for chunk in np.array_split(arr, [0, 1, 1, 1000, 3999]):
        assert len(session(chunk)) == 0
    expected = np.bincount((arr["y"] // 3) * 4 + arr["x"] // 4, minlength=16)
    assert session.counts.tolist() == expected.tolist()
    assert len(session.flush()) == 0
    result = replay(floor, arr, chunk_us=1000, label="floor")
    assert result.events_out == 0 and result.chunks > 0
    results = realtime_benchmark(arr, sensor, factor=4, methods=["event_count"],
                                 chunks_us=(1000,), rates=(None,), max_chunks=5)
    assert [r.method for r in results] == ["floor", "event_count"]
    rows = [line.split(" | ") for line in realtime_markdown(results).splitlines()]
    assert rows[0][10] == "x floor"
    assert rows[2][0] == "| floor" and rows[2][10] == "1"
    ratio = rows[3][10]
    assert ratio == f"{results[1].sustained_rate / results[0].sustained_rate:.3g}"


def test_without_numba_the_floor_is_a_note_not_an_error(monkeypatch, rng):
    from evdown_torch.bench import floor as floor_module
    from evdown_torch.bench.realtime import realtime_benchmark

    monkeypatch.setattr(floor_module, "numba_available", lambda: False)
    results = realtime_benchmark(random_stream(rng, 500, (8, 8, 2), t_max=5000), (8, 8, 2),
                                 methods=["downsample"], chunks_us=(1000,), rates=(None,))
    assert results[0].method == "floor" and "needs numba" in results[0].note
    assert results[1].method == "downsample" and not results[1].note


def test_each_stage_has_a_progress_bar_that_counts_its_measurements(monkeypatch):
    bars = []

    class Bar:  # records what run_benchmark tells its bars
        def __init__(self, label: str, total: int) -> None:
            self.label, self.total, self.done, self.closed = label, total, 0, False
            bars.append(self)

        def update(self, n: int = 1) -> None:
            self.done += n

        def close(self) -> None:
            self.closed = True

    monkeypatch.setattr(run, "stage_bar", Bar)
    results = run.run_benchmark(short=True, events=300, methods=["downsample", "event_count"],
                                scaling=True, memory=False)
    assert [b.label for b in bars] == ["method tables", "scaling sweeps"]
    sections = [[m for m in results.measurements if (m.section == "methods") == (i == 0)]
                for i in range(2)]
    for bar, measured in zip(bars, sections, strict=True):
        assert bar.total == bar.done == len(measured) > 0 and bar.closed


def test_evaluate_and_bench_help_describe_the_command(capsys):
    for command, words in (("evaluate", "speed/accuracy trade"), ("bench", "peak memory")):
        with pytest.raises(SystemExit):
            main([command, "--help"])
        assert words in " ".join(capsys.readouterr().out.split())
