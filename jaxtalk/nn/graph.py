"""Graph convolution (Kipf & Welling) on small fixed graphs such as the 68-landmark graph.

The normalised adjacency ``D^-1/2 (A + I) D^-1/2`` is built once in NumPy from the edge list and
enters the program as a constant; the layer is ``A_hat X W + b`` over any leading batch/frame axes.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import flax.linen as nn
import jax.numpy as jnp
import numpy as np

from jaxtalk.types import Array, Float, Shaped

__all__ = ["normalized_adjacency", "GraphConv"]

Dtype = Any
Initializer = Any


def normalized_adjacency(
    # Shape (num_edges, 2) is checked below with a ValueError rather than in the annotation.
    edges: Shaped[np.ndarray, "*dims"] | Shaped[Array, "*dims"] | Sequence[Sequence[int]],
    num_nodes: int,
    self_loops: bool = True,
) -> Float[np.ndarray, "{num_nodes} {num_nodes}"]:
    """Symmetric normalised adjacency ``D^-1/2 (A + I) D^-1/2`` of an undirected graph.

    ``A`` is the 0/1 adjacency of ``edges`` made symmetric (duplicates and both directions count
    once). With ``self_loops`` every diagonal entry of ``A + I`` is 1 (an explicit self-edge is not
    counted twice). ``D`` is the row sum of ``A + I``; a node of degree 0 (only possible without
    self-loops) gets an all-zero row and column.

    Args:
        edges: ``(num_edges, 2)`` integer node pairs (may be empty).
        num_nodes: number of nodes.
        self_loops: add the identity before normalising (Kipf & Welling's renormalisation trick).

    Returns:
        ``(num_nodes, num_nodes)`` float32 symmetric matrix.

    Raises:
        ValueError: on a non-positive ``num_nodes``, edges not of shape ``(E, 2)``, non-integer or
            non-finite entries, or a node index outside ``[0, num_nodes)``.
    """
    if num_nodes < 1:
        raise ValueError(f"num_nodes must be positive, got {num_nodes}")
    e = np.asarray(edges)
    if e.size == 0:
        e = np.zeros((0, 2), np.int64)
    if e.ndim != 2 or e.shape[1] != 2:
        raise ValueError(f"edges must have shape (num_edges, 2), got {e.shape}")
    if not np.issubdtype(e.dtype, np.integer):
        if not np.all(np.isfinite(e)) or np.any(e != np.round(e)):
            raise ValueError(f"edges must hold integer node indices, got dtype {e.dtype}")
        e = e.astype(np.int64)
    if e.size and (e.min() < 0 or e.max() >= num_nodes):
        raise ValueError(
            f"edge node indices must lie in [0, {num_nodes}), got range [{e.min()}, {e.max()}]"
        )
    a = np.zeros((num_nodes, num_nodes), np.float64)
    a[e[:, 0], e[:, 1]] = 1.0
    a[e[:, 1], e[:, 0]] = 1.0
    if self_loops:
        np.fill_diagonal(a, 1.0)
    degree = a.sum(axis=1)
    inv_sqrt = np.where(degree > 0, 1.0 / np.sqrt(np.maximum(degree, 1e-300)), 0.0)
    return (inv_sqrt[:, None] * a * inv_sqrt[None, :]).astype(np.float32)


class GraphConv(nn.Module):
    """``A_hat X W + b``: one graph-convolution layer over a fixed graph.

    Attributes:
        features: output features per node.
        adjacency: ``(nodes, nodes)`` normalised adjacency (NumPy, static), e.g. from
            :func:`normalized_adjacency`.
        use_bias: add a bias.
        dtype: computation dtype; param_dtype: parameter dtype; kernel_init: kernel initialiser.
    """

    features: int
    adjacency: np.ndarray
    use_bias: bool = True
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32
    kernel_init: Initializer = nn.initializers.lecun_normal()

    # The dataclass hash/eq would hash or compare the NumPy adjacency elementwise and fail; compare it
    # by value so the module stays usable as a static argument and inside lifted transforms.
    def _identity(self) -> tuple[Any, ...]:
        adjacency = np.asarray(self.adjacency)
        return tuple(
            (f.name, (adjacency.shape, adjacency.dtype.str, adjacency.tobytes()))
            if f.name == "adjacency"
            else (f.name, getattr(self, f.name))
            for f in dataclasses.fields(self)
            if f.name != "parent"
        )

    def __hash__(self) -> int:
        return hash(self._identity())

    def __eq__(self, other: object) -> bool:
        return type(other) is type(self) and self._identity() == other._identity()

    @nn.compact
    def __call__(
        self, x: Float[Array, "*batch nodes in_features"]
    ) -> Float[Array, "*batch nodes {self.features}"]:
        """Applies the layer to node features.

        Args:
            x: ``(*batch, nodes, in_features)``; any leading batch/frame axes.

        Returns:
            ``(*batch, nodes, features)``.

        Raises:
            ValueError: if the adjacency is not square or its size differs from ``nodes``.
        """
        adjacency = np.asarray(self.adjacency)
        if adjacency.ndim != 2 or adjacency.shape[0] != adjacency.shape[1]:
            raise ValueError(f"adjacency must be a square matrix, got shape {adjacency.shape}")
        if adjacency.shape[0] != x.shape[-2]:
            raise ValueError(
                f"adjacency is for {adjacency.shape[0]} nodes but the input has {x.shape[-2]} "
                f"(input shape {x.shape})"
            )
        h = nn.Dense(
            self.features,
            use_bias=False,
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            kernel_init=self.kernel_init,
            name="linear",
        )(x)
        y = jnp.einsum("ij,...jf->...if", jnp.asarray(adjacency, h.dtype), h)
        if self.use_bias:
            bias = self.param("bias", nn.initializers.zeros_init(), (self.features,), self.param_dtype)
            y = y + bias.astype(y.dtype).reshape((1,) * (y.ndim - 1) + (self.features,))
        return y
