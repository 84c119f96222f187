"""What a set of compiled kernels is specialised for, and the configurations the kernels cover.

Tile shapes are compile-time constants in Warp, so every kernel is built by a factory for one
``Spec`` (latent width F, rows per tile, K chunk of the products) and all kernels of one spec and one
block size share one Warp module: one compile per spec and block size whatever the passes, the
variant (vanilla or hybrid, with or without actuator graphs) or the topology (on a 2-core CPU ~15 s
a module, of which the C++ headers alone cost ~4 s: one module, not one per kernel).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

STATE = 12  # q, v, sigma per node
N_L = STATE * (STATE - 1) // 2  # 66: strict lower triangle of A
N_M = STATE * (STATE + 1) // 2  # 78: lower triangle of B
N_LM = N_L + N_M  # delta_e's outputs per edge and self-loop
N_GRAD = 2 * STATE  # delta_v's outputs per node: dE, dS
FEATURE_WIDTH = 24  # widest encoder input (18: the single-graph node features) padded to a multiple of 8
STAT_WIDTH = 9  # widest standardised raw feature set (the node's v, sigma)
# a mesh edge's 8 features padded to a tensor-core K (16): the mesh-edge encoder's first layer on wgmma
# (message_passing.edge_encoder_kernel)
EDGE_FEATURE_WIDTH = 16
GEMMS = ("native", "scalar", "mathdx", "fp16", "wgmma")  # the first is the default
TILE_KERNELS = ("encode", "edge_pass", "node_pass", "hybrid_fields", "node_registers")  # Spec.threads may name them
EDGE_KERNELS = ("edge_pass", "hybrid_fields")  # the edge-row launches (Spec.edge_kernels may name them)
# registers a thread where blocks queue for the SMs (Spec.many_blocks), so that their blocks an SM are bound by shared
# memory, not registers (Spec.kernel_options): the edge pass and the encoders on 128 threads, 5 edge blocks of 41 KiB
# instead of 4 at 127 registers and 4 encoder blocks of 52 KiB instead of 3 at 129 (batch 64 edge pass 390 -> 373 us,
# encoders 404 -> 372; bench/results/warp_occupancy_h200.json); the hybrid decoder's edge tiles, two 256-thread blocks
# an SM, where its port terms a thread a row took it to 250 registers and one block (the launch 495 -> 547 us, capped
# 443; warp_port_terms_a_row_h200.json)
MANY_BLOCKS_REGISTERS = {"edge_pass": 96, "encode": 128, "hybrid_fields": 128}


@dataclass(frozen=True)
class Spec:
    latent: int  # F
    tile_rows: int = 32  # rows (edges or nodes) per tile, one tile per block
    # rows per tile of the node launches (0: tile_rows), a divisor of tile_rows. L5's 670 nodes are 21 tiles of 32
    # for an H100's 132 SMs: on 84 tiles of 8 its node launch took 30 us instead of 62 (16 rows: 41 us), the 5-pass
    # step 335 us instead of 499 (bench/results/warp_tile_shapes_h100.json)
    node_rows: int = 8  # NODE_ROWS[0]; Network picks by graph size (node_rows_for)
    # K extent of each partial product (0: the largest divisor of F up to 32): (K, F) weight slices keep
    # a block's shared memory bounded at F = 128, where one (F, F) fp32 weight is 64 KiB. A Network picks it with
    # its node tiles (k_chunk_for: whole F = 64 weights with tiles of 8)
    k_chunk: int = 0
    # the tile products: "native", C++ over shared tiles (tiles.GEMM: a thread a (4, 4) block held in registers over
    # a part of K, rows read as 16-byte vectors, the K loop unrolled by 4); "scalar", Warp's cooperative scalar GEMM
    # (on an H200 it matched cuBLASDx bit for bit, steps 2-4 % faster and a module built in 28 s instead of 287 s:
    # bench/results/warp_gemm_h200.json); "mathdx", cuBLASDx. TF32 cuBLASDx products were slower still (359 us at
    # 5 passes against 335) and 3e-3 to 6e-3 off, and this tree's own mma.sync TF32 products slower than "native" too,
    # with padded rows (bench/results/warp_tensor_cores_h200.json) and without, the weights in blocks of 16 k
    # (warp_tensor_core_blocks_h200.json), so they are not offered; "fp16", operands rounded to half
    # precision and fp32 sums, on tensor cores from sm_80 (tiles.GEMM_F16; the half-precision stretch target: 1.5-1.9x
    # slower than "native" on an H200, warp_fp16_h200.json). The CPU runs "mathdx" as "scalar" and "fp16" with the
    # same rounding
    gemm: str = GEMMS[0]
    # the edge-row launches' tiles and products (edge pass, hybrid decoder), where they differ from the others' (0, "":
    # tile_rows, gemm): "wgmma" takes tiles of 64 rows (a multiple of tile_rows; the layout pads the edge and
    # self-loop blocks to them) and runs their products on Hopper's warpgroup tensor cores in fp32 data
    # (tiles.GEMM_WGMMA: sm_90a modules, weights packed in tf32 parts)
    edge_rows: int = 0
    edge_gemm: str = ""
    # which of the edge-row launches take edge_rows and edge_gemm (names of EDGE_KERNELS); the others run on
    # tile_rows and gemm within the layout's padding to edge_rows
    edge_kernels: tuple = EDGE_KERNELS
    # ((kernel, threads a block), ...): tile kernels whose CUDA launches take another block than the others' (names
    # of TILE_KERNELS). Each lives in a module of its block size (module_of): Warp builds a module for one. A Network
    # picks them (threads_for)
    threads: tuple = ()
    # the edge pass with each 64-row tile in one warpgroup's registers (kernels/register_edges.py; edge_gemm "wgmma",
    # F = 64): this many warpgroups a block, 1 a block a tile, more resident blocks looping over tiles; 0: off
    edge_warpgroups: int = 0
    # the node passes (the vanilla's last excepted) with each 64-row tile in one warpgroup's registers (register_nodes;
    # edge_gemm "wgmma", F = 64): this many warpgroups a resident block, one block an SM; 0: off
    node_warpgroups: int = 0
    # the hybrid decoder's fields (hybrid_fields on large graphs) with each 64-row tile in one warpgroup's registers
    # (kernels/register_decoder.py; edge_gemm "wgmma", F = 64): this many warpgroups a resident block; 0: off
    decoder_warpgroups: int = 0

    def __post_init__(self):
        for gemm in (self.gemm, self.edge_gemm or self.gemm):
            if gemm not in GEMMS:
                raise ValueError(f"gemm {gemm!r}: expected one of {', '.join(GEMMS)}")
        if self.edge_tile % self.tile_rows:
            raise ValueError(f"edge_rows {self.edge_tile} must be a multiple of tile_rows {self.tile_rows}")
        # wgmma: the edge-row launches' products only (edge_gemm; Spec.edges of gemm "wgmma" and 64-row tiles)
        edge_only = self.edge_gemm == "wgmma" or (self.gemm == "wgmma" and self.node_rows == 0 and not self.edge_gemm)
        if "wgmma" in (self.gemm, self.edge_gemm) and (not edge_only or self.edge_tile != 64 or self.latent % 16
                                                       or self.kc % 16):
            raise ValueError("wgmma products: the edge-row launches' only (edge_gemm), on edge tiles of 64 rows, F "
                             "and its K chunk multiples of 16")
        if self.edge_warpgroups and (self.edge_gemm != "wgmma" or self.latent != 64
                                     or "edge_pass" not in self.edge_kernels or self.edge_warpgroups > 4):
            raise ValueError("edge_warpgroups: the edge pass on wgmma (edge_gemm) at F = 64, 1 to 4 warpgroups")
        # at most two: the register node pass takes 255 registers a thread (three warpgroups a block would not launch)
        if self.node_warpgroups and (self.edge_gemm != "wgmma" or self.latent != 64 or self.node_warpgroups > 2):
            raise ValueError("node_warpgroups: with wgmma edge products (edge_gemm, an sm_90a build) at F = 64, 1 or 2 "
                             "warpgroups")
        # at most two: with both weights (104 KiB) each warpgroup's rows take 44 KiB of shared memory
        if self.decoder_warpgroups and (self.edge_gemm != "wgmma" or self.latent != 64 or self.decoder_warpgroups > 2
                                        or "hybrid_fields" not in self.edge_kernels):
            raise ValueError("decoder_warpgroups: the hybrid decoder on wgmma (edge_gemm, edge_kernels) at F = 64, "
                             "1 or 2 warpgroups")
        kernels = tuple(k for k in EDGE_KERNELS if k in self.edge_kernels)
        if len(kernels) != len(set(self.edge_kernels)) or not kernels:
            raise ValueError(f"edge_kernels {self.edge_kernels!r}: expected some of {', '.join(EDGE_KERNELS)}")
        if self.edge_tile == self.tile_rows and (self.edge_gemm or self.gemm) == self.gemm:
            kernels = EDGE_KERNELS  # edge tiles and products as the others': which launches take them says nothing
        object.__setattr__(self, "edge_kernels", kernels)  # one order
        threads = tuple(sorted((str(k), int(n)) for k, n in dict(self.threads).items() if n))
        unknown = sorted({k for k, _ in threads} - set(TILE_KERNELS))
        if unknown:
            raise ValueError(f"threads: unknown kernel {unknown[0]!r}: expected one of {', '.join(TILE_KERNELS)}")
        object.__setattr__(self, "threads", threads)  # one order, so equal specs compare and hash equal

    @property
    def kc(self) -> int:
        kc = self.k_chunk or math.gcd(self.latent, 32)
        if self.latent % kc:
            raise ValueError(f"k_chunk {kc} must divide the latent width {self.latent}")
        return kc

    @property
    def node_kc(self) -> int:
        """K rows of the weight chunks of the node pass's first layer and W2 (and of the encoder's W2 and node
        products on tiles of 8, message_passing.encoder_kernel; where blocks queue for the SMs, many_blocks, of the
        edge pass's products and the node pass's next-stage product too): twice kc where that divides F (F = 128's
        chunks of 64; batch 64 at F = 64: whole weights), else kc. With the per-chunk adds gone (tiles.GEMM_CARRY)
        half as many chunks wait for half as many copies and barriers, and their buffers (2 kc, F) stay within the
        (kc, 3F) ones of the launch's next-stage product (at batch 64 one whole (F, 3F) buffer as large as two chunks'
        and the edge pass's one (F, F) as large as two): no more shared memory. On an H200 (L5) at F = 128, 12
        passes: hybrid 518.5 -> 510.4 us, vanilla 494.8 -> 485.9; batch 64 (F = 64: W2 whole) 3430.5 -> 3416.3 us,
        then with the edge pass's products 3428 -> 3389 us and the next-stage product 3375.7 -> 3363.0 us; the edge
        pass's wgmma products in chunks of 64 at F = 128 took 6 us longer (bench/results/warp_node_chunks_h200.json,
        calls N3, N1, S18a, S18c)."""
        return 2 * self.kc if self.latent % (2 * self.kc) == 0 else self.kc

    @property
    def fused_layers(self) -> bool:
        """Whether an MLP's first-layer product activates its own output and the second adds its bias, and node
        products start from zero rather than a zeroed tile (tiles.matmul_fused), instead of bias fills, activate
        steps and zeroing, each a pass over a tile and a barrier: with whole weights (one K chunk) on the "native"
        and "wgmma" products. The same sums in the same order, so the same outputs bit for bit; on an H200 (L5,
        batch 1, F = 64) hybrid 50.55 / 112.55 / 221.6 -> 49.5 / 109.2 / 213.3 us at 1 / 5 / 12 passes, vanilla
        34.75 / 96.5 / 204.9 -> 34.0 / 93.2 / 197.0 (bench/results/warp_fused_layers_h200.json)."""
        return self.kc == self.latent and self.gemm in ("native", "wgmma")

    @property
    def fused_norm(self) -> bool:
        """Whether an MLP's second product also applies its LayerNorm (and residual) from the accumulators
        (tiles.matmul_norm): fused_layers on tensor cores ("wgmma"): the batch-1 edge pass on an H100 / H200 (and the
        mesh-edge encoder there where it runs with whole weights, not a Network's pick at F = 64). There
        (L5, F = 64) hybrid 49.55 / 109.1 / 213.3 -> 48.9 / 107.15 / 208.8 us at 1 / 5 / 12 passes, vanilla 34.0 /
        93.2 / 196.9 -> 33.3 / 91.35 / 192.65, the outputs within 6.5e-7 relative (the statistics summed in another
        order; bench/results/warp_fused_layers_h200.json, call S18f)."""
        return self.fused_layers and self.gemm == "wgmma"

    def kernel_options(self, kernel: str) -> dict:
        """Warp kernel options of ``kernel``: its register cap where blocks queue for the SMs (MANY_BLOCKS_REGISTERS);
        not the edge pass on tensor cores (64-row blocks on 256 threads, their registers uncapped as measured)."""
        tensor = kernel == "edge_pass" and self.edges("edge_pass").gemm == "wgmma"
        capped = self.many_blocks and kernel in MANY_BLOCKS_REGISTERS and not tensor
        return {"cuda_max_registers": MANY_BLOCKS_REGISTERS[kernel]} if capped else {}

    @property
    def many_blocks(self) -> bool:
        """K chunks at F <= 64: a Network's pick for graphs of more than a node tile an SM (k_chunk_for), where the
        blocks queue for the SMs and how many fit an SM (their shared memory and registers) sets a launch's speed;
        also on GPUs allowing a block less than whole weights' shared memory (sm_86 / sm_89), at every size there
        (not measured on those)."""
        return self.kc != self.latent and self.latent <= 64

    @property
    def features_in_encoder(self) -> bool:
        """Whether the encoder's blocks compute their rows' raw features (kernels/features.py) rather than read them
        from a features launch before: unless K chunks at F <= 64 (many_blocks: a Network's pick for graphs of more
        than a node tile an SM, where blocks queue for the SMs; at F = 128 always, measured at batch 1). On an H200
        (L5):
        batch 1 hybrid 58.5 / 123.8 / 238.5 -> 55.7 / 121.1 / 235.6 us at 1 / 5 / 12 passes, vanilla 42.0 / 107.2 /
        221.4 -> 39.2 / 104.3 / 218.4, F = 128 12 passes 639.5 -> 632.7; at batch 64 the encoder's blocks wait
        for their features' loads one wave after another: 3712 -> 3746 us
        (bench/results/warp_features_inline_h200.json)."""
        return not self.many_blocks

    @property
    def node_tile(self) -> int:
        n = self.node_rows or self.tile_rows
        if self.tile_rows % n:
            raise ValueError(f"node_rows {n} must divide tile_rows {self.tile_rows}")
        return n

    @property
    def edge_tile(self) -> int:
        return self.edge_rows or self.tile_rows

    def edges(self, kernel: str) -> "Spec":
        """The tile shape and products of the edge-row launch ``kernel`` (edge_pass or hybrid_fields; its tile
        helpers, the kernel lives in this spec's modules): edge_rows and edge_gemm where edge_kernels names it."""
        if kernel not in EDGE_KERNELS:
            raise ValueError(f"{kernel!r} is not an edge-row launch ({', '.join(EDGE_KERNELS)})")
        if kernel in self.edge_kernels:
            return Spec(self.latent, self.edge_tile, 0, self.k_chunk, self.edge_gemm or self.gemm)
        return Spec(self.latent, self.tile_rows, 0, self.k_chunk, self.gemm)

    @property
    def sm90a(self) -> bool:
        """Whether the CUDA modules must be built for sm_90a (wgmma: Hopper only, Warp's cuda_arch_suffix "a")."""
        return self.edge_gemm == "wgmma"

    @property
    def nodes(self) -> "Spec":
        """The tile shape of the node launches (their tile helpers; the kernels live in this spec's modules)."""
        return Spec(self.latent, self.node_tile, 0, self.k_chunk, self.gemm)

    @property
    def module(self) -> str:
        nodes = f"_N{self.node_tile}" if self.node_tile != self.tile_rows else ""
        gemm = "" if self.gemm == GEMMS[0] else f"_{self.gemm}"
        if self.edge_tile != self.tile_rows or (self.edge_gemm or self.gemm) != self.gemm:
            gemm += f"_E{self.edge_tile}{self.edge_gemm}"
            if self.edge_kernels != EDGE_KERNELS:  # on some of the edge-row launches only
                gemm += "".join(f"_{k}" for k in self.edge_kernels)
            if self.edge_warpgroups:
                gemm += f"_R{self.edge_warpgroups}"
            if self.node_warpgroups:
                gemm += f"_V{self.node_warpgroups}"
            if self.decoder_warpgroups:
                gemm += f"_D{self.decoder_warpgroups}"
        # kernels moved to a module of another block size (threads) leave this one: its name says which, so that two
        # specs differing only there never share (and mix the kernels of) one Warp module
        moved = "".join(f"_{k}{n}" for k, n in self.threads)
        return f"warpgnn_kernels_F{self.latent}_T{self.tile_rows}{nodes}_K{self.kc}{gemm}{moved}"

    def threads_of(self, kernel: str) -> int:
        """Threads a block of ``kernel``'s launches (0: the Network's block_dim)."""
        return dict(self.threads).get(kernel, 0)

    def module_of(self, kernel: str) -> str:
        """The Warp module of ``kernel``: the spec's own, or that of its block size (threads_of)."""
        n = self.threads_of(kernel)
        return f"{self.module}_B{n}" if n else self.module

    @property
    def modules(self) -> dict:
        """{module name: threads a block (0: the Network's block_dim)} of every module of this spec."""
        return {self.module: 0} | {self.module_of(k): n for k, n in self.threads}


# Shared memory a block must be allowed (the device's opt-in limit) for whole weights: the node pass then takes 137
# KiB (kernels/aot's .meta). sm_80/sm_87 allow 163 KiB and sm_90 227 KiB; sm_86/sm_89/sm_120 (RTX 30x0, 40x0, 50x0,
# the paper's RTX 3090 among them) 99 KiB, where those kernels cannot launch and chunks of 32 (80 KiB at most) can.
WHOLE_WEIGHTS_SHARED = 160 * 1024
# that limit by architecture, for builds without the GPU (precompile --arch); others allow less than
# WHOLE_WEIGHTS_SHARED (sm_75 64 KiB; sm_86, sm_89, sm_120 99 KiB)
SHARED_OF_ARCH = {80: 163 * 1024, 87: 163 * 1024, 90: 227 * 1024, 100: 227 * 1024}


NODE_ROWS = (8, 16, 32)  # node tile sizes a Network picks from by its graph's size (node_rows_for); all shipped


def node_rows_allowed(latent: int, max_shared: int | None = None) -> tuple:
    """The NODE_ROWS a Network may take at width ``latent`` on a device allowing a block ``max_shared`` bytes of
    shared memory (None: no limit, as on the CPU): tiles of 32 only at F <= 64 on GPUs that take whole weights (their
    node pass holds 112 KiB with K chunks of 32 at F = 64: more than sm_86 / sm_89 allow, kernels/aot's .meta)."""
    wide = latent <= 64 and (max_shared is None or max_shared >= WHOLE_WEIGHTS_SHARED)
    return NODE_ROWS if wide else NODE_ROWS[:2]


def node_rows_for(n_nodes: int, sm_count: int, latent: int = 64, max_shared: int | None = None) -> int:
    """Rows per node tile for a graph of ``n_nodes`` on a GPU of ``sm_count`` SMs (0: not a GPU): the largest of
    node_rows_allowed that still makes a tile an SM, else the smallest. Larger tiles copy each weight once for more
    rows (the node pass's three weights are 112 KiB at F = 64), smaller ones keep every SM busy. On an H200 (132 SMs,
    L5's 670 nodes a graph, K chunks of 32) it picks the fastest measured at every batch: 8 at 1 and 2 (220 against
    249 / 298 us a 5-pass hybrid step at batch 2), 16 at 4 (364 against 397 / 411), 32 from 8 on (633 against 687
    / 680 at 8, 4.29 against 4.85 / 4.50 ms at 64) (bench/results/warp_large_graphs_h200.json)."""
    for rows in sorted(node_rows_allowed(latent, max_shared), reverse=True):
        if sm_count and -(-n_nodes // rows) >= sm_count:
            return rows
    return NODE_ROWS[0]


def max_shared_of(device) -> int | None:
    """The shared memory a block of the Warp ``device`` may take (its opt-in limit); None on the CPU (no limit)."""
    return device.max_shared_memory_per_block if device.is_cuda else None


def k_chunk_for(node_rows: int, latent: int, max_shared: int | None = None, node_tiles_per_sm: float = 1.0) -> int:
    """K rows of a weight chunk for a Network whose node tiles are ``node_rows`` (node_rows_for): whole weights of
    F <= 64 in one chunk while the graph is small (node tiles of 8, at most one a SM: ``node_tiles_per_sm``, 0 off a
    GPU), so a block waits for one weight copy a product instead of two (the 5-pass hybrid step 212 -> 199 us, the
    1-pass 89 -> 84 us on an H200); chunks of 32 on larger graphs, where the whole weights' staging buffers (the
    node pass 137 KiB) leave an SM room for one block: L5 at batch 2 (168 node tiles for 132 SMs) 357 against 297
    us a 5-pass hybrid step, batch 12 1.40 against 1.27 ms (warp_k_chunk_batches_h200.json), batch 64 6.79 against
    6.01 ms (warp_k_chunk_by_size_h200.json); and on GPUs that allow a block less than WHOLE_WEIGHTS_SHARED bytes
    of shared memory (``max_shared``: the device's opt-in limit; None: no limit, as on the CPU). 0: Spec's
    default. Keyed on the node tiles as node_rows_for chose them: a Network given node_rows=8 on a large graph
    gets whole weights only while its tiles are at most one a SM."""
    fits = max_shared is None or max_shared >= WHOLE_WEIGHTS_SHARED
    small = node_rows == NODE_ROWS[0] and node_tiles_per_sm <= 1
    return latent if small and latent <= 64 and fits else 0


def tile_rows_for(node_rows: int, latent: int, edge: dict) -> int:
    """Spec.tile_rows (the encoder's tiles, and the layout's) for a Network whose node tiles are ``node_rows`` and
    edge products ``edge`` (edge_products_for): at F > 64, where the edge-row launches take tiles of their own
    (edge_rows), the node tiles' rows, else Spec's 32. With K chunks (F = 128) the encoder's node tiles wait on a
    chain of products chunk by chunk: smaller tiles make shorter chains on more SMs. On an H200 (L5, F = 128, 12
    passes) tiles of 32 / 16 / 8 rows: hybrid 509.1 / 506.6 / 503.1 us, vanilla 485.1 / 482.9 / 480.3 (the encoder
    alone 37.0 / 25.9 / 22.3 us); with whole weights (F = 64) every tile copies them: batch 1 hybrid 51.2 / 53.4 /
    60.1 us at 1 pass (bench/results/warp_node_chunks_h200.json)."""
    return node_rows if latent > 64 and edge.get("edge_rows") else Spec.tile_rows


WIDE = 256  # threads a block of the kernels threads_for names


# node tiles an SM from which the register edge pass runs resident blocks of three warpgroups (edge_products_for)
RESIDENT_NODE_TILES = 6.0


def edge_products_for(k_chunk: int, latent: int, arch: int | None, small: bool = False,
                      node_tiles_per_sm: float = 0.0, tile_rows: int = Spec.tile_rows, node_rows: int = 0) -> dict:
    """Spec's edge_rows, edge_gemm, edge_kernels, edge_warpgroups, node_warpgroups and decoder_warpgroups for a Network
    on a GPU of compute capability ``arch`` (None: not a GPU): on sm_90 (H100, H200) the edge-row launches on tiles of
    64 rows with wgmma products (tiles.GEMM_WGMMA) on two warpgroups (threads_for) for small graphs (``small``: node
    tiles of 8, at most one an SM; at F = 64 whole weights, k_chunk_for, which says as much). At F = 64 on larger graphs
    (K chunks) the edge pass with each tile in a warpgroup's registers (kernels/register_edges.py), a block a tile up to
    RESIDENT_NODE_TILES node tiles an SM (``node_tiles_per_sm``), resident blocks of three warpgroups above, the hybrid
    decoder on the two-warpgroup tiles. On an H200 (L5, 5-pass hybrid steps,
    bench/results/warp_register_edges_h200.json), against the block-tile edge pass on wgmma (batch 2 to 8) or fp32 (16
    on), a block a tile / resident blocks of three: batch 2 186.8 -> 158.8 / 166.4 us, 4 304.5 -> 237.4 / 258.3, 8 558.7
    -> 394.9 / 421.6, 16 948.4 -> 756.9 / 778.5, 32 1746 -> 1382.6 / 1382.5, 64 3316 -> 2594 / 2540 (the edge pass's
    launch 339 -> 198 / 172 us); not at batch 1 (43.9 / 95.7 -> 46.2 / 109.5 us at 1 / 5 passes), whose small graph
    keeps the block tiles: there batch 1 62.2 / 130.3 / 249.9 -> 61.1 / 126.5 / 241.0 us at 1 / 5 / 12 passes with the
    wgmma edge pass, -> 58.2 / 124.1 / 239.1 with the decoder too; F = 128, 12 passes, 676.8 -> 639.7 us
    (warp_wgmma_edge_pass_h200.json, warp_wgmma_decoder_h200.json). Where the graph takes node tiles of 32
    (``node_rows``, node_rows_for: L5 from batch 8) also the node passes (the vanilla's last excepted) in registers,
    resident blocks of two warpgroups (kernels/register_nodes.py), and the mesh-edge rows' encoder on the edge pass's
    tiles (Network's edge_encoder): 5-pass hybrid on an H200 (bench/results/warp_register_nodes_h200.json), batch 8
    388.6 -> 372.2 us, 16 734.5 -> 603.8, 32 1336 -> 1157.8, 64 2450 -> 1995 (the node pass's launch 164 -> 101 us, the
    encoder's 330 -> 115 + 72); not on the smaller graphs' tiles of 8 and 16: batch 2 155.7 -> 232.3, 4 227.7 -> 276.0
    (a single tile's chain, its 224 KiB of weights staged for it, bounds the launch). With the register edge pass also
    the hybrid decoder's fields in registers, resident blocks of two warpgroups (kernels/register_decoder.py): 5-pass
    hybrid on an H200 (bench/results/warp_register_decoder_h200.json) batch 2 155.1 / 155.6 -> 147.9 / 148.3 us, 4 227.4
    / 227.8 -> 214.5 / 215.4, 8 370.4 -> 337.4, 16 605.2 -> 545.3, 32 1157.8 -> 1039.5, 64 2013.7 / 2012.3 -> 1773.8 /
    1776.4 (the decoder's launch 444 -> 202 us; one warpgroup a block 295 us, the step 1860.6). Else {} (the launches'
    tiles and products as the others'), as where wgmma cannot take the shape (K chunks not a multiple of 16,
    ``tile_rows`` not dividing 64)."""
    if arch != 90 or k_chunk % 16 or 64 % tile_rows:
        return {}
    tensor = {"edge_rows": 64, "edge_gemm": "wgmma"}
    if latent == 128:
        return tensor if small else {}
    if latent != 64:
        return {}
    if k_chunk == latent:
        return tensor
    nodes = {"node_warpgroups": 2} if node_rows == NODE_ROWS[-1] else {}
    edges = {"edge_warpgroups": 3 if node_tiles_per_sm > RESIDENT_NODE_TILES else 1, "decoder_warpgroups": 2}
    return tensor | edges | nodes


def edge_products(edge_rows: int | None, edge_gemm: str | None, k_chunk: int, latent: int, arch: int | None,
                  small: bool, edge_kernels: tuple | None = None, node_tiles_per_sm: float = 0.0,
                  tile_rows: int = Spec.tile_rows, edge_warpgroups: int | None = None,
                  node_warpgroups: int | None = None, node_rows: int = 0,
                  decoder_warpgroups: int | None = None) -> dict:
    """Spec's edge_rows, edge_gemm, edge_kernels, edge_warpgroups, node_warpgroups and decoder_warpgroups: those
    given, or where none is (None) edge_products_for's pick."""
    if edge_rows is None and edge_gemm is None and edge_kernels is None:
        edge = edge_products_for(k_chunk, latent, arch, small, node_tiles_per_sm, tile_rows, node_rows)
    else:
        edge = {"edge_rows": edge_rows or 0, "edge_gemm": edge_gemm or "", "edge_kernels": edge_kernels or EDGE_KERNELS}
    given = {"edge_warpgroups": edge_warpgroups, "node_warpgroups": node_warpgroups,
             "decoder_warpgroups": decoder_warpgroups}
    return edge | {k: v for k, v in given.items() if v is not None}


def threads_for(k_chunk: int, latent: int, cuda: bool, edge: dict | None = None, small: bool = False) -> tuple:
    """Spec.threads of a Network on CUDA (``cuda``) with ``k_chunk`` (k_chunk_for) and the edge products ``edge``
    (edge_products: Spec's edge_rows, edge_gemm, edge_kernels): with whole weights (small graphs), the node pass on
    WIDE threads: its block holds an SM alone (137 KiB at F = 64), and 256 threads give its products more warps a
    scheduler, each summing a part of K (tiles.GEMM: two parts when measured, up to four since), and its CSR sums two
    threads a row vector (tiles.SEGMENT_SUMS): 141.8 -> 138.3 us a 5-pass step, 278.4 -> 269.8 at 12 passes on an
    H200 (bench/results/warp_wide_blocks_h200.json). With K chunks on small graphs at F > 64 (``small``: node tiles of
    8, at most one an SM; F = 128 at batch 1) too, since the products carry their K parts in registers from chunk to
    chunk (tiles.GEMM_CARRY) and take chunks of 64 (Spec.node_kc): on an H200 (L5, F = 128) hybrid 494.5 -> 464.6 us at
    12 passes, 95.6 -> 91.0 at 1, vanilla 473.0 -> 445.3 and 72.8 -> 69.8, each node pass 19.5-20.8 -> 16.9-17.9 us of
    the step, the outputs within 1.2e-6 (bench/results/warp_node_threads_f128_h200.json; the encoder on 256 threads
    too was slower: 470.5 us). Not with K chunks on larger graphs (batch 64 at F = 64), nor when K chunks of 32 added
    their parts each chunk (F = 128: 705.5 -> 712.6 us at 12 passes then). The
    edge-row launches with wgmma products too: their 64-row tiles' products on two warpgroups, their other steps with
    a thread for as many rows as on 32-row tiles (edge_products_for's measurements; on 128 threads the wgmma edge pass
    was slower, 130.4 -> 137.3 us at 5 passes, warp_wgmma_edge_pass_h200.json)."""
    wide = [("node_pass", WIDE)] if cuda and (k_chunk == latent or (small and latent > 64)) else []
    tensor = cuda and edge and edge.get("edge_gemm") == "wgmma"
    edges = [(k, WIDE) for k in edge.get("edge_kernels", EDGE_KERNELS)] if tensor else []
    if tensor and edge.get("edge_warpgroups"):  # the register edge pass: a warpgroup a tile (kernels/register_edges)
        edges = [(k, n) for k, n in edges if k != "edge_pass"] + [("edge_pass", 128 * edge["edge_warpgroups"])]
    if tensor and edge.get("node_warpgroups"):  # the register node pass (kernels/register_nodes)
        edges += [("node_registers", 128 * edge["node_warpgroups"])]
    if tensor and edge.get("decoder_warpgroups"):  # the register decoder (kernels/register_decoder)
        edges = [(k, n) for k, n in edges if k != "hybrid_fields"]
        edges += [("hybrid_fields", 128 * edge["decoder_warpgroups"])]
    return tuple(sorted(edges + wide))


def check_config(config) -> None:
    """The kernels cover the paper's configurations: hybrid or vanilla, any passes and latent,
    with or without actuator graphs, one hidden layer per MLP. Anything else is refused in one line."""
    if getattr(config, "kind", None) not in ("hybrid", "vanilla"):
        raise ValueError(f"model kind {getattr(config, 'kind', None)!r} is not covered by the Warp kernels "
                         "(hybrid or vanilla)")
    if config.hidden_layers != 1:
        raise ValueError(f"hidden_layers = {config.hidden_layers} is not covered by the Warp kernels "
                         "(hidden_layers = 1 only)")
    if config.passes < 1 or config.latent < 1:
        raise ValueError("passes and latent must be >= 1")
