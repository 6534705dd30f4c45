"""DiffusionNet (Sharp et al. 2022) in Flax Linen, with the mesh operators fed in as arrays.

One network is written for one mesh: features ``(V, C)`` or ``(V, *frames, C)`` plus a
:class:`DiffusionOperators` pytree. Frames are carried as extra axes BETWEEN the vertex and the
channel axis (:func:`apply_frames` moves them there), so every operator product is one plain 2-D
matmul or row gather over ``(V, frames * C)``: the eigenbasis products become ``(V, k) x (k, T C)``
(one wide matmul for all frames, no per-frame batching or layout transposes inside the network)
and the gradient gathers read contiguous rows of ``T C`` floats. Meshes of different sizes are
batched by padding to a common vertex count with zero-mass vertices whose eigenvector rows and
gradient rows are zero (:func:`stack_operators`, :func:`apply_meshes`), so padding never leaks
into the real vertices.

Operators inside jitted code (never a V x V matrix):
* spectral diffusion uses the dense (V, k) eigenbasis: two skinny matmuls;
* the two sparse tangent-gradient operators are stored in a padded row ("ELL") layout: per vertex
  the column indices and X/Y weights of its one-ring (:func:`apply_gradient`), i.e. one row gather
  shared by both components and a dense reduction (no scatter in the forward pass; the backward
  pass of the gather is a scatter-add). This costs O(V D T C) memory
  traffic instead of the 2 V k T C FLOPs of multiplying by a precomputed dense ``G Phi``.

FLOP budget per vertex, frame and block at width C (k = C = 128 in the paper size): projection and
reconstruction 2 x 2kC, the complex-linear map of the gradient features 3 x 2C^2 (three real
matmuls, Karatsuba's complex product, instead of four) and the per-vertex MLP (3C -> C -> C -> C)
5 x 2C^2, i.e. about 10 x 2C^2: ~2.2 GFLOP per block and 8.8 GFLOP per frame at 6.7k vertices.

Learned diffusion time: one scalar per channel, initialised at 0 like the reference. The reference
clamps the stored parameter to >= 1e-8 after each step; here the forward pass uses
``max(t, 1e-8)`` with a straight-through gradient, so ``t`` can still leave 0 (a plain ``maximum``
would have zero gradient at the initial value and never learn).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

from jaxtalk.geometry.operators import Operators
from jaxtalk.nn.precision import matmul_layer
from jaxtalk.types import Array, Float, Int

__all__ = [
    "DiffusionOperators",
    "DiffusionNetConfig",
    "to_diffusion_operators",
    "stack_operators",
    "max_degree",
    "spectral_diffusion",
    "apply_gradient",
    "LearnedTimeDiffusion",
    "SpatialGradientFeatures",
    "DiffusionNetBlock",
    "DiffusionNet",
    "apply_frames",
    "apply_meshes",
]


@flax.struct.dataclass
class DiffusionOperators:
    """Operators of one mesh (or, with a leading axis, a padded batch of meshes) as JAX arrays.

    Attributes:
        mass: (V,) lumped mass; 0 on padding vertices.
        evals: (k,) eigenvalues, ascending.
        evecs: (V, k) M-orthonormal eigenvectors; zero rows on padding vertices.
        grad_index: (V, D) int32 column index of each one-ring entry (padding slots point at 0).
        grad_x: (V, D) X-component weights (0 in padding slots and padding rows).
        grad_y: (V, D) Y-component weights.
    """

    mass: Float[Array, "*b verts"]
    evals: Float[Array, "*b k"]
    evecs: Float[Array, "*b verts k"]
    grad_index: Int[Array, "*b verts deg"]
    grad_x: Float[Array, "*b verts deg"]
    grad_y: Float[Array, "*b verts deg"]

    @property
    def num_vertices(self) -> int:
        return int(self.mass.shape[-1])


def _csr_to_ell(grad_x: sp.csr_matrix, grad_y: sp.csr_matrix, num_rows: int, degree: int) -> tuple[np.ndarray, ...]:
    gx = sp.csr_matrix(grad_x)
    gy = sp.csr_matrix(grad_y)
    if gx.shape != gy.shape or not (
        np.array_equal(gx.indptr, gy.indptr) and np.array_equal(gx.indices, gy.indices)
    ):
        raise ValueError("grad_x and grad_y must share one sparsity pattern (same CSR indptr/indices)")
    counts = np.diff(gx.indptr)
    rows = np.repeat(np.arange(gx.shape[0]), counts)
    slots = np.arange(gx.nnz) - gx.indptr[rows]  # position of each entry inside its row
    index = np.zeros((num_rows, degree), dtype=np.int32)
    wx = np.zeros((num_rows, degree), dtype=np.float32)
    wy = np.zeros((num_rows, degree), dtype=np.float32)
    index[rows, slots] = gx.indices
    wx[rows, slots] = gx.data
    wy[rows, slots] = gy.data
    return index, wx, wy


def max_degree(ops: Operators) -> int:
    """The widest one-ring of the mesh's gradient operators (entries per row, at least 1).

    This is the ``degree`` that :func:`to_diffusion_operators` pads to by default; pass the maximum
    over several meshes to give them a common padded layout.

    Args:
        ops: operators from :func:`jaxtalk.geometry.operators.compute_operators`.

    Returns:
        The largest number of stored entries in a row of ``ops.grad_x`` (>= 1).
    """
    return int(np.diff(sp.csr_matrix(ops.grad_x).indptr).max(initial=1))


def to_diffusion_operators(
    ops: Operators, *, num_vertices: int | None = None, degree: int | None = None
) -> DiffusionOperators:
    """Convert precomputed operators to JAX arrays, optionally padded.

    Args:
        ops: operators from :func:`jaxtalk.geometry.operators.compute_operators`.
        num_vertices: pad to this many vertices (zero mass, zero eigenvector and gradient rows).
        degree: pad the per-vertex one-ring width to this (default: the mesh's maximum).

    Returns:
        A :class:`DiffusionOperators` with float32 arrays.

    Raises:
        ValueError: padding sizes smaller than the mesh's.
    """
    n = ops.num_vertices
    total = n if num_vertices is None else num_vertices
    width = max_degree(ops) if degree is None else degree
    if total < n:
        raise ValueError(f"num_vertices={total} is smaller than the mesh's {n} vertices")
    if width < max_degree(ops):
        raise ValueError(f"degree={width} is smaller than the mesh's one-ring width {max_degree(ops)}")
    index, wx, wy = _csr_to_ell(ops.grad_x, ops.grad_y, total, width)
    mass = np.zeros(total, np.float32)
    mass[:n] = ops.mass
    evecs = np.zeros((total, ops.k), np.float32)
    evecs[:n] = ops.evecs
    return DiffusionOperators(
        mass=jnp.asarray(mass),
        evals=jnp.asarray(ops.evals, dtype=jnp.float32),
        evecs=jnp.asarray(evecs),
        grad_index=jnp.asarray(index),
        grad_x=jnp.asarray(wx),
        grad_y=jnp.asarray(wy),
    )


def stack_operators(ops_list: Sequence[Operators], *, num_vertices: int | None = None) -> DiffusionOperators:
    """Pad several meshes' operators to a common size and stack them on a leading mesh axis.

    Args:
        ops_list: operators with the same ``k``.
        num_vertices: common vertex count (default: the largest mesh's).

    Returns:
        A :class:`DiffusionOperators` whose arrays have a leading axis of ``len(ops_list)``.

    Raises:
        ValueError: empty list or differing ``k``.
    """
    if not ops_list:
        raise ValueError("stack_operators needs at least one Operators")
    ks = {o.k for o in ops_list}
    if len(ks) != 1:
        raise ValueError(f"all meshes must have the same number of eigenpairs, got k in {sorted(ks)}")
    total = max(o.num_vertices for o in ops_list) if num_vertices is None else num_vertices
    degree = max(max_degree(o) for o in ops_list)
    padded = [to_diffusion_operators(o, num_vertices=total, degree=degree) for o in ops_list]
    return jax.tree.map(lambda *xs: jnp.stack(xs), *padded)


def _to_basis(x: Array, mass: Array, evecs: Array) -> Array:
    """``Phi^T M x`` for ``x`` of shape (V, *frames, C): one (k, V) x (V, frames * C) matmul."""
    flat = x.reshape(x.shape[0], -1)
    return (evecs.T @ (mass[:, None] * flat)).reshape(evecs.shape[1], *x.shape[1:])


def _from_basis(coefs: Array, evecs: Array) -> Array:
    """``Phi c`` for ``c`` of shape (k, *frames, C)."""
    flat = coefs.reshape(coefs.shape[0], -1)
    return (evecs @ flat).reshape(evecs.shape[0], *coefs.shape[1:])


def _decay(evals: Array, time: Array, ndim: int) -> Array:
    """``exp(-lambda_j t_c)`` shaped (k, 1, ..., 1, C) to broadcast over ``ndim - 2`` frame axes."""
    factor = jnp.exp(-evals[:, None] * time[None, :])
    return factor.reshape(factor.shape[0], *([1] * (ndim - 2)), factor.shape[1])


@jax.jit
def spectral_diffusion(
    x: Float[Array, "verts *frames channels"],
    mass: Float[Array, " verts"],
    evals: Float[Array, " k"],
    evecs: Float[Array, "verts k"],
    time: Float[Array, " channels"],
) -> Float[Array, "verts *frames channels"]:
    """Heat diffusion in the truncated eigenbasis: ``Phi (exp(-lambda t) * Phi^T (M x))``.

    Args:
        x: (V, C) features, or (V, *frames, C) with frames between vertices and channels.
        mass: (V,) lumped mass.
        evals: (k,) eigenvalues.
        evecs: (V, k) M-orthonormal eigenvectors.
        time: (C,) diffusion time per channel (>= 0; t = 0 is the projection onto the basis).

    Returns:
        Diffused features, shaped like ``x``.
    """
    coefs = _to_basis(x, mass, evecs) * _decay(evals, time, x.ndim)
    return _from_basis(coefs, evecs)


def _gradients(x: Array, ops: DiffusionOperators) -> tuple[Array, Array]:
    """Both tangent gradient components of (V, *frames, C) features; one shared row gather."""
    flat = x.reshape(x.shape[0], -1)
    neighbours = flat[ops.grad_index]  # (V, D, frames * C): contiguous rows, fused into the sums
    gx = jnp.einsum("vd,vdm->vm", ops.grad_x, neighbours)
    gy = jnp.einsum("vd,vdm->vm", ops.grad_y, neighbours)
    return gx.reshape(x.shape), gy.reshape(x.shape)


@jax.jit
def apply_gradient(
    weights: Float[Array, "verts deg"],
    index: Int[Array, "verts deg"],
    x: Float[Array, "verts *frames channels"],
) -> Float[Array, "verts *frames channels"]:
    """One tangent gradient component in the padded one-ring layout: ``sum_d w[v,d] x[index[v,d]]``.

    Args:
        weights: (V, D) weights (``grad_x`` or ``grad_y`` of :class:`DiffusionOperators`).
        index: (V, D) column indices.
        x: (V, C) features, or (V, *frames, C).

    Returns:
        Gradient component per channel, shaped like ``x``.
    """
    flat = x.reshape(x.shape[0], -1)
    return jnp.einsum("vd,vdm->vm", weights, flat[index]).reshape(x.shape)


@dataclasses.dataclass(frozen=True)
class DiffusionNetConfig:
    """Static DiffusionNet configuration.

    Attributes:
        in_features: input channels per vertex (3 for xyz).
        out_features: output channels per vertex.
        width: hidden channels (C).
        num_blocks: diffusion blocks.
        mlp_hidden: hidden sizes of each block's per-vertex MLP (reference: (width, width)).
        gradient_features: include the spatial gradient features.
        min_diffusion_time: lower clamp of the learned diffusion time.
    """

    in_features: int = 3
    out_features: int = 3
    width: int = 128
    num_blocks: int = 4
    mlp_hidden: tuple[int, ...] = (128, 128)
    gradient_features: bool = True
    min_diffusion_time: float = 1e-8

    def __post_init__(self) -> None:
        for name in ("in_features", "out_features", "width", "num_blocks"):
            if getattr(self, name) < 1:
                raise ValueError(f"DiffusionNetConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.min_diffusion_time < 0:
            raise ValueError(f"min_diffusion_time must be >= 0, got {self.min_diffusion_time}")

    @classmethod
    def paper(cls, in_features: int = 3, out_features: int = 3) -> DiffusionNetConfig:
        """FreeTalk STM / reference size: width 128, 4 blocks, MLP (128, 128)."""
        return cls(in_features, out_features, width=128, num_blocks=4, mlp_hidden=(128, 128))

    @classmethod
    def small(cls, in_features: int = 3, out_features: int = 3) -> DiffusionNetConfig:
        """A CPU-friendly size for tests and quick training: width 32, 2 blocks."""
        return cls(in_features, out_features, width=32, num_blocks=2, mlp_hidden=(32, 32))


class LearnedTimeDiffusion(nn.Module):
    """Spectral diffusion with one learned time per channel (init 0, clamped >= ``min_time``).

    Takes (V, C) or (V, *frames, C) features. Returns the diffused features and, when
    ``with_gradients``, their two tangent gradient components (sparse one-ring operators).
    """

    channels: int
    min_time: float = 1e-8
    with_gradients: bool = False

    @nn.compact
    def __call__(
        self, x: Float[Array, "verts *frames channels"], ops: DiffusionOperators
    ) -> Float[Array, "verts *frames channels"] | tuple[Float[Array, "verts *frames channels"], ...]:
        t = self.param("diffusion_time", nn.initializers.zeros, (self.channels,), jnp.float32)
        # Straight-through clamp: forward value max(t, min), gradient as if identity (see module doc).
        t = t + jax.lax.stop_gradient(jnp.maximum(t, self.min_time) - t)
        x_diff = spectral_diffusion(x, ops.mass, ops.evals, ops.evecs, t)
        if not self.with_gradients:
            return x_diff
        return (x_diff, *_gradients(x_diff, ops))


class _Kernel(nn.Module):
    """A bias-free (in, out) weight with ``nn.Dense``'s initialiser and parameter name."""

    features: int

    @nn.compact
    def __call__(self, in_features: int) -> Array:
        return self.param("kernel", nn.initializers.lecun_normal(), (in_features, self.features), jnp.float32)


@matmul_layer
class SpatialGradientFeatures(nn.Module):
    """``tanh(Re(conj(g) * (A g)))`` per channel, with g = gradX x + i gradY x and A complex-linear.

    A is two real matrices (real and imaginary parts, parameters ``A_re``/``A_im`` like two bias-free
    ``nn.Dense``). Because A is complex-linear, rotating a vertex's tangent frame
    (g -> e^{i theta} g) leaves ``conj(g) * (A g)`` unchanged, so the features do not depend on the
    arbitrary choice of tangent frames. ``A g`` is formed with three real matmuls instead of four
    (``t3 = (gx + gy)(A_re + A_im)``, ``Im = t3 - t1 - t2``): exact, a quarter fewer FLOPs.
    """

    channels: int

    @nn.compact
    def __call__(
        self, gx: Float[Array, "verts *frames channels"], gy: Float[Array, "verts *frames channels"]
    ) -> Float[Array, "verts *frames channels"]:
        a_re = _Kernel(self.channels, name="A_re")(gx.shape[-1])
        a_im = _Kernel(self.channels, name="A_im")(gx.shape[-1])
        t1 = gx @ a_re
        t2 = gy @ a_im
        t3 = (gx + gy) @ (a_re + a_im)
        return jnp.tanh(gx * (t1 - t2) + gy * (t3 - t1 - t2))


@matmul_layer
class _SplitDense(nn.Module):
    """``nn.Dense`` of a concatenation, computed as a sum of per-part matmuls (same parameters).

    Avoids materialising the concatenated (V, frames, 3C) array; the kernel is one (sum C_i, out)
    parameter exactly as ``nn.Dense`` would create for the concatenation.
    """

    features: int

    @nn.compact
    def __call__(self, parts: Sequence[Array]) -> Array:
        sizes = [p.shape[-1] for p in parts]
        kernel = self.param("kernel", nn.initializers.lecun_normal(), (sum(sizes), self.features), jnp.float32)
        bias = self.param("bias", nn.initializers.zeros, (self.features,), jnp.float32)
        offsets = np.cumsum([0, *sizes])
        out = sum(part @ kernel[lo:hi] for part, lo, hi in zip(parts, offsets[:-1], offsets[1:]))
        return out + bias.reshape((1,) * (out.ndim - 1) + (-1,))


class DiffusionNetBlock(nn.Module):
    """Diffusion + gradient features + per-vertex MLP over [x, x_diff, grad features], residual."""

    width: int
    mlp_hidden: tuple[int, ...]
    gradient_features: bool = True
    min_time: float = 1e-8

    @nn.compact
    def __call__(
        self, x: Float[Array, "verts *frames channels"], ops: DiffusionOperators
    ) -> Float[Array, "verts *frames channels"]:
        diffusion = LearnedTimeDiffusion(self.width, self.min_time, self.gradient_features, name="diffusion")
        if self.gradient_features:
            x_diff, gx, gy = diffusion(x, ops)
            parts = [x, x_diff, SpatialGradientFeatures(self.width, name="gradient_features")(gx, gy)]
        else:
            parts = [x, diffusion(x, ops)]
        sizes = (*self.mlp_hidden, self.width)
        h = _SplitDense(sizes[0], name="mlp_0")(parts)
        for i, size in enumerate(sizes[1:], start=1):
            h = nn.Dense(size, name=f"mlp_{i}")(nn.relu(h))
        return h + x


class DiffusionNet(nn.Module):
    """Linear in -> ``num_blocks`` DiffusionNet blocks -> linear out, on one mesh.

    Call with ``x`` (V, in_features) for one frame, or (V, *frames, in_features) for several frames
    on the same mesh (see :func:`apply_frames`), and the mesh's :class:`DiffusionOperators`; returns
    (V, [*frames,] out_features). Shape mismatches raise ``ValueError`` at trace time.
    """

    config: DiffusionNetConfig

    @nn.compact
    def __call__(
        self, x: Float[Array, "verts *frames c_in"], ops: DiffusionOperators
    ) -> Float[Array, "verts *frames c_out"]:
        cfg = self.config
        if x.ndim < 2 or x.shape[-1] != cfg.in_features:
            raise ValueError(
                f"features must have shape (V, {cfg.in_features}) or (V, *frames, {cfg.in_features}), got {x.shape}"
            )
        if ops.mass.ndim != 1 or ops.mass.shape[0] != x.shape[0]:
            raise ValueError(
                f"features have {x.shape[0]} vertices but operators have mass of shape {ops.mass.shape}"
            )
        h = nn.Dense(cfg.width, name="linear_in")(x)
        for i in range(cfg.num_blocks):
            h = DiffusionNetBlock(
                cfg.width, cfg.mlp_hidden, cfg.gradient_features, cfg.min_diffusion_time, name=f"block_{i}"
            )(h, ops)
        return nn.Dense(cfg.out_features, name="linear_out")(h)


@functools.partial(jax.jit, static_argnames="config")
def apply_frames(
    config: DiffusionNetConfig,
    params: dict,
    x: Float[Array, "frames verts c_in"],
    ops: DiffusionOperators,
) -> Float[Array, "frames verts c_out"]:
    """DiffusionNet over a leading frame axis with the mesh's operators shared (jitted).

    Args:
        config: static network configuration.
        params: the ``{"params": ...}`` variables from ``DiffusionNet(config).init``.
        x: (T, V, in_features) per-frame features.
        ops: one mesh's operators (no leading axis).

    Returns:
        (T, V, out_features).
    """
    # Frames go between vertices and channels so the operators act on (V, T * C) in one product.
    out = DiffusionNet(config).apply(params, jnp.moveaxis(x, 0, 1), ops)
    return jnp.moveaxis(out, 1, 0)


@functools.partial(jax.jit, static_argnames="config")
def apply_meshes(
    config: DiffusionNetConfig,
    params: dict,
    x: Float[Array, "meshes verts c_in"],
    ops: DiffusionOperators,
) -> Float[Array, "meshes verts c_out"]:
    """DiffusionNet over a padded batch of meshes from :func:`stack_operators` (jitted, vmapped).

    Args:
        config: static network configuration.
        params: variables from ``DiffusionNet(config).init``.
        x: (B, V_max, in_features) features, padding rows arbitrary (they do not affect real rows).
        ops: stacked operators with leading axis B.

    Returns:
        (B, V_max, out_features); rows beyond each mesh's vertex count are meaningless.
    """
    model = DiffusionNet(config)
    return jax.vmap(lambda xb, ob: model.apply(params, xb, ob))(x, ops)
