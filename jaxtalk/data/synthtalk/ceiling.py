"""How much can conversational context explain on SynthTalk? A ceiling from the generator's true events.

A model with ``k`` past turns of context sees the current 1-s turn and the ``k`` before it. This probe
gives a ridge regression the generator's TRUE causes of the agent's within-conversation motion that
fall inside that window, and measures the held-out R^2 it reaches, per group:

* **neck**: the user's realised head movement (neck minus their static pose) at the agent's own
  mimicry lag, when that moment lies in the window (``dyadic.mimicry``); and the user's phrase ends
  in 0.1-s lag bins over 0-3 s, which time the listener's nods (``motion.listener_reaction``);
* **upper face**: the conversation's mood as both voices' arousal inside the window determine it
  (``dyadic.shared_mood`` restricted to the window).

Targets are the agent's motion minus its per-conversation mean (a resting pose is not what context
explains), and the features are centred the same way (a within-conversation regression). The gain
from 0 to 7 past turns bounds what TIMAR's history can add on this corpus: no model can gain what
the data does not contain.
"""

from __future__ import annotations

import numpy as np

from jaxtalk.data.synthtalk import dyadic
from jaxtalk.data.synthtalk.emotions import face_offset
from jaxtalk.layout import GROUPS, NECK_SLICE

__all__ = ["LAG_BIN_S", "MAX_NOD_LAG_S", "window_starts", "side_features", "context_ceiling"]

LAG_BIN_S = 0.1
MAX_NOD_LAG_S = 3.0
_GROUPS = {"neck": np.arange(NECK_SLICE.start, NECK_SLICE.stop), "upper_face": GROUPS["upper_face"]}


def window_starts(num_frames: int, past_turns: int, frames_per_turn: int = 25) -> np.ndarray:
    """First visible frame of each frame's window (current turn plus ``past_turns``), ``(num_frames,)``."""
    return np.maximum((np.arange(num_frames) // frames_per_turn - past_turns) * frames_per_turn, 0)


def side_features(corpus, agent: int, user: int, past_turns: int, *, frames_per_turn: int = 25,
                  fps: int = 25) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per group, ``(centred features (T, F), centred agent target (T, G))`` of one agent side.

    Args:
        corpus: a ``SynthTalkCorpus``.
        agent, user: clip indices of the agent and its conversation partner.
        past_turns: turns of context before the current one.
        frames_per_turn: frames per turn.
        fps: frame rate.
    """
    a, u = corpus.clips[agent], corpus.clips[user]
    agent_motion, _ = corpus.motion_without_audio(agent)
    user_motion, _ = corpus.motion_without_audio(user)
    n = min(len(agent_motion), len(user_motion)) // frames_per_turn * frames_per_turn
    start = window_starts(n, past_turns, frames_per_turn)
    f = np.arange(n)
    # Neck: the user's head movement at the agent's mimicry lag, if inside the window.
    lag = max(1, int(round(a.style.mimic_lag * fps)))
    static = u.style.rest + corpus.spec.emotion_gain * face_offset(u.emotion, u.intensity)
    dev = user_motion[:, NECK_SLICE].astype(np.float64) - static[None, NECK_SLICE]
    src = f - lag
    seen = src >= start
    echo = np.where(seen[:, None], dev[np.clip(src, 0, None)], 0.0)
    # ... and the user's turn ends (not backchannels) in lag bins, if inside the window.
    ends = u.timeline.phrase_ends[~u.timeline.backchannel]
    bins = int(round(MAX_NOD_LAG_S / LAG_BIN_S))
    nods = np.zeros((n, bins))
    t = f / fps
    for end in ends:
        since = t - end
        visible = (since >= 0) & (since < MAX_NOD_LAG_S) & (end * fps >= start)
        nods[visible, (since[visible] / LAG_BIN_S).astype(int)] = 1.0
    neck_x = np.concatenate([echo, seen[:, None].astype(np.float64), nods], axis=1)
    # Upper face: the mood as the window's voices determine it.
    face_x = dyadic.shared_mood(a.timeline, u.timeline, n, fps, start=start)[:, None]
    out = {}
    for name, x in (("neck", neck_x), ("upper_face", face_x)):
        y = agent_motion[:n, _GROUPS[name]].astype(np.float64)
        # Within-conversation regression: features centred like the target (a per-side offset is the
        # resting pose's business, not context's).
        out[name] = (x - x.mean(0), y - y.mean(0))
    return out


def context_ceiling(corpus, train: list[tuple[int, int]], test: list[tuple[int, int]], past_turns: int, *,
                    alpha: float = 1.0) -> dict[str, float]:
    """Held-out R^2 per group of a ridge fit on the true events visible with ``past_turns`` of context.

    Args:
        corpus: a ``SynthTalkCorpus``.
        train, test: ``(agent, user)`` clip pairs (both roles of a conversation may appear).
        past_turns: turns of context before the current one.
        alpha: ridge penalty.

    Returns:
        ``{"neck": R^2, "upper_face": R^2}``, each pooled over the group's channels
        (``1 - SSE / SST`` on the test sides).
    """
    feats = {"train": [side_features(corpus, a, u, past_turns) for a, u in train],
             "test": [side_features(corpus, a, u, past_turns) for a, u in test]}
    out = {}
    for name in _GROUPS:
        x, y = (np.concatenate(p) for p in zip(*[d[name] for d in feats["train"]]))
        xt, yt = (np.concatenate(p) for p in zip(*[d[name] for d in feats["test"]]))
        w = np.linalg.solve(x.T @ x + alpha * np.eye(x.shape[1]), x.T @ y)
        out[name] = float(1.0 - np.sum((yt - xt @ w) ** 2) / np.sum(yt**2))
    return out
