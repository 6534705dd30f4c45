"""Checkpoint loading (round trip, clear errors) and the SpeechEncoder front end (no torch needed)."""

from __future__ import annotations

import json
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("safetensors")
from safetensors.numpy import load_file, save_file  # noqa: E402

from jaxtalk.audio import TokenStream, resample_audio, resample_features  # noqa: E402
from jaxtalk.audio.encoders import (  # noqa: E402
    EncoderConfig,
    SpeechEncoder,
    Wav2Vec2Model,
    checkpoint_fingerprint,
    load_checkpoint,
    params_from_state_dict,
    params_to_state_dict,
    save_checkpoint,
    weight_files,
)
from jaxtalk.audio.encoders import frontend  # noqa: E402

CONFIG = EncoderConfig.small("hubert", "base")


@pytest.fixture(scope="module")
def params():
    init = jax.jit(Wav2Vec2Model(CONFIG).init)
    return init(jax.random.key(0), jnp.zeros((1, CONFIG.receptive_field)))["params"]


@pytest.fixture
def checkpoint(tmp_path, params):
    return save_checkpoint(tmp_path / "ckpt", CONFIG, params, normalize=True)


def _audio(samples: int, seed: int = 0) -> np.ndarray:
    return (0.3 * np.random.default_rng(seed).standard_normal(samples)).astype(np.float32)


def test_checkpoint_round_trip(checkpoint, params):
    ckpt = load_checkpoint(checkpoint)
    assert ckpt.config == CONFIG and ckpt.normalize is True and ckpt.sample_rate == 16_000
    assert ckpt.ignored == ()
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(ckpt.params)):
        np.testing.assert_array_equal(np.asarray(a), b)
    state = load_file(str(checkpoint / "model.safetensors"))
    assert state["encoder.layers.1.attention.q_proj.weight"].shape == (32, 32)
    assert state["encoder.pos_conv_embed.conv.parametrizations.weight.original0"].shape == (1, 1, 8)
    assert state["feature_extractor.conv_layers.0.conv.weight"].shape == (16, 1, 10)
    # Layouts: Dense kernels are transposed Linear weights, stacked layers split by index.
    np.testing.assert_array_equal(
        state["encoder.layers.1.attention.q_proj.weight"],
        np.asarray(params["encoder"]["layers"]["attention"]["q_proj"]["kernel"][1]).T,
    )


def test_missing_files_and_directories(tmp_path, checkpoint):
    with pytest.raises(FileNotFoundError, match="checkpoint directory not found"):
        load_checkpoint(tmp_path / "nowhere")
    (checkpoint / "model.safetensors").unlink()
    with pytest.raises(FileNotFoundError, match=r"holds no weights.*config\.json"):
        load_checkpoint(checkpoint)
    (checkpoint / "config.json").unlink()
    with pytest.raises(FileNotFoundError, match="config file not found"):
        load_checkpoint(checkpoint)


def test_sharded_weights_load_and_the_fingerprint_follows_the_files_read(checkpoint, params):
    state = load_file(str(checkpoint / "model.safetensors"))
    fingerprint = checkpoint_fingerprint(checkpoint)
    assert checkpoint_fingerprint(checkpoint) == fingerprint  # read from the file system: stable
    # Transformers' sharded layout: an index naming the shard of every tensor.
    names = sorted(state)
    shards = {"model-00001-of-00002.safetensors": names[::2], "model-00002-of-00002.safetensors": names[1::2]}
    for shard, keys in shards.items():
        save_file({k: state[k] for k in keys}, str(checkpoint / shard))
    weight_map = {k: shard for shard, keys in shards.items() for k in keys}
    (checkpoint / "model.safetensors.index.json").write_text(json.dumps({"weight_map": weight_map}))
    (checkpoint / "model.safetensors").unlink()
    assert [p.name for p in weight_files(checkpoint)] == ["model.safetensors.index.json", *sorted(shards)]
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(load_checkpoint(checkpoint).params)):
        np.testing.assert_array_equal(np.asarray(a), b)
    assert checkpoint_fingerprint(checkpoint) != fingerprint
    sharded = checkpoint_fingerprint(checkpoint)
    (checkpoint / "README.md").write_text("a file the loader does not read")
    assert checkpoint_fingerprint(checkpoint) == sharded
    # Other weights in the same folder. (A file rewritten with the same size within the file system's
    # timestamp granularity, a few ms, would keep its time: here the size differs, as the test needs.)
    shard = checkpoint / "model-00002-of-00002.safetensors"
    save_file({**{k: state[k] + 1 for k in shards[shard.name]}, "extra": np.zeros(3, np.float32)}, str(shard))
    assert checkpoint_fingerprint(checkpoint) != sharded


def test_unknown_architecture_and_unsupported_options(checkpoint):
    config = json.loads((checkpoint / "config.json").read_text())
    for change, pattern in (
        ({"model_type": "wavlm"}, "unsupported model_type 'wavlm'"),
        ({"model_type": None}, "unsupported model_type None"),
        ({"add_adapter": True}, "add_adapter"),
        ({"adapter_attn_dim": 16}, "adapter_attn_dim"),
        ({"feat_extract_norm": "batch"}, "feat_extract_norm"),
        ({"hidden_act": "mish"}, "hidden_act 'mish'"),
        ({"num_attention_heads": 5}, "not divisible by num_attention_heads"),
        ({"conv_kernel": [10, 3]}, "equal lengths"),
    ):
        (checkpoint / "config.json").write_text(json.dumps({**config, **change}))
        with pytest.raises(ValueError, match=pattern):
            load_checkpoint(checkpoint)
    (checkpoint / "config.json").write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_checkpoint(checkpoint)


def test_missing_unexpected_and_misshaped_tensors_are_all_named(checkpoint, params):
    state = params_to_state_dict(CONFIG, params)
    del state["encoder.layers.1.final_layer_norm.bias"]
    state["encoder.layers.0.attention.k_proj.weight"] = np.zeros((32, 31), np.float32)
    state["encoder.extra_gate"] = np.zeros(3, np.float32)
    save_file(state, str(checkpoint / "model.safetensors"))
    with pytest.raises(ValueError) as info:
        load_checkpoint(checkpoint)
    message = str(info.value)
    assert "missing tensors (1): encoder.layers.1.final_layer_norm.bias" in message
    assert "unexpected tensors (1): encoder.extra_gate" in message
    assert "encoder.layers.0.attention.k_proj.weight: shape (32, 31), expected (32, 32)" in message
    # A checkpoint of another size fails on shapes, naming the tensors.
    with pytest.raises(ValueError, match="mis-shaped tensors"):
        params_from_state_dict(EncoderConfig.small("hubert", "base", hidden_size=64), params_to_state_dict(CONFIG, params))


def test_task_prefix_and_training_only_tensors_are_skipped(params):
    state = {f"hubert.{k}": v for k, v in params_to_state_dict(CONFIG, params).items()}
    state["hubert.masked_spec_embed"] = np.zeros(32, np.float32)
    state["classifier.weight"] = np.zeros((2, 32), np.float32)
    loaded, ignored = params_from_state_dict(CONFIG, state)
    assert ignored == ("classifier.weight", "hubert.masked_spec_embed")
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(loaded)):
        np.testing.assert_array_equal(np.asarray(a), b)


def test_pytorch_bin_without_torch_says_what_to_do(checkpoint, monkeypatch):
    (checkpoint / "model.safetensors").rename(checkpoint / "pytorch_model.bin")
    monkeypatch.setitem(sys.modules, "torch", None)  # import torch -> ImportError
    with pytest.raises(ImportError, match="install torch.*convert"):
        load_checkpoint(checkpoint)


def test_preprocessor_config(checkpoint):
    assert SpeechEncoder.from_pretrained(checkpoint).normalize is True
    (checkpoint / "preprocessor_config.json").write_text(json.dumps({"do_normalize": False}))
    assert SpeechEncoder.from_pretrained(checkpoint).normalize is False
    assert SpeechEncoder.from_pretrained(checkpoint, normalize=True).normalize is True
    (checkpoint / "preprocessor_config.json").write_text(json.dumps({"sampling_rate": 0}))
    with pytest.raises(ValueError, match="sampling_rate"):
        load_checkpoint(checkpoint)


def test_speech_encoder_interfaces(checkpoint, params):
    encoder = SpeechEncoder.from_pretrained(checkpoint, pad_multiple=4000)
    assert encoder.rate == 16_000 / 20 and encoder.dim == 32 and encoder.num_layers == 2
    audio = _audio(3333, seed=1)
    feats = encoder.features(audio)
    assert feats.shape == (CONFIG.num_frames(3333), 32)
    # Same as the module on the normalised, unpadded clip: bucket padding changes nothing.
    norm = (audio - audio.mean()) / np.sqrt(audio.var() + 1e-7)
    direct = jax.jit(Wav2Vec2Model(CONFIG).apply)({"params": params}, jnp.asarray(norm[None]))
    np.testing.assert_allclose(np.asarray(feats), np.asarray(direct.last_hidden_state[0]), atol=1e-5)

    # Clips in the same length bucket reuse the compiled program.
    before = frontend._jitted_features._cache_size()
    encoder.features(_audio(3100, seed=2))
    assert frontend._jitted_features._cache_size() == before

    at25 = encoder.features_at(audio, 25)
    assert at25.shape == (round(3333 / 16_000 * 25), 32)
    np.testing.assert_allclose(
        np.asarray(at25), np.asarray(resample_features(feats, encoder.rate, 25, num_frames=5)), atol=1e-6
    )
    interp = encoder.interpolated_features(audio, 25, num_frames=7)
    assert interp.shape == (7, 32) and bool(jnp.all(jnp.isfinite(interp)))

    stream = encoder.encode(audio)
    assert isinstance(stream, TokenStream) and stream.ids is None and stream.rate == encoder.rate
    np.testing.assert_allclose(stream.embeddings, np.asarray(feats), atol=1e-6)
    assert stream.to_frame_rate(25).shape == (round(len(stream) * 25 / encoder.rate), 32)

    batch, mask = encoder.features_batch([audio, audio[:2000]])
    assert batch.shape == (2, feats.shape[0], 32)
    assert int(mask[1].sum()) == CONFIG.num_frames(2000)
    np.testing.assert_allclose(np.asarray(batch[0]), np.asarray(feats), atol=1e-5)
    np.testing.assert_allclose(
        np.asarray(batch[1, : CONFIG.num_frames(2000)]), np.asarray(encoder.features(audio[:2000])), atol=1e-5
    )


def test_audio_at_another_rate_is_resampled_and_bad_audio_refused(checkpoint):
    encoder = SpeechEncoder.from_pretrained(checkpoint, pad_multiple=4000)
    audio_8k = _audio(1500, seed=3)
    np.testing.assert_allclose(
        np.asarray(encoder.features(audio_8k, sample_rate=8000)),
        np.asarray(encoder.features(resample_audio(audio_8k, 8000, 16_000))),
        atol=1e-6,
    )
    bad = [
        (np.zeros(CONFIG.receptive_field - 1, np.float32), {}, "too short"),
        (_audio(400).reshape(2, 200), {}, r"shape \(samples,\)"),
        (np.full(500, np.nan, np.float32), {}, "NaN"),
        (np.zeros(500, np.int16), {}, "float waveform"),
        (_audio(500), {"sample_rate": 0}, "sample_rate"),
        (_audio(500), {"sample_rate": -16_000}, "sample_rate"),
    ]
    for audio, kwargs, pattern in bad:
        with pytest.raises(ValueError, match=pattern):
            encoder.features(audio, **kwargs)
    with pytest.raises(ValueError, match="layer must be"):
        encoder.features(_audio(500), layer=7)
    with pytest.raises(ValueError, match="non-empty list"):
        encoder.features_batch([])
    with pytest.raises(ValueError, match="num_frames"):
        encoder.interpolated_features(_audio(500), num_frames=0)
