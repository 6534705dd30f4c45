"""Training runs on disk and the registry of models: ``run.json``, ``--set key=value`` overrides, loading.

A run directory holds ``checkpoint/`` (orbax, written by :class:`jaxtalk.train.Checkpointer` through
the shared loop), ``run.json`` (the model, preset, overrides, the full model, training and optimiser
settings, the data it was trained on, and what the recipe fitted: TIMAR's normaliser, ATS's
displacement statistics, STM's meshes; the DualTalk baseline's normaliser, as TIMAR's),
``config.json`` (the resolved model config alone, for a reader without jaxtalk) and the inference
assets copied from the data (``features.json``, the VQ ``tokenizer.npz``, TokTalk's default
``style.npy``), so a run samples without its dataset. Every recipe writes this one format when given a
``run_dir``: it trains through :func:`fit_run`, which records the run (:func:`write_run`); the CLI, the
demo and the experiments all read it.

:data:`REGISTRY` names, for each model, its config class, its recipe and the recipe's default training
settings as dotted import paths resolved on demand: this module sits below the models (it may not
import them), and ``jaxtalk --help`` stays instant.
"""

from __future__ import annotations

import dataclasses
import importlib
import json
import types
import typing
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

if typing.TYPE_CHECKING:  # types only: this module imports no array library (``jaxtalk --help`` stays instant)
    from jax.sharding import Mesh

    from jaxtalk.data.loader import PreparedData, WindowRecipe
    from jaxtalk.train.loop import EvalFn, LoopSettings
    from jaxtalk.train.observers import StepObserver
    from jaxtalk.train.optim import OptimConfig, Trainable
    from jaxtalk.train.recipes import RecipeResult
    from jaxtalk.train.step import LossFn
    from jaxtalk.types import PRNGKeyArray

__all__ = [
    "MODELS",
    "REGISTRY",
    "RUN_FILE",
    "CONFIG_FILE",
    "ModelSpec",
    "Streamer",
    "SpeechAnimator",
    "SpeechConditions",
    "SPEC_PATHS",
    "RunInfo",
    "RunSettings",
    "RunRecord",
    "LoadedRun",
    "model_spec",
    "config_class",
    "preset_names",
    "parse_overrides",
    "split_overrides",
    "build_config",
    "checkpoint_dir",
    "load_run",
    "save_run_assets",
    "run_features",
    "default_style_clip",
    "write_run",
    "fit_run",
]

RUN_FILE = "run.json"
CONFIG_FILE = "config.json"


def _resolve(path: str) -> Any:
    """The object a ``"package.module:attribute"`` path names (the module imported on first use)."""
    module, _, attr = path.partition(":")
    return getattr(importlib.import_module(module), attr)


@dataclasses.dataclass(frozen=True)
class Streamer:
    """A model's streaming engine: ``init_stream(config, key, ...)`` makes the carried state,
    ``stream_step(params, config, state, ..., sample_steps=...)`` advances it by one chunk (a TokTalk
    chunk, a TIMAR turn), ``stream(params, config, ..., key, sample_steps=...)`` runs a whole input
    through the steps as a live stream would."""

    init_stream: Callable[..., Any]
    stream_step: Callable[..., Any]
    stream: Callable[..., Any]


@dataclasses.dataclass(frozen=True)
class SpeechConditions:
    """What ``jaxtalk sample`` and ``jaxtalk stream`` hand a :class:`SpeechAnimator` besides the speech, read
    from their options (None: the model's own default). A model reads those of its
    :attr:`SpeechAnimator.options`; the commands refuse the others.

    Attributes:
        style: ``(S, 56)`` reference motion (``--style``); None: the run's default style clip.
        style_file: the file ``style`` was read from, named in messages.
        partner: the partner's 16-kHz speech (``--partner``); None: a silent partner.
        cfg_scale: guidance weight.
        sample_steps: sampler steps.
        temperature: scale of the sampler's noise.
        seed: noise seed.
    """

    style: Any = None
    style_file: str | None = None
    partner: Any = None
    cfg_scale: float | None = None
    sample_steps: int | None = None
    temperature: float | None = None
    seed: int = 0


@dataclasses.dataclass(frozen=True)
class SpeechAnimator:
    """How ``jaxtalk sample`` and ``jaxtalk stream`` animate speech with a loaded run of a model, and
    ``jaxtalk eval --real-voice`` streams recordings through it; each model builds its own from its
    ``inference`` module, and the commands only open the files, call it and print.

    Attributes:
        options: the options of ``sample`` and ``stream`` the model reads besides ``--sample-steps`` and
            ``--seed`` (of ``--style``, ``--partner``, ``--cfg-scale``, ``--temperature``); another one given
            is refused rather than ignored.
        other_inputs: ``(suffix, what such a file holds)`` for each kind of input file the model takes
            besides audio (TokTalk: ``.npy`` token embeddings).
        read: ``(run, path) -> speech``: an input file as the model takes it (an audio file's 16-kHz
            waveform, one-dimensional; TokTalk's ``.npy``: ``(tokens, width)`` embeddings), refused before
            it is read when the run cannot animate it, and after when it is too short to animate.
        sample: ``(run, speech, conditions) -> (params (T, 56), the audio animated or None)``: offline.
        stream: ``(run, speech, conditions, on_chunk, echo) -> (params (T, 56), the audio animated or None,
            seconds per chunk)``: chunk by chunk (a TIMAR turn) as a live stream would, calling
            ``on_chunk(chunks, seconds, chunk_s, count=1)`` with each chunk's wall time (``count``: the last
            chunks at once) and ``echo`` with notes.
        step_frames: ``(config) -> frames`` the model animates at a time at the least: a stream animates
            whole steps of its audio (a TIMAR turn; TokTalk: 1).
        rest_note: ``(run) -> words`` on where the run's jaw should rest in silence, added to the
            real-voice tables' titles (TokTalk: its style clip's rest), or None.
    """

    options: tuple[str, ...]
    read: Callable[..., Any]
    sample: Callable[..., Any]
    stream: Callable[..., Any]
    step_frames: Callable[[Any], int]
    other_inputs: tuple[tuple[str, str], ...] = ()
    rest_note: Callable[[Any], str] | None = None


@dataclasses.dataclass(frozen=True)
class ModelSpec:
    """The interface of one model: what the run format, the commands and the experiments call.

    Each model package builds its own in its ``spec`` module (``jaxtalk.models.<model>.spec``);
    :data:`REGISTRY` points at those.

    Attributes:
        name: the model's name in ``run.json`` and on the command line.
        title: its name in prose: messages and table titles (``TokTalk``, ``TIMAR``).
        config_class: its frozen config dataclass.
        presets: the config presets (classmethods of ``config_class``: ``paper``, ``small``, ...).
        init_params: ``(config, key) -> params``.
        make_loss_fn: ``(config) -> (params, batch, key) -> (loss, metrics)`` for the training loop (STM
            binds its meshes: ``(config, meshes)``).
        train: the recipe's ``train(config, data, optim, *, key, run=RunSettings(), params=None, ...)``
            (:class:`RunSettings`; the keywords after ``params`` are the model's own).
        defaults: the recipe's default :class:`~jaxtalk.train.recipes.TrainSettings`.
        preset_defaults: ``{preset: TrainSettings}`` for presets whose settings differ (TIMAR's ``paper``).
        sample: ``sample(params, config, ..., key, *, sample_steps=..., ...)``, or None for the
            deterministic models (STM, the DualTalk baseline).
        guided: ``sample`` (and the streamer) take ``cfg_scale``, the guidance weight w of
            :func:`jaxtalk.samplers.flow.guided_apply` (0 = no guidance), and ``guidance=False``.
        streamer: the streaming engine, or None.
        evaluate: the model's evaluation protocol (``jaxtalk eval``): ``evaluate(run, data, split, settings,
            echo) -> (items scored, tables)`` (:data:`jaxtalk.metrics.evaluation.EvalProtocol`).
        eval_options: the ``jaxtalk eval`` options that mean something for the model beyond ``--max-clips``
            and ``--seed`` (TokTalk's ``--flame``, ``--sample-steps``, ``--offline``; ``--temperature`` of
            the models with sampler noise): ``--flame`` and ``--temperature`` are refused for the others, as
            ``--sample-steps`` is with ``--real-voice``.
        animator: how ``jaxtalk sample`` and ``jaxtalk stream`` animate speech with the model's runs (and
            ``jaxtalk eval --real-voice`` streams recordings through them), or None for a model whose runs
            they refuse.
        sample_refusal: for a model without an ``animator``: what ``sample`` and ``stream`` say when given
            one of its runs, and how its runs are used instead (``{run}``: the run folder).
        animates_user_meshes: ``jaxtalk sample RUN AUDIO --stm RUN_STM --mesh FILE`` takes the model's runs:
            its output drives a user's mesh through an STM run (ATS).
        live: makes a live model from a loaded run (``live(run, style=..., cfg_scale=...,
            sample_steps=...)``: ``open(key)`` streams, ``push(audio)`` returns frames), for models that
            animate speech as it arrives (``jaxtalk stream`` and ``jaxtalk serve``); None for the others.
        data_fields: ``(config field, manifest key)`` pairs: input widths that follow the prepared data
            unless set explicitly, and that evaluation data must match.
        windows: how the recipe cuts windows when their length is not a setting (None: the
            ``window_frames`` setting applies).
        style_asset: the run keeps a default style clip (a training clip) for sampling.
        family: the system the model is one part of, where one name stands for several models (``freetalk``:
            ATS and STM, which ``jaxtalk bench --model freetalk`` times together); None for a model that
            stands alone.
        reads: what the model reads, in words, for messages (``audio tokens (...)``, ``landmarks``,
            ``speech features``).
        voice_validation: for a model whose training validation can also stream real recordings
            (``jaxtalk train --real-voice FOLDER``, and ``--select`` of the metric its best checkpoint is
            chosen by): ``(folder, recordings, select, echo)``, called before anything is opened with the
            recordings read (None: no ``--real-voice``), checks ``select`` and says what each evaluation will
            stream; its ``train`` then takes ``real_voice=`` and ``select=``. None: the model takes neither
            option.
        fine_tune_refusal: why ``jaxtalk train --init RUN`` cannot fine-tune the model (what its recipe fits
            on the new data that the starting weights were not trained with), or None when it can.
        export_stream: writes the live model's stream as ONNX graphs and a manifest into a folder
            (``export_stream(live_model, folder, run_name=...) -> manifest``: ``jaxtalk export-model``), or None.
        export_refusal: for a model without ``export_stream``, why ``jaxtalk export-model`` does not export it.
    """

    name: str
    title: str
    config_class: type
    presets: tuple[str, ...]
    init_params: Callable[..., Any]
    make_loss_fn: Callable[..., Any]
    train: Callable[..., Any]
    defaults: Any
    preset_defaults: dict[str, Any] = dataclasses.field(default_factory=dict)
    sample: Callable[..., Any] | None = None
    guided: bool = False
    streamer: Streamer | None = None
    evaluate: Callable[..., Any] | None = None
    eval_options: tuple[str, ...] = ()
    animator: SpeechAnimator | None = None
    sample_refusal: str | None = None
    animates_user_meshes: bool = False
    live: Callable[..., Any] | None = None
    data_fields: tuple[tuple[str, str], ...] = ()
    windows: str | None = None
    style_asset: bool = False
    family: str | None = None
    reads: str = "speech features"
    voice_validation: Callable[..., Any] | None = None
    fine_tune_refusal: str | None = None
    export_stream: Callable[..., Any] | None = None
    export_refusal: str | None = None

    def settings(self, preset: str = "small") -> Any:
        """The recipe's default :class:`~jaxtalk.train.recipes.TrainSettings` for a config preset."""
        return self.preset_defaults.get(preset, self.defaults)

    @property
    def reads_speech(self) -> bool:
        """Whether the model's input is the prepared speech features (``speech`` or ``turn_speech``:
        ATS, TIMAR and the DualTalk baseline), whose front end ``--features`` chooses; its data widths
        say so. TokTalk reads audio tokens and STM landmarks instead."""
        return any(key in ("speech_dim", "turn_speech_dim") for _, key in self.data_fields)


# Where each model's spec lives. This module sits below the models (it may not import them), so the
# specs are imported on first use; ``jaxtalk --help`` stays instant. tests/test_layers.py checks that
# these name ``spec`` modules of the models layer.
SPEC_PATHS: dict[str, str] = {
    "toktalk": "jaxtalk.models.toktalk.spec:SPEC",
    "ats": "jaxtalk.models.freetalk.spec:ATS",
    "stm": "jaxtalk.models.freetalk.spec:STM",
    "timar": "jaxtalk.models.timar.spec:SPEC",
    "dualtalk": "jaxtalk.models.dualtalk.spec:SPEC",
}


class _Registry(Mapping[str, ModelSpec]):
    """The models by name, each spec imported when it is first asked for."""

    def __getitem__(self, model: str) -> ModelSpec:
        spec = _resolve(SPEC_PATHS[model])
        if not isinstance(spec, ModelSpec) or spec.name != model:
            raise TypeError(f"{SPEC_PATHS[model]} is not the ModelSpec of {model!r}")
        return spec

    def __iter__(self) -> Iterator[str]:
        return iter(SPEC_PATHS)

    def __len__(self) -> int:
        return len(SPEC_PATHS)


REGISTRY: Mapping[str, ModelSpec] = _Registry()
MODELS = tuple(SPEC_PATHS)


def model_spec(model: str) -> ModelSpec:
    """``model``'s entry in :data:`REGISTRY`.

    Raises:
        ValueError: unknown model name.
    """
    if model not in REGISTRY:
        raise ValueError(f"unknown model {model!r}; expected one of {', '.join(MODELS)}")
    return REGISTRY[model]

# Config fields renamed when every model took one vocabulary (the same name for the same concept):
# runs written before keep loading and resuming under the new names.
RENAMED_FIELDS = {
    "toktalk": {"token_dim": "speech_dim", "channels": "width", "num_steps": "sample_steps",
                "cond_dropout": "cfg_dropout"},
    "ats": {"audio_dim": "speech_dim", "num_sampling_steps": "sample_steps"},
    "timar": {"cfg_prob": "cfg_dropout", "dropout_rate": "dropout"},
    "dualtalk": {"dropout_rate": "dropout"},
}


# The run record's format. 2: every model's cfg_scale is one guidance weight w (0 = no guidance); TIMAR's
# records of format 1 hold the paper's omega = 1 + w.
RUN_FORMAT = 2


def _migrated(raw: dict[str, Any]) -> dict[str, Any]:
    """A run record as today's jaxtalk reads it: renamed config fields under their current names, fields
    added since with the values older runs were trained with, and, from format 1, TIMAR's guidance omega as
    the weight ``omega - 1`` (in ``config`` and the ``--set`` items)."""
    raw = _renamed(raw.get("model", ""), raw)
    model, config = raw.get("model"), dict(raw.get("config", {}))
    # Fields added after runs were first written take the value those runs were trained with.
    if model == "toktalk":
        config.setdefault("noise_frames", 0.0)  # trained on white noise before noise_frames existed
    if model == "ats" and "num_emotions" in config:
        # ATS runs recorded before the vocabulary was a setting have the EmoVOCA table (12 rows).
        if config.pop("num_emotions") != 12:
            raise ValueError("this ATS run's emotion table has no vocabulary on record; train it again")
    raw = {**raw, "config": config}
    if raw.get("format", 1) < 2 and model == "timar":
        config = dict(raw.get("config", {}))
        if "cfg_scale" in config:
            config["cfg_scale"] = float(config["cfg_scale"]) - 1.0
        items = []
        for item in raw.get("items", []):
            key, sep, value = item.partition("=")
            try:
                items.append(f"{key}={float(value) - 1.0:g}" if sep and key.strip() == "cfg_scale" else item)
            except ValueError:
                items.append(item)
        raw = {**raw, "config": config, "items": items}
    return {**raw, "format": RUN_FORMAT}


def _renamed(model: str, raw: dict[str, Any]) -> dict[str, Any]:
    """A run record's dict with renamed config fields (in ``config`` and the ``--set`` items) under
    their current names."""
    table = RENAMED_FIELDS.get(raw.get("model", model), {})
    if not table:
        return raw
    config = {table.get(k, k): v for k, v in raw.get("config", {}).items()}
    items = []
    for item in raw.get("items", []):
        key, sep, value = item.partition("=")
        items.append(f"{table.get(key.strip(), key.strip())}{sep}{value}" if sep else item)
    return {**raw, "config": config, "items": items}


def config_class(model: str) -> type:
    """The frozen config dataclass of ``model`` (imported on demand).

    Raises:
        ValueError: unknown model name.
    """
    return model_spec(model).config_class


def preset_names(model: str) -> tuple[str, ...]:
    """The presets (``paper``, ``small``, ``tiny``) that ``model``'s config class defines."""
    return model_spec(model).presets


_TRUE = {"true", "1", "yes", "on"}
_FALSE = {"false", "0", "no", "off"}


def _parse_value(name: str, text: str, annotation: Any) -> Any:
    """``text`` converted to the field's annotated type (int, float, bool, str, optional)."""
    args = typing.get_args(annotation)
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        if type(None) in args and text.strip().lower() in ("none", "null"):
            return None
        inner = [a for a in args if a is not type(None)]
        return _parse_value(name, text, inner[0]) if len(inner) == 1 else text
    try:
        if annotation is bool:
            low = text.strip().lower()
            if low not in _TRUE | _FALSE:
                raise ValueError
            return low in _TRUE
        if annotation is int:
            return int(text)
        if annotation is float:
            return float(text)
    except ValueError:
        raise ValueError(f"--set {name}={text}: expected {annotation.__name__}, got {text!r}") from None
    return text


def parse_overrides(cls: type, items: Sequence[str]) -> dict[str, Any]:
    """Parse ``["key=value", ...]`` into typed keyword arguments of the dataclass ``cls``.

    Args:
        cls: a config dataclass.
        items: ``key=value`` strings (later ones win).

    Returns:
        ``{field: value}`` with values converted to the fields' types.

    Raises:
        ValueError: an item without ``=``, an unknown field (the valid ones are listed), or a value
            that does not parse as the field's type.
    """
    hints = typing.get_type_hints(cls)
    fields = [f.name for f in dataclasses.fields(cls)]
    out: dict[str, Any] = {}
    for item in items:
        if "=" not in item:
            raise ValueError(f"--set expects key=value, got {item!r}")
        key, value = (s.strip() for s in item.split("=", 1))
        if key not in fields:
            raise ValueError(f"--set {key}: {cls.__name__} has no field {key!r}; fields: {', '.join(fields)}")
        out[key] = _parse_value(key, value, hints[key])
    return out


def split_overrides(model: str, items: Sequence[str]) -> tuple[list[str], dict[str, Any]]:
    """``--set`` items split into model-config items and parsed training settings.

    Raises:
        ValueError: a key that is neither a config field nor a training setting (both lists named).
    """
    from jaxtalk.train.recipes import TrainSettings

    train_fields = {f.name for f in dataclasses.fields(TrainSettings)}
    config_fields = {f.name for f in dataclasses.fields(config_class(model))}
    model_items, train_items = [], []
    for item in items:
        key = item.split("=", 1)[0].strip()
        if key in train_fields and key not in config_fields:
            train_items.append(item)
        elif key in config_fields or "=" not in item:
            model_items.append(item)
        else:
            raise ValueError(f"--set {key}: neither a {config_class(model).__name__} field nor a training setting; "
                             f"config fields: {', '.join(sorted(config_fields))}; training: {', '.join(sorted(train_fields))}")
    return model_items, parse_overrides(TrainSettings, train_items)


def build_config(model: str, preset: str, items: Sequence[str] = ()) -> Any:
    """``model``'s config from a preset plus ``key=value`` overrides (validated by the dataclass).

    Raises:
        ValueError: unknown model or preset, bad overrides, or values the config rejects.
    """
    spec = model_spec(model)
    cls = spec.config_class
    if preset not in spec.presets:
        raise ValueError(f"{model} has no preset {preset!r}; expected one of {', '.join(spec.presets)}")
    return getattr(cls, preset)(**parse_overrides(cls, items))


def checkpoint_dir(run_dir: str | Path) -> Path:
    """Where a run's orbax checkpoints live."""
    return Path(run_dir) / "checkpoint"


@dataclasses.dataclass
class RunRecord:
    """The ``run.json`` of a training run: everything that sampling, evaluation and resuming need
    besides the checkpoint.

    Attributes:
        model: ``toktalk``, ``ats``, ``stm``, ``timar`` or ``dualtalk``.
        preset: config preset name (None: a config built in Python that equals no preset).
        items: the ``--set KEY=VALUE`` items as given.
        config: every field of the model config (``dataclasses.asdict``).
        train: every field of the :class:`jaxtalk.train.recipes.TrainSettings`.
        optim: every field of the :class:`jaxtalk.train.OptimConfig` (its structure, EMA and
            clipping, is what a restore needs).
        data: ``{"spec", "path", "key"}``: the data as named, its prepared folder, and its identity
            (source and feature settings).
        seed: training seed.
        extra: what the recipe fitted on the training split (normalisers, meshes, window sizes).
        format: the record's format (:data:`RUN_FORMAT`); an older record is brought up to it on loading.
    """

    model: str
    preset: str | None
    items: list[str]
    config: dict[str, Any]
    train: dict[str, Any]
    optim: dict[str, Any]
    data: dict[str, Any]
    seed: int
    extra: dict[str, Any] = dataclasses.field(default_factory=dict)
    format: int = RUN_FORMAT

    def save(self, run_dir: str | Path) -> Path:
        """Write ``run_dir/run.json`` (atomically) and return its path."""
        from jaxtalk.files import atomic_write_json

        return atomic_write_json(Path(run_dir) / RUN_FILE, dataclasses.asdict(self))

    @classmethod
    def load(cls, run_dir: str | Path) -> RunRecord:
        """Read ``run_dir/run.json``.

        Raises:
            FileNotFoundError: no run directory or no ``run.json`` in it.
            ValueError: a ``run.json`` that is not a run record (or one written by an older jaxtalk).
        """
        path = Path(run_dir) / RUN_FILE
        if not path.is_file():
            raise FileNotFoundError(f"{run_dir} is not a training run (no {RUN_FILE}; make one with `jaxtalk train`)")
        try:
            raw = json.loads(path.read_text())
            return cls(**_migrated(raw))
        except (json.JSONDecodeError, TypeError) as err:
            raise ValueError(f"{path} is not a run record of this jaxtalk version ({err}); train it again") from None

    def model_config(self) -> Any:
        """The model config instance."""
        return config_class(self.model)(**self.config)

    def optim_config(self) -> Any:
        """The :class:`jaxtalk.train.OptimConfig` instance."""
        from jaxtalk.train import OptimConfig

        return OptimConfig(**self.optim)


# Files a run keeps beside run.json so that sampling needs neither the dataset nor SynthTalk.
TOKENIZER_FILE = "tokenizer.npz"
STYLE_FILE = "style.npy"
FEATURES_FILE = "features.json"


def save_run_assets(run_dir: str | Path, model: str, data: Any, config: Any) -> None:
    """Copy what inference needs from the prepared data into the run: the feature settings, the VQ
    tokenizer (when the data has one) and, for TokTalk, a default style clip (a training clip)."""
    from jaxtalk.files import atomic_copy, atomic_save_npy, atomic_write_json

    run_dir = Path(run_dir)
    m = data.manifest
    features = {"audio": m["settings"]["audio"], "tokens": m["settings"]["tokens"], "token_rate": m.get("token_rate"),
                "token_dim": m.get("token_dim"), "speech_dim": m.get("speech_dim"),
                "turn_speech_dim": m.get("turn_speech_dim")}
    atomic_write_json(run_dir / FEATURES_FILE, features)
    if m.get("tokenizer"):
        atomic_copy(data.root / m["tokenizer"], run_dir / TOKENIZER_FILE)
    if model_spec(model).style_asset:
        atomic_save_npy(run_dir / STYLE_FILE, default_style_clip(data, config))


def default_style_clip(data: Any, config: Any) -> Any:
    """TokTalk's default reference motion, what a run saves as ``style.npy`` (``jaxtalk stream``'s style
    without ``--style``): the first ``4 * style_frames`` frames of the longest training clip of ``data``.

    Args:
        data: the prepared data (:class:`~jaxtalk.data.loader.PreparedData`) with a ``train`` split.
        config: the TokTalk config (``style_frames``).

    Returns:
        ``(S, 56)`` float32 motion (a NumPy array; typed ``Any`` so that this module imports no array
        library, and ``jaxtalk --help`` stays instant).
    """
    import numpy as np

    train = data.split("train")
    clip = max(train, key=lambda i: data.clips[i]["frames"])
    style = data.record(clip, ("motion",), frames=(0, 4 * config.style_frames))["motion"]
    return np.asarray(style, np.float32)


@dataclasses.dataclass(frozen=True)
class RunInfo:
    """What ``run.json`` records that a recipe cannot see: how the run was asked for.

    Attributes:
        preset: the preset the config was built from (None: the preset the config equals, if any).
        items: the ``--set KEY=VALUE`` items given.
        data_spec: the data as the user named it (None: the prepared folder).
        settings: the :class:`~jaxtalk.train.recipes.TrainSettings` (None: read back from the
            optimiser settings and the recipe's batch size, window and validation period).
    """

    preset: str | None = None
    items: tuple[str, ...] = ()
    data_spec: str | None = None
    settings: Any = None


def _preset_of(model: str, config: Any) -> str | None:
    """The preset whose config equals ``config`` (a run built in Python names one when it can)."""
    spec = model_spec(model)
    cls = spec.config_class
    return next((p for p in spec.presets if getattr(cls, p)() == config), None)


def write_run(run_dir: str | Path, model: str, config: Any, data: Any, optim: Any, *, seed: int,
              extra: dict[str, Any], settings: Any, info: RunInfo | None = None,
              features: dict[str, Any] | None = None) -> RunRecord:
    """Write a trained run's ``run.json``, ``config.json`` and inference assets into ``run_dir``.

    Every recipe calls this after training when it is given a ``run_dir`` (the checkpoints are
    already in ``run_dir/checkpoint``), so a run made from Python opens like one made by
    ``jaxtalk train``.

    Args:
        run_dir: the run folder.
        model: a :data:`REGISTRY` name.
        config: the model config it trained.
        data: the :class:`~jaxtalk.data.loader.PreparedData` it trained on.
        optim: the :class:`~jaxtalk.train.OptimConfig`.
        seed: the training seed.
        extra: what the recipe fitted on the training split.
        settings: the training settings used when ``info`` names none.
        info: how the run was asked for (preset, ``--set`` items, data as named, settings).
        features: only with ``data=None`` (a run made without prepared data, e.g. converted from
            another implementation's checkpoint): the ``features.json`` record of the speech front
            end its inputs come from (``{"audio": spec, "turn_speech_dim": width, ...}``).

    Returns:
        The :class:`RunRecord` written.

    Raises:
        ValueError: ``data`` and ``features`` both or neither given.
    """
    from jaxtalk.files import atomic_write_json

    if (data is None) == (features is None):
        raise ValueError("write_run needs the prepared data, or (for a run made without data) its feature record")
    info = info or RunInfo()
    preset = info.preset if info.preset is not None else _preset_of(model, config)
    if data is None:
        data_record = {"spec": info.data_spec, "path": None, "key": None}
    else:
        data_record = {"spec": info.data_spec or str(data.root), "path": str(Path(data.root).absolute()), "key": data.key}
    record = RunRecord(model=model, preset=preset, items=list(info.items), config=dataclasses.asdict(config),
                       train=dataclasses.asdict(info.settings if info.settings is not None else settings),
                       optim=optim.to_dict(), data=data_record, seed=seed, extra=extra)
    record.save(run_dir)
    atomic_write_json(Path(run_dir) / CONFIG_FILE, record.config)
    if data is None:
        atomic_write_json(Path(run_dir) / FEATURES_FILE, features)
    else:
        save_run_assets(run_dir, model, data, config)
    return record


def _default_loop() -> LoopSettings:
    from jaxtalk.train.loop import LoopSettings

    return LoopSettings()


@dataclasses.dataclass(frozen=True)
class RunSettings:
    """How a recipe's run goes, besides the model, the data, the optimiser and the key: what every
    recipe's ``train`` takes (``train(config, data, optim, *, key, run=RunSettings(...), ...)``).

    Attributes:
        steps: stop at this step (None: the optimiser's ``total_steps``).
        batch_size: windows per batch on each process (a smaller training split trains with the largest
            batch it allows, and the run records that one).
        seed: data-order seed (and the recipe's own choices of windows, such as TokTalk's style clips).
        window_frames: frames per training window (None: the model's default; 0: ATS's whole clips),
            for the models whose windows have a length setting (not TIMAR's or the baseline's turns).
        eval_every: validation period in steps (None: only at the end).
        run_dir: write a complete run here (``run.json``, ``config.json``, the checkpoints in
            ``run_dir/checkpoint``, the inference assets), or None.
        ckpt_dir: checkpoint folder (exact resume); None: ``run_dir/checkpoint`` with a ``run_dir``,
            else no checkpoints.
        mesh: device mesh for data parallelism, or None.
        info: how the run was asked for (:class:`RunInfo`: the CLI's preset, ``--set`` items and
            settings), recorded in ``run.json``; None: a Python call.
        loop: the rest of the loop's settings (:class:`~jaxtalk.train.LoopSettings`: ``progress``,
            ``save_every``, ``log_every``, ...). Its length and evaluation period are ``steps`` and
            ``eval_every`` here, and its best checkpoint is the recipe's choice, so those stay unset.
        observers: :class:`~jaxtalk.train.StepObserver` s that watch the steps (a profiler trace, a
            stop request, the benchmark's probe).

    Raises:
        ValueError: a count or period below 1 (``window_frames`` below 0), or ``loop`` settings that
            are the run's or the recipe's (``max_steps``, ``eval_every``, ``best_metric``, ``best_mode``).
    """

    steps: int | None = None
    batch_size: int = 16
    seed: int = 0
    window_frames: int | None = None
    eval_every: int | None = None
    run_dir: str | Path | None = None
    ckpt_dir: str | Path | None = None
    mesh: Mesh | None = None
    info: RunInfo | None = None
    loop: LoopSettings = dataclasses.field(default_factory=_default_loop)
    observers: Sequence[StepObserver] = ()

    def __post_init__(self) -> None:
        for name in ("steps", "eval_every"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise ValueError(f"{name} must be >= 1 or None, got {value}")
        if self.batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {self.batch_size}")
        if self.window_frames is not None and self.window_frames < 0:
            raise ValueError(f"window_frames must be >= 0 or None, got {self.window_frames}")
        loop = self.loop
        taken = [name for name, value in (("max_steps", loop.max_steps), ("eval_every", loop.eval_every),
                                          ("best_metric", loop.best_metric)) if value is not None]
        taken += ["best_mode"] if loop.best_mode != "min" else []
        if taken:
            raise ValueError(f"RunSettings.loop sets {', '.join(taken)}: a run's length and validation period are "
                             "RunSettings.steps and eval_every, and its recipe chooses the best checkpoint")
        object.__setattr__(self, "observers", tuple(self.observers))  # settings compare by value

    @property
    def ckpt_path(self) -> Path | None:
        """The checkpoint folder the run uses: ``ckpt_dir``, else ``run_dir/checkpoint``, else None."""
        if self.ckpt_dir is not None:
            return Path(self.ckpt_dir)
        return None if self.run_dir is None else checkpoint_dir(self.run_dir)


def fit_run(recipe: WindowRecipe, data: PreparedData, loss_fn: LossFn, params: Any, optim: OptimConfig, *,
            config: Any, key: PRNGKeyArray, eval_key: PRNGKeyArray, run: RunSettings, metadata: dict[str, Any],
            extra: dict[str, Any], sample_eval: EvalFn | None = None, best_metric: str | None = None,
            best_mode: typing.Literal["min", "max"] = "min", trainable: Trainable = None) -> RecipeResult:
    """Train a model on a recipe's windows and, given ``run.run_dir``, record the run: what every model
    recipe calls once its windows, loss and initial parameters are set.

    The training is :func:`jaxtalk.train.recipes.fit_recipe`'s (checkpoints in ``run.ckpt_path``); the
    record is :func:`write_run`'s, written by process 0 only (every process checkpoints, one writes the
    record), with the batch the run trained with (smaller than asked on a small training split).

    Args:
        recipe, data, loss_fn, params, optim, key, eval_key, sample_eval, trainable: as
            :func:`~jaxtalk.train.recipes.fit_recipe`.
        config: the model config (recorded).
        run: the run's settings.
        metadata: saved with each checkpoint; ``metadata["model"]`` names the run's model.
        extra: what the recipe fitted on the training split (recorded, and the result's ``extra``).
        best_metric: the metric of ``sample_eval`` the best checkpoint is chosen by (None: the
            validation loss), in the direction of ``best_mode`` (``"min"``: lower is better, or ``"max"``).

    Returns:
        The :class:`~jaxtalk.train.recipes.RecipeResult`, ``extra`` included.
    """
    import jax

    from jaxtalk.train.recipes import TrainSettings, fit_recipe

    loop = dataclasses.replace(run.loop, max_steps=run.steps, eval_every=run.eval_every, best_metric=best_metric,
                               best_mode=best_mode)
    result = fit_recipe(recipe, data, loss_fn, params, optim, key=key, eval_key=eval_key, batch_size=run.batch_size,
                        seed=run.seed, settings=loop, ckpt_dir=run.ckpt_path, mesh=run.mesh, metadata=metadata,
                        sample_eval=sample_eval, trainable=trainable, observers=run.observers)
    result = dataclasses.replace(result, extra=extra)
    if run.run_dir is not None and jax.process_index() == 0:  # every process checkpoints; one writes the record
        info = run.info or RunInfo()
        if info.settings is not None:  # the run records the batch it trained with
            info = dataclasses.replace(info, settings=dataclasses.replace(info.settings, batch_size=result.batch_size))
        settings = TrainSettings.of_run(optim, batch_size=result.batch_size, window_frames=run.window_frames,
                                        eval_every=run.eval_every)
        write_run(run.run_dir, metadata["model"], config, data, optim, seed=run.seed, extra=extra, settings=settings,
                  info=info)
    return result


@dataclasses.dataclass
class LoadedRun:
    """A trained run ready to sample.

    Attributes:
        record: its ``run.json``.
        config: the model config.
        params: the evaluation parameters (the EMA when the run kept one).
        step: the checkpoint step they come from.
        run_dir: the run folder.
    """

    record: RunRecord
    config: Any
    params: Any
    step: int
    run_dir: Path

    def tokenizer(self) -> Any:
        """The VQ tokenizer the run's data was prepared with, or None (the data had its own tokens).

        The tokenizer turns new audio into the token space the model was trained on.
        """
        path = self.run_dir / TOKENIZER_FILE
        if not path.is_file():
            return None
        from jaxtalk.audio import VQTokenizer

        return VQTokenizer.load(path)

    def default_style(self) -> Any:
        """TokTalk's default reference motion ``(S, 56)``: a training clip saved with the run.

        Raises:
            FileNotFoundError: a run without one (not TokTalk).
        """
        from jaxtalk.files import load_npy

        path = self.run_dir / STYLE_FILE
        if not path.is_file():
            raise FileNotFoundError(f"{self.run_dir} has no {STYLE_FILE}; pass --style")
        return load_npy(path)

    def features(self) -> dict[str, Any]:
        """The feature settings the run's data was prepared with (:func:`run_features`)."""
        return run_features(self.run_dir)


def run_features(run_dir: str | Path) -> dict[str, Any]:
    """A run's ``features.json``: the feature settings its data was prepared with (``audio``: the
    speech front end as ``prepare --features`` spells it; token stream and widths), read without
    loading the run.

    Raises:
        FileNotFoundError: no ``features.json`` (not a finished run).
    """
    path = Path(run_dir) / FEATURES_FILE
    if not path.is_file():
        raise FileNotFoundError(f"{run_dir} has no {FEATURES_FILE} (not a finished run: train it with `jaxtalk train`)")
    return json.loads(path.read_text())


def _restore_state(directory: Path, step: int | None) -> tuple[dict[str, Any], int]:
    """The saved train state as stored (a dict of arrays), without a template.

    A template would have to repeat each model's training-time structure (TokTalk's data-dependent
    normalisation entry, the optimiser's frozen-parameter mask); the checkpoint already knows it.
    """
    from jaxtalk.train import Checkpointer

    # Orbax's notes on a read-only open are filtered by the Checkpointer itself.
    try:
        with Checkpointer(directory, read_only=True) as ckpt:
            return ckpt.restore_saved(step)
    except FileNotFoundError as err:
        if "no complete checkpoint" in str(err):  # nothing trained yet: tell the user what to do
            raise FileNotFoundError(f"{err} (train first: `jaxtalk train`)") from err
        raise


def load_run(run_dir: str | Path, *, step: int | None = None, best: bool = False) -> LoadedRun:
    """Restore a run's newest (or a given, or its best-validated) checkpoint.

    Args:
        run_dir: the folder ``jaxtalk train`` wrote.
        step: checkpoint step (default: the newest).
        best: the checkpoint the run's validation chose instead (kept when the data has a
            validation split): the lowest value of the run's selection metric (TokTalk: streamed lip
            error on the validation clips; the other models: validation loss).

    Returns:
        :class:`LoadedRun` with the EMA parameters when the run kept an EMA.

    Raises:
        FileNotFoundError: not a run, no complete checkpoint in it, or ``best`` for a run without a
            validated checkpoint.
        ValueError: a corrupt checkpoint, or ``best`` together with ``step``.
    """
    from jaxtalk.train import best_checkpoint_dir

    record = RunRecord.load(run_dir)
    config = record.model_config()
    directory = checkpoint_dir(run_dir).absolute()
    if best:
        if step is not None:
            raise ValueError("choose a checkpoint by step or the best one, not both")
        directory = best_checkpoint_dir(directory)
        if not directory.is_dir():
            raise FileNotFoundError(f"{run_dir} has no best checkpoint (its data had no validation split)")
    state, step = _restore_state(directory, step)
    params = state.get("ema_params") or state["params"]
    return LoadedRun(record=record, config=config, params=params, step=step, run_dir=Path(run_dir))
