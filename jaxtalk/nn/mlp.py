"""A plain multi-layer perceptron over the last axis, shared by feed-forward and projection heads."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import flax.linen as nn
import jax.numpy as jnp

from jaxtalk.types import Array, Float

__all__ = ["MLP", "gelu_exact"]

Dtype = Any
Initializer = Any


def gelu_exact(x: Array) -> Array:
    """GELU with the erf form (PyTorch's ``nn.GELU()`` default; Flax's default is the tanh form)."""
    return nn.gelu(x, approximate=False)


class MLP(nn.Module):
    """Dense layers of the given widths with an activation between them.

    Attributes:
        features: output width of each Dense layer, e.g. ``(1024, 256)``.
        activation: applied after every layer but the last (and after the last if
            ``activate_final``).
        activate_final: also apply the activation to the output.
        use_bias: whether the Dense layers have biases.
        dropout_rate: dropout after each hidden activation (when ``deterministic=False``; needs the
            ``"dropout"`` RNG stream).
        dtype: computation dtype (``None``: inferred).
        param_dtype: parameter dtype.
        kernel_init: kernel initialiser of every layer.
        bias_init: bias initialiser of every layer.
    """

    features: Sequence[int]
    activation: Callable[[Array], Array] = gelu_exact
    activate_final: bool = False
    use_bias: bool = True
    dropout_rate: float = 0.0
    dtype: Dtype | None = None
    param_dtype: Dtype = jnp.float32
    kernel_init: Initializer = nn.initializers.lecun_normal()
    bias_init: Initializer = nn.initializers.zeros_init()

    @nn.compact
    def __call__(
        self, x: Float[Array, "*batch in_features"], *, deterministic: bool = True
    ) -> Float[Array, "*batch out_features"]:
        """Applies the layers.

        Args:
            x: ``(*batch, in_features)``.
            deterministic: disables dropout.

        Returns:
            ``(*batch, features[-1])``.

        Raises:
            ValueError: if ``features`` is empty or holds a non-positive width.
        """
        widths = tuple(self.features)
        if not widths or any(int(w) < 1 for w in widths):
            raise ValueError(f"MLP features must be a non-empty list of positive widths, got {widths}")
        for i, width in enumerate(widths):
            x = nn.Dense(
                int(width),
                use_bias=self.use_bias,
                dtype=self.dtype,
                param_dtype=self.param_dtype,
                kernel_init=self.kernel_init,
                bias_init=self.bias_init,
                name=f"dense_{i}",
            )(x)
            last = i == len(widths) - 1
            if not last or self.activate_final:
                x = self.activation(x)
            if not last and self.dropout_rate > 0.0:
                x = nn.Dropout(self.dropout_rate)(x, deterministic=deterministic)
        return x
