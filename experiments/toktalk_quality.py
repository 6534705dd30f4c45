"""TokTalk Table 3 on SynthTalk test: without style, with style, adapted stream B; mean pose and oracle.

All TokTalk rows run the streaming engine (chunk 0.4 s, 10 Euler steps, CFG w = 0.7), as the paper
evaluates in its real-time setting. "With style" encodes a crop of ANOTHER clip of the same test
speaker; "without style" uses the mean training style vector (the same network; the paper trains a
separate model without style input). "Adapted" feeds stream B (25 Hz x 48) through the stage-2
adapter. LVE (max over lip vertices of the squared error, mean over frames) in mm^2 on the built-in face.

Bars: TokTalk (with style) beats the mean pose by >= 30% on LVE; style beats no style; adapted within
15% of the base model.

Usage: ``python experiments/toktalk_quality.py [--size tiny] [--steps 1500] [--adapter-steps 400]``
"""

from __future__ import annotations

import argparse
import time

import jax
import numpy as np

from jaxtalk.benchmarking import machine_info, print_table, write_json
from jaxtalk.models import toktalk as tt
from jaxtalk.models.toktalk.train import make_windows
from toktalk_common import RESULTS, evaluate, load_corpus, style_clip_for, trained_small, weighted_mean


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="tiny")
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--adapter-steps", type=int, default=400)
    parser.add_argument("--out", default=str(RESULTS / "toktalk_quality.json"))
    args = parser.parse_args()
    corpus = load_corpus(args.size)
    cfg, params, train_info = trained_small(corpus, args.steps, args.adapter_steps)
    rng = np.random.default_rng(0)
    train_w = make_windows(corpus, corpus.split("train"), cfg, window_frames=50, hop_frames=50)
    mean_pose = train_w["motion"][train_w["mask"]].mean(0)
    mean_style = np.asarray(tt.encode_style(params, cfg, train_w["style"])).mean(0, keepdims=True)
    rows: dict[str, list[dict]] = {k: [] for k in ("mean pose", "oracle", "TokTalk w/o style",
                                                   "TokTalk w/ style", "TokTalk adapted (stream B)")}
    t0 = time.perf_counter()
    for i, clip in enumerate(corpus.split("test")):
        gt = np.asarray(corpus.motion(clip))
        rows["mean pose"].append(evaluate(corpus, np.repeat(mean_pose[None], len(gt), 0), clip))
        rows["oracle"].append(evaluate(corpus, np.asarray(corpus.oracle(clip)), clip))
        tok_a = np.asarray(corpus.tokens(clip, "A").embeddings)[None]
        style = tt.encode_style(params, cfg, style_clip_for(corpus, clip, cfg.style_frames, rng))
        key = jax.random.key(100 + i)
        for name, tokens, sty in (("TokTalk w/o style", tok_a, mean_style), ("TokTalk w/ style", tok_a, style)):
            pred = np.asarray(tt.stream(params, cfg, tokens, sty, key))[0]
            rows[name].append(evaluate(corpus, pred, clip, cfg.chunk_frames))
        src = np.asarray(corpus.tokens(clip, "B").embeddings)[None]
        adapted = tt.adapt_tokens(params, cfg, src, 25.0)
        pred = np.asarray(tt.stream(params, cfg, adapted, style, key))[0]
        rows["TokTalk adapted (stream B)"].append(evaluate(corpus, pred, clip, cfg.chunk_frames))
    table = [{"model": k, "mse": weighted_mean(v, "mse"), "lve_mm2": weighted_mean(v, "lve_mm2"),
              "jitter": weighted_mean(v, "jitter")} for k, v in rows.items()]
    by = {r["model"]: r for r in table}
    claims = {
        "beats_mean_pose_by_30pct_lve": by["TokTalk w/ style"]["lve_mm2"] <= 0.7 * by["mean pose"]["lve_mm2"],
        "style_beats_no_style_lve": by["TokTalk w/ style"]["lve_mm2"] < by["TokTalk w/o style"]["lve_mm2"],
        "style_beats_no_style_mse": by["TokTalk w/ style"]["mse"] < by["TokTalk w/o style"]["mse"],
        "adapted_within_15pct_lve": by["TokTalk adapted (stream B)"]["lve_mm2"]
        <= 1.15 * by["TokTalk w/ style"]["lve_mm2"],
    }
    print_table(table, f"TokTalk quality on SynthTalk {args.size} test ({len(corpus.split('test'))} clips, streaming)")
    print_table([{k: str(v) for k, v in claims.items()}], "Bars")
    write_json(args.out, {"machine": machine_info(), "args": vars(args), "train": train_info, "table": table,
                          "claims": claims, "eval_s": time.perf_counter() - t0})


if __name__ == "__main__":
    main()
