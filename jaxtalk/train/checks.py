"""Host-side batch validation run before each step: structure/shape/dtype against the first batch
(or the spec stored in a checkpoint) and an optional NaN/inf scan."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["BatchSpec", "check_finite"]

PyTree = Any


@dataclasses.dataclass(frozen=True)
class BatchSpec:
    """Names, shapes and dtypes of a batch's arrays (the model was initialised for these)."""

    names: tuple[str, ...]
    shapes: tuple[tuple[int, ...], ...]
    dtypes: tuple[str, ...]

    @classmethod
    def from_batch(cls, batch: PyTree) -> BatchSpec:
        """Record the spec of ``batch``."""
        flat = jax.tree_util.tree_flatten_with_path(batch)[0]
        return cls(
            names=tuple(jax.tree_util.keystr(p) for p, _ in flat),
            shapes=tuple(tuple(int(d) for d in np.shape(x)) for _, x in flat),
            dtypes=tuple(str(np.result_type(x)) for _, x in flat),
        )

    def to_json(self) -> dict[str, list]:
        """JSON form (stored in checkpoint metadata)."""
        return {"names": list(self.names), "shapes": [list(s) for s in self.shapes], "dtypes": list(self.dtypes)}

    @classmethod
    def from_json(cls, data: dict[str, list]) -> BatchSpec:
        """Inverse of :meth:`to_json`."""
        return cls(tuple(data["names"]), tuple(tuple(s) for s in data["shapes"]), tuple(data["dtypes"]))

    def check(self, batch: PyTree, variable_axes: Sequence[int] = (), *, step: int | None = None) -> None:
        """Raise ValueError naming the array and both shapes if ``batch`` does not match this spec.

        Args:
            batch: the batch to check.
            variable_axes: axes allowed to differ in size (the padded length axis of bucketed data).
            step: step number for the message.

        Raises:
            ValueError: missing/extra arrays, or a dtype, rank or size mismatch.
        """
        at = "" if step is None else f" at step {step}"
        got = BatchSpec.from_batch(batch)
        if got.names != self.names:
            missing = sorted(set(self.names) - set(got.names))
            extra = sorted(set(got.names) - set(self.names))
            raise ValueError(
                f"batch structure changed{at}: missing arrays {missing}, unexpected arrays {extra} "
                f"(expected {list(self.names)})"
            )
        for name, want, have, wd, hd in zip(self.names, self.shapes, got.shapes, self.dtypes, got.dtypes):
            free = {a % len(want) for a in variable_axes if -len(want) <= a < len(want)}
            if len(want) != len(have) or any(w != h for i, (w, h) in enumerate(zip(want, have)) if i not in free):
                raise ValueError(
                    f"batch array {name}{at} has shape {have}, but the model was set up for shape {want}"
                    + (f" (axes {sorted(free)} may vary)" if free else "")
                )
            if wd != hd:
                raise ValueError(f"batch array {name}{at} has dtype {hd}, expected {wd}")


def check_finite(batch: PyTree, *, step: int | None = None) -> None:
    """Raise ValueError if a floating array of ``batch`` holds NaN or inf.

    Args:
        batch: pytree of arrays (host arrays are cheapest; device arrays are fetched).
        step: step number for the message.

    Raises:
        ValueError: naming the array, the step and how many values are not finite.
    """
    for path, leaf in jax.tree_util.tree_flatten_with_path(batch)[0]:
        arr = np.asarray(leaf)
        if jnp.issubdtype(arr.dtype, jnp.inexact):  # jnp knows bfloat16, np does not
            bad = arr.size - int(np.count_nonzero(np.isfinite(arr)))
            if bad:
                at = "" if step is None else f" at step {step}"
                raise ValueError(
                    f"batch array {jax.tree_util.keystr(path)}{at} has {bad} NaN/inf value(s) "
                    f"of {arr.size}; refusing to train on it (pass check_finite=False to skip this check)"
                )
