"""Disk cache of DiffusionNet operators, keyed by a hash of the mesh and the Laplacian method.

One ``.npz`` file per mesh. An entry computed with more eigenpairs than requested is reused (sliced);
a request for more replaces it. Writes go to a temporary file in the same directory followed by
``os.replace``, so a reader never sees a half-written entry even with concurrent writers.
"""

from __future__ import annotations

import hashlib
import os
import zipfile

import numpy as np
import scipy.sparse as sp

from jaxtalk.files import atomic_savez
from jaxtalk.geometry.operators import Operators

__all__ = ["CACHE_VERSION", "cache_key", "cache_path", "load", "save"]

# Bump when the precompute changes meaning (conventions, regularisers), to invalidate old entries.
CACHE_VERSION = 1


def cache_key(vertices: np.ndarray, faces: np.ndarray, method: str) -> str:
    """SHA-256 of the float64 vertices, int64 faces, method and cache version.

    Args:
        vertices: (V, 3) positions.
        faces: (F, 3) indices.
        method: the resolved Laplacian method ("cotan" or "robust").

    Returns:
        A 64-character hex digest.
    """
    h = hashlib.sha256()
    for arr in (np.ascontiguousarray(vertices, dtype=np.float64), np.ascontiguousarray(faces, dtype=np.int64)):
        h.update(str(arr.shape).encode())
        h.update(arr.tobytes())
    h.update(f"{method}|v{CACHE_VERSION}".encode())
    return h.hexdigest()


def cache_path(cache_dir: str | os.PathLike[str], key: str) -> str:
    """Path of the entry for ``key`` inside ``cache_dir``."""
    return os.path.join(os.fspath(cache_dir), f"ops_{key}.npz")


def load(cache_dir: str | os.PathLike[str], key: str, k: int) -> Operators | None:
    """The cached operators truncated to ``k`` eigenpairs, or ``None`` (missing, too few, unreadable).

    A corrupt entry (e.g. from a crash of an older non-atomic writer) counts as missing so that the
    caller recomputes and overwrites it.
    """
    path = cache_path(cache_dir, key)
    if not os.path.exists(path):
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            if int(z["k"]) < k:
                return None
            n = int(z["num_vertices"])

            def csr(name: str) -> sp.csr_matrix:
                return sp.csr_matrix((z[f"{name}_data"], z[f"{name}_indices"], z[f"{name}_indptr"]), shape=(n, n))

            ops = Operators(
                mass=z["mass"],
                evals=z["evals"],
                evecs=z["evecs"],
                grad_x=csr("grad_x"),
                grad_y=csr("grad_y"),
                frames=z["frames"],
                method=str(z["method"]),
            )
    except (OSError, KeyError, ValueError, zipfile.BadZipFile):
        return None
    return ops.truncated(k)


def save(cache_dir: str | os.PathLike[str], key: str, ops: Operators) -> str:
    """Write ``ops`` atomically under ``key``; returns the entry's path.

    Raises:
        OSError: the directory cannot be created or written.
    """
    os.makedirs(cache_dir, exist_ok=True)
    path = cache_path(cache_dir, key)
    arrays = {
        "k": np.asarray(ops.k),
        "num_vertices": np.asarray(ops.num_vertices),
        "mass": ops.mass,
        "evals": ops.evals,
        "evecs": ops.evecs,
        "frames": ops.frames,
        "method": np.asarray(ops.method),
    }
    for name in ("grad_x", "grad_y"):
        mat = sp.csr_matrix(getattr(ops, name))
        arrays[f"{name}_data"] = mat.data
        arrays[f"{name}_indices"] = mat.indices
        arrays[f"{name}_indptr"] = mat.indptr
    atomic_savez(path, **arrays)
    return path
