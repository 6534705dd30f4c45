"""Score every checkpoint of a TokTalk run as users sample it, on training and held-out clips.

For each saved checkpoint step of RUN (or the steps given), stream a fixed set of clips of each split
chunk by chunk at 1 and ``sample_steps`` Euler steps, exactly as the run's own validation does
(:func:`jaxtalk.models.toktalk.validation.streamed_validation`), and score them on the built-in face:
LVE (mm^2, lips), MVE (mm), jitter (mm/frame^2). Beside each split it scores the mean pose (the
training mean repeated) on the same clips, so "beats the mean pose" is read from one table. Options
vary what can change after training without retraining: the overlap frames fed back between chunks
(``--overlap 0,5``), the guidance weight (``--cfg``), the sampling temperature (``--temperature 1,0.5``)
and the EMA against the raw weights (``--raw``).

    python experiments/toktalk_checkpoints.py runs/toktalk --splits train,val,test --overlap 0,5 \
        --out experiments/results/toktalk_checkpoints.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import jax
import numpy as np


def mean_pose_scores(config, data, split: str, clips: int) -> dict[str, float]:
    """LVE / MVE of the training mean repeated, on the clips streamed_validation picks."""
    from jaxtalk.face import builtin_face
    from jaxtalk.metrics import lve, mve
    from jaxtalk.models.toktalk.model import frames_for_tokens
    from jaxtalk.train.recipes import spread

    face = builtin_face(0)
    lips = face.regions["lips"]
    mean = np.asarray(data.motion_stats()["mean"], np.float32)
    candidates = [i for i in data.split(split) if data.clips[i]["tokens"]]
    sums, frames = {"LVE_mm2": 0.0, "MVE_mm": 0.0}, 0
    for j in spread(len(candidates), clips):
        rec = data.record(candidates[int(j)], ("motion", "tokens"))
        t = min(frames_for_tokens(len(rec["tokens"]), config.token_rate, config.fps), rec["motion"].shape[0])
        gt = np.asarray(face.vertices_seq(np.asarray(rec["motion"], np.float32)[:t]))
        pred = np.asarray(face.vertices_seq(np.broadcast_to(mean, (t, mean.shape[0])).copy()))
        sums["LVE_mm2"] += t * float(lve(pred, gt, lips)) * 1e6
        sums["MVE_mm"] += t * float(mve(pred, gt)) * 1e3
        frames += t
    return {k: v / frames for k, v in sums.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path)
    parser.add_argument("--steps", default="", help="checkpoint steps, comma separated (default: every saved one)")
    parser.add_argument("--splits", default="train,val,test")
    parser.add_argument("--overlap", default="", help="overlap_frames values to stream with (default: the run's)")
    parser.add_argument("--cfg", default="", help="cfg_scale values to stream with (default: the run's)")
    parser.add_argument("--temperature", default="", help="temperatures to stream with (default: the run's)")
    parser.add_argument("--raw", action="store_true", help="also score the raw (non-EMA) weights")
    parser.add_argument("--clips", type=int, default=8)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path)
    parser.add_argument("--data", type=Path, help="prepared data of a run still training")
    parser.add_argument("--preset", default="small")
    parser.add_argument("--set", action="append", default=[], help="KEY=VALUE of a run still training")
    args = parser.parse_args()

    from jaxtalk.data.loader import PreparedData
    from jaxtalk.models.toktalk.validation import streamed_validation
    from jaxtalk.runs import RunRecord, _restore_state, build_config, checkpoint_dir, model_spec
    from jaxtalk.train.checkpoint import Checkpointer

    if (args.run / "run.json").is_file():
        record = RunRecord.load(args.run)
        config, data = record.model_config(), PreparedData(record.data["path"])
    else:  # a run still training (run.json is written when it ends): the preset on the data given
        if args.data is None:
            raise SystemExit(f"{args.run} has no run.json yet: pass --data (and --set) as it was trained")
        data = PreparedData(args.data)
        fields = [f"{field}={data.manifest[key]}" for field, key in model_spec("toktalk").data_fields]
        config = build_config("toktalk", args.preset, [*fields, *args.set])
    with Checkpointer(checkpoint_dir(args.run), read_only=True) as ckpt:
        saved = sorted(ckpt.all_steps())
    steps = [int(s) for s in args.steps.split(",") if s] or saved
    overlaps = [int(o) for o in args.overlap.split(",") if o] or [config.overlap_frames]
    scales = [float(w) for w in args.cfg.split(",") if w] or [config.cfg_scale]
    taus = [float(t) for t in args.temperature.split(",") if t] or [config.temperature]
    splits = [s for s in args.splits.split(",") if s]
    key = jax.random.key(args.seed)
    rows = []
    baselines = {split: mean_pose_scores(config, data, split, args.clips) for split in splits}
    for split, scores in baselines.items():
        print(f"mean pose, {split}: LVE {scores['LVE_mm2']:.1f} mm^2, MVE {scores['MVE_mm']:.2f} mm", flush=True)
    for step in steps:
        state, _ = _restore_state(checkpoint_dir(args.run), step)
        weights = {"ema": state.get("ema_params")} if state.get("ema_params") is not None else {}
        if args.raw or not weights:
            weights["raw"] = state["params"]
        for overlap, scale, tau in [(o, w, t) for o in overlaps for w in scales for t in taus]:
            cfg = dataclasses.replace(config, overlap_frames=overlap, cfg_scale=scale, temperature=tau)
            for split in splits:
                evaluate = streamed_validation(cfg, data, split, key=key, clips=args.clips)
                for which, params in weights.items():
                    t0 = time.perf_counter()
                    scores = evaluate(params, None, step)
                    row = {"step": step, "split": split, "overlap_frames": overlap, "cfg_scale": scale,
                           "temperature": tau, "weights": which,
                           **{k: round(v, 3) for k, v in scores.items()},
                           "mean_pose_LVE_mm2": round(baselines[split]["LVE_mm2"], 3)}
                    rows.append(row)
                    lves = " ".join(f"{k[8:]}={v:.1f}" for k, v in scores.items() if k.startswith("LVE_mm2_"))
                    print(f"step {step:>5} {split:<5} overlap {overlap} cfg {scale:g} T {tau:g} {which:<3}: LVE {lves} "
                          f"(mean pose {baselines[split]['LVE_mm2']:.1f}) [{time.perf_counter() - t0:.0f} s]",
                          flush=True)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"run": str(args.run), "config": dataclasses.asdict(config),
                                        "clips": args.clips, "seed": args.seed, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
