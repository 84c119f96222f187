"""bench/studies/operator_magnitudes.py against a hybrid whose operator outputs are known by hand (the edge
decoder's last layer reduced to its bias), and its rows against the mesh's own node and edge counts."""

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "bench" / "studies"))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: synthetic.py
from error_breakdown import CLASSES, node_classes
from operator_magnitudes import by_class, operator_outputs
from synthetic import make_dataset

from warpgnn.data import load_file
from warpgnn.model import TIGNN, ModelConfig
from warpgnn.port_metriplectic import N_L, N_M
from warpgnn.training import fit_normalizer


@pytest.fixture(scope="module")
def sims(tmp_path_factory):
    return load_file(make_dataset(tmp_path_factory.mktemp("om"), sims_per_file=2, steps=4) / "L5.h5")


def tiny_hybrid(sims, seed=0):
    torch.manual_seed(seed)
    model = TIGNN(ModelConfig(passes=1, latent=8))
    fit_normalizer(model, sims)
    return model


def constant_operators(sims, l_value, m_value):
    """A tiny hybrid whose edge decoder gives l_value in every l entry and m_value in every m entry."""
    model = tiny_hybrid(sims)
    last = model.decoder.delta_e.rest[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.copy_(torch.cat([torch.full((N_L,), l_value), torch.full((N_M,), m_value)]))
    return model.eval()


def test_rows_are_every_self_loop_and_edge_of_every_snapshot(sims):
    """Counts per class (on a bidirected mesh they cannot tell receivers from senders: the last test does)."""
    sim = sims[0]
    lm, cls = operator_outputs(tiny_hybrid(sims), sim)
    top, node_cls = sim.topology, node_classes(sim)
    assert lm.shape == (sim.steps * (top.n_nodes + len(top.receivers)), N_L + N_M)
    for k in range(len(CLASSES)):
        expected = (node_cls == k).sum() + (node_cls[top.receivers.numpy()] == k).sum()
        assert (cls == k).sum() == sim.steps * expected


def test_statistics_of_known_outputs(sims):
    stats = by_class(constant_operators(sims, -2.0, 0.25), sims)
    rows = sum(s.steps * (s.topology.n_nodes + len(s.topology.receivers)) for s in sims)
    everything = stats["all"]
    assert everything["rows"] == rows
    assert sum(stats[c]["rows"] for c in CLASSES if c in stats) == rows
    assert everything["entry_share_above_1"] == pytest.approx(N_L / (N_L + N_M))  # |-2| counts, 0.25 does not
    assert everything["entry_percentiles"][50] == pytest.approx(0.25)  # 78 of 144 entries are 0.25
    assert everything["entry_percentiles"][99] == pytest.approx(2.0)
    assert everything["row_max_median"] == pytest.approx(2.0)
    assert everything["row_share_above"] == {"0.5": 1.0, "1.0": 1.0}
    small = by_class(constant_operators(sims, 0.75, 0.1), sims)["all"]
    assert small["row_share_above"] == {"0.5": 1.0, "1.0": 0.0} and small["entry_share_above_1"] == 0.0
    assert np.isclose(small["row_max_median"], 0.75)


def test_each_edge_row_is_classed_by_its_receiving_node(sims):
    """With the edge decoder blind to the edge latent and the sender, an edge's output is its receiver's
    self-loop output: every distinct output must then carry one class (a sender's class would differ on
    edges between classes, which the synthetic box has)."""
    model = tiny_hybrid(sims, seed=1)
    with torch.no_grad():
        model.decoder.delta_e.edge.weight.zero_()
        model.decoder.delta_e.sender.weight.zero_()
    lm, cls = operator_outputs(model.eval(), sims[0])
    classes_of_value = {}
    for row, c in zip(np.round(lm[:, :4], 9).tolist(), cls.tolist()):
        classes_of_value.setdefault(tuple(row), set()).add(c)
    assert len(classes_of_value) > 1 and all(len(c) == 1 for c in classes_of_value.values())
    top = sims[0].topology
    crossing = node_classes(sims[0])[top.senders.numpy()] != node_classes(sims[0])[top.receivers.numpy()]
    assert crossing.any()  # the check above can tell a receiver's class from a sender's
