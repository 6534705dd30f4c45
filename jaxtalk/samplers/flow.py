"""Euler ODE sampler for conditional flow matching, with batched CFG and path-consistent inpainting.

Path and target (TokTalk / CosyVoice): ``x_t = (1 - (1 - sigma_min) t) z + t x1`` with
``z ~ N(0, I)`` at ``t = 0`` and data at ``t = 1``; the model predicts the velocity
``u = x1 - (1 - sigma_min) z``. Euler: ``x_{k+1} = x_k + (t_{k+1} - t_k) v(x_k, t_k)``.

The sampler is :func:`init` + a pure :func:`step`, scanned over the intervals of a time grid ``ts``
(a traced array: one compiled program serves uniform, cosine or any other grid with the same number
of steps). The model enters as ``apply_fn(x, t, cond)`` with ``x: (B, ...)``, ``t: (B,)`` and
``cond`` a pytree of arrays with leading axis B; it returns the velocity, shaped like ``x``.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.checks import check_finite
from jaxtalk.types import Array, Float, Shaped

__all__ = [
    "ApplyFn",
    "FlowState",
    "as_model",
    "guided_apply",
    "init",
    "step",
    "sample_euler",
]


# Public entry points take JAX or NumPy arrays. Shapes/dtypes that the code validates itself are
# annotated loosely so that a bad value reaches the ValueError that names it.
class _Like:
    def __init__(self, kind: Any) -> None:
        self.kind = kind

    def __getitem__(self, dims: str) -> Any:
        return self.kind[Array, dims] | self.kind[np.ndarray, dims]


FloatLike = _Like(Float)
ShapedLike = _Like(Shaped)

ApplyFn = Callable[[Any, Any, Any], Any]
"""``apply_fn(x: (B, ...), t: (B,), cond: pytree with leading B) -> prediction shaped like x``."""


def as_model(apply_fn: ApplyFn | Any) -> jax.tree_util.Partial:
    """The model as a pytree that can cross ``jit`` as an ordinary argument.

    A ``jax.tree_util.Partial(fn, params)`` keeps ``params`` as traced leaves (new parameters do not
    recompile, and they are not baked into the executable as constants); any other callable is
    wrapped as ``Partial(fn)``, whose identity is part of the jit cache key (so the same function
    object must be passed again to reuse the compiled sampler).

    Args:
        apply_fn: a callable ``apply_fn(x, t, cond)`` or a ``jax.tree_util.Partial``.

    Returns:
        A ``jax.tree_util.Partial``.

    Raises:
        ValueError: ``apply_fn`` is not callable.
    """
    if isinstance(apply_fn, jax.tree_util.Partial):
        return apply_fn
    if not callable(apply_fn):
        raise ValueError(f"apply_fn must be callable, got {type(apply_fn).__name__}")
    return jax.tree_util.Partial(apply_fn)


class FlowState(NamedTuple):
    """Loop state of the Euler sampler.

    Attributes:
        x: ``(B, ...)`` the current sample at time ``t``.
        z: ``(B, ...)`` the initial noise (kept for path-consistent inpainting).
        t: ``()`` the current time.
    """

    x: Float[Array, "batch *dims"]
    z: Float[Array, "batch *dims"]
    t: Float[Array, ""]


def guided_apply(
    apply_fn: ApplyFn,
    x: Float[Array, "batch *dims"],
    t: Float[Array, " batch"],
    cond: Any,
    uncond: Any = None,
    cfg_scale: Float[Array, ""] | float = 0.0,
    guided_channels: int | None = None,
) -> Float[Array, "batch *out"]:
    """Model prediction with classifier-free guidance in ONE batched call of ``apply_fn``.

    Without ``uncond``: ``apply_fn(x, t, cond)``. With it, ``x`` and ``t`` are stacked twice and
    ``cond``/``uncond`` leaf-wise along axis 0 (batch 2B), and the output is
    ``(1 + w) out_cond - w out_uncond``.

    This is jaxtalk's one guidance convention, which every model's ``cfg_scale`` (and the CLI's
    ``--cfg-scale``) takes: Ho and Salimans' guidance weight w, 0 = no guidance (the conditional
    prediction), -1 = the unconditional one, > 0 guided. A paper that writes
    ``u + omega (c - u)`` (MAR, TIMAR) has ``omega = 1 + w``.

    Args:
        apply_fn: the model.
        x: ``(B, ...)`` model input.
        t: ``(B,)`` per-example time.
        cond: conditioning pytree, every leaf with leading axis B.
        uncond: the unconditional pytree (same structure and shapes), or None for no guidance.
        cfg_scale: ``()`` guidance weight w (traced).
        guided_channels: if given, guide only the first ``guided_channels`` entries of the output's
            last axis and take the rest from the conditional branch (e.g. a learned variance).

    Returns:
        ``(B, ...)`` the guided prediction.
    """
    if uncond is None:
        return apply_fn(x, t, cond)
    both = jax.tree.map(lambda c, u: jnp.concatenate([c, u], axis=0), cond, uncond)
    out = apply_fn(jnp.concatenate([x, x], axis=0), jnp.concatenate([t, t], axis=0), both)
    out_c, out_u = jnp.split(out, 2, axis=0)
    w = jnp.asarray(cfg_scale, out.dtype)
    guided = (1 + w) * out_c - w * out_u
    if guided_channels is not None:
        guided = jnp.concatenate([guided[..., :guided_channels], out_c[..., guided_channels:]], axis=-1)
    return guided


def _path(z: Any, x1: Any, t: Any, sigma_min: float) -> Any:
    return (1 - (1 - sigma_min) * t) * z + t * x1


def _impose(x: Any, z: Any, t: Any, known: Any, known_mask: Any, sigma_min: float) -> Any:
    if known is None:
        return x
    return jnp.where(known_mask, _path(z, known, t, sigma_min), x)


def init(
    noise: Float[Array, "batch *dims"],
    t0: Float[Array, ""] | float = 0.0,
    *,
    known: Float[Array, "batch *dims"] | None = None,
    known_mask: Shaped[Array, "batch *mdims"] | None = None,
    sigma_min: float = 1e-6,
) -> FlowState:
    """Initial state at time ``t0`` (normally 0): ``x = noise`` with known entries put on their path.

    Args:
        noise: ``(B, ...)`` the Gaussian sample z.
        t0: ``()`` start time (``ts[0]``).
        known: optional ``(B, ...)`` known values (inpainting), shaped like ``noise``.
        known_mask: ``(B, ...)`` bool broadcastable to ``noise`` (same rank), True where known.
        sigma_min: the path's minimum noise level.

    Returns:
        :class:`FlowState`.
    """
    t0 = jnp.asarray(t0, noise.dtype)
    x = _impose(noise, noise, t0, known, known_mask, sigma_min)
    return FlowState(x=x, z=noise, t=t0)


def step(
    state: FlowState,
    t1: Float[Array, ""],
    *,
    apply_fn: ApplyFn,
    cond: Any,
    uncond: Any = None,
    cfg_scale: Float[Array, ""] | float = 0.0,
    known: Float[Array, "batch *dims"] | None = None,
    known_mask: Shaped[Array, "batch *mdims"] | None = None,
    sigma_min: float = 1e-6,
) -> FlowState:
    """One Euler step from ``state.t`` to ``t1`` (pure; usable in a caller's own loop).

    Evaluates the (guided) velocity at ``(state.x, state.t)``, moves to ``t1`` and, when inpainting,
    re-imposes the known entries at their path value ``(1 - (1 - sigma_min) t1) z + t1 known`` with
    the same ``z`` as the sample.

    Args:
        state: current :class:`FlowState`.
        t1: ``()`` the next time.
        apply_fn, cond, uncond, cfg_scale: see :func:`guided_apply`.
        known, known_mask, sigma_min: see :func:`init`.

    Returns:
        The :class:`FlowState` at ``t1``.
    """
    x, z, t0 = state
    t_batch = jnp.broadcast_to(t0, (x.shape[0],))
    v = guided_apply(apply_fn, x, t_batch, cond, uncond, cfg_scale)
    t1 = jnp.asarray(t1, x.dtype)
    x = x + (t1 - t0) * v.astype(x.dtype)
    x = _impose(x, z, t1, known, known_mask, sigma_min)
    return FlowState(x=x, z=z, t=t1)


@functools.partial(jax.jit, static_argnames=("sigma_min", "return_trajectory", "remat"))
def _sample_euler(
    apply_fn, noise, cond, ts, uncond, cfg_scale, known, known_mask, sigma_min, return_trajectory, remat
):
    kwargs = dict(
        apply_fn=apply_fn,
        cond=cond,
        uncond=uncond,
        cfg_scale=cfg_scale,
        known=known,
        known_mask=known_mask,
        sigma_min=sigma_min,
    )

    def body(state, t1):
        new = step(state, t1, **kwargs)
        return new, (new.x if return_trajectory else None)

    if remat:
        body = jax.checkpoint(body)
    state0 = init(noise, ts[0], known=known, known_mask=known_mask, sigma_min=sigma_min)
    final, traj = jax.lax.scan(body, state0, ts[1:])
    x = final.x
    if known is not None:
        # Along the path the known entries sit at sigma_min * z + known at t = 1; the result must hold
        # exactly the given values.
        x = jnp.where(known_mask, known, x)
    if return_trajectory:
        traj = jnp.concatenate([state0.x[None], traj], axis=0)
        traj = traj.at[-1].set(x)
        return x, traj
    return x


def sample_euler(
    apply_fn: ApplyFn,
    noise: FloatLike["batch *dims"],
    cond: Any,
    ts: ShapedLike["*grid"],
    *,
    uncond: Any = None,
    cfg_scale: ShapedLike["*scale"] | float | int = 0.0,
    known: ShapedLike["*kdims"] | None = None,
    known_mask: ShapedLike["*mdims"] | None = None,
    sigma_min: float = 1e-6,
    return_trajectory: bool = False,
    remat: bool = False,
) -> Float[Array, "batch *dims"] | tuple[Float[Array, "batch *dims"], Float[Array, "grid batch *dims"]]:
    """Sample a conditional flow-matching model with Euler steps over the time grid ``ts``.

    jit-compiled; recompiles only when a static thing changes: the function of ``apply_fn`` (by
    identity: pass the same object; wrap parameters as ``jax.tree_util.Partial(fn, params)`` so they
    are traced, see :func:`as_model`), shapes/dtypes (including ``len(ts)``), pytree structure (e.g.
    ``uncond`` None or not), ``sigma_min``, ``return_trajectory``, ``remat``. ``cfg_scale`` and the
    VALUES of ``ts`` are traced. Differentiable (w.r.t. ``noise``, ``cond``, ``cfg_scale``, ``ts``)
    and vmap-able. Concrete inputs are checked for NaN/inf (one small device sync per call).

    Args:
        apply_fn: velocity model ``apply_fn(x (B, ...), t (B,), cond) -> (B, ...)``; preferably a
            ``jax.tree_util.Partial(fn, params)``.
        noise: ``(B, ...)`` the starting Gaussian sample z (draw it with ``jax.random.normal``).
        cond: conditioning pytree; every leaf has leading axis B.
        ts: ``(N + 1,)`` increasing times, normally from 0 to 1 (e.g. :func:`cosine_grid`); N steps.
        uncond: unconditional pytree for classifier-free guidance (same structure as ``cond``), or None.
        cfg_scale: ``()`` guidance weight w: ``v = (1 + w) v_cond - w v_uncond``.
        known: ``(B, ...)`` values to inpaint (e.g. the overlap with the previous chunk), or None.
        known_mask: bool, same rank as ``noise`` and broadcastable to it (e.g. ``(B, T, 1)``); True
            where ``known`` holds. Required iff ``known`` is given.
        sigma_min: minimum noise level of the path.
        return_trajectory: also return every state including the start.
        remat: ``jax.checkpoint`` the step (memory O(1) in N when differentiating through sampling).

    Returns:
        ``x1: (B, ...)``; with ``return_trajectory`` also ``(N + 1, B, ...)`` states (the last equals x1).
        Known entries of ``x1`` equal ``known`` exactly.

    Raises:
        ValueError: ``ts`` not 1-D with >= 2 entries or (when concrete) not finite; noise without a
            batch axis or not floating; ``known``/``known_mask`` given alone or with wrong shapes;
            NaN/inf in concrete inputs; ``uncond`` with a different structure from ``cond``.
    """
    noise = jnp.asarray(noise)
    if noise.ndim < 1 or not jnp.issubdtype(noise.dtype, jnp.floating):
        raise ValueError(f"noise must be a floating array with a batch axis, got {noise.dtype} {noise.shape}")
    dtype = noise.dtype
    ts = jnp.asarray(ts, dtype)
    if ts.ndim != 1 or ts.shape[0] < 2:
        raise ValueError(f"ts must be a 1-D grid with at least 2 times, got shape {ts.shape}")
    check_finite(ts, "ts")
    check_finite(noise, "noise")
    cfg_scale = jnp.asarray(cfg_scale, dtype)
    if cfg_scale.ndim != 0:
        raise ValueError(f"cfg_scale must be a scalar (vmap for several), got shape {cfg_scale.shape}")
    _check_cond(cond, uncond, noise.shape[0])
    known, known_mask = _check_known(known, known_mask, noise)
    return _sample_euler(
        as_model(apply_fn),
        noise,
        cond,
        ts,
        uncond,
        cfg_scale,
        known,
        known_mask,
        float(sigma_min),
        bool(return_trajectory),
        bool(remat),
    )


def _check_cond(cond: Any, uncond: Any, batch: int) -> None:
    for leaf in jax.tree.leaves(cond):
        shape = np.shape(leaf)
        if len(shape) == 0 or shape[0] != batch:
            raise ValueError(f"every cond leaf needs leading batch axis {batch}, got shape {shape}")
    if uncond is not None:
        if jax.tree.structure(uncond) != jax.tree.structure(cond):
            raise ValueError(
                f"uncond must have the structure of cond: {jax.tree.structure(uncond)} vs "
                f"{jax.tree.structure(cond)}"
            )
        for c, u in zip(jax.tree.leaves(cond), jax.tree.leaves(uncond)):
            if np.shape(c) != np.shape(u):
                raise ValueError(f"uncond leaf shape {np.shape(u)} != cond leaf shape {np.shape(c)}")


def _check_known(known: Any, known_mask: Any, noise: Any) -> tuple[Any, Any]:
    if (known is None) != (known_mask is None):
        raise ValueError("known and known_mask must be given together")
    if known is None:
        return None, None
    known = jnp.asarray(known, noise.dtype)
    known_mask = jnp.asarray(known_mask)
    if known.shape != noise.shape:
        raise ValueError(f"known must have the noise shape {noise.shape}, got {known.shape}")
    if known_mask.dtype != bool:
        raise ValueError(f"known_mask must be bool, got {known_mask.dtype}")
    if known_mask.ndim != noise.ndim or any(m not in (1, n) for m, n in zip(known_mask.shape, noise.shape)):
        raise ValueError(
            f"known_mask shape {known_mask.shape} must have rank {noise.ndim} and broadcast to {noise.shape}"
        )
    check_finite(known, "known")
    return known, known_mask
