"""FreeTalk STM across topologies: metrics on seen and held-out topologies and identities (SynthTalk).

STM is trained on some (identity, topology) meshes of the built-in face and evaluated on SynthTalk's
test clips, fed the ground-truth landmark motion (this isolates STM; ATS is measured in
``freetalk_emotion.py``), on
  * seen meshes (training identities and topologies, unseen clips),
  * held-out meshes: topologies and identities never seen in training.
Beside the model: the mean-pose baseline (the mesh's mean training displacement) and the oracle
(SynthTalk's deterministic motion, the best any model can do from audio; here STM sees the true
landmarks, so it can beat the oracle on blinks). Bar (issue 5): held-out LVE within 20% of seen LVE.

Metrics: LVE, MVE, FDD, DTW, DFD, delta_M, delta_Cd (``jaxtalk.metrics``), in millimetres (squared
where the metric is squared). Lip and upper-face vertices of a remeshed face are those whose base triangle has
at least two corners in the base region.

Usage: python experiments/freetalk_topology.py [--size tiny|small] [--steps N] [--resolution low]
       [--out PATH]
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
from jaxtalk.face import builtin_face
from jaxtalk.geometry.topology import make_variant
from jaxtalk.models.freetalk import data, stm
from jaxtalk.models.freetalk.config import STMConfig
from jaxtalk.models.freetalk.fit import fit_stm
from jaxtalk.train import OptimConfig

SEEN = [(0, "base"), (1, "decimated"), (2, "subdivided")]
HELD_OUT = [(0, "retriangulated"), (3, "base"), (3, "retriangulated")]


def build_mesh(identity: int, kind: str, resolution: str):
    face = builtin_face(identity, resolution=resolution)
    template, faces = np.asarray(face.template, np.float64), np.asarray(face.faces)
    variant = None if kind == "base" else make_variant(template, faces, kind, seed=identity)
    verts = template if variant is None else variant.vertices
    tris = faces if variant is None else variant.faces

    def region(name: str) -> np.ndarray:
        base = np.asarray(face.regions[name])
        if variant is None:
            return base
        corners = variant.base_faces[variant.face_index]
        return np.flatnonzero(np.isin(corners, base).sum(axis=1) >= 2)

    return {"face": face, "variant": variant, "vertices": verts, "faces": tris,
            "lips": region("lips"), "upper": region("upper_face"), "name": f"id{identity}/{kind}"}


def evaluate(pred: np.ndarray, gt: np.ndarray, rest: np.ndarray, mesh: dict) -> dict:
    p, g = pred + rest, gt + rest
    mm = 1000.0
    return {
        "LVE_mm2": float(metrics.lve(p, g, mesh["lips"])) * mm * mm,
        "MVE_mm": float(metrics.mve(p, g)) * mm,
        "FDD_mm2": float(metrics.fdd(p, g, rest, mesh["upper"])) * mm * mm,
        "DTW_mm": float(metrics.dtw(p, g, mesh["lips"])) * mm,
        "DFD_mm": float(metrics.dfd(p, g, mesh["lips"])) * mm,
        "dM_mm2": float(metrics.delta_m(p, g)) * mm * mm,
        "dCd": float(metrics.delta_cd(p, g)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="tiny")
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--resolution", default="low")
    parser.add_argument("--window", type=int, default=8)
    parser.add_argument("--test-clips", type=int, default=4)
    parser.add_argument("--cache", default=None)
    parser.add_argument("--out", type=Path, default=Path("experiments/results/freetalk_topology.json"))
    args = parser.parse_args()
    t0 = time.time()
    corpus = synthtalk.generate(args.size, seed=0, cache_dir=args.cache)
    cfg = STMConfig.small()
    meshes = [build_mesh(i, k, args.resolution) for i, k in SEEN + HELD_OUT]
    vmax = max(len(m["vertices"]) for m in meshes[: len(SEEN)])
    prepared = [stm.prepare_mesh(m["vertices"], m["faces"], cfg, num_vertices=vmax, degree=16)
                for m in meshes[: len(SEEN)]]
    tracks = []
    for idx, m in enumerate(meshes[: len(SEEN)]):
        for clip in corpus.split("train"):
            lm, vd, _ = data.mesh_motion(m["face"], corpus.motion(clip), m["variant"])
            tracks.append((idx, lm, vd))
    windows = data.stm_windows(tracks, vmax, window=args.window, hop=args.window)
    mean_disp = {i: np.concatenate([t[2] for t in tracks if t[0] == i]).mean(axis=0) for i in range(len(SEEN))}
    print(f"data ready: {windows['vertices'].shape} in {time.time() - t0:.0f} s", flush=True)
    optim = OptimConfig(lr=2e-3, warmup_steps=min(50, args.steps // 10), total_steps=args.steps)
    params, history = fit_stm(cfg, prepared, windows, optim, jax.random.key(0), progress=True)
    print(f"trained {args.steps} steps, final loss {history[-1]['loss']:.4f}, {time.time() - t0:.0f} s", flush=True)

    rows = []
    for idx, m in enumerate(meshes):
        mesh = stm.prepare_mesh(m["vertices"], m["faces"], cfg)
        features = stm.stm_mesh_features(params, cfg, mesh)
        rest = np.asarray(m["vertices"], np.float32)
        results = {"model": [], "mean_pose": [], "oracle": []}
        mean = mean_disp.get(idx)
        if mean is None:  # held-out mesh: its mean displacement over the training clips' motion
            mean = np.concatenate([data.mesh_motion(m["face"], corpus.motion(c), m["variant"])[1]
                                   for c in corpus.split("train")[:4]]).mean(axis=0)
        for clip in corpus.split("test")[: args.test_clips]:
            lm, gt, _ = data.mesh_motion(m["face"], corpus.motion(clip), m["variant"])
            pred = np.asarray(stm.stm_decode(params, cfg, features, lm, mesh))
            oracle = data.mesh_motion(m["face"], corpus.oracle(clip), m["variant"])[1]
            results["model"].append(evaluate(pred, gt, rest, m))
            results["mean_pose"].append(evaluate(np.broadcast_to(mean, gt.shape), gt, rest, m))
            results["oracle"].append(evaluate(oracle, gt, rest, m))
        for method, rs in results.items():
            row = {"mesh": m["name"], "split": "seen" if idx < len(SEEN) else "held-out",
                   "V": len(m["vertices"]), "method": method}
            row.update({k: float(np.mean([r[k] for r in rs])) for k in rs[0]})
            rows.append(row)
    bm.print_table(rows, "STM on SynthTalk test clips (ground-truth landmarks in)")
    seen = np.mean([r["LVE_mm2"] for r in rows if r["split"] == "seen" and r["method"] == "model"])
    held = np.mean([r["LVE_mm2"] for r in rows if r["split"] == "held-out" and r["method"] == "model"])
    verdict = {"seen_LVE": seen, "held_out_LVE": held, "ratio": held / seen, "bar_within_20pct": held <= 1.2 * seen}
    print(verdict)
    print(f"wrote {bm.write_json(args.out, {'rows': rows, 'verdict': verdict, 'steps': args.steps})}")


if __name__ == "__main__":
    main()
