"""TokTalk Table 3 on SynthTalk test: without style, with style, adapted stream B; baselines and oracle.

The model is the demo's (:func:`jaxtalk.demo.train_or_load`, TokTalk ``small``); stage 2 (the adapter
for stream B, 25 Hz x 48) is trained on top with the base frozen. Every TokTalk row runs the streaming
engine (chunk 0.4 s, CFG w = 0.7), as the paper evaluates in its real-time setting, at each requested
Euler step count (1 step from pure noise = the posterior mean, the demo's default; 10 = the paper's).
"With style" encodes a crop (8 s by default) of ANOTHER clip of the same test speaker; "without style" uses the mean
training style vector (the same network; the paper trains a separate model without style input).
Stream B is fed to the streaming engine as source tokens (adapted chunk by chunk by the causal
adaptation layer). Baselines: the training mean pose, and the mean pose of the same style reference clip (what the
style anchor alone gives); the oracle is SynthTalk's deterministic motion. LVE = max over lip vertices
of the squared error, mean over frames, in mm^2 on the built-in face; FDD (mm^2, upper-face
dynamics) and MOD (mm, mouth opening); frame-weighted over clips.

Bars (at the first step count): TokTalk with style beats the mean pose by >= 30% on LVE; style beats
no style; adapted within 15% of the base model.

``--seed S`` trains on SynthTalk of seed S with training seed S (the demo's recipe ties the two) and
writes ``toktalk_quality_seedS.json``.

Usage: ``python experiments/toktalk_quality.py [--size small] [--steps 1200] [--sample-steps 1 10] [--seed 0]``
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from jaxtalk.benchmarking import machine_info, print_table, write_json
from jaxtalk.models import toktalk as tt
from jaxtalk.models.toktalk.sampling import default_grid
from jaxtalk.data.loader import iter_windows, open_data
from jaxtalk.models.toktalk.recipe import TokTalkWindows
from toktalk_common import DATA, RESULTS, evaluate, load_corpus, style_clip_for, trained_small, weighted_mean


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="small")
    parser.add_argument("--steps", type=int, default=1200, help="base training steps (the demo's: 1200)")
    parser.add_argument("--adapter-steps", type=int, default=400)
    parser.add_argument("--sample-steps", type=int, nargs="+", default=[1, 10], help="Euler step counts")
    parser.add_argument("--clips", type=int, default=0, help="test clips to use (0: all)")
    parser.add_argument("--style-seconds", type=float, default=8.0,
                        help="length of the reference clip (a crop of another clip of the same speaker)")
    parser.add_argument("--seed", type=int, default=0, help="corpus and training seed")
    parser.add_argument("--out", default=None, help="default: results/toktalk_quality_seed<S>.json")
    args = parser.parse_args()
    args.out = args.out or str(RESULTS / f"toktalk_quality_seed{args.seed}.json")
    step_counts = list(args.sample_steps)
    corpus = load_corpus(args.size, args.seed)
    cfg, params, train_info = trained_small(corpus, args.steps, args.adapter_steps, seed=args.seed)
    rng = np.random.default_rng(0)
    # The training split's 2-s windows as TokTalk's recipe cuts them (the demo's prepared corpus).
    windows = list(iter_windows(open_data(f"synthtalk:{args.size}:{corpus.seed}", cache_dir=DATA),
                                TokTalkWindows(cfg, 50, hop_frames=50), "train"))
    train_w = {k: np.stack([w[k] for w in windows]) for k in ("motion", "mask", "style")}
    mean_pose = train_w["motion"][train_w["mask"]].mean(0)
    mean_style = np.asarray(tt.encode_style(params, cfg, train_w["style"])).mean(0, keepdims=True)
    variants = ("TokTalk w/o style", "TokTalk w/ style", "TokTalk adapted (stream B)")
    rows: dict[str, list[dict]] = {"mean pose": [], "reference-clip mean pose": [], "oracle": []}
    rows.update({f"{v}, {n} step{'s' * (n > 1)}": [] for n in step_counts for v in variants})
    clips = corpus.split("test")[: args.clips or None]
    t0 = time.perf_counter()
    for i, clip in enumerate(clips):
        gt = np.asarray(corpus.motion(clip))
        ref = style_clip_for(corpus, clip, round(args.style_seconds * cfg.fps), rng)
        rows["mean pose"].append(evaluate(corpus, np.repeat(mean_pose[None], len(gt), 0), clip))
        rows["reference-clip mean pose"].append(evaluate(corpus, np.repeat(ref[0].mean(0)[None], len(gt), 0), clip))
        rows["oracle"].append(evaluate(corpus, np.asarray(corpus.oracle(clip)), clip))
        tok_a = np.asarray(corpus.tokens(clip, "A").embeddings)[None]
        tok_b = np.asarray(corpus.tokens(clip, "B").embeddings)[None]
        style = tt.encode_style(params, cfg, ref)
        key = jax.random.key(100 + i)
        for n in step_counts:
            # Stream B goes in as SOURCE tokens: the streaming adaptation layer adapts each chunk as it
            # arrives (causal, bounded past), as a live stream from the other audio LLM would.
            for name, tokens, sty, rate in zip(variants, (tok_a, tok_a, tok_b), (mean_style, style, style),
                                                (None, None, 25.0)):
                pred = np.asarray(tt.stream(params, cfg, tokens, sty, key, ts=default_grid(cfg, n), src_rate=rate))[0]
                rows[f"{name}, {n} step{'s' * (n > 1)}"].append(evaluate(corpus, pred, clip, cfg.chunk_frames))
    table = [{"model": k, **{m: weighted_mean(v, m) for m in ("mse", "lve_mm2", "fdd_mm2", "mod_mm", "jitter")}}
             for k, v in rows.items()]
    by = {r["model"]: r for r in table}
    claims = {}
    for n in step_counts:
        sfx = f", {n} step{'s' * (n > 1)}"
        with_style, without = by["TokTalk w/ style" + sfx], by["TokTalk w/o style" + sfx]
        claims[f"{n} steps"] = {
            "lve_reduction_vs_mean_pose": 1.0 - with_style["lve_mm2"] / by["mean pose"]["lve_mm2"],
            "beats_mean_pose_by_30pct_lve": with_style["lve_mm2"] <= 0.7 * by["mean pose"]["lve_mm2"],
            "style_beats_no_style_lve": with_style["lve_mm2"] < without["lve_mm2"],
            "style_beats_no_style_mse": with_style["mse"] < without["mse"],
            "adapted_lve_ratio": by["TokTalk adapted (stream B)" + sfx]["lve_mm2"] / with_style["lve_mm2"],
            "adapted_within_15pct_lve": by["TokTalk adapted (stream B)" + sfx]["lve_mm2"] <= 1.15 * with_style["lve_mm2"],
        }
    print_table(table, f"TokTalk quality on SynthTalk {args.size} test ({len(clips)} clips, streaming)")
    print_table([{"steps": k, **{c: (f"{v:.3f}" if isinstance(v, float) else str(v)) for c, v in d.items()}}
                 for k, d in claims.items()], "Bars")
    write_json(args.out, {"machine": machine_info(), "args": vars(args), "train": train_info, "table": table,
                          "claims": claims, "eval_s": time.perf_counter() - t0})


if __name__ == "__main__":
    main()
