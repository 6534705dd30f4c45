"""FreeTalk's evaluation protocols (``jaxtalk eval`` on an ATS or STM run; :attr:`jaxtalk.runs.ModelSpec.evaluate`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from jaxtalk.metrics.evaluation import EvalSettings, EvalTable, method_rows
from jaxtalk.metrics.landmarks import landmark_metrics

__all__ = ["evaluate_ats", "evaluate_stm"]

# Fixed batch of ATS windows per sampler call (one compiled program for every clip).
_ATS_BATCH = 8
# Frames per STM decoder call (STM decodes frame by frame, so chunks of a fixed size compile once).
_STM_CHUNK = 50


def evaluate_ats(run: Any, data: Any, split: str, opts: EvalSettings, echo: Callable[[str], None]
                 ) -> tuple[int, list[EvalTable]]:
    """ATS on a split of prepared data: landmark displacements (68 landmarks on the built-in face, head pose
    removed) sampled for consecutive training-length windows of each clip (whole clips for a run trained on
    whole clips), de-standardised with the run's statistics, and scored by LVE over the mouth landmarks 48-67,
    mean landmark error and jitter, beside the mean pose, neutral, the oracle and the data's own jitter.

    Raises:
        ValueError: a split without a clip of the run's window, data without landmark displacements.
    """
    import jax

    from jaxtalk.face import builtin_face
    from jaxtalk.data.batching import window_starts
    from jaxtalk.face.motion import landmark_motion, without_head_pose
    from jaxtalk.models.freetalk.data import DisplacementStats
    from jaxtalk.models.freetalk.emotions import NEUTRAL, emotion_ids
    from jaxtalk.models.freetalk.fit import FittedATS, sample_displacements

    extra = run.record.extra
    stats = DisplacementStats(mean=np.asarray(extra["stats"]["mean"], np.float32),
                              std=np.asarray(extra["stats"]["std"], np.float32))
    # A run trained on whole clips (window 0) is scored on whole clips, sampled one at a time (each up to
    # max_frames long: a longer clip in max_frames pieces); a windowed run on windows of its length.
    whole = int(extra["window"]) == 0
    window = run.config.max_frames if whole else int(extra["window"])
    clips = [i for i in data.split(split) if whole or data.clips[i]["frames"] >= window]
    if not clips:
        raise ValueError(f"split {split!r} of {data.root} has no clip of at least {window} frames (the run's window)")
    chosen = clips[: opts.max_clips]
    fitted = FittedATS(run.config, run.params, stats, [])
    face = builtin_face(0)
    recs, items = [], []  # items: (record index, start)
    for n, i in enumerate(chosen):
        rec = data.record(i, ("landmarks", "speech", "oracle"))
        if "landmarks" not in rec:
            raise ValueError(f"{data.root} has no landmark displacements (prepared without --landmarks)")
        if "oracle" in rec:
            rec["oracle_landmarks"] = landmark_motion(face, without_head_pose(rec.pop("oracle")))
        recs.append(rec)
        frames = rec["landmarks"].shape[0]
        items += ([(n, st) for st in range(0, frames, window)] if whole
                  else [(n, st) for st in window_starts(frames, window, window, pad_short=False)])
    lengths = [min(window, recs[n]["landmarks"].shape[0] - st, recs[n]["speech"].shape[0] - st) for n, st in items]
    echo(f"sampling {len(items)} {'whole clips (at most ' if whole else 'windows of '}{window} frames"
         f"{')' if whole else ''} from {len(chosen)} {split} clips of {data.root} with ATS (step {run.step})")
    key = jax.random.key(opts.seed)
    preds = []
    per_call = 1 if whole else _ATS_BATCH  # whole clips differ in length: one call each
    for b in range(0, len(items), per_call):
        batch = items[b:b + per_call]
        batch = batch + [batch[-1]] * (per_call - len(batch))  # one compiled shape
        audio = np.stack([recs[n]["speech"][st:st + lengths[b]] for n, st in batch]).astype(np.float32)
        emotion = np.concatenate([emotion_ids(data.clips[chosen[n]]["emotion"] or NEUTRAL, run.config.emotions)
                                  for n, _ in batch])
        intensity = np.asarray([data.clips[chosen[n]]["intensity"] if data.clips[chosen[n]]["intensity"] is not None
                                else 1.0 for n, _ in batch], np.float32)
        out = sample_displacements(fitted, audio, emotion, intensity, jax.random.fold_in(key, b))
        preds += list(np.asarray(out, np.float32)[: min(per_call, len(items) - b)])
    per: dict[str, list[dict[str, float | None]]] = {"ats (sampled)": [], "mean pose": [], "neutral": [], "oracle": [],
                                                     "ground truth": []}
    with_oracle = all("oracle_landmarks" in r for r in recs)
    for (n, st), pred, length in zip(items, preds, lengths):
        gt = recs[n]["landmarks"][st:st + length].astype(np.float32)
        per["ats (sampled)"].append(landmark_metrics(pred, gt))
        per["mean pose"].append(landmark_metrics(np.broadcast_to(stats.mean, gt.shape).copy(), gt))
        per["neutral"].append(landmark_metrics(np.zeros_like(gt), gt))
        if with_oracle:
            per["oracle"].append(landmark_metrics(recs[n]["oracle_landmarks"][st:st + length], gt))
        per["ground truth"].append({"LVE_mm2": None, "LE_mm": None, "jitter_mm": landmark_metrics(gt, gt)["jitter_mm"]})
    rows = method_rows(per, lengths, count="windows")
    return len(chosen), [EvalTable(f"ATS on {split} ({data.root.name}, {len(chosen)} clips), 68 landmarks on the "
                                   "built-in face (head pose removed); LVE over the mouth landmarks 48-67", rows)]


def evaluate_stm(run: Any, data: Any, split: str, opts: EvalSettings, echo: Callable[[str], None]
                 ) -> tuple[int, list[EvalTable]]:
    """STM on a split of prepared data: the split's motion (head pose removed) rendered on each of the run's
    meshes, the true landmark displacements mapped to vertex displacements, scored by MVE, LVE over the
    mesh's lip region and jitter, beside neutral and the data's own jitter.

    Raises:
        ValueError: a split without a clip with motion.
    """
    from jaxtalk.metrics import jitter, lve, mve
    from jaxtalk.models.freetalk import stm
    from jaxtalk.models.freetalk.data import face_mesh, without_head_pose

    config, extra = run.config, run.record.extra
    clips = data.split(split)
    if not clips:
        raise ValueError(f"split {split!r} of {data.root} has no clip with motion")
    chosen = clips[: opts.max_clips]
    motions = [without_head_pose(np.asarray(data.record(i, ("motion",))["motion"], np.float32)) for i in chosen]
    frames = [m.shape[0] for m in motions]
    echo(f"mapping the true landmarks of {len(chosen)} {split} clips of {data.root} onto "
         f"{len(extra['meshes'])} meshes with STM (step {run.step})")
    rows = []
    for identity, kind in extra["meshes"]:
        fm = face_mesh(int(identity), kind, resolution=extra.get("resolution", "low"))
        mesh = stm.prepare_mesh(fm.vertices, fm.faces, config)
        features = stm.stm_mesh_features(run.params, config, mesh)
        lips = fm.region("lips")
        per: dict[str, list[dict[str, float | None]]] = {"stm": [], "neutral": [], "ground truth": []}
        for motion in motions:
            lms, verts = fm.motion(motion)
            t = lms.shape[0]
            pad = -t % _STM_CHUNK
            padded = np.concatenate([lms, np.zeros((pad, *lms.shape[1:]), np.float32)])
            pred = np.concatenate([np.asarray(stm.stm_decode(run.params, config, features,
                                                             padded[c:c + _STM_CHUNK], mesh))
                                   for c in range(0, t + pad, _STM_CHUNK)])[:t]
            for name, x in (("stm", pred), ("neutral", np.zeros_like(verts))):
                per[name].append({"MVE_mm": float(mve(x, verts)) * 1e3, "LVE_mm2": float(lve(x, verts, lips)) * 1e6,
                                  "jitter_mm": float(jitter(x)) * 1e3})
            per["ground truth"].append({"MVE_mm": None, "LVE_mm2": None, "jitter_mm": float(jitter(verts)) * 1e3})
        rows += method_rows(per, frames, lead={"mesh": f"{fm.name} ({fm.vertices.shape[0]} v)"})
    return len(chosen), [EvalTable(f"STM on {split} ({data.root.name}): the true landmarks mapped to each training "
                                   "mesh (head pose removed)", rows)]
