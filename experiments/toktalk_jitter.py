"""Why TokTalk's many-step samples jitter more than the data, and which sampling settings bring them back.

For each RUN (a TokTalk run folder trained on SynthTalk, e.g. ``jaxtalk-demo``): the first ``--clips``
test monologues of the run's corpus, the style from another clip of the same speaker, streamed with the
run's own chunk and guidance. Per Euler step count x starting-noise temperature: LVE (mm^2, built-in
face), vertex jitter over all frames and near chunk boundaries (mm/frame^2, ``jaxtalk.metrics.jitter``)
beside the ground truth's.

The sampled part: a sample at temperature T minus the sample at T = 0 from the same key is what the
starting noise adds. Its RMS vertex displacement (mm) and its jitter give its roughness (jitter per mm
of motion); SynthTalk's own undetermined motion (the ground truth minus the generator's noise-free
oracle: blinks, head drift, the speaker's noise) gives the data's. A sampled part far rougher than the
data's undetermined motion is noise the decoder has not shaped into motion, and it is what raises the
samples' jitter above the data's.

Usage: ``python experiments/toktalk_jitter.py RUN [RUN ...] [--clips 8] [--sample-steps 1,10]
[--temperatures 0,0.25,0.5,1] [--out experiments/results/toktalk_jitter.json]``
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import numpy as np

from jaxtalk.benchmarking import machine_info, print_table, write_json
from jaxtalk.metrics import jitter, lve
from jaxtalk.models import toktalk as tt
from jaxtalk.runs import RunRecord, load_run
from toktalk_common import RESULTS, load_corpus, style_clip_for


def _corpus_of(record: RunRecord):
    """The SynthTalk corpus a run was trained on, from its data spec ``synthtalk:SIZE[:SEED]``."""
    spec = record.data["spec"]
    parts = spec.split(":")
    if parts[0] != "synthtalk":
        raise SystemExit(f"{spec}: this experiment needs a run trained on SynthTalk (it scores against its oracle)")
    return load_corpus(parts[1], int(parts[2]) if len(parts) > 2 else 0)


def _rough(v: np.ndarray) -> tuple[float, float]:
    """(RMS displacement from its own mean, mm; jitter, mm/frame^2) of a vertex track ``(T, V, 3)``."""
    rms = float(np.sqrt(np.mean(np.sum(np.square(v - v.mean(0)), -1)))) * 1e3
    return rms, float(jitter(v)) * 1e3


def measure(run_dir: Path, clips: int, steps: list[int], temps: list[float]) -> dict:
    record = RunRecord.load(run_dir)
    run = load_run(run_dir, best=True)
    config, params = run.config, run.params
    corpus = _corpus_of(record)
    face = corpus.face(0)
    lips = np.asarray(face.regions["lips"])
    chosen = [c for c in corpus.split("test") if not corpus.clips[c].is_conversation][:clips]
    rng = np.random.default_rng(0)
    cells: dict[tuple[int, float], list[dict]] = {(n, t): [] for n in steps for t in temps}
    truth, undetermined = [], []
    for i, c in enumerate(chosen):
        gt = np.asarray(corpus.motion(c), np.float32)
        style = tt.encode_style(params, config, style_clip_for(corpus, c, 4 * config.style_frames, rng))
        tokens = np.asarray(corpus.tokens(c, "A").embeddings, np.float32)[None]
        v_gt = np.asarray(face.vertices_seq(gt))
        v_free = np.asarray(face.vertices_seq(np.asarray(corpus.oracle(c), np.float32)))
        truth.append({"frames": len(gt), "jitter": float(jitter(v_gt)) * 1e3})
        rms, jit = _rough(v_gt - v_free)
        undetermined.append({"frames": len(gt), "rms": rms, "jitter": jit})
        for n in steps:
            by_temp = {}
            for t in temps:
                out = np.asarray(tt.stream(params, config, tokens, style, jax.random.key(i), sample_steps=n,
                                           temperature=t))[0]
                k = min(len(out), len(gt))
                by_temp[t] = np.asarray(face.vertices_seq(out[:k]))
                bounds = list(range(config.chunk_frames, k - 1, config.chunk_frames))
                cells[(n, t)].append({"frames": k, "lve_mm2": float(lve(by_temp[t], v_gt[:k], lips)) * 1e6,
                                      "jitter": float(jitter(by_temp[t])) * 1e3,
                                      "jitter_boundary": float(jitter(by_temp[t], bounds)) * 1e3})
            for t in temps:
                if t > 0 and 0.0 in by_temp:
                    rms, jit = _rough(by_temp[t] - by_temp[0.0])
                    cells[(n, t)][-1].update(sampled_rms=rms, sampled_jitter=jit)

    def mean(rows: list[dict], key: str) -> float:
        w = np.array([r["frames"] for r in rows], float)
        return float(np.sum(w * np.array([r[key] for r in rows])) / w.sum())

    table = []
    for (n, t), rows in cells.items():
        row = {"sample_steps": n, "temperature": t, "lve_mm2": mean(rows, "lve_mm2"), "jitter": mean(rows, "jitter"),
               "jitter_boundary": mean(rows, "jitter_boundary")}
        if "sampled_rms" in rows[0]:
            row.update(sampled_rms_mm=mean(rows, "sampled_rms"), sampled_jitter=mean(rows, "sampled_jitter"))
            row["sampled_roughness"] = row["sampled_jitter"] / row["sampled_rms_mm"]
        table.append(row)
    data = {"jitter": mean(truth, "jitter"), "undetermined_rms_mm": mean(undetermined, "rms"),
            "undetermined_jitter": mean(undetermined, "jitter")}
    data["undetermined_roughness"] = data["undetermined_jitter"] / data["undetermined_rms_mm"]
    return {"run": str(run_dir), "step": run.step, "data": record.data["spec"], "clips": [int(c) for c in chosen],
            "config": {k: getattr(config, k) for k in ("sample_steps", "temperature", "cfg_scale", "noise_frames",
                                                       "chunk_frames")},
            "ground_truth": data, "table": table}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+")
    parser.add_argument("--clips", type=int, default=8)
    parser.add_argument("--sample-steps", default="1,10")
    parser.add_argument("--temperatures", default="0,0.25,0.5,1")
    parser.add_argument("--out", type=Path, default=RESULTS / "toktalk_jitter.json")
    args = parser.parse_args()
    steps = [int(s) for s in args.sample_steps.split(",")]
    temps = [float(t) for t in args.temperatures.split(",")]
    results = []
    for run_dir in args.runs:
        res = measure(run_dir, args.clips, steps, temps)
        print_table(res["table"], f"{run_dir} (step {res['step']}): ground truth jitter {res['ground_truth']['jitter']:.3f}, "
                                  f"undetermined motion's roughness {res['ground_truth']['undetermined_roughness']:.3f}")
        results.append(res)
    write_json(args.out, {"machine": machine_info(), "args": {k: str(v) for k, v in vars(args).items()},
                          "runs": results})


if __name__ == "__main__":
    main()
