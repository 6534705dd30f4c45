"""``jaxtalk train {toktalk,ats,stm,timar,dualtalk} --data DATA``: a config preset + overrides, trained with the
model's recipe on a prepared dataset (or ``synthtalk:SIZE``, prepared once into a cache).

Every model trains through its recipe (``jaxtalk.models.<model>.recipe``) and the shared loop, which
checkpoints into ``<out>/checkpoint`` (keeping the best validation checkpoint too) and resumes exactly
(parameters, optimiser, EMA, RNG and loader position): an interrupted run started again with the same
``--steps`` ends where the uninterrupted one would. A larger ``--steps`` continues the run with the
learning-rate schedule stretched to the new length. The model config, training settings, data and
seed of a resumed run come from its ``run.json`` and cannot be changed.

``--set KEY=VALUE`` sets a field of the model config or of the training settings
(:class:`jaxtalk.train.recipes.TrainSettings`: lr, weight_decay, warmup_steps, ema_decay,
batch_size, window_frames, eval_every, ...). Widths the data decides (TokTalk's token width and rate,
TIMAR's, the DualTalk baseline's and ATS's speech feature width) follow the data unless set explicitly.

``--features hubert:PATH`` / ``wav2vec2:PATH`` (ATS, TIMAR, DualTalk) prepares ``synthtalk:`` data with a
pretrained speech encoder instead of log-mel, once, into a cache folder of its own
(:func:`jaxtalk.data.loader.open_data`); the run's ``features.json`` records the front end, so that
``jaxtalk sample`` and ``jaxtalk stream`` compute the same features from new audio.

``dualtalk`` is the non-causal DualTalk baseline of TIMAR's Table 1 (:mod:`jaxtalk.models.dualtalk`),
trained on TIMAR's windows with TIMAR's settings.
"""

from __future__ import annotations

import contextlib
import dataclasses
import inspect
import os
import sys
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from jaxtalk.files import LOCK_FILE, folder_lock
from jaxtalk.runs import (
    MODELS,
    load_run,
    RunInfo,
    RunRecord,
    RunSettings,
    build_config,
    checkpoint_dir,
    config_class,
    model_spec,
    parse_overrides,
    preset_names,
    split_overrides,
)
from jaxtalk.train.observers import StepObserver, StopRequest

DEFAULT_DATA = "synthtalk:tiny"
# Where ``--profile`` writes its trace, inside the run folder.
PROFILE_DIR = "profile"
# What the loop says when a resumed run's schedule is stretched to the new --steps (intended).

__all__ = ["DEFAULT_DATA", "PROFILE_DIR", "TrainOptions", "TrainSummary", "train_run"]


@dataclasses.dataclass(frozen=True)
class TrainOptions:
    """Settings of :func:`train_run` (the CLI's options).

    Attributes:
        model: ``toktalk``, ``ats``, ``stm``, ``timar`` or ``dualtalk``.
        out_dir: run folder (``run.json`` + ``checkpoint/``).
        data: a prepared dataset folder (``jaxtalk prepare``) or ``synthtalk:SIZE[:SEED]``; None (not
            given): :data:`DEFAULT_DATA` for a new run, the run's own data when resuming (any other
            value is refused when resuming).
        preset: config preset (``small``, ``paper``; ``tiny`` for TokTalk); None: ``small`` for a new
            run, the run's own preset when resuming.
        overrides: ``key=value`` overrides of the config or the training settings.
        steps: train until this many optimiser steps in total.
        seed: initialisation and data-order seed.
        cache_dir: where ``synthtalk:`` data is prepared.
        features: the speech front end (``logmel``, ``hubert:PATH``, ``wav2vec2:PATH``) of the models
            that read speech features (ATS, TIMAR, DualTalk; :attr:`jaxtalk.runs.ModelSpec.reads_speech`):
            ``synthtalk:`` data is prepared with it (once, into a folder of its own under
            ``cache_dir``); a prepared folder must have been prepared with it. None: log-mel for
            ``synthtalk:``, a folder's own features, a resumed run's own.
        resume: continue an existing run in ``out_dir`` (False: refuse to touch it).
        progress: show the progress bar.
        save_every: checkpoint period in steps (default: 5 checkpoints per run; the last step always).
        data_parallel: shard every batch over all devices (``jaxtalk.train.make_mesh``).
        distributed: call ``jax.distributed.initialize()`` first (several hosts; settings from the
            environment) and train on the global mesh. Every process runs the same command; the
            ``batch_size`` setting is per process (the global batch is ``batch_size`` x processes,
            the same batches as one process with the global batch size), all processes write the
            checkpoints together and process 0 alone writes ``run.json`` and the run's assets.
        profile: ``(start, stop)``: write a :mod:`jax.profiler` trace of updates ``start..stop``
            (1-based, counted from the run's first step, resumed runs included) to
            ``<out_dir>/profile`` (:class:`jaxtalk.train.TraceSteps`); None: no trace.
        init: fine-tune: start from this run's newest parameters (a trained or converted run of the same
            model), with its config and, for turn models, its normaliser (so the inputs keep the
            standardisation the weights were trained with); None: fresh parameters.
        real_voice: TokTalk: a folder of real recordings (and their tracked motion as ``STEM.npz``) that
            every evaluation also streams, recording ``real_corr`` and the other real-voice metrics
            (:func:`jaxtalk.models.toktalk.validation.real_voice_validation`); None: none.
        select: TokTalk: the metric the best checkpoint is chosen by (``LVE_mm2``, ``real_corr``); None:
            a resumed run's own, else ``LVE_mm2``.
    """

    model: str
    out_dir: Path
    data: str | None = None
    preset: str | None = None
    overrides: tuple[str, ...] = ()
    steps: int = 1000
    seed: int = 0
    cache_dir: Path = Path(".cache/prepared")
    features: str | None = None
    resume: bool = True
    progress: bool = True
    save_every: int | None = None
    data_parallel: bool = False
    distributed: bool = False
    profile: tuple[int, int] | None = None
    init: Path | None = None
    real_voice: Path | None = None
    select: str | None = None


@dataclasses.dataclass
class TrainSummary:
    """What :func:`train_run` did.

    Attributes:
        run_dir: the run folder.
        start_step: checkpoint step the run resumed from (0 for a fresh run).
        step: step reached.
        final_loss: mean loss over the last logged steps (None when no step ran).
        val_loss: the last validation loss (None without a validation split).
        examples: training windows (this process's shard).
        wall_s: seconds.
        interrupted: stopped early by Ctrl-C (``step`` is checkpointed; run again to resume).
    """

    run_dir: Path
    start_step: int
    step: int
    final_loss: float | None
    val_loss: float | None
    examples: int
    wall_s: float
    interrupted: bool = False


def _data_fields(model: str, data: Any, explicit: dict[str, Any]) -> list[str]:
    """Config overrides that make the model's input widths match the data (unless set explicitly)."""
    m = data.manifest
    wanted = {field: m.get(key) for field, key in model_spec(model).data_fields}
    return [f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in wanted.items()
            if v is not None and k not in explicit]


def train_run(opts: TrainOptions, *, echo: Callable[[str], None] = print) -> TrainSummary:
    """Train (or continue training) one model on a prepared dataset with checkpoints in ``opts.out_dir``.

    Args:
        opts: settings.
        echo: where progress lines go.

    Returns:
        :class:`TrainSummary`.

    Raises:
        ValueError: unknown model or preset, bad overrides or values, ``steps < 1``, data that does not
            fit the model, an existing run of another model or with other settings, ``--no-resume``
            on an existing run, ``--steps`` below the step the run already reached, ``features`` for a
            model that reads no speech features, unknown ``features``, or a prepared folder or run of
            other features; ``--real-voice`` or ``--select`` for a model other than TokTalk, a bad
            ``--real-voice`` folder, an unknown ``--select`` metric or one the recordings cannot give
            (checked before anything is opened).
        FileNotFoundError: a data folder that is not prepared, a speech encoder's checkpoint folder,
            its ``config.json`` or weights missing (before any data is prepared), a ``--real-voice``
            folder that does not exist.
        jaxtalk.files.FolderInUseError: another process is training into ``opts.out_dir``.
    """
    import jax

    start = time.perf_counter()
    spec = model_spec(opts.model)
    if opts.steps < 1:
        raise ValueError(f"--steps must be >= 1, got {opts.steps}")
    if opts.features is not None:
        _check_features(opts.model, opts.features)
    if opts.distributed:
        from jaxtalk.train.distributed import initialize

        # First: reading the checkpoint directory below (orbax) starts the JAX backend, and only a
        # backend started after initialize() sees the other processes.
        initialize()
    recordings = _real_voices(opts, echo)
    out = Path(opts.out_dir)
    _check_run_folder(out)
    stop = StopRequest()
    with contextlib.ExitStack() as held:
        # One writer per run folder, taken before anything is read from it (process 0 of a multi-process
        # run holds it for all); the loop below takes the same lock again, within this process.
        held.enter_context(_stop_on_interrupt(stop, out))
        if jax.process_index() == 0:
            held.enter_context(folder_lock(out))
        return _train_into(opts, out, spec, stop, start, echo, recordings)


def _real_voices(opts: TrainOptions, echo: Callable[[str], None]) -> Any:
    """The ``--real-voice`` recordings, read once, and ``--select`` checked against them, before any
    folder or data is opened (None without ``--real-voice``)."""
    if opts.real_voice is None and opts.select is None:
        return None
    given = " and ".join(f for f, v in (("--real-voice", opts.real_voice), ("--select", opts.select)) if v is not None)
    plan = model_spec(opts.model).voice_validation
    if plan is None:
        raise ValueError(f"{given}: TokTalk settings (its validation streams real recordings); not for "
                         f"{opts.model}")
    from jaxtalk.data.recordings import read_recordings

    recordings = None if opts.real_voice is None else read_recordings(opts.real_voice, echo=echo)
    plan(opts.real_voice, recordings, opts.select, echo)
    return recordings


def _train_into(opts: TrainOptions, out: Path, spec: Any, stop: StopRequest, start: float,
                echo: Callable[[str], None], recordings: Any = None) -> TrainSummary:
    """:func:`train_run` once the run folder is held: read it, open the data, train (``recordings``:
    the ``--real-voice`` recordings already read, or None)."""
    import jax

    from jaxtalk.train import latest_checkpoint_step

    existing = RunRecord.load(out) if (out / "run.json").is_file() else None
    done = latest_checkpoint_step(checkpoint_dir(out)) or 0
    if existing is not None and not opts.resume:
        raise ValueError(f"{out} already holds a {existing.model} run at step {done}; drop --no-resume to continue it")
    if existing is not None and existing.model != opts.model:
        raise ValueError(f"{out} holds a {existing.model} run, not {opts.model}; choose another --out")
    if done > opts.steps:
        raise ValueError(f"{out} is already at step {done} > --steps {opts.steps}")
    if existing is not None:
        if opts.preset not in (None, existing.preset) or (opts.overrides and tuple(opts.overrides) != tuple(existing.items)):
            raise ValueError(f"{out} was trained with preset {existing.preset!r} and --set {list(existing.items)}; "
                             "resume it with the same settings or choose another --out")
        if opts.data is not None and not _same_data(opts.data, existing.data):
            raise ValueError(f"{out} was trained on --data {existing.data['spec']}, not {opts.data}: resume it with "
                             f"--data {existing.data['spec']} (or no --data), or choose another --out")
        opts = dataclasses.replace(opts, preset=existing.preset, overrides=tuple(existing.items),
                                   data=existing.data["spec"], seed=existing.seed,
                                   features=_resumed_features(out, spec, opts.features))
    if opts.data is None:
        opts = dataclasses.replace(opts, data=DEFAULT_DATA)
    # A run made from Python with a config that equals no preset resumes with None (its config is on record).
    preset = existing.preset if existing is not None else opts.preset or "small"
    spec = model_spec(opts.model)
    train_fn, defaults = spec.train, spec.settings(preset or "small")
    model_items, train_kw = split_overrides(opts.model, opts.overrides)
    if existing is None and opts.init is None:
        # A bad --set value is refused before the data is opened (preparing synthtalk:small takes minutes);
        # the widths the prepared data sets are applied below.
        build_config(opts.model, preset, model_items)
    # A resumed run reads the prepared folder it started on (a synthtalk: spec would otherwise be looked
    # up again under this call's --cache-dir), and only if it still holds the same data.
    data = _open_data_once(opts, existing.data["path"] if existing is not None else None)
    if existing is not None and data.key != existing.data["key"]:
        raise ValueError(f"{out} was trained on prepared data {existing.data['key']!r}, but {data.root} now holds "
                         f"{data.key!r}; resume it on the same data or choose another --out")
    init = _init_run(opts, existing, model_items, done)
    if init is not None and opts.preset is None:  # the starting run's preset sets the training defaults
        preset = init.record.preset
        train_fn, defaults = model_spec(opts.model).train, model_spec(opts.model).settings(preset or "small")
    if existing is not None:
        config = existing.model_config()
    elif init is not None:
        config = init.config
    else:
        explicit = parse_overrides(config_class(opts.model), model_items)
        config = build_config(opts.model, preset, [*_data_fields(opts.model, data, explicit), *model_items])
    settings = dataclasses.replace(defaults, **train_kw)
    if existing is not None and "batch_size" not in train_kw and existing.train.get("batch_size"):
        # The batch the run trained with (smaller than the default on a small training split).
        settings = dataclasses.replace(settings, batch_size=int(existing.train["batch_size"]))
    if settings.window_frames is not None and spec.windows is not None:
        raise ValueError(f"window_frames is not a {opts.model} setting ({opts.model} windows are {spec.windows})")
    echo(f"{'resuming' if done else 'training'} {opts.model} ({preset or 'custom config'}) from step {done} to {opts.steps} "
         f"on {data}; checkpoints in {checkpoint_dir(out)}")
    optim = settings.optim(opts.steps)
    echo(settings.describe(opts.steps))
    mesh = None
    if opts.data_parallel or opts.distributed:
        from jaxtalk.train import make_mesh

        mesh = make_mesh()
        local = jax.local_device_count()
        if settings.batch_size % local:
            raise ValueError(f"batch_size {settings.batch_size} must divide by the {local} local devices")
    kw: dict[str, Any] = {}
    if settings.val_clips is not None:
        if "val_clips" not in inspect.signature(train_fn).parameters:
            raise ValueError(f"val_clips is not a {opts.model} setting: its validation scores the loss only")
        kw["val_clips"] = settings.val_clips
    if init is not None:
        kw["params"] = init.params
        echo(f"fine-tuning from {opts.init} (step {init.step})")
    # A fine-tuned turn model keeps its starting run's normaliser, on resume too (run.json records it).
    started_from = init.record.extra if init is not None else (existing.extra if existing is not None and
                                                               existing.extra.get("init") else None)
    if started_from is not None and "normalizer" in started_from:
        kw["normalizer"] = started_from["normalizer"]
    observers: list[StepObserver] = []
    if opts.profile is not None:
        from jaxtalk.train import TraceSteps

        if opts.profile[0] <= done or opts.profile[1] > opts.steps:
            raise ValueError(f"--profile {opts.profile[0]}:{opts.profile[1]} is outside the steps this run trains "
                             f"({done + 1}..{opts.steps})")
        observers.append(TraceSteps(*opts.profile, out / PROFILE_DIR))
    observers.append(stop)
    if spec.voice_validation is not None:  # None: no real voices, and a resumed run's own selection
        kw.update(real_voice=recordings, select=opts.select)
    from jaxtalk.train import LoopSettings

    run = RunSettings(steps=opts.steps, batch_size=settings.batch_size, seed=opts.seed,
                      window_frames=settings.window_frames, eval_every=settings.period(opts.steps), run_dir=out,
                      mesh=mesh, info=RunInfo(preset=preset, items=tuple(opts.overrides), data_spec=opts.data,
                                              settings=settings),
                      loop=LoopSettings(progress=opts.progress, save_every=opts.save_every or max(opts.steps // 5, 1)),
                      observers=observers)
    with warnings.catch_warnings():
        # The library's warnings (a smaller batch than asked, ...) as one line each, not Python's
        # two-line "file:line: UserWarning" form.
        warnings.showwarning = lambda message, *_args, **_kw: echo(f"warning: {message}")
        result = train_fn(config, data, optim, key=jax.random.key(opts.seed), run=run, **kw)
    losses = [h["loss"] for h in result.history[-10:] if "loss" in h]
    evals = [h["eval"]["val_loss"] for h in result.history if "eval" in h and "val_loss" in h["eval"]]
    return TrainSummary(run_dir=out, start_step=done, step=int(result.state.step),
                        final_loss=float(np.mean(losses)) if losses else None, val_loss=evals[-1] if evals else None,
                        examples=result.windows, wall_s=time.perf_counter() - start, interrupted=stop.requested)


@contextlib.contextmanager
def _stop_on_interrupt(stop: StopRequest, out: Path) -> Iterator[None]:
    """Ctrl-C (SIGINT) during training: the first stops the loop after the update in flight (it is
    checkpointed, the run resumes from it); before the loop runs, or a second time, it ends the process
    at once with one line. Never a ``KeyboardInterrupt`` unwinding through a compile, a restore or a
    save: that is what crashed the interpreter on its way out."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield  # signal handlers belong to the main thread; a caller's thread keeps its own policy
        return

    def handler(signum: int, frame: Any) -> None:
        if stop.running and not stop.requested:
            stop.request()
            sys.stderr.write("interrupted: stopping after this step and saving it (Ctrl-C again stops at once)\n")
            sys.stderr.flush()
            return
        from jaxtalk.train import latest_checkpoint_step

        step = latest_checkpoint_step(checkpoint_dir(out))
        kept = f"the last checkpoint (step {step}) is intact" if step else "no checkpoint was written"
        sys.stdout.flush()
        sys.stderr.write(f"error: interrupted; {kept} in {checkpoint_dir(out)}\n")
        sys.stderr.flush()
        os._exit(130)  # checkpoints are committed atomically; an unfinished save is removed on resume

    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _init_run(opts: TrainOptions, existing: Any, model_items: list[str], done: int) -> Any:
    """The run ``--init`` names, loaded, or None; refuses what would silently not be a fine-tune."""
    if opts.init is None:
        return None
    if existing is not None or done:
        raise ValueError(f"{opts.out_dir} already holds a run; --init starts a new one: choose another --out "
                         "(a fine-tuned run resumes without --init)")
    if model_items:
        raise ValueError(f"--init takes {opts.init}'s model config; --set of model fields ({', '.join(model_items)}) "
                         "would not match its weights (training settings such as lr may be set)")
    refusal = model_spec(opts.model).fine_tune_refusal
    if refusal is not None:
        raise ValueError(f"--init is not available for {opts.model}: {refusal}")
    run = load_run(opts.init)
    if run.record.model != opts.model:
        raise ValueError(f"--init {opts.init} is a {run.record.model} run, not {opts.model}")
    return run


def _check_run_folder(out: Path) -> None:
    """Refuse an ``--out`` that is a file, or a folder of files that is not a run: training writes
    run.json, checkpoints and the run's assets there, and would replace a user's files of those names.

    A folder with a ``checkpoint/`` but no ``run.json`` is a run killed before its first save: resumed.
    """
    from jaxtalk.files import OutputError

    if out.exists() and not out.is_dir():
        raise OutputError(f"--out {str(out)!r} is a file; a run is a folder: choose another --out")
    # Files, not folders: the demo keeps its corpus cache in a subfolder of its run folder.
    # The lock file a killed training leaves is no user's file.
    if out.is_dir() and not (out / "run.json").is_file() and not checkpoint_dir(out).is_dir() and any(
            p.is_file() and p.name != LOCK_FILE for p in out.iterdir()):
        raise OutputError(f"--out {str(out)!r} holds files but no jaxtalk run; train into a new or empty folder")


def _check_features(model: str, features: str) -> None:
    """Refuse ``--features`` for a model that reads no speech features, and an unknown front end or an
    incomplete checkpoint folder, before any data is generated or prepared."""
    from jaxtalk.data.features import parse_audio_features
    from jaxtalk.runs import REGISTRY

    if not model_spec(model).reads_speech:
        readers = ", ".join(name for name, spec in REGISTRY.items() if spec.reads_speech)
        raise ValueError(f"--features chooses the speech front end of {readers}; {model} reads "
                         f"{model_spec(model).reads}: drop --features")
    parse_audio_features(features)


def _resumed_features(out: Path, spec: Any, given: str | None) -> str | None:
    """The front end a resumed run keeps (its ``features.json``; None for a model that reads none);
    ``given`` must be that one."""
    from jaxtalk.data.features import parse_audio_features
    from jaxtalk.runs import run_features

    if not spec.reads_speech:
        return None
    own = run_features(out)["audio"]
    if given is not None and given != own and parse_audio_features(given).spec != own:
        raise ValueError(f"{out} was trained with --features {own}, not {given}: resume it without --features, or "
                         "choose another --out")
    return own


def _same_data(spec: str, recorded: dict[str, Any]) -> bool:
    """Whether ``--data spec`` names the data a run recorded (its spec, or the same prepared folder)."""
    if spec == recorded["spec"]:
        return True
    return not spec.startswith("synthtalk:") and Path(spec).resolve() == Path(recorded["path"]).resolve()


def _open_data_once(opts: TrainOptions, prepared: str | None = None) -> Any:
    """``open_data`` for this run (the folder ``prepared`` when it is still there); with several
    processes, process 0 first.

    ``synthtalk:`` data is prepared on first use: processes sharing a file system must not prepare
    it at the same time, so the others wait for process 0 and then find it prepared (on a host with
    its own file system a process still prepares its own copy).
    """
    import jax

    from jaxtalk.data.loader import PreparedData, open_data
    from jaxtalk.data.prepare import MANIFEST

    def one() -> Any:
        if prepared is not None and (Path(prepared) / MANIFEST).is_file():
            return PreparedData(prepared)
        return open_data(opts.data, cache_dir=opts.cache_dir, progress=opts.progress and jax.process_index() == 0,
                         features=opts.features)

    if jax.process_count() == 1:
        return one()
    from jax.experimental import multihost_utils

    data = one() if jax.process_index() == 0 else None
    multihost_utils.sync_global_devices("jaxtalk train: data prepared")
    return data if data is not None else one()


def describe_presets(models: Sequence[str] = MODELS) -> str:
    """One line per model listing its presets (for ``--help``)."""
    return "; ".join(f"{m}: {', '.join(preset_names(m))}" for m in models)
