"""``jaxtalk eval RUN``: a trained run scored on a split of prepared data, next to baselines.

The data is the run's own prepared folder unless ``--data`` names another one (or
``synthtalk:SIZE``); it must carry the features the run was trained on (token width and rate for
TokTalk, the audio front end and its width for TIMAR and ATS), else a ``ValueError`` says which.
Each model is scored the way it is used:

Each model's protocol lives in its package (``jaxtalk.models.<model>.evaluation``, named by its
:attr:`~jaxtalk.runs.ModelSpec.evaluate`):

* TokTalk: every clip of the split with motion and tokens (up to ``--max-clips``) is streamed chunk
  by chunk (the live engine, :func:`jaxtalk.models.toktalk.stream`) in the speaking style of another
  clip of the same speaker in the split (the run's default style when the speaker has none), and posed
  on the built-in face (``builtin_face(0)``), or on FLAME with ``--flame FILE`` (its lip and
  upper-face regions come from ``FLAME_masks.pkl`` beside FILE; without it LVE and FDD are left out,
  and MOD always is: FLAME has no mouth-opening vertex pairs). Columns: MSE of the 56-d parameters;
  LVE (mm^2: per frame the max over the lip vertices of the squared error, averaged); MVE (mm, mean
  vertex error); FDD (mm^2, signed upper-face dynamics deviation: positive when the prediction moves
  the upper face less than the truth); MOD (mm, mouth-opening distance); jitter (mm per frame^2, mean
  vertex acceleration).
* TIMAR: every conversation side of the split whose partner is prepared is streamed turn by turn
  (:func:`jaxtalk.models.timar.streaming.stream`, standardised with the run's normaliser; a
  partner without tracked motion is the run's still pose, as in training), and scored with the
  DualTalk benchmark (:func:`jaxtalk.metrics.conversation_metrics`) per group (exp, jaw, pose): FD,
  P-FD, MSE, SID (k-means fit on the ground truth) and rPCC, in the published scaling
  (``PUBLISHED_SCALE``, in each table's title). SID needs 40 frames per side; shorter sides leave it
  out.
* DualTalk baseline (``dualtalk`` runs): the same sides, normaliser and tables as TIMAR, each turn
  predicted from the window of its past turns (as many as the training window holds, less one) and
  the whole current turn (:func:`jaxtalk.models.dualtalk.predict_turns`).
* ATS: landmark displacements (68 landmarks on the built-in face, head pose removed, as ``prepare``
  computes them) are sampled for consecutive training-length windows of each clip (the last one flush
  with the clip's end) and de-standardised with the run's statistics. Columns: LVE (mm^2, the lip
  analogue on the 20 mouth landmarks 48-67), LE (mm, mean landmark error), jitter (mm per frame^2).
* STM: the split's motion (head pose removed) is rendered on each of the run's meshes; STM maps the
  true landmark displacements to vertex displacements, scored against the rendered vertices: MVE
  (mm), LVE (mm^2, the mesh's lip region), jitter (mm per frame^2).

Real voices (``--real-voice FOLDER``, TokTalk and TIMAR): every recording of FOLDER (``.wav``,
``.flac``...; any rate, mono or stereo), each optionally with its speaker's tracked motion beside it
(``STEM.npz`` holding DualTalk's ``pose (T, 6)``, jaw = ``pose[:, 3]``, or jaxtalk's ``params (T, 56)``,
jaw = ``params[:, 50]``, at 25 fps), is streamed through the run as ``jaxtalk stream`` does, and its
predicted jaw opening measured with :func:`jaxtalk.metrics.speech_sync.speech_sync`: against the
tracked jaw at lag 0 and at its best lag (positive: the prediction is late), beside the loudness
follower (the recording's log loudness against the tracked jaw, the baseline a lip-sync model must
beat); against the loudness itself; and the predicted jaw's mean over silent and speech frames (an
energy voice-activity detector). A ``mean`` row averages the recordings (the tracked-jaw columns over
those with tracked motion), and a last row gives the rest jaw: the jaw streamed on 3 s of digital
silence in the same style. Nothing is written beside the recordings.

Baselines: the mean pose, the training mean repeated (what a model that ignores its input scores:
TokTalk's motion standardiser, TIMAR's normaliser, ATS's displacement statistics); ``neutral`` (zero
displacement) for ATS and STM; and, where the records have one (SynthTalk), the generator's oracle, the
deterministic part of the motion (what a perfect model gets: blinks and sway are unpredictable). A
``ground truth`` row gives the data's own jitter. Per-clip metrics are averaged over clips weighted by
their frames (FDD: the plain mean over clips, as ``fdd_batch``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from jaxtalk.checks import check_temperature
from jaxtalk.data.recordings import MAX_LAG, Recording, read_recordings
from jaxtalk.metrics.evaluation import EvalSettings, EvalTable
from jaxtalk.runs import LoadedRun, RunRecord, checkpoint_dir, load_run, model_spec, run_features

__all__ = ["EvalOptions", "EvalReport", "evaluate_run", "open_eval_data", "check_eval_data", "REST_SECONDS"]

@dataclasses.dataclass(frozen=True)
class EvalOptions:
    """Settings of :func:`evaluate_run`.

    Attributes:
        run_dir: a folder written by ``jaxtalk train`` (any model).
        data: a prepared folder or ``synthtalk:SIZE[:SEED]``; None: the run's own data.
        split: split of the data (``train``, ``val``, ``test``, ``ood``); None: ``test``.
        max_clips: at most this many clips (TokTalk, ATS, STM), conversation sides (TIMAR) or
            recordings (``real_voice``).
        seed: noise seed.
        flame: TokTalk: a FLAME 2020 model file to pose the parameters on instead of the built-in face.
        cache_dir: where ``synthtalk:`` data is prepared.
        best: evaluate the best-validated checkpoint (``checkpoint/best``) instead of the latest.
        sample_steps: TokTalk: Euler step counts, one streamed row each (empty: the config's).
        offline: TokTalk: also sample each clip offline in one pass (full attention), per step count.
        temperature: scale of the sampler's noise (TokTalk: the starting noise, None: the config's;
            TIMAR: MAR's temperature, None: 1). Refused for the models that take none.
        real_voice: TokTalk, TIMAR: a folder of real recordings (and tracked motion) to measure the
            predicted jaw on instead of prepared data (see the module docstring); TokTalk's
            ``sample_steps`` give one table each.
        scoring: TIMAR and the DualTalk baseline: ``jaxtalk`` and/or ``public`` (as the public
            ``calc_metric.py``), one set of tables each (:data:`jaxtalk.metrics.evaluation.SCORINGS`).
    """

    run_dir: Path
    data: str | None = None
    split: str | None = None
    max_clips: int = 8
    seed: int = 0
    flame: Path | None = None
    cache_dir: Path = Path(".cache/prepared")
    best: bool = False
    sample_steps: tuple[int, ...] = ()
    offline: bool = False
    temperature: float | None = None
    real_voice: Path | None = None
    scoring: tuple[str, ...] = ("jaxtalk",)


@dataclasses.dataclass
class EvalReport:
    """What :func:`evaluate_run` measured.

    Attributes:
        model: the run's model.
        run_dir: the run folder.
        step: the checkpoint step evaluated.
        data: the prepared folder evaluated on (``real_voice``: the recordings' folder).
        split: its split (None for real voices).
        items: clips (TokTalk, ATS, STM), conversation sides (TIMAR) or recordings evaluated.
        tables: the result tables.
    """

    model: str
    run_dir: str
    step: int
    data: str
    split: str | None
    items: int
    tables: list[EvalTable]

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


# ---------------------------------------------------------------------------------------------- data


def open_eval_data(record: RunRecord, spec: str | Path | None, cache_dir: str | Path = ".cache/prepared",
                   features: str | None = None) -> Any:
    """The prepared data to evaluate on: ``spec``, or the run's own (its folder, else its spec again).

    Args:
        record: the run's ``run.json``.
        spec: a prepared folder or ``synthtalk:SIZE[:SEED]``; None: the run's own data.
        cache_dir: where ``synthtalk:`` data is prepared.
        features: the run's speech front end (its ``features.json``'s ``audio``), with which
            ``synthtalk:`` data is prepared for a model that reads speech features (a folder keeps its
            own: :func:`check_eval_data` says when it is not the run's).

    Raises:
        FileNotFoundError: a folder that is not prepared.
    """
    from jaxtalk.data.loader import PreparedData, open_data
    from jaxtalk.data.prepare import MANIFEST

    spec = str(spec) if spec is not None else None
    path = record.data.get("path")
    if spec is None and path and (Path(path) / MANIFEST).is_file():
        return PreparedData(path)
    spec = spec if spec is not None else record.data["spec"]
    synthtalk_features = features if spec.startswith("synthtalk:") and model_spec(record.model).reads_speech else None
    return open_data(spec, cache_dir=cache_dir, progress=False, features=synthtalk_features)


def check_eval_data(record: RunRecord, features: dict[str, Any], data: Any) -> None:
    """Raise ValueError unless ``data`` carries the inputs the run was trained on.

    TokTalk: token width and rate; TIMAR and the DualTalk baseline: per-turn speech of the run's audio front
    end and width; ATS: per-frame speech likewise. Every model: 56-d motion.
    """
    m, cfg = data.manifest, record.config
    where = f"{data.root} (prepared from {m['source']['spec']})"
    if m.get("stats") is None:
        raise ValueError(f"{where} has no training split with motion; prepare it from data with 56-d motion")
    spec = model_spec(record.model)
    wanted = {key: cfg[field] for field, key in spec.data_fields}
    if "token_dim" in wanted:  # a model that reads audio tokens: their width and rate
        width, rate = wanted["token_dim"], wanted["token_rate"]
        if not m.get("token_dim"):
            raise ValueError(f"{where} has no token stream, the {spec.title} run needs tokens of width {width}")
        if m["token_dim"] != width or float(m["token_rate"]) != float(rate):
            raise ValueError(f"{where} has tokens of width {m['token_dim']} at {m['token_rate']:g} Hz, the run was "
                             f"trained on width {width} at {rate:g} Hz")
        return
    from jaxtalk.data.features import same_encoder

    for key, width in wanted.items():  # a model that reads speech features: their front end and width
        # The front end must be the run's; its waveform normalisation may differ (per turn as trained,
        # or over the whole recording as the public TIMAR loader evaluates).
        if not same_encoder(m["settings"]["audio"], features.get("audio")) or m.get(key) != width:
            raise ValueError(f"{where} has {m.get(key)}-d {m['settings']['audio']!r} speech features, the run was "
                             f"trained on {width}-d {features.get('audio')!r} features; prepare it with "
                             f"--features {features.get('audio')}")


def _models_where(has: Callable[[Any], bool], *, words: Callable[[Any], str] = lambda spec: spec.name) -> str:
    """The models whose spec ``has`` something, in ``words`` (``toktalk and timar``)."""
    from jaxtalk.runs import REGISTRY

    return " and ".join(words(spec) for spec in REGISTRY.values() if has(spec))


# ------------------------------------------------------------------------------------- real voices

# Seconds of digital silence streamed for the rest jaw (a TIMAR run: whole turns, at least this long).
REST_SECONDS = 3.0


def _eval_real_voices(run: LoadedRun, recordings: list[Recording], opts: EvalOptions,
                      echo: Callable[[str], None]) -> tuple[int, list[EvalTable]]:
    from jaxtalk.commands.inference import SampleOptions, stream_audio
    from jaxtalk.data.recordings import mean_row, recording_sync, sync_row
    from jaxtalk.types import AUDIO_SAMPLE_RATE, MOTION_FPS

    spec = model_spec(run.record.model)
    title, turn = spec.title, spec.animator.step_frames(run.config)
    if len(recordings) > opts.max_clips:
        echo(f"note: the first {opts.max_clips} of {len(recordings)} recordings (--max-clips)")
        recordings = recordings[: opts.max_clips]
    tracked = sum(r.tracked_jaw is not None for r in recordings)
    echo(f"streaming {len(recordings)} recordings of {opts.real_voice} ({tracked} with tracked motion) with "
         f"{title} (step {run.step})")
    rest_frames = -(-int(REST_SECONDS * MOTION_FPS) // turn) * turn
    silence = np.zeros(rest_frames * AUDIO_SAMPLE_RATE // MOTION_FPS, np.float32)
    silent = Recording(f"digital silence ({silence.shape[0] / AUDIO_SAMPLE_RATE:g} s)", Path(opts.real_voice),
                       silence, None, None)
    quiet = lambda line: None  # noqa: E731  (per-chunk times: `jaxtalk stream` prints them)
    rest_note = "" if spec.animator.rest_note is None else f"; {spec.animator.rest_note(run)}"

    variants = [(n, f", {n} step{'s' * (n > 1)}") for n in opts.sample_steps] or [(None, "")]
    tables = []
    for steps, label in variants:
        sample = SampleOptions(run_dir=opts.run_dir, input=Path(opts.real_voice), sample_steps=steps,
                               temperature=opts.temperature, seed=opts.seed, best=opts.best)
        rows = []
        for rec in recordings:
            pred = stream_audio(run, rec.audio, dataclasses.replace(sample, input=rec.path), echo=quiet)
            rows.append(sync_row(rec.name, "no" if rec.tracked_jaw is None else "yes", recording_sync(rec, pred)))
            r = rows[-1]
            echo(f"  {rec.name}: {r['frames']} frames" + (f", corr {r['corr']:.3f} (loudness follower "
                                                          f"{r['loudness_corr']:.3f})" if r["corr"] is not None else ""))
        rest = stream_audio(run, silence, sample, echo=quiet)
        rest_row = sync_row(silent.name, None, recording_sync(silent, rest))
        tables.append(EvalTable(f"{title} on real voices ({Path(opts.real_voice).name}{label}): predicted jaw "
                                "opening (rad) vs the tracked jaw and the loudness; lags in frames, positive = late"
                                + rest_note, [*rows, mean_row(rows), rest_row]))
    return len(recordings), tables


def evaluate_run(opts: EvalOptions, *, echo: Callable[[str], None] = print) -> EvalReport:
    """Score a trained run on a split of prepared data (see the module docstring).

    Args:
        opts: settings.
        echo: where progress lines and notes go.

    Returns:
        :class:`EvalReport` with the tables.

    Raises:
        FileNotFoundError: not a run, no checkpoint (not trained yet), a data folder that is not
            prepared, a missing ``--flame`` file.
        ValueError: an unknown split, a split without clips the model can use, ``max_clips < 1``,
            data whose features differ from the run's, ``--flame`` for a model other than TokTalk;
            with ``real_voice``: a run without a jaw (ATS, STM, the DualTalk baseline), options of
            prepared data, a bad folder or recording (:func:`jaxtalk.data.recordings.read_recordings`).
    """
    record = RunRecord.load(opts.run_dir)
    spec = model_spec(record.model)
    protocol = spec.evaluate
    if protocol is None:
        raise ValueError(f"{opts.run_dir} is a {record.model!r} run, which has no evaluation protocol")
    if opts.max_clips < 1:
        raise ValueError(f"--max-clips must be >= 1, got {opts.max_clips}")
    if opts.real_voice is not None:
        if spec.animator is None:
            article = "an" if record.model[0] in "aeiou" else "a"
            animated = _models_where(lambda s: s.animator is not None)
            raise ValueError(f"--real-voice streams recordings through {animated} runs (their output has a jaw); "
                             f"{opts.run_dir} is {article} {record.model} run")
        given = [flag for flag, value in (("--data", opts.data), ("--split", opts.split), ("--flame", opts.flame),
                                          ("--offline", opts.offline or None),
                                          ("--scoring", None if opts.scoring == ("jaxtalk",) else opts.scoring))
                 if value is not None]
        if given:
            raise ValueError(f"{', '.join(given)}: not with --real-voice, which measures the recordings of "
                             f"{opts.real_voice}, not prepared data")
        if opts.sample_steps and "--sample-steps" not in spec.eval_options:
            owners = _models_where(lambda s: "--sample-steps" in s.eval_options, words=lambda s: s.title)
            raise ValueError(f"--sample-steps gives {owners} one table per step count; a {record.model} run streams "
                             "with its own")
    if opts.flame is not None:
        if "--flame" not in spec.eval_options:
            raise ValueError(f"--flame poses TokTalk's parameters on FLAME; {opts.run_dir} is a {record.model} run")
        if not Path(opts.flame).is_file():
            raise FileNotFoundError(f"FLAME model file not found: {str(opts.flame)!r}")
    if opts.scoring != ("jaxtalk",) and "--scoring" not in spec.eval_options:
        owners = _models_where(lambda s: "--scoring" in s.eval_options, words=lambda s: s.title)
        raise ValueError(f"--scoring chooses how {owners} score conversation sides; {opts.run_dir} is a "
                         f"{record.model} run")
    if opts.temperature is not None:
        if "--temperature" not in spec.eval_options:
            owners = _models_where(lambda s: "--temperature" in s.eval_options, words=lambda s: f"{s.title}'s")
            raise ValueError(f"--temperature scales {owners} sampler noise; {opts.run_dir} is a {record.model} run")
        check_temperature(opts.temperature, name="--temperature")
    from jaxtalk.train import latest_checkpoint_step

    split = opts.split or "test"
    if opts.real_voice is None:
        data = open_eval_data(record, opts.data, opts.cache_dir, run_features(opts.run_dir).get("audio"))
        data.split(split)  # an unknown split: ValueError naming the known ones
    else:  # a bad folder or file is refused before the run is loaded
        step = spec.animator.step_frames(record.model_config())
        recordings = read_recordings(opts.real_voice, min_frames=max(MAX_LAG + 3, step), echo=echo)
    if latest_checkpoint_step(checkpoint_dir(opts.run_dir)) is None:
        raise FileNotFoundError(f"{opts.run_dir} is not trained yet (no checkpoint in {checkpoint_dir(opts.run_dir)}); "
                                "train it with `jaxtalk train`")
    run = load_run(opts.run_dir, best=opts.best)
    if opts.real_voice is not None:
        items, tables = _eval_real_voices(run, recordings, opts, echo)
        return EvalReport(model=record.model, run_dir=str(opts.run_dir), step=run.step, data=str(opts.real_voice),
                          split=None, items=items, tables=tables)
    check_eval_data(record, run.features(), data)
    settings = EvalSettings(max_clips=opts.max_clips, seed=opts.seed, flame=opts.flame,
                            sample_steps=tuple(opts.sample_steps), offline=opts.offline, temperature=opts.temperature,
                            scoring=tuple(opts.scoring))
    items, tables = protocol(run, data, split, settings, echo)
    return EvalReport(model=record.model, run_dir=str(opts.run_dir), step=run.step, data=str(data.root),
                      split=split, items=items, tables=tables)
