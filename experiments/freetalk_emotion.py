"""FreeTalk ATS emotion control on SynthTalk: upper-face deviation from neutral per emotion and intensity.

ATS (``small``) is trained on SynthTalk train clips (identity 0 landmarks, head pose removed) with its
recipe, as ``jaxtalk train ats --data synthtalk:SIZE --set max_frames=W window_frames=W`` does, then
the same test audio windows are sampled with every emotion at intensities 1, 2 and 3 (same noise).
For each (emotion, intensity) and the upper face (brows 17-26, eyes 36-47), in millimetres:

* ``upper``: the expression offset, i.e. the norm of the mean (over windows and frames) change of
  each upper-face landmark between the emotional and the neutral sample, averaged over landmarks.
  SynthTalk's emotions are static offsets of the resting face, so this is what the label controls.
* ``frame``: the mean per-frame distance between the two samples. It also counts blinks and brow
  motion that the label change merely shifted in time (these are random in SynthTalk, not driven by
  the label), so it sits well above the true offsets and is reported for reference only.
* ``true``: SynthTalk's own upper-face offset of that emotion and intensity on the same face.
* ``along``: the model's mean offset projected on the direction of the true one (signed, per
  landmark, averaged; mm). Sampling noise that does not depend on the label averages out of this one
  instead of adding a positive floor, so it shows whether the label moves the face the right way.

Every sample is drawn with ``--seeds`` noise seeds (the same seeds for every label) and the offsets
are pooled over seeds, windows and frames; ``upper_se`` is the seed-to-seed standard error of
``upper`` (how much of a difference between intensities is noise).

Checks: ``upper`` grows with intensity and differs between emotions (coefficient of
variation at intensity 3, and its correlation with ``true``). Accuracy: lip-landmark error (mm) of
ATS samples with the true labels against the mean-pose baseline and the generator's oracle motion,
on the same windows.

The trained model is a run folder (``run.json`` + ``checkpoint/``, the format ``jaxtalk train``
writes and ``jaxtalk sample`` reads) in ``--ckpt-dir`` (default under ``experiments/results``); a
second run with the same arguments loads it instead of training again, an interrupted one resumes.

Usage: python experiments/freetalk_emotion.py [--size small|tiny] [--steps N] [--ddim-steps N]
       [--seeds N] [--train-seed S] [--ckpt-dir DIR] [--cache DIR] [--out PATH]

``--emotion-gain K`` trains and scores on the positive-control corpus: SynthTalk with
every emotion's face offset K times its own (``SizeSpec.emotion_gain``), so that the label and its
intensity change the face by a known, large amount; ``true`` and ``along`` use the scaled offsets.

The verdict's ``gain_ratio`` (intensity 1 -> 3 along the true direction, over the generator's own gain)
is the number the scale curve (experiments/scale_curves.py) plots against the training budget
(``experiments/scale_curves.py``).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import jax
import numpy as np

from jaxtalk import benchmarking as bm
from jaxtalk.data import synthtalk
from jaxtalk.data.synthtalk.emotions import face_offset
from jaxtalk.runs import RUN_FILE, checkpoint_dir, load_run
from jaxtalk.commands.training import TrainOptions, train_run
from jaxtalk.models.freetalk import data
from jaxtalk.models.freetalk.emotions import EMOTIONS
from jaxtalk.models.freetalk.fit import FittedATS, sample_displacements
from jaxtalk.train import latest_checkpoint_step

UPPER = np.r_[17:27, 36:48]
LIPS = np.r_[48:68]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="small")
    parser.add_argument("--steps", type=int, default=4000)
    parser.add_argument("--window", type=int, default=32)
    parser.add_argument("--ddim-steps", type=int, default=20)
    parser.add_argument("--cache", type=Path, default=Path(".cache/prepared"),
                        help="SynthTalk and its prepared copy (the default is jaxtalk train's)")
    parser.add_argument("--seeds", type=int, default=4, help="noise seeds every label is sampled with")
    parser.add_argument("--max-windows", type=int, default=0,
                        help="score at most this many held-out windows, evenly spread (0: all)")
    parser.add_argument("--emotion-gain", type=float, default=1.0,
                        help="the control corpus: every emotion's face offset times this (SynthTalk's own: 1)")
    parser.add_argument("--train-seed", type=int, default=0, help="ATS initialisation and data-order seed")
    parser.add_argument("--ckpt-dir", type=Path, default=None,
                        help="run folder; default: experiments/results/freetalk_emotion_run/<size>-<steps>-w<window>")
    parser.add_argument("--out", type=Path, default=Path("experiments/results/freetalk_emotion.json"))
    args = parser.parse_args()
    t0 = time.time()
    # The corpus cache that open_data prepares the training data from (one generation for both).
    corpus = synthtalk.generate(corpus_spec(args), seed=0, cache_dir=args.cache / "synthtalk")
    test_clips = corpus.split("val") + corpus.split("test")
    test_w = data.ats_windows(corpus, test_clips, window=args.window, hop=args.window)
    if args.max_windows and len(test_w["clip"]) > args.max_windows:
        # Evenly spread over the held-out clips: 34 labels x seeds sampler calls on every window cost
        # ~13 min for SynthTalk small's ~375 windows.
        keep = np.linspace(0, len(test_w["clip"]) - 1, args.max_windows).round().astype(int)
        test_w = {k: v[keep] for k, v in test_w.items()}
    run_dir = args.ckpt_dir or Path("experiments/results/freetalk_emotion_run") / (
        f"{args.size}-{args.steps}-w{args.window}" + (f"-s{args.train_seed}" if args.train_seed else "")
        + (f"-gain{args.emotion_gain:g}" if args.emotion_gain != 1 else ""))
    fitted = trained_ats(run_dir, args, corpus)
    train_s = time.time() - t0
    print(f"ATS at step {args.steps} ready (trained or loaded) in {train_s:.0f} s", flush=True)

    key = jax.random.key(1)
    gt = test_w["displacements"]
    pred = sample_displacements(fitted, test_w["audio"], test_w["emotion"], test_w["intensity"], key,
                                sample_steps=args.ddim_steps)
    face = corpus.face(0)
    oracle = []
    for c, s in zip(test_w["clip"], test_w["start"]):
        track = data.landmark_motion(face, data.without_head_pose(corpus.oracle(int(c))))
        oracle.append(track[s:s + args.window])

    def lip_err(p):
        return float(np.linalg.norm(p[:, :, LIPS] - gt[:, :, LIPS], axis=-1).mean() * 1000)

    accuracy = [
        {"method": "ATS", "lip_mm": lip_err(pred)},
        {"method": "mean_pose", "lip_mm": lip_err(np.broadcast_to(fitted.stats.mean, gt.shape))},
        {"method": "oracle", "lip_mm": lip_err(np.stack(oracle))},
    ]
    bm.print_table(accuracy, "Lip-landmark error on held-out windows (true emotion labels)")

    audio = test_w["audio"]
    keys = jax.random.split(jax.random.key(2), args.seeds)

    def upper_samples(emotion: str, level: float) -> np.ndarray:
        """(seeds, windows, frames, 22, 3) upper-face displacements, the same noise for every label."""
        return np.stack([sample_displacements(fitted, audio, emotion, level, k, sample_steps=args.ddim_steps)[:, :, UPPER]
                         for k in keys])

    neutral = upper_samples("neutral", 1.0)
    reference = generator_offsets(face, args.emotion_gain)
    rows = []
    for emotion in EMOTIONS[1:]:
        row = {"emotion": emotion}
        for level in (1, 2, 3):
            diff = upper_samples(emotion, float(level)) - neutral
            per_seed = diff.mean(axis=(1, 2))  # (seeds, 22, 3) mean offset of each landmark
            offset = per_seed.mean(axis=0)
            # The expression offset: the mean displacement change over every seed, window and frame.
            row[f"upper_mm_i{level}"] = float(np.linalg.norm(offset, axis=-1).mean() * 1000)
            se = np.sqrt(per_seed.var(axis=0, ddof=1).sum(axis=-1) / args.seeds) if args.seeds > 1 else np.nan
            row[f"upper_se_i{level}"] = float(np.mean(se) * 1000)
            true = reference[emotion]["offset"][level - 1]
            direction = true / np.maximum(np.linalg.norm(true, axis=-1, keepdims=True), 1e-12)
            row[f"along_mm_i{level}"] = float(np.sum(offset * direction, axis=-1).mean() * 1000)
            row[f"along_seeds_mm_i{level}"] = (np.sum(per_seed * direction, axis=-1).mean(axis=-1) * 1000).tolist()
            # Frame by frame: also counts blinks and brow motion that merely moved in time.
            row[f"frame_mm_i{level}"] = float(np.linalg.norm(diff, axis=-1).mean() * 1000)
            row[f"true_mm_i{level}"] = reference[emotion]["mm"][level - 1]
        row["grows"] = row["upper_mm_i1"] < row["upper_mm_i2"] < row["upper_mm_i3"]
        row["grows_along"] = row["along_mm_i1"] < row["along_mm_i2"] < row["along_mm_i3"]
        rows.append(row)
    bm.print_table([{k: v for k, v in r.items() if not k.startswith("along_seeds")} for r in rows],
                   "Upper-face deviation from neutral (mm) by emotion and intensity "
                   "(upper: expression offset; frame: per-frame distance; true: SynthTalk's own offset)")
    at3 = np.array([r["upper_mm_i3"] for r in rows])
    true3 = np.array([r["true_mm_i3"] for r in rows])
    verdict = {
        "grows_with_intensity": sum(r["grows"] for r in rows),
        "grows_along_true_direction": sum(r["grows_along"] for r in rows),
        "of": len(rows),
        "emotion_spread_cv": float(at3.std() / at3.mean()),
        "corr_with_true_offsets_i3": float(np.corrcoef(at3, true3)[0, 1]),
        "ats_beats_mean": accuracy[0]["lip_mm"] < accuracy[1]["lip_mm"],
        **intensity_gain(rows),
    }
    print(verdict)
    payload = {"args": {k: str(v) for k, v in vars(args).items()}, "train_s": train_s,
               "accuracy": accuracy, "emotion": rows, "verdict": verdict}
    print(f"wrote {bm.write_json(args.out, payload)}")


def intensity_gain(rows: list[dict]) -> dict[str, float]:
    """How much of the true intensity effect the model reproduces, as one number per run.

    ``gain_mm``: the along-the-true-direction offset at intensity 3 minus that at intensity 1, averaged
    over emotions (mm); ``true_gain_mm``: the same for SynthTalk's own offsets; ``gain_ratio``: their
    ratio (1: the label scales the face as the generator does; 0: intensity changes nothing). The
    standard error is across noise seeds (each seed's gain averaged over emotions), so it says how much
    of the gain is sampling noise, not how much another training seed would differ.
    """
    per_seed = np.mean([np.subtract(r["along_seeds_mm_i3"], r["along_seeds_mm_i1"]) for r in rows], axis=0)
    true_gain = float(np.mean([r["true_mm_i3"] - r["true_mm_i1"] for r in rows]))
    se = float(per_seed.std(ddof=1) / np.sqrt(len(per_seed))) if len(per_seed) > 1 else float("nan")
    gain = float(per_seed.mean())
    return {"gain_mm": gain, "gain_se_mm": se, "true_gain_mm": true_gain, "gain_ratio": gain / true_gain}


def corpus_spec(args: argparse.Namespace):
    """The size name (SynthTalk's own emotions) or, with ``--emotion-gain``, the control corpus's spec."""
    if args.emotion_gain == 1:
        return args.size
    return dataclasses.replace(synthtalk.SIZES[args.size], emotion_gain=args.emotion_gain)


def training_data(args: argparse.Namespace, corpus) -> str:
    """``synthtalk:SIZE``, or the control corpus prepared once beside it (a folder ``jaxtalk train`` takes)."""
    if args.emotion_gain == 1:
        return f"synthtalk:{args.size}"
    from jaxtalk.data.prepare import is_current, prepare
    from jaxtalk.data.sources import synthtalk_source

    out = args.cache / f"synthtalk-{args.size}-emotion-gain-{args.emotion_gain:g}-seed0"
    if not is_current(out):
        prepare(synthtalk_source(corpus, f"synthtalk:{args.size}:0 emotion_gain={args.emotion_gain:g}"), out)
    return str(out)


def trained_ats(run_dir: Path, args: argparse.Namespace, corpus) -> FittedATS:
    """ATS ``small`` trained by its recipe through :func:`jaxtalk.commands.training.train_run` (the
    recipe's defaults: AdamW 1e-3, 100 warm-up steps, batch 16; ``window``-frame windows every quarter
    window, displacements standardised with the training split's statistics), or loaded from a
    finished run in ``run_dir``."""
    done = latest_checkpoint_step(checkpoint_dir(run_dir)) if checkpoint_dir(run_dir).exists() else None
    if done != args.steps or not (run_dir / RUN_FILE).is_file():
        opts = TrainOptions(model="ats", out_dir=run_dir, data=training_data(args, corpus), preset="small",
                            overrides=(f"max_frames={args.window}", f"window_frames={args.window}"),
                            steps=args.steps, seed=args.train_seed, cache_dir=args.cache)
        train_run(opts)
    else:
        print(f"found the finished run {run_dir} (step {done}): not training again", flush=True)
    run = load_run(run_dir)
    stats = run.record.extra["stats"]
    return FittedATS(run.config, jax.tree.map(jax.numpy.asarray, run.params),
                     data.DisplacementStats(np.asarray(stats["mean"], np.float32), np.asarray(stats["std"], np.float32)),
                     [])


def generator_offsets(face, gain: float = 1.0) -> dict[str, dict[str, list]]:
    """SynthTalk's own upper-face emotion offsets on ``face`` at intensities 1-3, head pose removed
    (times ``gain``, the corpus's ``emotion_gain``).

    Returns, per emotion, ``mm`` (mean landmark offset norm in mm, one per intensity) and ``offset``
    (the (22, 3) upper-face landmark offsets in metres, one per intensity).
    """
    neutral = data.neutral_landmarks(face)
    out = {}
    for emotion in EMOTIONS[1:]:
        out[emotion] = {"mm": [], "offset": []}
        for level in (1, 2, 3):
            offset = data.without_head_pose((gain * face_offset(emotion, level))[None].astype(np.float32))[0]
            delta = np.asarray(face.landmarks(jax.numpy.asarray(offset)))[UPPER] - neutral[UPPER]
            out[emotion]["mm"].append(float(np.linalg.norm(delta, axis=-1).mean() * 1000))
            out[emotion]["offset"].append(delta)
    return out


if __name__ == "__main__":
    main()
