"""Training FreeTalk's two modules with the shared loop (:func:`jaxtalk.train.train`).

ATS and STM are trained independently (section 3.3): ATS on landmark-displacement windows
standardised with :class:`~jaxtalk.models.freetalk.data.DisplacementStats`, STM on landmark and
dense vertex displacement windows over several meshes (identities and topologies).
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from typing import Any

import jax
import numpy as np

from jaxtalk.data.batching import BatchIterator
from jaxtalk.models.freetalk import ats, stm
from jaxtalk.models.freetalk.config import ATSConfig, STMConfig
from jaxtalk.models.freetalk.data import DisplacementStats
from jaxtalk.train import OptimConfig, train
from jaxtalk.types import PRNGKeyArray

__all__ = ["FittedATS", "FittedSTM", "fit_ats", "fit_stm", "sample_displacements"]

PyTree = Any


def _load_run(run_dir: str | os.PathLike[str], model: str, best: bool) -> Any:
    """The newest (or best-validated) checkpoint of a ``model`` run.

    Raises:
        FileNotFoundError: not a run, or no checkpoint.
        ValueError: a run of another model.
    """
    from jaxtalk.runs import load_run

    run = load_run(run_dir, best=best)
    if run.record.model != model:
        raise ValueError(f"{run_dir} is a {run.record.model} run, not an {model} run")
    return run


@dataclasses.dataclass(frozen=True)
class FittedATS:
    """A trained ATS: its configuration, parameters and the data standardisation it was trained on.

    Attributes:
        config, params, stats, history: the model, its weights, the displacement statistics of its
            training split, the training log.
        window: the training window in frames (longer audio is sampled in such windows; default
            ``config.max_frames``).
        features: the audio front end it was trained on (``logmel``, ``hubert:PATH``...).
    """

    config: ATSConfig
    params: PyTree
    stats: DisplacementStats
    history: list[dict[str, Any]]
    window: int | None = None
    features: str = "logmel"

    @property
    def window_frames(self) -> int:
        return min(self.window or self.config.max_frames, self.config.max_frames)

    def audio_features(self, audio: np.ndarray, num_frames: int) -> np.ndarray:
        """``(num_frames, speech_dim)`` features of 16 kHz ``audio`` with the run's front end.

        Raises:
            ValueError: features of another width than the model's ``speech_dim``.
        """
        from jaxtalk.data.features import parse_audio_features

        feats = parse_audio_features(self.features).speech(np.asarray(audio, np.float32), num_frames)
        if feats.shape[-1] != self.config.speech_dim:
            raise ValueError(f"the {self.features} front end gives {feats.shape[-1]}-d features but this ATS "
                             f"expects speech_dim={self.config.speech_dim}")
        return feats

    @classmethod
    def from_run(cls, run_dir: str | os.PathLike[str], *, best: bool = False) -> FittedATS:
        """A trained ATS from a run folder (``jaxtalk train ats``; see :func:`_load_run`)."""
        run = _load_run(run_dir, "ats", best)
        extra = run.record.extra
        stats = DisplacementStats(np.asarray(extra["stats"]["mean"], np.float32),
                                  np.asarray(extra["stats"]["std"], np.float32))
        return cls(run.config, jax.tree.map(jax.numpy.asarray, run.params), stats, [], window=int(extra["window"]),
                   features=run.features()["audio"])


@dataclasses.dataclass(frozen=True)
class FittedSTM:
    """A trained STM: its configuration, parameters and the built-in face resolution it was trained on.

    The template face (identity 0 of the built-in face at ``resolution``) defines the frame, units
    and landmark positions STM expects: a user's mesh is aligned to it before STM runs.
    """

    config: STMConfig
    params: PyTree
    resolution: str = "low"

    def template(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(vertices (V, 3) m, faces (F, 3), landmarks (68, 3) m)`` of the template face."""
        from jaxtalk.face import builtin_face
        from jaxtalk.models.freetalk.data import neutral_landmarks

        face = builtin_face(0, resolution=self.resolution)
        return np.asarray(face.template, np.float64), np.asarray(face.faces), neutral_landmarks(face).astype(np.float64)

    @classmethod
    def from_run(cls, run_dir: str | os.PathLike[str], *, best: bool = False) -> FittedSTM:
        """A trained STM from a run folder (``jaxtalk train stm``; see :func:`_load_run`)."""
        run = _load_run(run_dir, "stm", best)
        return cls(run.config, jax.tree.map(jax.numpy.asarray, run.params), run.record.extra.get("resolution", "low"))


def fit_ats(
    config: ATSConfig,
    windows: dict[str, np.ndarray],
    optim: OptimConfig,
    key: PRNGKeyArray,
    *,
    batch_size: int = 16,
    progress: bool = False,
    ckpt_dir: str | os.PathLike[str] | None = None,
    save_every: int | None = None,
    max_steps: int | None = None,
) -> FittedATS:
    """Train ATS on windows from :func:`~jaxtalk.models.freetalk.data.ats_windows`.

    Displacements are standardised per coordinate (fitted on ``windows``), so ``config`` should use
    ``displacement_scale = 1``.

    Args:
        config: ATS configuration (``max_frames`` >= the window length).
        windows: ``displacements``, ``audio``, ``emotion``, ``intensity`` arrays.
        optim: optimiser settings (``total_steps`` = training length).
        key: PRNG key (initialisation and training).
        batch_size: windows per step.
        progress: show the loop's progress bar.
        ckpt_dir: checkpoint directory (atomic orbax checkpoints of the train state and the data
            position through :func:`jaxtalk.train.train`); a run over an existing directory resumes
            from its newest checkpoint exactly. None: no checkpoints.
        save_every: also checkpoint every this many steps (the final step is always saved).
        max_steps: stop at this step (default ``optim.total_steps``; the schedule still spans
            ``total_steps``), e.g. to train in several sessions with ``ckpt_dir``.

    Returns:
        :class:`FittedATS`.

    Raises:
        ValueError: ``displacement_scale != 1``, windows longer than ``config.max_frames`` or
            malformed arrays.
    """
    if config.displacement_scale != 1.0:
        raise ValueError(
            "fit_ats standardises the displacements itself; use a config with displacement_scale=1.0, "
            f"got {config.displacement_scale}"
        )
    disp = np.asarray(windows["displacements"], np.float32)
    if disp.ndim != 4 or disp.shape[-2:] != (config.num_landmarks, 3):
        raise ValueError(f"displacements must have shape (N, T, {config.num_landmarks}, 3), got {disp.shape}")
    if disp.shape[1] > config.max_frames:
        raise ValueError(f"windows of {disp.shape[1]} frames exceed config.max_frames={config.max_frames}")
    stats = DisplacementStats.fit(disp)
    data = {
        "displacements": stats.normalize(disp).astype(np.float32),
        "audio": np.asarray(windows["audio"], np.float32),
        "emotion": np.asarray(windows["emotion"], np.int32),
        "intensity": np.asarray(windows["intensity"], np.float32),
    }
    k_init, k_train = jax.random.split(key)
    params = ats.init_params(config, k_init)
    it = BatchIterator(data, batch_size, seed=int(jax.random.randint(k_init, (), 0, 2**30)))
    result = train(ats.make_loss_fn(config), params, it, optim, key=k_train, progress=progress,
                   log_every=max(1, optim.total_steps // 20), ckpt_dir=ckpt_dir, save_every=save_every,
                   max_steps=max_steps, metadata={"model": "freetalk_ats", "model_config": dataclasses.asdict(config)})
    return FittedATS(config, result.state.eval_params, stats, result.history)


def sample_displacements(
    fitted: FittedATS,
    audio: np.ndarray,
    emotion: Any,
    intensity: Any,
    key: PRNGKeyArray,
    *,
    sample_steps: int | None = None,
    eta: float = 0.0,
    noise: np.ndarray | None = None,
) -> np.ndarray:
    """Sample landmark displacements (metres) from a fitted ATS.

    Args:
        fitted: from :func:`fit_ats`.
        audio: ``(B, T, speech_dim)`` features.
        emotion: names or ids (one per example, or one for all).
        intensity: scalar or ``(B,)``.
        key: PRNG key.
        sample_steps: DDIM steps (default the config's).
        eta: DDIM eta.
        noise: ``(B, T, 3N)`` starting noise (default: drawn from ``key``), see :func:`ats.sample_ats`.

    Returns:
        ``(B, T, N, 3)`` displacements in metres.
    """
    cond = ats.make_condition(fitted.config, audio, emotion, intensity)
    out = ats.sample(fitted.params, fitted.config, cond, key, sample_steps=sample_steps, eta=eta, noise=noise)
    return np.asarray(fitted.stats.denormalize(np.asarray(out)))


def fit_stm(
    config: STMConfig,
    meshes: Sequence[stm.STMMesh],
    windows: dict[str, np.ndarray],
    optim: OptimConfig,
    key: PRNGKeyArray,
    *,
    batch_size: int = 4,
    progress: bool = False,
    ckpt_dir: str | os.PathLike[str] | None = None,
    save_every: int | None = None,
    max_steps: int | None = None,
) -> tuple[PyTree, list[dict[str, Any]]]:
    """Train STM on windows from :func:`~jaxtalk.models.freetalk.data.stm_windows`.

    Args:
        config: STM configuration.
        meshes: the training meshes, prepared with a common ``num_vertices`` and ``degree`` (the
            windows' ``"mesh"`` entries index this list).
        windows: ``mesh``, ``landmarks``, ``vertices`` arrays.
        optim: optimiser settings.
        key: PRNG key.
        batch_size: windows per step.
        progress: show the loop's progress bar.
        ckpt_dir: checkpoint directory (resumes exactly from its newest checkpoint; see
            :func:`fit_ats`). None: no checkpoints.
        save_every: also checkpoint every this many steps.
        max_steps: stop at this step (default ``optim.total_steps``).

    Returns:
        ``(params, history)``.

    Raises:
        ValueError: a window that names a mesh outside ``meshes``.
    """
    idx = np.asarray(windows["mesh"])
    if idx.min() < 0 or idx.max() >= len(meshes):
        raise ValueError(f"windows name meshes {sorted(set(idx.tolist()))} but {len(meshes)} meshes were given")
    stacked = stm.stack_meshes(list(meshes))
    k_init, k_train = jax.random.split(key)
    params = stm.init_params(config, k_init, meshes[0])
    it = BatchIterator(dict(windows), batch_size, seed=int(jax.random.randint(k_init, (), 0, 2**30)))
    result = train(stm.make_loss_fn(config, stacked), params, it, optim, key=k_train, progress=progress,
                   log_every=max(1, optim.total_steps // 20), ckpt_dir=ckpt_dir, save_every=save_every,
                   max_steps=max_steps, metadata={"model": "freetalk_stm", "model_config": dataclasses.asdict(config)})
    return result.state.eval_params, result.history
