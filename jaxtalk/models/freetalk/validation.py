"""FreeTalk's validations as users measure the models: ATS sampled with DDIM and scored in landmarks, STM
on meshes it never trained on and scored in vertices.

The denoising loss on validation windows says how well the model predicts the noise at random
timesteps; a user samples the whole DDIM chain and measures the landmarks. :func:`sampled_validation`
gives the training loop what ``jaxtalk eval`` reports for an ATS run, for the run to select its best
checkpoint by: each evaluation samples one window of each of a fixed, evenly spread set of clips of the
split (the run's own windows: 50-frame windows, or whole clips for a whole-clip run), with the
same starting noise every time, at the config's DDIM step count, and scores them with
:func:`~jaxtalk.metrics.landmarks.landmark_metrics`: LVE over the mouth landmarks (mm^2), the mean
landmark error LE (mm) and jitter (mm/frame^2), frame-weighted over the windows.

STM's validation loss is on the training meshes; :func:`held_out_mesh_validation` maps held-out clips'
true landmarks onto held-out meshes (other identities and topologies) and scores the vertices with the
same columns as ``jaxtalk eval``: LVE (lips, mm^2), MVE (mm), jitter. Both select by ``LVE_mm2``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from jaxtalk.metrics.landmarks import landmark_metrics
from jaxtalk.models.freetalk import ats
from jaxtalk.models.freetalk.config import ATSConfig
from jaxtalk.train.loop import EvalFn
from jaxtalk.train.recipes import VAL_CLIPS, host_copy, spread
from jaxtalk.types import PRNGKeyArray

__all__ = ["sampled_validation", "held_out_mesh_validation", "SELECTION_METRIC"]

# The metric an ATS run selects its best checkpoint by: the sampled lip error over the mouth landmarks
# (an STM run: the lip error on the held-out meshes).
SELECTION_METRIC = "LVE_mm2"


def sampled_validation(
    config: ATSConfig,
    data: Any,
    windows: Any,
    split: str = "val",
    *,
    key: PRNGKeyArray,
    clips: int = VAL_CLIPS,
) -> EvalFn | None:
    """An ``eval_fn`` for the training loop that samples ``clips`` windows of ``split`` and scores them.

    Args:
        config: the ATS config.
        data: the prepared dataset (:class:`~jaxtalk.data.loader.PreparedData`).
        windows: the run's window recipe (:class:`~jaxtalk.models.freetalk.recipe.ATSWindows`): the
            windows, their standardisation and the emotion vocabulary.
        split: the split to score.
        key: the sampling key (the same starting noise at every evaluation).
        clips: how many clips, evenly spread over the split's clips with a window; each gives its
            first window.

    Returns:
        ``eval_fn(params, ema_params, step) -> {"LVE_mm2", "LE_mm", "jitter_mm"}`` (the EMA
        parameters when the run keeps them), or None when ``clips`` is 0 or the split has no window.
    """
    if clips < 1 or not data.split(split):
        return None
    table = windows.table(data, split)
    if not len(table):
        return None
    _, first = np.unique(table[:, 0], return_index=True)  # each clip's first window
    rows = table[np.sort(first)]
    examples = [windows.example(data, rows[int(j)]) for j in spread(len(rows), clips)]
    batch = {name: np.stack([e[name] for e in examples]) for name in examples[0]}
    frames = [int(e["mask"].sum()) if "mask" in e else e["displacements"].shape[0] for e in examples]
    cond = ats.make_condition(config, batch["audio"], batch["emotion"], batch["intensity"],
                              mask=batch.get("mask"), audio_mask=batch.get("audio_mask"))
    stats = windows.stats
    truth = [np.asarray(stats.denormalize(d[:n]), np.float32) for d, n in zip(batch["displacements"], frames)]

    def eval_fn(params: Any, ema_params: Any, step: int) -> dict[str, float]:
        use = host_copy(ema_params if ema_params is not None else params)
        sampled = np.asarray(stats.denormalize(np.asarray(ats.sample(use, config, cond, key))), np.float32)
        sums = {"LVE_mm2": 0.0, "LE_mm": 0.0, "jitter_mm": 0.0}
        for pred, gt, n in zip(sampled, truth, frames):
            for name, value in landmark_metrics(pred[:n], gt).items():
                sums[name] += n * value
        return {name: value / sum(frames) for name, value in sums.items()}

    return eval_fn


def held_out_mesh_validation(
    config: Any,
    data: Any,
    meshes: Sequence[tuple[int, str]],
    split: str = "val",
    *,
    window: int = 16,
    clips: int = VAL_CLIPS,
    resolution: str = "low",
) -> EvalFn | None:
    """An ``eval_fn`` that maps the true landmarks of ``split`` onto meshes STM never trained on and scores
    the vertices, FreeTalk's claim that STM animates ANY face mesh.

    Each of ``clips`` clips (evenly spread over the split's clips of at least ``window`` frames) gives
    its first ``window`` frames (head pose removed), rendered on every mesh of ``meshes`` for the
    landmarks and the true vertices; STM decodes the landmarks on that mesh. The meshes are prepared
    (eigenbasis, operators) once, here.

    Args:
        config: the STM config.
        data: the prepared dataset.
        meshes: ``(identity, topology)`` pairs of :func:`~jaxtalk.models.freetalk.data.face_mesh`, the
            held-out ones (:data:`~jaxtalk.models.freetalk.recipe.STM_HELD_OUT`).
        split: the split whose motion is mapped.
        window: frames per clip (the run's training window).
        clips: how many clips.
        resolution: the meshes' resolution (the run's).

    Returns:
        ``eval_fn(params, ema_params, step) -> {"LVE_mm2", "MVE_mm", "jitter_mm"}`` frame-weighted
        over clips and meshes (the EMA parameters when the run keeps them), or None when ``clips`` is
        0, no mesh is given or the split has no clip of ``window`` frames.
    """
    from jaxtalk.metrics import jitter, lve, mve
    from jaxtalk.models.freetalk import stm
    from jaxtalk.models.freetalk.data import face_mesh, without_head_pose

    if clips < 1 or not meshes or not data.split(split):
        return None
    usable = [i for i in data.split(split) if data.clips[i]["frames"] >= window]
    if not usable:
        return None
    motions = [without_head_pose(np.asarray(data.record(usable[int(j)], ("motion",))["motion"], np.float32)[:window])
               for j in spread(len(usable), clips)]
    targets = []
    for identity, kind in meshes:
        fm = face_mesh(int(identity), kind, resolution=resolution)
        rendered = [fm.motion(m) for m in motions]  # (landmarks, vertices) per clip
        targets.append((stm.prepare_mesh(fm.vertices, fm.faces, config), fm.region("lips"), rendered))

    def eval_fn(params: Any, ema_params: Any, step: int) -> dict[str, float]:
        use = host_copy(ema_params if ema_params is not None else params)
        sums, frames = {"LVE_mm2": 0.0, "MVE_mm": 0.0, "jitter_mm": 0.0}, 0
        for prepared, lips, rendered in targets:
            features = stm.stm_mesh_features(use, config, prepared)
            for landmarks, vertices in rendered:
                pred = np.asarray(stm.stm_decode(use, config, features, landmarks, prepared))
                n = vertices.shape[0]
                sums["LVE_mm2"] += n * float(lve(pred, vertices, lips)) * 1e6
                sums["MVE_mm"] += n * float(mve(pred, vertices)) * 1e3
                sums["jitter_mm"] += n * float(jitter(pred)) * 1e3
                frames += n
        return {name: value / frames for name, value in sums.items()}

    return eval_fn
