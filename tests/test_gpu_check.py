"""The GPU check's CPU half (benchmarks/gpu_check.py): tiny batches, the report's content."""

from __future__ import annotations

import json

import pytest

from benchmarks import gpu_check
from evdown_torch.collate import EventBatch
from evdown_torch.events import Events
from evdown_torch.transforms.registry import METHODS


def test_parse_pytest_summary():
    output = "tests/a.py ..F\n=== short test summary ===\n2 failed, 14 passed, 1 error in 3.1s\n"
    assert gpu_check.parse_pytest_summary(output) == {"passed": 14, "failed": 2, "errors": 1}
    assert gpu_check.parse_pytest_summary("5 passed, 300 deselected, 2 warnings in 9s") == {
        "passed": 5, "deselected": 300, "warnings": 2}
    assert gpu_check.parse_pytest_summary("no summary here") == {}


def test_tests_ok():
    assert gpu_check.tests_ok({}, cuda=True)
    assert gpu_check.tests_ok({"returncode": 0}, cuda=True)
    # pytest's 5 means nothing was selected: expected without CUDA, a failure with it.
    assert gpu_check.tests_ok({"returncode": 5}, cuda=False)
    assert not gpu_check.tests_ok({"returncode": 5}, cuda=True)
    assert not gpu_check.tests_ok({"returncode": 1}, cuda=False)
    assert not gpu_check.tests_ok({"returncode": None}, cuda=False)  # timed out


def test_same_batch_tells_outputs_apart():
    batch = gpu_check.TINY_WORKLOADS[0].batch()
    assert gpu_check.same_batch(batch, batch.to("cpu"))
    x, y, t, p = (c.clone() for c in batch.events)
    t[-1] += 1
    other = EventBatch(Events(x, y, t, p), batch.lengths)
    assert not gpu_check.same_batch(batch, other)
    moved = EventBatch(batch.events, (batch.lengths[0] - 1, batch.lengths[1] + 1,
                                                *batch.lengths[2:]))
    assert not gpu_check.same_batch(batch, moved)


def test_gpu_check_cpu_half_writes_its_report(tmp_path, capsys):
    # The whole entry point on the CPU ("device" side on the CPU too), tiny sizes, with the
    # tests step running one small real test file instead of the CUDA tests.
    rc = gpu_check.main(["--out", str(tmp_path), "--device", "cpu", "--tiny", "--repeats", "1",
                         "--pytest-args", "tests/test_text.py"])
    assert rc == 0
    report = json.loads((tmp_path / "gpu_check.json").read_text())
    markdown = (tmp_path / "gpu_check.md").read_text()
    assert report["ok"] is True
    assert report["environment"]["device"] == "cpu"
    assert report["tests"]["returncode"] == 0
    assert report["tests"]["counts"]["passed"] > 0
    assert "failed" not in report["tests"]["counts"]
    rows = report["benchmark"]
    # Every method on both workloads, measured (nothing skipped), each output equal to the
    # CPU's (the same kernel ran on both sides).
    assert {(r["workload"], r["method"]) for r in rows} == {
        (w.name, m) for w in gpu_check.TINY_WORKLOADS for m in METHODS}
    for r in rows:
        assert r["skipped"] == ""
        assert r["equal"] is True
        assert r["exact"] == (r["method"] in gpu_check.EXACT_METHODS)
        workload = next(w for w in gpu_check.TINY_WORKLOADS if w.name == r["workload"])
        assert r["events_in"] == workload.recordings * workload.events
        assert r["events_out_cpu"] == r["events_out_device"] > 0
        assert r["cpu_ms"] > 0 and r["device_ms"] > 0
        assert r["speedup"] == pytest.approx(r["cpu_ms"] / r["device_ms"])
        assert f"| {r['workload']} | {r['method']} |" in markdown
    assert "no CUDA" in markdown and "Result: **pass**" in markdown
    assert "wrote" in capsys.readouterr().out


def test_gpu_check_fails_when_an_exact_method_differs(tmp_path, monkeypatch):
    # Outputs that differ fail the check for an exact method, not for a float one.
    monkeypatch.setattr(gpu_check, "same_batch", lambda a, b: False)
    args = ["--out", str(tmp_path), "--device", "cpu", "--tiny", "--repeats", "1",
            "--skip-tests"]
    assert gpu_check.main([*args, "--methods", "lif"]) == 0
    assert gpu_check.main([*args, "--methods", "event_count", "lif"]) == 1
    report = json.loads((tmp_path / "gpu_check.json").read_text())
    assert report["ok"] is False and report["tests"] == {}
    assert {r["method"]: r["equal"] for r in report["benchmark"]} == {
        "event_count": False, "lif": False}
    markdown = (tmp_path / "gpu_check.md").read_text()
    assert "| nmnist | event_count |" in markdown and "| NO | yes |" in markdown
    assert "Result: **FAIL**" in markdown and "Not run (`--skip-tests`)" in markdown


def test_gpu_check_skips_what_the_budget_leaves_no_time_for(tmp_path):
    # A deadline already past: every measurement is listed as skipped, none is run.
    rows = gpu_check.run_benchmark(gpu_check.TINY_WORKLOADS[:1], ["downsample", "lif"],
                                   gpu_check.torch.device("cpu"), 1, deadline=0.0)
    assert [(r["method"], r["skipped"]) for r in rows] == [
        ("downsample", "time budget"), ("lif", "time budget")]


def test_gpu_check_refuses_cuda_without_cuda(tmp_path):
    if gpu_check.torch.cuda.is_available():
        pytest.skip("CUDA is present")
    with pytest.raises(SystemExit):
        gpu_check.main(["--out", str(tmp_path), "--device", "cuda", "--skip-tests"])
