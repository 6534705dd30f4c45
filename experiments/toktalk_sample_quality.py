"""Why TokTalk's many-step samples are jerky: a trained run's samples on held-out clips, by sampler
setting, and its flow loss by flow time.

For ``--clips`` test clips of the run's data (style: another clip of the same speaker, as ``jaxtalk
eval``): LVE (mm^2), vertex jitter (mm/frame^2) and parameter jitter (the TokTalk tables' unit) of
offline samples (full attention and chunk mask) at 1/2/5/10/20 Euler steps, with and without guidance,
and of the streaming engine; the data's own
jitter beside them. Then, on validation windows, the conditional flow loss at fixed flow times next to
the loss of the preconditioning's linear part alone (``F = 0``): where the network gains little over
it, samples keep the noise the linear part cannot remove. A high-frequency split of the 1-step output
(energy of the second difference) shows whether the starting noise leaks into the posterior mean.
The mean of four 10-step samples against a single sample separates the samples' spread (what the
model has not pinned down, which a single sample's LVE adds) from their bias.

Usage: ``python experiments/toktalk_sample_quality.py RUN [--cache-dir DIR] [--clips 8] [--best]``
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.benchmarking import machine_info, print_table, write_json
from jaxtalk.commands.evaluation import open_eval_data
from jaxtalk.metrics.evaluation import vertex_metrics
from jaxtalk.runs import RunRecord, load_run
from jaxtalk.face import builtin_face
from jaxtalk.metrics import jitter
from jaxtalk.models import toktalk as tt
from jaxtalk.models.toktalk.loss import flow_matching_terms
from jaxtalk.models.toktalk.noise import prior_noise
from jaxtalk.models.toktalk.model import Condition, frames_for_tokens, interpolate_tokens, to_flow_space, velocity
from jaxtalk.models.toktalk.sampling import default_grid

RESULTS = Path(__file__).resolve().parent / "results"


def _clips(data, split, n):
    by_speaker: dict[str, list[int]] = {}
    for i in data.split(split):
        by_speaker.setdefault(data.clips[i]["speaker"], []).append(i)
    chosen = [i for i in data.split(split) if data.clips[i]["tokens"]][:n]
    return chosen, by_speaker


def _reference(data, by_speaker, i, frames):
    """The first ``frames`` frames of another clip of clip ``i``'s speaker (itself when it has none)."""
    other = next((j for j in by_speaker[data.clips[i]["speaker"]] if j != i), i)
    return np.asarray(data.record(other, ("motion",))["motion"], np.float32)[:frames]


def sample_rows(run, data, clips, by_speaker, args):
    config, params = run.config, run.params
    face = builtin_face(0)
    template = np.asarray(face.vertices(np.zeros(56, np.float32)))
    s = 4 * config.style_frames
    settings = [(f"offline, {n} step{'s' * (n > 1)}", "offline", n, None) for n in (1, 2, 5, 10, 20)]
    settings += [("offline, 10 steps, no guidance", "offline", 10, 0.0),
                 ("offline chunk mask, 1 step", "chunked", 1, None), ("offline chunk mask, 10 steps", "chunked", 10, None),
                 ("streamed, 1 step", "stream", 1, None), ("streamed, 10 steps", "stream", 10, None),
                 ("streamed, 10 steps, no guidance", "stream", 10, 0.0),
                 ("offline, 10 steps, mean of 4 samples", "mean4", 10, None)]
    per = {name: [] for name, *_ in settings}
    per["mean pose"], per["ground truth"] = [], []
    frames = []
    mean_pose = np.asarray(params["norm"]["mean"], np.float32)
    key = jax.random.key(args.seed)
    for n, i in enumerate(clips):
        rec = data.record(i, ("motion", "tokens"))
        style = tt.encode_style(params, config, _reference(data, by_speaker, i, s)[None])
        tokens = np.asarray(rec["tokens"], np.float32)[None]
        t = min(frames_for_tokens(tokens.shape[1], config.token_rate, config.fps), rec["motion"].shape[0])
        gt = np.asarray(rec["motion"], np.float32)[:t]
        vg = np.asarray(face.vertices_seq(gt))
        for name, mode, steps, w in settings:
            k = jax.random.fold_in(key, n)
            grid = default_grid(config, steps)
            if mode == "stream":
                out = tt.stream(params, config, tokens, style, k, ts=grid, cfg_scale=w)
            elif mode == "mean4":  # the samples' own mean: what a sharp posterior's samples would give
                out = sum(tt.sample(params, config, tokens, style, jax.random.fold_in(k, r), ts=grid, cfg_scale=w)
                          for r in range(4)) / 4
            else:
                out = tt.sample(params, config, tokens, style, k, ts=grid, cfg_scale=w, chunked=mode == "chunked")
            pred = np.asarray(out)[0][:t]
            per[name].append({**vertex_metrics(pred, gt, face, gt_vertices=vg, template=template),
                              "jitter_params": float(jitter(pred))})
        per["mean pose"].append({**vertex_metrics(np.broadcast_to(mean_pose, gt.shape).copy(), gt, face, gt_vertices=vg,
                                                  template=template), "jitter_params": 0.0})
        per["ground truth"].append({"LVE_mm2": 0.0, "MSE": 0.0, "jitter_mm": float(jitter(vg)) * 1e3,
                                    "jitter_params": float(jitter(gt))})
        frames.append(t)
    w = np.asarray(frames, float)
    rows = []
    for name, items in per.items():
        row = {"setting": name}
        for key_ in ("MSE", "LVE_mm2", "jitter_mm", "jitter_params"):
            row[key_] = float(np.sum(w * np.array([it[key_] for it in items])) / w.sum())
        rows.append(row)
    return rows


def loss_by_time(run, data, clips, by_speaker, args):
    """Conditional flow loss at fixed t on windows of the clips, and the linear part's (F = 0) loss."""
    config, params = run.config, run.params
    win = 100
    s = 4 * config.style_frames
    motion, tokens, styles = [], [], []
    for i in clips:
        rec = data.record(i, ("motion", "tokens"))
        ref = _reference(data, by_speaker, i, s)
        for start in range(0, rec["motion"].shape[0] - win + 1, win):
            motion.append(rec["motion"][start:start + win])
            tokens.append(rec["tokens"][start // 2:(start + win) // 2])
            styles.append(ref)
    motion = jnp.asarray(np.stack(motion), jnp.float32)
    tokens = jnp.asarray(np.stack(tokens), jnp.float32)
    style = tt.encode_style(params, config, np.stack(styles))
    x1 = to_flow_space(params, config, motion, style)
    b = x1.shape[0]
    cond = Condition(tokens=interpolate_tokens(tokens, config.token_rate, config.fps, win, config.token_alignment),
                     style=style, known=jnp.zeros_like(x1), known_mask=jnp.zeros((b, win), bool),
                     keep=jnp.ones((b,)), mask=jnp.ones((b, win), bool), chunked=jnp.zeros((b,), bool))
    zero = jax.tree.map(jnp.zeros_like, params["decoder"])
    v_of = jax.jit(lambda p, x, t: velocity(p, config, x, t, cond))
    rows = []
    for t in (0.0, 0.1, 0.3, 0.5, 0.7, 0.9, 0.97):
        losses, base, hf = [], [], []
        for r in range(args.repeats):
            z = prior_noise(jax.random.key(100 + r), x1.shape, config.noise_frames)  # the run's own prior
            times = jnp.full((b,), t)
            x_t, u = flow_matching_terms(x1, z, times, config.sigma_min)
            v = v_of(params, x_t, times)
            v0 = v_of({**params, "decoder": zero}, x_t, times)
            losses.append(float(jnp.mean(jnp.square(v - u))))
            base.append(float(jnp.mean(jnp.square(v0 - u))))
            # Second-difference energy of the predicted clean motion x_t + (1 - t) v vs the data's.
            x_hat = x_t + (1 - t) * v
            hf.append(float(jnp.mean(jnp.square(jnp.diff(x_hat, 2, axis=1))))
                      / float(jnp.mean(jnp.square(jnp.diff(x1, 2, axis=1)))))
        rows.append({"t": t, "flow_loss": float(np.mean(losses)), "linear_part_loss": float(np.mean(base)),
                     "gain": 1 - float(np.mean(losses)) / float(np.mean(base)),
                     "x1_hat_accel_energy_vs_data": float(np.mean(hf))})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--cache-dir", type=Path, default=Path(".cache/prepared"))
    parser.add_argument("--clips", type=int, default=8)
    parser.add_argument("--best", action="store_true")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=4)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    run = load_run(args.run, best=args.best)
    data = open_eval_data(RunRecord.load(args.run), None, args.cache_dir)
    clips, by_speaker = _clips(data, "test", args.clips)
    rows = sample_rows(run, data, clips, by_speaker, args)
    print_table(rows, title=f"samples on {len(clips)} test clips, step {run.step}")
    val, val_speakers = _clips(data, "val", 4 * args.clips)
    trows = loss_by_time(run, data, val, val_speakers, args)
    print_table(trows, title="validation flow loss by flow time")
    out = args.out or RESULTS / f"toktalk_sample_quality_{args.run.name}.json"
    write_json(out, {"machine": machine_info(), "run": str(args.run), "step": run.step, "samples": rows,
                     "loss_by_time": trows, "config": json.loads(json.dumps(run.record.config))})
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
