"""The ``jaxtalk`` command line.

Every command has ``--help`` and sensible defaults. User mistakes (a missing file, a bad option value,
a malformed input) end with one clear line on stderr and exit code 2, never a traceback; pass
``--debug`` before the command to see the traceback anyway.
"""

from __future__ import annotations

import dataclasses
import functools
import sys
import warnings
from pathlib import Path
from collections.abc import Callable
from typing import Annotated, Any

import typer

from jaxtalk.demo import DemoOptions
from jaxtalk.viewer import ViewerError

app = typer.Typer(
    name="jaxtalk",
    help="Speech-driven 3D face animation in JAX (TokTalk, FreeTalk, TIMAR).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

_STATE = {"debug": False}

_OVERWRITE = Annotated[bool, typer.Option(
    help="Let files whose names the command picks itself (default output names, side files such as the audio "
         "beside a .glb, a folder's report) replace existing files. A path you name with --out is replaced "
         "anyway; an input of the command never is.")]

# Errors that mean "the user asked for something wrong", reported as one line.
# (ViewerError: no Node.js / npm for `jaxtalk view`, or its install failed; jaxtalk.viewer imports only the
# standard library, so naming it here costs the CLI's start-up nothing.)
USER_ERRORS = (ValueError, FileNotFoundError, NotADirectoryError, FileExistsError, PermissionError, KeyError,
               ViewerError)


def _one_line_notes(show: Callable[..., Any]) -> Callable[..., Any]:
    """``warnings.showwarning`` that prints a warning whose category has a ``cli_prefix`` (a face file's
    KTX2 textures passed over: ``note: ...``) as one line, and hands every other warning to ``show``."""

    def showwarning(message: Any, category: type[Warning], filename: str, lineno: int, file: Any = None,
                    line: str | None = None) -> None:
        prefix = getattr(category, "cli_prefix", None)
        if prefix is None:
            show(message, category, filename, lineno, file, line)
        else:
            typer.echo(f"{prefix}: {message}", err=True)

    return showwarning


def _user_errors(fn: Callable[..., Any]) -> Callable[..., Any]:
    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            with warnings.catch_warnings():
                warnings.showwarning = _one_line_notes(warnings.showwarning)
                return fn(*args, **kwargs)
        except USER_ERRORS as err:
            if _STATE["debug"]:
                raise
            message = err.args[0] if isinstance(err, KeyError) and err.args else err
            typer.echo(f"error: {message}", err=True)
            raise typer.Exit(code=2) from None

    return wrapper


@app.callback()
def _main(
    debug: Annotated[bool, typer.Option("--debug", help="Show full tracebacks.")] = False,
) -> None:
    _STATE["debug"] = debug


@app.command()
@_user_errors
def data(
    size: Annotated[str, typer.Option(help="Corpus size: tiny, small, full, tiny+espeak or small+espeak.")] = "tiny",
    seed: Annotated[int, typer.Option(help="Random seed (same seed, byte-identical corpus).")] = 0,
    cache_dir: Annotated[
        Path, typer.Option(help="Where the corpus and its fitted tokenizers are cached.")
    ] = Path(".cache/synthtalk"),
    tokens: Annotated[bool, typer.Option(help="Also fit the token streams A and B.")] = True,
    metadata: Annotated[
        Path | None, typer.Option(help="Write the corpus metadata (clips, speakers) as JSON here.")
    ] = None,
    out: Annotated[
        Path | None, typer.Option(help="Also write the corpus as a dataset folder in the generic layout "
                                       "(wav + npz + tokens + metadata.csv), ready for `jaxtalk prepare`.")
    ] = None,
    overwrite: _OVERWRITE = False,
) -> None:
    """Generate (or load from cache) the built-in SynthTalk corpus and print a summary."""
    from jaxtalk.commands.corpus import CorpusOptions, make_corpus

    make_corpus(CorpusOptions(size=size, seed=seed, cache_dir=cache_dir, tokens=tokens, metadata=metadata, out=out,
                              overwrite=overwrite), echo=typer.echo)


@app.command()
@_user_errors
def demo(
    out: Annotated[Path, typer.Option(help="Output folder (checkpoint, video, plots, report).")] = Path("jaxtalk-demo"),
    audio: Annotated[
        Path | None, typer.Option(help="Also animate your own speech file (WAV/FLAC, any rate, mono or stereo).")
    ] = None,
    size: Annotated[str, typer.Option(help="SynthTalk size: small+espeak+mic (eSpeak NG voices and the source-filter "
                                            "voice, as real microphones record them), small+mic, small (clean "
                                            "sound), or tiny... for a quick look.")] = "small+espeak+mic",
    steps: Annotated[int, typer.Option(help="Training steps of the small TokTalk model.")] = DemoOptions.train_steps,
    seed: Annotated[int, typer.Option(help="Corpus and training seed.")] = 0,
    sample_steps: Annotated[
        int, typer.Option(help="Euler steps of the streamed clip (1 = the posterior mean).")
    ] = DemoOptions.sample_steps,
    retrain: Annotated[bool, typer.Option(help="Ignore an existing checkpoint and retrain.")] = False,
    sweep: Annotated[bool, typer.Option(help="Run the chunk size x Euler steps sweep.")] = True,
    render: Annotated[bool, typer.Option(help="Write the mp4 and GIF.")] = True,
    progress: Annotated[bool, typer.Option(help="Show the training progress bar.")] = True,
    overwrite: _OVERWRITE = False,
) -> None:
    """Train TokTalk on SynthTalk, stream a held-out clip, and write video, plots and a report."""
    from jaxtalk.demo import DemoOptions, run_demo

    options = DemoOptions(out_dir=out, size=size, seed=seed, train_steps=steps, sample_steps=sample_steps, retrain=retrain,
                          audio=audio, sweep=sweep, render=render, progress=progress, overwrite=overwrite)
    result = run_demo(options, echo=typer.echo)
    from jaxtalk.benchmarking import format_table

    typer.echo(format_table(result.quality, title="quality on the held-out clip"))
    typer.echo(f"done in {result.wall_s:.1f} s; outputs in {result.out_dir.resolve()}")
    for name, path in result.files.items():
        typer.echo(f"  {name:15s} {path}")
    typer.echo(f"play the animation with its audio in a browser: jaxtalk view {result.out_dir}")


_MODEL_HELP = ("Model: toktalk, ats (FreeTalk landmarks), stm (FreeTalk sparse-to-mesh), timar or dualtalk (TIMAR's "
               "non-causal baseline).")


def _echo_table(rows: list[dict[str, Any]], title: str) -> None:
    from jaxtalk.benchmarking import format_table

    typer.echo(format_table(rows, title=title))


@app.command()
@_user_errors
def train(
    model: Annotated[str, typer.Argument(help=_MODEL_HELP)],
    data: Annotated[
        str | None, typer.Option(help="Prepared dataset folder (`jaxtalk prepare`), or synthtalk:SIZE[:SEED]. "
                                      "Default synthtalk:tiny, or the run's own when resuming.")
    ] = None,
    out: Annotated[Path | None, typer.Option(help="Run folder (run.json + checkpoint/); default runs/MODEL.")] = None,
    preset: Annotated[
        str | None, typer.Option(help="Config preset: small, paper (tiny for toktalk). Default small, or the run's own.")
    ] = None,
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", help="Override a config field or training setting, KEY=VALUE (repeatable), e.g. "
                                   "--set sample_steps=5 --set lr=5e-4 --set ema_decay=0.999 --set window_frames=50."),
    ] = None,
    steps: Annotated[int, typer.Option(help="Train until this many optimiser steps in total.")] = 1000,
    seed: Annotated[int, typer.Option(help="Initialisation and data-order seed.")] = 0,
    cache_dir: Annotated[Path, typer.Option(help="Where synthtalk: data is prepared.")] = Path(".cache/prepared"),
    features: Annotated[
        str | None, typer.Option(help="Speech front end of ats, timar and dualtalk: logmel, or hubert:PATH / "
                                      "wav2vec2:PATH (a local Hugging Face folder: config.json + model.safetensors). "
                                      "synthtalk: data is prepared with it once, into its own folder under "
                                      "--cache-dir; a prepared folder must have been prepared with it. Default "
                                      "logmel, the folder's own, or the run's own when resuming.")
    ] = None,
    resume: Annotated[bool, typer.Option(help="Continue the run in --out if there is one.")] = True,
    progress: Annotated[bool, typer.Option(help="Show the progress bar.")] = True,
    data_parallel: Annotated[
        bool, typer.Option(help="Shard each batch over all local devices (jax.sharding); batch must divide.")
    ] = False,
    distributed: Annotated[
        bool, typer.Option(help="Several hosts: jax.distributed.initialize() (JAXTALK_COORDINATOR, "
                                "JAXTALK_NUM_PROCESSES, JAXTALK_PROCESS_ID) and the global device mesh.")
    ] = False,
    profile: Annotated[
        str | None, typer.Option(help="START:STOP: write a jax.profiler trace of those steps (1-based, both included) to "
                                      "OUT/profile, for Perfetto or TensorBoard.")
    ] = None,
    init: Annotated[
        Path | None, typer.Option(help="Fine-tune: start from this run's parameters, config and normaliser (a trained "
                                       "run or one made by `jaxtalk convert`).")
    ] = None,
    real_voice: Annotated[
        Path | None, typer.Option(help="TokTalk: a folder of real recordings (.wav, .flac), each optionally with its "
                                       "tracked motion (STEM.npz), as for `jaxtalk eval --real-voice`: every "
                                       "evaluation also streams the first 8 at 1 sampler step in the run's default "
                                       "style and records real_corr, real_loudness_corr, real_best_lag and "
                                       "real_silence_minus_rest.")
    ] = None,
    select: Annotated[
        str | None, typer.Option(help="TokTalk: the metric the best checkpoint (checkpoint/best) is chosen by: LVE_mm2 "
                                      "(the lowest streamed lip error on val clips) or real_corr (the highest, needs "
                                      "--real-voice with tracked motion). Default LVE_mm2, or the run's own.")
    ] = None,
) -> None:
    """Train a model on a prepared dataset with checkpoints; run again with more --steps to continue exactly."""
    from jaxtalk.commands.training import TrainOptions, train_run
    from jaxtalk.train.observers import parse_step_range

    opts = TrainOptions(model=model, out_dir=out or Path("runs") / model, data=data, preset=preset,
                        overrides=tuple(set_ or ()), steps=steps, seed=seed, cache_dir=cache_dir, features=features,
                        resume=resume,
                        progress=progress, data_parallel=data_parallel, distributed=distributed,
                        profile=None if profile is None else parse_step_range(profile), init=init,
                        real_voice=real_voice, select=select)
    summary = train_run(opts, echo=typer.echo)
    if summary.interrupted:
        typer.echo(f"error: interrupted at step {summary.step}; it is checkpointed in {summary.run_dir / 'checkpoint'}: "
                   "run the same command again to resume", err=True)
        raise typer.Exit(code=130)
    loss = "-" if summary.final_loss is None else f"{summary.final_loss:.4f}"
    val = "" if summary.val_loss is None else f", validation loss {summary.val_loss:.4f}"
    typer.echo(f"{model}: step {summary.start_step} -> {summary.step} on {summary.examples} windows, "
               f"final loss {loss}{val}, {summary.wall_s:.1f} s; run in {summary.run_dir}")


@app.command()
@_user_errors
def prepare(
    source: Annotated[str, typer.Argument(help="Dataset folder (DualTalk, VOCASET or generic layout) or "
                                               "synthtalk:SIZE[:SEED].")],
    out: Annotated[Path, typer.Option(help="Prepared dataset folder (shards + manifest.json + report.csv).")],
    features: Annotated[
        str, typer.Option(help="Audio features: logmel, or hubert:PATH / wav2vec2:PATH (a local Hugging Face folder); "
                               "wav2vec2+recording:PATH normalises each recording's waveform as a whole, as the "
                               "public TIMAR loader does (offline evaluation).")
    ] = "logmel",
    tokens: Annotated[
        str, typer.Option(help="TokTalk token stream: auto, clip (the clips' .tokens.npy), vq (fitted on the "
                               "training split) or none.")
    ] = "auto",
    layout: Annotated[str | None, typer.Option(help="Force a layout: dualtalk, vocaset or generic.")] = None,
    min_seconds: Annotated[float, typer.Option(help="Shortest usable clip in seconds.")] = 1.0,
    split_seed: Annotated[int, typer.Option(help="Seed of the speaker-disjoint splits where the layout has none.")] = 0,
    strict: Annotated[bool, typer.Option(help="Stop at the first bad clip (default: skip it and report).")] = False,
    progress: Annotated[bool, typer.Option(help="Show the progress bar.")] = True,
    overwrite: _OVERWRITE = False,
) -> None:
    """Check every clip of a dataset and compute each model's inputs once; bad clips are skipped and reported."""
    from jaxtalk.data.prepare import PrepareSettings
    from jaxtalk.data.prepare import prepare as run_prepare
    from jaxtalk.data.sources import open_source

    settings = PrepareSettings(audio=features, tokens=tokens, min_frames=max(int(round(min_seconds * 25)), 1),
                               split_seed=split_seed)
    run_prepare(open_source(source, layout=layout), out, settings, strict=strict, progress=progress, echo=typer.echo,
                overwrite=overwrite)


def _sample_options(run: Path, input_: Path, out: Path | None, style: Path | None, partner: Path | None,
                    cfg_scale: float | None, sample_steps: int | None, temperature: float | None, seed: int, best: bool,
                    overwrite: bool) -> Any:
    from jaxtalk.commands.inference import SampleOptions

    return SampleOptions(run_dir=run, input=input_, out=out, style=style, partner=partner, cfg_scale=cfg_scale,
                         sample_steps=sample_steps, temperature=temperature, seed=seed, best=best, overwrite=overwrite)


_RUN = Annotated[Path, typer.Argument(help="Run folder written by `jaxtalk train` (toktalk or timar; ats with --stm).")]
_INPUT = Annotated[Path, typer.Argument(help="Speech: WAV/FLAC (any rate, mono or stereo), or a .npy of token "
                                              "embeddings (tokens, width) for TokTalk.")]
_OUT = Annotated[Path | None, typer.Option(help="Output .npz, replaced if it exists (default: INPUT_params.npz beside "
                                                 "the input, which needs --overwrite to replace a file).")]
_STYLE = Annotated[Path | None, typer.Option(help="TokTalk: reference motion .npz for the speaking style.")]
_PARTNER = Annotated[Path | None, typer.Option(help="TIMAR: the partner's audio (default: silence).")]
_CFG = Annotated[float | None, typer.Option(help="Guidance weight w of (1 + w) cond - w uncond: 0 = none, -1 = "
                                                 "unconditional (every model; the default is the run's).")]
def _step_counts(values: list[str]) -> tuple[int, ...]:
    """``eval --sample-steps``: one whole number per use (as ``sample`` and ``stream`` take it)."""
    for value in values:
        if "," in value:
            raise ValueError(f"--sample-steps takes one number per use, as in sample and stream; for several, "
                             f"repeat it: {' '.join('--sample-steps ' + v.strip() for v in value.split(','))}")
    try:
        return tuple(int(v) for v in values)
    except ValueError:
        raise ValueError(f"--sample-steps must be a whole number of steps, got {values!r}") from None


_SAMPLE_STEPS = Annotated[int | None, typer.Option("--sample-steps", help="Sampler steps: Euler (TokTalk) or DDIM / DDPM "
                                                                           "(ATS, TIMAR) (default: the model's).")]
_TEMPERATURE = Annotated[float | None, typer.Option(help="Scale of the sampler's noise, >= 0 (TokTalk: the starting "
                                                         "noise, default the model's; TIMAR: MAR's temperature, default "
                                                         "1); below 1 trades diversity for accuracy.")]
_SEED = Annotated[int, typer.Option(help="Noise seed.")]
_BEST = Annotated[bool, typer.Option(help="Use the run's best-validated checkpoint (lowest selection metric: TokTalk's "
                                            "streamed lip error, else validation loss).")]


def _frames(count: int) -> str:
    """``"126 frames (5.04 s)"``: the duration of the frames written, at 25 fps."""
    return f"{count} frames ({count / 25:.2f} s)"


@app.command()
@_user_errors
def sample(
    run: _RUN, input_: _INPUT, out: _OUT = None, style: _STYLE = None, partner: _PARTNER = None,
    cfg_scale: _CFG = None, sample_steps: _SAMPLE_STEPS = None, temperature: _TEMPERATURE = None, seed: _SEED = 0,
    best: _BEST = False, overwrite: _OVERWRITE = False,
    stm: Annotated[Path | None, typer.Option(help="FreeTalk: the STM run that maps an ATS run's landmarks onto --mesh.")] = None,
    mesh: Annotated[Path | None, typer.Option(help="FreeTalk: the face mesh to animate (OBJ, PLY, GLB/GLTF, OFF, "
                                                   "STL).")] = None,
    emotion: Annotated[str | None, typer.Option(help="FreeTalk: an emotion of the ATS run's vocabulary (default "
                                                     "neutral).")] = None,
    intensity: Annotated[float | None, typer.Option(help="FreeTalk: emotion intensity, continuous in [1, levels] "
                                                         "(default 1).")] = None,
    units: Annotated[str | None, typer.Option(help="FreeTalk: the mesh's units, m|dm|cm|mm|um (default: from its size).")] = None,
    landmarks: Annotated[Path | None, typer.Option(help="FreeTalk: the mesh's 68 landmarks, (68, 3) positions or (68,) "
                                                        "vertex indices (.npy/.txt), to guide the alignment.")] = None,
) -> None:
    """Animate a speech file with a trained model; writes head parameters (.npz, 25 fps), or with an ATS
    run, --stm and --mesh, the mesh's vertices (.npy, 25 fps, the mesh's own units and frame)."""
    from jaxtalk.commands.inference import MeshOptions, animate_run, sample_run

    opts = _sample_options(run, input_, out, style, partner, cfg_scale, sample_steps, temperature, seed, best, overwrite)
    freetalk = {"--emotion": emotion, "--intensity": intensity, "--units": units, "--landmarks": landmarks}
    if stm is not None or mesh is not None:
        if stm is None or mesh is None:
            raise ValueError("FreeTalk needs both --stm RUN_STM and --mesh FILE")
        given = {k.lstrip("-"): v for k, v in freetalk.items() if v is not None}
        result = animate_run(opts, MeshOptions(stm_run=stm, mesh=mesh, **given), echo=typer.echo)
        typer.echo(f"{_frames(result.params.shape[0])} of {result.params.shape[1]} vertices written to {result.path}; "
                   f"render: jaxtalk render {result.path} --faces {mesh} --audio {input_}")
        return
    result = sample_run(dataclasses.replace(opts, mesh_options=tuple(k for k, v in freetalk.items() if v is not None)))
    typer.echo(f"{_frames(result.params.shape[0])} written to {result.path}")


@app.command()
@_user_errors
def stream(run: _RUN, input_: _INPUT, out: _OUT = None, style: _STYLE = None, partner: _PARTNER = None,
           cfg_scale: _CFG = None, sample_steps: _SAMPLE_STEPS = None, temperature: _TEMPERATURE = None, seed: _SEED = 0,
           best: _BEST = False, overwrite: _OVERWRITE = False) -> None:
    """Animate a speech file chunk by chunk as a live stream would, printing each chunk's latency."""
    from jaxtalk.commands.inference import stream_run

    result = stream_run(_sample_options(run, input_, out, style, partner, cfg_scale, sample_steps, temperature, seed, best,
                                        overwrite), echo=typer.echo)
    typer.echo(f"{_frames(result.params.shape[0])} written to {result.path}")


def _scorings(text: str) -> tuple[str, ...]:
    """``--scoring``: one of the evaluation's scorings, or ``both``."""
    from jaxtalk.metrics.evaluation import SCORINGS

    if text == "both":
        return tuple(SCORINGS)
    if text not in SCORINGS:
        raise ValueError(f"--scoring must be {', '.join(SCORINGS)} or both, got {text!r}")
    return (text,)


@app.command(name="eval")
@_user_errors
def eval_(
    run: Annotated[Path, typer.Argument(help="Run folder written by `jaxtalk train` (toktalk, timar, dualtalk, ats or stm).")],
    data: Annotated[
        str | None, typer.Option(help="Prepared dataset folder or synthtalk:SIZE (default: the run's own data); its "
                                      "features must be the run's.")
    ] = None,
    split: Annotated[str | None, typer.Option(help="Split of the data: train, val, test or ood (default test).")] = None,
    max_clips: Annotated[int, typer.Option(help="At most this many clips (TIMAR: conversation sides; --real-voice: "
                                                "recordings).")] = 8,
    seed: _SEED = 0,
    json_out: Annotated[Path | None, typer.Option("--json", help="Also write the report as JSON here (replaced if it "
                                                               "exists; never a file of the run).")] = None,
    flame: Annotated[
        Path | None, typer.Option(help="TokTalk: FLAME 2020 model file to pose on instead of the built-in face "
                                       "(FLAME_masks.pkl beside it gives the lip and upper-face regions).")
    ] = None,
    cache_dir: Annotated[Path, typer.Option(help="Where synthtalk: data is prepared.")] = Path(".cache/prepared"),
    best: Annotated[bool, typer.Option(help="Evaluate the best-validated checkpoint (checkpoint/best).")] = False,
    sample_steps: Annotated[
        list[str] | None, typer.Option("--sample-steps", help="TokTalk: Euler steps, one table each; repeat it for "
                                                               "several: --sample-steps 1 --sample-steps 10 (default "
                                                               "the run's sample_steps).")
    ] = None,
    offline: Annotated[bool, typer.Option(help="TokTalk: also sample whole clips offline (full attention).")] = False,
    temperature: _TEMPERATURE = None,
    scoring: Annotated[
        str, typer.Option(help="TIMAR, DualTalk baseline: how conversation sides are scored: jaxtalk (whole sides, "
                               "the tail after the last whole turn repeating it), public (as the public TIMAR "
                               "code's calc_metric.py: whole seconds, cut to the shortest) or both.")
    ] = "jaxtalk",
    real_voice: Annotated[
        Path | None, typer.Option(help="TokTalk, TIMAR: instead of prepared data, a folder of real recordings (.wav, "
                                       ".flac; any rate), each optionally with its speaker's tracked motion beside it "
                                       "(STEM.npz: DualTalk's pose (T, 6) or jaxtalk's params (T, 56), 25 fps). Each "
                                       "is streamed as `jaxtalk stream` does and its predicted jaw measured against "
                                       "the tracked jaw (corr, best lag: positive = late), the loudness follower and "
                                       "the loudness; jaw in silence vs speech, and the rest jaw on 3 s of silence.")
    ] = None,
) -> None:
    """Score a trained run on a split of prepared data, next to the mean pose (and the oracle where known),
    or with --real-voice on real recordings.

    TokTalk: LVE, MVE, FDD, MOD, jitter of vertices. TIMAR and the DualTalk baseline: FD, P-FD, MSE, SID,
    rPCC per group (exp, jaw, pose) in the published scaling. ATS: landmark LVE, mean error, jitter. STM: vertex errors on
    the run's meshes from the true landmarks. --real-voice (TokTalk, TIMAR): the predicted jaw opening against the
    tracked jaw and the speech's loudness, per recording (docs/evaluation.md).
    """
    from jaxtalk.commands.evaluation import EvalOptions, evaluate_run
    from jaxtalk.files import Output, claim_outputs

    if json_out is not None:
        # Every file inside the run folder is an input of eval (its history, checkpoints, assets).
        claim_outputs([Output(json_out, named=True)], inputs=[run, flame, real_voice])
    steps = _step_counts(sample_steps or [])
    report = evaluate_run(EvalOptions(run_dir=run, data=data, split=split, max_clips=max_clips, seed=seed,
                                      flame=flame, cache_dir=cache_dir, best=best, sample_steps=steps,
                                      offline=offline, temperature=temperature, real_voice=real_voice,
                                      scoring=_scorings(scoring)),
                           echo=typer.echo)
    for table in report.tables:
        _echo_table(table.rows, table.title)
    if json_out is not None:
        from jaxtalk.files import atomic_write_json

        atomic_write_json(json_out, report.to_dict())


@app.command()
@_user_errors
def bench(
    models: Annotated[
        list[str] | None, typer.Option("--model", help="Sampling: toktalk, timar or freetalk; with --train also ats, "
                                                       "stm and dualtalk (freetalk = ats + stm). Repeatable; default all.")
    ] = None,
    paper: Annotated[bool, typer.Option(help="Also the paper-size presets (minutes of compilation).")] = False,
    repeats: Annotated[int, typer.Option(help="Timed runs per case (median).")] = 5,
    train: Annotated[bool, typer.Option("--train", help="Also time each model's train step in a real recipe run: compiled "
                                                        "step, FLOPs, fraction of peak, compile time, memory, loader "
                                                        "time per batch and the loop's host overhead.")] = False,
    preset: Annotated[list[str] | None, typer.Option("--preset", help="With --train: the presets to train, small or paper "
                                                                     "(repeatable; default small, and paper with "
                                                                     "--paper).")] = None,
    sampling: Annotated[bool, typer.Option(help="With --train: also the sampling tables of the chosen models.")] = True,
    data: Annotated[str, typer.Option(help="With --train: the prepared data the models train on (a folder or "
                                           "synthtalk:SIZE).")] = "synthtalk:tiny",
    cache_dir: Annotated[Path, typer.Option(help="Where synthtalk: data is prepared.")] = Path(".cache/prepared"),
    set_: Annotated[list[str] | None, typer.Option("--set", help="With --train: a config field or training setting for "
                                                                "every trained model, KEY=VALUE (repeatable), e.g. "
                                                                "--set batch_size=4.")] = None,
    loop_steps: Annotated[int, typer.Option(help="With --train: loop steps timed for the host overhead.")] = 10,
    paper_batch: Annotated[int | None, typer.Option(help="With --train: the batch of the paper rows (default the "
                                                         "recipe's, e.g. TIMAR's 32: minutes per step on a CPU).")] = None,
    profile: Annotated[Path | None, typer.Option(help="With --train: write a jax.profiler trace of each row's timed train "
                                                      "steps to DIR/MODEL-PRESET (Perfetto or TensorBoard).")] = None,
    out: Annotated[Path | None, typer.Option(help="JSON with every row and the machine (replaced if it exists; default "
                                                  "experiments/results/bench_all.json, which needs --overwrite to "
                                                  "replace a file).")] = None,
    overwrite: _OVERWRITE = False,
) -> None:
    """Speed tables of all three models in one run, with the matmul peak and the achieved fraction; --train
    adds each model's training step."""
    from jaxtalk.commands.benchmarking import BenchOptions, run_bench

    opts = BenchOptions(models=tuple(models or ()), paper=paper, repeats=repeats, train=train, presets=tuple(preset or ()),
                        sampling=sampling, data=data, cache_dir=cache_dir, overrides=tuple(set_ or ()),
                        loop_steps=loop_steps, paper_batch=paper_batch, profile=profile, out=out, overwrite=overwrite)
    run_bench(opts, echo=typer.echo)


@app.command()
@_user_errors
def render(
    input_: Annotated[Path, typer.Argument(help="Head parameters .npz (params or params56) or vertices .npy.")],
    out: Annotated[Path | None, typer.Option(help="Output .mp4 (with audio) or .gif, replaced if it exists (default "
                                                  "render.mp4, which needs --overwrite to replace a file).")] = None,
    audio: Annotated[Path | None, typer.Option(help="Audio track (default: the audio stored in the .npz).")] = None,
    compare: Annotated[Path | None, typer.Option(help="A second file drawn beside the first.")] = None,
    faces: Annotated[Path | None, typer.Option(help="Triangles of vertices of another mesh: an (F, 3) .npy, or the mesh file "
                                                     "they were animated on (OBJ, PLY, GLB/GLTF).")] = None,
    flame: Annotated[Path | None, typer.Option(help="FLAME 2020 model file to pose parameters on.")] = None,
    size: Annotated[int, typer.Option(help="Panel size in pixels.")] = 256,
    captions: Annotated[bool, typer.Option(help="Caption each panel with its file name.")] = True,
    overwrite: _OVERWRITE = False,
) -> None:
    """Render parameters or vertices to an mp4 (with audio) or GIF, optionally side by side."""
    from jaxtalk.commands.rendering import RenderOptions, render_file

    path = render_file(RenderOptions(input=input_, out=out, audio=audio, compare=compare, faces=faces, flame=flame,
                                     size=size, captions=captions, overwrite=overwrite))
    typer.echo(f"written {path}")


@app.command()
@_user_errors
def export(
    input_: Annotated[Path, typer.Argument(help="Head parameters .npz (params or params56) or vertices .npy.")],
    out: Annotated[Path | None, typer.Option(help="Output binary glTF (.glb), replaced if it exists (default anim.glb, "
                                                  "which needs --overwrite to replace a file); the audio goes beside "
                                                  "it as OUT.glb.wav.")] = None,
    audio: Annotated[Path | None, typer.Option(help="Audio to write beside it (default: the audio stored in the .npz).")] = None,
    faces: Annotated[Path | None, typer.Option(help="Triangles of vertices of another mesh: an (F, 3) .npy, or the mesh file "
                                                     "they were animated on (OBJ, PLY, GLB/GLTF).")] = None,
    flame: Annotated[Path | None, typer.Option(help="FLAME 2020 model file to write parameters on.")] = None,
    fps: Annotated[float, typer.Option(help="Frame rate of a vertex sequence (an .npz states its own).")] = 25.0,
    max_error_mm: Annotated[float, typer.Option(help="Largest vertex error of a vertex sequence's morph basis, mm.")] = 0.1,
    overwrite: _OVERWRITE = False,
) -> None:
    """Export motion as a glTF 2.0 animation (morph targets + jaw/neck skin) that 3D tools and browsers play."""
    from jaxtalk.commands.exporting import ExportOptions, export_file

    result = export_file(ExportOptions(input=input_, out=out, audio=audio, faces=faces, flame=flame, fps=fps,
                                       max_error_mm=max_error_mm, overwrite=overwrite))
    typer.echo(f"written {result.summary.describe()}")
    typer.echo(f"written {result.audio}" if result.audio is not None else "no audio: pass --audio to write it beside the .glb")


@app.command(name="export-model")
@_user_errors
def export_model(
    run: Annotated[Path, typer.Argument(help="Run folder written by `jaxtalk train` (toktalk).")],
    out: Annotated[Path, typer.Option(help="Folder to write: new, empty, or an earlier export (with --overwrite).")],
    format_: Annotated[str, typer.Option("--format", help="Model file format.")] = "onnx",
    style: _STYLE = None, cfg_scale: _CFG = None, sample_steps: _SAMPLE_STEPS = None,
    temperature: _TEMPERATURE = None, best: _BEST = False,
    page: Annotated[bool, typer.Option(help="Write the browser page (three.js and onnxruntime-web from npm).")] = True,
    overwrite: Annotated[bool, typer.Option(help="Replace an earlier export in --out.")] = False,
) -> None:
    """Export the run's live stream to run without Python: ONNX graphs, a manifest, a reference host (host.py)
    and a static page that animates the microphone in the browser."""
    from jaxtalk.commands.portable import ExportModelOptions, export_model_run

    export_model_run(ExportModelOptions(run_dir=run, out=out, format=format_, style=style, cfg_scale=cfg_scale,
                                        sample_steps=sample_steps, temperature=temperature, best=best, page=page,
                                        overwrite=overwrite), echo=typer.echo)


@app.command()
@_user_errors
def retarget(
    motion: Annotated[Path, typer.Argument(help="Head parameters .npz (params or params56) or vertices .npy (FreeTalk's "
                                                "output).")],
    rig: Annotated[str, typer.Option(help="Blendshape rig: a .glb/.gltf with morph targets, a folder of OBJ shapes with "
                                          "a neutral.obj, or 'builtin' (the built-in 52-shape ARKit rig).")] = "builtin",
    out: Annotated[Path | None, typer.Option(help="Output .glb, replaced if it exists (default retarget.glb, which needs "
                                                  "--overwrite to replace a file); OUT.csv (Live Link Face), OUT.json and "
                                                  "the audio OUT.glb.wav go beside it, and like the default they replace "
                                                  "an existing file only with --overwrite.")] = None,
    audio: Annotated[Path | None, typer.Option(help="Audio to write beside the .glb (default: the audio stored in the "
                                                    ".npz).")] = None,
    mesh: Annotated[Path | None, typer.Option(help="The mesh file (OBJ, PLY, GLB/GLTF) a vertex sequence was animated "
                                                   "on, when it is neither a built-in face nor the rig's mesh.")] = None,
    flame: Annotated[Path | None, typer.Option(help="FLAME 2020 model file the parameters are posed on.")] = None,
    units: Annotated[str | None, typer.Option(help="Units of the rig or mesh file (m, dm, cm, mm, um; default: from "
                                                   "its size).")] = None,
    landmarks: Annotated[Path | None, typer.Option(help="The rig file's 68 landmarks, (68, 3) positions in its units or "
                                                        "(68,) vertex indices (.npy/.txt), to register it by (as "
                                                        "sample's --landmarks align a mesh).")] = None,
    fps: Annotated[float, typer.Option(help="Frame rate of a vertex sequence (an .npz states its own).")] = 25.0,
    smoothness: Annotated[float, typer.Option(help="Temporal smoothness of the weights (0: frames independent).")] = 0.01,
    l1: Annotated[float, typer.Option(help="L1 penalty (sparser weights).")] = 0.0,
    l2: Annotated[float, typer.Option(help="L2 penalty.")] = 1e-4,
    symmetry: Annotated[float, typer.Option(help="Tie of left/right shape pairs (found by name).")] = 0.0,
    overwrite: _OVERWRITE = False,
) -> None:
    """Retarget motion onto a blendshape rig (ARKit names): an animated .glb, a Live Link Face CSV and JSON."""
    from jaxtalk.commands.retargeting import RetargetOptions, retarget_file

    retarget_file(RetargetOptions(motion=motion, rig=rig, out=out, audio=audio, mesh=mesh, flame=flame, units=units,
                                  landmarks=landmarks, fps=fps, smoothness=smoothness, l1=l1, l2=l2, symmetry=symmetry,
                                  overwrite=overwrite),
                  echo=typer.echo)


@app.command()
@_user_errors
def view(
    folder: Annotated[Path | None, typer.Argument(help="Folder of exported .glb files (and the NAME.glb.wav beside "
                                                       "each); not with --live.")] = None,
    port: Annotated[int, typer.Option(help="Port on 127.0.0.1 (0: any free one).")] = 8000,
    open_browser: Annotated[bool, typer.Option("--open", help="Open the page in the default browser.")] = False,
    live: Annotated[bool, typer.Option("--live", help="Stream the microphone (or a file) to `jaxtalk serve` and drive "
                                                      "the face with its frames, showing the latency.")] = False,
    server: Annotated[str, typer.Option(help="With --live: the `jaxtalk serve` to stream to.")] = "ws://127.0.0.1:8765",
) -> None:
    """Play exported animations in sync with their audio on a local web page (three.js, installed by npm), or
    with --live animate the face from the microphone through a running `jaxtalk serve`."""
    from jaxtalk.viewer import start_live_server, start_server

    if live:
        if folder is not None:
            raise ValueError("--live streams to a server and plays no folder: drop FOLDER, or drop --live")
        viewer = start_live_server(server, port=port)
        typer.echo(f"jaxtalk view --live: {viewer.url} streams to {server} (start it with `jaxtalk serve RUN`; "
                   "Ctrl-C stops)")
    else:
        if folder is None:
            raise ValueError("name a FOLDER of exported .glb files to play, or pass --live to stream to `jaxtalk serve`")
        viewer = start_server(folder, port=port)
        typer.echo(f"jaxtalk view: {viewer.url} (Ctrl-C stops)")
    if open_browser:
        import webbrowser

        webbrowser.open(viewer.url)
    try:
        viewer.thread.join()
    except KeyboardInterrupt:
        viewer.close()


@app.command()
@_user_errors
def serve(
    run: Annotated[Path, typer.Argument(help="Run folder written by `jaxtalk train` (toktalk).")],
    host: Annotated[str, typer.Option(help="Interface to listen on (127.0.0.1: this machine only).")] = "127.0.0.1",
    port: Annotated[int, typer.Option(help="TCP port (0: any free one).")] = 8765,
    style: _STYLE = None, cfg_scale: _CFG = None, sample_steps: _SAMPLE_STEPS = None, temperature: _TEMPERATURE = None,
    best: _BEST = False,
    max_clients: Annotated[int, typer.Option(help="Clients served at once; one more is told the server is busy.")] = 8,
    max_chunk_s: Annotated[float, typer.Option(help="Longest audio message a client may send, in seconds.")] = 1.0,
    live_link: Annotated[str | None, typer.Option(help="Send every client's ARKit curves as Live Link Face UDP packets "
                                                       "to HOST:PORT (or PORT on 127.0.0.1; Unreal listens on 11111).")] = None,
    allow_origin: Annotated[list[str] | None, typer.Option(help="A web page origin allowed to connect besides this "
                                                                 "machine's own (http://localhost:*): http(s)://HOST or "
                                                                 "http(s)://HOST:PORT, PORT * for any; repeatable.")] = None,
) -> None:
    """Animate live speech over WebSocket: clients send 16-kHz PCM, each chunk's frames come back (params, glTF
    morph weights or ARKit weights) with their timestamps and the compute time (protocol: docs/serve.md)."""
    from jaxtalk.commands.serving import ServeCommandOptions, serve_run

    running = serve_run(ServeCommandOptions(run_dir=run, host=host, port=port, style=style, cfg_scale=cfg_scale,
                                            sample_steps=sample_steps, temperature=temperature, best=best,
                                            max_clients=max_clients,
                                            max_chunk_s=max_chunk_s, live_link=live_link,
                                            origins=tuple(allow_origin or ())), echo=typer.echo)
    try:
        running.thread.join()
    except KeyboardInterrupt:
        running.close()


convert_app = typer.Typer(help="Convert another implementation's checkpoint into a jaxtalk run.", no_args_is_help=True)
app.add_typer(convert_app, name="convert")


@convert_app.command("timar")
@_user_errors
def convert_timar(
    checkpoint: Annotated[Path, typer.Argument(help="Checkpoint of the public TIMAR code (.pth with model, model_ema, "
                                                    "args), e.g. the released TIMAR.pth.")],
    out: Annotated[Path, typer.Option(help="Run folder to write.")],
    features: Annotated[str, typer.Option(help="Speech front end of the run's inputs, as `jaxtalk prepare --features` "
                                               "takes it: wav2vec2:PATH, the wav2vec2-large-960h-lv60-self folder.")],
    stats: Annotated[Path | None, typer.Option(help="The public code's stat_flame.json: the run's motion normaliser "
                                                    "(default: identity, as the public commands train).")] = None,
    ema: Annotated[bool, typer.Option("--ema/--no-ema", help="Convert the EMA weights (what the public evaluation "
                                                             "loads) or the raw ones.")] = True,
    overwrite: Annotated[bool, typer.Option(help="Replace an earlier conversion at --out (a folder holding an input "
                                                 "or a user's files is never replaced).")] = False,
) -> None:
    """Convert the public TIMAR code's checkpoint into a run that sample, stream and eval open (needs torch:
    pip install "jaxtalk[torch]")."""
    from jaxtalk.commands.converting import ConvertOptions, convert_timar_run

    report = convert_timar_run(ConvertOptions(checkpoint=checkpoint, out=out, features=features, stats=stats, ema=ema,
                                              overwrite=overwrite))
    for line in report.warnings:
        typer.echo(f"warning: {line}", err=True)
    for line in report.lines:
        typer.echo(line)


def main() -> None:
    """Console-script entry point."""
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
