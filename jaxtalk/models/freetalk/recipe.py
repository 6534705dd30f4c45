"""FreeTalk's recipes: ATS (audio -> 68 landmark displacements) and STM (landmarks -> any mesh), each
with its windows over a prepared dataset and the one way it is trained.

* ATS windows: ``window`` frames of the landmark displacements ``prepare`` computed on the built-in
  face (head pose removed), standardised per coordinate with statistics of the training split, with
  the whole-clip speech features, the clip's emotion (neutral when the dataset has none) and
  intensity (1 when unknown).
* STM windows: 16-frame windows of the training motion rendered on several face identities and mesh
  topologies (three by default: :data:`STM_MESHES`), landmark and vertex displacements, vertices
  zero-padded to the largest mesh.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import numpy as np

from jaxtalk.data.loader import PreparedData
from jaxtalk.models.freetalk.config import ATSConfig, STMConfig
from jaxtalk.models.freetalk.data import DisplacementStats
from jaxtalk.models.freetalk.emotions import EMOTIONS
from jaxtalk.runs import RunSettings, fit_run
from jaxtalk.train import OptimConfig
from jaxtalk.data.batching import window_starts
from jaxtalk.train.recipes import VAL_CLIPS, RecipeResult, TrainSettings
from jaxtalk.types import PRNGKeyArray

PyTree = Any

__all__ = ["DEFAULTS", "ATS_PRESET_DEFAULTS", "STM_PRESET_DEFAULTS", "ATSWindows", "STMWindows", "STM_MESHES", "STM_HELD_OUT",
           "fit_displacement_stats", "train_ats", "train_stm"]

# Three face identities on three mesh topologies (FreeTalk's seen meshes). Windows are padded to the
# largest mesh, so the ~4x denser subdivided topology is not among them (it would make every window
# 4x dearer); the experiments hold it out instead, with a fourth identity, as unseen meshes.
STM_MESHES = ((0, "base"), (1, "decimated"), (2, "retriangulated"))
STM_HELD_OUT = ((0, "subdivided"), (3, "base"), (3, "retriangulated"))
# ATS and STM on 2 CPU cores.
DEFAULTS = TrainSettings(lr=1e-3, warmup_steps=100)
# The paper's optimiser (AdamW 1e-4, weight decay 1e-2, clip 1.0, batch 16; no schedule is stated, so a
# constant rate) and, for ATS, whole clips rather than 50-frame windows (window_frames=0).
ATS_PRESET_DEFAULTS: dict[str, TrainSettings] = {
    "paper": TrainSettings(lr=1e-4, weight_decay=1e-2, warmup_steps=0, final_lr_ratio=1.0, clip_norm=1.0,
                           batch_size=16, window_frames=0)}
STM_PRESET_DEFAULTS: dict[str, TrainSettings] = {
    "paper": TrainSettings(lr=1e-4, weight_decay=1e-2, warmup_steps=0, final_lr_ratio=1.0)}


def fit_displacement_stats(data: PreparedData) -> DisplacementStats:
    """Per-coordinate landmark displacement statistics of the training split.

    Raises:
        ValueError: a training split without landmarks (a dataset without 56-d motion).
    """
    clips = [data.record(i, ("landmarks",)) for i in data.split("train")]
    lms = [c["landmarks"] for c in clips if "landmarks" in c]
    if not lms:
        raise ValueError(f"{data.root}: no landmark displacements in the training split (ATS needs 56-d motion)")
    return DisplacementStats.fit(np.concatenate(lms))


@dataclasses.dataclass(frozen=True)
class ATSWindows:
    """ATS's window recipe (see the module docstring); ``emotions`` is the model's vocabulary.

    Attributes:
        window: frames per window; 0 trains on WHOLE clips (the paper's): each example is a clip
            (a clip longer than ``pad_to`` is cut into ``pad_to``-frame pieces) zero-padded to
            ``pad_to`` frames with a padding ``mask`` (and ``audio_mask``) that the loss and the
            attention honour.
        stats: the displacement standardisation.
        emotions: the model's emotion vocabulary.
        pad_to: with ``window == 0``, the length every example is padded to (the longest clip, at
            most the model's ``max_frames``).
    """

    window: int
    stats: DisplacementStats
    emotions: tuple[str, ...] = EMOTIONS
    pad_to: int = 0

    @property
    def whole(self) -> bool:
        return self.window == 0

    def table(self, data: PreparedData, split: str) -> np.ndarray:
        """Rows ``(clip, start)``; clips shorter than a window give none (whole clips: every clip)."""
        if self.whole:
            rows = [(i, s) for i in data.split(split) for s in range(0, data.clips[i]["frames"], self.pad_to)]
        else:
            rows = [(i, s) for i in data.split(split) if data.clips[i]["frames"] >= self.window
                    for s in window_starts(data.clips[i]["frames"], self.window, max(self.window // 4, 1))]
        return np.asarray(rows, np.int64).reshape(-1, 2)

    def example(self, data: PreparedData, row: np.ndarray) -> dict[str, np.ndarray]:
        from jaxtalk.models.freetalk.emotions import NEUTRAL, emotion_ids

        i, s = (int(v) for v in row)
        rec = data.record(i, ("landmarks", "speech"), frames=(s, s + (self.pad_to if self.whole else self.window)))
        clip = data.clips[i]
        example = {"displacements": np.asarray(self.stats.normalize(rec["landmarks"]), np.float32),
                   "audio": rec["speech"].astype(np.float32),
                   "emotion": np.asarray(emotion_ids(clip["emotion"] or NEUTRAL, self.emotions)[0], np.int32),
                   "intensity": np.asarray(clip["intensity"] if clip["intensity"] is not None else 1.0, np.float32)}
        if self.whole:
            n = min(example["displacements"].shape[0], example["audio"].shape[0])
            for name in ("displacements", "audio"):
                padded = np.zeros((self.pad_to, *example[name].shape[1:]), np.float32)
                padded[:n] = example[name][:n]
                example[name] = padded
            example["mask"] = example["audio_mask"] = np.arange(self.pad_to) < n
        return example


def train_ats(
    config: ATSConfig,
    data: PreparedData,
    optim: OptimConfig,
    *,
    key: PRNGKeyArray,
    run: RunSettings = RunSettings(),
    params: PyTree | None = None,
    val_clips: int = VAL_CLIPS,
) -> RecipeResult:
    """Train ATS on ``data``'s training split (arguments as every recipe's ``train``; ``run.window_frames``
    default 50 frames, at most ``max_frames``; 0: whole clips, padded and masked).

    The model sees standardised displacements, so ``config.displacement_scale`` must be 1. Each
    evaluation computes the loss on up to :data:`~jaxtalk.train.recipes.VAL_WINDOWS` windows of the
    ``val`` split and samples one window of each of ``val_clips`` of its clips with DDIM
    (:func:`~jaxtalk.models.freetalk.validation.sampled_validation`: LVE over the mouth landmarks, LE,
    jitter); the best checkpoint is the one of the lowest sampled LVE (the validation loss when
    nothing is sampled).

    Returns:
        :class:`~jaxtalk.train.recipes.RecipeResult`; ``extra`` holds the window and the statistics.

    Raises:
        ValueError: ``displacement_scale != 1``, or speech features of another width than ``speech_dim``.
    """
    from jaxtalk.models.freetalk import ats

    if config.displacement_scale != 1.0:
        raise ValueError(f"ATS trains on standardised displacements: displacement_scale must be 1.0, "
                         f"got {config.displacement_scale}")
    if data.manifest["speech_dim"] != config.speech_dim:
        raise ValueError(f"{data.root} has {data.manifest['speech_dim']}-d speech features but the model expects "
                         f"speech_dim={config.speech_dim} (--set speech_dim=...)")
    labels = sorted({c["emotion"] for c in data.clips if c["emotion"]} - set(config.emotions))
    if labels:
        raise ValueError(f"{data.root} has emotion labels {labels} outside the model's vocabulary "
                         f"({', '.join(config.emotions)}): set emotions to the data's (--set emotions=mead, or a "
                         "comma-separated list starting with neutral)")
    stats = fit_displacement_stats(data)
    if run.window_frames == 0:  # whole clips, padded to the longest (at most max_frames) and masked
        if config.audio_frames_per_frame != 1:
            raise ValueError("whole-clip ATS training (window_frames=0) needs speech features at the motion rate "
                             f"(audio_frames_per_frame=1, got {config.audio_frames_per_frame})")
        longest = max(data.clips[i]["frames"] for i in data.split("train")) if data.split("train") else 1
        recipe = ATSWindows(0, stats, config.emotions, pad_to=min(longest, config.max_frames))
    else:
        recipe = ATSWindows(run.window_frames or min(config.max_frames, 50), stats, config.emotions)
    k_init, k_train, k_eval = jax.random.split(key, 3)
    params = ats.init_params(config, k_init) if params is None else params
    extra = {"window": recipe.window, "stats": {"mean": stats.mean.tolist(), "std": stats.std.tolist()}}
    from jaxtalk.models.freetalk.validation import SELECTION_METRIC, sampled_validation

    sample_eval = sampled_validation(config, data, recipe, "val", key=jax.random.fold_in(k_eval, 1), clips=val_clips)
    return fit_run(recipe, data, ats.make_loss_fn(config), params, optim, config=config, key=k_train, eval_key=k_eval,
                   run=run, metadata={"model": "ats"}, extra=extra, sample_eval=sample_eval, best_metric=SELECTION_METRIC)


@dataclasses.dataclass(frozen=True, eq=False)
class STMWindows:
    """STM's window recipe (see the module docstring).

    Attributes:
        meshes: the face meshes (``freetalk.data.FaceMesh``) the motion is rendered on.
        num_vertices: padded vertex count (the largest mesh).
        window: frames per window.
    """

    meshes: tuple[Any, ...]
    num_vertices: int
    window: int = 16

    def table(self, data: PreparedData, split: str) -> np.ndarray:
        """Rows ``(mesh, clip, start)``: every clip's windows on every mesh."""
        rows = [(k, i, s) for k in range(len(self.meshes)) for i in data.split(split)
                if data.clips[i]["frames"] >= self.window
                for s in window_starts(data.clips[i]["frames"], self.window, self.window)]
        return np.asarray(rows, np.int64).reshape(-1, 3)

    def example(self, data: PreparedData, row: np.ndarray) -> dict[str, np.ndarray]:
        from jaxtalk.models.freetalk.data import without_head_pose

        k, i, s = (int(v) for v in row)
        motion = data.record(i, ("motion",), frames=(s, s + self.window))["motion"]
        lms, verts = self.meshes[k].motion(without_head_pose(motion))
        return {"mesh": np.asarray(k, np.int32), "landmarks": lms.astype(np.float32),
                "vertices": np.pad(verts, ((0, 0), (0, self.num_vertices - verts.shape[1]), (0, 0))).astype(np.float32)}


def train_stm(
    config: STMConfig,
    data: PreparedData,
    optim: OptimConfig,
    *,
    key: PRNGKeyArray,
    run: RunSettings = RunSettings(),
    params: PyTree | None = None,
    meshes: tuple[tuple[int, str], ...] = STM_MESHES,
    held_out: tuple[tuple[int, str], ...] = STM_HELD_OUT,
    resolution: str = "low",
    val_clips: int = VAL_CLIPS,
) -> RecipeResult:
    """Train STM on ``data``'s training motion rendered on ``meshes`` (identity, topology) pairs
    (arguments as every recipe's ``train``; ``run.window_frames`` default 16).

    Each evaluation computes the loss on val windows on the training meshes and maps the true
    landmarks of ``val_clips`` val clips onto the ``held_out`` meshes
    (:func:`~jaxtalk.models.freetalk.validation.held_out_mesh_validation`: LVE, MVE, jitter); the best
    checkpoint is the one of the lowest held-out LVE (the validation loss when ``val_clips`` is 0 or
    ``held_out`` is empty).

    Returns:
        :class:`~jaxtalk.train.recipes.RecipeResult`; ``extra`` holds the meshes, resolution and window.
    """
    from jaxtalk.models.freetalk import stm
    from jaxtalk.models.freetalk.data import face_mesh

    faces = tuple(face_mesh(i, kind, resolution=resolution) for i, kind in meshes)
    prepared = stm.prepare_meshes([(m.vertices, m.faces) for m in faces], config)
    recipe = STMWindows(faces, max(p.num_vertices for p in prepared), window=run.window_frames or 16)
    k_init, k_train, k_eval = jax.random.split(key, 3)
    params = stm.init_params(config, k_init, prepared[0]) if params is None else params
    extra = {"meshes": [list(m) for m in meshes], "resolution": resolution, "window": recipe.window}
    from jaxtalk.models.freetalk.validation import SELECTION_METRIC, held_out_mesh_validation

    sample_eval = held_out_mesh_validation(config, data, held_out, "val", window=recipe.window, clips=val_clips,
                                           resolution=resolution)
    return fit_run(recipe, data, stm.make_loss_fn(config, stm.stack_meshes(prepared)), params, optim, config=config,
                   key=k_train, eval_key=k_eval, run=run, metadata={"model": "stm"}, extra=extra,
                   sample_eval=sample_eval, best_metric=SELECTION_METRIC)
