"""bench/studies/generic_parts.py: its cells partition every node of every snapshot once, its error terms add up to the
network's own one-step error, and a hybrid without dissipation (B = 0) has no irreversible part; a vanilla network gets
the same cells, its target and error only."""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench" / "studies"))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: synthetic.py
from error_breakdown import CLASSES, node_classes
from generic_parts import PHASES, rms_table
from synthetic import make_dataset

from warpgnn.data import load_file, make_batch
from warpgnn.graphs import GROUPS
from warpgnn.model import TIGNN, ModelConfig
from warpgnn.port_metriplectic import N_L
from warpgnn.training import fit_normalizer


@pytest.fixture(scope="module")
def sims(tmp_path_factory):
    return load_file(make_dataset(tmp_path_factory.mktemp("gp"), sims_per_file=2, steps=4) / "L5.h5")


def tiny_hybrid(sims):
    torch.manual_seed(0)
    model = TIGNN(ModelConfig(passes=1, latent=8))
    fit_normalizer(model, sims)
    return model


def whole(table, group, term) -> tuple[float, int]:
    """Mean square of ``term`` over every cell of ``table`` (weighted by its rows) and the rows in all."""
    cells = [c for cls in table.values() for c in cls.values()]
    rows = sum(c["rows"] for c in cells)
    return sum(c[group][term] ** 2 * c["rows"] for c in cells) / rows, rows


def test_cells_cover_every_row_once_and_add_up_to_the_one_step_error(sims):
    model = tiny_hybrid(sims)
    table = rms_table(model, sims)
    counts = np.bincount(np.concatenate([node_classes(s) for s in sims]), minlength=len(CLASSES))
    for k, name in enumerate(CLASSES):
        assert sum(c["rows"] for c in table[name].values()) == counts[k] * sims[0].steps
    assert {ph for cls in table.values() for ph in cls} == set(PHASES)  # 4 snapshots: 2 of ramp, 2 of hold
    for group, cols in GROUPS.items():
        errors, targets = [], []
        for sim in sims:
            b = make_batch([sim], [(0, t) for t in range(sim.steps)])
            with torch.no_grad():
                pred = model(b.topology, b.z, b.u_now, b.u_next)
            target = b.zdot / model.normalizer.zdot_scale
            errors.append((pred.zdot_standardized - target)[:, cols].numpy())
            targets.append(target[:, cols].numpy())
        for term, values in (("error", errors), ("target", targets)):
            mean_square, rows = whole(table, group, term)
            assert rows == sum(len(v) for v in values)
            assert mean_square == pytest.approx(np.square(np.concatenate(values)).mean(), rel=1e-5)


def test_without_dissipation_the_rate_is_all_reversible(sims):
    model = tiny_hybrid(sims)
    last = model.decoder.delta_e.rest[-1]
    with torch.no_grad():  # every m output 0: B = 0, so M = B B^T = 0
        last.weight[N_L:] = 0.0
        last.bias[N_L:] = 0.0
    for cls in rms_table(model, sims).values():
        for cell in cls.values():
            for group in GROUPS:
                assert cell[group]["irreversible"] == 0.0
                assert cell[group]["error"] == pytest.approx(cell[group]["error_reversible_only"], rel=1e-6)
                assert cell[group]["reversible"] > 0.0


def test_a_vanilla_network_gets_target_and_error_in_the_same_cells(sims):
    torch.manual_seed(0)
    vanilla = TIGNN(ModelConfig(kind="vanilla", passes=1, latent=8))
    fit_normalizer(vanilla, sims)
    table, reference = rms_table(vanilla, sims), rms_table(tiny_hybrid(sims), sims)
    errors = []
    for sim in sims:
        b = make_batch([sim], [(0, t) for t in range(sim.steps)])
        with torch.no_grad():
            errors.append((vanilla(b.topology, b.z, b.u_now, b.u_next).zdot_standardized
                           - b.zdot / vanilla.normalizer.zdot_scale).numpy())
    for group, cols in GROUPS.items():
        mean_square, _ = whole(table, group, "error")
        assert mean_square == pytest.approx(np.square(np.concatenate(errors)[:, cols]).mean(), rel=1e-5)
    for name, cls in table.items():
        for ph, cell in cls.items():
            assert cell["rows"] == reference[name][ph]["rows"]
            for group in GROUPS:
                assert set(cell[group]) == {"target", "error"}
                assert cell[group]["target"] == pytest.approx(reference[name][ph][group]["target"], rel=1e-6)
