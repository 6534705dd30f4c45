"""TIMAR's recipe: conversation windows of a prepared dataset, and the one way the model is trained.

Every clip with motion whose conversation partner is in the dataset is an agent side; the partner is
the user. A window is ``num_turns`` whole 1-s turns starting on a turn boundary: both sides' per-turn
speech features (each turn computed from its own audio by ``prepare``) and both motions, standardised
with a :class:`~jaxtalk.models.timar.data.Normalizer` fitted on the training agents. A partner without
tracked motion (DualTalk's audio-only sides) contributes its speech and the training mean pose as its
motion: a constant that carries no information about the agent.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import numpy as np

from jaxtalk.data.loader import PreparedData
from jaxtalk.data.standardize import fit_standardizer
from jaxtalk.models.timar.config import TimarConfig
from jaxtalk.models.timar.data import Normalizer
from jaxtalk.train import OptimConfig
from jaxtalk.train.recipes import RecipeResult, TrainSettings, fit_recipe
from jaxtalk.types import PRNGKeyArray

__all__ = ["DEFAULTS", "TimarWindows", "agent_sides", "fit_data_normalizer", "window_turns", "train"]

PyTree = Any

# What trains the small model on 2 CPU cores; the paper: AdamW 1e-4 at batch 32, 100 warm-up steps.
DEFAULTS = TrainSettings(lr=1e-3, warmup_steps=20, final_lr_ratio=0.1)


def agent_sides(data: PreparedData, split: str) -> list[tuple[int, int]]:
    """``(agent, user)`` clip positions: clips with motion, per-turn speech and a prepared partner."""
    out = []
    for i in data.split(split):
        j = data.partner(i)
        if j is not None and data.clips[i]["frames"] >= data.manifest["turn_frames"]:
            out.append((i, j))
    return out


def fit_data_normalizer(data: PreparedData, *, floor: float = 1e-3) -> Normalizer:
    """The speech and motion standardisation of the training split's agent sides.

    Raises:
        ValueError: a training split without conversations.
    """
    sides = agent_sides(data, "train")
    if not sides:
        raise ValueError(f"{data.root}: TIMAR trains on conversations and the training split has none "
                         "(a clip with motion needs its partner's clip)")
    speech, motion = [], []
    for i, _ in sides:
        rec = data.record(i, ("turn_speech", "motion"))
        speech.append(rec["turn_speech"])
        motion.append(rec["motion"][: rec["turn_speech"].shape[0]])
    s, m = fit_standardizer(np.concatenate(speech), floor=floor), fit_standardizer(np.concatenate(motion), floor=floor)
    return Normalizer(s["mean"], s["std"], m["mean"], m["std"])


def window_turns(config: TimarConfig, data: PreparedData) -> int:
    """Turns per training window: the config's ``max_turns``, capped by the longest training side."""
    sides = agent_sides(data, "train")
    longest = max(min(data.clips[i]["frames"], data.clips[j]["frames"]) for i, j in sides) // config.frames_per_turn
    return max(1, min(config.max_turns, longest))


@dataclasses.dataclass(frozen=True)
class TimarWindows:
    """TIMAR's window recipe (see the module docstring).

    Attributes:
        config: the model config (frames per turn).
        num_turns: turns per window.
        normalizer: the training standardisation.
        still: ``(56,)`` the motion of a partner without tracked motion (the training mean pose).
    """

    config: TimarConfig
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


def make_windows(config: TimarConfig, data: PreparedData) -> TimarWindows:
    """The recipe with its normaliser fitted on ``data``'s training split."""
    if data.manifest["turn_speech_dim"] != config.speech_dim:
        raise ValueError(f"{data.root} has {data.manifest['turn_speech_dim']}-d speech features but the model "
                         f"expects speech_dim={config.speech_dim} (--set speech_dim=...)")
    normalizer = fit_data_normalizer(data)
    still = tuple(float(v) for v in data.motion_stats()["mean"])
    return TimarWindows(config, window_turns(config, data), normalizer, still)


def train(
    config: TimarConfig,
    data: PreparedData,
    optim: OptimConfig,
    *,
    steps: int | None = None,
    key: PRNGKeyArray,
    batch_size: int = 16,
    seed: int = 0,
    params: PyTree | None = None,
    ckpt_dir: Any = None,
    mesh: Any = None,
    eval_every: int | None = None,
    **loop_kwargs: Any,
) -> RecipeResult:
    """Train TIMAR on ``data``'s training conversations (arguments as every recipe's ``train``).

    Returns:
        :class:`~jaxtalk.train.recipes.RecipeResult`; ``extra`` holds the normaliser, the window's
        turns and the still pose of motionless partners.
    """
    from jaxtalk.models.timar.loss import make_loss_fn
    from jaxtalk.models.timar.model import init_params
    recipe = make_windows(config, data)
    k_init, k_train, k_eval = jax.random.split(key, 3)
    if params is None:
        params = init_params(config, k_init)
    extra = {"normalizer": recipe.normalizer.to_dict(), "num_turns": recipe.num_turns, "still": list(recipe.still)}
    return fit_recipe(recipe, data, make_loss_fn(config), params, optim, key=k_train, eval_key=k_eval, steps=steps, batch_size=batch_size, seed=seed, ckpt_dir=ckpt_dir, mesh=mesh, eval_every=eval_every,
                      metadata={"model": "timar"}, extra=extra, **loop_kwargs)
