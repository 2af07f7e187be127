"""The plot tests need matplotlib (skipped without it) and draw on the Agg backend."""

from __future__ import annotations

import pytest

matplotlib = pytest.importorskip("matplotlib")
matplotlib.use("Agg")
