"""FreeTalk's two trained modules as objects: :class:`FittedATS` and :class:`FittedSTM`, loaded from the
runs their recipes write (:func:`jaxtalk.models.freetalk.recipe.train_ats` / ``train_stm``, the one way
each is trained), and :func:`sample_displacements` in metres from a fitted ATS.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import numpy as np

from jaxtalk.models.freetalk import ats
from jaxtalk.models.freetalk.config import ATSConfig, STMConfig
from jaxtalk.models.freetalk.data import DisplacementStats
from jaxtalk.types import PRNGKeyArray

__all__ = ["FittedATS", "FittedSTM", "sample_displacements"]

PyTree = Any


def _check_run(run: Any, model: str) -> Any:
    """``run`` (a :class:`~jaxtalk.runs.LoadedRun`) when it is a ``model`` run.

    Raises:
        ValueError: a path instead of a loaded run, or a run of another model.
    """
    from jaxtalk.runs import LoadedRun

    if not isinstance(run, LoadedRun):
        raise ValueError(f"from_run takes a loaded run: from_run(jaxtalk.runs.load_run({str(run)!r})), "
                         f"got {type(run).__name__}")
    if run.record.model != model:
        raise ValueError(f"{run.run_dir} is a {run.record.model} run, not an {model} run")
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
    def from_run(cls, run: Any) -> FittedATS:
        """A trained ATS from its loaded run (``jaxtalk.runs.load_run(dir)`` of ``jaxtalk train ats``), as
        every model is opened from a run.

        Raises:
            ValueError: a path instead of a loaded run, or a run of another model.
        """
        run = _check_run(run, "ats")
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

    def face(self) -> Any:
        """The template face model (the built-in face, identity 0, at STM's resolution)."""
        from jaxtalk.face import builtin_face

        return builtin_face(0, resolution=self.resolution)

    def template(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(vertices (V, 3) m, faces (F, 3), landmarks (68, 3) m)`` of the template face."""
        from jaxtalk.geometry.canonical import face_reference

        return face_reference(self.face())  # the built-in face always has its landmarks

    @classmethod
    def from_run(cls, run: Any) -> FittedSTM:
        """A trained STM from its loaded run (``jaxtalk.runs.load_run(dir)`` of ``jaxtalk train stm``).

        Raises:
            ValueError: a path instead of a loaded run, or a run of another model.
        """
        run = _check_run(run, "stm")
        return cls(run.config, jax.tree.map(jax.numpy.asarray, run.params), run.record.extra.get("resolution", "low"))


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
        fitted: a trained ATS (:meth:`FittedATS.from_run`).
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
