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
from collections.abc import Callable
from pathlib import Path
from typing import Any

import jax
import numpy as np

from jaxtalk.data.loader import PreparedData
from jaxtalk.data.standardize import fit_standardizer
from jaxtalk.data.turns import TurnConfig
from jaxtalk.models.timar.config import TimarConfig
from jaxtalk.models.timar.data import Normalizer
from jaxtalk.runs import RunInfo
from jaxtalk.train import OptimConfig
from jaxtalk.train.recipes import RecipeResult, TrainSettings, fit_recipe
from jaxtalk.types import PRNGKeyArray

__all__ = ["DEFAULTS", "PRESET_DEFAULTS", "TimarWindows", "agent_sides", "fit_data_normalizer", "window_turns", "make_windows",
           "train"]

PyTree = Any

# What trains the small model on 2 CPU cores.
DEFAULTS = TrainSettings(lr=1e-3, warmup_steps=20, final_lr_ratio=0.1)
# Training settings of each config preset. The paper (Sec. 4): AdamW at 1e-4, batch 32, a 100-iteration
# warm-up and no stated decay, so the rate stays constant after the warm-up (as MAR's public recipe).
PRESET_DEFAULTS: dict[str, TrainSettings] = {
    "small": DEFAULTS,
    "paper": TrainSettings(lr=1e-4, warmup_steps=100, final_lr_ratio=1.0, batch_size=32),
}


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
class TimarWindows:
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


def make_windows(config: TurnConfig, data: PreparedData) -> TimarWindows:
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
    run_dir: str | Path | None = None,
    run_info: RunInfo | None = None,
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

    return train_on_turn_windows("timar", config, data, optim, init_params, make_loss_fn, steps=steps, key=key,
                                 batch_size=batch_size, seed=seed, params=params, run_dir=run_dir, run_info=run_info, ckpt_dir=ckpt_dir, mesh=mesh,
                                 eval_every=eval_every, **loop_kwargs)


def train_on_turn_windows(
    model: str,
    config: Any,
    data: PreparedData,
    optim: OptimConfig,
    init_params: Callable[[Any, PRNGKeyArray], PyTree],
    make_loss_fn: Callable[[Any], Callable[..., Any]],
    *,
    steps: int | None,
    key: PRNGKeyArray,
    batch_size: int,
    seed: int,
    params: PyTree | None,
    run_dir: str | Path | None,
    run_info: RunInfo | None,
    ckpt_dir: Any,
    mesh: Any,
    eval_every: int | None,
    **loop_kwargs: Any,
) -> RecipeResult:
    """The training TIMAR and the DualTalk baseline share: :func:`make_windows`' turn windows and
    normaliser, one key split (init / train / eval) and the run's ``extra`` (normaliser, window turns,
    still pose), so that both models see the same data under the same settings.

    Args:
        model: the run's model name (``"timar"``, ``"dualtalk"``).
        config: the model's config (a :class:`TurnConfig`).
        init_params: ``(config, key) -> params`` (used when ``params`` is None).
        make_loss_fn: ``config -> loss_fn`` for :func:`~jaxtalk.train.recipes.fit_recipe`.
        others: as :func:`train`.
    """
    recipe = make_windows(config, data)
    k_init, k_train, k_eval = jax.random.split(key, 3)
    if params is None:
        params = init_params(config, k_init)
    extra = {"normalizer": recipe.normalizer.to_dict(), "num_turns": recipe.num_turns, "still": list(recipe.still)}
    return fit_recipe(recipe, data, make_loss_fn(config), params, optim, key=k_train, eval_key=k_eval, steps=steps,
                      batch_size=batch_size, seed=seed, ckpt_dir=ckpt_dir, mesh=mesh, eval_every=eval_every,
                      metadata={"model": model}, extra=extra, config=config, run_dir=run_dir, run_info=run_info, **loop_kwargs)
