"""The guide's section on event budgets runs as a script, offline, as a user would paste it."""

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
GUIDE = (ROOT / "docs" / "guide.md").read_text(encoding="utf-8")


def test_the_event_budget_example_runs_and_meets_its_peak(tmp_path):
    section = GUIDE.split("\n## Event budgets")[1].split("\n## ")[0]
    blocks = re.findall(r"^```python\n(.*?)^```", section, re.M | re.S)
    assert len(blocks) == 1
    for name in ("calibrate", "calibration", "BudgetTarget", "window_rates", "RateLimiter"):
        assert re.search(rf"^from evdown_torch[\w.]* import .*\b{name}\b", blocks[0], re.M)
    script = tmp_path / "budgets.py"
    script.write_text(blocks[0], encoding="utf-8")
    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    done = subprocess.run([sys.executable, str(script)], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    peak = int(re.search(r"peak ([\d,]+) events/s", done.stdout)[1].replace(",", ""))
    assert peak <= 100_000  # at most 100 events in any 1 ms
    assert int(re.search(r"the limiter dropped (\d+) events", done.stdout)[1]) > 0
