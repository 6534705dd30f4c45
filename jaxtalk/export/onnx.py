"""JAX functions as ONNX files (through ``jax2onnx``), for hosts that run a model without Python.

:func:`write_onnx` converts one traced function of fixed-shape arrays (the parameters closed over, so
they become the file's initializers) and writes it atomically; a model's exporter (e.g.
:func:`jaxtalk.models.toktalk.portable.export_stream`) calls it once per graph and describes the graphs in
a manifest whose entries :func:`io_spec` makes. The stand-alone reference host that reads such a folder
with ``onnxruntime`` is :mod:`jaxtalk.export.onnx_host`.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import numpy as np

from jaxtalk.files import atomic_output

__all__ = ["OPSET", "IOSpec", "io_spec", "write_onnx", "require_converter"]

# The ONNX opset written: onnxruntime 1.2x (Python, C++, C#) and onnxruntime-web run it.
OPSET = 21

IOSpec = dict[str, Any]


def io_spec(name: str, shape: Sequence[int], dtype: Any, **extra: Any) -> IOSpec:
    """One input or output of a graph as a manifest lists it: ``{"name", "shape", "dtype", ...extra}``."""
    return {"name": name, "shape": [int(n) for n in shape], "dtype": np.dtype(dtype).name, **extra}


def require_converter() -> Any:
    """The ``jax2onnx`` module.

    Raises:
        ImportError: when it is not installed, naming the extra that installs it.
    """
    try:
        import jax2onnx
    except ImportError as error:
        raise ImportError("exporting to ONNX needs jax2onnx and onnxruntime: pip install 'jaxtalk[onnx]'") from error
    return jax2onnx


def write_onnx(fn: Callable[..., Any], inputs: Sequence[IOSpec], outputs: Sequence[str], path: str | os.PathLike) -> Path:
    """Convert ``fn`` (positional arrays in the order of ``inputs``, returning a tuple in the order of
    ``outputs``) to one self-contained ONNX file at ``path`` (written atomically).

    Args:
        fn: a JAX function of fixed-shape arrays; whatever it closes over is written as constants.
        inputs: the inputs (:func:`io_spec`), in ``fn``'s argument order.
        outputs: the outputs' names, in ``fn``'s result order.
        path: the ``.onnx`` file.

    Returns:
        ``path``.

    Raises:
        ImportError: jax2onnx is not installed.
    """
    converter = require_converter()
    specs = [jax.ShapeDtypeStruct(tuple(spec["shape"]), np.dtype(spec["dtype"])) for spec in inputs]
    path = Path(path)
    try:
        # The converter traces layers with implementations of its own, which broadcast by rank promotion: allow
        # it while it traces, whatever the caller's setting (the test suite raises on it).
        with atomic_output(path) as tmp, warnings.catch_warnings(), jax.numpy_rank_promotion("allow"):
            # The converter's own lowering of the FFT asks for float64, which JAX (x64 off) truncates: harmless.
            warnings.filterwarnings("ignore", message="Explicitly requested dtype float64")
            converter.to_onnx(fn, specs, model_name=path.stem, opset=OPSET, return_mode="file", output_path=str(tmp),
                              input_names=[spec["name"] for spec in inputs], output_names=list(outputs),
                              export_mode="web")
    finally:
        # The converter traces jitted functions with primitives of its own, and jit caches what it traced: a
        # later ordinary call with the same shapes would get that program and fail. Start them afresh.
        jax.clear_caches()
    return path
