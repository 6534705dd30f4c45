"""FreeTalk STM across topologies: metrics on seen and held-out topologies and identities (SynthTalk).

STM is trained on some (identity, topology) meshes of the built-in face with its recipe
(``jaxtalk.models.freetalk.recipe.train_stm``: 16-frame windows of the prepared SynthTalk training
motion rendered on those meshes, as ``jaxtalk train stm`` trains on its three default meshes) and
evaluated on SynthTalk's test clips, fed the ground-truth landmark motion (this isolates STM; ATS is measured in
``freetalk_emotion.py``), on
  * seen meshes (training identities and topologies, unseen clips),
  * held-out meshes: topologies and identities never seen in training.
Beside the model: the mean-pose baseline (the mesh's mean training displacement) and the oracle
(SynthTalk's deterministic motion, the best any model can do from audio; here STM sees the true
landmarks, so it can beat the oracle on blinks). Bar: held-out LVE within 20% of seen LVE.

Metrics: LVE, MVE, FDD, DTW, DFD, delta_M, delta_Cd (``jaxtalk.metrics``), in millimetres
(squared where the metric is squared). Lip and upper-face vertices of a remeshed face are those whose
nearest base corner is in the base region (``FaceMesh.region``). Head pose is removed from the
motion (FreeTalk animates the face; see ``data.without_head_pose``).

Usage: python experiments/freetalk_topology.py [--size tiny|small] [--steps N] [--batch N]
       [--resolution low] [--cache DIR] [--out PATH]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
import numpy as np

from jaxtalk import benchmarking as bm
from jaxtalk import metrics
from jaxtalk.data import synthtalk
from jaxtalk.data.loader import open_data
from jaxtalk.models.freetalk import data, stm
from jaxtalk.models.freetalk import recipe as freetalk_recipe
from jaxtalk.models.freetalk.config import STMConfig
from jaxtalk.runs import RunSettings
from jaxtalk.train import LoopSettings, OptimConfig

# The recipe's training meshes (seen) and the held-out ones: the subdivided topology tests a
# resolution never seen in training; each retriangulation is a fresh random remesh (seeded by the
# identity), so (3, "retriangulated") is a connectivity never seen in training.
SEEN = list(freetalk_recipe.STM_MESHES)
HELD_OUT = list(freetalk_recipe.STM_HELD_OUT)


def evaluate(pred: np.ndarray, gt: np.ndarray, rest: np.ndarray, lips: np.ndarray, upper: np.ndarray) -> dict:
    p, g = pred + rest, gt + rest
    mm = 1000.0
    return {
        "LVE_mm2": float(metrics.lve(p, g, lips)) * mm * mm,
        "MVE_mm": float(metrics.mve(p, g)) * mm,
        "FDD_mm2": float(metrics.fdd(p, g, rest, upper)) * mm * mm,
        "DTW_mm": float(metrics.dtw(p, g, lips)) * mm,
        "DFD_mm": float(metrics.dfd(p, g, lips)) * mm,
        "dM_mm2": float(metrics.delta_m(p, g)) * mm * mm,
        "dCd": float(metrics.delta_cd(p, g)),
    }


# STM on SynthTalk: AdamW 2e-3 (the recipe's default is 1e-3 for its longer CLI runs), batch 4.
LR = 2e-3


def train_stm(prepared, corpus, cfg: STMConfig, meshes: list[tuple[int, str]], steps: int, *, resolution: str,
              batch_size: int = 4):
    """Train STM with its recipe on the prepared corpus's training motion rendered on ``meshes``
    ((identity, topology) pairs at ``resolution``); returns ``(params, mean vertex displacement of
    each mesh over the training clips)`` (the means are the mean-pose baseline)."""
    optim = OptimConfig(lr=LR, warmup_steps=min(50, steps // 10), total_steps=steps)
    run = RunSettings(steps=steps, batch_size=batch_size, loop=LoopSettings(log_every=max(1, steps // 20)))
    result = freetalk_recipe.train_stm(cfg, prepared, optim, key=jax.random.key(0), run=run, meshes=tuple(meshes),
                                       resolution=resolution)
    faces = [data.face_mesh(i, k, resolution=resolution) for i, k in meshes]
    means = [np.concatenate([m.motion(data.without_head_pose(corpus.motion(c)))[1] for c in corpus.split("train")])
             .mean(axis=0) for m in faces]
    return result.state.eval_params, means


def load_data(size: str, cache: Path):
    """The SynthTalk corpus (in memory: test clips, oracle, baselines) and its prepared copy (training);
    one generation serves both (open_data prepares from ``cache/synthtalk``)."""
    corpus = synthtalk.generate(size, seed=0, cache_dir=Path(cache) / "synthtalk")
    return corpus, open_data(f"synthtalk:{size}", cache_dir=cache)


def evaluate_mesh(corpus, cfg: STMConfig, params, m: data.FaceMesh, mean: np.ndarray, clips: list[int]) -> dict:
    """Mean metrics over ``clips`` for the model, the mean pose and the oracle on one mesh."""
    mesh = stm.prepare_mesh(m.vertices, m.faces, cfg)
    features = stm.stm_mesh_features(params, cfg, mesh)
    rest = np.asarray(m.vertices, np.float32)
    lips, upper = m.region("lips"), m.region("upper_face")
    results: dict[str, list] = {"model": [], "mean_pose": [], "oracle": []}
    motions = [m.motion(data.without_head_pose(corpus.motion(clip))) for clip in clips]
    # STM is per frame, so all clips are decoded in ONE call (one compiled program per mesh rather
    # than one per clip length), then split back into clips.
    decoded = np.asarray(stm.stm_decode(params, cfg, features, np.concatenate([lm for lm, _ in motions]), mesh))
    splits = np.cumsum([len(lm) for lm, _ in motions])[:-1]
    for clip, (lm, gt), pred in zip(clips, motions, np.split(decoded, splits)):
        oracle = m.motion(data.without_head_pose(corpus.oracle(clip)))[1]
        results["model"].append(evaluate(pred, gt, rest, lips, upper))
        results["mean_pose"].append(evaluate(np.broadcast_to(mean, gt.shape), gt, rest, lips, upper))
        results["oracle"].append(evaluate(oracle, gt, rest, lips, upper))
    return {method: {k: float(np.mean([r[k] for r in rs])) for k in rs[0]} for method, rs in results.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="tiny")
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--batch", type=int, default=4, help="16-frame windows per step")
    parser.add_argument("--resolution", default="low")
    parser.add_argument("--test-clips", type=int, default=4)
    parser.add_argument("--cache", type=Path, default=Path(".cache/prepared"),
                        help="SynthTalk and its prepared copy (the default is jaxtalk train's)")
    parser.add_argument("--out", type=Path, default=Path("experiments/results/freetalk_topology.json"))
    args = parser.parse_args()
    t0 = time.time()
    corpus, prepared = load_data(args.size, args.cache)
    cfg = STMConfig.small()
    seen = [data.face_mesh(i, k, resolution=args.resolution) for i, k in SEEN]
    held = [data.face_mesh(i, k, resolution=args.resolution) for i, k in HELD_OUT]
    params, means = train_stm(prepared, corpus, cfg, SEEN, args.steps, resolution=args.resolution, batch_size=args.batch)
    print(f"trained {args.steps} steps in {time.time() - t0:.0f} s", flush=True)
    clips = corpus.split("test")[: args.test_clips]
    rows = []
    for split, meshes in (("seen", seen), ("held-out", held)):
        for i, m in enumerate(meshes):
            if split == "seen":
                mean = means[i]
            else:  # the held-out mesh's own mean training displacement: a generous baseline
                mean = np.concatenate([m.motion(data.without_head_pose(corpus.motion(c)))[1]
                                       for c in corpus.split("train")[:4]]).mean(axis=0)
            for method, values in evaluate_mesh(corpus, cfg, params, m, mean, clips).items():
                rows.append({"mesh": m.name, "split": split, "V": len(m.vertices), "method": method, **values})
    bm.print_table(rows, "STM on SynthTalk test clips (ground-truth landmarks in)")
    seen_lve = np.mean([r["LVE_mm2"] for r in rows if r["split"] == "seen" and r["method"] == "model"])
    held_lve = np.mean([r["LVE_mm2"] for r in rows if r["split"] == "held-out" and r["method"] == "model"])
    verdict = {"seen_LVE": seen_lve, "held_out_LVE": held_lve, "ratio": held_lve / seen_lve,
               "bar_within_20pct": bool(held_lve <= 1.2 * seen_lve)}
    print(verdict)
    print(f"wrote {bm.write_json(args.out, {'rows': rows, 'verdict': verdict, 'steps': args.steps, 'batch': args.batch})}")


if __name__ == "__main__":
    main()
