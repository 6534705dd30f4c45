"""FreeTalk ATS: band-diagonal cross-attention, affect conditioning, DDPM loss, DDIM sampling, errors."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.models.freetalk import ats
from jaxtalk.models.freetalk.config import ATSConfig
from jaxtalk.models.freetalk.emotions import EMOTIONS, check_intensity, emotion_ids
from jaxtalk.models.freetalk.loss import motion_loss
from jaxtalk.samplers.schedules import make_schedule
from helpers import assert_recipe_resumes_exactly

T = 12
AUDIO_DIM = 8


def _config(**kw) -> ATSConfig:
    base = dict(speech_dim=AUDIO_DIM, width=32, num_layers=1, num_heads=2, ff_dim=64, max_frames=32,
                time_frequency_dim=32)
    return ATSConfig(**{**base, **kw})



@pytest.fixture(scope="module")
def model():
    cfg = _config()
    return cfg, ats.init_params(cfg, jax.random.key(0))


def _cond(cfg, audio, emotion="happy", intensity=2.0, **kw):
    return ats.make_condition(cfg, audio, emotion, intensity, **kw)


def _audio(seed=0, b=1, frames=T):
    return np.random.default_rng(seed).normal(size=(b, frames, AUDIO_DIM)).astype(np.float32)


def test_presets_and_config_errors():
    paper = ATSConfig.paper()
    assert (paper.width, paper.num_layers, paper.num_heads, paper.ff_dim) == (512, 6, 8, 2048)
    assert (paper.num_timesteps, paper.sample_steps, paper.band_radius) == (1000, 100, 2)
    assert (paper.velocity_weight, paper.acceleration_weight, paper.motion_dim) == (0.3, 0.1, 204)
    assert ATSConfig.small().width < paper.width
    with pytest.raises(ValueError, match="divisible"):
        ATSConfig(width=30, num_heads=4)
    with pytest.raises(ValueError, match="band_radius"):
        ATSConfig(band_radius=-1)


def test_emotion_labels_match_the_corpus():
    from jaxtalk.data.synthtalk import EMOTIONS as CORPUS_EMOTIONS

    assert EMOTIONS == CORPUS_EMOTIONS and len(EMOTIONS) == 12 and EMOTIONS[0] == "neutral"
    np.testing.assert_array_equal(emotion_ids(["neutral", "upset", "happy"]), [0, 11, 5])
    with pytest.raises(ValueError, match="unknown emotion.*'bored'"):
        emotion_ids(["happy", "bored"])
    with pytest.raises(ValueError, match=r"\[0, 12\)"):
        emotion_ids(np.array([12]))


def test_cross_attention_mask_is_the_band():
    cfg = _config(band_radius=2)
    m = ats.cross_attention_mask(cfg, 7, 7)
    i, j = np.meshgrid(np.arange(7), np.arange(7), indexing="ij")
    np.testing.assert_array_equal(m, np.abs(i - j) <= 2)
    # 50 Hz features against 25 fps motion: audio frame j sits at motion time j / 2.
    m2 = ats.cross_attention_mask(_config(band_radius=1, audio_frames_per_frame=2.0), 5, 10)
    i, j = np.meshgrid(np.arange(5), np.arange(10), indexing="ij")
    np.testing.assert_array_equal(m2, np.abs(i - j / 2) <= 1)


def test_audio_outside_the_band_does_not_reach_a_frame(model):
    # One decoder layer: self-attention sees only the motion tokens, so frame i's output depends on
    # the audio only through its band-masked cross-attention row.
    cfg, params = model
    x = jax.random.normal(jax.random.key(1), (1, T, cfg.motion_dim))
    t = jnp.array([500.0])
    audio = _audio(0)
    base = ats.ats_denoise(params, cfg, x, t, _cond(cfg, audio))
    query, r = 5, cfg.band_radius
    outside = audio.copy()
    far = [j for j in range(T) if abs(j - query) > r]
    # Random offsets: a constant shift of a whole frame would vanish in the audio LayerNorm.
    outside[:, far] += 3.0 * np.random.default_rng(9).normal(size=(1, len(far), AUDIO_DIM))
    moved = ats.ats_denoise(params, cfg, x, t, _cond(cfg, outside))
    np.testing.assert_allclose(moved[0, query], base[0, query], rtol=1e-5, atol=1e-5)
    # Frames whose band covers the changed audio do move.
    assert float(jnp.abs(moved[0, 0] - base[0, 0]).max()) > 1e-3
    inside = audio.copy()
    inside[:, query + r] += 3.0 * np.random.default_rng(10).normal(size=(1, AUDIO_DIM))
    moved_in = ats.ats_denoise(params, cfg, x, t, _cond(cfg, inside))
    assert float(jnp.abs(moved_in[0, query] - base[0, query]).max()) > 1e-3


def test_emotion_and_intensity_change_the_prediction(model):
    cfg, params = model
    x = jax.random.normal(jax.random.key(2), (1, T, cfg.motion_dim))
    t = jnp.array([300.0])
    audio = _audio(1)
    outs = {
        (e, i): ats.ats_denoise(params, cfg, x, t, _cond(cfg, audio, e, i))
        for e, i in [("happy", 1.0), ("sad", 1.0), ("happy", 3.0), ("happy", 2.0)]
    }
    assert float(jnp.abs(outs["happy", 1.0] - outs["sad", 1.0]).max()) > 1e-3
    assert float(jnp.abs(outs["happy", 1.0] - outs["happy", 3.0]).max()) > 1e-3
    # Same label twice is the same function (no hidden randomness).
    again = ats.ats_denoise(params, cfg, x, t, _cond(cfg, audio, "happy", 2.0))
    np.testing.assert_array_equal(again, outs["happy", 2.0])


def test_affect_embedding_is_emotion_plus_intensity_scaled_direction(model):
    # g(e, i) = A_e + (i / I) B_e: affine in the intensity within one emotion (so levels a corpus lacks
    # for an emotion are still defined by its other levels), clipped to [1, I], and emotions differ.
    cfg, params = model
    affect = ats._AffectEmbedding(cfg)
    variables = {"params": params["params"]["affect"]}

    def g(emotion, intensity):
        return np.asarray(affect.apply(variables, jnp.asarray([emotion], jnp.int32), jnp.asarray([intensity])))[0]

    a = params["params"]["affect"]["emotion"]
    b = params["params"]["affect"]["intensity_direction"]
    np.testing.assert_allclose(g(5, 2.0), a[5] + (2.0 / 3.0) * b[5], rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(g(5, 2.0), 0.5 * (g(5, 1.0) + g(5, 3.0)), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(g(5, 1.5), 0.75 * g(5, 1.0) + 0.25 * g(5, 3.0), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(g(5, 7.0), g(5, 3.0), rtol=1e-6)  # clipped to the trained range
    assert float(np.abs(g(5, 2.0) - g(6, 2.0)).max()) > 1e-2


def test_padding_frames_do_not_affect_real_frames(model):
    cfg, params = model
    b_audio = _audio(2)
    mask = np.arange(T)[None] < 8
    x = np.asarray(jax.random.normal(jax.random.key(3), (1, T, cfg.motion_dim)))
    x2 = x.copy()
    x2[:, 8:] = 123.0
    audio2 = b_audio.copy()
    audio2[:, 8:] = -50.0
    t = jnp.array([10.0])
    a = ats.ats_denoise(params, cfg, jnp.asarray(x), t, _cond(cfg, b_audio, mask=mask, audio_mask=mask))
    b = ats.ats_denoise(params, cfg, jnp.asarray(x2), t, _cond(cfg, audio2, mask=mask, audio_mask=mask))
    np.testing.assert_allclose(a[:, :8], b[:, :8], rtol=1e-5, atol=1e-5)


@pytest.mark.slow
def test_one_ddim_step_is_the_denoiser_at_step_zero(model):
    # Respacing 1000 steps to one keeps timestep 0, where DDIM returns the x0 estimate itself.
    cfg, params = model
    cond = _cond(cfg, _audio(3, b=2), ["angry", "neutral"], [1.0, 3.0])
    key = jax.random.key(7)
    out = ats.sample(params, cfg, cond, key, sample_steps=1)
    noise = jax.random.normal(jax.random.split(key)[0], (2, T, cfg.motion_dim))
    ref = ats.ats_denoise(params, cfg, noise, jnp.zeros((2,)), cond) / cfg.displacement_scale
    np.testing.assert_allclose(out.reshape(2, T, -1), ref, rtol=1e-4, atol=1e-6)


@pytest.mark.slow
def test_explicit_noise_and_remat_reproduce_the_keyed_sampler(model):
    cfg, params = model
    cond = _cond(cfg, _audio(6, b=2), ["sad", "happy"], [2.0, 1.0])
    key = jax.random.key(11)
    keyed = ats.sample(params, cfg, cond, key, sample_steps=3)
    noise = jax.random.normal(jax.random.split(key)[0], (2, T, cfg.motion_dim))
    np.testing.assert_array_equal(ats.sample(params, cfg, cond, None, sample_steps=3, noise=noise), keyed)
    np.testing.assert_allclose(ats.sample(params, cfg, cond, None, sample_steps=3, noise=noise, remat=True),
                               keyed, rtol=1e-5, atol=1e-7)
    # The sample is a differentiable function of the starting noise (used by jaxtalk.fit's inversions).
    grad = jax.grad(lambda n: jnp.sum(ats.sample(params, cfg, cond, None, sample_steps=3, noise=n, remat=True)))
    assert float(jnp.abs(grad(noise)).max()) > 0
    with pytest.raises(ValueError, match=r"noise must have shape \(2, 12, 204\)"):
        ats.sample(params, cfg, cond, None, noise=noise[:, :5])
    with pytest.raises(ValueError, match="NaN or inf"):
        ats.sample(params, cfg, cond, None, noise=np.full((2, T, cfg.motion_dim), np.nan, np.float32))
    with pytest.raises(ValueError, match="needs a key"):
        ats.sample(params, cfg, cond, None)
    with pytest.raises(ValueError, match="needs a key for eta > 0"):
        ats.sample(params, cfg, cond, None, noise=noise, eta=0.5)


def test_ddim_shapes_and_no_recompilation_for_traced_knobs(model):
    cfg, params = model
    cond = _cond(cfg, _audio(4, b=2), ["pleased", "ill"], 1.0)
    key = jax.random.key(0)
    first = ats.sample(params, cfg, cond, key, sample_steps=4)
    assert first.shape == (2, T, 68, 3) and bool(jnp.all(jnp.isfinite(first)))
    size = ats._sample._cache_size()
    sweep = [
        ats.sample(params, cfg, cond._replace(intensity=jnp.asarray([i, 3.0], jnp.float32)), key,
                       sample_steps=4, eta=eta)
        for i, eta in [(1.5, 0.0), (3.0, 0.5), (2.0, 1.0)]
    ]
    assert ats._sample._cache_size() == size
    assert float(jnp.abs(sweep[0] - first).max()) > 0  # intensity reached the model
    assert float(jnp.abs(sweep[1] - sweep[2]).max()) > 0
    # Deterministic DDIM: same key, same result.
    np.testing.assert_array_equal(ats.sample(params, cfg, cond, key, sample_steps=4), first)
    with pytest.raises(ValueError, match="sample_steps"):
        ats.sample(params, cfg, cond, key, sample_steps=0)
    with pytest.raises(ValueError, match="eta"):
        ats.sample(params, cfg, cond, key, sample_steps=4, eta=float("nan"))


def test_motion_loss_matches_a_brute_force_reference():
    rng = np.random.default_rng(0)
    pred, target = rng.normal(size=(2, 2, 6, 4, 3))
    fmask = np.array([[1, 1, 1, 1, 0, 0], [1, 1, 1, 1, 1, 1]], bool)
    pmask = np.array([[1, 1, 1, 0], [1, 1, 1, 1]], bool)
    loss, parts = motion_loss(jnp.asarray(pred), jnp.asarray(target), jnp.asarray(fmask), jnp.asarray(pmask),
                              velocity_weight=0.3, acceleration_weight=0.1)

    def ref(order):
        num = den = 0.0
        for b in range(2):
            e = pred[b] - target[b]
            for t in range(6 - order):
                if not fmask[b, t:t + order + 1].all():
                    continue
                d = e[t] if order == 0 else (e[t + 1] - e[t] if order == 1 else e[t + 2] - 2 * e[t + 1] + e[t])
                for k in range(4):
                    if pmask[b, k]:
                        num += float(np.sum(d[k] ** 2))
                        den += 1
        return num / den

    np.testing.assert_allclose(parts["position"], ref(0), rtol=1e-5)
    np.testing.assert_allclose(parts["velocity"], ref(1), rtol=1e-5)
    np.testing.assert_allclose(parts["acceleration"], ref(2), rtol=1e-5)
    np.testing.assert_allclose(loss, ref(0) + 0.3 * ref(1) + 0.1 * ref(2), rtol=1e-5)


def test_loss_is_differentiable_and_masks_padding(model):
    cfg, params = model
    rng = np.random.default_rng(5)
    batch = {
        "displacements": (0.003 * rng.normal(size=(2, T, 68, 3))).astype(np.float32),
        "audio": _audio(5, b=2),
        "emotion": np.array([1, 5]),
        "intensity": np.array([1.0, 3.0], np.float32),
        "mask": np.arange(T)[None].repeat(2, 0) < np.array([[T], [7]]),
    }
    value_and_grad = jax.jit(jax.value_and_grad(ats.make_loss_fn(cfg), has_aux=True))
    key = jax.random.key(3)
    (loss, metrics), grads = value_and_grad(params, batch, key)
    assert np.isfinite(float(loss)) and set(metrics) == {"position", "velocity", "acceleration"}
    norms = [float(jnp.linalg.norm(g)) for g in jax.tree.leaves(grads)]
    assert all(np.isfinite(norms)) and max(norms) > 0
    # Values in padded frames are ignored.
    junk = dict(batch, displacements=batch["displacements"].copy())
    junk["displacements"][1, 7:] = 5.0
    np.testing.assert_allclose(value_and_grad(params, junk, key)[0][0], loss, rtol=1e-5)


def test_bad_inputs_raise_clear_errors(model):
    cfg, _ = model
    audio = _audio(0)
    with pytest.raises(ValueError, match="unknown emotion"):
        _cond(cfg, audio, "furious")
    with pytest.raises(ValueError, match=r"intensity must lie in \[1, 3\]"):
        _cond(cfg, audio, "happy", 3.5)
    with pytest.raises(ValueError, match=r"intensity must lie in \[1, 3\]"):
        _cond(cfg, audio, "happy", 0.0)
    with pytest.raises(ValueError, match="NaN"):
        check_intensity(float("nan"), 3, 1)
    with pytest.raises(ValueError, match="audio features must have shape"):
        _cond(cfg, audio[..., :5])
    bad = audio.copy()
    bad[0, 3, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        _cond(cfg, bad)
    with pytest.raises(ValueError, match="max_audio_frames|max_frames"):
        _cond(cfg, _audio(0, frames=40))
    with pytest.raises(ValueError, match="one emotion per example"):
        _cond(cfg, _audio(0, b=2), ["happy", "sad", "ill"])


def test_training_schedule_is_the_linear_ddpm_table():
    abar = ats._alphas_cumprod(1000)
    np.testing.assert_allclose(abar, make_schedule("linear", 1000).alphas_cumprod)
    np.testing.assert_allclose(abar[0], 1 - 1e-4)
    np.testing.assert_allclose(abar[-1], np.prod(1 - np.linspace(1e-4, 0.02, 1000)))


@pytest.mark.slow
def test_recipe_resumes_exactly_from_its_checkpoint(prepared_tiny, tmp_path):
    # ATS's one training path, the recipe, resumed from its step-2 checkpoint (tests/helpers.py).
    from jaxtalk.models.freetalk.recipe import train_ats

    cfg = _config(speech_dim=prepared_tiny.manifest["speech_dim"], max_frames=T, displacement_scale=1.0)
    assert_recipe_resumes_exactly(train_ats, cfg, prepared_tiny, tmp_path, window_frames=T)
