"""The exact part both estimators' curves start from: the regions' levels at their breakpoints.

``solver.breakpoint_levels`` gives ``n_r * M_r``'s integer part at every breakpoint: the sum of
the levels of the region's pixels there. Each pixel's level at time ``T`` is its events' signed
count up to ``T`` (ON +1, OFF -1), so the expectation is counted from the raw events.
"""

from __future__ import annotations

import numpy as np
import pytest

from evdown_torch._tensors import run_index, where_true
from evdown_torch.events import Events
from evdown_torch.transforms.functional.estimation.knots import pixel_knots, region_chunks
from evdown_torch.transforms.functional.estimation.solver import breakpoint_levels
from tests.helpers import random_stream

SENSOR = (12, 8, 2)
FACTOR = (3, 2)


@pytest.mark.parametrize("n", [1, 40, 600])
def test_breakpoint_levels_are_the_signed_event_counts_up_to_each_breakpoint(rng, n):
    arr = random_stream(rng, n, SENSOR, t_max=300)
    events = Events.from_columns(arr["x"], arr["y"], arr["t"], arr["p"])
    out_width = SENSOR[0] // FACTOR[0]
    chunk = next(region_chunks(events, factor=FACTOR, out_width=out_width, size=10 * n))
    knots = pixel_knots(chunk, factor=FACTOR, t_start=events.t[0], t_end=events.t[-1])
    bp_first_at = where_true(knots.bp_first)

    got = breakpoint_levels(knots, bp_first_at, run_index(knots.bp_first))

    region = (arr["y"] // FACTOR[1]) * out_width + arr["x"] // FACTOR[0]
    sign = np.where(arr["p"], 1, -1)
    bp_region = knots.bp_region(knots.bp_t.new_tensor(range(len(knots.bp_t)))).tolist()
    expected = [int(sign[(region == r) & (arr["t"] <= t)].sum())
                for r, t in zip(bp_region, knots.bp_t.tolist())]
    assert got.dtype == knots.level.dtype
    assert got.tolist() == expected
    assert sorted(set(bp_region)) == sorted(set(region.tolist()))  # every active region
