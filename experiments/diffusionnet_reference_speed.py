"""DiffusionNet forward against the public PyTorch code it reimplements, side by side on this CPU,
interleaved run by run.

Both sides run DiffusionNet at FreeTalk STM's size (width 128, 4 blocks, MLP (128, 128), spectral
diffusion, gradient features with rotations; xyz in, 3 out, per vertex) on the same mesh and the same
operators (jaxtalk's ``compute_operators``, k = 128 eigenvectors, handed to both), 25 frames (the
mesh deformed differently in each) per call, random weights (speed does not depend on them):

* reference: ``diffusion_net.layers.DiffusionNet`` (nmwsharp/diffusion-net, ``src/``) with the 25
  frames as its batch (the operators repeated per batch element, its gradients as sparse tensors,
  as its ``forward`` expects), under ``torch.no_grad`` with torch's threads set to the CPU
  count, in a child process run by ``--torch-python`` (torch, scipy, scikit-learn,
  robust-laplacian and potpourri3d: the package imports them);
* jaxtalk: :func:`jaxtalk.geometry.diffusionnet.apply_frames`, compiled once before timing.

Rounds alternate one jaxtalk call and one reference call (``--rounds``); the medians and their ratio
(reference / jaxtalk: above 1, jaxtalk is faster) are printed and written with both parameter
counts and jaxtalk's FLOPs (XLA's count) against the float32 matmul peak measured in the run.

    git -C diffusion-net archive HEAD src/diffusion_net | tar -x -C /work/ref/diffusionnet
    python experiments/diffusionnet_reference_speed.py --diffusion-net /work/ref/diffusionnet/src \\
        --torch-python /work/torchenv/bin/python
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

K, FRAMES, WIDTH, BLOCKS = 128, 25, 128, 4


def reference_child(src: str, operators: str) -> None:
    """The reference side: loads the operators, answers each stdin line with one timed call (JSON)."""
    import scipy  # noqa: F401  (the reference imports scipy before torch)
    import torch

    sys.path.insert(0, src)
    from diffusion_net.layers import DiffusionNet

    torch.set_num_threads(os.cpu_count() or 1)
    torch.manual_seed(0)
    z = np.load(operators)

    def sparse(name: str) -> torch.Tensor:
        m = torch.sparse_coo_tensor(np.stack([z[f"{name}_row"], z[f"{name}_col"]]), z[f"{name}_val"],
                                    (len(z["mass"]),) * 2).coalesce()
        return torch.stack([m] * FRAMES)

    net = DiffusionNet(C_in=3, C_out=3, C_width=WIDTH, N_block=BLOCKS, outputs_at="vertices", dropout=False).eval()
    print(json.dumps({"params": sum(p.numel() for p in net.parameters())}), flush=True)
    x = torch.from_numpy(z["frames_x"])
    mass, evals, evecs = (torch.from_numpy(z[k]).unsqueeze(0).expand(FRAMES, *z[k].shape) for k in ("mass", "evals", "evecs"))
    grad_x, grad_y = sparse("grad_x"), sparse("grad_y")
    with torch.no_grad():  # not inference_mode: the reference's sparse gather sets version counters
        for _ in sys.stdin:
            t0 = time.perf_counter()
            net(x, mass, evals=evals, evecs=evecs, gradX=grad_x, gradY=grad_y)
            print(json.dumps({"seconds": time.perf_counter() - t0}), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--diffusion-net", required=True, help="the reference's src/ folder (holding diffusion_net/)")
    parser.add_argument("--torch-python", default=sys.executable)
    parser.add_argument("--grid", type=int, default=82, help="side of the wavy sheet (82: ~6.7k vertices)")
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--out", default="experiments/results/diffusionnet_reference_speed.json")
    parser.add_argument("--child", nargs=2, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        reference_child(*args.child)
        return
    import jax
    import jax.numpy as jnp

    from jaxtalk import benchmarking as bm
    from jaxtalk.geometry import diffusionnet as dn
    from jaxtalk.geometry import operators as geo

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_geometry import wavy_sheet

    v, f = wavy_sheet(args.grid)
    ops = geo.compute_operators(v, f, K, method="cotan")
    frames_x = (v[None] + 0.01 * np.random.default_rng(1).standard_normal((FRAMES, *v.shape))).astype(np.float32)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "operators.npz"
        arrays = {"mass": ops.mass, "evals": ops.evals, "evecs": ops.evecs, "frames_x": frames_x}
        for name in ("grad_x", "grad_y"):
            coo = getattr(ops, name).tocoo()
            arrays |= {f"{name}_row": coo.row.astype(np.int64), f"{name}_col": coo.col.astype(np.int64),
                       f"{name}_val": coo.data.astype(np.float32)}
        np.savez(path, **{k: np.asarray(a, np.float32) if a.dtype == np.float64 else a for k, a in arrays.items()})
        child = subprocess.Popen([args.torch_python, __file__, "--diffusion-net", args.diffusion_net,
                                  "--child", str(Path(args.diffusion_net).resolve()), str(path)],
                                 stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)

        def answer() -> dict:
            line = child.stdout.readline()
            if not line:
                raise RuntimeError(f"the reference process stopped (exit code {child.wait()}); see its error above")
            return json.loads(line)

        def reference() -> float:
            child.stdin.write("run\n")
            child.stdin.flush()
            return answer()["seconds"]

        try:
            ref_params = answer()["params"]
            cfg = dn.DiffusionNetConfig.paper(in_features=3, out_features=3)
            dops = dn.to_diffusion_operators(ops)
            xs = jnp.asarray(frames_x)
            params = dn.DiffusionNet(cfg).init(jax.random.key(0), xs[0], dops)
            run = jax.jit(lambda p, x, o: dn.apply_frames(cfg, p, x, o))
            jax.block_until_ready(run(params, xs, dops))
            flops = bm.xla_flops(lambda p, x, o: dn.apply_frames(cfg, p, x, o), params, xs, dops)
            peak = bm.measure_matmul_peak() / 1e9
            reference()  # warm-up
            times: dict[str, list[float]] = {"jaxtalk": [], "reference": []}
            for _ in range(args.rounds):
                t0 = time.perf_counter()
                jax.block_until_ready(run(params, xs, dops))
                times["jaxtalk"].append(time.perf_counter() - t0)
                times["reference"].append(reference())
        finally:
            child.stdin.close()
            child.wait()
    jax_s, ref_s = statistics.median(times["jaxtalk"]), statistics.median(times["reference"])
    row = {"vertices": len(v), "frames": FRAMES, "jaxtalk_s": jax_s, "reference_s": ref_s,
           "reference_over_jaxtalk": ref_s / jax_s,
           "jaxtalk_params": sum(int(np.prod(leaf.shape)) for leaf in jax.tree.leaves(params)), "reference_params": ref_params,
           "gflops": None if flops is None else flops / 1e9,
           "jaxtalk_of_peak": None if flops is None else flops / jax_s / 1e9 / peak,
           "reference_of_peak": None if flops is None else flops / ref_s / 1e9 / peak}
    bm.print_table([row], f"DiffusionNet (width {WIDTH}, {BLOCKS} blocks), {FRAMES} frames per call: jaxtalk vs the reference "
                          f"(float32 peak {peak:.0f} GFLOP/s)")
    bm.write_json(args.out, {"matmul_peak_gflop_s": peak, "args": vars(args), "row": row, "runs_s": times})


if __name__ == "__main__":
    main()
