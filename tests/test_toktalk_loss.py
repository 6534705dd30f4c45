"""TokTalk losses: the CFM path and target (analytic), the random known segment, padding masking,
the loss normalisation (analytic value for a zero-velocity model), the adapter loss, bad batches."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.models import toktalk as tt

CFG = tt.TokTalkConfig.tiny()
B, T = 64, 16


@pytest.fixture(scope="module")
def params():
    return tt.init_params(CFG, jax.random.key(0), adapter_src_dim=48)


def _zero_output(params):
    """The same model with a zero output projection: it predicts v = 0 everywhere."""
    dec = dict(params["decoder"])
    dec["final_proj"] = jax.tree.map(jnp.zeros_like, dec["final_proj"])
    return {**params, "decoder": dec}


def _batch(seed=0, motion_scale=0.0):
    rng = np.random.default_rng(seed)
    mask = np.ones((B, T), bool)
    mask[B // 2 :, 10:] = False
    return {
        "motion": (motion_scale * rng.normal(size=(B, T, 56))).astype(np.float32),
        "tokens": rng.normal(size=(B, T // 2, 64)).astype(np.float32),
        "style": rng.normal(size=(B, CFG.style_frames, 56)).astype(np.float32),
        "mask": mask,
        "src_tokens": rng.normal(size=(B, T, 48)).astype(np.float32),
    }


_cfm = jax.jit(tt.make_loss_fn(CFG))


def test_flow_matching_path_and_target_are_analytic(float64):
    rng = np.random.default_rng(0)
    x1, z = (jnp.asarray(rng.normal(size=(3, 5, 4))) for _ in range(2))
    t = jnp.asarray([0.0, 0.4, 1.0])
    x_t, u = tt.flow_matching_terms(x1, z, t, 1e-6)
    np.testing.assert_allclose(x_t[0], z[0], atol=1e-15)
    np.testing.assert_allclose(x_t[2], x1[2] + 1e-6 * z[2], atol=1e-15)
    # u is the time derivative of the (linear) path.
    dx = jax.jacfwd(lambda s: tt.flow_matching_terms(x1, z, s, 1e-6)[0])(t)
    np.testing.assert_allclose(np.stack([dx[i, ..., i] for i in range(3)]), u, atol=1e-12)


def test_random_known_mask_is_one_contiguous_segment_inside_real_frames():
    valid = jnp.asarray(np.arange(20)[None, :] < np.array([20, 12, 5, 1])[:, None])
    valid = jnp.tile(valid, (50, 1))
    m = np.asarray(tt.random_known_mask(jax.random.key(1), valid, 1.0, 0.3))
    lengths = np.asarray(valid).sum(1)
    for row, n in zip(m, lengths):
        idx = np.nonzero(row)[0]
        assert idx.size >= 1 and idx.max() < n
        assert idx.size == idx.max() - idx.min() + 1  # contiguous
        assert idx.size <= max(1, int(0.3 * n))
    assert not np.asarray(tt.random_known_mask(jax.random.key(1), valid, 0.0, 0.3)).any()
    starts = [np.nonzero(r)[0].min() for r, n in zip(m, lengths) if n == 20]
    assert len(set(starts)) > 3  # not always a prefix


def _constant_pose_batch(seed=0):
    # Every frame of an example, and every frame of its reference clip, is the same unit-scale pose.
    batch = _batch(seed)
    pose = np.random.default_rng(seed + 10).normal(size=(B, 1, 56)).astype(np.float32)
    return {**batch, "motion": np.repeat(pose, T, 1), "style": np.repeat(pose, CFG.style_frames, 1)}


@pytest.mark.slow
def test_cfm_loss_of_zero_velocity_model_is_noise_energy(params):
    # Motion equal to the reference clip's (constant) pose is x1 = 0 in the anchored flow coordinates;
    # with v = 0 (raw decoder, no preconditioning skip) the loss is mean((1 - sigma_min)^2 z^2) over
    # real frames = 1 up to sampling. Without the anchor the same batch has x1 = pose, so the target
    # u = x1 - z adds mean(pose^2) = 1: the loss is 2.
    raw = dataclasses.replace(CFG, precondition=False)
    batch = _constant_pose_batch()
    loss, metrics = jax.jit(tt.make_loss_fn(raw))(_zero_output(params), batch, jax.random.key(3))
    n = (batch["mask"].sum()) * 56
    assert abs(float(metrics["flow"]) - 1.0) < 4 * np.sqrt(2.0 / n)
    assert float(metrics["kl"]) >= 0.0
    np.testing.assert_allclose(float(loss), float(metrics["flow"]) + CFG.kl_weight * float(metrics["kl"]),
                               rtol=1e-6)
    plain = dataclasses.replace(raw, style_anchor=False)
    plain_params = tt.init_params(plain, jax.random.key(0))
    _, m2 = jax.jit(tt.make_loss_fn(plain))(_zero_output(plain_params), batch, jax.random.key(3))
    expect = 1.0 + float(np.sum(np.square(batch["motion"]) * batch["mask"][..., None]) / n)
    assert abs(float(m2["flow"]) - expect) < 0.06


def test_flow_space_is_standardised_motion_minus_the_reference_mean_pose(params):
    rng = np.random.default_rng(3)
    norm = {"mean": rng.normal(size=56).astype(np.float32), "std": rng.uniform(0.5, 2.0, 56).astype(np.float32),
            "flow_scale": rng.uniform(0.2, 1.5, 56).astype(np.float32)}
    p = {**params, "norm": {k: jnp.asarray(v) for k, v in norm.items()}}
    clip = rng.normal(size=(2, 12, 56)).astype(np.float32)
    mask = np.ones((2, 12), bool)
    mask[1, 7:] = False
    style = np.asarray(tt.encode_style(p, CFG, clip, mask))
    assert style.shape == (2, CFG.style_dim + 56) == (2, CFG.style_vector_dim)
    # The anchor part, entry by entry: mean over the real frames of (clip - mean) / std.
    for b, n in ((0, 12), (1, 7)):
        expect = ((clip[b, :n] - norm["mean"]) / norm["std"]).mean(0)
        np.testing.assert_allclose(style[b, CFG.style_dim :], expect, rtol=1e-5, atol=1e-5)
    motion = rng.normal(size=(2, 5, 56)).astype(np.float32)
    x = np.asarray(tt.to_flow_space(p, CFG, jnp.asarray(motion), jnp.asarray(style)))
    expect = ((motion - norm["mean"]) / norm["std"] - style[:, None, CFG.style_dim :]) / norm["flow_scale"]
    np.testing.assert_allclose(x, expect, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(tt.from_flow_space(p, CFG, jnp.asarray(x), jnp.asarray(style)), motion,
                               rtol=1e-5, atol=1e-5)


@pytest.mark.slow
def test_cfm_loss_ignores_padded_frames_and_has_gradients(params):
    batch = _batch(1, motion_scale=1.0)
    loss_a, _ = _cfm(params, batch, jax.random.key(4))
    altered = dict(batch)
    motion = batch["motion"].copy()
    motion[~batch["mask"]] = 1e3
    altered["motion"] = motion
    loss_b, _ = _cfm(params, altered, jax.random.key(4))
    np.testing.assert_allclose(float(loss_a), float(loss_b), rtol=1e-5)
    grads = jax.grad(lambda p: _cfm(p, batch, jax.random.key(4))[0])(params)
    assert float(jnp.abs(grads["style"]["conv_out"]["conv"]["kernel"]).sum()) > 0
    assert float(jnp.abs(grads["decoder"]["token_proj"]["kernel"]).sum()) > 0


@pytest.mark.slow
def test_adapter_loss_alignment_term_is_analytic(params):
    zero_adapter = {**params, "adapter": dict(params["adapter"])}
    zero_adapter["adapter"]["out"] = jax.tree.map(jnp.zeros_like, params["adapter"]["out"])
    batch = _batch(2)
    loss_fn = jax.jit(lambda p, b, k: tt.adapter_loss(p, CFG, b, k, src_rate=25.0, flow_weight=0.5))
    loss, metrics = loss_fn(zero_adapter, batch, jax.random.key(5))
    # A zero adapter output: the alignment term is the mean square of the base tokens over real tokens
    # (a token is real when its first frame is: frames 0, 2, .., 8 for the padded half).
    tok_valid = batch["mask"][:, ::2]
    expect = np.sum(np.square(batch["tokens"]) * tok_valid[..., None]) / (tok_valid.sum() * 64)
    np.testing.assert_allclose(float(metrics["align"]), expect, rtol=1e-5)
    np.testing.assert_allclose(float(loss), float(metrics["align"]) + 0.5 * (
        float(metrics["flow"]) + CFG.kl_weight * float(metrics["kl"])), rtol=1e-5)


def test_adapter_training_positions_are_contiguous_windows_spread_over_the_stream_range():
    from jaxtalk.models.toktalk.loss import adapter_positions

    cfg = dataclasses.replace(CFG, adapter_max_position=1000)
    starts = []
    for i in range(300):
        pos = np.asarray(adapter_positions(cfg, jax.random.key(i), 8))
        np.testing.assert_array_equal(pos, pos[0] + np.arange(8))
        assert 0 <= pos[0] and pos[-1] < 1000
        starts.append(pos[0])
    # Uniform starts in [0, 992]: 300 draws reach both ends of the range (P(miss 10%) < 1e-13).
    assert min(starts) < 100 and max(starts) > 892
    # A window longer than the range starts at 0.
    np.testing.assert_array_equal(np.asarray(adapter_positions(cfg, jax.random.key(0), 1200)), np.arange(1200))


def test_adapter_loss_aligns_the_adapter_output_at_its_training_positions(params):
    from jaxtalk.models.toktalk.loss import adapter_positions
    from jaxtalk.models.toktalk.model import adapter_forward

    batch = jax.tree.map(jnp.asarray, _batch(3))
    key = jax.random.key(7)
    _, metrics = tt.adapter_loss(params, CFG, batch, key, src_rate=25.0, flow_weight=0.0)
    positions = adapter_positions(CFG, jax.random.fold_in(key, 2), batch["tokens"].shape[1])
    assert int(positions[0]) > 0  # this key places the window away from the start
    tok_valid = np.asarray(batch["mask"])[:, ::2][..., None]
    for at, same in ((positions, True), (None, False)):
        adapted = np.asarray(adapter_forward(params, CFG, batch["src_tokens"], 25.0, positions=at))
        align = np.sum(np.square(adapted - np.asarray(batch["tokens"])) * tok_valid) / (tok_valid.sum() * 64)
        assert np.isclose(float(metrics["align"]), align, rtol=1e-5) == same


def test_bad_batches_raise(params):
    batch = _batch(0)
    with pytest.raises(ValueError, match="tokens for 16 frames"):
        tt.loss(params, CFG, {**batch, "tokens": batch["tokens"][:, :5]}, jax.random.key(0))
    with pytest.raises(ValueError, match=r"batch\['tokens'\] must be"):
        tt.loss(params, CFG, {**batch, "tokens": batch["tokens"][..., :10]}, jax.random.key(0))
    with pytest.raises(ValueError, match=r"batch\['mask'\]"):
        tt.loss(params, CFG, {**batch, "mask": batch["mask"][:, :4]}, jax.random.key(0))


@pytest.mark.parametrize("sigma_min", [0.0, 1e-6, 0.1])
def test_preconditioning_is_the_best_linear_velocity_for_standardised_data(sigma_min):
    # For unit-variance data, c_skip must be the least-squares slope of u on x_t, c_out^2 the residual
    # variance and c_in the inverse spread of x_t: checked on 400k samples of a non-Gaussian x1.
    from jaxtalk.models.toktalk.model import preconditioning

    rng = np.random.default_rng(0)
    n = 400_000
    x1 = rng.choice([-1.0, 1.0], n)  # Rademacher: unit variance, far from Gaussian
    z = rng.normal(size=n)
    for t in (0.0, 0.2, 0.5, 0.9, 1.0):
        xt = (1 - (1 - sigma_min) * t) * z + t * x1
        u = x1 - (1 - sigma_min) * z
        slope = np.dot(xt, u) / np.dot(xt, xt)
        c_skip, c_out, c_in = (float(c[0]) for c in preconditioning(jnp.full((1,), t), sigma_min))
        assert c_skip == pytest.approx(slope, abs=6e-3)
        assert c_out**2 == pytest.approx(np.var(u - slope * xt), abs=1e-2)
        assert c_in * np.std(xt) == pytest.approx(1.0, abs=5e-3)


def test_fit_flow_scale_is_the_rms_of_the_anchored_standardised_motion():
    from jaxtalk.models.toktalk.model import fit_flow_scale

    rng = np.random.default_rng(4)
    mean, std = rng.normal(size=56), rng.uniform(0.5, 2.0, 56)
    p = {"norm": {"mean": mean, "std": std}}
    motion = rng.normal(size=(3, 6, 56))
    mask = np.ones((3, 6), bool)
    mask[2, 2:] = False
    style = rng.normal(size=(3, 4, 56))
    # Hand-built: channel 0 of every real frame, its own window's anchor subtracted.
    vals = [((motion[n, t, 0] - mean[0]) / std[0] - ((style[n, :, 0] - mean[0]) / std[0]).mean())
            for n in range(3) for t in range(6) if mask[n, t]]
    scale = fit_flow_scale(p, CFG, motion, mask, style, floor=0.0)
    assert scale.shape == (56,) and scale.dtype == np.float32
    np.testing.assert_allclose(scale[0], np.sqrt(np.mean(np.square(vals))), rtol=1e-6)
    # Without the anchor it is the plain RMS of the standardised motion; a still channel is floored.
    plain = dataclasses.replace(CFG, style_anchor=False)
    motion[:, :, 5] = mean[5]
    np.testing.assert_allclose(fit_flow_scale(p, plain, motion, mask, style, floor=0.0)[1],
                               np.sqrt(np.mean(np.square((motion[mask][:, 1] - mean[1]) / std[1]))), rtol=1e-6)
    assert fit_flow_scale(p, plain, motion, mask, style, floor=0.05)[5] == np.float32(0.05)
    with pytest.raises(ValueError, match="at least one real frame"):
        fit_flow_scale(p, CFG, motion, np.zeros_like(mask), style)
