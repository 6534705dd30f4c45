"""``jaxtalk train MODEL --data synthtalk:SIZE --features hubert:PATH``: SynthTalk prepared with a
pretrained speech encoder from a folder on disk, trained on and sampled from in one command each, and
the one-line errors of a bad ``--features``.

The checkpoint is a randomly initialised HuBERT port with the real base model's 768-d hidden states and
one layer (the same as ``test_cli_freetalk``'s); the corpus is the session's tiny one, so nothing is
generated again, and its log-mel preparation lies beside the encoder's, which must get a folder of its
own.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import soundfile as sf

from helpers import cli_error as _user_error
from helpers import cli_ok as _ok
from helpers import encoder_folder

# The paper preset at a size one CPU step affords: one decoder layer, 1-s windows, one validation
# clip sampled with two DDIM steps.
ATS_PAPER_SMALL = ["--preset", "paper", "--set", "num_layers=1", "--set", "max_frames=25", "--set", "window_frames=25",
                   "--set", "batch_size=2", "--set", "val_clips=1", "--set", "sample_steps=2"]


def _hubert_config():
    """The ``config.json`` of the test's HuBERT: the real base model's width, one layer, a narrow conv
    stack with the real hop (320 samples: 50 frames/s)."""
    from jaxtalk.audio.encoders import EncoderConfig

    return EncoderConfig.small("hubert", "base", hidden_size=768, num_hidden_layers=1, num_attention_heads=12,
                               intermediate_size=256, conv_dim=(16,) * 7, conv_kernel=(10, 3, 3, 3, 3, 2, 2),
                               conv_stride=(5, 2, 2, 2, 2, 2, 2), num_conv_pos_embedding_groups=16)


@pytest.fixture(scope="module")
def hubert(tmp_path_factory) -> Path:
    """A random-weight HuBERT checkpoint folder (config.json + model.safetensors)."""
    pytest.importorskip("safetensors")  # a dependency; an environment installed before it became one lacks it
    import jax
    import jax.numpy as jnp

    from jaxtalk.audio.encoders import Wav2Vec2Model, save_checkpoint

    enc = _hubert_config()
    params = jax.jit(Wav2Vec2Model(enc).init)(jax.random.key(0), jnp.zeros((1, enc.receptive_field)))["params"]
    return save_checkpoint(tmp_path_factory.mktemp("hubert") / "hubert-base", enc, params, normalize=False)


def _cache_with_the_sessions_corpus(root: Path, synthtalk_tiny, prepared_tiny) -> Path:
    """A ``--cache-dir`` whose SynthTalk cache is the session's tiny corpus and whose log-mel folder is
    the session's preparation of it (links: nothing is generated or prepared again for log-mel)."""
    cache = root / "prepared"
    cache.mkdir()
    (cache / "synthtalk").symlink_to(synthtalk_tiny._cache_dir, target_is_directory=True)
    (cache / prepared_tiny.root.name).symlink_to(prepared_tiny.root, target_is_directory=True)
    return cache


@pytest.mark.slow
def test_train_ats_on_synthtalk_with_a_pretrained_hubert_in_one_command_then_animate_a_voice(
        tmp_path, hubert, synthtalk_tiny, prepared_tiny, stm_run):
    import trimesh

    from jaxtalk.data.loader import open_data
    from jaxtalk.face import builtin_face
    from jaxtalk.runs import RunRecord

    cache = _cache_with_the_sessions_corpus(tmp_path, synthtalk_tiny, prepared_tiny)
    logmel_manifest = prepared_tiny.root / "manifest.json"
    logmel_written = logmel_manifest.stat().st_mtime_ns
    run = tmp_path / "run"
    output = _ok(["train", "ats", "--data", "synthtalk:tiny", "--features", f"hubert:{hubert}", "--cache-dir", cache,
                  *ATS_PAPER_SMALL, "--steps", "1", "--no-progress", "--out", run])
    assert "prepared 42 clips" in output  # the encoder ran on every clip, once

    # The run names the front end, and its data is a folder of its own beside the untouched log-mel one.
    features = json.loads((run / "features.json").read_text())
    assert features["audio"] == f"hubert:{hubert.absolute()}" and features["speech_dim"] == 768
    record = RunRecord.load(run)
    assert record.config["speech_dim"] == 768 and record.data["spec"] == "synthtalk:tiny"
    prepared = Path(record.data["path"])
    assert prepared.parent == cache.absolute() and prepared.name.startswith("synthtalk-tiny-seed0-hubert-")
    assert prepared.resolve() != prepared_tiny.root.resolve()
    assert logmel_manifest.stat().st_mtime_ns == logmel_written
    # Each front end finds its own folder again without preparing: log-mel the one it always had.
    assert open_data("synthtalk:tiny", cache_dir=cache, features=f"hubert:{hubert}", progress=False).root == \
        cache / prepared.name
    assert open_data("synthtalk:tiny", cache_dir=cache, progress=False).root == cache / "synthtalk-tiny-seed0"
    # A resumed run keeps its front end.
    _user_error(["train", "ats", "--features", "logmel", "--cache-dir", cache, "--steps", "2", "--out", run],
                f"{run} was trained with --features hubert:{hubert.absolute()}, not logmel")

    # Your own voice (1.2 s at 44.1 kHz) onto a mesh file, through the run's HuBERT.
    from jaxtalk.audio import resample_audio

    voice = tmp_path / "voice.wav"
    sf.write(voice, resample_audio(synthtalk_tiny.audio(synthtalk_tiny.split("test")[0])[:19200], 16000, 44100), 44100)
    face = builtin_face(3, resolution="low")
    trimesh.Trimesh(np.asarray(face.template), np.asarray(face.faces), process=False).export(tmp_path / "face.obj")
    out = tmp_path / "voice.npy"
    _ok(["sample", run, voice, "--stm", stm_run, "--mesh", tmp_path / "face.obj", "--sample-steps", "2", "--out", out])
    verts = np.load(out)
    assert verts.shape == (30, face.num_vertices, 3) and np.isfinite(verts).all()


def test_bad_features_are_one_line_errors_before_any_corpus_is_made(tmp_path, prepared_tiny):
    fake = encoder_folder(tmp_path / "hubert", "hubert")  # complete as far as the checks go: no weight is read
    no_config = tmp_path / "no-config"
    no_config.mkdir()
    no_weights = encoder_folder(tmp_path / "no-weights", "hubert")
    (no_weights / "model.safetensors").unlink()
    cache = tmp_path / "cache"
    base = ["train", "ats", "--data", "synthtalk:tiny", "--cache-dir", cache, "--steps", "1", "--out", tmp_path / "run"]

    for model, reads in (("toktalk", "toktalk reads audio tokens"), ("stm", "stm reads landmarks")):
        _user_error(["train", model, "--features", f"hubert:{fake}", "--cache-dir", cache, "--out", tmp_path / "r"],
                    "--features chooses the speech front end of ats, timar, dualtalk", reads, "drop --features")
    _user_error([*base, "--features", f"hubert:{tmp_path / 'absent'}"], "hubert checkpoint folder not found",
                "config.json and model.safetensors")
    _user_error([*base, "--features", f"hubert:{no_config}"], "has no config.json")
    _user_error([*base, "--features", f"hubert:{no_weights}"], "holds no weights", "model.safetensors")
    _user_error([*base, "--features", f"wav2vec2:{fake}"], "model_type 'hubert'", f"use hubert:{fake}")
    _user_error([*base, "--features", "mfcc"], "unknown audio features 'mfcc'", "logmel, hubert:PATH or wav2vec2:PATH")
    _user_error([*base, "--features", "hubert"], "hubert features need a local checkpoint folder: hubert:PATH")
    _user_error(["prepare", "synthtalk:tiny", "--out", tmp_path / "p", "--features", f"hubert:{no_config}"],
                "has no config.json")
    # A prepared folder keeps the features it was prepared with.
    _user_error(["train", "ats", "--data", prepared_tiny.root, "--features", f"hubert:{fake}", "--steps", "1",
                 "--out", tmp_path / "run"],
                f"{prepared_tiny.root} was prepared with --features logmel, not hubert:{fake}")
    assert not cache.exists() and not (tmp_path / "p").exists() and not (tmp_path / "run").exists()
