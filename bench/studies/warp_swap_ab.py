"""The node pass's products on Hopper's tensor cores with the operands swapped: out^T = W^T x^T, so the weight is
wgmma's 64-row A operand (read by each thread straight from global memory, fp32, split into tf32 hi and lo in
registers: no shared-memory staging, no chunk barriers) and the node tile's 8 (16) rows are its N. Against the fp32
products of the kernels (tiles.matmul: the weight staged into shared memory in K chunks, double-buffered), each
block running REPS products back to back (every repetition reads its weight again, as every node block does); the
time a product is (time(REPS) - time(1)) / (REPS - 1). Grids of one block an SM; each variant checked against a
float64 product.

    python bench/studies/warp_swap_ab.py --build DIR            # here: the sm_90a modules, ahead of time
    python bench/studies/warp_swap_ab.py --aot DIR --json OUT.json --device "..." --command "..."   # on the GPU
"""

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import numpy as np
import provenance
import warp as wp
from warp_product_latency import per_rep_us, wgmma_macro

from warpgnn.kernels import tiles
from warpgnn.kernels.weights import tf32

# (rows, K, N, K chunk of the fp32 product): the node pass's three products at F = 64 (whole weights) and at
# F = 128 (K chunks of 32), and node tiles of 16 at F = 128
SHAPES = ((8, 192, 64, 192), (8, 64, 64, 64), (8, 64, 192, 64), (8, 384, 128, 32), (8, 128, 128, 32),
          (8, 128, 384, 32), (16, 384, 128, 32))
THREADS = (128, 256)

# acc (T, N) += a (T, K) @ W[row0:row0 + K, col0:col0 + N] with W in swap_ab_layout (global memory): each warpgroup
# takes (64-column block, K part) tasks, its A fragments (4 floats a thread a k step of 8) one 16-byte load each from
# global memory, split into tf32 hi and lo; x^T (B) from shared memory in no-swizzle core matrices (xs: hi then lo,
# written here from a); three wgmmas a k step (lo hi, hi lo, hi hi). The tasks' results added into acc in task order
# (a warpgroup at a time), so a run repeats bit for bit.
SWAP_AB = r"""
    using LA = typename tile_a::Layout;
    using LX = typename tile_xs::Layout;
    using LC = typename tile_acc::Layout;
    constexpr int T = LA::Shape::dim(0), K = LA::Shape::dim(1), N = LC::Shape::dim(1);
    constexpr int SA = LA::Stride::dim(0), SC = LC::Stride::dim(0);
    static_assert(LX::Shape::dim(0) == 2 * T && LX::Shape::dim(1) == K && LX::Stride::dim(0) == K, "x^T scratch");
    static_assert((T == 8 || T == 16) && N % 64 == 0 && K % 8 == 0, "swap-AB shape");
    const wp::float32* __restrict__ pa = a.data.ptr;
    wp::float32* __restrict__ px = xs.data.ptr;
    wp::float32* __restrict__ pc = acc.data.ptr;
    const int CB = w.shape[1] / 64;  // W's 64-column blocks
#if defined(__CUDA_ARCH__)
#if !defined(__CUDA_ARCH_FEAT_SM90_ALL)
    static_assert(T < 0, "wgmma products need an sm_90a build");
#else
    constexpr int BD = WP_TILE_BLOCK_DIM, WG = BD / 128, MB = N / 64;
    constexpr int KS = MB % WG == 0 ? 1 : WG;  // K parts a column block, so the tasks fill the warpgroups evenly
    constexpr int TASKS = MB * KS, ROUNDS = TASKS / WG, STEPS = K / 8 / KS;
    static_assert(BD % 128 == 0 && TASKS % WG == 0 && (K / 8) % KS == 0, "swap-AB tasks");
    for (int i = threadIdx.x; i < T * K; i += BD) {  // x^T's hi and lo parts: [k step][n group][k half][n][4 k]
        const int n = i / K, k = i - n * K;
        const wp::float32 v = pa[n * SA + k];
        unsigned hi, lo;
        asm("cvt.rna.tf32.f32 %0, %1;\n" : "=r"(hi) : "f"(v));
        asm("cvt.rna.tf32.f32 %0, %1;\n" : "=r"(lo) : "f"(v - __uint_as_float(hi)));
        const int off = ((k / 8 * (T / 8) + n / 8) * 2 + (k % 8) / 4) * 32 + (n % 8) * 4 + k % 4;
        px[off] = __uint_as_float(hi);
        px[T * K + off] = __uint_as_float(lo);
    }
    asm volatile("fence.proxy.async.shared::cta;\n" ::: "memory");
    __syncthreads();
    const int group = threadIdx.x / 128, tw = threadIdx.x % 128, warp = tw / 32, lane = tw % 32;
    const int g = lane / 4, q = lane % 4;
    const unsigned long long base = static_cast<unsigned long long>(__cvta_generic_to_shared(px));
    const unsigned long long desc0 = ((base & 0x3FFFF) >> 4) | (8ull << 16) | (16ull << 32);
    constexpr unsigned long long LO = (T * K * 4) >> 4, STEP = (T / 8 * 256) >> 4;
    const float4* __restrict__ pw = reinterpret_cast<const float4*>(w.data);
    wp::float32 d[ROUNDS][T / 2];
    // k steps in chunks of S: a chunk's weight loads are issued before the chunk before's wgmmas, whose registers
    // are free again after its wait (registers still read by a wgmma in flight made ptxas serialize them all)
    constexpr int S = STEPS % 8 == 0 ? 8 : STEPS % 6 == 0 ? 6 : STEPS % 4 == 0 ? 4 : STEPS % 2 == 0 ? 2 : 1;
#pragma unroll
    for (int r = 0; r < ROUNDS; ++r) {
        const int t = r * WG + group, mb = t % MB, ks = t / MB;
        const float4* src = pw + (static_cast<long long>(row0 / 8 + ks * STEPS) * CB + col0 / 64 + mb) * 128 + tw;
        const long long stride = static_cast<long long>(CB) * 128;
#pragma unroll
        for (int i = 0; i < T / 2; ++i)
            d[r][i] = 0.f;
        float4 raw[S];
#pragma unroll
        for (int s = 0; s < S; ++s)
            raw[s] = src[s * stride];
#pragma unroll
        for (int c = 0; c < STEPS / S; ++c) {
            unsigned ah[S][4], al[S][4];
#pragma unroll
            for (int s = 0; s < S; ++s) {
                const wp::float32 vv[4] = {raw[s].x, raw[s].y, raw[s].z, raw[s].w};
#pragma unroll
                for (int e = 0; e < 4; ++e) {
                    asm("cvt.rna.tf32.f32 %0, %1;\n" : "=r"(ah[s][e]) : "f"(vv[e]));
                    asm("cvt.rna.tf32.f32 %0, %1;\n" : "=r"(al[s][e]) : "f"(vv[e] - __uint_as_float(ah[s][e])));
                }
            }
            if (c + 1 < STEPS / S) {
#pragma unroll
                for (int s = 0; s < S; ++s)
                    raw[s] = src[((c + 1) * S + s) * stride];
            }
            asm volatile("wgmma.fence.sync.aligned;\n" ::: "memory");
#pragma unroll
            for (int s = 0; s < S; ++s) {
                const unsigned long long dh = desc0 + (ks * STEPS + c * S + s) * STEP, dl = dh + LO;
                WGMMA(d[r], al[s], dh);
                WGMMA(d[r], ah[s], dl);
                WGMMA(d[r], ah[s], dh);
            }
            asm volatile("wgmma.commit_group.sync.aligned;\n" ::: "memory");
            asm volatile("wgmma.wait_group.sync.aligned 0;\n" ::: "memory");
        }
    }
#pragma unroll
    for (int r = 0; r < ROUNDS; ++r) {
#pragma unroll
        for (int gg = 0; gg < WG; ++gg) {
            if (group == gg) {
                const int t = r * WG + group, mb = t % MB;
                const int c = 64 * mb + 16 * warp + g;
#pragma unroll
                for (int j = 0; j < T / 8; ++j) {  // d: (m c, n 8 j + 2 q), (c, + 1), (c + 8, ..), (c + 8, .. + 1)
                    const int n = 8 * j + 2 * q;
                    pc[n * SC + c] += d[r][4 * j];
                    pc[(n + 1) * SC + c] += d[r][4 * j + 1];
                    pc[n * SC + c + 8] += d[r][4 * j + 2];
                    pc[(n + 1) * SC + c + 8] += d[r][4 * j + 3];
                }
            }
            if (WG > 1 || r + 1 == ROUNDS)
                __syncthreads();
        }
    }
#endif
#else
    for (int i = WP_TILE_THREAD_IDX; i < T * N; i += WP_TILE_BLOCK_DIM) {  // an output element a thread
        const int n = i / N, c = i - n * N, cg = col0 + c, cc = cg % 64;
        const int lane = 4 * (cc % 8), thread = 32 * (cc % 64 / 16) + lane, rh = cc % 16 / 8;
        wp::float32 s = wp::float32(0);
        for (int k = 0; k < K; ++k) {
            const int kg = row0 + k, kk = kg % 8;
            const long long off = ((static_cast<long long>(kg / 8) * CB + cg / 64) * 128 + thread + kk % 4) * 4
                                  + rh + 2 * (kk / 4);
            s = wp::muladd(pa[n * SA + k], w.data[off], s);
        }
        pc[n * SC + c] += s;
    }
#endif
"""


def swap_ab_layout(w: np.ndarray) -> np.ndarray:
    """A (K, N) weight (K a multiple of 8, N of 64) as SWAP_AB reads it, the same shape: for k step j and 64-column
    block b, 128 threads' float4s, thread 32 w + 4 g + q holding W[8 j + q, c], W[8 j + q, c + 8], W[8 j + q + 4,
    c], W[8 j + q + 4, c + 8] with c = 64 b + 16 w + g (wgmma's A fragment of the transposed weight)."""
    K, N = w.shape
    j, b, wq, g, q, kh, rh = np.meshgrid(np.arange(K // 8), np.arange(N // 64), np.arange(4), np.arange(8),
                                         np.arange(4), np.arange(2), np.arange(2), indexing="ij")
    return np.ascontiguousarray(w[8 * j + q + 4 * kh, 64 * b + 16 * wq + g + 8 * rh].reshape(K, N), np.float32)


def swap_ab_kernel(rows: int, k: int, n: int, threads: int):
    owner = f"swap_ab_{rows}_{k}_{n}_{threads}"
    rows2 = 2 * rows  # a compile-time constant for the kernel
    @wp.func_native(wgmma_macro(rows) + SWAP_AB + "#undef WGMMA\n")
    def product(a: wp.tile(dtype=float, shape=(rows, k)), w: wp.array2d(dtype=float), row0: int, col0: int,
                xs: wp.tile(dtype=float, shape=(rows2, k)), acc: wp.tile(dtype=float, shape=(rows, n))): ...

    @wp.kernel(enable_backward=False, module=owner)
    def products(a: wp.array2d(dtype=float), w: wp.array2d(dtype=float), reps: int, c: wp.array2d(dtype=float)):
        blk, _lane = wp.tid()
        ta = wp.tile_load(a, shape=(rows, k), storage="shared")
        xs = wp.tile_empty(shape=(rows2, k), dtype=float, storage="shared")
        acc = wp.tile_zeros(shape=(rows, n), dtype=float, storage="shared")
        i = int(0)
        while i < reps:
            product(ta, w, 0, 0, xs, acc)
            i += 1
        wp.tile_store(c, acc, offset=(blk * rows, 0))

    return products


def fp32_kernel(rows: int, k: int, n: int, kc: int, threads: int):
    owner = f"fp32_product_{rows}_{k}_{n}_{kc}_{threads}"
    mm = tiles.matmul(rows, k, kc, n, "native", owner)

    @wp.kernel(enable_backward=False, module=owner)
    def products(a: wp.array2d(dtype=float), w: wp.array2d(dtype=float), reps: int, c: wp.array2d(dtype=float)):
        blk, _lane = wp.tid()
        ta = wp.tile_load(a, shape=(rows, k), storage="shared")
        acc = wp.tile_zeros(shape=(rows, n), dtype=float, storage="shared")
        i = int(0)
        while i < reps:
            mm(ta, w, 0, 0, acc)
            i += 1
        wp.tile_store(c, acc, offset=(blk * rows, 0))

    return products


def kernels():
    """[(name, rows, k, n, threads, kernel, swap)] of every case timed."""
    out = []
    for rows, k, n, kc in SHAPES:
        for threads in THREADS:
            out.append((f"fp32 K{kc}", rows, k, n, threads, fp32_kernel(rows, k, n, kc, threads), False))
            out.append(("swap-AB wgmma", rows, k, n, threads, swap_ab_kernel(rows, k, n, threads), True))
    for *_case, threads, kernel, _swap in out:
        kernel.module.options["block_dim"] = threads
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--build", help="compile the modules for sm_90a into this folder and stop")
    ap.add_argument("--aot", help="load the modules --build made from this folder")
    ap.add_argument("--reps", type=int, default=100)
    ap.add_argument("--json")
    provenance.add_arguments(ap)
    a = ap.parse_args()
    wp.config.cuda_arch_suffix = "a"  # wgmma: sm_90a
    wp.init()
    cases = kernels()
    if a.build:
        for _name, _r, _k, _n, threads, kernel, _s in cases:
            wp.compile_aot_module(kernel.module, arch=90, module_dir=a.build, use_ptx=False)
        return
    device = wp.get_device("cuda:0")
    if a.aot:
        for _name, _r, _k, _n, threads, kernel, _s in cases:
            wp.load_aot_module(kernel.module, device=device, arch=90, module_dir=a.aot, use_ptx=False)
    sms = device.sm_count
    rng = np.random.default_rng(0)
    records = []
    for name, rows, k, n, threads, kernel, swap in cases:
        W = rng.standard_normal((k, n)).astype(np.float32)
        A_host = rng.standard_normal((rows, k)).astype(np.float32)
        A = wp.array(A_host, dtype=float, device=device)
        B = wp.array(swap_ab_layout(W) if swap else W, dtype=float, device=device)
        C = wp.zeros((rows, n), dtype=float, device=device)
        wp.launch_tiled(kernel, dim=[1], inputs=[A, B, 1, C], block_dim=threads, device=device)
        ref = A_host.astype(np.float64) @ W.astype(np.float64)
        err = float(np.abs(C.numpy() - ref).max() / np.abs(ref).max())
        C = wp.zeros((sms * rows, n), dtype=float, device=device)
        us = per_rep_us(lambda r: wp.launch_tiled(kernel, dim=[sms], inputs=[A, B, r, C], block_dim=threads,
                                                  device=device), a.reps, device)
        records.append({"product": name, "rows": rows, "k": k, "n": n, "threads": threads, "us": us,
                        "max_error": err})
        print(f"({rows}, {k}) x ({k}, {n}) {name:14s} {threads} threads: {us:.3f} us (error {err:.1e})")
    Path(a.json).write_text(json.dumps({**provenance.record(a), "note": __doc__.split("\n\n")[0].replace("\n", " "),
                                        "tf32_check": float(tf32(np.float32([1.0]))[0]), "records": records},
                                       indent=1))


if __name__ == "__main__":
    main()
