"""Benchmark harness: FLOP counts, timing record, table formatting, JSON output."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk import benchmarking as bm


@pytest.mark.parametrize("n", [16, 48])
def test_xla_flops_of_matmul_is_2n3(n):
    a = jnp.ones((n, n))
    assert bm.xla_flops(jnp.matmul, a, a) == pytest.approx(2 * n**3, rel=1e-6)
    b = jnp.ones((n, 2 * n))
    assert bm.xla_flops(lambda x, y: x @ y, a, b) == pytest.approx(2 * n * n * 2 * n, rel=1e-6)


def test_xla_flops_counts_a_scan_body_once():
    # Documented behaviour the sampler benchmark relies on (it multiplies one step by N).
    a = jnp.ones((16, 16))

    def f(x):
        return jax.lax.scan(lambda c, _: (c @ c, None), x, None, length=10)[0]

    assert bm.xla_flops(f, a) == pytest.approx(2 * 16**3, rel=0.01)


def test_matmul_flops_counts_batched_dots_and_grouped_convolutions_by_hand():
    # (3, 8, 16) x (3, 16, 4) batched over the leading axis: 3 * 8 * 4 outputs, 16 multiply-adds each.
    dot = jax.make_jaxpr(lambda x, y: jnp.einsum("bmk,bkn->bmn", x, y))(jnp.ones((3, 8, 16)), jnp.ones((3, 16, 4)))
    assert bm.matmul_flops(dot) == 2 * 3 * 8 * 4 * 16
    # 1-D convolution, 3 -> 4 channels, kernel 5, 20 -> 16 frames, batch 2: 3 * 5 multiply-adds per output.
    conv = jax.make_jaxpr(lambda x, w: jax.lax.conv_general_dilated(x, w, (1,), "VALID"))(
        jnp.ones((2, 3, 20)), jnp.ones((4, 3, 5)))
    assert bm.matmul_flops(conv) == 2 * (2 * 4 * 16) * (3 * 5)
    # Depthwise (3 groups of one channel): 5 multiply-adds per output.
    depthwise = jax.make_jaxpr(lambda x, w: jax.lax.conv_general_dilated(x, w, (1,), "VALID", feature_group_count=3))(
        jnp.ones((2, 3, 20)), jnp.ones((3, 1, 5)))
    assert bm.matmul_flops(depthwise) == 2 * (2 * 3 * 16) * 5
    # Elementwise work is not counted; a cond counts its costlier branch; a jitted call is entered.
    branchy = jax.make_jaxpr(lambda p, x: jax.lax.cond(p, lambda v: jnp.sin(v), lambda v: jax.jit(jnp.matmul)(v, v), x))(
        True, jnp.ones((8, 8)))
    assert bm.matmul_flops(branchy) == 2 * 8**3


def test_loop_trip_factor_scales_scans_per_iteration_and_leaves_loop_free_programs_alone():
    w = jnp.ones((16, 16))

    def scanned(x):
        return jax.lax.scan(lambda c, _: (jnp.tanh(c @ w), None), x, None, length=5)[0]

    x = jnp.ones((8, 16))
    program = jax.make_jaxpr(scanned)(x)
    assert bm.matmul_flops(program) == 5 * 2 * 8 * 16 * 16
    assert bm.matmul_flops(program, per_trip=False) == 2 * 8 * 16 * 16
    assert bm.loop_trip_factor(program) == 5.0
    # Its gradient: 5 forward and 5 backward matmuls per trip, beside a loop-free matmul counted once.
    step = jax.jit(jax.grad(lambda x: (scanned(x) @ w).sum())).trace(x)
    assert bm.matmul_flops(step.jaxpr) == (10 + 2) * 2 * 8 * 16 * 16
    assert bm.loop_trip_factor(step.jaxpr) == pytest.approx(12 / 4)
    # XLA's count of the scanned program, so scaled, is the count of the program unrolled.
    unrolled = bm.xla_flops(lambda x: jnp.tanh(jnp.tanh(jnp.tanh(jnp.tanh(jnp.tanh(x @ w) @ w) @ w) @ w) @ w), x)
    assert bm.xla_flops(scanned, x) * bm.loop_trip_factor(program) == pytest.approx(unrolled, rel=0.02)
    assert bm.loop_trip_factor(jax.make_jaxpr(jnp.sin)(x)) == 1.0
    assert bm.loop_trip_factor(jax.make_jaxpr(lambda x: x @ w)(x)) == 1.0


def test_time_jitted_record():
    calls = []

    def f(x):
        calls.append(1)  # trace-time side effect: compiled once, then only executed
        return jnp.sin(x) @ x

    x = jnp.ones((32, 32))
    t = bm.time_jitted(f, x, repeats=5, warmup=1)
    assert len(calls) == 1
    assert len(t.runs) == 5 and all(r > 0 for r in t.runs)
    assert t.run_min_s == min(t.runs) and t.run_median_s == float(np.median(t.runs))
    assert 0 < t.lower_s <= t.compile_s
    with pytest.raises(ValueError, match="repeats"):
        bm.time_jitted(f, x, repeats=0)
    with pytest.raises(ValueError, match="warmup"):
        bm.time_jitted(f, x, warmup=-1)


def test_measure_matmul_peak_is_plausible():
    peak = bm.measure_matmul_peak(n=128, repeats=3)
    assert 1e6 < peak < 1e15
    with pytest.raises(ValueError, match="n must"):
        bm.measure_matmul_peak(n=0)


def test_measure_memory_bandwidth_is_plausible_and_refuses_bad_sizes():
    bandwidth = bm.measure_memory_bandwidth(nbytes=8 * 2**20, repeats=3)
    assert 1e7 < bandwidth < 1e13
    with pytest.raises(ValueError, match="nbytes must"):
        bm.measure_memory_bandwidth(nbytes=0)


def test_parameter_bytes_read_counts_exactly_the_leaves_the_function_uses():
    params = {"used": jnp.ones((10, 4), jnp.float32), "unused": jnp.ones((1000,), jnp.float32),
              "half": jnp.ones((6,), jnp.float16), "in_scan": jnp.ones((3, 3), jnp.float32)}

    def fn(p, x):
        y = x @ p["used"] + p["half"][:4].astype(jnp.float32).sum()
        carry, _ = jax.lax.scan(lambda c, _: (c @ p["in_scan"], None), jnp.ones((3,)), None, length=5)
        return y.sum() + carry.sum()

    assert bm.parameter_bytes_read(fn, params, jnp.ones((2, 10))) == 10 * 4 * 4 + 6 * 2 + 3 * 3 * 4
    assert bm.parameter_bytes_read(lambda p, x: x, params, jnp.ones(3)) == 0


def test_format_table_layout():
    rows = [
        {"sampler": "euler", "steps": 1, "run_ms": 1.23456, "note": None},
        {"sampler": "ddim", "steps": 20, "run_ms": 123.0, "extra": True},
    ]
    text = bm.format_table(rows, "Title")
    expected = "\n".join(
        [
            "Title",
            "sampler | steps | run_ms | note | extra",
            "--------+-------+--------+------+------",
            "euler   |     1 |  1.235 |    - | -",
            "ddim    |    20 |    123 |    - | True",
        ]
    )
    assert text == expected
    with pytest.raises(ValueError, match="at least one row"):
        bm.format_table([], "empty")


def test_print_table(capsys):
    bm.print_table([{"a": 1}], "T")
    assert capsys.readouterr().out == "T\na\n-\n1\n"


def test_write_json_creates_dirs_and_adds_machine_info_date_and_command(tmp_path):
    timing = bm.Timing(compile_s=1.0, lower_s=0.5, run_median_s=0.2, run_min_s=0.1, runs=(0.1, 0.2, 0.3))
    path = tmp_path / "a" / "b" / "out.json"
    written = bm.write_json(
        path, {"rows": [{"x": np.float32(1.5), "n": np.int64(3)}], "timing": timing, "arr": np.arange(3)}
    )
    assert written == path and path.exists()
    data = json.loads(path.read_text())
    assert data["rows"] == [{"x": 1.5, "n": 3}]
    assert data["timing"]["runs"] == [0.1, 0.2, 0.3]
    assert data["arr"] == [0, 1, 2]
    info = data["machine_info"]
    assert info["jax"] == jax.__version__ and info["backend"] == jax.default_backend()
    assert info["cpu_cores"] >= 1 and isinstance(info["cpu_model"], str)
    import datetime
    import pathlib
    import sys

    recorded = data["recorded"]
    assert datetime.datetime.fromisoformat(recorded["date_utc"]).tzinfo is not None
    assert recorded["command"].split()[0] == pathlib.Path(sys.argv[0]).name
