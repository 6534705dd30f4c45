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

__all__ = ["OPSET", "MANIFEST_FORMAT", "IOSpec", "io_spec", "write_onnx", "require_converter", "hoist_loop_constants"]

# What an exported folder's manifest.json says it is (``format``, ``version``); the reference host checks it.
MANIFEST_FORMAT = ("jaxtalk-onnx-stream", 1)

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
            model = converter.to_onnx(fn, specs, model_name=path.stem, opset=OPSET, return_mode="proto",
                                      input_names=[spec["name"] for spec in inputs], output_names=list(outputs))
            import onnx

            model = hoist_loop_constants(model)
            onnx.checker.check_model(model)
            onnx.save(model, str(tmp))
    finally:
        # The converter traces jitted functions with primitives of its own, and jit caches what it traced: a
        # later ordinary call with the same shapes would get that program and fail. Start them afresh.
        jax.clear_caches()
    return path


def hoist_loop_constants(model: Any) -> Any:
    """Loop-invariant values out of every ``Loop``'s carried state, in place (returns ``model``).

    The converter lowers a ``lax.scan`` to a ``Loop`` and threads everything the scan closes over (the model's
    weights: almost all a TokTalk Euler step carries) through the loop as state, passed on by an
    ``Identity`` each iteration. Read from the outer scope instead, they are constants that onnxruntime folds
    once (the convolutions' kernel transposes) rather than copying and transposing them at every step, with
    bitwise the same outputs (docs/onnx.md).

    Args:
        model: an ``onnx.ModelProto``.
    """
    graph = model.graph
    for loop in graph.node:
        if loop.op_type != "Loop":
            continue
        body = next(a.g for a in loop.attribute if a.name == "body")
        carried = len(body.input) - 2  # body inputs: iteration, condition, carried...; outputs: condition, carried..., scans...
        producer = {name: node for node in body.node for name in node.output}

        def passes_through(k: int) -> bool:
            node = producer.get(body.output[1 + k].name)
            return body.output[1 + k].name == body.input[2 + k].name or (
                node is not None and node.op_type == "Identity" and node.input[0] == body.input[2 + k].name)

        invariant = [k for k in range(carried) if passes_through(k)]
        if not invariant:
            continue
        kept = [k for k in range(carried) if k not in invariant]
        outer = {body.input[2 + k].name: loop.input[2 + k] for k in invariant}  # body name -> outer value
        dropped = {id(producer[body.output[1 + k].name]) for k in invariant if body.output[1 + k].name in producer}
        final = {loop.output[k]: loop.input[2 + k] for k in invariant}  # the loop's final value: the initial one
        nodes = [node for node in body.node if id(node) not in dropped]
        for node in nodes:
            node.input[:] = [outer.get(name, name) for name in node.input]
        inputs = [body.input[0], body.input[1], *(body.input[2 + k] for k in kept)]
        outputs = [body.output[0], *(body.output[1 + k] for k in kept), *body.output[1 + carried:]]
        inputs, outputs = [_copy(v) for v in inputs], [_copy(v) for v in outputs]
        del body.node[:], body.input[:], body.output[:]
        body.node.extend(nodes)
        body.input.extend(inputs)
        body.output.extend(outputs)
        loop_inputs = [loop.input[0], loop.input[1], *(loop.input[2 + k] for k in kept)]
        loop_outputs = [*(loop.output[k] for k in kept), *loop.output[carried:]]
        loop.input[:] = loop_inputs
        loop.output[:] = loop_outputs
        for node in graph.node:
            node.input[:] = [final.get(name, name) for name in node.input]
        for value in graph.output:
            if value.name in final:
                raise ValueError(f"the graph outputs a loop-invariant value ({value.name}): not hoisted")
    return model


def _copy(value: Any) -> Any:
    import onnx

    out = onnx.ValueInfoProto()
    out.CopyFrom(value)
    return out
