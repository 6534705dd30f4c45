"""``jaxtalk train {toktalk,ats,stm,timar}``: a config preset + overrides, trained on SynthTalk.

Every model trains through the shared loop (:func:`jaxtalk.train.train`), which checkpoints into
``<out>/checkpoint`` and resumes exactly (parameters, optimiser, EMA, RNG and data position): an
interrupted run started again with the same ``--steps`` ends where the uninterrupted one would. A
larger ``--steps`` continues the run with the learning-rate schedule stretched to the new length (the
loop warns that the optimiser config changed). The model config, seed and batch size of a resumed run
come from its ``run.json`` and cannot be changed.

TokTalk and TIMAR train through their packages' entry points (``train_base``, ``train_timar``); ATS
and STM through the loop directly with the recipe of ``freetalk.fit`` (standardised displacements for
ATS; three identities on three mesh topologies for STM), because ``fit_ats``/``fit_stm`` take no
checkpoint directory.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from jaxtalk.commands.runs import MODELS, RunRecord, build_config, checkpoint_dir, config_class, parse_overrides

__all__ = ["TrainOptions", "TrainSummary", "train_run"]

# SEEN meshes of the FreeTalk topology experiment: three identities on three mesh topologies.
STM_MESHES = ((0, "base"), (1, "decimated"), (2, "subdivided"))


@dataclasses.dataclass(frozen=True)
class TrainOptions:
    """Settings of :func:`train_run` (the CLI's options).

    Attributes:
        model: ``toktalk``, ``ats``, ``stm`` or ``timar``.
        out_dir: run folder (``run.json`` + ``checkpoint/``).
        preset: config preset (``small``, ``paper``; ``tiny`` for TokTalk); None: ``small`` for a new
            run, the run's own preset when resuming.
        overrides: ``key=value`` config overrides.
        steps: train until this many optimiser steps in total.
        size: SynthTalk size.
        seed: corpus, initialisation and data-order seed.
        cache_dir: corpus cache (None: generate in memory).
        batch_size: examples per step (a resumed run keeps its own, and its seed).
        lr: peak learning rate.
        resume: continue an existing run in ``out_dir`` (False: refuse to touch it).
        progress: show the progress bar.
        save_every: checkpoint period in steps (default: 5 checkpoints per run; the last step always).
        data_parallel: shard every batch over all local devices (``jaxtalk.train.make_mesh``); the
            batch size must divide by the device count.
    """

    model: str
    out_dir: Path
    preset: str | None = None
    overrides: tuple[str, ...] = ()
    steps: int = 1000
    size: str = "tiny"
    seed: int = 0
    cache_dir: Path | None = Path(".cache/synthtalk")
    batch_size: int = 16
    lr: float = 1e-3
    resume: bool = True
    progress: bool = True
    save_every: int | None = None
    data_parallel: bool = False


@dataclasses.dataclass
class TrainSummary:
    """What :func:`train_run` did.

    Attributes:
        run_dir: the run folder.
        start_step: checkpoint step the run resumed from (0 for a fresh run).
        step: step reached.
        final_loss: mean loss over the last logged steps (None when no step ran).
        examples: training examples (windows).
        wall_s: seconds.
    """

    run_dir: Path
    start_step: int
    step: int
    final_loss: float | None
    examples: int
    wall_s: float


def _resolve_config(opts: TrainOptions, existing: RunRecord | None) -> tuple[Any, dict[str, Any]]:
    if existing is None:
        config = build_config(opts.model, opts.preset, opts.overrides)
        return config, parse_overrides(config_class(opts.model), opts.overrides)
    asked = parse_overrides(config_class(opts.model), opts.overrides)
    if (opts.overrides and asked != existing.overrides) or opts.preset != existing.preset:
        raise ValueError(
            f"{opts.out_dir} was trained with preset {existing.preset!r} and overrides {existing.overrides}; "
            "resume it with the same settings or choose another --out"
        )
    return existing.model_config(), existing.overrides


def _optim(opts: TrainOptions, **kw: Any) -> Any:
    from jaxtalk.train import OptimConfig

    base = dict(lr=opts.lr, weight_decay=1e-2, warmup_steps=min(100, opts.steps // 10), total_steps=opts.steps,
                clip_norm=1.0)
    return OptimConfig(**{**base, **kw})


def _toktalk(corpus: Any, config: Any, opts: TrainOptions, train_kw: dict[str, Any]) -> tuple[Any, Any, dict, int]:
    import jax

    from jaxtalk.models.toktalk.train import make_windows, train_base

    window = 100 if config.chunk_frames <= 20 else 5 * config.chunk_frames
    windows = make_windows(corpus, corpus.split("train"), config, window_frames=window, hop_frames=window // 4,
                           seed=opts.seed)
    optim = _optim(opts, ema_decay=0.999)
    result = train_base(config, windows, optim, key=jax.random.key(opts.seed), batch_size=opts.batch_size,
                        seed=opts.seed, **train_kw)
    return result, optim, {"window_frames": window}, int(windows["motion"].shape[0])


def _timar(corpus: Any, config: Any, opts: TrainOptions, train_kw: dict[str, Any]) -> tuple[Any, Any, dict, int]:
    from jaxtalk.models.timar import data as tdata
    from jaxtalk.models.timar.train import train_timar
    from jaxtalk.train import OptimConfig

    convs = tdata.conversations(corpus, "train", frames_per_turn=config.frames_per_turn)
    normalizer = tdata.fit_normalizer(convs)
    longest = max(c.num_frames for c in convs) // config.frames_per_turn
    turns = min(config.max_turns, longest)
    windows = tdata.windows(convs, normalizer, num_turns=turns, frames_per_turn=config.frames_per_turn)
    # Warm-up shorter than the run (the cosine part needs at least one step).
    warmup = min(20, opts.steps // 10)
    result = train_timar(config, windows, steps=opts.steps, batch_size=opts.batch_size, lr=opts.lr, seed=opts.seed,
                         warmup_steps=warmup, progress=opts.progress,
                         **{k: v for k, v in train_kw.items() if k != "progress"})
    # The optimiser train_timar builds, recorded in run.json.
    optim = OptimConfig(lr=opts.lr, weight_decay=1e-2, warmup_steps=warmup, total_steps=opts.steps, final_lr_ratio=0.1)
    return result, optim, {"normalizer": normalizer.to_dict(), "num_turns": turns}, int(windows["agent_motion"].shape[0])


def _ats(corpus: Any, config: Any, opts: TrainOptions, train_kw: dict[str, Any]) -> tuple[Any, Any, dict, int]:
    import jax

    from jaxtalk.data.batching import BatchIterator
    from jaxtalk.models.freetalk import ats
    from jaxtalk.models.freetalk.data import DisplacementStats, ats_windows
    from jaxtalk.train import train

    window = min(config.max_frames, 50)
    windows = ats_windows(corpus, corpus.split("train"), window=window, hop=max(window // 4, 1))
    # Standardised displacements (the fit_ats recipe): the model sees unit-variance data.
    stats = DisplacementStats.fit(windows["displacements"])
    data = {"displacements": stats.normalize(windows["displacements"]).astype(np.float32),
            "audio": windows["audio"].astype(np.float32), "emotion": windows["emotion"].astype(np.int32),
            "intensity": windows["intensity"].astype(np.float32)}
    k_init, k_train = jax.random.split(jax.random.key(opts.seed))
    optim = _optim(opts)
    result = train(ats.make_ats_loss(config), ats.init_ats(config, k_init),
                   BatchIterator(data, min(opts.batch_size, len(data["emotion"])), seed=opts.seed), optim,
                   key=k_train, metadata={"model": "ats"}, **train_kw)
    extra = {"window": window, "stats": {"mean": stats.mean.tolist(), "std": stats.std.tolist()}}
    return result, optim, extra, int(data["emotion"].shape[0])


def _stm(corpus: Any, config: Any, opts: TrainOptions, train_kw: dict[str, Any]) -> tuple[Any, Any, dict, int]:
    import jax

    from jaxtalk.data.batching import BatchIterator
    from jaxtalk.models.freetalk import stm
    from jaxtalk.models.freetalk.data import face_mesh, stm_windows, without_head_pose
    from jaxtalk.train import train

    resolution, window = "low", 16
    meshes = [face_mesh(i, kind, resolution=resolution) for i, kind in STM_MESHES]
    prepared = stm.prepare_meshes([(m.vertices, m.faces) for m in meshes], config)
    tracks = [(i, *m.motion(without_head_pose(corpus.motion(c)))) for i, m in enumerate(meshes)
              for c in corpus.split("train")]
    windows = stm_windows(tracks, prepared[0].num_vertices, window=window, hop=window)
    k_init, k_train = jax.random.split(jax.random.key(opts.seed))
    optim = _optim(opts)
    n = int(windows["mesh"].shape[0])
    result = train(stm.make_stm_loss(config, stm.stack_meshes(prepared)), stm.init_stm(config, k_init, prepared[0]),
                   BatchIterator(dict(windows), min(opts.batch_size, n), seed=opts.seed), optim, key=k_train,
                   metadata={"model": "stm"}, **train_kw)
    return result, optim, {"meshes": [list(m) for m in STM_MESHES], "resolution": resolution, "window": window}, n


_RECIPES: dict[str, Callable[..., tuple[Any, Any, dict, int]]] = {
    "toktalk": _toktalk, "timar": _timar, "ats": _ats, "stm": _stm,
}


def train_run(opts: TrainOptions, *, echo: Callable[[str], None] = print) -> TrainSummary:
    """Train (or continue training) one model on SynthTalk with checkpoints in ``opts.out_dir``.

    Args:
        opts: settings.
        echo: where progress lines go.

    Returns:
        :class:`TrainSummary`.

    Raises:
        ValueError: unknown model or preset, bad overrides or values, ``steps < 1``, an existing run
            of another model or with other settings, ``--no-resume`` on an existing run, or
            ``--steps`` below the step the run already reached.
    """
    from jaxtalk.data import synthtalk
    from jaxtalk.train import latest_checkpoint_step

    start = time.perf_counter()
    if opts.model not in MODELS:
        raise ValueError(f"unknown model {opts.model!r}; expected one of {', '.join(MODELS)}")
    if opts.steps < 1 or opts.batch_size < 1:
        raise ValueError(f"--steps and --batch-size must be >= 1, got {opts.steps} and {opts.batch_size}")
    out = Path(opts.out_dir)
    existing = RunRecord.load(out) if (out / "run.json").is_file() else None
    done = latest_checkpoint_step(checkpoint_dir(out)) or 0
    if existing is not None and not opts.resume:
        raise ValueError(f"{out} already holds a {existing.model} run at step {done}; drop --no-resume to continue it")
    if done > opts.steps:
        raise ValueError(f"{out} is already at step {done} > --steps {opts.steps}")
    if existing is not None:
        if existing.model != opts.model:
            raise ValueError(f"{out} holds a {existing.model} run, not {opts.model}; choose another --out")
        opts = dataclasses.replace(opts, preset=opts.preset or existing.preset, seed=existing.seed,
                                   batch_size=existing.batch_size)
    else:
        opts = dataclasses.replace(opts, preset=opts.preset or "small")
    config, overrides = _resolve_config(opts, existing)
    if opts.model == "ats" and config.displacement_scale != 1.0:
        # ATS trains on standardised displacements (the fit_ats recipe), so the model's own scale is 1.
        if "displacement_scale" in overrides:
            raise ValueError(f"ats trains on standardised displacements: displacement_scale must be 1.0, "
                             f"got {config.displacement_scale}")
        config = dataclasses.replace(config, displacement_scale=1.0)
    corpus_spec = ({"size": opts.size, "seed": opts.seed, "cache_dir": None if opts.cache_dir is None
                    else str(Path(opts.cache_dir).absolute())} if existing is None else existing.corpus)
    corpus = synthtalk.generate(size=corpus_spec["size"], seed=int(corpus_spec["seed"]),
                                cache_dir=corpus_spec["cache_dir"])
    echo(f"{'resuming' if done else 'training'} {opts.model} ({opts.preset}) from step {done} to {opts.steps} "
         f"on SynthTalk {corpus_spec['size']}; checkpoints in {checkpoint_dir(out)}")
    train_kw = {"ckpt_dir": checkpoint_dir(out), "progress": opts.progress,
                "save_every": opts.save_every or max(opts.steps // 5, 1)}
    if opts.data_parallel:
        import jax

        from jaxtalk.train import make_mesh

        if opts.batch_size % jax.device_count():
            raise ValueError(f"--batch-size {opts.batch_size} must divide by the {jax.device_count()} devices")
        train_kw["mesh"] = make_mesh()
    result, optim, extra, examples = _RECIPES[opts.model](corpus, config, opts, train_kw)
    record = RunRecord(model=opts.model, preset=opts.preset, overrides=overrides,
                       config=dataclasses.asdict(config), optim=optim.to_dict(), corpus=corpus_spec,
                       seed=opts.seed, batch_size=opts.batch_size, extra=extra)
    record.save(out)
    losses = [h["loss"] for h in result.history[-10:] if "loss" in h]
    return TrainSummary(run_dir=out, start_step=done, step=int(result.state.step),
                        final_loss=float(np.mean(losses)) if losses else None, examples=examples,
                        wall_s=time.perf_counter() - start)


def describe_presets(models: Sequence[str] = MODELS) -> str:
    """One line per model listing its presets (for ``--help``)."""
    from jaxtalk.commands.runs import preset_names

    return "; ".join(f"{m}: {', '.join(preset_names(m))}" for m in models)
