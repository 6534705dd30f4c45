"""DDPM (ancestral) and DDIM (eta) samplers over respaced timesteps, as init + pure step + lax.scan.

Forward process: ``x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) eps``. The model ``apply_fn(x, t, cond)``
receives ``t: (B,)`` holding the ORIGINAL training timestep (e.g. 999 .. 0, as a float of the compute
dtype) and predicts, by ``prediction``:

* ``"x0"``: the clean sample (FreeTalk ATS, TIMAR);
* ``"eps"``: the noise (MAR);
* ``"v"``: ``v = sqrt(abar) eps - sqrt(1 - abar) x0`` (Salimans & Ho).

With ``variance="learned_range"`` the model returns twice the channels on the last axis, the second
half ``v`` in [-1, 1] interpolating the log variance between the clipped posterior variance and beta
(improved diffusion, as MAR/TIMAR train it); guidance then applies to the first half only and the
variance comes from the conditional branch.

The respaced tables (:class:`~jaxtalk.samplers.schedules.RespacedSchedule`) are computed in float64
NumPy and converted to the compute dtype once, at the public entry point; inside, they are traced
arrays, so a different schedule with the same number of steps does not recompile, and neither does
a different ``eta`` or ``cfg_scale``.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.checks import check_finite
from jaxtalk.samplers.flow import (
    ApplyFn,
    FloatLike,
    ShapedLike,
    _check_cond,
    as_model,
    guided_apply,
)
from jaxtalk.samplers.schedules import RespacedSchedule
from jaxtalk.types import Array, Float, PRNGKeyArray

__all__ = [
    "PREDICTIONS",
    "VARIANCES",
    "ClipGroup",
    "DiffusionState",
    "StepTables",
    "predict_x0",
    "clip_x0",
    "init",
    "ddim_step",
    "ddpm_step",
    "sample_ddim",
    "sample_ddpm",
]

PREDICTIONS = ("x0", "eps", "v")
VARIANCES = ("fixed_small", "fixed_large", "learned_range")


class ClipGroup(NamedTuple):
    """Clip the x0 estimate on some indices of the last axis to ``[low, high]`` (static config).

    Attributes:
        indices: indices into the last axis (e.g. the jaw group of the 56-d head vector).
        low, high: bounds, ``low <= high``.
    """

    indices: tuple[int, ...]
    low: float
    high: float


class DiffusionState(NamedTuple):
    """Loop state of the diffusion samplers.

    Attributes:
        x: ``(B, ...)`` the current noisy sample.
        x0: ``(B, ...)`` the latest (guided, clipped) estimate of the clean sample.
    """

    x: Float[Array, "batch *dims"]
    x0: Float[Array, "batch *dims"]


class StepTables(NamedTuple):
    """The scalars one respaced step needs (one row of a :class:`RespacedSchedule`), all ``()``."""

    timestep: Any
    alpha_bar: Any
    alpha_bar_prev: Any
    coef_x0: Any
    coef_xt: Any
    log_var_small: Any
    log_beta: Any
    nonzero: Any  # 0 on the final step (adds no noise), else 1


def _safe_sqrt(x: Any) -> Any:
    # sqrt(0) has an infinite derivative; the DDIM direction term is exactly 0 at the last step.
    positive = x > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, x, 1.0)), 0.0)


def predict_x0(
    output: Float[Array, "batch *dims"],
    x: Float[Array, "batch *dims"],
    alpha_bar: Float[Array, ""],
    prediction: str,
) -> Float[Array, "batch *dims"]:
    """Convert a model output of the given parameterisation to the x0 estimate.

    Args:
        output: ``(B, ...)`` model output (x0, eps or v).
        x: ``(B, ...)`` the noisy input ``x_t``.
        alpha_bar: ``()`` ``abar_t``.
        prediction: ``"x0"``, ``"eps"`` or ``"v"``.

    Returns:
        ``(B, ...)`` x0 estimate.

    Raises:
        ValueError: unknown prediction.
    """
    if prediction == "x0":
        return output
    a, s = jnp.sqrt(alpha_bar), jnp.sqrt(1 - alpha_bar)
    if prediction == "eps":
        return (x - s * output) / a
    if prediction == "v":
        return a * x - s * output
    raise ValueError(f"unknown prediction {prediction!r}; expected one of {PREDICTIONS}")


def clip_x0(x0: Float[Array, "batch *dims"], clip: Sequence[ClipGroup]) -> Float[Array, "batch *dims"]:
    """Clip groups of the last axis of the x0 estimate to their bounds.

    Args:
        x0: ``(B, ..., D)`` estimate.
        clip: static :class:`ClipGroup` s.

    Returns:
        The clipped estimate, same shape.
    """
    for group in clip:  # a static handful of parameter groups, unrolled at trace time
        idx = np.asarray(group.indices, dtype=np.int32)
        x0 = x0.at[..., idx].set(jnp.clip(x0[..., idx], group.low, group.high))
    return x0


def init(noise: Float[Array, "batch *dims"]) -> DiffusionState:
    """Initial state from Gaussian noise ``x_T``.

    Args:
        noise: ``(B, ...)`` standard normal sample.

    Returns:
        :class:`DiffusionState` with ``x = noise`` and ``x0 = 0``.
    """
    return DiffusionState(x=noise, x0=jnp.zeros_like(noise))


def _model_x0(state, tables, apply_fn, cond, uncond, cfg_scale, prediction, clip, variance):
    x = state.x
    t = jnp.broadcast_to(tables.timestep, (x.shape[0],)).astype(x.dtype)
    d = x.shape[-1]
    if variance == "learned_range":
        # Guidance acts on the prediction channels only; the variance comes from the conditional branch.
        raw = guided_apply(apply_fn, x, t, cond, uncond, cfg_scale, guided_channels=d)
        if raw.shape[-1] != 2 * d:
            raise ValueError(
                f"variance='learned_range' needs a model output with {2 * d} channels, got {raw.shape}"
            )
        out, var_v = raw[..., :d], raw[..., d:]
        frac = (var_v + 1) / 2
        log_var = frac * tables.log_beta + (1 - frac) * tables.log_var_small
    else:
        out = guided_apply(apply_fn, x, t, cond, uncond, cfg_scale)
        log_var = tables.log_var_small if variance == "fixed_small" else tables.log_beta
    x0 = clip_x0(predict_x0(out.astype(x.dtype), x, tables.alpha_bar, prediction), clip)
    return x0, log_var


def ddim_step(
    state: DiffusionState,
    tables: StepTables,
    key: PRNGKeyArray,
    *,
    apply_fn: ApplyFn,
    cond: Any,
    uncond: Any = None,
    cfg_scale: Float[Array, ""] | float = 0.0,
    eta: Float[Array, ""] | float = 0.0,
    prediction: str = "x0",
    clip: Sequence[ClipGroup] = (),
    variance: str = "fixed_small",
) -> DiffusionState:
    """One DDIM step from respaced step ``t`` to the next cleaner one (pure).

    ``x_prev = sqrt(abar_prev) x0 + sqrt(1 - abar_prev - sigma^2) eps + sigma noise`` with
    ``sigma = eta sqrt((1 - abar_prev)/(1 - abar)) sqrt(1 - abar/abar_prev)`` and ``eps`` recomputed
    from the (clipped) x0. ``eta = 0`` is deterministic; ``eta = 1`` matches DDPM's variance.

    Args:
        state: current :class:`DiffusionState`.
        tables: this step's :class:`StepTables` (compute dtype).
        key: PRNG key for this step's noise.
        apply_fn, cond, uncond, cfg_scale: see :func:`~jaxtalk.samplers.flow.guided_apply`.
        eta: ``()`` stochasticity (traced).
        prediction: ``"x0"``, ``"eps"`` or ``"v"``.
        clip: x0 clipping groups.
        variance: only matters for ``"learned_range"`` (the model output has 2x channels; DDIM
            ignores the variance half).

    Returns:
        The next :class:`DiffusionState`.
    """
    x = state.x
    x0, _ = _model_x0(state, tables, apply_fn, cond, uncond, cfg_scale, prediction, clip, variance)
    abar, abar_prev = tables.alpha_bar, tables.alpha_bar_prev
    eps = (x - jnp.sqrt(abar) * x0) / jnp.sqrt(1 - abar)
    eta = jnp.asarray(eta, x.dtype)
    sigma = eta * _safe_sqrt((1 - abar_prev) / (1 - abar) * (1 - abar / abar_prev))
    noise = jax.random.normal(key, x.shape, x.dtype)
    x_prev = (
        jnp.sqrt(abar_prev) * x0 + _safe_sqrt(1 - abar_prev - sigma**2) * eps + tables.nonzero * sigma * noise
    )
    return DiffusionState(x=x_prev, x0=x0)


def ddpm_step(
    state: DiffusionState,
    tables: StepTables,
    key: PRNGKeyArray,
    *,
    apply_fn: ApplyFn,
    cond: Any,
    uncond: Any = None,
    cfg_scale: Float[Array, ""] | float = 0.0,
    prediction: str = "x0",
    clip: Sequence[ClipGroup] = (),
    variance: str = "fixed_small",
    temperature: Float[Array, ""] | float = 1.0,
    step_noise: Float[Array, "batch *dims"] | None = None,
) -> DiffusionState:
    """One ancestral DDPM step: sample ``q(x_prev | x_t, x0_hat)`` (pure).

    ``x_prev = mean + temperature * exp(log_var / 2) * noise``: MAR's temperature scales every
    step's noise (``p_sample`` of its diffusion loss), 1 samples the model's reverse process.

    Args:
        state, tables, key, apply_fn, cond, uncond, cfg_scale, prediction, clip: see :func:`ddim_step`.
        variance: ``"fixed_small"`` (clipped posterior variance), ``"fixed_large"`` (beta) or
            ``"learned_range"``.
        temperature: ``()`` factor on the step noise (traced).
        step_noise: the standard normal draw of this step, shaped as ``state.x``, used instead of
            drawing one from ``key`` (to reproduce another implementation's random stream).

    Returns:
        The next :class:`DiffusionState` (no noise is added on the final step).
    """
    x = state.x
    x0, log_var = _model_x0(state, tables, apply_fn, cond, uncond, cfg_scale, prediction, clip, variance)
    mean = tables.coef_x0 * x0 + tables.coef_xt * x
    draw = jax.random.normal(key, x.shape, x.dtype) if step_noise is None else step_noise.astype(x.dtype)
    noise = draw * jnp.asarray(temperature, x.dtype)
    return DiffusionState(x=mean + tables.nonzero * jnp.exp(0.5 * log_var) * noise, x0=x0)


def _tables(s: RespacedSchedule, dtype: Any) -> StepTables:
    """Rows of the schedule, ordered in SAMPLING order (noisiest first), for ``lax.scan``."""
    n = s.alphas_cumprod.shape[0]
    rev = lambda a: a[::-1]  # noqa: E731
    return StepTables(
        timestep=rev(s.timesteps),
        alpha_bar=rev(s.alphas_cumprod),
        alpha_bar_prev=rev(s.alphas_cumprod_prev),
        coef_x0=rev(s.posterior_coef_x0),
        coef_xt=rev(s.posterior_coef_xt),
        log_var_small=rev(s.posterior_log_variance_clipped),
        log_beta=rev(s.log_betas),
        nonzero=(jnp.arange(n)[::-1] > 0).astype(dtype),
    )


@functools.partial(
    jax.jit,
    static_argnames=("kind", "prediction", "clip", "variance", "return_trajectory", "remat"),
)
def _sample(
    apply_fn,
    noise,
    cond,
    schedule,
    key,
    uncond,
    cfg_scale,
    eta,
    kind,
    prediction,
    clip,
    variance,
    return_trajectory,
    remat,
    step_noise=None,
):
    kwargs = dict(
        apply_fn=apply_fn,
        cond=cond,
        uncond=uncond,
        cfg_scale=cfg_scale,
        prediction=prediction,
        clip=clip,
        variance=variance,
    )
    # ``eta`` is DDIM's stochasticity or, for DDPM, the temperature on the step noise.
    if kind == "ddim":
        step_fn = functools.partial(ddim_step, eta=eta, **kwargs)
    else:
        step_fn = functools.partial(ddpm_step, temperature=eta, **kwargs)

    def body(state, xs):
        tables, k, sn = xs
        new = step_fn(state, tables, k) if sn is None else step_fn(state, tables, k, step_noise=sn)
        return new, (new.x if return_trajectory else None)

    if remat:
        body = jax.checkpoint(body)
    tables = _tables(schedule, noise.dtype)
    keys = jax.random.split(key, tables.alpha_bar.shape[0])
    state0 = init(noise)
    final, traj = jax.lax.scan(body, state0, (tables, keys, step_noise))
    if return_trajectory:
        return final.x, jnp.concatenate([noise[None], traj], axis=0)
    return final.x


def _prepare(noise, cond, schedule, key, uncond, cfg_scale, eta, prediction, clip, variance):
    noise = jnp.asarray(noise)
    if noise.ndim < 1 or not jnp.issubdtype(noise.dtype, jnp.floating):
        raise ValueError(f"noise must be a floating array with a batch axis, got {noise.dtype} {noise.shape}")
    check_finite(noise, "noise")
    if prediction not in PREDICTIONS:
        raise ValueError(f"unknown prediction {prediction!r}; expected one of {PREDICTIONS}")
    if variance not in VARIANCES:
        raise ValueError(f"unknown variance {variance!r}; expected one of {VARIANCES}")
    if not isinstance(schedule, RespacedSchedule):
        raise ValueError(f"schedule must be a RespacedSchedule (see schedules.respace), got {type(schedule)}")
    for name, field in zip(schedule._fields, schedule):
        if np.ndim(field) != 1 or np.shape(field)[0] != np.shape(schedule.alphas_cumprod)[0]:
            raise ValueError(f"schedule.{name} must be 1-D of length num_steps, got shape {np.shape(field)}")
    if np.shape(schedule.alphas_cumprod)[0] == 0:
        raise ValueError("schedule has no steps")
    # The single explicit float64 -> compute-dtype conversion (no-op for already converted tables).
    schedule = schedule.astype(noise.dtype) if isinstance(schedule.alphas_cumprod, np.ndarray) else schedule
    check_finite(schedule.alphas_cumprod, "schedule.alphas_cumprod")
    clip = tuple(ClipGroup(tuple(int(i) for i in g[0]), float(g[1]), float(g[2])) for g in clip)
    for g in clip:
        if g.low > g.high:
            raise ValueError(f"clip group {g.indices} has low {g.low} > high {g.high}")
        d = noise.shape[-1]
        if any(i < -d or i >= d for i in g.indices):
            raise ValueError(f"clip group indices {g.indices} out of range for last axis {d}")
    cfg_scale = jnp.asarray(cfg_scale, noise.dtype)
    eta = jnp.asarray(eta, noise.dtype)
    if cfg_scale.ndim != 0 or eta.ndim != 0:
        raise ValueError(f"cfg_scale and eta (DDPM: temperature) must be scalars, got shapes {cfg_scale.shape} and {eta.shape}")
    _check_cond(cond, uncond, noise.shape[0])
    if not (
        isinstance(key, jax.Array) and (jnp.issubdtype(key.dtype, jax.dtypes.prng_key) or key.shape == (2,))
    ):
        raise ValueError(f"key must be a JAX PRNG key, got {type(key).__name__} {getattr(key, 'shape', '')}")
    return noise, schedule, cfg_scale, eta, clip


def sample_ddim(
    apply_fn: ApplyFn,
    noise: FloatLike["batch *dims"],
    cond: Any,
    schedule: RespacedSchedule,
    key: PRNGKeyArray | Any,
    *,
    uncond: Any = None,
    cfg_scale: ShapedLike["*scale"] | float | int = 0.0,
    eta: ShapedLike["*scale"] | float | int = 0.0,
    prediction: str = "x0",
    clip: Sequence[ClipGroup] = (),
    variance: str = "fixed_small",
    return_trajectory: bool = False,
    remat: bool = False,
) -> Float[Array, "batch *dims"] | tuple[Float[Array, "batch *dims"], Float[Array, "grid batch *dims"]]:
    """DDIM sampling over the respaced steps of ``schedule`` (from ``x_T = noise`` to x0).

    Step j (j = 0..N-1, noisiest first) uses key ``jax.random.split(key, N)[j]``. Static (recompile):
    the function of ``apply_fn`` (see :func:`~jaxtalk.samplers.flow.as_model`), shapes, ``N``,
    ``prediction``, ``clip``, ``variance``, flags. Traced: the schedule VALUES, ``cfg_scale``, ``eta``.
    Differentiable and vmap-able.

    Args:
        apply_fn: ``apply_fn(x (B, ...), t (B,), cond) -> (B, ...)`` (``(..., 2D)`` with learned
            variance); ``t`` holds the original training timestep. Preferably a
            ``jax.tree_util.Partial(fn, params)`` so parameters are traced.
        noise: ``(B, ...)`` standard normal ``x_T``.
        cond: conditioning pytree with leading axis B.
        schedule: :func:`~jaxtalk.samplers.schedules.respace` output (float64 NumPy tables are
            converted to ``noise.dtype`` here, once; already converted JAX tables are used as given).
        key: PRNG key (used when ``eta > 0``).
        uncond: unconditional pytree for CFG, or None.
        cfg_scale: ``()`` w: ``out = (1 + w) out_cond - w out_uncond`` on the model output.
        eta: ``()`` DDIM stochasticity (0 = deterministic).
        prediction: model parameterisation, ``"x0"``, ``"eps"`` or ``"v"``.
        clip: :class:`ClipGroup` s applied to every x0 estimate.
        variance: see module docstring (DDIM only uses it to split a learned-range output).
        return_trajectory: also return ``(N + 1, B, ...)`` states from ``x_T`` to the result.
        remat: ``jax.checkpoint`` each step (for gradients through many steps).

    Returns:
        ``(B, ...)`` sample (and the trajectory when asked).

    Raises:
        ValueError: unknown prediction/variance, malformed schedule, bad clip groups, non-scalar
            knobs, cond/uncond mismatch, NaN/inf in concrete noise, bad key.
    """
    noise, schedule, cfg_scale, eta, clip = _prepare(
        noise, cond, schedule, key, uncond, cfg_scale, eta, prediction, clip, variance
    )
    return _sample(
        as_model(apply_fn),
        noise,
        cond,
        schedule,
        key,
        uncond,
        cfg_scale,
        eta,
        "ddim",
        prediction,
        clip,
        variance,
        bool(return_trajectory),
        bool(remat),
    )


def sample_ddpm(
    apply_fn: ApplyFn,
    noise: FloatLike["batch *dims"],
    cond: Any,
    schedule: RespacedSchedule,
    key: PRNGKeyArray | Any,
    *,
    uncond: Any = None,
    cfg_scale: ShapedLike["*scale"] | float | int = 0.0,
    prediction: str = "x0",
    clip: Sequence[ClipGroup] = (),
    variance: str = "fixed_small",
    temperature: ShapedLike["*scale"] | float | int = 1.0,
    return_trajectory: bool = False,
    remat: bool = False,
    step_noise: FloatLike["steps batch *dims"] | None = None,
) -> Float[Array, "batch *dims"] | tuple[Float[Array, "batch *dims"], Float[Array, "grid batch *dims"]]:
    """Ancestral DDPM sampling over the respaced steps of ``schedule``.

    Same conventions as :func:`sample_ddim` (keys, static/traced split); ``variance`` selects the
    per-step noise: ``"fixed_small"`` (default), ``"fixed_large"`` or ``"learned_range"``.

    Args:
        apply_fn, noise, cond, schedule, key, uncond, cfg_scale, prediction, clip, return_trajectory,
            remat: see :func:`sample_ddim`.
        variance: the reverse-step variance.
        temperature: ``()`` factor on every step's noise (traced; MAR's sampling temperature;
            ``noise`` itself, x_T, is used as given).
        step_noise: ``(N, B, ...)`` the standard normal draws of the N steps in sampling order
            (noisiest first), used instead of drawing them from ``key`` (the last one is never
            used: no noise is added on the final step). For reproducing another implementation's
            random stream number for number; None draws them from ``key``.

    Returns:
        ``(B, ...)`` sample (and the trajectory when asked).

    Raises:
        ValueError: as :func:`sample_ddim`, or a ``step_noise`` not shaped ``(N,) + noise.shape``.
    """
    noise, schedule, cfg_scale, eta, clip = _prepare(
        noise, cond, schedule, key, uncond, cfg_scale, temperature, prediction, clip, variance
    )
    if step_noise is not None:
        step_noise = jnp.asarray(step_noise, noise.dtype)
        expected = (np.shape(schedule.alphas_cumprod)[0],) + noise.shape
        if step_noise.shape != expected:
            raise ValueError(f"step_noise must have shape {expected} (steps, *noise.shape), got {step_noise.shape}")
    return _sample(
        as_model(apply_fn),
        noise,
        cond,
        schedule,
        key,
        uncond,
        cfg_scale,
        eta,
        "ddpm",
        prediction,
        clip,
        variance,
        bool(return_trajectory),
        bool(remat),
        step_noise,
    )
