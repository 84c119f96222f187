"""A node tile's products on the SM's mma.sync tensor-core path with the operands swapped and the chains independent:
out^T = W^T x^T, the weight the instruction's 16-row A operand (m16n8k8, tf32: each warp's tasks are (16 output
columns, a part of K)), the node tile's 8 rows its N, each k step's three products (hi hi, hi lo, lo hi: fp32's
accuracy) into three accumulators of their own and every other k step into a second set, so that no instruction waits
for the one before (the tensor-core products measured before, tiles.GEMM's "tf32x3" at 9dbfc38, chained every mma of
an output tile on one accumulator: about one m16n8k8 per 19-25 cycles a scheduler, bench/results/
warp_tensor_core_blocks_h200.json). The weight sits in shared memory in the fragments' order (a lane's four values of
a k step one 16-byte load), either as fp32 (split into tf32 hi and lo in registers, "mma-split") or split on the host
(hi then lo, twice the bytes, "mma-presplit"); the node tile is split once a product into the B fragments' order.
Against the fp32 products of the kernels (tiles.GEMM) on the weight in shared memory alike, and staged each product
(tiles.matmul, as the F = 128 node pass's K chunks are), a block's products back to back on one block an SM: the time a
product is (time(REPS) - time(1)) / (REPS - 1). Each variant checked against a float64 product; on the CPU (here) the
same fragment indexing runs element by element, so the layouts are checked without a GPU.

    python bench/studies/warp_mma_swap.py --check                      # the CPU: every shape against float64
    python bench/studies/warp_mma_swap.py --build DIR                  # sm_90 modules ahead of time
    python bench/studies/warp_mma_swap.py --aot DIR --json OUT.json --device "..." --command "..."   # on the GPU
"""

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/: provenance.py
import numpy as np
import provenance
import warp as wp
from warp_product_latency import per_rep_us, repeat_kernel
from warp_swap_ab import fp32_kernel as staged_kernel

from warpgnn.kernels import tiles
from warpgnn.kernels.weights import tf32

# (rows, K, N): the node pass's products at F = 64 (first layer, W2, next stage, delta_v's second layer padded to 32
# columns) and at F = 128
SHAPES = ((8, 192, 64), (8, 64, 64), (8, 64, 192), (8, 64, 32), (8, 384, 128), (8, 128, 128), (8, 128, 384))
THREADS = 256
# floats of the largest weight the fp32 product takes whole (F = 64's (192, 64), as the batch-1 node pass); larger ones
# in K chunks of 64 as the F = 128 node pass (Spec.node_kc), copied again each product as there, and the split weight
# only up to this size (twice the bytes)
WHOLE = 192 * 64

# acc (T, N) += a (T, K) @ W, W (K, N) in shared memory in MMA order (mma_layout), xs (T, 2 K) scratch for x^T's
# fragments. Tasks (16-column tile t, K part p): tile-major within a part, P parts so that the tasks fill the warps
# evenly; a warp's tasks' partial sums are added into acc part by part (a barrier between parts), so a run repeats
# bit for bit.
MMA_SWAP = r"""
    using LA = typename tile_a::Layout;
    using LC = typename tile_acc::Layout;
    constexpr int T = LA::Shape::dim(0), K = LA::Shape::dim(1), N = LC::Shape::dim(1);
    constexpr int SA = LA::Stride::dim(0), SC = LC::Stride::dim(0);
    static_assert(T == 8 && N % 16 == 0 && K % 8 == 0, "swap-AB mma shape");
    constexpr int BD = WP_TILE_BLOCK_DIM, WARPS = BD >= 32 ? BD / 32 : 8, NT = N / 16, KS = K / 8;
    constexpr int P = (NT % WARPS == 0 || KS % 2) ? 1 : (2 * NT) % WARPS == 0 || KS % 4 ? 2 : 4;
    constexpr int TASKS = NT * P, STEPS = KS / P;
    static_assert(KS % P == 0, "K parts");
    const wp::float32* __restrict__ pa = a.data.ptr;
    const wp::float32* __restrict__ pw = w.data.ptr;
    wp::float32* __restrict__ px = xs.data.ptr;
    wp::float32* __restrict__ pc = acc.data.ptr;
    // x^T's B fragments: for k step j and lane (g, q): {hi(x[g][8j+q]), hi(x[g][8j+q+4]), lo(..), lo(..)}
    auto tf32 = [](wp::float32 v) -> wp::float32 {
#if defined(__CUDA_ARCH__)
        unsigned r;
        asm("cvt.rna.tf32.f32 %0, %1;\n" : "=r"(r) : "f"(v));
        return __uint_as_float(r);
#else
        union { wp::float32 f; unsigned u; } bits;
        bits.f = v;
        bits.u = (bits.u + 0x1000u) & 0xFFFFE000u;  // to nearest, ties away (finite values)
        return bits.f;
#endif
    };
    for (int i = WP_TILE_THREAD_IDX; i < KS * 32 * 2; i += BD) {
        const int j = i / 64, lane = (i / 2) % 32, h = i % 2;
        const wp::float32 v = pa[(lane / 4) * SA + 8 * j + lane % 4 + 4 * h];
        const wp::float32 hi = tf32(v);
        px[(j * 32 + lane) * 4 + h] = hi;
        px[(j * 32 + lane) * 4 + 2 + h] = tf32(v - hi);
    }
    WP_TILE_SYNC();
#if defined(__CUDA_ARCH__)
    const int warp = threadIdx.x / 32, lane = threadIdx.x % 32, g = lane / 4, q = lane % 4;
    constexpr int MINE = (TASKS + WARPS - 1) / WARPS;
    wp::float32 d[MINE][4];
#pragma unroll
    for (int m = 0; m < MINE; ++m) {
        const int task = warp + m * WARPS;
        if (task >= TASKS)
            break;
        const int t = task % NT, p = task / NT;
        wp::float32 e[2][3][4] = {};
        // one k step into the accumulators f: its three products, each on an accumulator of its own
        auto step = [&](int j, wp::float32 (&f)[3][4]) {
            const float4 b = *reinterpret_cast<const float4*>(px + (j * 32 + lane) * 4);
            unsigned ah[4], al[4];
#if PRESPLIT
            const float4 wh = *reinterpret_cast<const float4*>(pw + ((j * NT + t) * 32 + lane) * 4);
            const float4 wl = *reinterpret_cast<const float4*>(pw + K * N + ((j * NT + t) * 32 + lane) * 4);
            ah[0] = __float_as_uint(wh.x); ah[1] = __float_as_uint(wh.y); ah[2] = __float_as_uint(wh.z);
            ah[3] = __float_as_uint(wh.w);
            al[0] = __float_as_uint(wl.x); al[1] = __float_as_uint(wl.y); al[2] = __float_as_uint(wl.z);
            al[3] = __float_as_uint(wl.w);
#else
            const float4 wv = *reinterpret_cast<const float4*>(pw + ((j * NT + t) * 32 + lane) * 4);
            const wp::float32 vv[4] = {wv.x, wv.y, wv.z, wv.w};
#pragma unroll
            for (int c = 0; c < 4; ++c) {
                const wp::float32 hi = tf32(vv[c]);
                ah[c] = __float_as_uint(hi);
                al[c] = __float_as_uint(tf32(vv[c] - hi));
            }
#endif
            const unsigned bh0 = __float_as_uint(b.x), bh1 = __float_as_uint(b.y);
            const unsigned bl0 = __float_as_uint(b.z), bl1 = __float_as_uint(b.w);
#define MMA(D, A, B0, B1) asm volatile("mma.sync.aligned.m16n8k8.row.col.f32.tf32.tf32.f32 {%0,%1,%2,%3}, " \
    "{%4,%5,%6,%7}, {%8,%9}, {%0,%1,%2,%3};\n" : "+f"(D[0]), "+f"(D[1]), "+f"(D[2]), "+f"(D[3]) \
    : "r"(A[0]), "r"(A[1]), "r"(A[2]), "r"(A[3]), "r"(B0), "r"(B1))
            MMA(f[0], al, bh0, bh1);
            MMA(f[1], ah, bl0, bl1);
            MMA(f[2], ah, bh0, bh1);
#undef MMA
        };
#pragma unroll 2
        for (int s = 0; s < STEPS; s += 2) {  // even steps into e[0], odd ones into e[1]: six chains
            step(p * STEPS + s, e[0]);
            if (s + 1 < STEPS)
                step(p * STEPS + s + 1, e[1]);
        }
#pragma unroll
        for (int c = 0; c < 4; ++c)
            d[m][c] = ((e[0][0][c] + e[1][0][c]) + (e[0][1][c] + e[1][1][c])) + (e[0][2][c] + e[1][2][c]);
    }
    // D[m][n] = out[n][16 t + m]: d0 (g, 2q), d1 (g, 2q + 1), d2 (g + 8, 2q), d3 (g + 8, 2q + 1)
#pragma unroll
    for (int part = 0; part < P; ++part) {
#pragma unroll
        for (int m = 0; m < MINE; ++m) {
            const int task = warp + m * WARPS;
            if (task < TASKS && task / NT == part) {
                const int c = 16 * (task % NT) + g;
                pc[(2 * q) * SC + c] += d[m][0];
                pc[(2 * q + 1) * SC + c] += d[m][1];
                pc[(2 * q) * SC + c + 8] += d[m][2];
                pc[(2 * q + 1) * SC + c + 8] += d[m][3];
            }
        }
        WP_TILE_SYNC();
    }
#else
    // the same fragments element by element: each task's 16 x 8 A (W^T) and 8 x 8 B (x^T) gathered from the lanes'
    // fragments, the three products summed as above (fp32, k in order)
    for (int part = 0; part < P; ++part)
        for (int t = 0; t < NT; ++t) {
            wp::float32 e[2][3][16][8] = {};
            for (int s = 0; s < STEPS; ++s) {
                const int j = part * STEPS + s;
                wp::float32 Ah[16][8], Al[16][8], Bh[8][8], Bl[8][8];
                for (int lane = 0; lane < 32; ++lane) {
                    const int g = lane / 4, q = lane % 4;
                    const wp::float32* b = px + (j * 32 + lane) * 4;
                    Bh[q][g] = b[0]; Bh[q + 4][g] = b[1]; Bl[q][g] = b[2]; Bl[q + 4][g] = b[3];
                    const int rows[4] = {g, g + 8, g, g + 8}, ks[4] = {q, q, q + 4, q + 4};
                    for (int c = 0; c < 4; ++c) {
                        wp::float32 hi, lo;
#if PRESPLIT
                        hi = pw[((j * NT + t) * 32 + lane) * 4 + c];
                        lo = pw[K * N + ((j * NT + t) * 32 + lane) * 4 + c];
#else
                        const wp::float32 v = pw[((j * NT + t) * 32 + lane) * 4 + c];
                        hi = tf32(v);
                        lo = tf32(v - hi);
#endif
                        Ah[rows[c]][ks[c]] = hi;
                        Al[rows[c]][ks[c]] = lo;
                    }
                }
                for (int m = 0; m < 16; ++m)
                    for (int n = 0; n < 8; ++n)
                        for (int k = 0; k < 8; ++k) {
                            e[s % 2][0][m][n] += Al[m][k] * Bh[k][n];
                            e[s % 2][1][m][n] += Ah[m][k] * Bl[k][n];
                            e[s % 2][2][m][n] += Ah[m][k] * Bh[k][n];
                        }
            }
            for (int m = 0; m < 16; ++m)
                for (int n = 0; n < 8; ++n)
                    pc[n * SC + 16 * t + m] += ((e[0][0][m][n] + e[1][0][m][n]) + (e[0][1][m][n] + e[1][1][m][n]))
                                               + (e[0][2][m][n] + e[1][2][m][n]);
        }
#endif
"""


def mma_layout(w: np.ndarray, presplit: bool) -> np.ndarray:
    """A (K, N) weight as MMA_SWAP reads it: for k step j and 16-column tile t, 32 lanes' float4s, lane 4 g + q
    holding W[8 j + q, 16 t + g], W[8 j + q, 16 t + g + 8], W[8 j + q + 4, 16 t + g], W[8 j + q + 4, 16 t + g + 8]
    (the m16n8k8 A fragment of W^T); ``presplit``: tf32 hi, then lo, (2 K, N)."""
    K, N = w.shape
    j, t, g, q, kh, mh = np.meshgrid(np.arange(K // 8), np.arange(N // 16), np.arange(8), np.arange(4),
                                     np.arange(2), np.arange(2), indexing="ij")
    vals = w[8 * j + q + 4 * kh, 16 * t + g + 8 * mh].astype(np.float32).reshape(K, N)
    if not presplit:
        return np.ascontiguousarray(vals)
    hi = tf32(vals)
    return np.concatenate([hi, tf32(vals - hi)])


def mma_kernel(rows: int, k: int, n: int, presplit: bool):
    owner = f"mma_swap_{rows}_{k}_{n}_{int(presplit)}"
    wrows = 2 * k if presplit else k
    k2 = 2 * k  # tile shapes in a kernel's body: names, not expressions

    @wp.func_native(f"#define PRESPLIT {int(presplit)}\n" + MMA_SWAP + "#undef PRESPLIT\n")
    def product(a: wp.tile(dtype=float, shape=(rows, k)), w: wp.tile(dtype=float, shape=(wrows, n)),
                xs: wp.tile(dtype=float, shape=(rows, k2)), acc: wp.tile(dtype=float, shape=(rows, n))): ...

    @wp.func
    def with_scratch(a: wp.tile(dtype=float, shape=(rows, k)), w: wp.tile(dtype=float, shape=(wrows, n)),
                     acc: wp.tile(dtype=float, shape=(rows, n))):
        xs = wp.tile_empty(shape=(rows, k2), dtype=float, storage="shared")
        product(a, w, xs, acc)

    return repeat_kernel(with_scratch, rows, k, k, wrows, n, owner)


def fp32_kernel(rows: int, k: int, n: int, staged: bool):
    """The kernels' fp32 product (tiles.GEMM): on the weight loaded into shared memory once, as the mma variants'
    (``staged`` False), or staged by tiles.matmul each product (whole, or in K chunks of 64 beyond WHOLE, as the
    node pass copies its weights: ``staged`` True)."""
    if staged:
        return staged_kernel(rows, k, n, k if k * n <= WHOLE else 64, THREADS)
    owner = f"fp32_{rows}_{k}_{n}"
    return repeat_kernel(tiles.gemm(rows, k, n, "native", owner), rows, k, k, k, n, owner)


def cases():
    """[(name, rows, k, n, kernel, layout)]: layout maps a (K, N) weight to what the kernel reads."""
    out = []
    for rows, k, n in SHAPES:
        out.append(("fp32 staged", rows, k, n, fp32_kernel(rows, k, n, True), lambda w: w))
        # the weight whole in shared memory, beside the tiles (an SM's 227 KiB; not F = 128's first layer)
        if 4 * (k * n + rows * (3 * k + n)) > 227 * 1024:
            continue
        out.append(("fp32", rows, k, n, fp32_kernel(rows, k, n, False), lambda w: w))
        for presplit in (False, True)[:2 if k * n <= WHOLE else 1]:
            out.append((f"mma-{'presplit' if presplit else 'split'}", rows, k, n, mma_kernel(rows, k, n, presplit),
                        lambda w, p=presplit: mma_layout(w, p)))
    for *_c, kernel, _l in out:
        kernel.module.options["block_dim"] = THREADS
    return out


def error(kernel, layout, rows, k, n, device, threads) -> float:
    rng = np.random.default_rng(0)
    W = rng.standard_normal((k, n)).astype(np.float32)
    A_host = rng.standard_normal((rows, k)).astype(np.float32)
    A = wp.array(A_host, dtype=float, device=device)
    B = wp.array(layout(W), dtype=float, device=device)
    C = wp.zeros((rows, n), dtype=float, device=device)
    wp.launch_tiled(kernel, dim=[1], inputs=[A, B, 1, C], block_dim=threads, device=device)
    ref = A_host.astype(np.float64) @ W.astype(np.float64)
    return float(np.abs(C.numpy() - ref).max() / np.abs(ref).max())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=100)
    a = provenance.parse_ahead_of_time(ap, "on the CPU: each variant against float64, then stop")
    wp.init()
    all_cases = cases()
    if a.check:
        for name, rows, k, n, kernel, layout in all_cases:
            print(f"({rows}, {k}) x ({k}, {n}) {name}: error {error(kernel, layout, rows, k, n, 'cpu', 1):.1e}")
        return
    if a.build:
        for *_c, kernel, _l in all_cases:
            wp.compile_aot_module(kernel.module, arch=90, module_dir=a.build, use_ptx=False)
        return
    device = wp.get_device("cuda:0")
    if a.aot:
        for *_c, kernel, _l in all_cases:
            wp.load_aot_module(kernel.module, device=device, arch=90, module_dir=a.aot, use_ptx=False)
    sms = device.sm_count
    rng = np.random.default_rng(1)
    records = []
    for name, rows, k, n, kernel, layout in all_cases:
        err = error(kernel, layout, rows, k, n, device, THREADS)
        A = wp.array(rng.standard_normal((rows, k)).astype(np.float32), dtype=float, device=device)
        B = wp.array(layout(rng.standard_normal((k, n)).astype(np.float32)), dtype=float, device=device)
        C = wp.zeros((sms * rows, n), dtype=float, device=device)
        us = per_rep_us(lambda r: wp.launch_tiled(kernel, dim=[sms], inputs=[A, B, r, C], block_dim=THREADS,
                                                  device=device), a.reps, device)
        records.append({"product": name, "rows": rows, "k": k, "n": n, "threads": THREADS, "us": round(us, 4),
                        "max_error": err})
        print(f"({rows}, {k}) x ({k}, {n}) {name:13s}: {us:.3f} us (error {err:.1e})", flush=True)
    Path(a.json).write_text(json.dumps({**provenance.record(a), "note": __doc__.split("\n\n")[0].replace("\n", " "),
                                        "records": records}, indent=1) + "\n")


if __name__ == "__main__":
    main()
