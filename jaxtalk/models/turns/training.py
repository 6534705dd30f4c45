"""How TIMAR and the DualTalk baseline are trained: the same turn windows, settings and key split.

TIMAR's Table 1 retrains DualTalk "under the same training configuration as TIMAR"; both recipes call
:func:`train_on_turn_windows` with their own model's ``init_params`` and loss, so neither imports the
other.
"""

from __future__ import annotations

import dataclasses

from collections.abc import Callable
from typing import Any

import jax
import numpy as np

from jaxtalk.data.batching import fit_length
from jaxtalk.models.turns.windows import Normalizer, TurnWindows, agent_sides, make_windows, side_streams
from jaxtalk.data.loader import PreparedData
from jaxtalk.metrics import CONVERSATION_GROUPS, PUBLISHED_SCALE, SID_CLUSTERS, conversation_metrics
from jaxtalk.metrics.evaluation import SCORINGS, EvalSettings, EvalTable
from jaxtalk.runs import RunSettings, fit_run
from jaxtalk.train.optim import OptimConfig
from jaxtalk.train.recipes import VAL_CLIPS, RecipeResult, TrainSettings, host_copy, spread
from jaxtalk.types import PRNGKeyArray

__all__ = ["TURN_DEFAULTS", "TURN_PRESET_DEFAULTS", "train_on_turn_windows", "conversation_validation",
           "SELECTION_METRIC", "evaluate_sides", "SidePredictor"]

PyTree = Any
# ``predict(params, (user_speech, user_motion, agent_speech), key, context) -> (1, F, 56)``: a turn
# model's agent motion for one conversation side, in the training normalisation.
Predict = Callable[[PyTree, tuple[np.ndarray, np.ndarray, np.ndarray], PRNGKeyArray, int], Any]

# The metric a turn model's run selects its best checkpoint by: the Frechet distance of the agent's
# motion to the truth's, at the scale the published tables print, averaged over the three groups
# (expression, jaw, pose); the metric TIMAR's tables lead with.
SELECTION_METRIC = "FD"

# What trains TIMAR's small model (and the baseline's) on 2 CPU cores.
TURN_DEFAULTS = TrainSettings(lr=1e-3, warmup_steps=20, final_lr_ratio=0.1)
# Training settings of each config preset. The paper (Sec. 4): AdamW at 1e-4, batch 32, a 100-iteration
# warm-up and no stated decay, so the rate stays constant after the warm-up (as MAR's public recipe).
TURN_PRESET_DEFAULTS: dict[str, TrainSettings] = {
    "small": TURN_DEFAULTS,
    "paper": TrainSettings(lr=1e-4, warmup_steps=100, final_lr_ratio=1.0, batch_size=32),
}
# The public code's released model (``TimarConfig.reference``, ``jaxtalk convert``) trained like the paper.
TURN_PRESET_DEFAULTS["reference"] = TURN_PRESET_DEFAULTS["paper"]


def train_on_turn_windows(
    model: str,
    config: Any,
    data: PreparedData,
    optim: OptimConfig,
    init_params: Callable[[Any, PRNGKeyArray], PyTree],
    make_loss_fn: Callable[[Any], Callable[..., Any]],
    *,
    key: PRNGKeyArray,
    run: RunSettings,
    params: PyTree | None = None,
    normalizer: Normalizer | dict[str, Any] | None = None,
    predict: Predict | None = None,
    val_clips: int = VAL_CLIPS,
) -> RecipeResult:
    """The training TIMAR and the DualTalk baseline share: :func:`make_windows`' turn windows and
    normaliser, one key split (init / train / eval) and the run's ``extra`` (normaliser, window turns,
    still pose), so that both models see the same data under the same settings.

    Args:
        model: the run's model name (``"timar"``, ``"dualtalk"``).
        config: the model's config (a :class:`TurnConfig`).
        init_params: ``(config, key) -> params`` (used when ``params`` is None).
        make_loss_fn: ``config -> loss_fn`` for :func:`~jaxtalk.runs.fit_run`.
        run: the run's settings (:class:`~jaxtalk.runs.RunSettings`); its ``window_frames`` must be None
            (the windows are ``num_turns`` whole turns).
        normalizer: the standardisation to train with (a :class:`~jaxtalk.models.turns.windows.Normalizer`
            or its ``to_dict()``): a fine-tuned run keeps its starting run's; None: fitted on ``data``.
        predict: how the model predicts a conversation side as users run it (TIMAR: streamed turn by
            turn; the baseline: turn windows); each evaluation then predicts ``val_clips`` val sides
            (:func:`conversation_validation`) and the best checkpoint is the one of the lowest
            :data:`SELECTION_METRIC`. None: the validation loss only.
        val_clips: conversation sides predicted at each evaluation (0: the validation loss only).
        others: as every recipe's ``train``.

    Raises:
        ValueError: ``run.window_frames`` set.
    """
    if run.window_frames is not None:
        raise ValueError(f"window_frames is not a {model} setting: its windows are whole turns (max_turns)")
    recipe = make_windows(config, data)
    if normalizer is not None:
        given = normalizer if isinstance(normalizer, Normalizer) else Normalizer.from_dict(normalizer)
        recipe = dataclasses.replace(recipe, normalizer=given)
    k_init, k_train, k_eval = jax.random.split(key, 3)
    if params is None:
        params = init_params(config, k_init)
    extra = {"normalizer": recipe.normalizer.to_dict(), "num_turns": recipe.num_turns, "still": list(recipe.still)}
    if normalizer is not None:
        extra["init"] = True  # the normaliser came with the starting parameters: a resume keeps it
    sample_eval = None if predict is None else conversation_validation(
        data, recipe, "val", predict=predict, key=jax.random.fold_in(k_eval, 1), clips=val_clips)
    return fit_run(recipe, data, make_loss_fn(config), params, optim, config=config, key=k_train, eval_key=k_eval,
                   run=run, metadata={"model": model}, extra=extra, sample_eval=sample_eval, best_metric=SELECTION_METRIC)


def conversation_validation(
    data: PreparedData,
    windows: TurnWindows,
    split: str = "val",
    *,
    predict: Predict,
    key: PRNGKeyArray,
    clips: int = VAL_CLIPS,
) -> Callable[[Any, Any, int], dict[str, float]] | None:
    """An ``eval_fn`` for the training loop that predicts ``clips`` conversation sides of ``split`` as
    ``jaxtalk eval`` does and scores them with the DualTalk benchmark's metrics.

    Each side is the agent's whole turns (with ``windows.num_turns - 1`` turns of context), and the
    frames after its last whole turn repeat the last prediction (TIMAR's protocol); a partner without
    tracked motion is the run's still pose. The same sides and keys at every evaluation. Scored with
    :func:`~jaxtalk.metrics.conversation_metrics` at the published scale, without SID (its k-means is
    slow and needs 40 frames per side).

    Args:
        data: the prepared dataset.
        windows: the run's turn windows (normaliser, turns per window, still pose).
        split: the split to score.
        predict: the model's prediction of one side (see :data:`Predict`).
        key: the sampling key (side ``n`` uses ``fold_in(key, n)``).
        clips: how many sides, evenly spread over the split's.

    Returns:
        ``eval_fn(params, ema_params, step) -> {"FD_g", "P-FD_g", "MSE_g", "rPCC_g" for g in exp, jaw,
        pose, and "FD": the mean of the three FDs}`` (the EMA parameters when the run keeps them), or
        None when ``clips`` is 0 or the split has no side of a whole turn.
    """
    from jaxtalk.metrics import conversation_metrics

    if clips < 1 or not data.split(split):
        return None
    norm = windows.normalizer
    context = max(windows.num_turns - 1, 0)
    sides = [side for i, j in agent_sides(data, split)
             if (side := side_streams(data, i, j, norm, windows.still, windows.config.frames_per_turn)) is not None]
    if not sides:
        return None
    sides = [sides[int(k)] for k in spread(len(sides), clips)]

    def eval_fn(params: Any, ema_params: Any, step: int) -> dict[str, float]:
        use = host_copy(ema_params if ema_params is not None else params)
        preds = [fit_length(norm.unmotion(np.asarray(predict(use, s.streams, jax.random.fold_in(key, n), context))[0]),
                            s.truth.shape[0]) for n, s in enumerate(sides)]
        scores = conversation_metrics(preds, [s.truth for s in sides], [s.partner for s in sides], scaled=True,
                                      sid_convention=None)
        scores[SELECTION_METRIC] = float(np.mean([scores[f"FD_{g}"] for g in ("exp", "jaw", "pose")]))
        return scores

    return eval_fn

# ------------------------------------------------------------------------------------------ evaluation
_GROUP_COLUMNS = ("FD", "P-FD", "MSE", "SID", "rPCC")
# ``predict(streams, key, context)`` of a turn model for one conversation side (see :func:`evaluate_sides`).
SidePredictor = Callable[[tuple[Any, Any, Any], PRNGKeyArray, int], Any]


def evaluate_sides(run: Any, data: PreparedData, split: str, opts: EvalSettings, echo: Callable[[str], None], *,
                   predict: SidePredictor, title: str, label: str, verb: str) -> tuple[int, list[EvalTable]]:
    """A turn model on a split of prepared data: every conversation side whose partner is prepared (up to
    ``max_clips``), predicted by ``predict`` with the run's normaliser and context, and scored with the
    DualTalk benchmark (:func:`jaxtalk.metrics.conversation_metrics`) per group (exp, jaw, pose): FD, P-FD,
    MSE, SID (k-means fit on the ground truth; 40 frames per side, else left out) and rPCC, in the
    published scaling, beside the mean pose and the oracle (where every side has one).

    Args:
        run: the loaded run (TIMAR or the DualTalk baseline).
        data, split: the prepared data and its split.
        opts: the settings.
        echo: where progress lines and notes go.
        predict: ``predict(streams, key, context)``: the side's standardised ``(user_speech, user_motion,
            agent_speech)`` streams ``(1, T, .)`` -> ``(1, T', 56)`` standardised agent motion.
        title: the model's name in the tables; label: its row; verb: what it does to a side (progress).

    Raises:
        ValueError: a split without a conversation side of a whole turn.
    """
    config, extra = run.config, run.record.extra
    sides = agent_sides(data, split)
    if not sides:
        raise ValueError(f"split {split!r} of {data.root} has no conversation side (a clip with motion whose "
                         "partner's clip is prepared)")
    norm = Normalizer.from_dict(extra["normalizer"])
    still = np.asarray(extra.get("still", norm.motion_mean), np.float32)
    context = max(extra.get("num_turns", config.max_turns) - 1, 0)
    f = config.frames_per_turn
    key = jax.random.key(opts.seed)
    chosen = sides[: opts.max_clips]
    echo(f"{verb} {len(chosen)} {split} conversation sides of {data.root} with {title} (step {run.step})")
    preds, gts, partners, oracles, still_partners, padded_frames = [], [], [], [], 0, 0
    for n, (i, j) in enumerate(chosen):
        # Scored over the agent's whole side (as far as the partner's motion goes); the model predicts
        # whole turns, and the frames after the last whole one repeat its last prediction (the paper's
        # protocol, TIMAR Sec. 4.4).
        side = side_streams(data, i, j, norm, still, f)
        if side is None:
            continue
        still_partners += side.still_partner
        padded_frames += side.padded_frames
        out = predict(side.streams, jax.random.fold_in(key, n), context)
        preds.append(norm.unmotion(np.asarray(out)[0]))  # the whole turns predicted
        gts.append(side.truth)
        partners.append(side.partner)
        oracles.append(side.oracle)
    if not preds:
        raise ValueError(f"split {split!r} of {data.root} has no conversation side of a whole {f}-frame turn")
    if padded_frames and "jaxtalk" in opts.scoring:
        echo(f"note: {padded_frames} frames after the sides' last whole {f}-frame turns repeat the last prediction "
             "(TIMAR's protocol)")
    if still_partners:
        echo(f"note: {still_partners} of {len(preds)} partners have no tracked motion; P-FD and rPCC use the run's "
             "still pose for them (as training did)")
    tables = []
    for scoring in opts.scoring:
        tables += _scored_tables(scoring, label, preds, gts, partners, oracles, norm, echo,
                                 f"{title} on {split} ({data.root.name})", named=len(opts.scoring) > 1)
    return len(gts), tables


def _scored_tables(scoring: str, label: str, preds: list[np.ndarray], gts: list[np.ndarray],
                   partners: list[np.ndarray], oracles: list[Any], norm: Normalizer, echo: Callable[[str], None],
                   title: str, *, named: bool) -> list[EvalTable]:
    """The tables of one :data:`~jaxtalk.metrics.evaluation.SCORINGS` entry: ``jaxtalk`` scores each
    agent's whole side (the prediction's tail repeats its last whole turn); ``public`` cuts prediction,
    truth and partner to the shortest, as the public ``calc_metric.py`` does with predictions of whole
    seconds."""
    public = scoring == "public"
    if public:
        scored = [min(p.shape[0], g.shape[0], q.shape[0]) for p, g, q in zip(preds, gts, partners)]
        fitted = list(preds)
    else:
        scored = [g.shape[0] for g in gts]
        fitted = [fit_length(p, g.shape[0]) for p, g in zip(preds, gts)]
    with_sid = min(scored) >= max(SID_CLUSTERS.values())
    if not with_sid:
        echo(f"note: a side is shorter than {max(SID_CLUSTERS.values())} frames: SID left out")
    methods = {label: fitted, "mean pose": [np.broadcast_to(norm.motion_mean, g.shape).astype(np.float32)
                                             for g in gts]}
    if all(o is not None for o in oracles):
        methods["oracle"] = oracles
    if public:  # every method on the frames the prediction covers
        methods = {name: [m[:n] for m, n in zip(arrays, scored)] for name, arrays in methods.items()}
    scores = {name: conversation_metrics(list(p), gts, partners, scaled=True, truncate=public,
                                         sid_convention="fit_gt" if with_sid else None)
              for name, p in methods.items()}
    frames = int(sum(scored))
    tables = []
    for group in CONVERSATION_GROUPS:
        rows = []
        for name, m in scores.items():
            row: dict[str, Any] = {"method": name, "sides": len(gts), "frames": frames}
            for col in _GROUP_COLUMNS:
                row[col] = m.get(f"SID_fit_gt_{group}") if col == "SID" else m[f"{col}_{group}"]
            rows.append(row)
        scaling = ", ".join(f"{col} x{PUBLISHED_SCALE[f'{col}_{group}']:g}" for col in _GROUP_COLUMNS
                            if f"{col}_{group}" in PUBLISHED_SCALE)
        how = f" [{scoring} scoring: {SCORINGS[scoring]}]" if named or public else ""
        tables.append(EvalTable(f"{title}, {group}{' (' + scaling + ')' if scaling else ''}{how}", rows))
    return tables
