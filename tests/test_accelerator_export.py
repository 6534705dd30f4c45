"""Ready for accelerators: every model's jitted train step, sampler and stream step lowers for the
``cuda`` and ``tpu`` platforms with :func:`jax.export.export` (nothing runs), and the exported
programs hold no host callback, no custom call outside a small portable set (a CPU-only kernel such
as LAPACK or ducc FFT would be one), no float64 and no data-dependent (dynamic) shape.

The functions exported are the library's own: the train step is the shared loop's jitted step as a
recipe builds it (captured by a loop observer before it runs), and each sampler or stream step is
the jitted program its public entry point calls (captured as it is called, so the public function's
validation and argument preparation are the real ones).
"""

from __future__ import annotations

import contextlib
import importlib
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.train.observers import StepObserver

PLATFORMS = ("cuda", "tpu")
# Custom calls that every platform implements (sharding annotations of jit and shard_map).
PORTABLE_TARGETS = {"Sharding", "SPMDFullToShardShape", "SPMDShardToFullShape", "shape_assertion"}
MODELS = ("toktalk", "ats", "stm", "timar", "dualtalk")
# Tiny configs: lowering time grows with the program.
TINY = {
    "toktalk": ("batch_size=2",),
    "ats": ("batch_size=2", "width=32", "num_layers=1", "num_heads=2", "ff_dim=64"),
    "stm": ("batch_size=2", "encoder_blocks=1", "decoder_blocks=1"),
    "timar": ("batch_size=2", "width=32", "num_layers=1", "num_heads=2", "head_width=32", "head_blocks=1",
              "decoder_layers=1", "sample_steps=2"),
    "dualtalk": ("batch_size=2", "width=32", "num_layers=1", "num_heads=2", "lstm_layers=1"),
}


class _Captured(Exception):
    pass


def custom_call_targets(text: str) -> set[str]:
    """The custom-call targets named in an exported module's MLIR text (both spellings)."""
    return set(re.findall(r'call_target_name = "([^"]+)"', text)) | set(re.findall(r"custom_call @([\w.$-]+)", text))


@contextlib.contextmanager
def _abstract_pytrees_allowed():
    """The suite's runtime type checker off while JAX rebuilds the arguments' pytrees (dataclasses
    with array annotations, such as the mesh operators) around abstract leaves, as exporting does."""
    import jaxtyping

    previous = jaxtyping.config.jaxtyping_disable
    jaxtyping.config.update("jaxtyping_disable", True)
    try:
        yield
    finally:
        jaxtyping.config.update("jaxtyping_disable", previous)


def check_portable(fn, args, kwargs=None, *, what: str) -> jax.export.Exported:
    """Export ``fn`` for :data:`PLATFORMS` and check the program (see the module docstring).

    A host callback fails either in :func:`jax.export.export` itself (it refuses them by default) or
    here, as a custom call (``xla_ffi_python_cpu_callback`` and the like).
    """
    with _abstract_pytrees_allowed():
        exported = jax.export.export(fn, platforms=PLATFORMS)(*args, **(kwargs or {}))
    assert tuple(exported.platforms) == PLATFORMS
    text = exported.mlir_module()
    foreign = custom_call_targets(text) - PORTABLE_TARGETS
    assert not foreign, f"{what}: custom calls {sorted(foreign)} are not portable"
    assert not re.search(r"\bf64\b|xf64>", text), f"{what}: float64 in the program"
    assert not re.search(r"tensor<[^>]*\?", text), f"{what}: a dynamic (data-dependent) shape"
    return exported


def test_the_checker_catches_callbacks_float64_and_cpu_only_kernels(float64):
    def with_callback(x):
        return jax.pure_callback(lambda v: np.asarray(v) * 2, jax.ShapeDtypeStruct(x.shape, x.dtype), x)

    with pytest.raises(Exception):  # noqa: B017  (export's own refusal or the custom-call check)
        check_portable(jax.jit(with_callback), (jnp.ones(3),), what="callback")
    with pytest.raises(AssertionError, match="float64"):
        check_portable(jax.jit(lambda x: x * 2), (jnp.ones(3, jnp.float64),), what="f64")
    assert "lapack_sgetrf_ffi" in custom_call_targets('stablehlo.custom_call @lapack_sgetrf_ffi(%0)')
    check_portable(jax.jit(lambda x: jnp.tanh(x) @ x.T), (jnp.ones((3, 3), jnp.float32),), what="ok")


class _CaptureStep(StepObserver):
    def before_step(self, step, state, batch, step_fn):
        self.got = (step_fn, state, batch)
        raise _Captured


@pytest.mark.slow
@pytest.mark.parametrize("model", MODELS)
def test_the_train_step_lowers_for_cuda_and_tpu(model, prepared_tiny):
    from jaxtalk.bench import recipe_setup
    from jaxtalk.runs import RunSettings
    from jaxtalk.train import LoopSettings

    quiet = LoopSettings(progress=False)
    train_fn, config, settings = recipe_setup(model, "tiny" if model == "toktalk" else "small", prepared_tiny,
                                              TINY[model])
    capture = _CaptureStep()
    with pytest.raises(_Captured):
        train_fn(config, prepared_tiny, settings.optim(2), key=jax.random.key(0),
                 run=RunSettings(steps=2, batch_size=settings.batch_size, loop=quiet, observers=[capture]))
    step_fn, state, batch = capture.got
    check_portable(step_fn, (state, batch), what=f"{model} train step")
    # The same program in bf16 (mixed precision) is as portable.
    import dataclasses

    capture = _CaptureStep()
    with pytest.raises(_Captured):
        train_fn(dataclasses.replace(config, compute_dtype="bfloat16"), prepared_tiny, settings.optim(2),
                 key=jax.random.key(0),
                 run=RunSettings(steps=2, batch_size=settings.batch_size, loop=quiet, observers=[capture]))
    check_portable(capture.got[0], capture.got[1:], what=f"{model} bf16 train step")


def _capture_call(monkeypatch, module_name: str, attr: str, call) -> tuple:
    """``(jitted function, args, kwargs)`` that ``call()`` passes to ``module_name.attr``."""
    module = importlib.import_module(module_name)
    original = getattr(module, attr)
    got = {}

    def record(*args, **kwargs):
        got.update(args=args, kwargs=kwargs)
        raise _Captured

    monkeypatch.setattr(module, attr, record)
    with pytest.raises(_Captured):
        call()
    monkeypatch.setattr(module, attr, original)
    return original, got["args"], got["kwargs"]


def _config(model):
    from jaxtalk.runs import build_config

    items = [i for i in TINY[model] if not i.startswith("batch_size")]
    extra = {"ats": ["speech_dim=16", "max_frames=50"], "timar": ["speech_dim=8", "max_turns=3"],
             "dualtalk": ["speech_dim=8", "max_turns=3"]}.get(model, [])
    return build_config(model, "tiny" if model == "toktalk" else "small", [*items, *extra])


def _turn_streams(config, turns):
    rng = np.random.default_rng(0)
    t = turns * config.frames_per_turn
    return tuple(jnp.asarray(rng.normal(size=(1, t, d)), jnp.float32)
                 for d in (config.speech_dim, config.param_dim, config.speech_dim))


def _samplers(model, monkeypatch):
    """``[(what, jitted, args, kwargs)]``: the model's sampler and, for streaming models, its stream step."""
    key = jax.random.key(0)
    rng = np.random.default_rng(0)
    config = _config(model)
    if model == "toktalk":
        from jaxtalk.models import toktalk as tt

        params = tt.init_params(config, key)
        tokens = jnp.asarray(rng.normal(size=(1, 8, config.speech_dim)), jnp.float32)
        style = jnp.asarray(rng.normal(size=(1, config.style_vector_dim)), jnp.float32)
        state = tt.init_stream(config, key, batch=1)
        chunk = jnp.asarray(rng.normal(size=(1, tt.tokens_per_chunk(config), config.speech_dim)), jnp.float32)
        return [
            ("sampler", *_capture_call(monkeypatch, "jaxtalk.models.toktalk.sampling", "_sample",
                                       lambda: tt.sample(params, config, tokens, style, key, sample_steps=2))),
            ("stream step", *_capture_call(monkeypatch, "jaxtalk.models.toktalk.streaming", "_stream_step",
                                           lambda: tt.stream_step(params, config, state, chunk, style))),
        ]
    if model == "ats":
        from jaxtalk.models.freetalk import ats

        params = ats.init_params(config, key)
        cond = ats.make_condition(config, rng.normal(size=(1, 20, config.speech_dim)).astype(np.float32), "happy", 2.0)
        return [("sampler", *_capture_call(monkeypatch, "jaxtalk.models.freetalk.ats", "_sample",
                                           lambda: ats.sample(params, config, cond, key, sample_steps=2)))]
    if model == "stm":
        from jaxtalk.face import builtin_face
        from jaxtalk.models.freetalk import stm

        face = builtin_face(0, resolution="low")
        mesh = stm.prepare_mesh(np.asarray(face.template, np.float64), np.asarray(face.faces), config)
        params = stm.init_params(config, key, mesh)
        disp = jnp.asarray(0.004 * rng.normal(size=(2, config.num_landmarks, 3)), jnp.float32)
        features = stm.stm_mesh_features(params, config, mesh)
        return [
            ("mesh features", *_capture_call(monkeypatch, "jaxtalk.models.freetalk.stm", "_mesh_features",
                                             lambda: stm.stm_mesh_features(params, config, mesh))),
            ("decoder", *_capture_call(monkeypatch, "jaxtalk.models.freetalk.stm", "_decode_jit",
                                       lambda: stm.stm_decode(params, config, features, disp, mesh))),
        ]
    us, um, as_ = _turn_streams(config, 2)
    if model == "timar":
        from jaxtalk.models.timar import init_params, sample
        from jaxtalk.models.timar.streaming import init_stream, stream_step

        params = init_params(config, key)
        state = init_stream(config, key, context=1)
        f = config.frames_per_turn
        return [
            ("sampler", *_capture_call(monkeypatch, "jaxtalk.models.timar.sampling", "_sample",
                                       lambda: sample(params, config, us, um, as_, key))),
            ("stream step", *_capture_call(monkeypatch, "jaxtalk.models.timar.streaming", "_step",
                                           lambda: stream_step(params, config, state, us[:, :f], um[:, :f], as_[:, :f]))),
        ]
    from jaxtalk.models.dualtalk.model import init_params
    from jaxtalk.models.dualtalk.predict import predict_window

    params = init_params(config, key)
    return [("predictor", *_capture_call(monkeypatch, "jaxtalk.models.dualtalk.predict", "_forward",
                                         lambda: predict_window(params, config, us, um, as_)))]


@pytest.mark.parametrize("model", MODELS)
def test_samplers_and_stream_steps_lower_for_cuda_and_tpu(model, monkeypatch):
    for what, fn, args, kwargs in _samplers(model, monkeypatch):
        check_portable(fn, args, kwargs, what=f"{model} {what}")
