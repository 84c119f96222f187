"""Simulations as tensors, the paper's splits, and training batches with noise (and rotation) augmentation.

Splits (paper section 2.3): L1-L4 train (760 simulations in the paper preset); every fifth
simulation of L5 (20%) validates for early stopping; Test is all of L5 (the paper evaluates
on all 190, validation ones included); Extra and Extra* are their own files.
"""

from __future__ import annotations

import fnmatch
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import h5py
import numpy as np
import torch

from . import dataset
from .errors import InputError
from .graphs import NODE_FREE, Topology, batch, make_topology

TRAIN_FILES = ("L1", "L2", "L3", "L4")
TEST_FILE = "L5"
VALIDATION_EVERY = 5  # 20% of L5


@dataclass
class Simulation:
    name: str  # "<file stem>/<sim name>"
    topology: Topology  # kept on the CPU: batches are stacked there, then copied once
    z: torch.Tensor  # (S+1, N, 12) states q, v, sigma
    u: torch.Tensor  # (S+1, K, 3) displacement of each tool
    dt: float  # between snapshots
    mean_edge: float  # mean rest edge length, the scale of the position noise

    @property
    def steps(self) -> int:
        return self.z.shape[0] - 1


def sim_names(path: Path) -> list[str]:
    return sorted(dataset.simulation_names(path))


def load_file(path, device="cpu", names=None) -> list[Simulation]:
    """Simulations of one dataset file (all of them, or ``names``), fields checked."""
    path = Path(path)
    mesh = dataset.read_mesh(path)
    with h5py.File(path, "r") as f:
        if "dt" not in f.attrs:
            raise InputError(f"{path}: attribute 'dt' missing")
        dt = float(f.attrs["dt"])
    names = sim_names(path) if names is None else names
    if not names:
        raise InputError(f"{path}: no simulations")
    edges = mesh.edges()
    mean_edge = float(np.linalg.norm(mesh.nodes[edges[:, 0]] - mesh.nodes[edges[:, 1]], axis=1).mean())
    sims = []
    for name in names:
        rec = dataset.read_simulation(path, name)
        footprint = ("footprint_nodes", "footprint_load", "footprint_weight")
        tip = [rec[k] for k in footprint] if all(k in rec for k in footprint) else [None] * 3
        top = make_topology(mesh, rec["loaded"], *tip, edges=edges, shared=sims[0].topology if sims else None)
        z = torch.as_tensor(dataset.state(rec), dtype=torch.float32, device=device)
        sims.append(Simulation(f"{path.stem}/{name}", top, z,
                               torch.as_tensor(rec["u"], dtype=torch.float32, device=device), dt, mean_edge))
    return sims


def file_path(data_dir: Path, stem: str) -> Path:
    path = Path(data_dir) / f"{stem}.h5"
    if not path.is_file():
        raise InputError(f"{data_dir}: dataset file {stem}.h5 missing")
    return path


def dataset_stems(data_dir, patterns) -> list[str]:
    """The stems of the folder's dataset files that names or globs in ``patterns`` pick, in their order, each once;
    a pattern that picks nothing ends in one line."""
    stems = sorted(p.stem for p in Path(data_dir).glob("*.h5"))
    out = []
    for pattern in patterns:
        if not any(c in pattern for c in "*?["):  # a plain name: file_path says if it is missing
            out += [pattern] if pattern not in out else []
            continue
        picked = [s for s in stems if fnmatch.fnmatchcase(s, pattern)]
        if not picked:
            raise InputError(f"{data_dir}: no dataset file matches {pattern!r}")
        out += [s for s in picked if s not in out]
    return out


def preset_train_sets(data_dir) -> tuple[str, ...]:
    """The training files the folder's preset names in its manifest (`generate` writes it; the wide preset's
    W*), else L1..L4."""
    for manifest in sorted(Path(data_dir).glob("manifest*.json")):
        sets = json.loads(manifest.read_text()).get("train_sets")
        if sets:
            return tuple(sets)
    return TRAIN_FILES


def load_splits(data_dir, device="cpu", train_fraction: float = 1.0, seed: int = 0, train_files=None,
                val_file: str = TEST_FILE, val_every: int = VALIDATION_EVERY) -> dict[str, list[Simulation]]:
    """Train (L1-L4, optionally a random ``train_fraction`` of them) and validation (20% of L5), or those of
    other files of the folder (``train_files``: names or globs; None: the folder's preset's)."""
    train = []
    train_files = dataset_stems(data_dir, train_files or preset_train_sets(data_dir))
    for stem in train_files:
        path = file_path(data_dir, stem)
        names = sim_names(path)
        if train_fraction < 1.0:
            rng = np.random.default_rng([seed, list(train_files).index(stem)])
            keep = max(1, round(train_fraction * len(names)))
            names = sorted(rng.choice(names, keep, replace=False).tolist())
        train += load_file(path, device, names)
    test = file_path(data_dir, val_file)
    val = load_file(test, device, sim_names(test)[::val_every])
    return {"train": train, "val": val}


@dataclass
class Batch:
    topology: Topology
    z: torch.Tensor  # (N, 12) input state (noisy when augmenting)
    u_now: torch.Tensor  # (K, 3)
    u_next: torch.Tensor  # (K, 3)
    z_next: torch.Tensor  # (N, 12) the ground truth's state after the trained step
    dt: torch.Tensor  # (N, 1) snapshot interval of each node's simulation (1 on padding)
    node_mask: torch.Tensor | None = None  # (N,) 1 on real nodes, 0 on padding (padded batches only)
    # pushforward training: the tools' displacements (lead + 1, K, 3) along the ``lead`` steps the
    # network takes from ``z`` first, and which nodes each of those steps moves (lead, N): a sample
    # whose step t has fewer than ``lead`` snapshots before it starts at t = 0 and sits out the first ones
    lead_u: torch.Tensor | None = None
    lead_active: torch.Tensor | None = None

    @property
    def zdot(self) -> torch.Tensor:
        """The target: (z(t+1) - z) / dt, from the state the network is given (noisy, or its own)."""
        return (self.z_next - self.z) / self.dt


def _counts(top: Topology) -> tuple[int, ...]:
    """What a padded shape must hold: (nodes, mesh edges, tools, actuator edges, prescribed nodes)."""
    return top.n_nodes, top.senders.numel(), top.n_tools, top.act_senders.numel(), top.prescribed.numel()


@dataclass(frozen=True)
class BatchShape:
    """The fixed sizes of padded batches. A CUDA graph replays one shape, while snapshots of
    different meshes and tool counts stack to different sizes: padding every batch to the
    largest a batch of ``batch_size`` snapshots can reach lets one graph serve them all
    (``fitting``), and a short ladder of shapes (``ladder``) lets a few graphs serve them with
    far less padding.

    Padding is inert by construction: the padded edges of both edge sets run between one
    extra *sink* node and one extra *sink* tool, so their messages reach only the sink, and
    the loss masks the padded nodes out (LayerNorm and the MLPs act row by row; nothing else
    mixes nodes)."""

    nodes: int
    edges: int
    tools: int
    actuator_edges: int
    prescribed: int

    @classmethod
    def holding(cls, counts) -> BatchShape:
        """The shape for ``counts`` real (nodes, edges, tools, actuator edges, prescribed), plus the sinks."""
        n, e, k, a, p = (int(c) for c in counts)
        return cls(nodes=n + 1, edges=e, tools=k + 1, actuator_edges=a, prescribed=p)

    @property
    def capacity(self) -> tuple[int, ...]:
        """The real (nodes, edges, tools, actuator edges, prescribed) it holds, the sinks aside."""
        return self.nodes - 1, self.edges, self.tools - 1, self.actuator_edges, self.prescribed

    def fits(self, top: Topology) -> bool:
        return all(c <= m for c, m in zip(_counts(top), self.capacity))

    @classmethod
    def fitting(cls, sims: list[Simulation], batch_size: int) -> BatchShape:
        """The largest batch of ``batch_size`` snapshots: each size of the largest simulation, times batch_size."""
        return cls.holding(batch_size * np.array([_counts(s.topology) for s in sims]).max(0))

    @classmethod
    def ladder(cls, sims: list[Simulation], batch_size: int, quantiles=(0.5, 0.999), draws: int = 4000
               ) -> tuple[BatchShape, ...]:
        """Shapes from small to large, each size at these quantiles of random batches (``draws``
        batches of ``batch_size`` snapshots drawn as an epoch draws them, with a fixed seed), then
        ``fitting``, which every batch fits. A batch is padded to the first it fits
        (``make_batch``). On the paper's training set (1-3 tools on four meshes) one shape pads an
        average batch by 24 % in nodes, 27 % in mesh edges and 86 % in actuator edges; the
        0.999 rung alone would pad 9 %, 10 % and 23 %. Rungs that the smallest batch (``smallest``)
        does not fit are left out, so that every rung can be recorded before training."""
        counts = np.array([_counts(s.topology) for s in sims])
        weights = np.array([s.steps for s in sims], dtype=float)
        picks = np.random.default_rng(0).choice(len(sims), (draws, batch_size), p=weights / weights.sum())
        totals = counts[picks].sum(1)
        least = counts[smallest(sims)] * batch_size
        rungs = [cls.holding(np.quantile(totals, q, axis=0, method="higher")) for q in quantiles]
        rungs = [r for r in rungs if (np.array(r.capacity) >= least).all()] + [cls.fitting(sims, batch_size)]
        return tuple(sorted(set(rungs), key=lambda r: r.capacity))  # quantiles grow in every size together


def smallest(sims: list[Simulation]) -> int:
    """The simulation with the fewest nodes, tools and edges (in that order): a batch of its
    snapshots alone fits every rung of a ``BatchShape.ladder``."""
    return min(range(len(sims)), key=lambda i: (sims[i].topology.n_nodes, sims[i].topology.n_tools, _counts(sims[i].topology)))


def first_fitting(shapes: BatchShape | Sequence[BatchShape], top: Topology) -> BatchShape:
    """The first of ``shapes`` (smallest first) that ``top`` fits."""
    for shape in (shapes,) if isinstance(shapes, BatchShape) else shapes:
        if shape.fits(top):
            return shape
    raise ValueError(f"batch of (nodes, edges, tools, actuator edges, prescribed) {_counts(top)} exceeds {shapes}")


def _grow(x: torch.Tensor, size: int, fill, dim: int = 0) -> torch.Tensor:
    """``x`` extended along axis ``dim`` to ``size`` entries of ``fill``."""
    pad = list(x.shape)
    pad[dim] = size - x.shape[dim]
    return torch.cat([x, x.new_full(pad, fill)], dim)


def pad_topology(top: Topology, shape: BatchShape) -> Topology:
    n = top.n_nodes
    shape = first_fitting(shape, top)
    sink, sink_tool = shape.nodes - 1, shape.tools - 1
    return Topology(
        rest=_grow(top.rest, shape.nodes, 0.0), senders=_grow(top.senders, shape.edges, sink),
        receivers=_grow(top.receivers, shape.edges, sink), node_type=_grow(top.node_type, shape.nodes, NODE_FREE),
        loaded=_grow(top.loaded, shape.tools, sink), act_senders=_grow(top.act_senders, shape.actuator_edges, sink_tool),
        act_receivers=_grow(top.act_receivers, shape.actuator_edges, sink),
        prescribed=_grow(top.prescribed, shape.prescribed, sink),
        prescribed_tool=_grow(top.prescribed_tool, shape.prescribed, sink_tool),
        prescribed_weight=_grow(top.prescribed_weight, shape.prescribed, 0.0),
        graph_sizes=torch.cat([top.graph_sizes, torch.tensor([shape.nodes - n])]))


# Voigt order xx yy zz xy yz xz (DESIGN.md): the symmetric tensor's entry (i, j) is component VOIGT[i][j]
VOIGT = ((0, 3, 5), (3, 1, 4), (5, 4, 2))
VOIGT_ROWS, VOIGT_COLS = (0, 1, 2, 0, 1, 0), (0, 1, 2, 1, 2, 2)


def rotate_states(z: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """States (N, 12) rotated by each node's (N, 3, 3) rotation: q and v as vectors (about the
    origin), sigma (Voigt) as a tensor, R sigma R^T."""
    q, v = (torch.einsum("nij,nj->ni", R, z[:, c:c + 3]) for c in (0, 3))
    sigma = R @ z[:, 6:][:, VOIGT] @ R.transpose(1, 2)
    return torch.cat([q, v, sigma[:, VOIGT_ROWS, VOIGT_COLS]], -1)


def vertical_rotations(angles: torch.Tensor, mirror: torch.Tensor | None = None) -> torch.Tensor:
    """(S, 3, 3) rotations by ``angles`` about the z axis; with ``mirror`` (S signs, +-1) each after
    x -> mirror x, R diag(mirror, 1, 1): a reflection through a vertical plane where the sign is -1 (the
    mirrored livers of bench/studies/rotation_probe.py)."""
    c, s, zero, one = angles.cos(), angles.sin(), torch.zeros_like(angles), torch.ones_like(angles)
    m = one if mirror is None else mirror.to(angles)
    return torch.stack([c * m, -s, zero, s * m, c, zero, zero, zero, one], -1).reshape(-1, 3, 3)


def quadratic_basis(x: torch.Tensor) -> torch.Tensor:
    """(N, 10) monomials of the coordinates x up to degree 2: 1, x, y, z, x^2, y^2, z^2, xy, yz, zx
    (the first column spans the uniform fields, the first four the affine ones)."""
    return torch.cat([torch.ones_like(x[:, :1]), x, x.square(), x * x.roll(-1, 1)], 1)


def smooth_displacements(rest: torch.Tensor, sizes: torch.Tensor, weight: torch.Tensor, amplitude: torch.Tensor,
                         coefficients: torch.Tensor) -> torch.Tensor:
    """(N, 3) quadratic displacement fields of the rest coordinates, one per stacked graph (``sizes``
    nodes each): sum_k coefficients[g, k] phi_k(x) over the ``quadratic_basis`` phi of the graph's
    coordinates centred and scaled to unit RMS radius, then scaled to RMS
    ``amplitude[g]`` over the nodes of ``weight`` (1: counted and displaced, 0: left in place)."""
    graph_of = torch.repeat_interleave(torch.arange(len(sizes), device=rest.device), sizes.to(rest.device))
    n = sizes.to(rest.device, rest.dtype)[:, None]
    x = rest - (torch.zeros(len(sizes), 3, device=rest.device, dtype=rest.dtype).index_add(0, graph_of, rest) / n)[graph_of]
    radius = (torch.zeros(len(sizes), device=rest.device, dtype=rest.dtype).index_add(0, graph_of, x.square().sum(1))
              / n[:, 0]).sqrt()
    x = x / radius[graph_of, None]
    d = torch.einsum("nk,nkc->nc", quadratic_basis(x), coefficients.to(rest)[graph_of]) * weight[:, None]
    rms = (torch.zeros_like(radius).index_add(0, graph_of, d.square().sum(1))
           / torch.zeros_like(radius).index_add(0, graph_of, 3 * weight).clamp_min(1)).sqrt()
    return d * (amplitude.to(rest) / rms.clamp_min(1e-30))[graph_of, None]


def make_batch(sims: list[Simulation], samples, noise_q: float = 0.0, noise_v: float = 0.0,
               generator: torch.Generator | None = None, shape: BatchShape | Sequence[BatchShape] | None = None,
               lead: int = 0, noise_v_add: float = 0.0, rotate: bool = False, noise_smooth: float = 0.0,
               noise_smooth_gamma: float = 1.0, noise_smooth_velocity: float = 0.0) -> Batch:
    """Stack the steps t -> t+1 of ``samples`` = [(simulation index, t), ...] into one graph,
    padded to ``shape`` if given, or to the first of several shapes that it fits (the real nodes,
    their noise and targets are the same either way). The target is built from the state the
    network is given, so it leads back from any noise to the ground truth's next state.

    Noise (paper appendix A): q' = q + mean_edge * eps * noise_q on free nodes, v' = v (1 + eps
    noise_v), sigma' = sigma (1 + eps noise_v), eps ~ U(-1, 1).
    ``noise_v_add``: v' += mean_edge / dt * eps' * noise_v_add on free nodes (own draws); relative
    noise vanishes where v does (once the tools stop), additive noise does not.
    ``rotate`` turns each sample as a whole (rest shape, states, target, tools' path) by its own random
    angle about the vertical z axis: without gravity and with an isotropic material a turned simulation
    is another exact one (the fixed visceral face stays a z plane).
    ``noise_smooth``: the free nodes' positions move by a random quadratic field of the rest coordinates
    (``smooth_displacements``) of RMS mean_edge * noise_smooth * U(0, 1): per-node noise leaves alone the
    smooth error a rollout carries. The target takes back the share ``noise_smooth_gamma`` of what is left
    of it per step the network takes (MeshGraphNets' noise_gamma), and its velocity carries the share
    ``noise_smooth_velocity`` of that take-back: v - S gamma (1 - gamma)^k d / dt after k lead-in steps.
    Every draw comes in a fixed order (the paper's noise, the additive noise, the angles, the smooth field),
    each only when its option is on, so turning one on leaves the earlier ones' streams as they were.
    With ``lead`` > 0 (pushforward training) ``z`` is the (noisy) state min(lead, t) snapshots
    before t, ``lead_u`` the tools' path from there to t (its first entries repeat the start when
    t < lead) and ``lead_active`` which nodes each lead step moves (none of the padding).
    """
    picked = [(sims[i], max(t - lead, 0)) for i, t in samples]  # where each sample's lead-in starts
    device = picked[0][0].z.device
    top = batch([s.topology for s, _ in picked])
    real_nodes = top.n_nodes
    shape = None if shape is None else first_fitting(shape, top)
    top = (top if shape is None else pad_topology(top, shape)).to(device)
    z = torch.cat([s.z[t] for s, t in picked])
    z_next = torch.cat([sims[i].z[t + 1] for i, t in samples])
    sizes = torch.tensor([s.topology.n_nodes for s, _ in picked])
    # per-node columns: dt, then the position-noise amplitude and 12 U(-1, 1) draws, then (noise_v_add)
    # the additive velocity amplitude and 3 more draws
    host = [torch.tensor([s.dt for s, _ in picked]).repeat_interleave(sizes)[:, None]]
    noisy = noise_q > 0 or noise_v > 0 or noise_v_add > 0
    if noisy:
        host += [torch.tensor([s.mean_edge * noise_q for s, _ in picked]).repeat_interleave(sizes)[:, None],
                 torch.rand((len(z), 12), generator=generator) * 2 - 1]
    if noise_v_add > 0:  # drawn only then: the paper's noise keeps its random stream
        host += [torch.tensor([s.mean_edge / s.dt * noise_v_add for s, _ in picked]).repeat_interleave(sizes)[:, None],
                 torch.rand((len(z), 3), generator=generator) * 2 - 1]
    host = torch.cat(host, 1).float()
    host = (host.pin_memory() if device.type == "cuda" else host).to(device, non_blocking=True)
    dt = host[:, :1]
    # the tools' path t - lead .. t + 1 of each sample, held at its start before t = 0
    u = torch.stack([torch.cat([sims[i].u[max(t - lead + j, 0)] for i, t in samples]) for j in range(lead + 2)])
    if rotate:
        R = vertical_rotations(torch.rand(len(samples), generator=generator, dtype=torch.float64) * 2 * math.pi)
        R_node = R.repeat_interleave(sizes, 0).to(device, z.dtype)
        z, z_next = rotate_states(z, R_node), rotate_states(z_next, R_node)
        rest = torch.einsum("nij,nj->ni", R_node.to(top.rest.dtype), top.rest[:real_nodes])
        top = replace(top, rest=torch.cat([rest, top.rest[real_nodes:]]))
        R_tool = R.repeat_interleave(torch.tensor([len(s.topology.loaded) for s, _ in picked]), 0).to(device, u.dtype)
        u = torch.einsum("kij,lkj->lki", R_tool, u)
    free = (top.node_type[:real_nodes] == NODE_FREE)[:, None].to(z.dtype)
    if noisy:
        amp, eps = host[:, 1:2], host[:, 2:14]
        z = torch.cat([z[:, :3] + free * amp * eps[:, :3], z[:, 3:] * (1 + eps[:, 3:] * noise_v)], -1)
        if noise_v_add > 0:
            z[:, 3:6] += free * host[:, 14:15] * host[:, 15:18]
    active = None
    if lead:  # lead step j moves a sample's nodes once its path has begun (j >= lead - t)
        first = torch.tensor([max(lead - t, 0) for _, t in samples]).repeat_interleave(sizes)
        active = (torch.arange(lead)[:, None] >= first[None]).to(device)
    if noise_smooth > 0:  # drawn last: the other noises' and the angles' streams stay as they were
        coefficients = torch.randn((len(samples), 10, 3), generator=generator, dtype=torch.float64)
        amplitude = torch.tensor([s.mean_edge * noise_smooth for s, _ in picked], dtype=torch.float64)
        amplitude = amplitude * torch.rand(len(samples), generator=generator, dtype=torch.float64)
        d = smooth_displacements(top.rest[:real_nodes], sizes, free[:, 0], amplitude, coefficients).to(z.dtype)
        z = torch.cat([z[:, :3] + d, z[:, 3:]], -1)
        led = torch.as_tensor(active.sum(0) if lead else 0, device=device, dtype=z.dtype).reshape(-1, 1)  # lead-in steps
        left = (1 - noise_smooth_gamma) ** led * d  # what is left of it when the trained step starts
        q_next, v_next = z_next[:, :3] + (1 - noise_smooth_gamma) * left, z_next[:, 3:6]
        if noise_smooth_velocity:
            v_next = v_next - noise_smooth_velocity * noise_smooth_gamma * left / dt.to(z.dtype)  # (float32 dt)
        z_next = torch.cat([q_next, v_next, z_next[:, 6:]], -1)
    if shape is None:
        return Batch(top, z, u[-2], u[-1], z_next, dt, lead_u=u[:-1] if lead else None, lead_active=active)
    mask = _grow(torch.ones(real_nodes, device=device), shape.nodes, 0.0)
    u = _grow(u, shape.tools, 0.0, dim=1)
    if active is not None:
        active = _grow(active, shape.nodes, False, dim=1)
    return Batch(top, _grow(z, shape.nodes, 0.0), u[-2], u[-1], _grow(z_next, shape.nodes, 0.0),
                 _grow(dt, shape.nodes, 1.0), mask, lead_u=u[:-1] if lead else None, lead_active=active)


def all_samples(sims: list[Simulation]) -> list[tuple[int, int]]:
    """Every step t -> t+1 of every simulation."""
    return [(i, t) for i, s in enumerate(sims) for t in range(s.steps)]
