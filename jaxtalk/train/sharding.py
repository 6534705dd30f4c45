"""Data parallelism with ``jax.sharding``: a 1-D device mesh, batch axis sharded, state replicated.

Single process: :func:`shard_batch` splits the host batch over the local devices.

Multi-host (several processes, e.g. one per machine): call
:func:`jaxtalk.train.distributed.initialize` first; ``jax.devices()`` then lists every process's
devices and :func:`make_mesh` spans them. Each process then passes only its **local** part of the
global batch to :func:`shard_batch` (so the batch size a process's data loader yields is the
per-process batch, and the global batch is ``per-process batch x process_count``), and
:func:`replicate` expects the same state on every process (same ``init_params`` and key), which it
checks.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

__all__ = ["DATA_AXIS", "make_mesh", "batch_sharding", "replicated_sharding", "shard_batch", "replicate"]

DATA_AXIS = "data"
PyTree = Any


def make_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A 1-D mesh named ``"data"`` over ``devices`` (default: all devices of all processes).

    In a multi-process run the default orders the devices by process, so each process's devices
    are contiguous on the mesh and process ``p``'s local batch becomes rows ``[p * b, (p + 1) * b)``
    of the global batch (``b`` the per-process batch size).

    Args:
        devices: devices to use (default ``jax.devices()``, grouped by process).

    Returns:
        The mesh.

    Raises:
        ValueError: an empty device list.
    """
    if devices is None:
        devs = list(jax.devices())
        if jax.process_count() > 1:
            devs.sort(key=lambda d: (d.process_index, d.id))
    else:
        devs = list(devices)
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
    """Raise ValueError unless every batch leaf's leading axis divides evenly over the devices it fills.

    Single process: the mesh's devices. Multi-process: this process's devices on the mesh, since
    each process's (local) batch is split over those alone.
    """
    multi = jax.process_count() > 1
    n = _local_mesh_size(mesh) if multi else mesh.size
    for path, leaf in jax.tree_util.tree_flatten_with_path(batch)[0]:
        if _is_global(leaf):
            continue  # already assembled on the mesh; its sharding vouches for the split
        shape = np.shape(leaf)
        if not shape:
            raise ValueError(f"batch array {jax.tree_util.keystr(path)} is a scalar; it needs a batch axis to shard")
        if shape[0] % n:
            if multi:
                raise ValueError(
                    f"per-process batch size {shape[0]} of batch array {jax.tree_util.keystr(path)} (shape "
                    f"{shape}) is not divisible by the {n} devices this process holds on the mesh "
                    f"({mesh.size} devices over {jax.process_count()} processes)"
                )
            raise ValueError(
                f"batch size {shape[0]} of batch array {jax.tree_util.keystr(path)} (shape {shape}) "
                f"is not divisible by the {n} devices of the mesh"
            )


def shard_batch(batch: PyTree, mesh: Mesh) -> PyTree:
    """Place a host batch on the mesh, split along the batch axis.

    Single process: ``batch`` is the whole batch. Multi-process: ``batch`` is this process's local
    part (every process passes the same per-process shape); the result is one global array per
    leaf whose batch axis is ``per-process size x (mesh devices / this process's mesh devices)``,
    i.e. ``x process_count`` on a mesh over all devices. Leaves that are already global
    ``jax.Array`` s are resharded, not re-assembled.

    Args:
        batch: pytree of arrays with a common leading batch axis.
        mesh: the data mesh.

    Returns:
        The batch as sharded ``jax.Array`` s.

    Raises:
        ValueError: a leaf whose (per-process) batch size is not divisible by the number of devices
            it is split over, or (multi-process) a mesh holding none of this process's devices.
    """
    check_batch_divisible(batch, mesh)
    sharding = batch_sharding(mesh)
    if jax.process_count() == 1:
        return jax.device_put(batch, sharding)

    def assemble(leaf: Any) -> jax.Array:
        if _is_global(leaf):
            return jax.device_put(leaf, sharding)
        # Each process contributes the rows of its own devices; no data crosses processes here.
        return jax.make_array_from_process_local_data(sharding, np.asarray(leaf))

    return jax.tree.map(assemble, batch)


def replicate(tree: PyTree, mesh: Mesh) -> PyTree:
    """Copy every leaf of ``tree`` onto all devices of ``mesh``.

    Multi-process: every process must pass the same values (same ``init_params``, same key): each
    process places its own copy on its own devices, so differing copies would silently diverge the
    "replicated" state. A fingerprint of every leaf is compared across processes (one small
    all-gather) to catch that. Typed PRNG key leaves are supported; already global leaves are
    resharded as they are.

    Args:
        tree: pytree of arrays (NumPy, ``jax.Array``, typed PRNG keys or scalars).
        mesh: the data mesh.

    Returns:
        The tree with every leaf a ``jax.Array`` replicated over the mesh.

    Raises:
        ValueError: (multi-process) leaves whose values differ between processes (naming them), or a
            mesh holding none of this process's devices.
    """
    sharding = replicated_sharding(mesh)
    if jax.process_count() == 1:
        return jax.device_put(tree, sharding)
    _local_mesh_size(mesh)  # raises if this process has no devices on the mesh

    paths_leaves, treedef = jax.tree_util.tree_flatten_with_path(tree)
    host: list[np.ndarray | None] = []  # None: already global
    for _, leaf in paths_leaves:
        if _is_global(leaf):
            host.append(None)
        elif _is_key(leaf):
            host.append(np.asarray(jax.random.key_data(leaf)))
        else:
            # Python scalars via jnp: JAX's dtype (float32, int32), not NumPy's float64.
            array_like = isinstance(leaf, np.ndarray | np.generic | jax.Array)
            host.append(np.asarray(leaf if array_like else jnp.asarray(leaf)))
    _check_same_on_every_process([jax.tree_util.keystr(p) for p, _ in paths_leaves], host)

    out = []
    for (_, leaf), data in zip(paths_leaves, host):
        if data is None:
            out.append(jax.device_put(leaf, sharding))
            continue
        # Each process fills its own devices from its own (identical) copy: no cross-process transfer,
        # which jax.device_put of a committed single-device array cannot do on CPU.
        arr = jax.make_array_from_callback(data.shape, sharding, lambda index, data=data: data[index])
        out.append(jax.random.wrap_key_data(arr, impl=jax.random.key_impl(leaf)) if _is_key(leaf) else arr)
    return jax.tree_util.tree_unflatten(treedef, out)


def _is_global(leaf: Any) -> bool:
    """A ``jax.Array`` spanning devices of other processes too."""
    return isinstance(leaf, jax.Array) and not leaf.is_fully_addressable


def _is_key(leaf: Any) -> bool:
    return isinstance(leaf, jax.Array) and jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key)


def _local_mesh_size(mesh: Mesh) -> int:
    """How many of the mesh's devices belong to this process (raises if none)."""
    n = sum(d.process_index == jax.process_index() for d in mesh.devices.flat)
    if n == 0:
        raise ValueError(
            f"the mesh's {mesh.size} devices include none of process {jax.process_index()}'s; every "
            "process taking part in training needs devices on the mesh"
        )
    return n


def _check_same_on_every_process(names: list[str], host: list[np.ndarray | None]) -> None:
    """Raise ValueError naming the leaves whose bytes differ between processes."""
    from jax.experimental import multihost_utils  # deferred: only multi-process runs need it

    # 8-byte digests as uint32 pairs: JAX without x64 has no uint64 to gather.
    digests = np.zeros((len(host), 2), np.uint32)
    for i, data in enumerate(host):
        if data is not None:
            h = hashlib.blake2b(digest_size=8)
            h.update(f"{data.dtype.str}{data.shape}".encode())
            h.update(np.ascontiguousarray(data).tobytes())
            digests[i] = np.frombuffer(h.digest(), np.uint32)
    everyone = np.asarray(multihost_utils.process_allgather(digests))  # (processes, leaves, 2)
    differ = [name for i, name in enumerate(names) if (everyone[:, i] != everyone[0, i]).any()]
    if differ:
        raise ValueError(
            f"replicate: {len(differ)} leaves differ between processes ({', '.join(differ[:5])}"
            f"{', ...' if len(differ) > 5 else ''}); every process must build the same state "
            "(same init_params and key) for multi-process training"
        )
