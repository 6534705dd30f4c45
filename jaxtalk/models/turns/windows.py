"""Conversation windows of a prepared dataset, as TIMAR trains on them and the DualTalk baseline too.

Every clip with motion whose conversation partner is in the dataset is an agent side; the partner is
the user. A window is ``num_turns`` whole 1-s turns starting on a turn boundary: both sides' per-turn
speech features (each turn computed from its own audio by ``prepare``) and both motions, standardised
with a :class:`Normalizer` fitted on the training agents. A partner without tracked motion (DualTalk's
audio-only sides) contributes its speech and the training mean pose as its motion: a constant that
carries no information about the agent.

TIMAR's Table 1 retrains DualTalk on TIMAR's data, so both models read their windows from here, their
family package, instead of one model importing the other.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from jaxtalk.data.loader import PreparedData
from jaxtalk.data.standardize import fit_standardizer, standardize, unstandardize
from jaxtalk.models.turns.streams import TurnConfig
from jaxtalk.types import Float

__all__ = ["Normalizer", "TurnWindows", "ConversationSide", "agent_sides", "side_streams", "fit_data_normalizer",
           "window_turns", "make_windows"]


@dataclasses.dataclass(frozen=True)
class Normalizer:
    """Per-channel standardisation of speech features and head motion (fit on training data).

    A pair of :mod:`jaxtalk.data.standardize` statistics (``{"mean", "std"}``) under the field names
    that TIMAR checkpoints store (:meth:`to_dict`); :meth:`speech_stats` / :meth:`motion_stats` give
    them in the shared form.

    Attributes:
        speech_mean, speech_std: ``(80,)``.
        motion_mean, motion_std: ``(56,)``.
    """

    speech_mean: np.ndarray
    speech_std: np.ndarray
    motion_mean: np.ndarray
    motion_std: np.ndarray

    @property
    def speech_stats(self) -> dict[str, np.ndarray]:
        """The speech statistics as a :func:`jaxtalk.data.standardize.standardize` dict."""
        return {"mean": self.speech_mean, "std": self.speech_std}

    @property
    def motion_stats(self) -> dict[str, np.ndarray]:
        """The motion statistics as a :func:`jaxtalk.data.standardize.standardize` dict."""
        return {"mean": self.motion_mean, "std": self.motion_std}

    def speech(self, x: Float[np.ndarray, "*frames dim"]) -> np.ndarray:
        """Raw speech features -> standardised (float32 NumPy)."""
        return standardize(self.speech_stats, np.asarray(x, np.float32))

    def motion(self, x: Float[np.ndarray, "*frames 56"]) -> np.ndarray:
        """Raw head parameters -> standardised (float32 NumPy)."""
        return standardize(self.motion_stats, np.asarray(x, np.float32))

    def unmotion(self, x: Any) -> np.ndarray:
        """Normalised motion back to raw head parameters."""
        return unstandardize(self.motion_stats, np.asarray(x, np.float32))

    def to_dict(self) -> dict[str, list[float]]:
        return {k: np.asarray(v).tolist() for k, v in dataclasses.asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict[str, Sequence[float]]) -> Normalizer:
        return cls(**{k: np.asarray(v, np.float32) for k, v in d.items()})


def agent_sides(data: PreparedData, split: str) -> list[tuple[int, int]]:
    """``(agent, user)`` clip positions: clips with motion, per-turn speech and a prepared partner."""
    out = []
    for i in data.split(split):
        j = data.partner(i)
        if j is not None and data.clips[i]["frames"] >= data.manifest["turn_frames"]:
            out.append((i, j))
    return out


@dataclasses.dataclass(frozen=True)
class ConversationSide:
    """One agent side as a turn model is scored on it (``jaxtalk eval`` and in-training validation).

    Attributes:
        streams: ``(user_speech, user_motion, agent_speech)``, each ``(1, usable, D)`` in the
            training normalisation, over the side's whole turns.
        truth: ``(total, 56)`` the agent's motion over the whole side (as far as the partner's
            motion goes): the frames after the last whole turn are scored too (TIMAR's protocol pads
            them with the last prediction).
        partner: ``(total, 56)`` the user's motion, or the still pose where it has none.
        still_partner: the partner has no tracked motion (``partner`` is the still pose).
        oracle: ``(total, 56)`` the agent's oracle motion where the dataset has one (SynthTalk), else None.
    """

    streams: tuple[np.ndarray, np.ndarray, np.ndarray]
    truth: np.ndarray
    partner: np.ndarray
    still_partner: bool
    oracle: np.ndarray | None = None

    @property
    def padded_frames(self) -> int:
        """Frames after the side's last whole turn (scored as repeats of the last prediction)."""
        return self.truth.shape[0] - self.streams[0].shape[1]


def side_streams(data: PreparedData, agent: int, user: int, normalizer: Normalizer,
                 still: np.ndarray | Sequence[float], frames_per_turn: int) -> ConversationSide | None:
    """The side of clip ``agent`` talking with clip ``user`` (:func:`agent_sides`), or None when it has no
    whole ``frames_per_turn``-frame turn."""
    a = data.record(agent, ("turn_speech", "motion", "oracle"))
    u = data.record(user, ("turn_speech", "motion"))
    total = a["motion"].shape[0] if "motion" not in u else min(a["motion"].shape[0], u["motion"].shape[0])
    usable = min(a["turn_speech"].shape[0], u["turn_speech"].shape[0], total) // frames_per_turn * frames_per_turn
    if usable == 0:
        return None
    still = np.asarray(still, np.float32)
    partner = (np.asarray(u["motion"], np.float32)[:total] if "motion" in u
               else np.broadcast_to(still, (total, still.shape[0])).copy())
    streams = (normalizer.speech(u["turn_speech"][:usable])[None], normalizer.motion(partner[:usable])[None],
               normalizer.speech(a["turn_speech"][:usable])[None])
    oracle = np.asarray(a["oracle"], np.float32)[:total] if "oracle" in a else None
    return ConversationSide(streams, np.asarray(a["motion"], np.float32)[:total], partner, "motion" not in u, oracle)


def fit_data_normalizer(data: PreparedData, *, floor: float = 1e-3) -> Normalizer:
    """The speech and motion standardisation of the training split's agent sides.

    Raises:
        ValueError: a training split without conversations.
    """
    sides = agent_sides(data, "train")
    if not sides:
        raise ValueError(f"{data.root}: TIMAR and the DualTalk baseline train on conversations and the "
                         "training split has none (a clip with motion needs its partner's clip)")
    speech, motion = [], []
    for i, _ in sides:
        rec = data.record(i, ("turn_speech", "motion"))
        speech.append(rec["turn_speech"])
        motion.append(rec["motion"][: rec["turn_speech"].shape[0]])
    s, m = fit_standardizer(np.concatenate(speech), floor=floor), fit_standardizer(np.concatenate(motion), floor=floor)
    return Normalizer(s["mean"], s["std"], m["mean"], m["std"])


def window_turns(config: TurnConfig, data: PreparedData) -> int:
    """Turns per training window: the config's ``max_turns``, capped by the longest training side."""
    sides = agent_sides(data, "train")
    longest = max(min(data.clips[i]["frames"], data.clips[j]["frames"]) for i, j in sides) // config.frames_per_turn
    return max(1, min(config.max_turns, longest))


@dataclasses.dataclass(frozen=True)
class TurnWindows:
    """TIMAR's window recipe (see the module docstring), also the DualTalk baseline's: both models train
    and validate on the same windows.

    Attributes:
        config: the model config (frames per turn).
        num_turns: turns per window.
        normalizer: the training standardisation.
        still: ``(56,)`` the motion of a partner without tracked motion (the training mean pose).
    """

    config: TurnConfig
    num_turns: int
    normalizer: Normalizer
    still: tuple[float, ...]

    def table(self, data: PreparedData, split: str) -> np.ndarray:
        """Rows ``(agent, user, start)``, one window per turn step."""
        f = self.config.frames_per_turn
        length = self.num_turns * f
        rows = []
        for i, j in agent_sides(data, split):
            usable = min(data.clips[i]["frames"], data.clips[j]["frames"]) // f * f
            rows += [(i, j, s) for s in range(0, usable - length + 1, f)]
        return np.asarray(rows, np.int64).reshape(-1, 3)

    def example(self, data: PreparedData, row: np.ndarray) -> dict[str, np.ndarray]:
        i, j, s = (int(v) for v in row)
        sl = slice(s, s + self.num_turns * self.config.frames_per_turn)
        agent = data.record(i, ("turn_speech", "motion"))
        user = data.record(j, ("turn_speech", "motion"))
        user_motion = user["motion"][sl] if "motion" in user else np.broadcast_to(
            np.asarray(self.still, np.float32), (sl.stop - sl.start, len(self.still)))
        n = self.normalizer
        return {"user_speech": n.speech(user["turn_speech"][sl]), "user_motion": n.motion(user_motion),
                "agent_speech": n.speech(agent["turn_speech"][sl]), "agent_motion": n.motion(agent["motion"][sl])}


def make_windows(config: TurnConfig, data: PreparedData) -> TurnWindows:
    """The recipe with its normaliser fitted on ``data``'s training split."""
    if data.manifest["turn_speech_dim"] != config.speech_dim:
        raise ValueError(f"{data.root} has {data.manifest['turn_speech_dim']}-d speech features but the model "
                         f"expects speech_dim={config.speech_dim} (--set speech_dim=...)")
    normalizer = fit_data_normalizer(data)
    still = tuple(float(v) for v in data.motion_stats()["mean"])
    return TurnWindows(config, window_turns(config, data), normalizer, still)
