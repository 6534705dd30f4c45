"""``jaxtalk sample`` and ``jaxtalk stream``: a trained run + speech -> 56-d head parameters (.npz).

Inputs: an audio file (WAV/FLAC, any rate, mono or stereo) or, for TokTalk, a ``.npy`` of token
embeddings ``(tokens, speech_dim)`` at the model's token rate (e.g. your own audio-LLM tokens). Every
default comes from the run folder, never from a regenerated corpus: TokTalk turns audio into tokens
with the tokenizer its data was prepared with and takes its default style clip from the run; TIMAR
turns audio into per-turn speech features with the same front end as ``prepare`` and animates the
agent (the partner is silent and still unless ``--partner`` names their audio). Outputs are written
with :func:`jaxtalk.data.formats.save_npz`
(``params (T, 56)``, ``fps``, and the audio), in raw FLAME units.
"""

from __future__ import annotations

import dataclasses
import math
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from jaxtyping import Float

from jaxtalk.audio.io import AUDIO_SUFFIXES
from jaxtalk.checks import check_temperature
from jaxtalk.runs import LoadedRun, RunRecord, SpeechAnimator, SpeechConditions, load_run, model_spec

__all__ = ["SampleOptions", "SampleResult", "MeshOptions", "sample_run", "stream_run", "stream_audio", "animate_run",
           "check_sampling_options"]


@dataclasses.dataclass(frozen=True)
class SampleOptions:
    """Settings of :func:`sample_run` / :func:`stream_run`.

    Attributes:
        run_dir: a folder written by ``jaxtalk train``.
        input: audio file, or (TokTalk) ``.npy`` token embeddings.
        out: output ``.npz`` (default: beside the input, ``<stem>_params.npz``, which replaces no existing
            file without ``overwrite``); an input is never written over.
        style: TokTalk reference motion (``.npz`` with ``params``, e.g. a previous output); default: the
            training clip saved with the run.
        partner: TIMAR: the partner's audio (default: silence).
        cfg_scale: guidance weight (default: the config's).
        sample_steps: sampler steps (default: the config's).
        temperature: scale of the sampler's noise (TokTalk: the starting noise, default the config's;
            TIMAR: MAR's temperature, default 1). Below 1 trades diversity for accuracy.
        seed: noise seed.
        best: use the run's best-validated checkpoint instead of its newest.
        overwrite: let the default output name replace an existing file.
        mesh_options: FreeTalk-only options given (``"--emotion"``...), refused for other models.
    """

    run_dir: Path
    input: Path
    out: Path | None = None
    style: Path | None = None
    partner: Path | None = None
    cfg_scale: float | None = None
    sample_steps: int | None = None
    temperature: float | None = None
    seed: int = 0
    best: bool = False
    overwrite: bool = False
    mesh_options: tuple[str, ...] = ()


@dataclasses.dataclass
class SampleResult:
    """Output of :func:`sample_run` / :func:`stream_run`.

    Attributes:
        path: the ``.npz`` written.
        params: ``(T, 56)`` motion.
        chunk_ms: wall time of every streamed chunk/turn in ms (empty for offline sampling; the first
            includes compilation).
        chunk_s: duration of one chunk/turn in seconds (None offline).
    """

    path: Path
    params: np.ndarray
    chunk_ms: list[float]
    chunk_s: float | None


def _check_input(opts: SampleOptions, model: str, other_inputs: Sequence[tuple[str, str]] = ()) -> None:
    """The input exists and is audio or another kind the model takes (``(suffix, what it holds)``)."""
    path = Path(opts.input)
    if not path.is_file():
        raise FileNotFoundError(f"input file not found: {str(path)!r}")
    suffix = path.suffix.lower()
    if suffix in AUDIO_SUFFIXES or suffix in dict(other_inputs):
        return
    kinds = "an audio file (" + ", ".join(AUDIO_SUFFIXES) + ")" + "".join(f" or {what}" for _, what in other_inputs)
    raise ValueError(f"{str(path)!r}: expected {kinds} for {'an' if model[0] in 'aeiou' else 'a'} {model} run")


def _claim_output(opts: SampleOptions, suffix: str, default_suffix: str, *, extra_inputs: Sequence[Path | None] = ()) -> Path:
    """The output path, checked before any work: named by ``--out`` or ``<input stem><default_suffix>``
    beside the input, never one of the command's inputs (the run's files included)."""
    from jaxtalk.files import Output, claim_outputs

    path = Path(opts.input)
    out = Path(opts.out) if opts.out is not None else path.with_name(f"{path.stem}{default_suffix}")
    inputs = [opts.input, opts.style, opts.partner, opts.run_dir, *extra_inputs]
    (out,) = claim_outputs([Output(out, named=opts.out is not None, suffixes=(suffix,))], inputs,
                           overwrite=opts.overwrite)
    return out


# The options of ``jaxtalk sample RUN_ATS AUDIO --stm RUN_STM --mesh FILE``; a speech animator's are its own
# (:attr:`jaxtalk.runs.SpeechAnimator.options`). ``--out``, ``--seed``, ``--best`` and ``--sample-steps`` apply to
# all; any other one given is refused rather than ignored.
_MESH_OPTIONS = ("--stm", "--mesh", "--emotion", "--intensity", "--units", "--landmarks")


def _check_options(opts: SampleOptions, name: str, own: Sequence[str]) -> None:
    """Every option before any work: values in range, none but ``own`` (those of a ``name`` run)."""
    given = [flag for flag, value in (("--style", opts.style), ("--partner", opts.partner),
                                      ("--cfg-scale", opts.cfg_scale), ("--temperature", opts.temperature))
             if value is not None]
    unused = [flag for flag in (*given, *opts.mesh_options) if flag not in own]
    if unused:
        raise ValueError(f"{', '.join(unused)}: not {'an option' if len(unused) == 1 else 'options'} of a {name} run "
                         f"(it takes {', '.join(own)}, --sample-steps, --seed)")
    check_sampling_options(opts.cfg_scale, opts.sample_steps, opts.temperature)


def check_sampling_options(cfg_scale: float | None, sample_steps: int | None, temperature: float | None) -> None:
    """The sampler's options as the commands take them (None: the model's own), before any work.

    Raises:
        ValueError: a NaN or infinite ``--cfg-scale``, ``--sample-steps`` below 1, or a ``--temperature``
            that is negative, NaN or infinite.
    """
    if cfg_scale is not None and not math.isfinite(cfg_scale):
        raise ValueError(f"--cfg-scale must be a finite number, got {cfg_scale}")
    if sample_steps is not None and sample_steps < 1:
        raise ValueError(f"--sample-steps must be >= 1, got {sample_steps}")
    if temperature is not None:
        check_temperature(temperature, name="--temperature")


def _load(opts: SampleOptions) -> tuple[LoadedRun, SpeechAnimator, Any]:
    """The run, its model's animator, and the input as the model takes it (every option and the output
    checked first). A run of a model without an animator is refused with its spec's words."""
    record = RunRecord.load(opts.run_dir)
    spec = model_spec(record.model)
    animator = spec.animator
    if animator is None:
        refusal = spec.sample_refusal or "{run} is a " + record.model + " run, which sample and stream do not animate"
        raise ValueError(refusal.format(run=opts.run_dir))
    _check_options(opts, spec.title, animator.options)
    _check_input(opts, record.model, animator.other_inputs)
    _claim_output(opts, ".npz", "_params.npz")
    run = load_run(opts.run_dir, best=opts.best)
    return run, animator, animator.read(run, opts.input)


def _conditions(opts: SampleOptions) -> SpeechConditions:
    """The conditions the options give, their files read (``--style``, ``--partner``)."""
    style = partner = None
    if opts.style is not None:
        from jaxtalk.commands.rendering import read_params

        style = read_params(opts.style)
    if opts.partner is not None:
        from jaxtalk.audio import load_audio

        partner = load_audio(opts.partner, allow_silence=True)
    return SpeechConditions(style=style, style_file=None if opts.style is None else str(opts.style), partner=partner,
                            cfg_scale=opts.cfg_scale, sample_steps=opts.sample_steps, temperature=opts.temperature,
                            seed=opts.seed)


def _write(opts: SampleOptions, params: np.ndarray, audio: np.ndarray | None) -> Path:
    from jaxtalk.data.formats import MotionClip, save_npz
    from jaxtalk.types import MOTION_FPS

    out = _claim_output(opts, ".npz", "_params.npz")  # checked again: a file may have appeared meanwhile
    clip = MotionClip(name=Path(opts.input).stem, fps=MOTION_FPS, params=np.asarray(params, np.float32),
                      audio=None if audio is None else np.asarray(audio, np.float32))
    return save_npz(out, clip)


def sample_run(opts: SampleOptions) -> SampleResult:
    """Animate ``opts.input`` offline (TokTalk: the whole sequence in one sampler call, or minute-long
    windows for longer inputs, :func:`~jaxtalk.models.toktalk.sample_long`; TIMAR: turn by turn, its
    only mode).

    Returns:
        :class:`SampleResult`.

    Raises:
        FileNotFoundError: missing run, checkpoint, input, style or partner file.
        ValueError: a run of another model, an input of the wrong kind/shape, a too-short audio.
    """
    run, animator, speech = _load(opts)
    params, audio = animator.sample(run, speech, _conditions(opts))
    return SampleResult(path=_write(opts, params, audio), params=params, chunk_ms=[], chunk_s=None)


class _ChunkTimer:
    """Wall time of each streamed chunk/turn in ms, echoed as it is produced."""

    def __init__(self, echo: Callable[[str], None]):
        self.echo, self.ms = echo, []

    def __call__(self, n: int, dt: float, chunk_s: float, chunks: int = 1) -> None:
        i = len(self.ms)
        self.ms.append(1e3 * dt / chunks)
        note = " (incl. compile)" if i == 0 else f" (real-time factor {dt / chunks / chunk_s:.3f})"
        which = f"chunk {i + 1:3d}" if chunks == 1 else f"chunks {i + 1}-{i + chunks}"
        self.echo(f"{which}/{n}: {1e3 * dt / chunks:8.1f} ms for {chunk_s:.2f} s{note}")


def stream_audio(run: LoadedRun, audio: Float[np.ndarray, " samples"], opts: SampleOptions, *,
                 echo: Callable[[str], None] = print) -> Float[np.ndarray, "frames 56"]:
    """Animate a 16-kHz mono waveform with a loaded run as :func:`stream_run` does (TokTalk: the live path,
    chunk by chunk; TIMAR: turn by turn, whole turns only, the partner silent unless ``opts.partner``),
    writing nothing. Silence is accepted (a model's rest pose).

    Args:
        run: a TokTalk or TIMAR run (:func:`jaxtalk.runs.load_run`).
        audio: the waveform.
        opts: the sampling options (``input`` only names the audio in messages; ``out`` is not read).
        echo: where each chunk's wall time goes.

    Returns:
        ``(T, 56)`` head parameters at 25 fps.

    Raises:
        ValueError: a run of another model, options it does not take, a TokTalk run without a
            tokenizer, audio shorter than one TIMAR turn.
    """
    spec = model_spec(run.record.model)
    if spec.animator is None:
        raise ValueError(f"{run.run_dir} is a {run.record.model} run; stream_audio animates toktalk and timar runs")
    _check_options(opts, spec.title, spec.animator.options)
    audio = np.asarray(audio, np.float32)
    if audio.ndim != 1 or not np.all(np.isfinite(audio)):
        raise ValueError(f"audio must be a finite one-dimensional waveform, got shape {audio.shape}")
    timer = _ChunkTimer(echo)
    return spec.animator.stream(run, audio, _conditions(opts), timer, timer.echo)[0]


def stream_run(opts: SampleOptions, *, echo: Callable[[str], None] = print) -> SampleResult:
    """Animate ``opts.input`` chunk by chunk (TokTalk) or turn by turn (TIMAR) as a live stream would,
    echoing each chunk's wall time as it is produced.

    Returns:
        :class:`SampleResult` with the per-chunk times.

    Raises:
        See :func:`sample_run`.
    """
    run, animator, speech = _load(opts)
    timer = _ChunkTimer(echo)
    params, audio, chunk_s = animator.stream(run, speech, _conditions(opts), timer, timer.echo)
    times = timer.ms
    if len(times) > 1:
        steady = times[1:]
        echo(f"median {statistics.median(steady):.1f} ms per {chunk_s:.2f}-s chunk after the first "
             f"(real-time factor {statistics.median(steady) / 1e3 / chunk_s:.3f})")
    return SampleResult(path=_write(opts, params, audio), params=params, chunk_ms=times, chunk_s=chunk_s)


@dataclasses.dataclass(frozen=True)
class MeshOptions:
    """FreeTalk's ``jaxtalk sample RUN_ATS AUDIO --stm RUN_STM --mesh FILE`` settings.

    Attributes:
        stm_run: the STM run folder.
        mesh: the mesh to animate (OBJ, PLY, GLB/GLTF, OFF, STL).
        emotion: a name of the ATS run's emotion vocabulary.
        intensity: continuous, in ``[1, num_intensities]``.
        units: the mesh's unit (``m``, ``dm``, ``cm``, ``mm``, ``um``); None: detected from its size.
        landmarks: optional landmark file (see :func:`jaxtalk.models.freetalk.animate.read_landmarks`).
    """

    stm_run: Path
    mesh: Path
    emotion: str = "neutral"
    intensity: float = 1.0
    units: str | None = None
    landmarks: Path | None = None


def animate_run(opts: SampleOptions, mesh_opts: MeshOptions, *, echo: Callable[[str], None] = print) -> SampleResult:
    """FreeTalk end to end: an ATS run + an STM run + speech + a user's mesh -> ``(T, V, 3)`` vertices
    (``.npy``, the mesh's units, frame and vertex order), rendered with ``jaxtalk render OUT.npy --faces MESH``.

    Returns:
        :class:`SampleResult` whose ``params`` holds the ``(T, V, 3)`` vertices.

    Raises:
        FileNotFoundError: a missing run, audio, mesh or landmark file.
        ValueError: runs of the wrong models, bad audio, an unknown emotion, an intensity out of range,
            a mesh that cannot be animated (a point cloud, too few vertices, not the size or shape of a face).
    """
    import jax

    from jaxtalk.audio import load_audio
    from jaxtalk.geometry.canonical import UNITS, load_mesh
    from jaxtalk.models.freetalk.animate import animate, prepare_user_mesh, read_landmarks
    from jaxtalk.models.freetalk.fit import FittedATS, FittedSTM
    from jaxtalk.files import atomic_save_npy

    _check_options(opts, "FreeTalk", _MESH_OPTIONS)
    path = Path(opts.input)
    _check_input(opts, "ats")
    if mesh_opts.units is not None and mesh_opts.units not in UNITS:
        raise ValueError(f"--units must be one of {', '.join(UNITS)}, got {mesh_opts.units!r}")
    stm_files = [p for p in Path(mesh_opts.stm_run).iterdir() if p.is_file()] if Path(mesh_opts.stm_run).is_dir() else []
    out = _claim_output(opts, ".npy", "_vertices.npy", extra_inputs=[mesh_opts.mesh, mesh_opts.landmarks, *stm_files])
    # The emotion and intensity against the run's record, before any parameters are loaded.
    ats_record = RunRecord.load(opts.run_dir)
    if not model_spec(ats_record.model).animates_user_meshes:
        raise ValueError(f"{opts.run_dir} is a {ats_record.model} run, not an ats run")
    ats_config = ats_record.model_config()
    emotions, levels = ats_config.emotions, ats_config.num_intensities
    if mesh_opts.emotion not in emotions:
        raise ValueError(f"--emotion {mesh_opts.emotion}: not an emotion of this run; it knows: {', '.join(emotions)}")
    if not (math.isfinite(mesh_opts.intensity) and 1 <= mesh_opts.intensity <= levels):
        raise ValueError(f"--intensity must lie in [1, {levels}] for this run, got {mesh_opts.intensity:g}")
    ats = FittedATS.from_run(load_run(opts.run_dir, best=opts.best))
    stm = FittedSTM.from_run(load_run(mesh_opts.stm_run, best=opts.best))
    audio = load_audio(path)
    vertices, faces = load_mesh(mesh_opts.mesh)
    landmarks = None if mesh_opts.landmarks is None else read_landmarks(mesh_opts.landmarks, vertices)
    t0 = time.perf_counter()
    mesh = prepare_user_mesh(stm, (vertices, faces), units=mesh_opts.units, landmarks=landmarks)
    echo(f"mesh {mesh_opts.mesh}: {vertices.shape[0]} vertices, {faces.shape[0]} faces, {mesh.canonical.describe()} "
         f"in {time.perf_counter() - t0:.1f} s")
    verts = animate(ats, stm, audio, mesh_opts.emotion, mesh_opts.intensity, mesh, key=jax.random.key(opts.seed),
                    sample_steps=opts.sample_steps)
    atomic_save_npy(out, verts)
    return SampleResult(path=out, params=verts, chunk_ms=[], chunk_s=None)
