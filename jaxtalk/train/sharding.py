"""Data parallelism with ``jax.sharding``: a 1-D device mesh, batch axis sharded, state replicated.

Multi-host runs call ``jax.distributed.initialize()`` first; ``jax.devices()`` then lists every
host's devices and the same mesh spans them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

__all__ = ["DATA_AXIS", "make_mesh", "batch_sharding", "replicated_sharding", "shard_batch", "replicate"]

DATA_AXIS = "data"
PyTree = Any


def make_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A 1-D mesh named ``"data"`` over ``devices`` (default: all devices).

    Args:
        devices: devices to use (default ``jax.devices()``).

    Returns:
        The mesh.

    Raises:
        ValueError: an empty device list.
    """
    devs = list(jax.devices() if devices is None else devices)
    if not devs:
        raise ValueError("make_mesh needs at least one device, got an empty list")
    return Mesh(np.array(devs), (DATA_AXIS,))


def batch_sharding(mesh: Mesh) -> NamedSharding:
    """Leading (batch) axis split over the mesh's data axis; other axes whole."""
    return NamedSharding(mesh, PartitionSpec(DATA_AXIS))


def replicated_sharding(mesh: Mesh) -> NamedSharding:
    """Whole array on every device."""
    return NamedSharding(mesh, PartitionSpec())


def check_batch_divisible(batch: PyTree, mesh: Mesh) -> None:
    """Raise ValueError unless every batch leaf's leading axis divides evenly over the mesh."""
    n = mesh.size
    for path, leaf in jax.tree_util.tree_flatten_with_path(batch)[0]:
        shape = np.shape(leaf)
        if not shape:
            raise ValueError(f"batch array {jax.tree_util.keystr(path)} is a scalar; it needs a batch axis to shard")
        if shape[0] % n:
            raise ValueError(
                f"batch size {shape[0]} of batch array {jax.tree_util.keystr(path)} (shape {shape}) "
                f"is not divisible by the {n} devices of the mesh"
            )


def shard_batch(batch: PyTree, mesh: Mesh) -> PyTree:
    """Place a host batch on the mesh, split along the batch axis.

    Args:
        batch: pytree of arrays with a common leading batch axis.
        mesh: the data mesh.

    Returns:
        The batch as sharded ``jax.Array`` s.

    Raises:
        ValueError: a leaf whose batch size is not divisible by the number of devices.
    """
    check_batch_divisible(batch, mesh)
    return jax.device_put(batch, batch_sharding(mesh))


def replicate(tree: PyTree, mesh: Mesh) -> PyTree:
    """Copy every leaf of ``tree`` onto all devices of ``mesh``."""
    return jax.device_put(tree, replicated_sharding(mesh))
