"""Every Python block of the README runs as a script from the repository root, offline.

Each block runs in its own process (as a user pasting it into a file would), so a block that
starts worker processes has to carry its own ``if __name__ == "__main__":`` guard.
"""

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BLOCKS = re.findall(r"^```python\n(.*?)^```", (ROOT / "README.md").read_text(encoding="utf-8"),
                    re.M | re.S)


def test_the_readme_has_python_blocks_and_stays_a_guide():
    assert len(BLOCKS) >= 4
    assert len((ROOT / "README.md").read_text(encoding="utf-8").splitlines()) <= 300


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_block_runs(index, tmp_path):
    if "import tonic" in BLOCKS[index]:
        pytest.importorskip("tonic")
    script = tmp_path / f"readme_block_{index}.py"
    script.write_text(BLOCKS[index], encoding="utf-8")
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    done = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, f"README block {index}:\n{BLOCKS[index]}\n{done.stderr[-3000:]}"


def test_the_streaming_promise_states_its_exceptions_where_it_is_made():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    promise = text[text.index("whatever the chunk sizes"):text.index("```python",
                                                                     text.index("### Streaming"))]
    promise = " ".join(promise.split())
    assert "LinearEstimation on float timestamps" in promise and "last place" in promise
    assert "the same events" in promise  # a crossing at a chunk's edge once (docs/guide.md)
    assert "compiled int64 session" in promise and "docs/guide.md#streaming" in promise
