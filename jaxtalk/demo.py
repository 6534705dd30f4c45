"""``jaxtalk demo``: the whole TokTalk pipeline on the built-in SynthTalk corpus, end to end.

Generate the corpus -> train the ``small`` TokTalk with its recipe on the prepared corpus, exactly as
``jaxtalk train toktalk --data synthtalk:SIZE:SEED`` does (checkpointed, resumable; the output folder
is the training run, so ``jaxtalk stream OUT speech.wav`` animates new speech with it) -> stream a
held-out clip chunk by chunk (per-chunk latency measured, compile excluded) -> compare with the
mean-pose baseline and the generator's oracle -> sweep chunk size x Euler steps (the paper's Table 5)
-> write parameters, an mp4 with audio (ground truth beside prediction), a GIF, the sweep plot, the
training curve and a Markdown report. A second run finds the finished run and the cached sweep and
finishes in seconds.

``--audio FILE`` animates the user's own speech (any rate, mono or stereo) with the trained model, and
the report measures how its jaw follows that speech (:func:`jaxtalk.metrics.speech_sync.speech_sync`:
the jaw in silence and in speech, at rest on digital silence, and against the recording's loudness).
"""

from __future__ import annotations

import dataclasses
import json
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from jaxtalk.files import atomic_savez, atomic_write_text

__all__ = ["DemoOptions", "DemoResult", "run_demo", "SWEEP_CHUNKS_S", "SWEEP_STEPS"]

# The paper's Table 5 grid: chunk {0.4, 0.8, 1.2} s x Euler steps {1, 5, 10, 20}.
SWEEP_CHUNKS_S = (0.4, 0.8, 1.2)
SWEEP_STEPS = (1, 5, 10, 20)


@dataclasses.dataclass(frozen=True)
class DemoOptions:
    """Settings of :func:`run_demo` (the CLI's options).

    Attributes:
        out_dir: output folder (created). It is also the model's training run (``run.json``,
            ``checkpoint/`` and the inference assets, as ``jaxtalk train`` writes them), so
            ``jaxtalk sample`` / ``jaxtalk stream`` take it as their RUN.
        size: SynthTalk size: "small+espeak+mic" (default: the ``small`` corpus with three speakers in
            four talking through eSpeak NG voices, as real microphones record it, so that the model also
            hears a user's own voice), "small+mic", "small" (clean studio sound), "tiny+espeak+mic" /
            "tiny" for a quick look.
        seed: corpus and training seed.
        train_steps: optimiser steps of the base model.
        batch_size: training windows per step.
        window_frames: frames per training window.
        learning_rate: peak AdamW learning rate.
        retrain: delete an existing run (checkpoint and ``run.json``) and cached results first.
        audio: the user's own audio file to animate (skips nothing else); the report gets its
            speech-sync row.
        chunk_frames: the model's streaming chunk in frames, a training setting too (the chunk
            attention mask and the streaming window are trained at this size).
        sample_steps: Euler steps of the streamed clip and of ``audio``. One step from pure noise is
            the model's posterior mean (smooth, lowest error); more steps add sampled detail that a
            model trained for minutes on 2 CPU cores has not learned well (the sweep shows both).
        sweep: run the chunk x steps sweep.
        render: write the mp4 and GIF.
        render_size: panel size in pixels.
        progress: show the training progress bar.
        cache_dir: where the SynthTalk corpus and its prepared copy (``synthtalk-SIZE-seedSEED``) are
            kept (default ``out_dir/cache``).
        overwrite: let the demo's outputs replace existing files in an ``out_dir`` that is not a
            previous demo's folder (a demo folder's own outputs are always updated).
    """

    out_dir: Path = Path("jaxtalk-demo")
    overwrite: bool = False
    size: str = "small+espeak+mic"
    seed: int = 0
    train_steps: int = 400
    sample_steps: int = 1
    chunk_frames: int = 10
    batch_size: int = 16
    window_frames: int = 100
    learning_rate: float = 2e-3
    retrain: bool = False
    audio: Path | None = None
    sweep: bool = True
    render: bool = True
    render_size: int = 256
    progress: bool = True
    cache_dir: Path | None = None


@dataclasses.dataclass
class DemoResult:
    """What the demo measured and wrote.

    Attributes:
        out_dir: the output folder.
        files: name -> path of every file written.
        quality: rows of the quality table (model, mean pose, oracle).
        latency: streaming latency of the held-out clip.
        sweep: rows of the chunk x steps table.
        trained: whether this run trained (False: loaded from the checkpoint).
        wall_s: seconds the whole run took.
        user_sync: with ``--audio``: the speech-sync row of the user's recording (None without).
    """

    out_dir: Path
    files: dict[str, Path]
    quality: list[dict[str, Any]]
    latency: dict[str, float]
    sweep: list[dict[str, Any]]
    trained: bool
    wall_s: float
    user_sync: dict[str, Any] | None = None


def model_config(chunk_frames: int = 10, sample_steps: int = 10):
    """The demo model's config at a chunk size (frames) and Euler step count (inference settings)."""
    from jaxtalk.models.toktalk import TokTalkConfig

    # Left context: two chunks (at least 20 frames), so latency is bounded whatever the chunk.
    return TokTalkConfig.small(chunk_frames=chunk_frames, context_frames=max(20, 2 * chunk_frames),
                               sample_steps=sample_steps)


def _pick_clips(corpus: Any) -> tuple[int, int]:
    """A held-out monologue to show, and a reference clip of the same speaker for its style."""
    test = [i for i in corpus.split("test") if not corpus.clips[i].is_conversation] or corpus.split("test")
    clip = max(test, key=lambda i: corpus.clips[i].num_frames)
    same = [j for j in corpus.split("test") if j != clip and corpus.clips[j].speaker == corpus.clips[clip].speaker]
    return clip, (same[0] if same else clip)


DEMO_MODEL = "toktalk"
DEMO_PRESET = "small"


def data_spec(options: DemoOptions) -> str:
    """The demo's training data: SynthTalk at the demo's size and seed (prepared once under the cache)."""
    return f"synthtalk:{options.size}:{options.seed}"


def cache_dir(options: DemoOptions) -> Path:
    """Where the demo's SynthTalk corpus and its prepared copy live."""
    return Path(options.cache_dir) if options.cache_dir is not None else Path(options.out_dir) / "cache"


def train_overrides(options: DemoOptions) -> tuple[str, ...]:
    """``--set`` items that turn the ``small`` preset and TokTalk's recipe defaults into the demo's
    model (:func:`model_config`) and training settings: only what differs from them.

    The run's ``sample_steps`` is the demo's (``--sample-steps``, 1 by default): what ``jaxtalk stream``
    on the demo folder uses, and the step count the run's validation streams and selects by (one
    step: a fifth of the validation time of the preset's 1 and 10)."""
    from jaxtalk.models.toktalk import TokTalkConfig
    from jaxtalk.models.toktalk.recipe import DEFAULTS, default_window

    want, base = model_config(options.chunk_frames, options.sample_steps), TokTalkConfig.small()
    items = [f"{f.name}={getattr(want, f.name)}" for f in dataclasses.fields(want)
             if getattr(want, f.name) != getattr(base, f.name)]
    if options.learning_rate != DEFAULTS.lr:
        items.append(f"lr={options.learning_rate!r}")
    if options.batch_size != DEFAULTS.batch_size:
        items.append(f"batch_size={options.batch_size}")
    if options.window_frames != default_window(want):
        items.append(f"window_frames={options.window_frames}")
    return tuple(items)


def _history(run_dir: Path) -> list[dict]:
    """The loss curve the training loop wrote beside the run's checkpoints (empty when there is none)."""
    from jaxtalk.runs import checkpoint_dir
    from jaxtalk.train import read_history

    return [{"step": r["step"], "loss": r["loss"]} for r in read_history(checkpoint_dir(run_dir))
            if r.get("type") == "train" and r.get("loss") is not None]


@dataclasses.dataclass(frozen=True)
class DemoModel:
    """The model :func:`train_or_load` gives.

    Attributes:
        params: the EMA parameters.
        history: the training-loss curve (``step``, ``loss`` rows, from the run's ``history.jsonl``;
            empty when the loop wrote none).
        trained: whether any training ran in this call.
        step: the step of the checkpoint the parameters come from.
        validated: whether the run's validation chose that checkpoint (False: the newest, for data
            without a validation split).
    """

    params: Any
    history: list[dict]
    trained: bool
    step: int
    validated: bool


def train_or_load(options: DemoOptions, echo: Callable[[str], None] = print) -> DemoModel:
    """The demo's TokTalk ``small``, trained with TokTalk's recipe (:func:`jaxtalk.commands.training.train_run`,
    as ``jaxtalk train toktalk``) into the run folder ``options.out_dir`` and loaded from it.

    The folder is an ordinary training run (``run.json``, ``checkpoint/``, ``features.json``,
    ``tokenizer.npz``, ``style.npy``), so ``jaxtalk sample`` / ``jaxtalk stream`` work on it. A run
    already at ``train_steps`` is loaded without training; a shorter one is resumed (a killed run
    continues from its last checkpoint); ``retrain`` deletes the run first. The parameters are those
    of the checkpoint the run's validation chose (TokTalk's: the lowest streamed lip error on the
    validation speakers), the newest where the data has no validation split. Shared by the demo and
    the TokTalk experiments, so the tables describe the model the demo ships.

    Args:
        options: ``out_dir``, ``size``, ``seed``, ``train_steps``, ``batch_size``, ``window_frames``,
            ``learning_rate``, ``retrain``, ``progress`` and ``cache_dir`` are used.
        echo: where progress lines go.

    Returns:
        The parameters with how they were made (:class:`DemoModel`).

    Raises:
        ValueError: ``out_dir`` holds a run of other settings or a checkpoint of an older jaxtalk
            (both say to use ``--retrain``), or a run already past ``train_steps``.
    """
    import shutil

    from jaxtalk.runs import RUN_FILE, RunRecord, checkpoint_dir, load_run
    from jaxtalk.commands.training import TrainOptions, train_run
    from jaxtalk.train import CheckpointMismatchError, latest_checkpoint_step, read_best

    out = Path(options.out_dir)
    ckpt = checkpoint_dir(out)
    if options.retrain:
        for path in (ckpt, out / RUN_FILE):
            if path.is_dir():
                shutil.rmtree(path)
            elif path.exists():
                path.unlink()
    items, data = train_overrides(options), data_spec(options)
    record = RunRecord.load(out) if (out / RUN_FILE).is_file() else None
    if record is not None and (record.model, record.preset, tuple(record.items), record.data.get("spec")) != (
            DEMO_MODEL, DEMO_PRESET, items, data):
        raise ValueError(f"{out} holds a {record.model} ({record.preset}) run on {record.data.get('spec')} with "
                         f"--set {list(record.items)}, not this demo's ({DEMO_PRESET} on {data} with --set {list(items)}); "
                         "run again with --retrain (or another --out folder)")
    done = latest_checkpoint_step(ckpt) if ckpt.exists() else None
    if done is not None and done > options.train_steps:
        raise ValueError(f"{ckpt} is already at step {done} > --steps {options.train_steps}; "
                         f"run again with --steps {done} or --retrain")
    trained = record is None or done != options.train_steps
    if trained:
        what = "resuming" if done else "training"
        echo(f"{what} TokTalk small for {options.train_steps} steps on {data} (run folder: {out})")
        train_opts = TrainOptions(model=DEMO_MODEL, out_dir=out, data=data, preset=DEMO_PRESET, overrides=items,
                                  steps=options.train_steps, seed=options.seed, cache_dir=cache_dir(options),
                                  progress=options.progress)
        try:
            summary = train_run(train_opts, echo=echo)
        except CheckpointMismatchError as err:
            # A checkpoint of another model version or of the old demo format: say what to do.
            raise ValueError(f"{err}\nThe checkpoint in {ckpt} was written by a different model "
                             "configuration; run again with --retrain (or another --out folder).") from err
        except ValueError as err:
            if record is None and done and "loader state" in str(err):
                # A checkpoint without run.json whose data position is not the recipe's loader's:
                # the old demo's own training code wrote it.
                raise ValueError(f"{ckpt} was written by an older jaxtalk demo (no {RUN_FILE}; {err}); "
                                 "run again with --retrain (or another --out folder)") from err
            raise
        echo(f"trained to step {summary.step} in {summary.wall_s:.0f} s (last loss {summary.final_loss:.4g})"
             if summary.final_loss is not None else f"trained to step {summary.step}")
    else:
        echo(f"found a finished checkpoint at step {done} in {ckpt}: no retraining (use --retrain)")
    # The run's validation streams held-out speakers and keeps the checkpoint with the lowest lip
    # error (TokTalk's selection metric): ship that one, not the newest (docs/design-decisions.md).
    best = read_best(ckpt)
    run = load_run(out, best=best is not None)
    if best is not None:
        echo(f"using the checkpoint of step {run.step}: lowest validation {best['metric']} ({best['value']:.4g})")
    return DemoModel(run.params, _history(out), trained, run.step, validated=best is not None)


def _stream_timed(params: Any, config: Any, tokens: np.ndarray, style_vec: Any, key: Any,
                  num_frames: int) -> tuple[np.ndarray, list[float]]:
    """Stream one clip chunk by chunk as a live stream would; wall time of every chunk call."""
    import jax
    import jax.numpy as jnp

    from jaxtalk.models.toktalk import init_stream, stream_step, tokens_per_chunk

    ct = tokens_per_chunk(config)
    chunks = -(-tokens.shape[0] // ct)
    pad = chunks * ct - tokens.shape[0]
    if pad:
        tokens = np.concatenate([tokens, np.repeat(tokens[-1:], pad, axis=0)], axis=0)
    state = init_stream(config, key)
    outs, times = [], []
    for c in range(chunks):
        chunk = jnp.asarray(tokens[None, c * ct:(c + 1) * ct])
        start = time.perf_counter()
        state, out = stream_step(params, config, state, chunk, style_vec)
        jax.block_until_ready(out)
        times.append(time.perf_counter() - start)
        outs.append(np.asarray(out[0]))
    return np.concatenate(outs, axis=0)[:num_frames], times


def _quality_row(name: str, pred: np.ndarray, gt: np.ndarray, face: Any, chunk: int | None) -> dict[str, Any]:
    from jaxtalk.metrics import jitter, lve, mve

    vp, vg = np.asarray(face.vertices_seq(pred)), np.asarray(face.vertices_seq(gt))
    row = {
        "method": name,
        "MSE": float(np.mean((pred - gt) ** 2)),
        "LVE_mm2": float(lve(vp, vg, face.regions["lips"])) * 1e6,
        "MVE_mm": float(mve(vp, vg)) * 1e3,
        "jitter": float(jitter(pred)),
    }
    if chunk is not None and pred.shape[0] > chunk + 2:
        row["jitter_boundary"] = float(jitter(pred, boundaries=range(chunk, pred.shape[0] - 1, chunk)))
    return row


def _sweep(params: Any, corpus: Any, clip: int, style_clip: np.ndarray, echo: Callable[[str], None]) -> list[dict]:
    import jax

    from jaxtalk.metrics import jitter
    from jaxtalk.models.toktalk import encode_style

    gt = np.asarray(corpus.motion(clip), np.float32)
    tokens = np.asarray(corpus.tokens(clip, "A").embeddings, np.float32)
    rows = []
    for chunk_s in SWEEP_CHUNKS_S:
        chunk = int(round(chunk_s * 25))
        for steps in SWEEP_STEPS:
            config = model_config(chunk_frames=chunk, sample_steps=steps)
            style_vec = encode_style(params, config, style_clip[None])
            pred, times = _stream_timed(params, config, tokens, style_vec, jax.random.key(1), gt.shape[0])
            boundaries = range(chunk, gt.shape[0] - 1, chunk)
            row = {
                "chunk_s": chunk_s,
                "steps": steps,
                "MSE": float(np.mean((pred - gt) ** 2)),
                "jitter_boundary": float(jitter(pred, boundaries=boundaries)),
                "latency_ms": 1e3 * statistics.median(times[1:]) if len(times) > 1 else float("nan"),
                "first_chunk_s": times[0],
                "rtf": (statistics.median(times[1:]) if len(times) > 1 else times[0]) / chunk_s,
            }
            rows.append(row)
            echo(f"  sweep chunk {chunk_s:.1f} s x {steps:2d} steps: MSE {row['MSE']:.4f}, "
                 f"jitter {row['jitter_boundary']:.4f}, {row['latency_ms']:.1f} ms/chunk")
    return rows


def _markdown_table(rows: Sequence[dict[str, Any]]) -> str:
    if not rows:
        return "(none)\n"
    keys = list(rows[0])
    fmt = lambda v: "-" if v is None else f"{v:.4g}" if isinstance(v, float) else str(v)  # noqa: E731
    lines = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    lines += ["| " + " | ".join(fmt(r.get(k, "")) for k in keys) + " |" for r in rows]
    return "\n".join(lines) + "\n"


# Seconds of digital silence streamed for the rest jaw of the --audio report.
REST_SECONDS = 3.0
# The shortest --audio (frames) measured: speech_sync's lags of +-8 frames need 11.
_SYNC_MIN_FRAMES = 11


def _animate_user_audio(params: Any, corpus: Any, style_vec: Any, options: DemoOptions,
                        files: dict[str, Path], echo: Callable[[str], None], *,
                        style_rest: float) -> dict[str, Any] | None:
    """Stream the user's audio; write its parameters (and video). Returns its speech-sync row: how the
    predicted jaw follows the recording (no tracked jaw: the loudness), the rest jaw, and the style
    clip's own rest ``style_rest`` beside it (None for audio too short to measure)."""
    import jax

    from jaxtalk.audio import load_audio
    from jaxtalk.layout import JAW_OPEN_INDEX
    from jaxtalk.metrics.speech_sync import speech_sync

    audio = load_audio(options.audio)
    tokenizer = corpus.tokenizer("A")
    tokens = np.asarray(tokenizer.encode(audio).embeddings, np.float32)
    frames = int(round(audio.shape[0] / 16000 * 25))
    config = model_config(options.chunk_frames, sample_steps=options.sample_steps)
    pred, times = _stream_timed(params, config, tokens, style_vec, jax.random.key(2), frames)
    stem = Path(options.audio).stem
    files["user_params"] = options.out_dir / f"{stem}_params.npz"
    atomic_savez(files["user_params"], params56=pred, fps=np.asarray(25))
    echo(f"animated {options.audio} ({audio.shape[0] / 16000:.1f} s, "
         f"{1e3 * statistics.median(times[1:] or times):.1f} ms per 0.4-s chunk)")
    row = None
    if pred.shape[0] < _SYNC_MIN_FRAMES:
        echo(f"note: {options.audio} is shorter than {_SYNC_MIN_FRAMES / 25:g} s: no speech-sync row in the report")
    else:
        # The same stream on digital silence in the same style: does the mouth close?
        silence = np.zeros(int(REST_SECONDS * 16000), np.float32)
        rest, _ = _stream_timed(params, config, np.asarray(tokenizer.encode(silence).embeddings, np.float32),
                                style_vec, jax.random.key(2), int(REST_SECONDS * 25))
        sync = speech_sync(pred[:, JAW_OPEN_INDEX], audio, 16000, max_lag=_SYNC_MIN_FRAMES - 3).to_dict()
        row = {"audio": Path(options.audio).name, "frames": sync["frames"], "speech_frames": sync["speech_frames"],
               "jaw_silence": sync["jaw_silence"], "jaw_speech": sync["jaw_speech"],
               "rest_jaw": float(rest[:, JAW_OPEN_INDEX].mean()), "style_rest_jaw": style_rest,
               "loudness_pred_corr": sync["loudness_pred_corr"],
               "loudness_pred_best_lag": sync["loudness_pred_best_lag"]}
        echo(f"jaw opening: {row['jaw_silence']:.3f} rad in silence, {row['jaw_speech']:.3f} in speech, "
             f"{row['rest_jaw']:.3f} at rest (digital silence; the style clip rests at {style_rest:.3f})")
    if options.render:
        from jaxtalk.render import render_clip

        face = corpus.face(0)
        files["user_video"] = render_clip(options.out_dir / f"{stem}.mp4", np.asarray(face.vertices_seq(pred)),
                                          face.faces, audio=audio, captions=["jaxtalk"],
                                          size=options.render_size, rest_vertices=face.template)
    return row


# The files of a demo folder besides the run (run.json, checkpoint/, the run's assets, the cache).
DEMO_OUTPUTS = ("prediction.npz", "animation.glb", "animation.glb.wav", "sweep.json", "sweep.png", "training.png",
                "animation.mp4", "animation.gif", "report.md")


def claim_demo_outputs(options: DemoOptions) -> None:
    """Check, before any work, that the demo may write its files into ``options.out_dir``.

    A folder that already holds a run (``run.json``) is a previous demo's (a run of other settings is
    refused later with its own message): its outputs are the demo's own and are updated. In any other
    folder an existing file under one of the demo's names is a user's file, kept unless
    ``options.overwrite``. The user's ``--audio`` is never written over.

    Raises:
        jaxtalk.files.OutputError: a name that would replace a user's file, or the audio itself.
    """
    from jaxtalk.runs import RUN_FILE, STYLE_FILE, TOKENIZER_FILE, FEATURES_FILE
    from jaxtalk.files import Output, claim_outputs

    out = Path(options.out_dir)
    own = (out / RUN_FILE).is_file()
    names = [*DEMO_OUTPUTS, RUN_FILE, STYLE_FILE, TOKENIZER_FILE, FEATURES_FILE]
    if options.audio is not None:
        stem = Path(options.audio).stem
        names += [f"{stem}_params.npz", f"{stem}.mp4"]
    claim_outputs([Output(out / name) for name in names], inputs=[options.audio], overwrite=options.overwrite or own)


def run_demo(options: DemoOptions = DemoOptions(), *, echo: Callable[[str], None] = print) -> DemoResult:
    """Run the demo; see the module docstring.

    Args:
        options: settings.
        echo: where progress lines go.

    Returns:
        :class:`DemoResult`.

    Raises:
        ValueError / FileNotFoundError: bad options or a bad ``--audio`` file (checked before training).
    """
    import jax

    from jaxtalk.data import synthtalk
    from jaxtalk.layout import JAW_OPEN_INDEX
    from jaxtalk.metrics.speech_sync import style_rest_jaw
    from jaxtalk.models.toktalk import encode_style

    wall = time.perf_counter()
    if options.sample_steps < 1:
        raise ValueError(f"sample_steps must be >= 1, got {options.sample_steps}")
    if options.train_steps < 1:
        raise ValueError(f"train_steps must be >= 1, got {options.train_steps}")
    if options.audio is not None:
        from jaxtalk.audio import load_audio

        load_audio(options.audio)  # fail fast on a bad file, before minutes of training
    claim_demo_outputs(options)
    out = Path(options.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files: dict[str, Path] = {}

    # The same corpus cache the prepared training data is made from (jaxtalk.data.loader.open_data).
    corpus_cache = cache_dir(options) / "synthtalk"
    echo(f"SynthTalk {options.size}: generating or loading from {corpus_cache}")
    corpus = synthtalk.generate(size=options.size, seed=options.seed, cache_dir=corpus_cache)
    model = train_or_load(options, echo)
    params, history = model.params, model.history
    files["run"] = out / "run.json"
    files["checkpoint"] = out / "checkpoint"

    config = model_config(options.chunk_frames, sample_steps=options.sample_steps)
    clip, style_ref = _pick_clips(corpus)
    gt = np.asarray(corpus.motion(clip), np.float32)
    tokens = np.asarray(corpus.tokens(clip, "A").embeddings, np.float32)
    ref = np.asarray(corpus.motion(style_ref), np.float32)[: config.style_frames * 4]
    style_vec = encode_style(params, config, ref[None])
    pred, times = _stream_timed(params, config, tokens, style_vec, jax.random.key(1), gt.shape[0])
    steady = times[1:] or times
    latency = {
        "chunk_s": config.chunk_frames / config.fps,
        "steps": config.sample_steps,
        "first_chunk_s_incl_compile": times[0],
        "median_chunk_ms": 1e3 * statistics.median(steady),
        "p90_chunk_ms": 1e3 * float(np.percentile(steady, 90)),
        "real_time_factor": statistics.median(steady) / (config.chunk_frames / config.fps),
        "chunks": len(times),
    }
    echo(f"streamed held-out clip {clip} ({gt.shape[0] / 25:.1f} s) in {len(times)} chunks: "
         f"{latency['median_chunk_ms']:.1f} ms per {latency['chunk_s']:.1f}-s chunk "
         f"(real-time factor {latency['real_time_factor']:.3f}; first chunk {times[0]:.1f} s incl. compile)")

    face = corpus.face(0)
    train_motion = np.concatenate([np.asarray(corpus.motion(i)) for i in corpus.split("train")], axis=0)
    mean_pose = np.broadcast_to(train_motion.mean(axis=0), gt.shape).astype(np.float32)
    quality = [
        _quality_row("TokTalk small (streamed)", pred, gt, face, config.chunk_frames),
        _quality_row("mean pose (baseline)", mean_pose, gt, face, None),
        _quality_row("oracle (generator, no noise)", np.asarray(corpus.oracle(clip), np.float32), gt, face, None),
    ]

    files["params"] = out / "prediction.npz"
    atomic_savez(files["params"], params56=pred, ground_truth=gt, fps=np.asarray(25), clip=np.asarray(clip))
    # The prediction as a glTF animation with its audio beside it: Blender, engines and `jaxtalk view` play it.
    from jaxtalk.export import audio_path_for, export_face_model, write_audio_beside

    glb = out / "animation.glb"
    files["gltf"] = export_face_model(face, pred, glb, name="jaxtalk demo", audio_file=audio_path_for(glb).name).path
    audio = np.asarray(corpus.audio(clip), np.float32)
    files["gltf_audio"] = write_audio_beside(files["gltf"], audio)

    sweep_path = out / "sweep.json"
    sweep_rows: list[dict] = []
    if options.sweep:
        if sweep_path.exists() and not model.trained and not options.retrain:
            sweep_rows = json.loads(sweep_path.read_text())["rows"]
            echo(f"chunk x steps sweep: cached in {sweep_path}")
        else:
            echo("chunk x steps sweep (the paper's Table 5) on the held-out clip:")
            sweep_rows = _sweep(params, corpus, clip, ref, echo)
            atomic_write_text(sweep_path, json.dumps({"clip": clip, "rows": sweep_rows}, indent=1))
        files["sweep_json"] = sweep_path
        from jaxtalk.render import plot_sweep

        files["sweep_plot"] = plot_sweep(out / "sweep.png", sweep_rows, row="chunk_s", col="steps",
                                         metrics=["MSE", "jitter_boundary", "latency_ms"],
                                         title="TokTalk small: chunk size x Euler steps")
    if history:
        from jaxtalk.render import plot_training_curves

        # history.jsonl rows are already means over the loop's log period (10 steps): 3 rows ~ 30 steps.
        files["training_curve"] = plot_training_curves(out / "training.png", history, metrics=("loss",),
                                                       smooth=3, title="TokTalk small: training loss")

    if options.render:
        from jaxtalk.render import render_clip

        verts = [np.asarray(face.vertices_seq(gt)), np.asarray(face.vertices_seq(pred))]
        captions = ["ground truth", "jaxtalk (streamed)"]
        files["video"] = render_clip(out / "animation.mp4", verts, face.faces, audio=audio, captions=captions,
                                     size=options.render_size, rest_vertices=[face.template, face.template])
        short = [v[: 4 * 25] for v in verts]
        files["gif"] = render_clip(out / "animation.gif", short, face.faces, captions=captions,
                                   size=min(options.render_size, 192),
                                   rest_vertices=[face.template, face.template])

    user_sync = None
    if options.audio is not None:
        user_sync = _animate_user_audio(params, corpus, style_vec, options, files, echo,
                                        style_rest=style_rest_jaw(ref[:, JAW_OPEN_INDEX]))

    wall_s = time.perf_counter() - wall
    shipped_why = (" (the lowest streamed lip error on the validation speakers, `jaxtalk stream --best`)"
                   if model.validated else "")
    report = [
        "# jaxtalk demo report\n",
        f"SynthTalk `{options.size}` (seed {options.seed}); TokTalk `small` trained {options.train_steps} steps "
        f"({'this run' if model.trained else 'loaded from checkpoint'}), the checkpoint of step {model.step} used"
        f"{shipped_why}; held-out test clip {clip} "
        f"({gt.shape[0] / 25:.1f} s, speaker {corpus.clips[clip].speaker}, style from clip {style_ref}).\n",
        "## Quality on the held-out clip\n",
        "LVE in mm^2 (max squared lip-vertex error per frame, mean over frames), MVE in mm, jitter = mean "
        "norm of the parameter second difference (all frames / within 2 frames of chunk boundaries).\n",
        _markdown_table(quality),
        f"Streamed with {config.sample_steps} Euler step(s) (`--sample-steps`); the sweep below compares 1-20.\n",
        "## Streaming latency (this machine, compile excluded)\n",
        _markdown_table([latency]),
    ]
    if sweep_rows:
        report += ["## Chunk size x Euler steps (streamed, held-out clip)\n", _markdown_table(sweep_rows)]
    if user_sync is not None:
        report += [
            "## Your audio\n",
            "How the predicted jaw opening (rad) follows your recording (`jaxtalk.metrics.speech_sync`): its mean "
            "over silent and speech frames (energy voice activity), the rest jaw (the same stream on "
            f"{REST_SECONDS:g} s of digital silence) beside the style clip's own rest (its 5th-percentile jaw: "
            "where the mouth should be in silence), and its correlation with the recording's log loudness at lag 0 "
            "and the lag of the best one (frames, positive = the jaw is late; lips lead sound, so near 0 or "
            "slightly negative is right). `jaxtalk eval RUN --real-voice FOLDER` measures recordings with tracked "
            "motion.\n",
            _markdown_table([user_sync]),
        ]
    report += ["## Files\n"] + [f"- `{k}`: `{v}`\n" for k, v in files.items()]
    report.append(f"\nTotal wall time of this run: {wall_s:.1f} s.\n")
    files["report"] = out / "report.md"
    atomic_write_text(files["report"], "\n".join(report))
    return DemoResult(out_dir=out, files=files, quality=quality, latency=latency, sweep=sweep_rows,
                      trained=model.trained, wall_s=wall_s, user_sync=user_sync)
