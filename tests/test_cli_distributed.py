"""``jaxtalk train toktalk --distributed`` with two processes on this machine.

Two ``python -m jaxtalk train`` processes, each with 2 forced CPU devices, join one JAX run over
loopback (gloo collectives) and train TokTalk (tiny) for 3 steps on prepared SynthTalk tiny with 2
windows per process (a global batch of 4). A third, single process with 4 devices trains the same
run with ``--data-parallel`` and batch size 4: the reference. The loader gives each process its
contiguous half of every global batch of the one shuffled stream, so both runs see the same batches
row for row; the parameters, EMA and optimiser state they end with must agree to float32 rounding
(the cross-process all-reduce sums in another order).

With 3 steps the CLI checkpoints and validates after every step, so the run also exercises, across
processes: orbax saves (every process takes part), the best-validation checkpoint, the validation
loss on parameters that span both processes, and the run files only process 0 writes (``run.json``,
``history.jsonl``). The distributed run is then read back in this single process (``load_run``).
Finally its last checkpoint is deleted and the two processes resume it: from process 0's saved loader
position, each process continues its own part of the batches and the run ends where it did.

The processes run concurrently, in subprocesses because the device count and the distributed runtime
are fixed when JAX starts, and are killed if they outlive a deadline.
"""

from __future__ import annotations

import re
import shutil
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest
from multiprocess_helpers import free_port, gloo_available, run_all, worker_env

# Per phase, all its processes together. Measured on the 2 shared cores: 170-200 s and 85-135 s
# while other jobs kept them busy (load 5-9); the whole test uses about 3.5 CPU-minutes.
DEADLINE_S = 420
STEPS = 3
# Attention key biases: softmax ignores them, so their gradient is zero but for float32 rounding, which
# differs with the summation order; Adam scales each gradient element to about the learning rate, so
# they move by rounding noise (~1e-5 here) in both runs, just not the same noise.
NOISE = "['key']['bias']"
# The learning rate is 2e-3 and Adam's first steps move each parameter by about that much whatever the
# size of its gradient: an element whose gradient is near zero turns the gradient's rounding
# difference into a visible update difference. Hence, on top of float32's rtol, an absolute tolerance
# of lr / 200 for the bulk of the elements (measured: 5.6e-6 at most), and lr / 20 for the few
# near-zero-gradient ones (CI measured one element of 512 at 1.6e-5). A wrong run (gradients not
# all-reduced, batches misaligned) moves nearly every element by about lr, so both bounds still catch it.
PARAM_ATOL = 1e-5
OUTLIER_ATOL = 1e-4
OUTLIER_FRACTION = 1e-3  # of all the tree's elements
PARAMS_CLOSE = {"atol": PARAM_ATOL, "noise_atol": 1e-4, "outlier_atol": OUTLIER_ATOL}
# The optimiser's moments are gradients taken at parameters that differ by the rounding above: they
# agree to a small fraction of each leaf's scale (measured: 1.6e-5 of the leaf's max), where a wrong run
# differs by its whole scale.
MOMENT_SCALE_RTOL = 1e-4
# TokTalk's smallest graph (compile time dominates a 3-step run).
# One streamed validation clip: sampling on parameters that span both processes, at an eighth of the cost.
COMMON = ["train", "toktalk", "--data", "synthtalk:tiny", "--preset", "tiny", "--set", "num_mid_blocks=0",
          "--set", "val_clips=1",
          "--steps", str(STEPS), "--seed", "0", "--no-progress"]


def _env(device_count: int, cache: Path, extra: dict[str, str] | None = None) -> dict[str, str]:
    return worker_env(device_count, {
        "JAX_DISABLE_MOST_OPTIMIZATIONS": "1",  # compile time dominates; the same in every process
        # The resumed run compiles what the first one did: a persistent cache saves most of it.
        "JAX_COMPILATION_CACHE_DIR": str(cache),
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
        "TF_CPP_MIN_LOG_LEVEL": "2",
        **(extra or {}),
    })


def _run_all(jobs: list[tuple[list[str], dict[str, str], Path]]) -> None:
    run_all([([sys.executable, "-m", "jaxtalk", *args], env, log) for args, env, log in jobs], DEADLINE_S)


def _summary(log: Path) -> dict[str, float]:
    """The numbers of the CLI's last line (``toktalk: step 0 -> 3 on N windows, final loss ...``)."""
    m = re.search(r"step 0 -> (\d+) on (\d+) windows, final loss ([\d.]+), validation loss ([\d.]+)", log.read_text())
    assert m, log.read_text()[-2000:]
    return {"step": int(m[1]), "windows": int(m[2]), "loss": float(m[3]), "val_loss": float(m[4])}


def _saved(ckpt_dir: Path, step: int | None = None) -> dict:
    from jaxtalk.train import Checkpointer

    with Checkpointer(ckpt_dir, read_only=True) as ckpt:
        state, _ = ckpt.restore_saved(step)
    return state


def _max_diff(a, b) -> float:
    return max(float(np.max(np.abs(np.asarray(x, np.float64) - np.asarray(y, np.float64)), initial=0.0))
               for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True))


def _assert_trees_close(a, b, what: str, *, rtol: float = 1e-5, atol: float = 0.0, scale_rtol: float = 0.0,
                        noise_atol: float | None = None, outlier_atol: float | None = None) -> None:
    """Leafwise ``|a - b| <= atol + scale_rtol * max|b| + rtol * |b|``; leaves in :data:`NOISE` get
    ``noise_atol`` instead (None: only their shapes are compared). With ``outlier_atol``, up to
    :data:`OUTLIER_FRACTION` of the tree's elements may miss that bound if they are within ``outlier_atol``."""
    assert jax.tree.structure(a) == jax.tree.structure(b), what
    outliers, total = [], 0
    for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(a), jax.tree.leaves(b), strict=True):
        x, y, name = np.asarray(x), np.asarray(y), jax.tree_util.keystr(path)
        assert x.shape == y.shape, name
        if NOISE in name:
            if noise_atol is not None:
                np.testing.assert_allclose(x, y, rtol=0, atol=noise_atol, err_msg=f"{what}{name}: 2 processes vs 1")
            continue
        tol = atol + scale_rtol * float(np.max(np.abs(y), initial=0.0))
        if outlier_atol is None:
            np.testing.assert_allclose(x, y, rtol=rtol, atol=tol, err_msg=f"{what}{name}: 2 processes vs 1")
            continue
        err = np.abs(x.astype(np.float64) - y) - rtol * np.abs(y)
        np.testing.assert_allclose(x, y, rtol=rtol, atol=outlier_atol, err_msg=f"{what}{name}: 2 processes vs 1")
        outliers += [(name, float(e)) for e in err[err > tol]]
        total += x.size
    assert len(outliers) <= OUTLIER_FRACTION * total, \
        f"{what}: {len(outliers)} of {total} elements beyond {atol}: {outliers[:10]}"


@pytest.mark.multiprocess
@pytest.mark.slow  # 3 + 2 JAX processes compiling TokTalk on 2 shared cores: 2-5 min (see DEADLINE_S)
@pytest.mark.skipif(not gloo_available(), reason="this jaxlib has no gloo CPU collectives")
def test_cli_train_distributed_two_processes_match_one_process(prepared_tiny, tmp_path):
    from jaxtalk.runs import RunRecord, checkpoint_dir, load_run
    from jaxtalk.train import read_best, read_history

    cache = str(prepared_tiny.root.parent)  # --data synthtalk:tiny is found there, already prepared
    jax_cache = tmp_path / "jax_cache"
    multi, single = tmp_path / "multi", tmp_path / "single"

    def distributed_jobs() -> list[tuple[list[str], dict[str, str], Path]]:
        coordinator = f"127.0.0.1:{free_port()}"
        # The coordinator service listens on loopback only (JAX's default: every interface).
        cluster = {"JAXTALK_COORDINATOR": coordinator, "JAXTALK_NUM_PROCESSES": "2",
                   "JAX_COORDINATOR_BIND_ADDRESS": coordinator}
        args = [*COMMON, "--cache-dir", cache, "--set", "batch_size=2", "--distributed", "--out", str(multi)]
        return [(args, _env(2, jax_cache, {**cluster, "JAXTALK_PROCESS_ID": str(p)}), tmp_path / f"process{p}.log")
                for p in range(2)]

    reference = ([*COMMON, "--cache-dir", cache, "--set", "batch_size=4", "--data-parallel", "--out", str(single)],
                 _env(4, jax_cache), tmp_path / "single.log")
    t0 = time.monotonic()
    _run_all([*distributed_jobs(), reference])
    print(f"three processes: {time.monotonic() - t0:.1f} s")

    # Both processes trained the same model: the same losses (the loss of the global batch).
    p0, p1, ref = (_summary(tmp_path / name) for name in ("process0.log", "process1.log", "single.log"))
    assert p0["step"] == p1["step"] == ref["step"] == STEPS
    assert (p0["loss"], p0["val_loss"]) == (p1["loss"], p1["val_loss"])
    assert p0["windows"] + p1["windows"] == ref["windows"]  # each process's share of the windows
    assert not any(path.name.endswith("-tmp") or "tmp" in path.suffix for path in multi.rglob("*"))

    # The run files are written once (by process 0), and the run reads like a one-process run.
    record, ref_record = RunRecord.load(multi), RunRecord.load(single)
    assert record.config == ref_record.config and record.extra == ref_record.extra
    assert record.train["batch_size"] == 2 and ref_record.train["batch_size"] == 4
    history, ref_history = read_history(checkpoint_dir(multi)), read_history(checkpoint_dir(single))
    assert [(r["type"], r["step"]) for r in history] == [(r["type"], r["step"]) for r in ref_history]
    assert [r["step"] for r in history if r["type"] == "eval"] == list(range(1, STEPS + 1))
    for row, ref_row in zip(history, ref_history):
        values = row.get("eval") or {"loss": row["loss"], **row["metrics"]}
        ref_values = ref_row.get("eval") or {"loss": ref_row["loss"], **ref_row["metrics"]}
        for k, v in ref_values.items():
            assert values[k] == pytest.approx(v, rel=1e-4, abs=1e-6), (row["step"], k)

    # Checkpoints: every step saved by both processes together; the same state as the reference's.
    from jaxtalk.train import Checkpointer

    with Checkpointer(checkpoint_dir(multi), read_only=True) as ckpt:
        assert ckpt.all_steps() == list(range(1, STEPS + 1))
    state, ref_state = _saved(checkpoint_dir(multi)), _saved(checkpoint_dir(single))
    assert int(state["step"]) == int(ref_state["step"]) == STEPS
    np.testing.assert_array_equal(state["rng"], ref_state["rng"])
    init = _saved(checkpoint_dir(single), 1)["params"]
    assert _max_diff(ref_state["params"], init) > 10 * OUTLIER_ATOL  # training moved the parameters (Adam: ~lr a step)
    print(f"max |params difference| 2 processes vs 1: {_max_diff(state['params'], ref_state['params']):.3g}, "
          f"EMA: {_max_diff(state['ema_params'], ref_state['ema_params']):.3g}, "
          f"optimiser state: {_max_diff(state['opt_state'], ref_state['opt_state']):.3g}")
    _assert_trees_close(state["params"], ref_state["params"], "params", **PARAMS_CLOSE)
    _assert_trees_close(state["ema_params"], ref_state["ema_params"], "ema_params", **PARAMS_CLOSE)
    _assert_trees_close(state["opt_state"], ref_state["opt_state"], "opt_state", scale_rtol=MOMENT_SCALE_RTOL)

    # The best-validation checkpoint: the same step, value and state.
    best, ref_best = read_best(checkpoint_dir(multi)), read_best(checkpoint_dir(single))
    assert best["step"] == ref_best["step"] and best["value"] == pytest.approx(ref_best["value"], rel=1e-4)

    # Read back in this single process, as sample/stream/eval would.
    loaded, ref_loaded = load_run(multi), load_run(single)
    assert loaded.step == STEPS
    _assert_trees_close(loaded.params, ref_loaded.params, "load_run params", **PARAMS_CLOSE)
    _assert_trees_close(load_run(multi, best=True).params, load_run(single, best=True).params, "best params",
                        **PARAMS_CLOSE)

    # Resume across processes: without its last checkpoint the run restarts from step STEPS - 1
    # (state, optimiser, RNG, each process's loader position, the history and the best record) and
    # must end where it did.
    shutil.rmtree(checkpoint_dir(multi) / str(STEPS))
    for p in range(2):
        (tmp_path / f"process{p}.log").rename(tmp_path / f"first{p}.log")
    _run_all(distributed_jobs())
    for p in range(2):
        assert f"resuming toktalk (tiny) from step {STEPS - 1} to {STEPS}" in (tmp_path / f"process{p}.log").read_text()
    resumed = _saved(checkpoint_dir(multi))
    assert int(resumed["step"]) == STEPS
    for what in ("params", "ema_params", "opt_state"):  # the same computation: bitwise, or nearly
        _assert_trees_close(resumed[what], state[what], f"resumed {what}", rtol=1e-6, atol=1e-9, noise_atol=1e-9)
    rows = read_history(checkpoint_dir(multi))
    assert [(r["type"], r["step"]) for r in rows] == [(r["type"], r["step"]) for r in history]
    assert read_best(checkpoint_dir(multi))["step"] == best["step"]
    print(f"two phases: {time.monotonic() - t0:.1f} s")
