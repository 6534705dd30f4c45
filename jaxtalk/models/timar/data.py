"""SynthTalk conversations as TIMAR inputs: per-turn speech features, roles, windows, normalisation.

Speech features follow the paper's per-chunk tokenisation (Sec. 3.1: "each chunk is encoded
independently ... so that no future information is exposed"): the audio of every 1-s turn is turned
into an 80-band log-mel spectrogram on its own (``jaxtalk.audio.log_mel``, 100 frames/s) and
interpolated to the turn's 25 motion frames (``jaxtalk.audio.resample_features``). Each conversation
gives two examples: speaker A as the agent with B as the user, and the reverse.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

# Shared with ``prepare`` (a lower layer), re-exported here as part of TIMAR's data API.
from jaxtalk.audio.speech import TURN_SPEECH_DIM as SPEECH_DIM
from jaxtalk.audio.speech import turn_speech_features
# Shared with the DualTalk baseline (a lower layer), re-exported here as part of TIMAR's data API.
from jaxtalk.models.turns.windows import Normalizer
from jaxtalk.data.standardize import fit_standardizer
from jaxtalk.types import AUDIO_SAMPLE_RATE, MOTION_FPS, PARAM_DIM

__all__ = [
    "SPEECH_DIM",
    "Conversation",
    "Normalizer",
    "turn_speech_features",
    "conversations",
    "monologues",
    "fit_normalizer",
    "windows",
]




@dataclasses.dataclass(frozen=True)
class Conversation:
    """One conversation side: the agent is the speaker whose motion is predicted.

    Attributes:
        agent_speech, user_speech: ``(T, 80)`` per-turn log-mel features.
        agent_motion, user_motion: ``(T, 56)`` head motion (raw, not normalised).
        agent_oracle: ``(T, 56)`` the generator's deterministic part of the agent's motion.
        agent_clip, user_clip: SynthTalk clip indices.
    """

    agent_speech: np.ndarray
    agent_motion: np.ndarray
    user_speech: np.ndarray
    user_motion: np.ndarray
    agent_oracle: np.ndarray
    agent_clip: int
    user_clip: int

    @property
    def num_frames(self) -> int:
        return int(self.agent_motion.shape[0])


def conversations(corpus: Any, split: str, *, frames_per_turn: int = MOTION_FPS) -> list[Conversation]:
    """Both role assignments of every conversation of a SynthTalk split, cut to whole turns.

    Args:
        corpus: a :class:`jaxtalk.data.synthtalk.SynthTalkCorpus`.
        split: ``"train"``, ``"val"``, ``"test"`` or ``"ood"``.
        frames_per_turn: frames per turn.

    Returns:
        ``2 x`` (number of conversations) :class:`Conversation` s.

    Raises:
        ValueError: unknown split or a split without conversations.
    """
    pairs = corpus.conversations(split)
    if not pairs:
        raise ValueError(f"split {split!r} has no conversations")
    out = []
    for a, b in pairs:
        turns = min(corpus.clips[a].num_frames, corpus.clips[b].num_frames) // frames_per_turn
        t = turns * frames_per_turn
        speech = {c: turn_speech_features(corpus.audio(c), turns, frames_per_turn=frames_per_turn) for c in (a, b)}
        for agent, user in ((a, b), (b, a)):
            out.append(Conversation(
                agent_speech=speech[agent], agent_motion=np.asarray(corpus.motion(agent)[:t], np.float32),
                user_speech=speech[user], user_motion=np.asarray(corpus.motion(user)[:t], np.float32),
                agent_oracle=np.asarray(corpus.oracle(agent)[:t], np.float32), agent_clip=agent,
                user_clip=user,
            ))
    return out


def monologues(corpus: Any, split: str, *, frames_per_turn: int = MOTION_FPS) -> list[Conversation]:
    """Every monologue clip of a split as a conversation side with a silent, still user.

    Extra training material for the audio-to-motion part of the model: in a SynthTalk conversation a
    silent partner's channel is silence (each clip holds only its speaker's voice), so the user here
    gets zero audio, and the split's mean pose as motion (a constant shared by every clip, so it
    leaks nothing about the agent). ``user_clip`` is -1.

    Args:
        corpus: a :class:`jaxtalk.data.synthtalk.SynthTalkCorpus`.
        split: ``"train"``, ``"val"``, ``"test"`` or ``"ood"``.
        frames_per_turn: frames per turn.

    Returns:
        One :class:`Conversation` per monologue clip with at least one whole turn.

    Raises:
        ValueError: a split without monologue clips.
    """
    clips = [i for i in corpus.split(split) if not corpus.clips[i].is_conversation]
    if not clips:
        raise ValueError(f"split {split!r} has no monologue clips")
    still = np.mean(np.concatenate([corpus.motion(i) for i in clips]), axis=0).astype(np.float32)
    spt = AUDIO_SAMPLE_RATE * frames_per_turn // MOTION_FPS
    silence = {}
    out = []
    for i in clips:
        turns = corpus.clips[i].num_frames // frames_per_turn
        if turns < 1:
            continue
        t = turns * frames_per_turn
        if turns not in silence:
            silence[turns] = turn_speech_features(np.zeros(turns * spt, np.float32), turns, frames_per_turn=frames_per_turn)
        out.append(Conversation(
            agent_speech=turn_speech_features(corpus.audio(i), turns, frames_per_turn=frames_per_turn),
            agent_motion=np.asarray(corpus.motion(i)[:t], np.float32), user_speech=silence[turns],
            user_motion=np.broadcast_to(still, (t, PARAM_DIM)).copy(),
            agent_oracle=np.asarray(corpus.oracle(i)[:t], np.float32), agent_clip=i, user_clip=-1,
        ))
    return out


def fit_normalizer(convs: Sequence[Conversation], *, floor: float = 1e-3) -> Normalizer:
    """Fit means and standard deviations on training conversations (agent sides; both roles of a
    conversation are two entries, so every speaker is pooled).

    Uses :func:`jaxtalk.data.standardize.fit_standardizer`, whose floor is relative to the mean std
    over channels: with ``1e-3`` a channel that is constant in the training data gets a std of a
    thousandth of the typical one (motion: ~4e-4) instead of 0, and every real channel keeps its own
    std. (The near-constant jaw channels of SynthTalk have std 2e-3 and 5e-3: a larger floor, such
    as the shared default 0.05, would shrink them in the grouped loss; a zero floor would divide by
    zero.)

    Args:
        convs: training conversations.
        floor: relative std floor (see :func:`~jaxtalk.data.standardize.fit_standardizer`).

    Returns:
        :class:`Normalizer`.

    Raises:
        ValueError: no conversations, or fewer than 2 frames in all.
    """
    if not convs:
        raise ValueError("fit_normalizer needs at least one conversation")
    speech = fit_standardizer(np.concatenate([c.agent_speech for c in convs]), floor=floor)
    motion = fit_standardizer(np.concatenate([c.agent_motion for c in convs]), floor=floor)
    return Normalizer(speech["mean"], speech["std"], motion["mean"], motion["std"])


def windows(
    convs: Sequence[Conversation],
    normalizer: Normalizer,
    *,
    num_turns: int,
    stride_turns: int = 1,
    frames_per_turn: int = MOTION_FPS,
) -> dict[str, np.ndarray]:
    """Cut conversations into normalised windows of ``num_turns`` whole turns (training examples).

    Args:
        convs: conversations.
        normalizer: the training normalisation.
        num_turns: turns per window (<= the model's ``max_turns``).
        stride_turns: hop between window starts, in turns.
        frames_per_turn: frames per turn.

    Returns:
        ``user_speech``/``agent_speech`` ``(W, num_turns F, 80)`` and ``user_motion``/``agent_motion``
        ``(W, num_turns F, 56)`` float32.

    Raises:
        ValueError: no conversation is long enough, or bad sizes.
    """
    if num_turns < 1 or stride_turns < 1:
        raise ValueError(f"num_turns and stride_turns must be >= 1, got {num_turns}, {stride_turns}")
    length = num_turns * frames_per_turn
    out: dict[str, list[np.ndarray]] = {k: [] for k in ("user_speech", "user_motion", "agent_speech", "agent_motion")}
    for c in convs:
        for start in range(0, c.num_frames - length + 1, stride_turns * frames_per_turn):
            sl = slice(start, start + length)
            out["user_speech"].append(normalizer.speech(c.user_speech[sl]))
            out["agent_speech"].append(normalizer.speech(c.agent_speech[sl]))
            out["user_motion"].append(normalizer.motion(c.user_motion[sl]))
            out["agent_motion"].append(normalizer.motion(c.agent_motion[sl]))
    if not out["agent_motion"]:
        raise ValueError(f"no conversation has {num_turns} whole turns ({length} frames)")
    assert PARAM_DIM == out["agent_motion"][0].shape[-1]
    return {k: np.stack(v) for k, v in out.items()}
