"""Benchmark DiffusionNet's mesh precompute and the Flax DiffusionNet forward pass.

Part 1, precompute (k = 128) on wavy height-field sheets of ~6.7k, ~25.6k and ~100k vertices:
  * Laplacian + mass (vectorised cotangent),
  * eigensolve: ours (ARPACK shift-invert with a CHOLMOD Cholesky solve, via cholespy) against the
    reference's plain ``scipy.sparse.linalg.eigsh(L + eps I, k, M, sigma=eps)`` (SuperLU) in the
    same run, with the largest eigenvalue difference between the two,
  * gradients: vectorised closed-form 2x2 normal equations against the reference-style Python loop
    over vertices (the loop only up to ``--loop-max-vertices``),
  * total of our ``compute_operators``.
Part 2, DiffusionNet width 128, 4 blocks, xyz in, 3 out, on the ~6.7k mesh with 25 frames through
``apply_frames``: compile time, median run time (seconds per frame), XLA's FLOP count and the
machine's measured float32 matmul rate, whose ratio is the floor on seconds per frame (the network
is matmul-bound: ~8.8 GFLOP per frame at this size, see ``jaxtalk.geometry.diffusionnet``).

Reference timings on this machine (measured when the benchmark was written): precompute 0.96 / 5.2 / 23.5 s (eigsh 0.35 /
3.0 / 14.7 s, gradient loop 0.55 / 2.1 / 8.3 s); PyTorch DiffusionNet 0.127 s per frame. The CPU
is shared with other jobs while these run, so absolute numbers are inflated: compare rows of one run.

Usage: python experiments/bench_geometry.py [--out PATH] [--sizes 82 160 316] [--repeats N]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from jaxtalk import benchmarking as bm
from jaxtalk.geometry import diffusionnet as dn
from jaxtalk.geometry import operators as geo

K = 128
FRAMES = 25


def wavy_sheet(n: int) -> tuple[np.ndarray, np.ndarray]:
    """An n x n grid over the unit square with a smooth height field, triangulated (2 per cell)."""
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n), indexing="ij")
    z = 0.1 * np.sin(3 * x) * np.cos(2 * y)
    v = np.stack([x, y, z], -1).reshape(-1, 3)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return v, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def reference_eigsh(lap: sp.csr_matrix, mass: np.ndarray, k: int, eps: float = 1e-8) -> np.ndarray:
    """The reference's call: shift-invert eigsh on L + eps I with SciPy's default SuperLU.

    Run with the same single-threaded BLAS as ours so the comparison isolates the solver.
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        vals, _ = sla.eigsh((lap + eps * sp.identity(lap.shape[0])).tocsc(), k, sp.diags(mass), sigma=eps)
    return np.sort(vals)


def reference_gradient_loop(v: np.ndarray, f: np.ndarray, frames: np.ndarray) -> sp.csr_matrix:
    """Reference-style gradient build: one small least-squares solve per vertex in Python."""
    src, dst = geo._directed_edges(v, f)
    starts = np.searchsorted(src, np.arange(len(v) + 1))
    a_all = np.einsum("ei,eci->ec", v[dst] - v[src], frames[src, :2])
    r = 1e-5 * float(np.mean(np.sum(a_all**2, axis=1)))
    rows, cols, vals = [], [], []
    for i in range(len(v)):
        nbr = dst[starts[i] : starts[i + 1]]
        a = a_all[starts[i] : starts[i + 1]]
        coef = np.linalg.solve(a.T @ a + r * np.eye(2), a.T)
        rows += [i] * (len(nbr) + 1)
        cols += [*nbr, i]
        vals += [*(coef[0] + 1j * coef[1]), -(coef[0] + 1j * coef[1]).sum()]
    return sp.csr_matrix((vals, (rows, cols)), shape=(len(v), len(v)))


def timed(fn, repeats: int):
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def bench_precompute(sizes: list[int], repeats: int, loop_max_vertices: int) -> list[dict]:
    rows = []
    for n in sizes:
        v, f = wavy_sheet(n)
        reps = repeats if len(v) < 50_000 else 1
        t_lap, (lap, mass) = timed(lambda: geo.laplacian_and_mass(v, f, "cotan"), reps)
        t_eig, (evals, _) = timed(lambda: geo.eigen_decomposition(lap, mass, K, solver="cholmod"), reps)
        t_ref, ref_vals = timed(lambda: reference_eigsh(lap, mass, K), 1)
        frames = geo.tangent_frames(geo.vertex_normals(v, f))
        t_frames, _ = timed(lambda: geo.tangent_frames(geo.vertex_normals(v, f)), reps)
        t_grad, (gx, gy) = timed(lambda: geo.gradient_operators(v, f, frames), reps)
        t_loop = None
        if len(v) <= loop_max_vertices:
            t_loop, ref_grad = timed(lambda: reference_gradient_loop(v, f, frames), 1)
            assert abs(ref_grad - (gx + 1j * gy)).max() < 1e-8, "vectorised gradients disagree with the loop"
        t_total, _ = timed(lambda: geo.compute_operators(v, f, K, method="cotan"), reps)
        rows.append(
            {
                "vertices": len(v),
                "laplacian_s": t_lap,
                "eig_cholmod_s": t_eig,
                "eig_ref_eigsh_superlu_s": t_ref,
                "eig_speedup": t_ref / t_eig,
                "max_rel_eval_diff": float(np.max(np.abs(evals - ref_vals)) / ref_vals.max()),
                "frames_s": t_frames,
                "grad_vectorised_s": t_grad,
                "grad_ref_loop_s": t_loop,
                "total_ours_s": t_total,
                "total_ref_style_s": t_lap + t_ref + t_frames + (t_loop if t_loop is not None else float("nan")),
            }
        )
        bm.print_table(rows[-1:], f"precompute, k={K}, {len(v)} vertices")
    return rows


def bench_diffusionnet(n: int, repeats: int) -> dict:
    v, f = wavy_sheet(n)
    ops = dn.to_diffusion_operators(geo.compute_operators(v, f, K, method="cotan"))
    cfg = dn.DiffusionNetConfig.paper(in_features=3, out_features=3)
    x = jnp.asarray(v, jnp.float32)
    params = dn.DiffusionNet(cfg).init(jax.random.key(0), x, ops)
    # Per-frame inputs: the mesh deformed differently in each frame.
    xs = x[None] + 0.01 * jax.random.normal(jax.random.key(1), (FRAMES, *x.shape))

    def run(p, frames_x, o):  # the public entry point: frames folded next to the channels
        return dn.apply_frames(cfg, p, frames_x, o)

    t = bm.time_jitted(run, params, xs, ops, repeats=repeats, warmup=1)
    flops = bm.xla_flops(run, params, xs, ops)
    # The machine's achievable float32 matmul rate right now: the ceiling for this matmul-bound net.
    peak = bm.measure_matmul_peak(n=1024, repeats=5)
    return {
        "vertices": len(v),
        "frames": FRAMES,
        "width": cfg.width,
        "blocks": cfg.num_blocks,
        "compile_s": t.compile_s,
        "run_median_s": t.run_median_s,
        "s_per_frame": t.run_median_s / FRAMES,
        "gflop_per_frame": None if flops is None else flops / FRAMES / 1e9,
        "achieved_gflops": None if flops is None else flops / t.run_median_s / 1e9,
        "matmul_peak_gflops": peak / 1e9,
        "floor_s_per_frame_at_peak": None if flops is None else flops / FRAMES / peak,
        "ref_pytorch_s_per_frame": 0.127,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("experiments/results/bench_geometry.json"))
    parser.add_argument("--sizes", type=int, nargs="+", default=[82, 160, 316], help="grid side lengths")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--loop-max-vertices", type=int, default=30_000)
    parser.add_argument("--skip-precompute", action="store_true")
    args = parser.parse_args()

    info = bm.machine_info()
    print(f"machine: {info['cpu_model']}, {info['cpu_cores']} cores, load {info['load_avg_1m']}", flush=True)
    net = bench_diffusionnet(args.sizes[0], args.repeats)
    bm.print_table([net], "DiffusionNet forward, 25 frames (apply_frames)")
    pre = [] if args.skip_precompute else bench_precompute(args.sizes, args.repeats, args.loop_max_vertices)
    if pre:
        bm.print_table(pre, f"precompute summary, k={K}")
    path = bm.write_json(args.out, {"precompute": pre, "diffusionnet": net, "load_avg_1m_end": bm.machine_info()["load_avg_1m"]})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
