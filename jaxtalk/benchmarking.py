"""Benchmark harness: compile vs run time, XLA FLOP counts, the machine's matmul peak, tables, JSON.

Conventions (diffrax ``benchmarks/``): compile time is measured separately (``lower`` + ``compile``
of ``jax.jit(fn)``), run time is the median (and min) of repeats of the COMPILED executable, every
run ends with ``block_until_ready``, and warm-up runs are discarded.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import platform
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "Timing",
    "time_jitted",
    "xla_flops",
    "matmul_flops",
    "loop_trip_factor",
    "measure_matmul_peak",
    "measure_memory_bandwidth",
    "parameter_bytes_read",
    "machine_info",
    "format_table",
    "print_table",
    "write_json",
]


@dataclasses.dataclass(frozen=True)
class Timing:
    """Timing of one jitted function on fixed arguments (seconds).

    Attributes:
        compile_s: tracing + lowering + XLA compilation (``jax.jit(fn).lower(*args).compile()``).
        lower_s: the tracing + lowering part of ``compile_s``.
        run_median_s: median wall time of the timed runs of the compiled executable.
        run_min_s: fastest timed run.
        runs: every timed run, in order.
    """

    compile_s: float
    lower_s: float
    run_median_s: float
    run_min_s: float
    runs: tuple[float, ...]


def _positive(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def _compile(fn: Callable[..., Any], args: Sequence[Any]) -> tuple[Any, float, float]:
    t0 = time.perf_counter()
    lowered = jax.jit(fn).lower(*args)
    t1 = time.perf_counter()
    compiled = lowered.compile()
    t2 = time.perf_counter()
    return compiled, t1 - t0, t2 - t0


def time_jitted(fn: Callable[..., Any], *args: Any, repeats: int = 10, warmup: int = 2) -> Timing:
    """Compile ``fn`` for ``args`` (timed), then time ``repeats`` runs after ``warmup`` untimed ones.

    Args:
        fn: a jit-able function of ``args`` (already-jitted functions are fine). Static arguments
            must be bound beforehand (e.g. ``functools.partial``).
        *args: example arguments (arrays / pytrees of arrays).
        repeats: timed runs (> 0).
        warmup: untimed runs before timing (>= 0).

    Returns:
        :class:`Timing`.

    Raises:
        ValueError: ``repeats <= 0`` or ``warmup < 0``.
    """
    _positive("repeats", repeats)
    if isinstance(warmup, bool) or not isinstance(warmup, (int, np.integer)) or warmup < 0:
        raise ValueError(f"warmup must be an integer >= 0, got {warmup!r}")
    compiled, lower_s, compile_s = _compile(fn, args)
    for _ in range(warmup):
        jax.block_until_ready(compiled(*args))
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        runs.append(time.perf_counter() - t0)
    return Timing(
        compile_s=compile_s,
        lower_s=lower_s,
        run_median_s=statistics.median(runs),
        run_min_s=min(runs),
        runs=tuple(runs),
    )


def xla_flops(fn: Callable[..., Any], *args: Any) -> float | None:
    """FLOPs of one call of ``jax.jit(fn)(*args)`` from XLA's compiled cost analysis.

    Args:
        fn: a jit-able function.
        *args: example arguments.

    Returns:
        The ``"flops"`` entry of the cost analysis, or None when the backend reports none. A dot of
        ``(m, k) x (k, n)`` counts ``2 m k n``. XLA counts the body of a loop (``lax.scan``,
        ``while_loop``) ONCE, not once per trip: for a scanned sampler, measure one step and
        multiply by the number of steps, or scale by :func:`loop_trip_factor`.
    """
    compiled, _, _ = _compile(fn, args)
    cost = compiled.cost_analysis()
    if isinstance(cost, (list, tuple)):  # older jax returned one dict per device program
        cost = cost[0] if cost else None
    if not cost or "flops" not in cost:
        return None
    flops = float(cost["flops"])
    return flops if math.isfinite(flops) and flops >= 0 else None


def _jaxprs_in(params: dict[str, Any]) -> list[Any]:
    """The jaxprs an equation's parameters hold (a jitted call's, a custom rule's, a remat's body)."""
    found = []
    for value in params.values():
        for item in value if isinstance(value, (tuple, list)) else (value,):
            inner = getattr(item, "jaxpr", item)  # a ClosedJaxpr holds its Jaxpr
            if hasattr(inner, "eqns"):
                found.append(inner)
    return found


def matmul_flops(jaxpr: Any, *, per_trip: bool = True) -> float:
    """Matmul and convolution FLOPs of a traced program: 2 per multiply-add of every ``dot_general``
    and ``conv_general_dilated``, nested calls included.

    Args:
        jaxpr: a ``Jaxpr`` or ``ClosedJaxpr`` (``jax.make_jaxpr(fn)(*args)``, ``jitted.trace(*args).jaxpr``).
        per_trip: count a ``lax.scan`` body once per iteration (its ``length``); False counts it once,
            as XLA's cost analysis does. A ``while_loop``'s trip count is not known when tracing: its
            body counts once either way. Of a ``lax.cond``, the costliest branch counts.

    Returns:
        FLOPs (elementwise work is not counted).
    """
    jaxpr = getattr(jaxpr, "jaxpr", jaxpr)
    total = 0.0
    for eqn in jaxpr.eqns:
        name = eqn.primitive.name
        if name == "dot_general":
            (contract, _), _ = eqn.params["dimension_numbers"]
            lhs = eqn.invars[0].aval.shape
            total += 2.0 * eqn.outvars[0].aval.size * math.prod(lhs[d] for d in contract)
        elif name == "conv_general_dilated":
            kernel = eqn.invars[1].aval.shape
            out_features = kernel[eqn.params["dimension_numbers"].rhs_spec[0]]
            # Each output element: one multiply-add per kernel entry of its feature group.
            total += 2.0 * eqn.outvars[0].aval.size * math.prod(kernel) / out_features
        elif name == "scan":
            total += matmul_flops(eqn.params["jaxpr"], per_trip=per_trip) * (eqn.params["length"] if per_trip else 1)
        elif name == "cond":
            total += max(matmul_flops(b, per_trip=per_trip) for b in eqn.params["branches"])
        else:
            total += sum(matmul_flops(sub, per_trip=per_trip) for sub in _jaxprs_in(eqn.params))
    return total


def loop_trip_factor(jaxpr: Any) -> float:
    """How much XLA's cost analysis undercounts a program by counting each ``lax.scan`` body once:
    its matmul FLOPs with every scan body counted per iteration over those with each counted once
    (1.0 for a program without scans or without matmuls).

    Multiply :func:`xla_flops` (or a compiled program's ``cost_analysis()["flops"]``) by it to count a
    program whose work sits in scans, such as a train step that decodes frame by frame in a
    ``lax.map``; elementwise work inside the loops is scaled by the matmul work's ratio.

    Args:
        jaxpr: the program, traced (``Jaxpr`` or ``ClosedJaxpr``).

    Returns:
        The factor (>= 1).
    """
    once = matmul_flops(jaxpr, per_trip=False)
    return matmul_flops(jaxpr) / once if once > 0 else 1.0


def measure_matmul_peak(dtype: Any = jnp.float32, n: int = 2048, repeats: int = 10) -> float:
    """Achievable matmul throughput of the default device: ``2 n^3 / best time`` of an n x n matmul.

    Args:
        dtype: operand dtype.
        n: matrix size (> 0).
        repeats: timed runs (> 0); the BEST run is used (peak, not typical).

    Returns:
        FLOP/s.

    Raises:
        ValueError: non-positive ``n`` or ``repeats``.
    """
    n = _positive("n", n)
    repeats = _positive("repeats", repeats)
    k1, k2 = jax.random.split(jax.random.key(0))
    a = jax.random.normal(k1, (n, n), dtype)
    b = jax.random.normal(k2, (n, n), dtype)
    timing = time_jitted(jnp.matmul, a, b, repeats=repeats, warmup=2)
    return 2.0 * n**3 / timing.run_min_s


def measure_memory_bandwidth(nbytes: int = 256 * 2**20, repeats: int = 10) -> float:
    """Streaming memory bandwidth of the default device: bytes read plus written per second by
    ``x * c`` over a float32 array of ``nbytes`` (far larger than a CPU's caches), best run.

    Args:
        nbytes: array size (> 0).
        repeats: timed runs (> 0); the BEST run is used.

    Returns:
        Bytes per second (``2 * nbytes / best time``).

    Raises:
        ValueError: non-positive ``nbytes`` or ``repeats``.
    """
    nbytes = _positive("nbytes", nbytes)
    repeats = _positive("repeats", repeats)
    x = jnp.ones((max(nbytes // 4, 1),), jnp.float32)
    timing = time_jitted(lambda x: x * 1.0001, x, repeats=repeats, warmup=2)
    return 2.0 * x.nbytes / timing.run_min_s


def parameter_bytes_read(fn: Callable[..., Any], params: Any, *args: Any) -> int:
    """Bytes of the arrays of ``params`` that ``fn(params, *args)`` uses (its jaxpr reads them): what
    one call must bring from memory at least once when they do not fit in the caches.

    Args:
        fn: a traceable function of ``params`` first.
        params: a pytree of arrays.
        *args: the other arguments.

    Returns:
        The summed ``nbytes`` of the used leaves.
    """
    closed = jax.make_jaxpr(fn)(params, *args)
    jaxpr = closed.jaxpr
    used = {id(v) for eqn in jaxpr.eqns for v in eqn.invars} | {id(v) for v in jaxpr.outvars}
    leaves = jax.tree.leaves(params)
    return int(sum(leaf.nbytes for leaf, var in zip(leaves, jaxpr.invars[:len(leaves)]) if id(var) in used))


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict[str, Any]:
    """Describe the machine and software a benchmark ran on.

    Returns:
        dict with ``cpu_model``, ``cpu_cores`` (logical, usable by this process), ``load_avg_1m``
        (others' work inflates timings), ``platform``, ``python``, ``jax``, ``jaxlib``, ``numpy``,
        ``backend``, ``device_kind``, ``device_count``, ``x64``.
    """
    import jaxlib

    devices = jax.devices()
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = os.cpu_count()
    try:
        load = os.getloadavg()[0]
    except OSError:
        load = None
    return {
        "cpu_model": _cpu_model(),
        "cpu_cores": cores,
        "load_avg_1m": load,
        "platform": platform.platform(),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "jaxlib": jaxlib.__version__,
        "numpy": np.__version__,
        "backend": jax.default_backend(),
        "device_kind": devices[0].device_kind,
        "device_count": len(devices),
        "x64": bool(jax.config.read("jax_enable_x64")),
    }


def _cell(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, (bool, np.bool_)):
        return str(bool(value))
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        v = float(value)
        if not math.isfinite(v):
            return str(v)
        return f"{v:.4g}"
    return str(value)


def format_table(rows: list[dict[str, Any]], title: str) -> str:
    """Render rows as a fixed-width text table (columns in first-seen key order).

    Numbers are right-aligned (floats with 4 significant digits), text left-aligned, missing or
    None cells shown as ``-``.

    Args:
        rows: one dict per row.
        title: printed above the table.

    Returns:
        The table as a string (no trailing newline).

    Raises:
        ValueError: no rows.
    """
    if not rows:
        raise ValueError(f"format_table needs at least one row (table {title!r})")
    columns: list[str] = []
    for row in rows:
        columns.extend(k for k in row if k not in columns)
    cells = [[_cell(row.get(c)) for c in columns] for row in rows]
    numeric = [
        all(
            r.get(c) is None
            or (isinstance(r.get(c), (int, float, np.number)) and not isinstance(r.get(c), (bool, np.bool_)))
            for r in rows
        )
        for c in columns
    ]
    widths = [max(len(c), *(len(r[i]) for r in cells)) for i, c in enumerate(columns)]

    def line(values: list[str]) -> str:
        parts = [v.rjust(w) if num else v.ljust(w) for v, w, num in zip(values, widths, numeric)]
        return " | ".join(parts).rstrip()

    rule = "-+-".join("-" * w for w in widths)
    return "\n".join([title, line(columns), rule, *(line(r) for r in cells)])


def print_table(rows: list[dict[str, Any]], title: str) -> None:
    """Print :func:`format_table` of ``rows``."""
    print(format_table(rows, title), flush=True)


def _to_json(value: Any) -> Any:
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.floating,)):
        return float(value)
    if isinstance(value, (np.ndarray, jax.Array)):
        return np.asarray(value).tolist()
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.asdict(value)
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot write {type(value).__name__} to JSON")


def write_json(path: str | os.PathLike[str], payload: dict[str, Any]) -> Path:
    """Write ``payload`` plus ``machine_info`` and ``recorded`` (UTC date and the command line) as
    indented JSON, atomically, creating parent directories.

    Args:
        path: output file.
        payload: JSON-able dict (NumPy/JAX scalars and arrays, dataclasses such as :class:`Timing`
            and paths are converted). A ``machine_info`` key is added unless present.

    Returns:
        The written path.

    Raises:
        ValueError: payload not a dict.
    """
    if not isinstance(payload, dict):
        raise ValueError(f"payload must be a dict, got {type(payload).__name__}")
    import datetime
    import shlex
    import sys

    from jaxtalk.files import atomic_write_text

    # When and by which command the numbers were made, so a figure quoted elsewhere can be traced.
    recorded = {"date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
                "command": shlex.join([Path(sys.argv[0]).name, *sys.argv[1:]])}
    full = {"machine_info": machine_info(), **payload} if "machine_info" not in payload else payload
    full = {"recorded": recorded, **full} if "recorded" not in full else full
    return atomic_write_text(path, json.dumps(full, indent=2, default=_to_json) + "\n")
