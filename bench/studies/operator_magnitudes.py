"""How large a trained hybrid's operator entries are: the raw outputs l, m of its edge decoder on every
self-loop and mesh edge, from the true states of a data file, by the class of the receiving node
(error_breakdown.py's: tool tip, fixed face, free within 2 cm of a tool, free far field). It says where a
bound on the entries would act: a tanh, as the paper group's public code has, changes an entry by more
than 4 % only beyond |0.35| and halves it near |2| (that option measured no gain and left the model after
commit ae2f903).

    python bench/studies/operator_magnitudes.py DATA_FILE.h5 CHECKPOINT.pt [...] --json OUT.json
        --device "..." --command "..."
"""

import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance
from error_breakdown import CLASSES, node_classes, true_states  # beside this script

ROW_THRESHOLDS = (0.5, 1.0)  # |entry| marks: shares of rows (edges, self-loops) holding an entry beyond each


def operator_outputs(model, sim) -> tuple[np.ndarray, np.ndarray]:
    """All snapshots of one simulation stacked: the raw (l, m) of every self-loop and mesh edge, (rows, 144),
    and the class of each row's receiving node."""
    b = true_states(sim)
    with torch.no_grad():
        x, e = model.latents(b.topology, b.z, b.u_now, b.u_next)
        lm_self, lm_edge = model.decoder.operator_outputs(x, e, b.topology.senders, b.topology.receivers)
    cls = np.tile(node_classes(sim), sim.steps)
    return (np.concatenate([lm_self.numpy(), lm_edge.numpy()]),
            np.concatenate([cls, cls[b.topology.receivers.numpy()]]))


def statistics(lm: np.ndarray) -> dict:
    """Percentiles of |entry|, the share of entries beyond 1, and per row its largest |entry|."""
    entries = np.abs(lm)
    row_max = entries.max(1)
    return {"rows": len(lm), "entry_percentiles": {p: float(np.percentile(entries, p)) for p in (50, 90, 99, 99.9)},
            "entry_share_above_1": float((entries > 1).mean()), "row_max_median": float(np.median(row_max)),
            "row_share_above": {str(t): float((row_max > t).mean()) for t in ROW_THRESHOLDS}}


def by_class(model, sims) -> dict:
    rows, classes = zip(*(operator_outputs(model, s) for s in sims))
    lm, cls = np.concatenate(rows), np.concatenate(classes)
    return {"all": statistics(lm)} | {name: statistics(lm[cls == k])
                                      for k, name in enumerate(CLASSES) if (cls == k).any()}


def measure(name, model, sims) -> dict:
    classes = by_class(model, sims)
    for cls, st in classes.items():
        print(f"{name} {cls:9s} rows {st['rows']:7d}: |entry| median {st['entry_percentiles'][50]:.3f}, "
              f"99% {st['entry_percentiles'][99]:.3f}; rows' largest entry median {st['row_max_median']:.3f}, "
              f"beyond 0.5 / 1: {st['row_share_above']['0.5']:.3f} / {st['row_share_above']['1.0']:.3f}")
    return {"classes": classes}


if __name__ == "__main__":
    provenance.run_hybrid_probe("operator_magnitudes", measure)
