"""The classifier's sanity checks (b) to (d) of the trade study, on the shipped configs.

Check (a), a superset of events never scoring significantly below its random subset, is a
statistical test of each run (``evaluation.analysis.sanity_check``, tested in
test_statistics.py and end to end in test_evaluate.py).
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from evdown_torch.evaluation.classifier import count_scale, draw_training_set, model_for
from evdown_torch.evaluation.config import load_config
from evdown_torch.evaluation.plan import pair

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


@pytest.mark.parametrize("name", ["quick", "full"])
def test_b_every_factor_reaches_the_first_spiking_layer_whole(name):
    # The former grid of 16 pooled x2 and x4 (64x64, 32x32) to 16x16 before the first spike.
    config = load_config(CONFIGS / f"{name}.toml")
    for factor in config.methods.all_factors:
        fx, fy = pair(factor)
        size = (128 // fx, 128 // fy)
        model = model_for(config, size, 11)
        assert model.stem is None, f"x{fx} is pooled by a stem of stride {model.stem_stride}"


def test_c_dense_and_sparse_inputs_get_the_same_energy():
    g = torch.Generator().manual_seed(0)
    dense = torch.poisson(torch.full((6, 12, 2, 8, 8), 20.0), generator=g)
    sparse = (torch.rand(dense.shape, generator=g) < 0.05).float()  # a thinned subset
    for counts in (dense, sparse):
        x = torch.cat([counts, torch.zeros_like(counts)], dim=2)
        x[:, :, :2] /= count_scale(x)
        assert float(x[:, :, :2].square().mean().sqrt()) == pytest.approx(1.0, rel=1e-6)
    # with the counts encoding the input does not depend on a uniform change of event rate
    x = torch.cat([dense, dense], dim=2)
    y = torch.cat([3 * dense, dense], dim=2)
    assert torch.allclose(x[:, :, :2] / count_scale(x), y[:, :, :2] / count_scale(y))
    for name in ("quick", "full", "dvsgesture"):
        training = load_config(CONFIGS / f"{name}.toml").training
        assert training.normalise and training.encoding == "counts"


def test_d_seed_draws_leave_the_validation_recordings_out():
    labels = torch.arange(198) % 11
    for seed in range(5):
        rows = draw_training_set(labels, 132, seed, exclude=33)
        assert len(rows) == 132 and int(rows.min()) >= 33
        assert torch.bincount(labels[rows], minlength=11).tolist() == [12] * 11
    a, b = (draw_training_set(labels, 132, s) for s in (0, 1))
    assert not torch.equal(a, b)  # each seed its own draw
    assert torch.equal(draw_training_set(labels, 0, 0, exclude=33), torch.arange(33, 198))


def test_plan_adds_native_outputs_and_the_tonic_peer_with_its_matched_control():
    from evdown_torch.evaluation.cells import CONTROL, TONIC, Cell
    from evdown_torch.evaluation.config import parse_config
    from evdown_torch.evaluation.plan import delay_of, plan

    config = parse_config({"methods": {"include": ["event_count"], "factors": [4],
                                       "budgets": [1.0], "native": True, "tonic_peer": True,
                                       "full_resolution": False}})
    labels = [(p.cell.label, delay_of(p.cell)) for p in plan(config)]
    assert labels == [("event_count x4 @ 1", "0"), ("event_count x4", "0"),
                      ("tonic integrator x4", "1 ms"),
                      ("control (matched to tonic integrator) x4", "0"), ("control x4 @ 1", "0")]
    with pytest.raises(ValueError, match="only a control without a budget"):
        Cell(CONTROL, (4, 4), 0.5, matches=TONIC)
    with pytest.raises(ValueError, match="only a control without a budget"):
        Cell("event_count", (4, 4), matches=TONIC)


def test_tonic_peer_row_is_tonics_event_downsampling():
    tonic = pytest.importorskip("tonic")
    import numpy as np

    from evdown_torch.evaluation.cells import TONIC, Cell
    from evdown_torch.events import DVS_DTYPE, to_events

    rng = np.random.default_rng(0)
    ev = np.zeros(3000, DVS_DTYPE)
    ev["x"], ev["y"] = rng.integers(0, 32, 3000), rng.integers(0, 32, 3000)
    ev["t"], ev["p"] = np.sort(rng.integers(0, 50_000, 3000)), rng.random(3000) < 0.5
    peer = Cell(TONIC, (4, 4)).transform((32, 32, 2))
    out = peer.kernel(to_events(ev, (32, 32, 2))[0])
    expected = tonic.transforms.EventDownsampling(
        sensor_size=(32, 32, 2), target_size=(8, 8), dt=1.0, downsampling_method="integrator",
        noise_threshold=1)(ev)
    assert out.num_events == len(expected) > 0
    for name, column in zip("xytp", out):
        assert np.array_equal(column.numpy(), expected[name].astype(column.numpy().dtype))


def test_peers_join_each_primary_factor_at_its_budget_as_exploratory_rows():
    from evdown_torch.evaluation.config import parse_config
    from evdown_torch.evaluation.plan import plan

    config = parse_config({"methods": {
        "include": ["event_count"], "factors": [4], "budgets": [0.5],
        "primary": ["event_count"], "primary_factors": [4, 8], "primary_budget": 1.0,
        "peers": ["density", "poisson"], "sanity": False, "full_resolution": False},
        "training": {"primary_seeds": 3, "control_seeds": 3, "seeds": [0, 1]}})
    rows = [(p.cell.label, p.role, p.seeds) for p in plan(config)]
    assert ("density x4 @ 1", "exploratory", (0, 1)) in rows
    assert ("poisson x8 @ 1", "exploratory", (0, 1)) in rows
    assert not any(label.startswith(("density", "poisson")) and "@ 0.5" in label
                   for label, _, _ in rows)
    for bad, message in ((["downsample"], "not a method with a budget"),
                         (["nope"], "not a method with a budget")):
        with pytest.raises(ValueError, match=message):
            parse_config({"methods": {"primary": ["event_count"], "primary_factors": [4],
                                      "peers": bad}})
    with pytest.raises(ValueError, match="methods.peers needs methods.primary_factors"):
        parse_config({"methods": {"peers": ["density"]}})
