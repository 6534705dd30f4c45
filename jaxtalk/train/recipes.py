"""What the model recipes share: the result type, a validation-loss evaluator, the training on windows.

A recipe (``jaxtalk.models.<model>.recipe``) is the one way a model is trained: it cuts windows from
a prepared dataset (:mod:`jaxtalk.data.loader`), fits what the model needs from the training split
(normalisers), and runs the shared loop. Every recipe's entry point has the same shape::

    train(config, data, optim, *, key, run=RunSettings(), params=None, ...) -> RecipeResult

where :class:`jaxtalk.runs.RunSettings` holds what every recipe takes (steps, batch, seed, window,
validation period, where the run goes, the mesh, the :class:`~jaxtalk.train.LoopSettings`) and the
keywords after ``params`` are the model's own.

A recipe trains through :func:`jaxtalk.runs.fit_run`: :func:`fit_recipe` here (the training alone), then,
given a ``run_dir``, the run record (:func:`jaxtalk.runs.write_run`) that ``jaxtalk sample``, ``eval`` and
:func:`jaxtalk.runs.load_run` open. This layer sits below the run format and knows nothing of it.
"""

from __future__ import annotations

import dataclasses
import os
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh

from jaxtalk.data.loader import PreparedData, WindowRecipe, make_loader
from jaxtalk.train.loop import EvalFn, LoopSettings, TrainResult, train
from jaxtalk.train.observers import StepObserver
from jaxtalk.train.optim import OptimConfig, Trainable
from jaxtalk.train.step import LossFn
from jaxtalk.types import PRNGKeyArray

PyTree = Any

__all__ = ["TrainSettings", "RecipeResult", "BatchSizeWarning", "usable_batch_size", "validation_eval", "split_validation",
           "fixed_batches", "spread", "host_copy", "evaluation", "merged_eval", "fit_recipe", "VAL_WINDOWS", "VAL_CLIPS"]

# Validation windows scored at each evaluation (a fixed, evenly spread subset of the split).
VAL_WINDOWS = 64
# Held-out clips (conversation sides for the turn models) that a model's validation samples and scores
# at each evaluation, as users run the model (every recipe's ``val_clips`` default).
VAL_CLIPS = 8


@dataclasses.dataclass(frozen=True)
class TrainSettings:
    """How a recipe trains, besides the model config: overridable like config fields (``--set``).

    Attributes:
        lr: peak learning rate (AdamW, linear warm-up then cosine decay).
        weight_decay: decoupled weight decay.
        warmup_steps: warm-up length (capped at a tenth of the run so short runs keep a decay phase;
            see :meth:`optim`).
        final_lr_ratio: learning rate at the end as a fraction of ``lr``.
        clip_norm: global gradient-norm clip.
        ema_decay: decay of the (bias-corrected) EMA of the weights used for sampling; None: off.
        batch_size: windows per step on each process.
        window_frames: frames per training window (None: the model's default; 0: whole clips, padded
            and masked: ATS's ``paper`` preset).
        eval_every: validation period in steps (None: five evaluations per run).
        val_clips: held-out clips sampled and scored at each evaluation by a model whose validation
            samples (TokTalk streamed, ATS with DDIM, TIMAR and DualTalk turn by turn, STM on
            held-out meshes); None: the model's default, 0: the validation loss only.
    """

    lr: float = 1e-3
    weight_decay: float = 1e-2
    warmup_steps: int = 100
    final_lr_ratio: float = 0.0
    clip_norm: float = 1.0
    ema_decay: float | None = None
    batch_size: int = 16
    window_frames: int | None = None
    eval_every: int | None = None
    val_clips: int | None = None

    def __post_init__(self) -> None:
        if self.batch_size < 1 or self.warmup_steps < 0 or (self.window_frames is not None and self.window_frames < 0):
            raise ValueError(f"batch_size must be >= 1, window_frames >= 0 and warmup_steps >= 0: {self}")
        if self.eval_every is not None and self.eval_every < 1:
            raise ValueError(f"eval_every must be >= 1 or None, got {self.eval_every}")
        if self.val_clips is not None and self.val_clips < 0:
            raise ValueError(f"val_clips must be >= 0 or None, got {self.val_clips}")

    def optim(self, steps: int) -> Any:
        """The :class:`~jaxtalk.train.OptimConfig` of a ``steps``-long run.

        The warm-up is capped at a tenth of the run so that a short run keeps its decay phase: a run of
        at least ``10 * warmup_steps`` steps gets the whole warm-up (the ``paper`` presets' 100 steps
        from 1,000 steps on). ``jaxtalk train`` prints the warm-up it uses and the cap when it binds, and
        the run records the warm-up it trained with.
        """
        from jaxtalk.train.optim import OptimConfig

        return OptimConfig(lr=self.lr, weight_decay=self.weight_decay, warmup_steps=min(self.warmup_steps, steps // 10),
                           total_steps=steps, clip_norm=self.clip_norm, ema_decay=self.ema_decay,
                           final_lr_ratio=self.final_lr_ratio)

    def describe(self, steps: int) -> str:
        """One line on the schedule of a ``steps``-long run: the learning rate and the warm-up it uses,
        with the cap when it binds (what ``jaxtalk train`` prints)."""
        warmup = self.optim(steps).warmup_steps
        capped = (f" (capped from {self.warmup_steps} at a tenth of this {steps}-step run)"
                  if warmup < self.warmup_steps else "")
        return f"learning rate {self.lr:g}, warm-up {warmup} steps{capped}"

    @classmethod
    def of_run(cls, optim: Any, *, batch_size: int, window_frames: int | None = None,
               eval_every: int | None = None) -> TrainSettings:
        """The settings a recipe ran with, read back from its optimiser settings and arguments (what a
        run made from Python records; the warm-up is the one the run used, already capped)."""
        return cls(lr=optim.lr, weight_decay=optim.weight_decay, warmup_steps=optim.warmup_steps,
                   final_lr_ratio=optim.final_lr_ratio, clip_norm=optim.clip_norm, ema_decay=optim.ema_decay,
                   batch_size=batch_size, window_frames=window_frames, eval_every=eval_every)

    def period(self, steps: int) -> int:
        """The validation period of a ``steps``-long run."""
        return self.eval_every or max(steps // 5, 1)


@dataclasses.dataclass
class RecipeResult(TrainResult):
    """:class:`~jaxtalk.train.TrainResult` plus what sampling needs besides the parameters.

    Attributes:
        extra: JSON-serialisable settings fitted on the training split (normalisers, window sizes),
            stored in the run's ``run.json``.
        windows: training windows (this process's shard).
        batch_size: windows per step on this process as trained: the requested batch, or the
            largest the training split allows (:func:`usable_batch_size`). A run's record stores
            this one, so a resume trains with the same batch.
    """

    extra: dict[str, Any] = dataclasses.field(default_factory=dict)
    windows: int = 0
    batch_size: int = 0


class BatchSizeWarning(UserWarning):
    """The training split has fewer windows than one batch: the recipe trains with a smaller one."""


def usable_batch_size(windows: int, batch_size: int, *, processes: int = 1, multiple: int = 1) -> int:
    """The batch a split of ``windows`` windows can train with: ``batch_size``, or the largest that fits.

    A global batch (``batch_size`` x ``processes``) must be cut from the windows of one pass, so a
    small dataset (a handful of conversations) cannot fill the default batch; rather than refuse to
    train, take the largest per-process batch that fits and is a multiple of ``multiple`` (the local
    devices a data-parallel batch is split over).

    Args:
        windows: windows in the training split.
        batch_size: the requested per-process batch.
        processes: processes sharing each global batch.
        multiple: the batch must divide into this many equal parts.

    Returns:
        ``batch_size`` when it fits, else the largest fitting multiple of ``multiple``.

    Raises:
        ValueError: not even ``multiple`` windows per process (the message names the counts).
    """
    if windows >= batch_size * processes:
        return batch_size
    fitted = windows // processes // multiple * multiple
    if fitted < 1:
        raise ValueError(f"split 'train' has {windows} windows, fewer than {multiple} per process x {processes} "
                         "process(es): too little data to train on")
    return fitted


def validation_eval(
    loss_fn: Callable[[Any, dict, jax.Array], tuple[jax.Array, dict]],
    batches: list[dict[str, np.ndarray]],
    key: jax.Array,
) -> Callable[[Any, Any, int], dict[str, float]]:
    """An ``eval_fn`` for :func:`jaxtalk.train.train`: the model's own loss on fixed validation batches.

    The same batches and keys at every evaluation, so the curve moves only with the parameters. The
    evaluated parameters are the EMA when the run keeps one (what sampling uses).

    In a multi-process run every process calls ``eval_fn`` with the same batches and its part of the
    replicated parameters (arrays over every process's devices): the jitted loss takes each batch as
    replicated too, so every process computes, and returns, the same value.

    Args:
        loss_fn: the training loss ``(params, batch, key) -> (loss, metrics)``.
        batches: validation batches (the same structure as training batches).
        key: the evaluation key.

    Returns:
        ``eval_fn(params, ema_params, step) -> {"val_loss": float}``.
    """
    jitted = jax.jit(lambda p, b, k: loss_fn(p, b, k)[0])
    keys = jax.random.split(key, max(len(batches), 1))

    def eval_fn(params: Any, ema_params: Any, step: int) -> dict[str, float]:
        use = ema_params if ema_params is not None else params
        losses = [float(jitted(use, b, k)) for b, k in zip(batches, keys)]
        return {"val_loss": float(np.mean(losses))}

    return eval_fn


def fixed_batches(examples: list[dict[str, np.ndarray]], batch_size: int) -> list[dict[str, np.ndarray]]:
    """Stack ``examples`` into full batches of ``batch_size`` (a last partial batch is dropped)."""
    out = []
    for s in range(0, len(examples) - batch_size + 1, batch_size):
        group = examples[s:s + batch_size]
        out.append({k: np.stack([e[k] for e in group]) for k in group[0]})
    return out


def spread(n: int, k: int) -> np.ndarray:
    """``min(n, k)`` indices spread evenly over ``range(n)`` (a deterministic subset)."""
    return np.unique(np.linspace(0, n - 1, min(n, k)).round().astype(np.int64)) if n else np.zeros(0, np.int64)


def host_copy(tree: Any) -> Any:
    """Parameters as one full copy on this process, for a validation that samples on one device: a
    data-parallel run's replicated arrays span several devices (some of another process's)."""
    def local(x: Any) -> Any:
        if isinstance(x, jax.Array) and len(x.sharding.device_set) > 1:
            return np.asarray(x.addressable_data(0))
        return x

    return jax.tree.map(local, tree)


def split_validation(data: Any, recipe: Any, loss_fn: Any, batch_size: int, key: jax.Array,
                     split: str = "val") -> Callable[[Any, Any, int], dict[str, float]] | None:
    """:func:`validation_eval` on up to :data:`VAL_WINDOWS` evenly spread windows of ``split``.

    ``batch_size`` is the per-process training batch; validation batches hold the global batch
    (``batch_size`` x ``jax.process_count()``), so a run on several processes scores the same batches
    with the same keys, and reports the same loss, as one process with the global batch size.

    Returns:
        The ``eval_fn``, or None when the split has fewer windows than one batch.
    """
    batch_size *= jax.process_count()
    table = recipe.table(data, split) if data.split(split) else np.zeros((0, 1), np.int64)
    if len(table) < batch_size:
        return None
    examples = [recipe.example(data, table[j]) for j in spread(len(table), max(VAL_WINDOWS, batch_size))]
    return validation_eval(loss_fn, fixed_batches(examples, batch_size), key)


def merged_eval(*eval_fns: Callable[[Any, Any, int], dict[str, float]] | None
                ) -> Callable[[Any, Any, int], dict[str, float]] | None:
    """One ``eval_fn`` returning the metrics of every given one (None entries skipped; None if none)."""
    fns = [f for f in eval_fns if f is not None]
    if not fns:
        return None

    def eval_fn(params: Any, ema_params: Any, step: int) -> dict[str, float]:
        out: dict[str, float] = {}
        for f in fns:
            out.update(f(params, ema_params, step))
        return out

    return eval_fn


def evaluation(eval_fn: EvalFn | None, settings: LoopSettings, ckpt_dir: str | os.PathLike | None) -> LoopSettings:
    """The loop's evaluation settings: validate every ``settings.eval_every`` steps and, with
    checkpoints, keep the state of the best ``settings.best_metric`` (the lowest with ``best_mode="min"``,
    the highest with ``"max"``) in ``<ckpt_dir>/best`` (no evaluation when there is no ``eval_fn``, no
    best checkpoint with ``best_metric=None`` or without ``ckpt_dir``). A resumed run whose best checkpoint
    was chosen by another metric (a run started before its model selected by sampling) keeps selecting by
    that one, and in its direction, with a warning."""
    if eval_fn is None:
        return dataclasses.replace(settings, eval_every=None, best_metric=None, best_mode="min")
    best_metric, best_mode = settings.best_metric, settings.best_mode
    if ckpt_dir is not None and best_metric is not None:
        from jaxtalk.train.checkpoint import read_best

        record = read_best(ckpt_dir)
        saved = None if record is None else record["metric"]
        if saved is not None and saved != best_metric:
            warnings.warn(f"this run's best checkpoint was chosen by {saved!r}; it keeps selecting by it rather "
                          f"than {best_metric!r}", stacklevel=4)
            best_metric, best_mode = saved, record["mode"]
    return dataclasses.replace(settings, best_metric=best_metric if ckpt_dir is not None else None,
                               best_mode=best_mode)


def fit_recipe(
    recipe: WindowRecipe,
    data: PreparedData,
    loss_fn: LossFn,
    params: PyTree,
    optim: OptimConfig,
    *,
    key: PRNGKeyArray,
    eval_key: PRNGKeyArray,
    batch_size: int,
    seed: int = 0,
    settings: LoopSettings = LoopSettings(),
    ckpt_dir: str | os.PathLike | None = None,
    mesh: Mesh | None = None,
    metadata: dict[str, Any] | None = None,
    sample_eval: EvalFn | None = None,
    trainable: Trainable = None,
    observers: Sequence[StepObserver] = (),
) -> RecipeResult:
    """Train on a recipe's windows: the grain loader over the training split, the validation loss on
    ``val`` (and the best checkpoint), the shared loop. What every recipe does once its windows, loss and
    initial parameters are set.

    A training split with fewer windows than one batch trains with the largest batch it allows
    (:func:`usable_batch_size`, a :class:`BatchSizeWarning`; ``RecipeResult.batch_size`` is the one
    used). With ``ckpt_dir``, the run folder (its parent) gets ``metrics.jsonl`` and TensorBoard event
    files (:mod:`jaxtalk.train.writers`) unless ``settings.log_dir`` names another folder.

    It only trains: the run record (``run.json`` and the inference assets) is the runs layer's
    (:func:`jaxtalk.runs.fit_run`, which the model recipes call).

    Args:
        recipe: the window recipe.
        data: the prepared dataset.
        loss_fn: ``(params, batch, key) -> (loss, metrics)``.
        params: initial parameters.
        optim: optimiser settings.
        key: the loop's base key.
        eval_key: the validation key.
        batch_size: windows per batch on this process (the largest the split allows when it is smaller).
        seed: data-order seed.
        settings: the loop's settings. Its ``best_metric`` is a metric of ``sample_eval`` the best
            checkpoint is chosen by, in the direction of ``best_mode``; None, or no ``sample_eval``: the
            validation loss (lower is better; no best checkpoint when there is no validation loss
            either).
        ckpt_dir: checkpoint folder (exact resume), or None.
        mesh: device mesh for data parallelism, or None.
        metadata: saved with each checkpoint (``metadata["model"]`` names the run's model).
        sample_eval: a validation that samples the model as users do (its metrics join the loss's at
            every evaluation), or None.
        trainable: which parameters train (:func:`jaxtalk.train.train`'s ``trainable``).
        observers: watch the steps (:func:`jaxtalk.train.train`'s ``observers``).

    Returns:
        :class:`RecipeResult` (``extra`` empty: what the recipe fitted is the caller's to add).
    """
    windows = len(recipe.table(data, "train")) if data.split("train") else 0
    fitted = usable_batch_size(windows, batch_size, processes=jax.process_count(),
                               multiple=jax.local_device_count() if mesh is not None else 1) if windows else batch_size
    if fitted != batch_size:
        warnings.warn(f"the training split has {windows} windows, fewer than batch_size={batch_size}"
                      f"{f' x {jax.process_count()} processes' if jax.process_count() > 1 else ''}: training with "
                      f"the largest batch it allows (--set batch_size={fitted})", BatchSizeWarning, stacklevel=4)
        batch_size = fitted
    loader = make_loader(data, recipe, "train", batch_size, seed=seed)
    val_eval = split_validation(data, recipe, loss_fn, batch_size, eval_key)
    eval_fn = merged_eval(val_eval, sample_eval)
    if sample_eval is None or settings.best_metric is None:  # the validation loss, when there is one
        settings = dataclasses.replace(settings, best_metric="val_loss" if val_eval is not None else None,
                                       best_mode="min")
    if ckpt_dir is not None and settings.log_dir is None:
        # The run folder of the run layout: <run>/checkpoint is the checkpoint directory.
        settings = dataclasses.replace(settings, log_dir=Path(ckpt_dir).parent)
    result = train(loss_fn, params, loader, optim, key=key, settings=evaluation(eval_fn, settings, ckpt_dir),
                   ckpt_dir=ckpt_dir, metadata=metadata, eval_fn=eval_fn, trainable=trainable, mesh=mesh,
                   observers=observers)
    return RecipeResult(state=result.state, history=result.history, best=result.best,
                        windows=loader.num_windows, batch_size=batch_size)
