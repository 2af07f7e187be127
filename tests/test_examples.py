"""The scripts in examples/ run from a fresh checkout, at small sizes, in their own process.

Each script checks its own results (a session's output against the whole-stream call, a
rerun keeping the cache's shards); these tests check that it ends cleanly and says so.
"""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def run_example(name: str, *args: str) -> str:
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    done = subprocess.run([sys.executable, str(ROOT / "examples" / name), *args], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout


def test_every_example_has_a_main_guard_and_a_test():
    scripts = sorted(p.name for p in (ROOT / "examples").glob("*.py"))
    assert scripts == ["live_stream.py", "preprocess_folder.py", "tonic_pipeline.py"]
    for name in scripts:
        assert 'if __name__ == "__main__":' in (ROOT / "examples" / name).read_text()


def test_tonic_pipeline_batches_frames_through_worker_processes():
    pytest.importorskip("tonic")
    out = run_example("tonic_pipeline.py", "--samples-per-class", "1", "--duration-ms", "300",
                      "--workers", "2", "--epochs", "1")
    assert "batch of frames: (8, 8, 2, 16, 16) torch.float32" in out
    assert re.search(r"test accuracy: [01]\.\d{3} \(11 recordings", out), out


def test_live_stream_sessions_equal_the_whole_stream():
    out = run_example("live_stream.py", "--duration-ms", "300", "--packet-ms", "5",
                      "--max-delay-us", "1000")
    assert "in 60 packets of 5.0 ms (0 empty)" in out
    # EventCount is causal: nothing it returns is older than the packet that returned it.
    waits = dict(re.findall(r"(\w+): .* at most (\d+) us older", out))
    assert set(waits) == {"EventCount", "LinearEstimation"}, out
    assert int(waits["EventCount"]) < 5000
    # LinearEstimation holds an event until the stream is max_delay past it: with no empty
    # packet, at most one packet plus max_delay.
    assert int(waits["LinearEstimation"]) <= 5000 + 1000


def test_preprocess_folder_writes_reads_and_resumes(tmp_path):
    out = run_example("preprocess_folder.py", "--out", str(tmp_path), "--recordings", "2",
                      "--duration-ms", "300", "--workers", "2")
    assert "6 recordings -> 2 shards" in out
    assert "first batch: frames (4, 5, 2, 16, 16), labels [0, 0, 1, 1]" in out
    assert "rerun: 2 shards kept, 0 written" in out
    assert (tmp_path / "cache" / "manifest.json").is_file()
