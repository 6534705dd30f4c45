"""1-D conv blocks: NumPy references, masked group norm, padding invariance, exact causality, shapes."""

from __future__ import annotations

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.nn import (
    Conv1d,
    Conv1dBlock,
    Downsample1D,
    ResnetBlock1D,
    Upsample1D,
    downsample_mask,
    masked_group_norm,
    upsample_mask,
)

from test_nn_support import random_params



def _np(tree):
    return jax.tree_util.tree_map(lambda a: np.asarray(a, np.float64), tree)


def _conv_reference(x, kernel, bias, pad, stride=1):
    """y[t] = sum_j xpad[t * stride + j] @ kernel[j] + bias, x (time, in), kernel (k, in, out)."""
    xp = np.pad(np.asarray(x, np.float64), (pad, (0, 0)))
    k = kernel.shape[0]
    n_out = (xp.shape[0] - k) // stride + 1
    return np.stack(
        [sum(xp[t * stride + j] @ kernel[j] for j in range(k)) + bias for t in range(n_out)]
    )


def _lengths_mask(lengths, time):
    return jnp.arange(time)[None, :] < jnp.asarray(lengths)[:, None]


@pytest.mark.parametrize(
    ("kernel_size", "stride", "causal", "pad"),
    [(3, 1, False, (1, 1)), (3, 1, True, (2, 0)), (4, 1, False, (1, 2)), (3, 2, False, (1, 1)), (3, 2, True, (2, 0))],
)
def test_conv1d_matches_reference(key, kernel_size, stride, causal, pad):
    x = jax.random.normal(key, (7, 3))
    conv = Conv1d(4, kernel_size, strides=stride, causal=causal)
    params = random_params(conv, x)
    p = _np(params["params"]["conv"])
    expected = _conv_reference(x, p["kernel"], p["bias"], pad, stride)
    out = conv.apply(params, x)
    assert out.shape == (-(-7 // stride), 4)
    np.testing.assert_allclose(out, expected, atol=1e-5)


def test_masked_group_norm_uses_real_frames_only(key):
    x = jax.random.normal(key, (2, 6, 8)) * 3.0 + 1.0
    mask = _lengths_mask([4, 6], 6)
    out = masked_group_norm(x, mask, num_groups=2)
    for b, n in enumerate([4, 6]):
        for g in range(2):
            block = np.asarray(x[b, :n, 4 * g : 4 * (g + 1)], np.float64)
            ref = (block - block.mean()) / np.sqrt(block.var() + 1e-5)
            np.testing.assert_allclose(out[b, :n, 4 * g : 4 * (g + 1)], ref, atol=1e-5)
    # Without a mask it is Flax's GroupNorm over (time, channels-in-group) without affine.
    flax_gn = nn.GroupNorm(num_groups=2, epsilon=1e-5, use_scale=False, use_bias=False, reduction_axes=(-2, -1))
    np.testing.assert_allclose(
        masked_group_norm(x, None, num_groups=2), flax_gn.apply({}, x), atol=1e-5
    )
    # A sequence without a single real frame stays finite.
    assert np.all(np.isfinite(masked_group_norm(x, jnp.zeros((2, 6), bool), num_groups=2)))


@pytest.mark.parametrize("module", [Conv1dBlock(8), ResnetBlock1D(8)], ids=["block", "resnet"])
def test_real_frames_do_not_depend_on_the_amount_of_padding(key, module):
    real = jax.random.normal(key, (1, 5, 6))
    t_emb = jax.random.normal(jax.random.fold_in(key, 1), (1, 4))
    args = lambda x, m: (x, m, t_emb) if isinstance(module, ResnetBlock1D) else (x, m)  # noqa: E731
    params = random_params(module, *args(real, jnp.ones((1, 5), bool)))
    apply = jax.jit(module.apply)
    outs = []
    for total in (5, 8, 13):
        garbage = 100.0 * jax.random.normal(jax.random.fold_in(key, total), (1, total - 5, 6))
        x = jnp.concatenate([real, garbage], axis=1)
        out = apply(params, *args(x, _lengths_mask([5], total)))
        outs.append(out[:, :5])
        if isinstance(module, Conv1dBlock):
            np.testing.assert_array_equal(out[:, 5:], 0.0)  # the mask zeroes padded frames
    np.testing.assert_allclose(outs[1], outs[0], atol=1e-5)
    np.testing.assert_allclose(outs[2], outs[0], atol=1e-5)


def test_resnet_block_is_block_time_block_plus_residual(key):
    x = jax.random.normal(key, (2, 6, 5))
    mask = _lengths_mask([6, 4], 6)
    t_emb = jax.random.normal(jax.random.fold_in(key, 1), (2, 7))
    module = ResnetBlock1D(8)
    params = random_params(module, x, mask, t_emb)["params"]
    block = Conv1dBlock(8)
    h = block.apply({"params": params["block1"]}, x, mask)
    p = _np(params["time_proj"])
    t = np.asarray(jax.nn.mish(t_emb), np.float64) @ p["kernel"] + p["bias"]
    h = block.apply({"params": params["block2"]}, h + jnp.asarray(t[:, None, :], jnp.float32), mask)
    r = _np(params["residual"]["conv"])
    residual = np.einsum("btc,cf->btf", np.asarray(x * mask[..., None]), r["kernel"][0]) + r["bias"]
    np.testing.assert_allclose(module.apply({"params": params}, x, mask, t_emb), h + residual, atol=1e-5)
    other = module.apply({"params": params}, x, mask, t_emb + 1.0)
    assert np.abs(other - (h + residual)).max() > 1e-3  # the time embedding matters


def _first_changed_frame(module, params, x, cut, extra=()):
    """Output frames computed before and after changing every input frame >= cut."""
    changed = x.at[:, cut:].set(jax.random.normal(jax.random.key(9), x[:, cut:].shape))
    return module.apply(params, x, *extra), module.apply(params, changed, *extra)


@pytest.mark.parametrize(
    ("name", "cut", "unchanged_frames"),
    [("conv", 4, 4), ("block", 4, 4), ("resnet", 4, 4), ("down", 5, 3), ("up", 4, 8)],
)
def test_causal_outputs_ignore_the_future_exactly(key, name, cut, unchanged_frames):
    """Inputs at times >= cut change: causal outputs that only see earlier times are bit-identical,
    while the offline variants do change there (so the check can fail)."""
    x = jax.random.normal(key, (2, 9, 8))
    mask = jnp.ones((2, 9), bool)
    t_emb = jax.random.normal(key, (2, 3))
    make = {
        "conv": (lambda c: Conv1d(8, 3, causal=c), ()),
        "block": (lambda c: Conv1dBlock(8, causal=c), (mask,)),
        "resnet": (lambda c: ResnetBlock1D(8, causal=c), (mask, t_emb)),
        "down": (lambda c: Downsample1D(causal=c), (mask,)),
        "up": (lambda c: Upsample1D(causal=c), (mask,)),
    }
    factory, extra = make[name]
    for causal in (True, False):
        module = factory(causal)
        params = random_params(module, x, *extra)
        before, after = _first_changed_frame(module, params, x, cut, extra)
        if causal:
            np.testing.assert_array_equal(
                before[:, :unchanged_frames], after[:, :unchanged_frames]
            )
            assert np.abs(before[:, unchanged_frames:] - after[:, unchanged_frames:]).max() > 0
        else:
            assert np.abs(before[:, :unchanged_frames] - after[:, :unchanged_frames]).max() > 1e-6


@pytest.mark.parametrize(("length", "down", "up"), [(7, 4, 14), (8, 4, 16), (1, 1, 2)])
def test_down_and_up_lengths(key, length, down, up):
    """Down: T -> ceil(T/2); up: T -> 2T; an odd length comes back one frame longer."""
    x = jax.random.normal(key, (2, length, 8))
    mask = _lengths_mask([length, max(length - 2, 1)], length)
    d = Downsample1D(features=4)
    y = d.apply(random_params(d, x, mask), x, mask)
    assert y.shape == (2, down, 4) and downsample_mask(mask).shape == (2, down)
    u = Upsample1D(features=3)
    z = u.apply(random_params(u, y, downsample_mask(mask)), y, downsample_mask(mask))
    assert z.shape == (2, 2 * down, 3) and upsample_mask(downsample_mask(mask)).shape == (2, 2 * down)
    assert 2 * down - length == length % 2
    z2 = u.apply(random_params(u, x), x)
    assert z2.shape == (2, up, 3)


def test_upsample_matches_transposed_conv_reference(key):
    """PyTorch ConvTranspose1d(k=4, s=2, p=1) offline; the causal variant crops the right side."""
    x = jax.random.normal(key, (5, 3))
    for causal, start in ((False, 1), (True, 0)):
        module = Upsample1D(features=2, causal=causal)
        params = random_params(module, x)
        p = _np(params["params"]["conv"])
        full = np.zeros((2 * 5 + 2, 2))
        for m in range(5):
            for j in range(4):
                # Flax's (non-transposed) kernel layout: tap j lands at full frame 2m + 3 - j.
                full[2 * m + 3 - j] += np.asarray(x[m], np.float64) @ p["kernel"][j]
        expected = full[start : start + 10] + p["bias"]
        np.testing.assert_allclose(module.apply(params, x), expected, atol=1e-5)


def test_masked_down_and_up_zero_padded_frames(key):
    x = jax.random.normal(key, (2, 6, 8))
    mask = np.arange(6)[None, :] < np.array([[6], [3]])  # a NumPy mask from the data pipeline
    d = Downsample1D()
    y = d.apply(random_params(d, x, mask), x, mask)
    np.testing.assert_array_equal(y[1, 2:], 0.0)  # frames 2i >= 3
    u = Upsample1D()
    z = u.apply(random_params(u, x, mask), x, mask)
    np.testing.assert_array_equal(z[1, 6:], 0.0)


def test_conv_errors(key):
    x = jnp.zeros((2, 6, 8))
    with pytest.raises(ValueError, match="causal Conv1dBlock cannot use a group norm"):
        jax.eval_shape(Conv1dBlock(8, causal=True, norm="group").init, key, x)
    with pytest.raises(ValueError, match="does not divide"):
        jax.eval_shape(Conv1dBlock(12, num_groups=8).init, key, x)
    with pytest.raises(ValueError, match="kernel_size"):
        jax.eval_shape(Conv1d(4, 0).init, key, x)
    with pytest.raises(ValueError, match="empty time axis"):
        jax.eval_shape(Upsample1D().init, key, jnp.zeros((2, 0, 8)))
