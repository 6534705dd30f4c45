"""The Flax wav2vec 2.0 / HuBERT modules on their own (no torch): brute-force references for the
pieces, padding invariance, layer selection, frozen vs fine-tuned gradients, dropout."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.audio.encoders import (
    EncoderConfig,
    Wav2Vec2Model,
    conv_output_lengths,
    encoder_features,
    interpolate_align_corners,
    normalize_waveform,
    resolve_layer,
)
from jaxtalk.audio.encoders.wav2vec2 import PositionalConvEmbedding


def _params(config: EncoderConfig, seed: int = 0):
    # jit: an eager Flax init dispatches (and compiles) op by op.
    init = jax.jit(Wav2Vec2Model(config).init)
    return init(jax.random.key(seed), jnp.zeros((1, config.receptive_field)))["params"]


def _audio(samples: int, seed: int) -> np.ndarray:
    return (0.3 * np.random.default_rng(seed).standard_normal(samples)).astype(np.float32)


@pytest.fixture(scope="module", params=["base", "large"])
def small(request):
    config = EncoderConfig.small("wav2vec2", request.param)
    return config, _params(config)


def test_standard_conv_stack_sizes():
    config = EncoderConfig.base()
    assert (config.receptive_field, config.hop_length, config.frame_rate(16_000)) == (400, 320, 50.0)
    assert config.num_frames(399) == 0 and config.num_frames(400) == 1 and config.num_frames(720) == 2
    assert config.num_frames(16_000) == 49  # HF gives 49 frames for 1 s
    assert EncoderConfig.large().hidden_size == 1024


@pytest.mark.parametrize("style", ["base", "large"])
def test_conv_lengths_agree_with_the_convolutions(style):
    config = EncoderConfig.small("hubert", style)
    model = Wav2Vec2Model(config)
    params = jax.eval_shape(lambda: _params(config))
    for samples in (config.receptive_field, 101, 257, 1000, 1001):
        if samples < config.receptive_field:
            assert config.num_frames(samples) == 0
            continue
        shape = jax.eval_shape(
            lambda p, x: model.apply({"params": p}, x, method=Wav2Vec2Model.extract)[0],
            params,
            jax.ShapeDtypeStruct((1, samples), jnp.float32),
        ).shape
        assert shape[1] == config.num_frames(samples)
        assert int(conv_output_lengths(config, jnp.array([samples]))[0]) == config.num_frames(samples)
    assert int(conv_output_lengths(config, jnp.array([config.receptive_field - 1]))[0]) == 0


def _conv_reference(x, weight, bias, groups, padding):
    """Direct grouped 1-D convolution in PyTorch layout: x (T, C), weight (out, in/groups, K)."""
    t, c = x.shape
    out, per_group, k = weight.shape
    xp = np.concatenate([np.zeros((padding, c)), x, np.zeros((padding, c))])
    frames = xp.shape[0] - k + 1
    y = np.zeros((frames, out))
    out_per_group = out // groups
    for o in range(out):
        g = o // out_per_group
        for f in range(frames):
            window = xp[f : f + k, g * per_group : (g + 1) * per_group]  # (K, in/groups)
            y[f, o] = np.sum(window * weight[o].T) + bias[o]
    return y


@pytest.mark.parametrize("kernel", [4, 3])
def test_weight_normalised_positional_conv_matches_direct_reference(kernel):
    """g * v / ||v|| with the norm over (out, in) per kernel tap (HF weight_norm dim=2), grouped conv,
    padding k // 2, the extra frame of an even kernel dropped, then GELU."""
    config = EncoderConfig.small(
        "wav2vec2", "base", hidden_size=8, num_attention_heads=2, num_conv_pos_embeddings=kernel,
        num_conv_pos_embedding_groups=2,
    )
    module = PositionalConvEmbedding(config)
    rng = np.random.default_rng(kernel)
    x = rng.standard_normal((1, 9, 8)).astype(np.float32)
    params = module.init(jax.random.key(0), jnp.asarray(x))["params"]
    v = rng.standard_normal(params["conv"]["weight_v"].shape).astype(np.float32)  # (K, 4, 8)
    g = (1 + rng.random(kernel)).astype(np.float32)
    b = rng.standard_normal(8).astype(np.float32)
    params = {"conv": {"weight_v": v, "weight_g": g, "bias": b}}
    ours = np.asarray(module.apply({"params": params}, jnp.asarray(x)))[0]

    torch_v = v.transpose(2, 1, 0).astype(np.float64)  # (out, in/groups, K)
    norm = np.sqrt(np.sum(torch_v**2, axis=(0, 1), keepdims=True))
    weight = g.reshape(1, 1, kernel) * torch_v / norm
    ref = _conv_reference(x[0].astype(np.float64), weight, b, groups=2, padding=kernel // 2)[:9]
    ref = np.asarray(jax.nn.gelu(ref, approximate=False))
    np.testing.assert_allclose(ours, ref, atol=2e-5)


def _jit_apply(config, **kwargs):
    return jax.jit(functools.partial(Wav2Vec2Model(config).apply, **kwargs))


@pytest.mark.slow
def test_padded_batch_equals_single_inputs(small):
    config, params = small
    lengths = [1600, 1111]
    clips = [_audio(n, seed=n) for n in lengths]
    batch = np.zeros((2, 1600), np.float32)
    for row, clip in enumerate(clips):
        batch[row, : clip.size] = clip
    mask = np.arange(1600)[None, :] < np.array(lengths)[:, None]
    padded = _jit_apply(config)({"params": params}, jnp.asarray(batch), jnp.asarray(mask))
    hf_style = _jit_apply(config, mask_group_norm=False)({"params": params}, jnp.asarray(batch), jnp.asarray(mask))
    single = _jit_apply(config)
    for row, clip in enumerate(clips):
        frames = config.num_frames(clip.size)
        alone = single({"params": params}, jnp.asarray(clip[None]))
        assert alone.last_hidden_state.shape[1] == frames
        assert int(np.sum(np.asarray(padded.frame_mask[row]))) == frames
        np.testing.assert_allclose(
            np.asarray(padded.hidden_states[:, row, :frames]), np.asarray(alone.hidden_states[:, 0]), atol=1e-5
        )
        np.testing.assert_allclose(
            np.asarray(padded.last_hidden_state[row, :frames]), np.asarray(alone.last_hidden_state[0]), atol=1e-5
        )
        # HF's group norm takes its statistics over the padded row: only the layer-norm extractor
        # (and rows without padding) are padding-invariant there.
        gap = float(np.max(np.abs(hf_style.last_hidden_state[row, :frames] - alone.last_hidden_state[0])))
        if config.feat_extract_norm == "layer" or clip.size == 1600:
            assert gap < 1e-5
        elif row > 0:
            assert gap > 1e-3


@pytest.mark.slow
def test_layer_selection(small):
    config, params = small
    audio = jnp.asarray(_audio(1200, seed=1)[None])
    full = _jit_apply(config)({"params": params}, audio)
    for layer in (0, -2):
        run = jax.jit(functools.partial(encoder_features, config=config, layer=layer))
        feats, _ = run(params, audio)
        np.testing.assert_allclose(np.asarray(feats), np.asarray(full.hidden_states[layer]), atol=1e-5)
    feats, _ = jax.jit(functools.partial(encoder_features, config=config))(params, audio)
    np.testing.assert_allclose(np.asarray(feats), np.asarray(full.last_hidden_state), atol=1e-5)
    # Stable layer norm: the model output is the LAST layer's output after the final LayerNorm.
    differs = float(np.max(np.abs(full.last_hidden_state - full.hidden_states[-1]))) > 1e-3
    assert differs == config.do_stable_layer_norm
    assert resolve_layer(config, -1) == config.num_hidden_layers and resolve_layer(config, None) is None
    assert resolve_layer(config, -3) == 0
    for bad in (3, -4):
        with pytest.raises(ValueError, match="layer must be"):
            resolve_layer(config, bad)


@pytest.mark.slow
def test_frozen_stops_gradients_and_finetuning_gradient_matches_finite_differences(float64):
    config = EncoderConfig.small("hubert", "large", num_hidden_layers=1)
    params = jax.tree.map(lambda a: a.astype(jnp.float64), _params(config, seed=2))
    audio = jnp.asarray(_audio(700, seed=3)[None], jnp.float64)
    target = jax.random.normal(jax.random.key(1), (1, config.num_frames(700), config.hidden_size), jnp.float64)

    @functools.partial(jax.jit, static_argnums=1)
    def loss(p, frozen):
        feats, _ = encoder_features(p, audio, config=config, frozen=frozen)
        return jnp.sum(feats * target)

    frozen_grad = jax.jit(jax.grad(loss), static_argnums=1)(params, True)
    assert all(float(jnp.max(jnp.abs(g))) == 0.0 for g in jax.tree.leaves(frozen_grad))
    grad = jax.jit(jax.grad(loss), static_argnums=1)(params, False)
    leaves, treedef = jax.tree.flatten(params)
    keys = jax.random.split(jax.random.key(5), len(leaves))
    direction = treedef.unflatten([jax.random.normal(k, a.shape, a.dtype) for k, a in zip(keys, leaves)])
    analytic = sum(float(jnp.sum(g * d)) for g, d in zip(jax.tree.leaves(grad), jax.tree.leaves(direction)))
    eps = 1e-6
    shifted = lambda s: jax.tree.map(lambda p, d: p + s * eps * d, params, direction)  # noqa: E731
    numeric = (float(loss(shifted(1.0), False)) - float(loss(shifted(-1.0), False))) / (2 * eps)
    assert abs(analytic) > 1e-3
    assert abs(analytic - numeric) <= 1e-6 * max(1.0, abs(analytic))


@pytest.mark.slow
def test_dropout_is_on_only_with_a_key():
    config = EncoderConfig.small("wav2vec2", "base", hidden_dropout=0.3, attention_dropout=0.3)
    params = _params(config)
    audio = jnp.asarray(_audio(900, seed=4)[None])
    run = jax.jit(functools.partial(encoder_features, config=config, frozen=False))
    plain, _ = run(params, audio)
    a, _ = run(params, audio, dropout_key=jax.random.key(1))
    b, _ = run(params, audio, dropout_key=jax.random.key(2))
    a2, _ = run(params, audio, dropout_key=jax.random.key(1))
    assert float(jnp.max(jnp.abs(a - plain))) > 1e-2 and float(jnp.max(jnp.abs(a - b))) > 1e-2
    np.testing.assert_array_equal(np.asarray(a), np.asarray(a2))
    assert bool(jnp.all(jnp.isfinite(a)))


def test_interpolate_align_corners_matches_numpy_interp():
    rng = np.random.default_rng(0)
    x = rng.standard_normal((3, 8, 5)).astype(np.float32)
    in_lengths, out_lengths = np.array([8, 4, 6]), np.array([5, 7, 1])
    out = np.asarray(interpolate_align_corners(jnp.asarray(x), jnp.asarray(in_lengths), jnp.asarray(out_lengths), 7))
    for row in range(3):
        n, m = in_lengths[row], out_lengths[row]
        positions = np.linspace(0, n - 1, m) if m > 1 else np.zeros(1)
        ref = np.stack([np.interp(positions, np.arange(n), x[row, :n, c]) for c in range(5)], axis=1)
        np.testing.assert_allclose(out[row, :m], ref, atol=1e-5)
        assert np.all(out[row, m:] == 0)
    # align_corners: first and last output frames are the first and last real input frames.
    np.testing.assert_allclose(out[1, 6], x[1, 3], atol=1e-6)


def test_normalize_waveform_uses_real_samples_only():
    rng = np.random.default_rng(1)
    x = (rng.standard_normal((2, 50)) * 2 + 1).astype(np.float32)
    x[1, 30:] = 123.0  # padding garbage must not leak into the statistics
    out = np.asarray(normalize_waveform(jnp.asarray(x), jnp.asarray([50, 30])))
    for row, n in enumerate((50, 30)):
        real = x[row, :n].astype(np.float64)
        np.testing.assert_allclose(out[row, :n], (real - real.mean()) / np.sqrt(real.var() + 1e-7), atol=1e-5)
        assert np.all(out[row, n:] == 0)
