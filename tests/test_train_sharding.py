"""Data parallelism on 4 forced host devices (in a subprocess: the device count is fixed at JAX start):
the sharded step gives the 1-device loss and parameters, and batch sizes must divide the devices."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from multiprocess_helpers import worker_env

SCRIPT = r"""
import json
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import install_import_hook

jax.config.update("jax_numpy_rank_promotion", "raise")
with install_import_hook(["jaxtalk"], "beartype.beartype"):
    from jaxtalk.data.batching import BatchIterator
    from jaxtalk.train import (LoopSettings, OptimConfig, create_train_state, make_mesh, make_optimizer,
                               make_train_step, shard_batch, train)

out = {"devices": len(jax.devices())}
rng = np.random.default_rng(0)
x = rng.normal(size=(64, 4)).astype(np.float32)
data = {"x": x, "y": np.tanh(x @ rng.normal(size=(4, 2))).astype(np.float32)}

def loss_fn(p, batch, key):
    h = jnp.tanh(batch["x"] @ p["w1"])
    h = h * jax.random.bernoulli(key, 0.9, h.shape) / 0.9  # same key on every device: same mask
    err = h @ p["w2"] - batch["y"]
    return jnp.mean(err ** 2), {"max_err": jnp.max(jnp.abs(err))}

k1, k2 = jax.random.split(jax.random.key(0))
params = {"w1": jax.random.normal(k1, (4, 32)), "w2": jax.random.normal(k2, (32, 2)) * 0.3}
cfg = OptimConfig(lr=1e-2, warmup_steps=2, total_steps=6, ema_decay=0.9)
out["init_params"] = {k: np.asarray(v).tolist() for k, v in params.items()}

runs = {}
for name, mesh in (("one", None), ("four", make_mesh())):
    res = train(loss_fn, params, BatchIterator(data, 8, seed=1), cfg, key=jax.random.key(5),
                mesh=mesh, settings=LoopSettings(progress=False))
    runs[name] = res
    out[name + "_loss"] = [h["loss"] for h in res.history]
    out[name + "_max_err"] = [h["metrics"]["max_err"] for h in res.history]
    out[name + "_params"] = {k: np.asarray(v).tolist() for k, v in res.state.params.items()}
out["four_param_devices"] = len(runs["four"].state.params["w1"].sharding.device_set)
out["four_replicated"] = bool(runs["four"].state.params["w1"].sharding.is_fully_replicated)

# Lower level: the batch really is split 4 ways.
mesh = make_mesh()
batch = shard_batch(next(BatchIterator(data, 8, seed=1)), mesh)
out["batch_shard_shapes"] = sorted({tuple(s.data.shape) for s in batch["x"].addressable_shards})

errors = []
try:
    shard_batch({"x": np.zeros((6, 4), np.float32)}, mesh)
except ValueError as e:
    errors.append(str(e))
try:
    train(loss_fn, params, BatchIterator(data, 6, seed=1), cfg, key=jax.random.key(5), mesh=mesh,
          settings=LoopSettings(progress=False))
except ValueError as e:
    errors.append(str(e))
out["errors"] = errors
print("RESULT" + json.dumps(out))
"""


def _run_on_four_devices() -> dict:
    env = worker_env(4)
    root = Path(__file__).resolve().parents[1]
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT], cwd=root, env=env, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    line = next(ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT"))
    return json.loads(line[len("RESULT") :])


@pytest.mark.multiprocess  # a subprocess started with 4 forced host devices
def test_four_device_data_parallel_matches_one_device():
    out = _run_on_four_devices()
    assert out["devices"] == 4
    assert out["batch_shard_shapes"] == [[2, 4]]  # batch of 8 split into 4 shards of 2
    assert out["four_param_devices"] == 4 and out["four_replicated"]
    assert len(out["one_loss"]) == 6
    np.testing.assert_allclose(out["four_loss"], out["one_loss"], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(out["four_max_err"], out["one_max_err"], rtol=1e-5, atol=1e-6)
    for k in ("w1", "w2"):
        np.testing.assert_allclose(out["four_params"][k], out["one_params"][k], rtol=1e-5, atol=1e-6)
    # Training really moved the parameters (the comparison is not between two untouched inits).
    moved = max(np.abs(np.subtract(out["one_params"][k], out["init_params"][k])).max() for k in ("w1", "w2"))
    assert moved > 1e-2
    assert len(out["errors"]) == 2
    for msg in out["errors"]:
        assert "batch size 6" in msg and "not divisible by the 4 devices" in msg and "['x']" in msg
