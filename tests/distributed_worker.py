"""One process of the multi-host training test (tests/test_train_distributed.py); not a test itself.

Trains a small linear regression for a few steps with :func:`jaxtalk.train.train` on a mesh over
every device of every process and writes what it ended with to ``<out>/result_p<index>.npz`` (and
a JSON of extra checks). ``--num-processes 1`` is the single-process reference: it feeds the whole
global batches; with 2 processes each feeds its contiguous half of each global batch.

Run by the test with ``XLA_FLAGS=--xla_force_host_platform_device_count=N`` and
``JAX_PLATFORMS=cpu``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import install_import_hook

START = time.perf_counter()

jax.config.update("jax_numpy_rank_promotion", "raise")
with install_import_hook(["jaxtalk"], "beartype.beartype"):
    from jaxtalk.train import LoopSettings, OptimConfig, make_mesh, replicate, shard_batch, train
    from jaxtalk.train.distributed import initialize, process_info

N_EXAMPLES, GLOBAL_BATCH, STEPS = 32, 8, 5


def dataset() -> dict[str, np.ndarray]:
    """32 fixed examples of a noisy 4 -> 2 linear map (the same on every process)."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=(N_EXAMPLES, 4)).astype(np.float32)
    w = rng.normal(size=(4, 2)).astype(np.float32)
    y = (x @ w + 0.1 * rng.normal(size=(N_EXAMPLES, 2))).astype(np.float32)
    return {"x": x, "y": y}


def global_batches(data: dict[str, np.ndarray]):
    """Endless global batches: each epoch a fresh fixed permutation cut into batches of 8."""
    per_epoch = N_EXAMPLES // GLOBAL_BATCH
    for s in itertools.count():
        perm = np.random.default_rng((1, s // per_epoch)).permutation(N_EXAMPLES)
        rows = perm[(s % per_epoch) * GLOBAL_BATCH : (s % per_epoch + 1) * GLOBAL_BATCH]
        yield {k: v[rows] for k, v in data.items()}


def local_part(batch: dict[str, np.ndarray], index: int, count: int) -> dict[str, np.ndarray]:
    """Process ``index``'s contiguous share of a global batch (make_mesh groups devices by process)."""
    b = GLOBAL_BATCH // count
    return {k: v[index * b : (index + 1) * b] for k, v in batch.items()}


def loss_fn(params, batch, key):
    # Input dropout: the step key must be the same on every process (replicated rng) for this to
    # match the single-process run.
    keep = jax.random.bernoulli(key, 0.8, batch["x"].shape)
    err = (batch["x"] * keep / 0.8) @ params["w"] + params["b"][None, :] - batch["y"]
    return jnp.mean(err**2), {"mae": jnp.mean(jnp.abs(err))}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", required=True)
    parser.add_argument("--num-processes", type=int, default=1)
    parser.add_argument("--process-id", type=int, default=0)
    parser.add_argument("--coordinator", default=None)
    args = parser.parse_args()

    t_init = time.perf_counter()
    if args.num_processes > 1:
        initialize(args.coordinator, args.num_processes, args.process_id)
        initialize(args.coordinator, args.num_processes, args.process_id)  # idempotent
        try:
            initialize(args.coordinator, args.num_processes, 1 - args.process_id)
            reinit_error = None
        except ValueError as e:
            reinit_error = str(e)
    index, count = process_info()
    mesh = make_mesh()
    data = dataset()
    checks: dict = {"index": index, "count": count, "devices": jax.device_count(), "local": jax.local_device_count()}
    checks["seconds"] = {"imports": t_init - START, "initialize": time.perf_counter() - t_init}

    # The local halves really assemble into the global batch, in order.
    first = next(global_batches(data))
    assembled = shard_batch(local_part(first, index, count), mesh)
    checks["global_shape"] = list(assembled["x"].shape)
    if count > 1:
        from jax.experimental import multihost_utils

        checks["reinit_error"] = reinit_error

        gathered = multihost_utils.process_allgather(assembled, tiled=True)
        checks["assembled_ok"] = all(np.array_equal(np.asarray(gathered[k]), first[k]) for k in first)
        # replicate refuses state that differs between processes.
        try:
            replicate({"w": np.full(3, index, np.float32), "same": np.ones(2, np.float32)}, mesh)
            checks["replicate_error"] = None
        except ValueError as e:
            checks["replicate_error"] = str(e)

    params = {"w": 0.1 * jax.random.normal(jax.random.key(0), (4, 2)), "b": jnp.zeros(2)}
    cfg = OptimConfig(lr=5e-2, warmup_steps=1, total_steps=STEPS, ema_decay=0.9)
    local_batches = (local_part(b, index, count) for b in global_batches(data))
    t_train = time.perf_counter()
    res = train(loss_fn, params, local_batches, cfg, key=jax.random.key(5), mesh=mesh,
                settings=LoopSettings(progress=False, log_every=2))

    checks["seconds"]["train"] = time.perf_counter() - t_train
    checks["replicated"] = bool(res.state.params["w"].sharding.is_fully_replicated)
    checks["param_devices"] = len(res.state.params["w"].sharding.device_set)
    out = Path(args.out)
    np.savez(
        out / f"result_p{index}.npz",
        w=np.asarray(res.state.params["w"]),
        b=np.asarray(res.state.params["b"]),
        ema_w=np.asarray(res.state.ema_params["w"]),
        ema_b=np.asarray(res.state.ema_params["b"]),
        loss=np.array([h["loss"] for h in res.history]),
        mae=np.array([h["metrics"]["mae"] for h in res.history]),
        init_w=np.asarray(params["w"]),
    )
    (out / f"checks_p{index}.json").write_text(json.dumps(checks))


if __name__ == "__main__":
    main()
