"""The one model interface: every entry of ``jaxtalk.runs.REGISTRY`` is a ``ModelSpec`` whose callables
have the signatures the registry promises, and whose guidance means the same in every model."""

from __future__ import annotations

import inspect

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.runs import MODELS, REGISTRY, SPEC_PATHS, ModelSpec


def _keywords(fn) -> set[str]:
    return {p.name for p in inspect.signature(fn).parameters.values() if p.kind is inspect.Parameter.KEYWORD_ONLY}


def _positional(fn) -> list[str]:
    kinds = (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    return [p.name for p in inspect.signature(fn).parameters.values() if p.kind in kinds]


@pytest.mark.parametrize("model", MODELS)
def test_every_registry_entry_is_its_models_spec_from_the_models_own_spec_module(model):
    spec = REGISTRY[model]
    assert isinstance(spec, ModelSpec) and spec.name == model
    module = SPEC_PATHS[model].partition(":")[0]
    assert module.startswith("jaxtalk.models.") and module.endswith(".spec")
    for preset in spec.presets:
        assert isinstance(getattr(spec.config_class, preset)(), spec.config_class)
    assert spec.settings("paper") is not None and spec.settings("small") is not None
    assert spec.evaluate is not None and _positional(spec.evaluate)[:5] == ["run", "data", "split", "opts", "echo"]


@pytest.mark.parametrize("model", MODELS)
def test_every_recipe_takes_config_data_optim_a_key_and_one_run_settings(model):
    from jaxtalk.runs import RunSettings

    params = inspect.signature(REGISTRY[model].train).parameters
    assert _positional(REGISTRY[model].train) == ["config", "data", "optim"]
    assert {"key", "run", "params"} <= _keywords(REGISTRY[model].train)
    assert isinstance(params["run"].default, RunSettings) and params["params"].default is None
    # The model's own options are named: no catch-all passes settings through unchecked.
    assert not any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())


@pytest.mark.parametrize("model", MODELS)
def test_init_params_takes_config_and_key_and_nothing_more_is_required(model):
    params = inspect.signature(REGISTRY[model].init_params).parameters
    names = list(params)
    assert names[:2] == ["config", "key"]
    assert all(p.default is not inspect.Parameter.empty for p in list(params.values())[2:]), names


@pytest.mark.parametrize("model", [m for m in MODELS if REGISTRY[m].sample is not None])
def test_every_sampler_takes_sample_steps_and_the_guided_ones_cfg_scale_and_guidance(model):
    spec = REGISTRY[model]
    assert _positional(spec.sample)[:2] == ["params", "config"] and "key" in _positional(spec.sample)
    keywords = _keywords(spec.sample)
    assert "sample_steps" in keywords
    assert ({"cfg_scale", "guidance"} <= keywords) == spec.guided


@pytest.mark.parametrize("model", [m for m in MODELS if REGISTRY[m].streamer is not None])
def test_every_streamer_takes_sample_steps_at_each_step_and_over_a_whole_input(model):
    spec = REGISTRY[model]
    streamer = spec.streamer
    assert _positional(streamer.init_stream)[:2] == ["config", "key"]
    assert _positional(streamer.stream_step)[:3] == ["params", "config", "state"]
    assert _positional(streamer.stream)[:2] == ["params", "config"] and "key" in _positional(streamer.stream)
    for fn in (streamer.stream_step, streamer.stream):
        assert "sample_steps" in _keywords(fn)
        assert ("cfg_scale" in _keywords(fn)) == spec.guided


def _perturbed(params, key):
    # Zero-initialised output layers make a fresh model's prediction exactly 0; perturb so guidance shows.
    leaves, tree = jax.tree.flatten(params)
    keys = jax.random.split(key, len(leaves))
    return jax.tree.unflatten(tree, [x + 0.05 * jax.random.normal(k, x.shape, x.dtype) for x, k in zip(leaves, keys)])


def _toktalk_case():
    from jaxtalk.models.toktalk import TokTalkConfig

    config = TokTalkConfig.tiny()
    rng = np.random.default_rng(0)
    tokens = rng.normal(size=(1, 10, config.speech_dim)).astype(np.float32)  # 0.8 s at 12.5 Hz
    style = rng.normal(size=(1, config.style_vector_dim)).astype(np.float32)
    return config, (tokens, style)


def _timar_case():
    from jaxtalk.models.timar import TimarConfig

    config = TimarConfig.small(width=32, num_layers=2, num_heads=2, head_width=32, speech_dim=8, max_turns=4,
                               frames_per_turn=5)
    rng = np.random.default_rng(0)
    return config, (rng.normal(size=(1, 10, 8)).astype(np.float32), rng.normal(size=(1, 10, 56)).astype(np.float32),
                    rng.normal(size=(1, 10, 8)).astype(np.float32))


GUIDED_CASES = {"toktalk": _toktalk_case, "timar": _timar_case}


def test_every_guided_model_has_a_case_in_the_guidance_test():
    assert {m for m in MODELS if REGISTRY[m].guided} == set(GUIDED_CASES)


@pytest.mark.parametrize("model", sorted(GUIDED_CASES))
def test_guidance_weight_zero_is_sampling_without_guidance_in_every_model(model):
    spec = REGISTRY[model]
    config, inputs = GUIDED_CASES[model]()
    params = _perturbed(spec.init_params(config, jax.random.key(0)), jax.random.key(1))
    key = jax.random.key(2)
    run = lambda **kw: np.asarray(spec.sample(params, config, *inputs, key, sample_steps=2, **kw))  # noqa: E731
    unguided = run(guidance=False)
    np.testing.assert_allclose(run(cfg_scale=0.0), unguided, atol=1e-5)
    # A positive weight guides: the sample moves away from the conditional one.
    assert np.abs(run(cfg_scale=2.0) - unguided).max() > 1e-3
    assert np.all(np.isfinite(unguided)) and jnp.shape(unguided)[0] == 1


@pytest.mark.parametrize("model", MODELS)
def test_sample_and_stream_either_animate_a_models_runs_or_say_how_to_use_them(model):
    spec = REGISTRY[model]
    assert (spec.animator is None) == (spec.sample_refusal is not None)
    if spec.sample_refusal is not None:
        assert "{run}" in spec.sample_refusal
        return
    animator = spec.animator
    assert set(animator.options) <= {"--style", "--partner", "--cfg-scale", "--temperature"}
    assert ("--cfg-scale" in animator.options) == spec.guided
    assert all(suffix.startswith(".") and what for suffix, what in animator.other_inputs)
    assert _positional(animator.read)[:2] == ["run", "path"]
    assert _positional(animator.sample)[:3] == ["run", "speech", "conditions"]
    assert _positional(animator.stream)[:5] == ["run", "speech", "conditions", "on_chunk", "echo"]
    for preset in spec.presets:
        assert animator.step_frames(getattr(spec.config_class, preset)()) >= 1


@pytest.mark.parametrize("model", MODELS)
def test_the_options_a_spec_names_are_options_of_the_commands(model):
    import typer

    from jaxtalk.cli import app

    spec = REGISTRY[model]
    command = typer.main.get_command(app).commands["eval"]
    options = {name for param in command.params for name in param.opts if name.startswith("--")}
    assert set(spec.eval_options) <= options - {"--data", "--split", "--max-clips", "--seed", "--json", "--best"}
    assert spec.title and spec.reads and spec.family in (None, "freetalk")


# Model-name comparisons allowed in the command layer: none, it asks the models' specs (a ratchet that
# reached 0; never raise it).
MODEL_NAME_BRANCHES_ALLOWED = 0


def test_the_command_layer_does_not_branch_on_model_names():
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "jaxtalk"
    names = "|".join(MODELS)
    pattern = re.compile(rf"""(==|!=|\bin|\bnot in)\s*\(?\s*["']({names})["']""")
    files = [*sorted((root / "commands").glob("*.py")), root / "cli.py"]
    found = [(f.name, n) for f in files for n, line in enumerate(f.read_text().splitlines(), 1) if pattern.search(line)]
    assert len(found) <= MODEL_NAME_BRANCHES_ALLOWED, found
    assert pattern.search('if record.model == "toktalk":') and not pattern.search('model = "toktalk"')
