"""How a trained hybrid builds its rate: zdot = L dE (reversible) + M dS (irreversible), each part's RMS
beside the true rate's, from the true states of a data file (no noise), in standardised units, by node
class (error_breakdown.py's: tool tip, fixed face, free within 2 cm of a tool, free far field), by
phase (ramp: the tools move; hold: they stand) and by group (q, v, sigma). Also the one-step error of
the sum and of the reversible part alone: what M dS adds to the fit. Parts much larger than their sum
cancel each other, a rate built as a small difference of large terms. A vanilla network, which has no
parts, gets its target and error only: the same cells, its peer's one-step error.

    python bench/studies/generic_parts.py DATA_FILE.h5 CHECKPOINT.pt [...] --json OUT.json
        --device "..." --command "..."
"""

import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import provenance
from error_breakdown import (  # beside this script
    CLASSES,
    node_classes,
    ramp_steps,
    true_states,
)

from warpgnn.graphs import GROUPS

PHASES = ("ramp", "hold")
TERMS = ("target", "reversible", "irreversible", "error", "error_reversible_only")


def terms(model, sim) -> tuple[dict, np.ndarray, np.ndarray]:
    """All snapshots of one simulation stacked: each term of TERMS per node (rows, 12), standardised (a vanilla
    network's target and error only); each row's node class and phase index."""
    b = true_states(sim)
    target = b.zdot / model.normalizer.zdot_scale
    with torch.no_grad():
        if model.config.kind == "vanilla":
            rate = model(b.topology, b.z, b.u_now, b.u_next).zdot_standardized
            out = {"target": target, "error": rate - target}
        else:
            x, e = model.latents(b.topology, b.z, b.u_now, b.u_next)
            rev, irr = model.decoder.parts(x, e, b.topology.senders, b.topology.receivers)
            out = {"target": target, "reversible": rev, "irreversible": irr, "error": rev + irr - target,
                   "error_reversible_only": rev - target}
    phase = np.repeat(np.arange(sim.steps) >= ramp_steps(sim), sim.topology.n_nodes).astype(int)
    return {k: v.numpy() for k, v in out.items()}, np.tile(node_classes(sim), sim.steps), phase


def rms_table(model, sims) -> dict:
    """{class: {phase: {group: {term: RMS}}}} over all snapshots of ``sims``, and each cell's row count."""
    sq, rows = {}, {}
    for sim in sims:
        parts, cls, phase = terms(model, sim)
        for k, name in enumerate(CLASSES):
            for p, ph in enumerate(PHASES):
                mask = (cls == k) & (phase == p)
                rows[name, ph] = rows.get((name, ph), 0) + int(mask.sum())
                for group, cols in GROUPS.items():
                    for term, values in parts.items():
                        key = (name, ph, group, term)
                        sq[key] = sq.get(key, 0.0) + float(np.square(values[mask][:, cols]).sum())
    present = [t for t in TERMS if any(key[3] == t for key in sq)]
    return {name: {ph: {"rows": rows[name, ph]} | {
        group: {term: float(np.sqrt(sq[name, ph, group, term] / (rows[name, ph] * (cols.stop - cols.start))))
                for term in present} for group, cols in GROUPS.items()}
        for ph in PHASES if rows[name, ph]} for name in CLASSES}


def measure(name, model, sims) -> dict:
    table = rms_table(model, sims)
    for cls in ("free_near", "free_far"):
        for ph, cell in table[cls].items():
            print(f"{name} {cls:9s} {ph}: " + "; ".join(
                f"{g} " + " ".join(f"{t[:3]} {v:.3f}" for t, v in cell[g].items()) for g in GROUPS))
    return {"classes": table}


if __name__ == "__main__":
    provenance.run_hybrid_probe("generic_parts", measure, vanilla_too=True, units="standardised (zdot_scale)")
