"""Time grids for flow matching and DDPM noise tables with respacing, in float64 NumPy.

Tables are computed once in float64 (a float32 ``cumprod`` over 1000 betas loses digits that matter
near ``alpha_bar -> 0`` and ``-> 1``) and converted to the compute dtype exactly once, explicitly, by
:func:`RespacedSchedule.astype` at the sampler boundary. Respacing follows the convention of improved
diffusion / MAR (``space_timesteps`` with a single section): ``N = 5`` of 1000 gives
``{0, 250, 500, 749, 999}`` and ``N = 100`` gives ``{0, 10, 20, ..., 989, 999}``.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np

from jaxtalk.types import Array, Float, Int

__all__ = [
    "uniform_grid",
    "cosine_grid",
    "linear_betas",
    "cosine_betas",
    "DiffusionSchedule",
    "make_schedule",
    "space_timesteps",
    "PosteriorCoefficients",
    "posterior_coefficients",
    "RespacedSchedule",
    "respace",
]


def _num_steps(value: Any, name: str = "num_steps") -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def uniform_grid(num_steps: int) -> Float[np.ndarray, " num_steps_plus_1"]:
    """Uniform flow-matching time grid ``t_k = k / N``, k = 0..N (t = 0 noise, t = 1 data).

    Args:
        num_steps: N > 0.

    Returns:
        ``(N + 1,)`` float64 array from 0 to 1.

    Raises:
        ValueError: N not a positive integer.
    """
    n = _num_steps(num_steps)
    return np.arange(n + 1, dtype=np.float64) / n


def cosine_grid(num_steps: int) -> Float[np.ndarray, " num_steps_plus_1"]:
    """Cosine flow-matching time grid ``t_k = 1 - cos(k/N * pi/2)`` (small steps near the noise end).

    Args:
        num_steps: N > 0.

    Returns:
        ``(N + 1,)`` float64 array, ``t_0 = 0`` and ``t_N = 1`` exactly.

    Raises:
        ValueError: N not a positive integer.
    """
    n = _num_steps(num_steps)
    ts = 1.0 - np.cos(np.arange(n + 1, dtype=np.float64) / n * (np.pi / 2))
    ts[-1] = 1.0  # cos(pi/2) is 6e-17, not 0
    return ts


def linear_betas(
    num_timesteps: int = 1000, beta_start: float = 1e-4, beta_end: float = 0.02
) -> Float[np.ndarray, " timesteps"]:
    """DDPM linear beta schedule (Ho et al.), float64.

    Args:
        num_timesteps: training steps T > 0.
        beta_start: beta at step 0, in (0, 1).
        beta_end: beta at step T-1, in [beta_start, 1).

    Returns:
        ``(T,)`` float64 betas.

    Raises:
        ValueError: bad T or betas outside (0, 1).
    """
    t = _num_steps(num_timesteps, "num_timesteps")
    if not (0 < beta_start <= beta_end < 1):
        raise ValueError(f"need 0 < beta_start <= beta_end < 1, got {beta_start!r}, {beta_end!r}")
    return np.linspace(beta_start, beta_end, t, dtype=np.float64)


def cosine_betas(
    num_timesteps: int = 1000, s: float = 0.008, max_beta: float = 0.999
) -> Float[np.ndarray, " timesteps"]:
    """Cosine schedule (Nichol & Dhariwal): ``alpha_bar(t) = cos^2(((t/T) + s)/(1 + s) * pi/2)``.

    ``beta_i = min(1 - alpha_bar((i+1)/T) / alpha_bar(i/T), max_beta)``.

    Args:
        num_timesteps: T > 0.
        s: offset (0.008 in the paper and MAR).
        max_beta: cap on every beta (0.999) to avoid a singular last step.

    Returns:
        ``(T,)`` float64 betas.

    Raises:
        ValueError: bad T or cap outside (0, 1).
    """
    t = _num_steps(num_timesteps, "num_timesteps")
    if not (0 < max_beta < 1):
        raise ValueError(f"max_beta must lie in (0, 1), got {max_beta!r}")

    def alpha_bar(u: np.ndarray) -> np.ndarray:
        return np.cos((u + s) / (1 + s) * (math.pi / 2)) ** 2

    i = np.arange(t, dtype=np.float64)
    return np.minimum(1.0 - alpha_bar((i + 1) / t) / alpha_bar(i / t), max_beta)


class DiffusionSchedule(NamedTuple):
    """A DDPM noise table in float64 NumPy.

    Attributes:
        betas: ``(T,)`` per-step noise variances.
        alphas_cumprod: ``(T,)`` ``alpha_bar_t = prod_{s<=t} (1 - beta_s)``.
    """

    betas: Float[np.ndarray, " timesteps"]
    alphas_cumprod: Float[np.ndarray, " timesteps"]

    @classmethod
    def from_betas(cls, betas: Float[np.ndarray, " timesteps"]) -> DiffusionSchedule:
        """Build from betas (converted to float64).

        Raises:
            ValueError: empty, not 1-D, or betas outside (0, 1].
        """
        b = np.asarray(betas, dtype=np.float64)
        if b.ndim != 1 or b.size == 0:
            raise ValueError(f"betas must be a non-empty 1-D array, got shape {b.shape}")
        if not np.all((b > 0) & (b <= 1)):
            raise ValueError(f"betas must lie in (0, 1], got min {b.min()!r} max {b.max()!r}")
        return cls(betas=b, alphas_cumprod=np.cumprod(1.0 - b))

    @property
    def num_timesteps(self) -> int:
        return int(self.betas.shape[0])


def make_schedule(kind: str = "linear", num_timesteps: int = 1000) -> DiffusionSchedule:
    """A named DDPM schedule: ``"linear"`` (1e-4 .. 0.02) or ``"cosine"`` (s = 0.008, cap 0.999).

    Args:
        kind: ``"linear"`` or ``"cosine"``.
        num_timesteps: T > 0.

    Returns:
        The float64 :class:`DiffusionSchedule`.

    Raises:
        ValueError: unknown kind.
    """
    if kind == "linear":
        return DiffusionSchedule.from_betas(linear_betas(num_timesteps))
    if kind == "cosine":
        return DiffusionSchedule.from_betas(cosine_betas(num_timesteps))
    raise ValueError(f"unknown schedule kind {kind!r}; expected 'linear' or 'cosine'")


def space_timesteps(num_timesteps: int, num_steps: int) -> Int[np.ndarray, " num_steps"]:
    """Evenly spaced subset of training timesteps (improved-diffusion / MAR convention).

    Takes ``round(i * (T - 1) / (N - 1))`` for i = 0..N-1, accumulating the fractional stride and
    rounding half to even as the reference does, so ``(1000, 5) -> [0, 250, 500, 749, 999]``.

    Args:
        num_timesteps: T > 0 training steps.
        num_steps: N, with 0 < N <= T.

    Returns:
        ``(N,)`` int64 sorted, distinct timesteps.

    Raises:
        ValueError: N outside ``[1, T]``.
    """
    t = _num_steps(num_timesteps, "num_timesteps")
    n = _num_steps(num_steps)
    if n > t:
        raise ValueError(f"cannot respace {t} timesteps to num_steps={n} > {t}")
    if n == 1:
        return np.zeros(1, dtype=np.int64)
    stride = (t - 1) / (n - 1)
    taken, cur = [], 0.0
    for _ in range(n):  # static host-side table construction, not a traced loop
        taken.append(round(cur))
        cur += stride
    return np.asarray(taken, dtype=np.int64)


class PosteriorCoefficients(NamedTuple):
    """Coefficients of ``q(x_prev | x_t, x0) = N(coef_x0 * x0 + coef_xt * x_t, variance)``.

    Every field has the broadcast shape of the inputs of :func:`posterior_coefficients`.
    """

    coef_x0: Any
    coef_xt: Any
    variance: Any
    beta: Any


def posterior_coefficients(alpha_bar_t: Any, alpha_bar_prev: Any) -> PosteriorCoefficients:
    """Posterior ``q(x_prev | x_t, x0)`` between any two (respaced) steps ``prev < t``.

    With ``beta = 1 - alpha_bar_t / alpha_bar_prev`` (the effective beta of the jump):
    ``coef_x0 = beta sqrt(alpha_bar_prev) / (1 - alpha_bar_t)``,
    ``coef_xt = (1 - beta)^(1/2) (1 - alpha_bar_prev) / (1 - alpha_bar_t)`` and
    ``variance = beta (1 - alpha_bar_prev) / (1 - alpha_bar_t)``. ``alpha_bar_prev = 1`` denotes the
    data end (x_prev = x0, variance 0). Works elementwise on NumPy or JAX arrays.

    Args:
        alpha_bar_t: ``alpha_bar`` at the noisier step, in (0, 1).
        alpha_bar_prev: ``alpha_bar`` at the cleaner step, in ``[alpha_bar_t, 1]``.

    Returns:
        :class:`PosteriorCoefficients`.
    """
    xp = jnp if isinstance(alpha_bar_t, Array) or isinstance(alpha_bar_prev, Array) else np
    beta = 1.0 - alpha_bar_t / alpha_bar_prev
    denom = 1.0 - alpha_bar_t
    return PosteriorCoefficients(
        coef_x0=beta * xp.sqrt(alpha_bar_prev) / denom,
        coef_xt=xp.sqrt(1.0 - beta) * (1.0 - alpha_bar_prev) / denom,
        variance=beta * (1.0 - alpha_bar_prev) / denom,
        beta=beta,
    )


class RespacedSchedule(NamedTuple):
    """Per-step tables of a respaced sampler, ordered from the CLEANEST step (index 0) upwards.

    Produced in float64 NumPy by :func:`respace`; :meth:`astype` converts every table once to the
    compute dtype (JAX arrays). All fields are ``(N,)``. Samplers run i = N-1 .. 0 and feed the model
    ``timesteps[i]`` (an original training-step index).

    Attributes:
        timesteps: original timestep of each respaced step.
        alphas_cumprod: ``alpha_bar`` at each respaced step.
        alphas_cumprod_prev: ``alpha_bar`` of the next cleaner respaced step (1 for i = 0).
        posterior_coef_x0, posterior_coef_xt, posterior_variance: see :func:`posterior_coefficients`.
        posterior_log_variance_clipped: log posterior variance with entry 0 (variance 0) replaced by
            entry 1, as in the reference ("fixed_small").
        log_betas: log of the effective betas with entry 0 replaced by the posterior variance of
            entry 1 ("fixed_large", and the upper end of a learned-range variance).
    """

    timesteps: Any
    alphas_cumprod: Any
    alphas_cumprod_prev: Any
    posterior_coef_x0: Any
    posterior_coef_xt: Any
    posterior_variance: Any
    posterior_log_variance_clipped: Any
    log_betas: Any

    @property
    def num_steps(self) -> int:
        return int(np.shape(self.alphas_cumprod)[0])

    def astype(self, dtype: Any) -> RespacedSchedule:
        """Convert every table to a JAX array of ``dtype`` (the one explicit dtype boundary).

        Args:
            dtype: a floating dtype (``timesteps`` are converted to it too, as the model's time input).

        Returns:
            A :class:`RespacedSchedule` of ``(N,)`` JAX arrays.
        """
        return RespacedSchedule(*(jnp.asarray(np.asarray(f, dtype=np.float64), dtype=dtype) for f in self))


def respace(schedule: DiffusionSchedule, num_steps: int) -> RespacedSchedule:
    """Respace a schedule to ``num_steps`` evenly spaced timesteps (float64 NumPy tables).

    Args:
        schedule: the training schedule (T steps).
        num_steps: N, 0 < N <= T.

    Returns:
        :class:`RespacedSchedule` with ``(N,)`` float64 tables (``timesteps`` int64).

    Raises:
        ValueError: N outside ``[1, T]``.
    """
    steps = space_timesteps(schedule.num_timesteps, num_steps)
    abar = np.asarray(schedule.alphas_cumprod, dtype=np.float64)[steps]
    abar_prev = np.concatenate([[1.0], abar[:-1]])
    post = posterior_coefficients(abar, abar_prev)
    var = post.variance
    # Entry 0 has variance exactly 0 (x_prev is x0); the reference clips its log to entry 1's. With a
    # single step there is no entry 1: fall back to its beta (the step adds no noise anyway).
    floor = var[1] if var.shape[0] > 1 else post.beta[0]
    log_var = np.log(np.concatenate([[floor], var[1:]]))
    log_betas = np.log(np.concatenate([[floor], post.beta[1:]]))
    return RespacedSchedule(
        timesteps=steps,
        alphas_cumprod=abar,
        alphas_cumprod_prev=abar_prev,
        posterior_coef_x0=post.coef_x0,
        posterior_coef_xt=post.coef_xt,
        posterior_variance=var,
        posterior_log_variance_clipped=log_var,
        log_betas=log_betas,
    )
