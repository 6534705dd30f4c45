"""The value checks of jaxtalk's public entry points: finite arrays, and the samplers' temperature.

Values are checked only when they are known: inside a caller's ``jit``/``vmap``/``grad`` an array is
a tracer and passes, so a metric can serve as a training loss and a sampler can be differentiated,
while a NaN handed to the same function eagerly fails at the boundary, naming the argument, instead
of deep inside XLA.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["check_finite", "check_temperature"]


def check_finite(x: Any, name: str) -> None:
    """Raise a ValueError naming ``name`` if a concrete array holds NaN or inf (tracers pass).

    Args:
        x: an array (NumPy or JAX), or a tracer.
        name: what the array is, for the message.

    Raises:
        ValueError: NaN or inf in a concrete ``x``, with their count and ``x``'s shape.
    """
    if isinstance(x, jax.core.Tracer):
        return
    values = np.asarray(x)
    finite = np.isfinite(values)
    if not finite.all():
        bad = int(values.size - np.count_nonzero(finite))
        raise ValueError(f"{name} contains {bad} non-finite value(s) (NaN or inf); shape {values.shape}")


def check_temperature(temperature: Any, dtype: Any = jnp.float32, name: str = "temperature", *,
                      default: float | None = None) -> jax.Array:
    """A sampler's temperature (the scale of its starting or step noise) as a ``()`` array.

    Args:
        temperature: a scalar >= 0 (a tracer passes unchecked, as in :func:`check_finite`), or None
            for ``default``.
        dtype: the floating dtype to return.
        name: what the messages call it (a command line says ``--temperature``).
        default: the model's own temperature, which None stands for.

    Returns:
        ``()`` array of ``dtype``.

    Raises:
        ValueError: a non-scalar, negative, NaN or infinite value, or None without a default.
    """
    if temperature is None:
        if default is None:
            raise ValueError(f"{name} is required (this sampler has no default)")
        temperature = default
    if np.ndim(temperature):
        raise ValueError(f"{name} must be a scalar, got shape {np.shape(temperature)}")
    if not isinstance(temperature, jax.core.Tracer):
        # Checked on the host before it becomes a device array: a stream checks it every chunk, and
        # reading a device scalar back would wait for the device each time.
        value = float(np.asarray(temperature))
        if not (np.isfinite(value) and value >= 0):
            raise ValueError(f"{name} must be a finite number >= 0, got {value}")
    return jnp.asarray(temperature, dtype)
