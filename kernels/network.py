"""The forward step of a TIGNN in Warp kernels, in the style of NVIDIA Warp's examples: every buffer
is allocated in __init__, ``forward()`` / ``step()`` only launch (recorded launches, replayed), so a
whole step can be captured once as a CUDA graph (``capture()``) and replayed.

    net = Network(model, topology, device="cuda:0")
    net.set_inputs(z, u_now, u_next, dt)      # copies into net.z, net.u_now, net.u_next, net.dt
    net.forward()                              # net.zdot, net.zdot_std, [net.degeneracy, net.entropy], net.z_next
    net.step()                                 # forward, then z <- z_next (a rollout: set u, step, ...)

Launches per step: encoders 1 (the raw features computed there; with K chunks at F <= 64, a Network's
pick for large graphs, a features launch before: Spec.features_in_encoder), 2 per pass, then the hybrid's
decoder and GENERIC tail 1 (Euler and boundary conditions included: decoders.hybrid_step on receiver groups,
small graphs; on large ones, or where a node has as many incoming edges as a tile has rows, the decoder fields 1
and the tail 1); the vanilla's decoder and tail run in its last node pass. ``step()`` adds one device copy. On
small graphs 2 P + 2 kernels (hybrid) or 2 P + 1 (vanilla), at F = 128 one more (the mesh-edge rows' encoder a
launch of its own: Network's edge_encoder).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from . import (
    decoders,
    features,
    generic_tail,
    integrate,
    message_passing,
    register_decoder,
    register_edges,
    register_nodes,
    rollout_graph,
    shipped,
)
from .graph import build
from .pdl import overlap_launches
from .spec import (
    FEATURE_WIDTH,
    N_GRAD,
    NODE_ROWS,
    STATE,
    Spec,
    edge_products,
    k_chunk_for,
    max_shared_of,
    node_rows_for,
    threads_for,
    tile_rows_for,
)
from .tiles import row_view
from .weights import pack


def build_kernels(spec: Spec) -> None:
    """Create every kernel of ``spec`` before any launch: they share one Warp module a block size (Spec.modules),
    each compiled once."""
    for module in (features, decoders, generic_tail, integrate, rollout_graph):
        module.kernels(spec)
    message_passing.encoder_kernel(spec)
    if spec.edge_warpgroups:  # its module (block size) holds the register edge pass and mesh-edge encoder alone
        register_edges.edge_registers_kernel(spec)
        register_edges.encoder_registers_kernel(spec)
    else:
        message_passing.edge_encoder_kernel(spec)
        message_passing.edge_kernel(spec)
    if spec.node_warpgroups:
        register_nodes.node_registers_kernel(spec)
    if spec.decoder_warpgroups:
        register_decoder.decoder_registers_kernel(spec)
    for decode in (0, message_passing.DECODE_FIELDS, message_passing.DECODE_STATE):
        message_passing.node_kernel(spec, decode)
    for module in spec.modules:
        wp.get_module(module).options["enable_mathdx_gemm"] = spec.gemm == "mathdx"  # part of the module's hash


def load_sm90a(spec: Spec, device, block_dim: int) -> None:
    """Build (or find in Warp's cache) and load ``spec``'s modules for sm_90a, the wgmma products' target: Warp
    builds for the device's plain architecture unless its (process-wide) cuda_arch_suffix says otherwise, so it is
    set around these loads only (shipped.arch_suffix). A launch then finds each module loaded."""
    if device.arch != 90:
        raise ValueError(f"wgmma products run on sm_90 GPUs (H100, H200), not sm_{device.arch}")
    with shipped.arch_suffix(spec):
        for module, dim in shipped.modules_of(spec, block_dim):
            module.load(device, dim)


def default_block_dim(device) -> int:
    """Threads a block of the tile kernels: shipped.BLOCK_DIM (128) on CUDA (every launch the same, so one build a
    module, the one kernels/aot ships), one on the CPU (which runs one unless wp.config.enable_cpu_blocks)."""
    return shipped.BLOCK_DIM if device.is_cuda else 1


def _as_warp(x, device):
    """A Warp view of a torch tensor (zero-copy where it can be), a Warp array, or array-like data."""
    if isinstance(x, wp.array):
        return x
    try:
        import torch
        if isinstance(x, torch.Tensor):
            return wp.from_torch(x.detach().float().contiguous())
    except ImportError:  # pragma: no cover
        pass
    return wp.array(np.ascontiguousarray(x, np.float32), dtype=float, device=device)


class Network:
    def __init__(self, model, topology, device=None, tile_rows: int | None = None, block_dim: int | None = None,
                 k_chunk: int | None = None, weights=None, node_rows: int | None = None, gemm: str = Spec.gemm,
                 threads: dict | None = None, edge_rows: int | None = None, edge_gemm: str | None = None,
                 edge_kernels: tuple | None = None, receiver_groups: bool | None = None,
                 split_products: bool | None = None, edge_encoder: bool | None = None,
                 edge_warpgroups: int | None = None, node_warpgroups: int | None = None,
                 decoder_warpgroups: int | None = None):
        """``model``: a warpgnn TIGNN (its config and weights are read once); ``topology``: a
        warpgnn.graphs.Topology, one simulation or a stacked batch. ``tile_rows``, ``node_rows``, ``k_chunk``,
        ``gemm``, ``edge_rows``, ``edge_gemm``, ``edge_kernels``: the kernels' Spec (node_rows and k_chunk None: by the
        graph's size, spec.node_rows_for and spec.k_chunk_for; the edge products None: by the GPU and the graph's size,
        spec.edge_products_for; tile_rows None: by those, spec.tile_rows_for; the shapes kernels/aot ships).
        ``block_dim``: threads a block of the tile kernels (default_block_dim); ``threads``: {kernel name: threads a
        block} of those whose CUDA launches take another (Spec.threads; None: by the K chunk, spec.threads_for).
        ``weights``: the model already packed on ``device`` (weights.pack), so Networks of many topologies share one
        copy.
        ``receiver_groups``: the hybrid decoder and tail in one launch on receiver-owned tiles (decoders.hybrid_step)
        where every node's incoming edges and self-loop fit a tile; None: on small graphs (a node tile an SM at most,
        not Spec.many_blocks: where blocks do not queue for the SMs; measured there only). ``split_products``: the
        encoder launch's pass-0 node products, a block for each (F, F) column block after the first (recomputing the
        node tile's two layers) instead of one chain of three a node tile; None: with whole weights (small graphs at
        F <= 64). Not at F = 128 (K chunks, node tiles of 8): there the encoder took 49.8 -> 51.7 us at batch 1, its
        12-pass step 626.8 -> 628.5 (bench/results/warp_vanilla_last_products_h200.json). ``edge_encoder``: the
        mesh-edge rows' encoder in a launch of its own on the edge pass's tiles and products
        (message_passing.edge_encoder_kernel); None: where the edge pass runs on tensor cores with K chunks and the
        encoder computes the features (F = 128 on small graphs on sm_90). ``edge_warpgroups``: the edge pass with each
        64-row tile in a warpgroup's registers, this many a block (Spec.edge_warpgroups; kernels/register_edges.py);
        None: by the GPU and the graph's size. ``node_warpgroups``: the node passes (the vanilla's last excepted)
        likewise, this many warpgroups a resident block (Spec.node_warpgroups; kernels/register_nodes.py); None: by
        those. ``decoder_warpgroups``: the hybrid decoder's fields likewise (Spec.decoder_warpgroups;
        kernels/register_decoder.py; where receiver groups do not take the decoder); None: by those."""
        self.device = wp.get_device(device)
        self.weights = w = weights if weights is not None else pack(model, self.device)
        if not node_rows:  # by the graph's size, a divisor of tile_rows where given
            node_rows = node_rows_for(topology.n_nodes, self.device.sm_count if self.device.is_cuda else 0, w.latent,
                                      max_shared_of(self.device))
            if tile_rows:
                node_rows = next(n for n in (node_rows, NODE_ROWS[0], tile_rows) if tile_rows % n == 0)
        tiles_per_sm = -(-topology.n_nodes // node_rows) / self.device.sm_count if self.device.is_cuda else 0
        small = node_rows == NODE_ROWS[0] and tiles_per_sm <= 1  # a node tile an SM at most
        if k_chunk is None:
            k_chunk = k_chunk_for(node_rows, w.latent, max_shared_of(self.device), tiles_per_sm)
        arch = self.device.arch if self.device.is_cuda else None
        # None: by the GPU and the graph's size
        edge = edge_products(edge_rows, edge_gemm, k_chunk, w.latent, arch, small, edge_kernels, tiles_per_sm,
                             tile_rows or Spec.tile_rows, edge_warpgroups, node_warpgroups, node_rows,
                             decoder_warpgroups)
        tile_rows = tile_rows or tile_rows_for(node_rows, w.latent, edge)
        threads = threads_for(k_chunk, w.latent, self.device.is_cuda, edge, small) if threads is None else threads
        self.spec = Spec(w.latent, tile_rows, node_rows, k_chunk, gemm, threads=tuple(dict(threads).items()), **edge)
        build_kernels(self.spec)
        self.block_dim = block_dim or default_block_dim(self.device)
        self.shipped_module = shipped.load(self.spec, self.device, self.block_dim)  # else Warp compiles it
        if self.spec.sm90a and self.device.is_cuda and not self.shipped_module:
            load_sm90a(self.spec, self.device, self.block_dim)
        self.split_products = self.spec.kc == w.latent if split_products is None else split_products
        # where measured faster (H200, L5, batch 1; bench/results/warp_edge_encoder_h200.json): F = 128, 12 passes,
        # vanilla / hybrid 598.2 / 626.1 -> 592.6 / 624.4 us (the encoder 49.5 -> 40-43 us beside the mesh edges'
        # 20 us); not with whole weights (F = 64): 52.9 / 117.7 -> 59.8 / 124.4 us at 1 / 5 passes, the encoder's
        # other rows alone still 15.5 us (its node rows' chain, not the mesh edges' blocks, bounds it) and the two
        # launches not overlapping enough to gain
        # with the edge pass in registers (Spec.edge_warpgroups), the mesh-edge encoder on its tiles, from the features
        # launch's rows (register_edges.encoder_registers_kernel), where the node pass runs in registers too (the large
        # graphs': spec.edge_products_for); on the smaller ones the encoder's launch alone was faster (H200, L5,
        # 5-pass hybrid: batch 2 155.7 against 160.0 us, 4 227.7 against 234.3; warp_register_nodes_h200.json)
        tensor = self.spec.edges("edge_pass").gemm == "wgmma" and self.spec.features_in_encoder
        registers = bool(self.spec.edge_warpgroups)
        large = registers and bool(self.spec.node_warpgroups) and not self.spec.features_in_encoder
        picked = large or (tensor and self.spec.kc != w.latent)
        self.edge_encoder = picked if edge_encoder is None else edge_encoder
        if self.edge_encoder and registers and self.spec.features_in_encoder:
            raise ValueError("edge_encoder: with the register edge pass, only where a features launch computes the "
                             "features (not Spec.features_in_encoder)")
        if self.edge_encoder and not registers and not self.spec.features_in_encoder:
            raise ValueError("edge_encoder: only where the encoder computes the features (Spec.features_in_encoder)")
        hybrid = w.kind == "hybrid"
        groups = small and not self.spec.many_blocks if receiver_groups is None else receiver_groups
        self.graph = build(topology, tile_rows, w.actuator_graphs, hybrid, self.device, self.spec.edge_tile,
                           self.spec.edges("hybrid_fields").tile_rows if groups and hybrid else 0)
        self.layout = lay = self.graph.layout
        n, k, F = lay.n_nodes, topology.n_tools, w.latent

        def zeros(*shape):
            return wp.zeros(shape, dtype=float, device=self.device)

        # inputs
        self.z, self.u_now, self.u_next = zeros(n, STATE), zeros(max(k, 1), 3), zeros(max(k, 1), 3)
        self.dt = zeros(n)
        self.n_tools = k
        # scratch: features (where a launch computes them: Spec.features_in_encoder) and latents of every row, node
        # (and tool) products, decoder fields
        self.feat = zeros(1 if self.spec.features_in_encoder else lay.rows, FEATURE_WIDTH)  # 1: a placeholder
        self.feat_groups = row_view(self.feat, FEATURE_WIDTH)  # the same rows, 4 floats an item (kernels.features)
        self.lat = zeros(lay.rows, F)
        self.lat_rows = row_view(self.lat, F)  # the same rows as vectors, for the node pass's CSR sums
        self.products = zeros(lay.nodes_pad + w.passes * lay.tools_pad, 3 * F)
        self.product_rows = row_view(self.products, F)  # as vectors, for the edge MLPs' gathers
        self.self_loop = w.self_loop if hybrid else zeros(1, F)
        # the hybrid's (dE, dS) a node, port terms L dE + M dS a mesh edge and self-loop, and each node's
        # per-component shares of its degeneracy residual and entropy production (generic_tail; in shared memory
        # where the tail runs in the decoder's blocks: receiver groups)
        self.grads = zeros(lay.nodes_pad, N_GRAD) if hybrid else None
        apart = hybrid and not self.graph.groups
        self.ports = zeros(lay.edges_pad + lay.self_pad, STATE) if apart else None
        self.node_terms = zeros(lay.self_pad, 2 * STATE) if apart else None
        # the last node pass's decoder MLP: the hybrid's delta_v into grads, or the vanilla's decoder (grads unused)
        self.node_decoder_args = ((w.dv_b1, w.dv_w2, w.dv_b2, self.grads) if hybrid
                                  else (w.vd_b1, w.vd_w2, w.vd_b2, zeros(1, 1)))
        # outputs
        self.zdot, self.zdot_std, self.z_next = zeros(n, STATE), zeros(n, STATE), zeros(n, STATE)
        self.degeneracy = zeros(n) if hybrid else None
        self.entropy = zeros(n) if hybrid else None
        self.tail = generic_tail.tail(self)  # what the decoders' last step reads and writes, for their launches

        self._launches = (features.launches(self) + message_passing.launches(self)
                          + decoders.launches(self) + generic_tail.launches(self))
        self._graphs = []  # CUDA graphs of forward and step, once captured

    @property
    def mesh_edges_in_registers(self) -> bool:
        """The mesh-edge rows encoded on the register edge pass's tiles (register_edges.encoder_registers_kernel),
        which read their 8 features alone."""
        return bool(self.edge_encoder and self.spec.edge_warpgroups)

    # ----------------------------------------------------------------------------- inputs and outputs
    def block_dim_of(self, kernel: str) -> int:
        """Threads a block of ``kernel``'s launches (Spec.threads, else block_dim)."""
        return self.spec.threads_of(kernel) or self.block_dim

    @property
    def n_launches(self) -> int:
        return len(self._launches)

    def set_inputs(self, z=None, u_now=None, u_next=None, dt=None) -> None:
        """Copy the state (N, 12), the tools' displacements (K, 3) at t and t + dt and the step dt
        (a number, or one per node: (N,) or (N, 1)) into the input buffers; None leaves one as it is."""
        for buf, x in ((self.z, z), (self.u_now, u_now), (self.u_next, u_next)):
            if x is None or (buf is not self.z and self.n_tools == 0):
                continue
            a = _as_warp(x, self.device)
            if a.shape != buf.shape:
                raise ValueError(f"expected shape {buf.shape}, got {a.shape}")
            wp.copy(buf, a)
        if dt is None:
            return
        size = dt.size if isinstance(dt, wp.array) else dt.numel() if hasattr(dt, "numel") else np.size(dt)
        if size > 1:
            a = _as_warp(dt, self.device)
            if a.size != self.layout.n_nodes:
                raise ValueError(f"dt: one number or one per node ({self.layout.n_nodes}), got {a.shape}")
            wp.copy(self.dt, a.reshape((self.layout.n_nodes,)))
        else:
            self.dt.fill_(float(dt))

    def outputs(self) -> dict:
        """The output buffers as torch tensors (zero-copy views: the next step overwrites them)."""
        names = ("zdot", "zdot_std", "degeneracy", "entropy", "z_next")
        return {k: wp.to_torch(getattr(self, k)) for k in names if getattr(self, k) is not None}

    # ----------------------------------------------------------------------------- running
    def _launch_all(self) -> None:
        for launch in self._launches:
            launch.launch()

    def forward(self) -> None:
        """TIGNN.forward at (z, u_now, u_next), and z(t + dt) = TIGNN.step's state into z_next."""
        if self._graphs:
            wp.capture_launch(self._graphs[0])
        else:
            self._launch_all()

    def step(self) -> None:
        """forward, then advance: z <- z_next (set u_now, u_next before each step of a rollout)."""
        if self._graphs:
            wp.capture_launch(self._graphs[1])
        else:
            self._launch_all()
            wp.copy(self.z, self.z_next)

    def integrate(self, zdot, out) -> None:
        """Euler and the boundary conditions with a given zdot (N, 12) into ``out`` (TIGNN.step's zdot=)."""
        integrate.launch(self, _as_warp(zdot, self.device), out)

    def overlap(self, graph, plain_into: tuple[str, ...] = ()) -> int:
        """Make the captured ``graph``'s launches overlap (kernels/pdl.py), except those into the kernels named in
        ``plain_into`` (kernel names, as edge_pass: studies), which start once the launch before has ended. Every
        launch overlapping is the fastest measured: H200, L5, F = 64, 5 / 12 passes 132.3 / 271.9 us against 139.9 /
        291.5 with the edge passes plain (whole weights, the edge pass at two blocks an SM: message_passing), F = 128
        12 passes 706.9 against 723.4 us (K chunks) (bench/results/warp_edge_occupancy_h200.json,
        warp_pdl_modes_h200.json). Returns the edges changed."""
        if not self.device.is_cuda:
            return 0
        functions = frozenset(int(launch.hooks.forward) for launch in self._launches  # keys: factory__locals__name
                              if launch.kernel.key.rsplit("__", 1)[-1] in plain_into)
        return overlap_launches(graph, self.device, functions)

    def captured(self, record, overlap: bool = True, plain_into: tuple[str, ...] = ()) -> wp.Graph:
        """``record()`` (launches and device copies only) captured as a CUDA graph, its launches overlapping where
        ``overlap`` (Network.overlap, ``plain_into`` as there)."""
        with wp.ScopedCapture(device=self.device) as cap:
            record()
        if overlap:
            self.overlap(cap.graph, plain_into)
        return cap.graph

    def capture(self, overlap: bool = True, plain_into: tuple[str, ...] = ()) -> None:
        """On CUDA: record forward() and step() once each as a CUDA graph, replayed from then on
        (a launch costs ~25 us from Python and ~1.3 us inside a graph on the H100: calibration notes).
        The modules were loaded when the launches were recorded, so nothing compiles while capturing.
        ``overlap``: consecutive launches overlap where the GPU allows it (kernels/pdl.py), except those into
        the kernels named in ``plain_into`` (Network.overlap)."""
        if not self.device.is_cuda:
            return
        self._graphs = []

        def advanced():
            self._launch_all()
            wp.copy(self.z, self.z_next)

        self._graphs = [self.captured(record, overlap, plain_into) for record in (self._launch_all, advanced)]
