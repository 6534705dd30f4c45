"""``jaxtalk bench`` and :mod:`jaxtalk.bench`: table structure, FLOP accounting, fraction of peak."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from typer.testing import CliRunner

from jaxtalk import bench
from jaxtalk.cli import app

runner = CliRunner()


def test_random_params_match_the_initialiser_shapes():
    from jaxtalk.models.toktalk import TokTalkConfig, init_params

    config = TokTalkConfig.tiny()
    got = bench.random_params(lambda k: init_params(config, k), seed=1)
    want = jax.eval_shape(lambda k: init_params(config, k), jax.random.key(0))
    assert jax.tree.structure(got) == jax.tree.structure(want)
    for (path, g), w in zip(jax.tree_util.tree_flatten_with_path(got)[0], jax.tree.leaves(want)):
        assert g.shape == w.shape and g.dtype == w.dtype
        name = jax.tree_util.keystr(path)
        if name.endswith("['scale']") or name.endswith("['std']"):
            assert np.all(np.asarray(g) == 1)
        elif name.endswith("['bias']"):
            assert np.all(np.asarray(g) == 0)
    again = bench.random_params(lambda k: init_params(config, k), seed=1)
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(again)))


def test_with_peak_divides_and_keeps_unknowns():
    rows = bench.with_peak([{"gflop_s": 5.0}, {"gflop_s": None}, {"x": 1}], 20.0)
    assert rows[0]["of_peak"] == 0.25 and rows[1]["of_peak"] is None and rows[2]["of_peak"] is None
    assert all("of_bandwidth" not in r for r in rows)


def test_median_time_waits_for_work_queued_before_it_before_timing():
    import time

    import jax
    import jax.numpy as jnp

    slow = jax.jit(lambda x: jax.lax.fori_loop(0, 200, lambda i, y: jnp.tanh(y @ y), x))
    x = jnp.ones((256, 256)) * 1e-3
    jax.block_until_ready(slow(x))  # compiled here, so that `alone` is one run's time, not the compile's
    t0 = time.perf_counter()
    jax.block_until_ready(slow(x))
    alone = time.perf_counter() - t0
    for _ in range(3):  # dispatched, not waited for: a fill loop before the timing
        x = slow(x)
    fast = jnp.zeros(())
    # A trivial call timed after the queue: only the untimed first call may wait for the queue.
    assert bench._median_time(lambda: fast + 1, 1) < alone / 4


def test_with_peak_puts_weight_reads_against_the_bandwidth_and_the_roofline():
    # 2 GFLOP and 1 GB of weights in 0.5 s, on a 20 GFLOP/s peak and 4 GB/s: the FLOPs need 0.1 s,
    # the weights 0.25 s, so the roofline's 0.25 s is half the latency.
    row = {"latency_s": 0.5, "gflops": 2.0, "gflop_s": 4.0, "weight_gb": 1.0, "weight_gb_s": 2.0, "z": 0}
    (got,) = bench.with_peak([row], 20.0, 4.0)
    assert list(got) == ["latency_s", "gflops", "gflop_s", "of_peak", "weight_gb", "weight_gb_s", "of_bandwidth",
                         "of_roofline", "z"]
    assert got["of_peak"] == 0.2 and got["of_bandwidth"] == 0.5 and got["of_roofline"] == 0.5
    (compute_bound,) = bench.with_peak([{**row, "gflops": 8.0, "gflop_s": 16.0}], 20.0, 4.0)
    assert compute_bound["of_roofline"] == pytest.approx(0.8)  # 8 GFLOP at 20 GFLOP/s = 0.4 s of 0.5
    (again,) = bench.with_peak([got], 40.0, 8.0)  # re-expressed against other limits, not appended twice
    assert list(again) == list(got) and again["of_bandwidth"] == 0.25 and again["of_roofline"] == 0.25


@pytest.mark.slow
def test_toktalk_table_rates_and_fraction_of_peak(monkeypatch):
    from jaxtalk import benchmarking
    from jaxtalk.models.toktalk import TokTalkConfig

    monkeypatch.setattr(benchmarking, "measure_matmul_peak", lambda *a, **k: 50e9)  # tested in test_benchmarking
    monkeypatch.setattr(benchmarking, "measure_memory_bandwidth", lambda *a, **k: 5e9)
    config = TokTalkConfig.tiny()
    lines: list[str] = []
    peak, bandwidth, tables = bench.run_benchmarks(["toktalk"], repeats=1, configs={"toktalk": config}, echo=lines.append)
    assert (peak, bandwidth) == (50.0, 5.0) and len(tables) == 1 and lines
    (row,) = tables[0].rows
    assert row["model"] == "TokTalk" and row["window_frames"] == config.context_frames + config.chunk_frames
    assert row["rtf"] == pytest.approx(row["latency_s"] / (config.chunk_frames / config.fps))
    assert row["gflop_s"] == pytest.approx(row["gflops"] / row["latency_s"])
    assert row["of_peak"] == pytest.approx(row["gflop_s"] / 50.0)
    # At least the decoder's matmuls: 2 (CFG) x steps x window x channels^2 (one dense layer's worth).
    floor = 2 * config.sample_steps * row["window_frames"] * config.width**2 * 2 / 1e9
    assert row["gflops"] > floor
    # Every Euler step reads the decoder's weights (not the style encoder's, nor the standardiser's).
    from jaxtalk.models.toktalk import init_params

    params = init_params(config, jax.random.key(0))
    decoder = sum(leaf.nbytes for leaf in jax.tree.leaves(params["decoder"]))
    assert row["weight_gb"] * 1e9 == pytest.approx(config.sample_steps * decoder, rel=1e-12)
    assert row["of_bandwidth"] == pytest.approx(row["weight_gb"] / row["latency_s"] / 5.0)


def test_bench_user_errors(tmp_path):
    result = runner.invoke(app, ["bench", "--model", "wavenet", "--out", str(tmp_path / "b.json")])
    assert result.exit_code == 2 and "unknown benchmark model(s) ['wavenet']" in result.output
    with pytest.raises(ValueError, match="repeats must be >= 1"):
        bench.run_benchmarks(["toktalk"], repeats=0)
