"""Small helpers several test modules share (import as ``from helpers import ...``)."""

from __future__ import annotations

import contextlib
import functools
from pathlib import Path

import jax
import numpy as np


def with_loop_settings(**kw) -> dict:
    """``kw`` as :func:`jaxtalk.train.train`'s keywords: the :class:`~jaxtalk.train.LoopSettings` fields
    among them gathered into ``settings`` (for tests that vary both kinds through one helper)."""
    import dataclasses

    from jaxtalk.train import LoopSettings

    fields = {f.name for f in dataclasses.fields(LoopSettings)}
    return {**{k: v for k, v in kw.items() if k not in fields},
            "settings": LoopSettings(**{k: v for k, v in kw.items() if k in fields})}


@functools.partial(jax.jit, static_argnames="scale")
def perturbed(params, key, scale: float = 0.05):
    """``params`` plus ``scale`` x standard-normal noise on every leaf.

    Zero-initialised layers (adaLN modulations, output projections) make a fresh model's output exactly
    0 or its input; tests of what a layer computes perturb them first so that comparisons see signal.
    """
    leaves, tree = jax.tree.flatten(params)
    keys = jax.random.split(key, len(leaves))
    return jax.tree.unflatten(tree, [x + scale * jax.random.normal(k, x.shape) for x, k in zip(leaves, keys)])


def timar_streams(batch: int, frames: int, seed: int = 0, speech_dim: int = 8) -> dict:
    """Random float32 TIMAR inputs, ``(batch, frames, .)``: both speakers' speech and motion."""
    import numpy as np

    rng = np.random.default_rng(seed)
    return {
        "user_speech": rng.normal(size=(batch, frames, speech_dim)).astype(np.float32),
        "user_motion": rng.normal(size=(batch, frames, 56)).astype(np.float32),
        "agent_speech": rng.normal(size=(batch, frames, speech_dim)).astype(np.float32),
        "agent_motion": rng.normal(size=(batch, frames, 56)).astype(np.float32),
    }


def read_event_file(path):
    """Every TensorBoard ``Event`` of one file, read with tensorboardX's protobufs and the TFRecord
    framing, each record's length and payload checksums verified (independent of jaxtalk's code)."""
    import struct

    from tensorboardX.proto.event_pb2 import Event
    from tensorboardX.record_writer import masked_crc32c

    data, offset, events = path.read_bytes(), 0, []
    while offset < len(data):
        header = data[offset:offset + 8]
        (length,) = struct.unpack("<Q", header)
        assert struct.unpack("<I", data[offset + 8:offset + 12])[0] == masked_crc32c(header)
        payload = data[offset + 12:offset + 12 + length]
        assert len(payload) == length, f"torn record in {path}"
        assert struct.unpack("<I", data[offset + 12 + length:offset + 16 + length])[0] == masked_crc32c(payload)
        events.append(Event.FromString(payload))
        offset += 16 + length
    return events


def event_files(run_dir):
    """A run folder's TensorBoard event files, in name (creation) order."""
    return sorted(p for p in run_dir.glob("events.out.tfevents.*") if not p.name.startswith("."))


def scalars(run_dir):
    """``tag -> [(step, value), ...]`` over all event files of a run folder, in file order."""
    out: dict[str, list[tuple[int, float]]] = {}
    for path in event_files(run_dir):
        for event in read_event_file(path):
            for value in event.summary.value:
                out.setdefault(value.tag, []).append((event.step, value.simple_value))
    return out


# DualTalk's demo clips (real data) live outside the repository, in ../shared; tests that read them
# also run on a DualTalk-layout folder exported from SynthTalk, so a fresh clone loses no code path.
DUALTALK_DEMO = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "dualtalk_demo"
DUALTALK_SOURCES = ("synthtalk", "real")


def dualtalk_folder(root, source: str, corpus=None) -> dict[str, tuple[str, int]]:
    """A DualTalk release-layout folder at ``root`` shaped like DualTalk's demo: a ``train/``
    conversation whose speaker 2 alone has tracked motion and a ``test/`` one whose speaker 1 alone has.

    Args:
        root: the folder to create.
        source: ``"real"``: the demo clips (the test skips where ``../shared`` lacks them);
            ``"synthtalk"``: ``corpus``'s training and test conversations (``export_dualtalk``), the
            other side's ``.npz`` removed.
        corpus: the SynthTalk corpus (``synthtalk`` only).

    Returns:
        ``{split: (conversation stem, the speaker with motion)}``; clip names are
        ``f"{stem}_speaker{k}"``.
    """
    import shutil

    import pytest

    if source == "real":
        if not DUALTALK_DEMO.is_dir():
            pytest.skip("shared DualTalk demo data not available")
        convs = {"train": ("UbjUDM1MiGE_sub_video_72", 2), "test": ("xkHwlcDSOjc_sub_video_109_000", 1)}
        for split, (conv, _) in convs.items():
            (root / split).mkdir(parents=True)
            for f in DUALTALK_DEMO.glob(f"{conv}_speaker*"):
                shutil.copy(f, root / split / f.name)
        return convs
    from jaxtalk.data.sources import export_dualtalk

    export_dualtalk(corpus, root)
    for split in ("val", "ood"):
        shutil.rmtree(root / split, ignore_errors=True)
    convs = {}
    for split, with_motion in (("train", 2), ("test", 1)):
        [npz] = (root / split).glob(f"*_speaker{3 - with_motion}.npz")
        npz.unlink()
        convs[split] = (npz.name[: -len(f"_speaker{3 - with_motion}.npz")], with_motion)
    return convs


@contextlib.contextmanager
def jax_flag(name: str, value: bool):
    """The JAX config flag ``name`` set to ``value`` while inside, restored after."""
    previous = jax.config.read(name)
    jax.config.update(name, value)
    try:
        yield
    finally:
        jax.config.update(name, previous)


@contextlib.contextmanager
def xla_options(**options):
    """XLA compiler options (``DebugOptions`` fields, as ``jax.jit(...).lower().compile(compiler_options)``
    takes them) for every program compiled while inside, the jitted functions of the library included.

    JAX has no process-wide setting for them, so this wraps its compile-options builder (a private
    function: if a JAX release renames it, this fails loudly rather than silently doing nothing)."""
    from jax._src import compiler

    build = compiler.get_compile_options

    def with_options(*args, env_options_overrides=None, **kwargs):
        return build(*args, env_options_overrides={**options, **(env_options_overrides or {})}, **kwargs)

    compiler.get_compile_options = with_options
    try:
        yield
    finally:
        compiler.get_compile_options = build


def crashing_batches(crash_at: int, *args, **kw):
    """A :class:`jaxtalk.data.batching.BatchIterator` whose process 'dies' (KeyboardInterrupt) when asked
    for batch number ``crash_at`` (1-based): a training run killed mid-way, for resume tests."""
    from jaxtalk.data.batching import BatchIterator

    class Crashing(BatchIterator):
        def __init__(self):
            super().__init__(*args, **kw)
            self.served = 0

        def __next__(self):
            self.served += 1
            if self.served == crash_at:
                raise KeyboardInterrupt("simulated kill")
            return super().__next__()

    return Crashing()


@contextlib.contextmanager
def few_validation_windows(count: int = 4):
    """The recipes validate on ``count`` windows instead of :data:`jaxtalk.train.recipes.VAL_WINDOWS`
    while inside (tests that need a validation pass, not a precise one: STM renders every window)."""
    from jaxtalk.train import recipes

    saved, recipes.VAL_WINDOWS = recipes.VAL_WINDOWS, count
    try:
        yield
    finally:
        recipes.VAL_WINDOWS = saved


def assert_recipe_resumes_exactly(train, config, data, folder: Path, window_frames: int | None = None, **kw) -> None:
    """A recipe (``train(config, data, optim, *, key, run=RunSettings(...), ...)``) run for 4 steps
    with a checkpoint every 2, then its step-4 checkpoint deleted (as if the run had died after step 2):
    a fresh call with the same arguments resumes from step 2 and ends bitwise where the uninterrupted
    run did, with the same losses on steps 3 and 4 (the loader's position and the RNG resume too)."""
    import shutil

    import numpy as np

    from jaxtalk.runs import RunSettings
    from jaxtalk.train import LoopSettings, OptimConfig

    ckpt = Path(folder) / "checkpoint"

    def run(save_every=None):
        settings = RunSettings(batch_size=2, window_frames=window_frames, ckpt_dir=ckpt,
                               loop=LoopSettings(progress=False, save_every=save_every))
        return train(config, data, OptimConfig(lr=1e-3, warmup_steps=1, total_steps=4), key=jax.random.key(0),
                     run=settings, **kw)

    with few_validation_windows():
        straight = run(save_every=2)
        assert sorted(p.name for p in ckpt.iterdir() if p.name.isdigit()) == ["2", "4"]
        shutil.rmtree(ckpt / "4")
        resumed = run()
    losses = {r["step"]: r["loss"] for r in straight.history if "loss" in r}
    again = {r["step"]: r["loss"] for r in resumed.history if "loss" in r}
    assert sorted(again) == [3, 4] and again == {k: losses[k] for k in (3, 4)}, (losses, again)
    for a, b in zip(jax.tree.leaves(resumed.state.params), jax.tree.leaves(straight.state.params), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
# The smallest graph of each model that ``jaxtalk train`` builds, as ``--preset`` / ``--set`` arguments
# (compile time dominates the suite's few-step runs); the session's shared runs use them.
TINY_TRAIN_ARGS = {
    # One sampled validation clip (side): the sampled metrics are recorded, at an eighth of the default cost.
    "toktalk": ["--preset", "tiny", "--set", "num_mid_blocks=0", "--set", "val_clips=1"],
    "timar": ["--set", "width=32", "--set", "num_layers=1", "--set", "num_heads=2", "--set", "head_width=32",
              "--set", "head_blocks=1", "--set", "max_turns=2", "--set", "val_clips=1"],
    "ats": ["--set", "width=32", "--set", "num_layers=1", "--set", "num_heads=2", "--set", "ff_dim=32",
            "--set", "sample_steps=4", "--set", "val_clips=1"],
}


def bad_numpy_files(folder) -> dict[str, list[str]]:
    """Writes into ``folder`` every kind of bad ``.npz`` / ``.npy`` a user may hand jaxtalk; returns
    ``{file name: words its one-line error must hold}``."""
    import zipfile

    import numpy as np

    (folder / "garbage.npz").write_bytes(b"garbage bytes, not an archive")
    (folder / "garbage.npy").write_bytes(b"garbage bytes, not an array")
    np.save(folder / "objects.npy", np.array([{"a": 1}, None], dtype=object), allow_pickle=True)
    np.savez(folder / "objects.npz", params=np.array([{"a": 1}], dtype=object), fps=25)
    with zipfile.ZipFile(folder / "members.npz", "w") as archive:
        archive.writestr("params.npy", b"not an array")
    np.savez(folder / "cut.npz", params=np.zeros((100, 56), np.float32), fps=25)
    data = (folder / "cut.npz").read_bytes()
    (folder / "cut.npz").write_bytes(data[: len(data) // 2])
    np.save(folder / "cut.npy", np.zeros((100, 56), np.float32))
    data = (folder / "cut.npy").read_bytes()
    (folder / "cut.npy").write_bytes(data[: len(data) // 2])
    np.savez(folder / "flipped.npz", params=np.zeros((100, 56), np.float32), fps=25)
    data = bytearray((folder / "flipped.npz").read_bytes())
    data[len(data) // 3] ^= 0xFF  # inside the params' bytes: the member's checksum no longer matches
    (folder / "flipped.npz").write_bytes(bytes(data))
    return {
        "garbage.npz": ["not an .npz file", "not a zip archive"],
        "garbage.npy": ["not a NumPy .npy file"],
        "objects.npy": ["holds an object array", "never reads"],
        "objects.npz": ["holds object arrays ('params')", "never reads"],
        "members.npz": ["'params.npy' is not a NumPy array"],
        "cut.npz": ["not an .npz file"],  # the archive's directory is at its end
        "cut.npy": ["damaged .npy file"],
        "flipped.npz": ["damaged .npz file"],
    }


def encoder_folder(path, kind: str = "wav2vec2", config=None) -> Path:
    """A speech-encoder checkpoint folder that passes every check made before its weights are read
    (``jaxtalk.data.features.parse_audio_features``): ``config.json`` of a ``kind`` model (``config``, an
    ``EncoderConfig``, or a small one) and an empty ``model.safetensors``. For tests of what happens
    before any encoder runs; one that computes features needs real weights (``save_checkpoint``)."""
    import json

    from jaxtalk.audio.encoders import EncoderConfig

    folder = Path(path)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "config.json").write_text(json.dumps((config or EncoderConfig.small(kind)).to_hf_dict()))
    (folder / "model.safetensors").write_bytes(b"")
    return folder


def cli_ok(args: list) -> str:
    """Run ``jaxtalk ARGS`` in-process (typer's runner); it must succeed. Returns its output."""
    from typer.testing import CliRunner

    from jaxtalk.cli import app

    result = CliRunner().invoke(app, [str(a) for a in args])
    assert result.exit_code == 0, result.output
    return result.output


def cli_error(args: list, *words: str) -> str:
    """Run ``jaxtalk ARGS``; it must be refused as a user error: exit 2, exactly one ``error:`` line
    (holding every one of ``words``) and no traceback. Returns that line."""
    from typer.testing import CliRunner

    from jaxtalk.cli import app

    result = CliRunner().invoke(app, [str(a) for a in args])
    assert result.exit_code == 2, result.output
    errors = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and all(w in errors[0] for w in words), result.output
    assert "Traceback" not in result.output
    return errors[0]


# ------------------------------------------------------------------------- real voices

# The recordings' rate (jaxtalk's audio rate).
SR = 16000


def syllables(seconds: float, rate: int = SR, seed: int = 0) -> np.ndarray:
    """A voice-like test signal: a faint room hiss, and 220-Hz syllables (3 per second) in the middle."""
    t = np.arange(int(seconds * rate)) / rate
    env = ((np.sin(2 * np.pi * 3 * t) > 0) & (t > 0.4) & (t < seconds - 0.4)).astype(np.float64)
    hiss = 1e-3 * np.random.default_rng(seed).normal(size=t.shape)
    return (0.3 * np.sin(2 * np.pi * 220 * t) * env + hiss).astype(np.float32)


def real_voices(folder: Path) -> dict[str, np.ndarray]:
    """A real-voice folder (``--real-voice`` of ``jaxtalk eval`` and ``jaxtalk train``): ``a.wav``
    (stereo, 22.05 kHz) with a jaxtalk params npz (51 frames, one more than the audio's 50), ``b.flac``
    with a DualTalk pose npz, ``c.wav`` without motion. Returns the tracked jaw of each tracked
    recording."""
    import soundfile as sf

    from jaxtalk.audio import resample_audio

    folder.mkdir()
    a = syllables(2.0)
    sf.write(folder / "a.wav", np.stack([resample_audio(a, SR, 22050)] * 2, axis=1), 22050)
    sf.write(folder / "b.flac", syllables(2.4, seed=1), SR)
    sf.write(folder / "c.wav", syllables(2.0, seed=2), SR)
    t = np.arange(60) / 25
    jaws = {"a": 0.1 * (np.sin(2 * np.pi * 3 * t[:51]) > 0) * (t[:51] > 0.4), "b": 0.05 + 0.02 * np.sin(t)}
    params = np.zeros((51, 56), np.float32)
    params[:, 50] = jaws["a"]
    np.savez(folder / "a.npz", params=params, fps=25)
    pose = np.zeros((60, 6), np.float32)
    pose[:, 3] = jaws["b"]
    np.savez(folder / "b.npz", pose=pose)
    return {k: v.astype(np.float32).astype(np.float64) for k, v in jaws.items()}


def cli_user_error(args: list, message: str) -> str:
    """Run ``jaxtalk ARGS`` in-process; it must end with exit code 2 and one ``error:`` line holding
    ``message``, no traceback. Returns its output."""
    from typer.testing import CliRunner

    from jaxtalk.cli import app

    result = CliRunner().invoke(app, [str(a) for a in args])
    assert result.exit_code == 2, result.output
    assert result.output.strip().splitlines()[-1].startswith("error:") and message in result.output, result.output
    assert "Traceback" not in result.output
    return result.output
