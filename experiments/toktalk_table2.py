"""TokTalk Table 2 on SynthTalk: the decoder conditioned on audio-LLM-like tokens vs frame-level log-mel.

The paper's Table 2 compares its token conditioning with frame-level speech features under the same
decoder. Here both conditions go through the user's path, the generic dataset layout:

* ``tokens``: ``jaxtalk data --size SIZE --out DIR`` writes SynthTalk with its base token stream
  (12.5 Hz x 64, the audio-LLM-like stream TokTalk is built for);
* ``logmel``: the same clips (the wav, motion and metadata files are linked, not copied) with
  ``<clip>.tokens.npy`` replaced by an 80-bin log-mel spectrogram of the clip's audio
  (:func:`jaxtalk.audio.melspec.log_mel`, 10-ms hop, 4 frames averaged -> 25 Hz, one vector per motion
  frame), standardised per bin with the training split's mean and standard deviation.

Each condition is prepared (``jaxtalk prepare``), trained with the default ``small`` recipe for the same
number of steps and seeds (only ``speech_dim`` and ``token_rate`` differ), validated by streaming the
val clips, and scored on the test clips (held-out speakers) by ``jaxtalk eval`` at 1 and 10 Euler steps,
for the newest and the validation-chosen checkpoint. Every step resumes: run it again to continue.

A HuBERT-architecture encoder (the paper's third row) needs pretrained weights, which nothing here may
download; a randomly initialised one would not be the paper's comparison, so it is not run.

    python experiments/toktalk_table2.py --root /tmp/t2 --steps 3000 --seeds 0,1 \
        --out experiments/results/toktalk_table2.json
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import time
from pathlib import Path

import numpy as np

from jaxtalk.benchmarking import machine_info, print_table, write_json

LOGMEL_RATE = 25.0
N_MELS = 80
POOL = 4  # 100-Hz log-mel frames averaged per 25-Hz vector


def run(cmd: list[str]) -> None:
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)


def logmel_folder(src: Path, dst: Path) -> None:
    """``dst``: the clips of ``src`` with log-mel vectors (standardised by the train split) as tokens."""
    import jax.numpy as jnp

    from jaxtalk.audio.io import load_audio
    from jaxtalk.audio.melspec import log_mel
    from jaxtalk.types import AUDIO_SAMPLE_RATE

    if (dst / "tokens.json").is_file():
        return
    tmp = dst.with_name(dst.name + ".partial")
    tmp.mkdir(parents=True, exist_ok=True)
    with open(src / "metadata.csv") as f:
        meta = list(csv.DictReader(f))
    feats = {}
    for row in meta:
        clip = row["clip"]
        audio = load_audio(src / f"{clip}.wav", AUDIO_SAMPLE_RATE)
        frames = np.load(src / f"{clip}.npz")
        motion = next(frames[k] for k in ("params56", "exp", "vertices") if k in frames)
        mel = np.asarray(log_mel(jnp.asarray(audio), AUDIO_SAMPLE_RATE, n_mels=N_MELS))
        n = mel.shape[0] // POOL
        pooled = mel[: n * POOL].reshape(n, POOL, N_MELS).mean(axis=1)
        t = motion.shape[0]
        # One vector per motion frame: the centred STFT gives a frame or two more or less than the motion.
        pooled = pooled[:t] if n >= t else np.concatenate([pooled, np.repeat(pooled[-1:], t - n, axis=0)])
        feats[clip] = pooled.astype(np.float32)
    train = np.concatenate([feats[r["clip"]] for r in meta if r.get("split") == "train"])
    mean, std = train.mean(axis=0), train.std(axis=0) + 1e-5
    for row in meta:
        clip = row["clip"]
        np.save(tmp / f"{clip}.tokens.npy", (feats[clip] - mean) / std)
        for suffix in (".wav", ".npz"):
            link = tmp / f"{clip}{suffix}"
            if not link.exists():
                os.symlink((src / f"{clip}{suffix}").resolve(), link)
    if not (tmp / "metadata.csv").exists():  # a rerun after an interrupted one
        os.symlink((src / "metadata.csv").resolve(), tmp / "metadata.csv")
    (tmp / "tokens.json").write_text(json.dumps({"rate": LOGMEL_RATE}))
    tmp.rename(dst)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, required=True, help="data, prepared folders and runs go here")
    ap.add_argument("--size", default="small")
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--seeds", default="0,1")
    ap.add_argument("--conditions", default="tokens,logmel")
    ap.add_argument("--eval-every", type=int, default=500)
    ap.add_argument("--clips", type=int, default=20, help="val clips streamed in training and test clips scored")
    ap.add_argument("--cache-dir", default=".cache/prepared", help="where SynthTalk is generated and cached")
    ap.add_argument("--out", type=Path, default=Path("experiments/results/toktalk_table2.json"))
    args = ap.parse_args()
    t0 = time.time()
    data = args.root / "data"
    if not (data / "tokens" / "metadata.csv").is_file():
        run(["jaxtalk", "data", "--size", args.size, "--cache-dir", f"{args.cache_dir}/synthtalk",
             "--out", str(data / "tokens")])
    logmel_folder(data / "tokens", data / "logmel")
    extra = {"tokens": [], "logmel": ["--set", f"speech_dim={N_MELS}", "--set", f"token_rate={LOGMEL_RATE:g}"]}
    rows = []
    for cond in args.conditions.split(","):
        prepared = args.root / "prepared" / cond
        run(["jaxtalk", "prepare", str(data / cond), "--out", str(prepared)])
        for seed in (int(s) for s in args.seeds.split(",")):
            out = args.root / "runs" / f"{cond}-s{seed}"
            run(["jaxtalk", "train", "toktalk", "--data", str(prepared), "--steps", str(args.steps),
                 "--seed", str(seed), "--out", str(out), "--set", f"eval_every={args.eval_every}",
                 "--set", f"val_clips={args.clips}", *extra[cond]])
            for which in ("last", "best"):
                report = out / f"test_{which}.json"
                if not report.is_file():
                    run(["jaxtalk", "eval", str(out), "--split", "test", "--max-clips", str(args.clips),
                         "--sample-steps", "1", "--sample-steps", "10", "--json", str(report),
                         *(["--best"] if which == "best" else [])])
                rows += [{"condition": cond, "seed": seed, "checkpoint": which, **r}
                         for r in table_rows(json.loads(report.read_text()))]
    print_table(rows, f"TokTalk conditioned on tokens vs log-mel, test split ({args.clips} clips of held-out speakers)")
    write_json(args.out, {"args": {k: str(v) for k, v in vars(args).items()}, "machine": machine_info(),
                          "wall_s": time.time() - t0, "rows": rows})
    print(f"wrote {args.out}")


def table_rows(report: dict) -> list[dict]:
    """The rows of ``jaxtalk eval --json``'s tables (method, MSE, LVE, MVE, FDD, MOD, jitter), with the
    checkpoint step."""
    return [{"step": report["step"], **row} for table in report["tables"] for row in table["rows"]]


if __name__ == "__main__":
    main()
