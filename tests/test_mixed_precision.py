"""Mixed precision (``compute_dtype=bfloat16``, :mod:`jaxtalk.nn.precision`): parameters and optimiser
state stay float32, the networks compute in bfloat16, a short bf16 run reaches the float32 run's loss
(within 5%), every sampler stays finite, and runs recorded before the setting load as float32."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.nn.precision import cast_floating, compute_in

BF16 = "bfloat16"


def _bf16(config):
    return dataclasses.replace(config, compute_dtype=BF16)


def test_compute_in_casts_inputs_and_outputs_and_float32_is_untouched():
    def fn(w, x, *, bias, mask):
        assert w.dtype == x.dtype == bias.dtype == jnp.bfloat16 and mask.dtype == bool
        return {"y": x @ w + bias[None], "n": jnp.sum(mask)}

    w, x, b = jnp.ones((3, 2)), jnp.ones((4, 3)), jnp.zeros(2)
    out = compute_in(BF16, fn)(w, x, bias=b, mask=jnp.ones(4, bool))
    assert out["y"].dtype == jnp.float32 and out["n"].dtype == jnp.int32
    assert compute_in("float32", fn) is fn
    grads = jax.grad(lambda w: compute_in(BF16, fn)(w, x, bias=b, mask=jnp.ones(4, bool))["y"].sum())(w)
    assert grads.dtype == jnp.float32  # the cast's transpose: float32 gradients for float32 weights
    tree = cast_floating({"a": jnp.ones(2), "i": jnp.ones(2, jnp.int32), "k": jax.random.key(0)}, jnp.bfloat16)
    assert tree["a"].dtype == jnp.bfloat16 and tree["i"].dtype == jnp.int32
    with pytest.raises(ValueError, match="compute_dtype must be one of float32, bfloat16"):
        compute_in("float16", fn)


@pytest.mark.parametrize("model", ["toktalk", "ats", "stm", "timar", "dualtalk"])
def test_every_config_takes_compute_dtype_and_checks_it(model):
    from jaxtalk.runs import build_config

    assert build_config(model, "small").compute_dtype == "float32"
    assert build_config(model, "small", ["compute_dtype=bfloat16"]).compute_dtype == BF16
    with pytest.raises(ValueError, match="compute_dtype must be one of"):
        build_config(model, "small", ["compute_dtype=float64"])


def test_a_run_recorded_without_compute_dtype_loads_as_float32(stm_run):
    import json

    from jaxtalk.runs import RUN_FILE, RunRecord

    raw = json.loads((stm_run / RUN_FILE).read_text())
    raw["config"].pop("compute_dtype", None)
    assert RunRecord(**raw).model_config().compute_dtype == "float32"


def _recipe_losses(config, data, steps):
    from jaxtalk.models.toktalk.recipe import train
    from jaxtalk.runs import RunSettings
    from jaxtalk.train import LoopSettings, OptimConfig

    result = train(config, data, OptimConfig(lr=2e-3, warmup_steps=2, total_steps=steps), key=jax.random.key(0),
                   run=RunSettings(steps=steps, batch_size=4, loop=LoopSettings(progress=False)),
                   val_clips=0)  # the loss is what is compared
    return result, np.asarray([h["loss"] for h in result.history if "loss" in h])


@pytest.mark.slow
def test_a_short_bf16_run_reaches_the_float32_loss_with_float32_state(prepared_tiny):
    from jaxtalk.models.toktalk import TokTalkConfig

    config = TokTalkConfig.tiny(num_mid_blocks=0, speech_dim=prepared_tiny.manifest["token_dim"],
                                token_rate=prepared_tiny.manifest["token_rate"])
    steps = 40
    _, f32 = _recipe_losses(config, prepared_tiny, steps)
    result, b16 = _recipe_losses(_bf16(config), prepared_tiny, steps)
    assert np.all(np.isfinite(b16)) and f32[-10:].mean() < 0.9 * f32[:5].mean()  # it learned something
    assert abs(b16[-10:].mean() - f32[-10:].mean()) <= 0.05 * f32[-10:].mean(), (b16[-10:].mean(), f32[-10:].mean())
    state = result.state
    floats = [x for x in jax.tree.leaves((state.params, state.opt_state, state.ema_params))
              if jnp.issubdtype(x.dtype, jnp.floating)]
    assert floats and all(x.dtype == jnp.float32 for x in floats)


def _tiny(model):
    from jaxtalk.runs import build_config

    items = {
        "toktalk": [],
        "ats": ["width=32", "num_layers=1", "num_heads=2", "ff_dim=64", "speech_dim=16", "max_frames=50"],
        "stm": [],
        "timar": ["width=32", "num_layers=1", "num_heads=2", "head_width=32", "head_blocks=1", "speech_dim=8",
                  "max_turns=2", "decoder_layers=1", "sample_steps=3"],
        "dualtalk": ["width=32", "num_layers=1", "num_heads=2", "lstm_layers=1", "speech_dim=8", "max_turns=2"],
    }[model]
    return build_config(model, "tiny" if model == "toktalk" else "small", items)


def _sampler(model, config):
    """``(params, run)`` where ``run(params, config)`` samples with fixed inputs and key."""
    key = jax.random.key(0)
    rng = np.random.default_rng(0)
    if model == "toktalk":
        from jaxtalk.models.toktalk import init_params, sample

        params = init_params(config, key)
        tokens = jnp.asarray(rng.normal(size=(1, 8, config.speech_dim)), jnp.float32)
        style = jnp.asarray(rng.normal(size=(1, config.style_vector_dim)), jnp.float32)
        return params, lambda p, c: sample(p, c, tokens, style, jax.random.key(1), sample_steps=3)
    if model == "ats":
        from jaxtalk.models.freetalk import ats

        params = ats.init_params(config, key)
        cond = ats.make_condition(config, rng.normal(size=(1, 20, config.speech_dim)).astype(np.float32), "happy", 2.0)
        return params, lambda p, c: ats.sample(p, c, cond, jax.random.key(1), sample_steps=3)
    if model == "stm":
        from jaxtalk.face import builtin_face
        from jaxtalk.models.freetalk import stm

        face = builtin_face(0, resolution="low")
        mesh = stm.prepare_mesh(np.asarray(face.template, np.float64), np.asarray(face.faces), config)
        params = stm.init_params(config, key, mesh)
        disp = jnp.asarray(0.004 * rng.normal(size=(2, config.num_landmarks, 3)), jnp.float32)
        return params, lambda p, c: stm.apply(p, c, mesh, disp)
    t = 2 * config.frames_per_turn
    us, um, as_ = (jnp.asarray(rng.normal(size=(1, t, d)), jnp.float32)
                   for d in (config.speech_dim, config.param_dim, config.speech_dim))
    if model == "timar":
        from jaxtalk.models.timar import init_params, sample

        return init_params(config, key), lambda p, c: sample(p, c, us, um, as_, jax.random.key(1))
    from jaxtalk.models.dualtalk.model import init_params
    from jaxtalk.models.dualtalk.predict import predict_window

    return init_params(config, key), lambda p, c: predict_window(p, c, us, um, as_)


@pytest.mark.parametrize("model", ["toktalk", "ats", "stm", "timar", "dualtalk"])
def test_samplers_stay_finite_in_bf16_and_near_float32(model):
    config = _tiny(model)
    params, run = _sampler(model, config)
    f32 = np.asarray(run(params, config))
    b16 = run(params, _bf16(config))
    assert b16.dtype == jnp.float32 and b16.shape == f32.shape
    b16 = np.asarray(b16)
    assert np.all(np.isfinite(b16))
    # Same weights, noise and inputs: bf16 rounding moves the result a little, not arbitrarily.
    scale = np.abs(f32).mean() + 1e-6
    assert np.abs(b16 - f32).mean() < 0.2 * scale, (np.abs(b16 - f32).mean(), scale)
    assert all(x.dtype == jnp.float32 for x in jax.tree.leaves(params) if jnp.issubdtype(x.dtype, jnp.floating))


def test_the_bf16_network_really_computes_in_bf16():
    from jaxtalk.models.toktalk import TokTalkConfig, init_params
    from jaxtalk.models.toktalk.model import Condition, velocity

    config = _bf16(TokTalkConfig.tiny())
    params = init_params(config, jax.random.key(0))
    w = 8
    cond = Condition(tokens=jnp.zeros((1, w, config.speech_dim)), style=jnp.zeros((1, config.style_vector_dim)),
                     known=jnp.zeros((1, w, config.param_dim)), known_mask=jnp.zeros((1, w), bool),
                     keep=jnp.ones((1,)), mask=jnp.ones((1, w), bool), chunked=jnp.ones((1,), bool))
    x = jnp.zeros((1, w, config.param_dim))
    text = jax.jit(lambda p: velocity(p, config, x, jnp.full((1,), 0.5), cond)).lower(params).as_text()
    dots = [line for line in text.splitlines() if "dot_general" in line or "convolution" in line]
    assert dots and sum("bf16" in line for line in dots) >= 0.8 * len(dots), dots[:5]
