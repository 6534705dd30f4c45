"""Positive control for TokTalk's step-count claim: a corpus where the step count must matter.

TokTalk's Table 5 says more Euler steps lower MSE and jitter. For a well-trained flow the maths says
otherwise for MSE: one Euler step from t = 0 lands on ``z + v(z, 0, c)``, and the optimal velocity at
t = 0 is ``E[x1 | c] - (1 - sigma_min) z``, so one step returns the conditional mean, the MSE-optimal
prediction; a sample from ``p(x | c)`` has twice the conditional variance as its expected squared error.
What more steps must buy is the distribution: the part of the motion the condition does not determine
comes back in samples and is averaged away by one step. Streaming adds one more effect: at t = 0 the
overlap frames fed back from the previous chunk sit at their path value, which is pure noise, so a
one-step chunk never sees the previous chunk's output.

The control corpus makes that part large and known. SynthTalk's clips (generic layout, the same wavs and
tokens) get a telegraph head nod on the first neck angle: ``A * s(t)``, ``s`` switching between -1 and +1
with a mean dwell of ``--dwell`` seconds (5-frame ramps), drawn independently of the audio. Nothing the
model sees at test time predicts ``s`` (the style comes from another clip of the speaker, whose nod is
drawn independently), so the maths predicts, on the nod's angle ``r = x - base`` (``base``: the clip's
motion before the nod):

* ``amplitude = mean |r| / A``: ~0 for the conditional mean (one step), ~1 for samples; and
  ``bimodal_share``, the share of frames with ``|r| > A / 2``: ~0 and ~1 (what is left of the clip's
  own neck motion, ~0.05 rad against A = 0.3, keeps the mean's figures a little above 0);
* ``nod_mse = mean (r - A s)^2 / A^2``: ~1 for the conditional mean, ~2 for independent samples;
* ``boundary_jump``: the mean |r_f - r_{f-1}| / A at the first frame of each chunk against the other
  frames (``inner_jump``): a stream that carries the nod across chunks keeps the two close.

A model and sampler in which the step count works show amplitude rising from ~0 toward 1 with steps. The
corpus's other motion is SynthTalk's; LVE/MVE on the whole face are reported beside it.

    python experiments/toktalk_step_control.py --root /tmp/ctl --steps 3000 \
        --out experiments/results/toktalk_step_control.json
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import os
import subprocess
import time
from pathlib import Path

import numpy as np

from jaxtalk.benchmarking import machine_info, print_table, write_json

NOD_DIM = 53  # params56 = [exp 50 | jaw 3 | neck 3]: the first neck angle


def run(cmd: list[str]) -> None:
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)


def telegraph(frames: int, rng: np.random.Generator, *, dwell_frames: float, ramp: int = 5) -> np.ndarray:
    """A +-1 switching signal (exponential dwell times, mean ``dwell_frames``) with linear ramps."""
    s, level, f = np.empty(frames, np.float32), rng.choice([-1.0, 1.0]), 0
    while f < frames:
        n = max(1, int(rng.exponential(dwell_frames)))
        s[f:f + n] = level
        f += n
        level = -level
    kernel = np.ones(ramp, np.float32) / ramp
    return np.convolve(np.pad(s, (ramp // 2, ramp - 1 - ramp // 2), mode="edge"), kernel, mode="valid")


def control_folder(src: Path, dst: Path, *, amplitude: float, dwell_s: float, seed: int) -> None:
    """``dst``: ``src``'s clips with a telegraph nod added (``<dst>/../nods/<clip>.npy`` keeps ``A s``)."""
    if (dst / "metadata.csv").is_file():
        return
    tmp, nods = dst.with_name(dst.name + ".partial"), dst.parent / "nods"
    tmp.mkdir(parents=True, exist_ok=True)
    nods.mkdir(exist_ok=True)
    rng = np.random.default_rng(seed)
    with open(src / "metadata.csv") as f:
        meta = list(csv.DictReader(f))
    for row in meta:
        clip = row["clip"]
        z = np.load(src / f"{clip}.npz")
        motion = np.asarray(z["params56"], np.float32)
        nod = amplitude * telegraph(motion.shape[0], rng, dwell_frames=dwell_s * float(z["fps"]))
        motion = motion.copy()
        motion[:, NOD_DIM] += nod
        np.save(nods / f"{clip}.npy", nod)
        np.savez(tmp / f"{clip}.npz", params56=motion, fps=z["fps"])
        for name in (f"{clip}.wav", f"{clip}.tokens.npy"):
            if not (tmp / name).exists():
                os.symlink((src / name).resolve(), tmp / name)
    for name in ("metadata.csv", "tokens.json"):
        if not (tmp / name).exists():  # a rerun after an interrupted one
            os.symlink((src / name).resolve(), tmp / name)
    tmp.rename(dst)


def score(run_dir: Path, nods: Path, *, step_counts: list[int], temperatures: list[float], clips: int,
          best: bool, seed: int) -> list[dict]:
    """Stream ``clips`` test clips at each step count and temperature; the nod metrics and LVE / MVE."""
    import jax

    from jaxtalk.data.loader import PreparedData
    from jaxtalk.face import builtin_face
    from jaxtalk.metrics import lve, mve
    from jaxtalk.models.toktalk.model import encode_style, frames_for_tokens
    from jaxtalk.models.toktalk.sampling import default_grid
    from jaxtalk.models.toktalk.streaming import stream
    from jaxtalk.runs import load_run
    from jaxtalk.train.recipes import spread

    loaded = load_run(run_dir, best=best)
    config, params = loaded.config, loaded.params
    data = PreparedData(loaded.record.data["path"])
    face = builtin_face(0)
    lips = face.regions["lips"]
    by_speaker: dict[str, list[int]] = {}
    for i in data.split("test"):
        by_speaker.setdefault(data.clips[i]["speaker"], []).append(i)
    candidates = data.split("test")
    rows = []
    for n in step_counts:
        for tau in temperatures:
            cfg = dataclasses.replace(config, temperature=tau)
            acc = {k: [] for k in ("amplitude", "bimodal_share", "nod_mse", "boundary_jump", "inner_jump", "true_boundary_jump",
                                   "LVE_mm2", "MVE_mm", "frames")}
            for k, j in enumerate(spread(len(candidates), clips)):
                i = candidates[int(j)]
                rec = data.record(i, ("motion", "tokens"))
                tokens = np.asarray(rec["tokens"], np.float32)[None]
                t = min(frames_for_tokens(tokens.shape[1], config.token_rate, config.fps), rec["motion"].shape[0])
                others = [o for o in by_speaker[data.clips[i]["speaker"]] if o != i]
                style = np.asarray(data.record(others[0] if others else i, ("motion",))["motion"], np.float32)
                style_vec = encode_style(params, cfg, style[None, :4 * cfg.style_frames])
                out = stream(params, cfg, tokens, style_vec, jax.random.fold_in(jax.random.key(seed), k),
                             ts=default_grid(cfg, n))
                pred = np.asarray(out, np.float32)[0][:t]
                gt = np.asarray(rec["motion"], np.float32)[:t]
                nod = np.load(nods / f"{data.clips[i]['name']}.npy")[:t]
                amp = float(np.abs(nod).mean())
                r = pred[:, NOD_DIM] - (gt[:, NOD_DIM] - nod)
                jumps, true_jumps = np.abs(np.diff(r)), np.abs(np.diff(nod))
                first = np.zeros(t - 1, bool)
                first[np.arange(cfg.chunk_frames, t, cfg.chunk_frames) - 1] = True
                acc["amplitude"].append(np.abs(r).mean() / amp)
                acc["bimodal_share"].append((np.abs(r) > amp / 2).mean())
                acc["nod_mse"].append(((r - nod) ** 2).mean() / amp**2)
                acc["boundary_jump"].append(jumps[first].mean() / amp)
                acc["inner_jump"].append(jumps[~first].mean() / amp)
                acc["true_boundary_jump"].append(true_jumps[first].mean() / amp)
                v_pred, v_gt = np.asarray(face.vertices_seq(pred)), np.asarray(face.vertices_seq(gt))
                acc["LVE_mm2"].append(float(lve(v_pred, v_gt, lips)) * 1e6)
                acc["MVE_mm"].append(float(mve(v_pred, v_gt)) * 1e3)
                acc["frames"].append(t)
            w = np.asarray(acc.pop("frames"), float)
            rows.append({"checkpoint": f"step {loaded.step}" + (" (best)" if best else ""), "euler_steps": n,
                         "temperature": tau, **{k: float(np.average(v, weights=w)) for k, v in acc.items()},
                         "clips": len(w)})
    return rows


def mean_pose_row(run_dir: Path, nods: Path, clips: int) -> dict:
    """The nod metrics of the training mean (one number for every frame): the floor of a model that ignores the nod."""
    from jaxtalk.data.loader import PreparedData
    from jaxtalk.runs import load_run
    from jaxtalk.train.recipes import spread

    data = PreparedData(load_run(run_dir).record.data["path"])
    mean = np.asarray(data.motion_stats()["mean"], np.float32)
    amp, share, mse = [], [], []
    candidates = data.split("test")
    for j in spread(len(candidates), clips):
        i = candidates[int(j)]
        gt = np.asarray(data.record(i, ("motion",))["motion"], np.float32)
        nod = np.load(nods / f"{data.clips[i]['name']}.npy")[: len(gt)]
        r = mean[NOD_DIM] - (gt[:, NOD_DIM] - nod)
        a = np.abs(nod).mean()
        amp.append(np.abs(r).mean() / a)
        share.append((np.abs(r) > a / 2).mean())
        mse.append(((r - nod) ** 2).mean() / a**2)
    return {"checkpoint": "mean pose", "amplitude": float(np.mean(amp)), "bimodal_share": float(np.mean(share)),
            "nod_mse": float(np.mean(mse))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, required=True, help="data, prepared folder and run go here")
    ap.add_argument("--source", type=Path, default=None,
                    help="a generic-layout SynthTalk folder with tokens (default: ROOT/data/tokens, written by "
                         "jaxtalk data)")
    ap.add_argument("--size", default="small")
    ap.add_argument("--amplitude", type=float, default=0.3,
                    help="nod amplitude A (radians; SynthTalk's own neck angles have a std of ~0.05, so the nod dominates)")
    ap.add_argument("--dwell", type=float, default=2.0, help="mean seconds between nod switches")
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--euler-steps", default="1,2,5,10")
    ap.add_argument("--temperatures", default="1,0.5")
    ap.add_argument("--clips", type=int, default=20)
    ap.add_argument("--cache-dir", default=".cache/prepared")
    ap.add_argument("--out", type=Path, default=Path("experiments/results/toktalk_step_control.json"))
    args = ap.parse_args()
    t0 = time.time()
    source = args.source or args.root / "data" / "tokens"
    if not (source / "metadata.csv").is_file():
        run(["jaxtalk", "data", "--size", args.size, "--cache-dir", f"{args.cache_dir}/synthtalk", "--out", str(source)])
    control = args.root / "data" / "nod"
    control_folder(source, control, amplitude=args.amplitude, dwell_s=args.dwell, seed=1234)
    prepared, run_dir = args.root / "prepared" / "nod", args.root / "runs" / f"nod-s{args.seed}"
    run(["jaxtalk", "prepare", str(control), "--out", str(prepared)])
    run(["jaxtalk", "train", "toktalk", "--data", str(prepared), "--steps", str(args.steps), "--seed", str(args.seed),
         "--out", str(run_dir), "--set", "eval_every=500"])
    steps = [int(s) for s in args.euler_steps.split(",")]
    taus = [float(t) for t in args.temperatures.split(",")]
    rows = [mean_pose_row(run_dir, args.root / "data" / "nods", args.clips)]
    for best in (False, True):
        rows += score(run_dir, args.root / "data" / "nods", step_counts=steps, temperatures=taus, clips=args.clips,
                      best=best, seed=0)
    print_table(rows, f"Telegraph-nod control (A = {args.amplitude} rad, dwell {args.dwell} s): test clips")
    write_json(args.out, {"args": {k: str(v) for k, v in vars(args).items()}, "machine": machine_info(),
                          "wall_s": time.time() - t0, "rows": rows})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
