"""Multi-host data parallelism, with two processes on this machine.

Two worker processes (tests/distributed_worker.py), each with 2 forced CPU devices, join one JAX run
over loopback (gloo collectives) and train a small linear regression on a 4-device mesh, each
feeding its half of every global batch. A third, single process with 4 devices trains on the full
global batches. Parameters, EMA, losses and metrics must agree (to float32 rounding: the
cross-process all-reduce sums in a different order), and the two processes must hold identical
parameters. The processes run concurrently, in subprocesses because the device count and the
distributed runtime are fixed when JAX starts, and are killed if they outlive a deadline.

The settings validation of :func:`jaxtalk.train.distributed.initialize` is tested in-process: it
raises before touching JAX.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxtalk.train import distributed
from multiprocess_helpers import ROOT, free_port, gloo_available, run_all, worker_env

WORKER = ROOT / "tests" / "distributed_worker.py"
DEADLINE_S = 240  # all three processes together; a healthy run takes 10-20 s


def _run_all(jobs: list[tuple[list[str], dict[str, str], Path]]) -> None:
    run_all([([sys.executable, str(WORKER), *args], env, log) for args, env, log in jobs], DEADLINE_S)


@pytest.mark.multiprocess
@pytest.mark.slow  # three JAX processes on a shared 2-core machine: 13-22 s
@pytest.mark.skipif(not gloo_available(), reason="this jaxlib has no gloo CPU collectives")
def test_two_processes_match_one_process(tmp_path):
    multi, single = tmp_path / "multi", tmp_path / "single"
    multi.mkdir()
    single.mkdir()
    port = free_port()
    coordinator = f"127.0.0.1:{port}"
    # Bind the coordinator service to loopback only (JAX's default is every interface).
    loopback = {"JAX_COORDINATOR_BIND_ADDRESS": coordinator}
    jobs = [
        (
            ["--out", str(multi), "--num-processes", "2", "--process-id", str(p), "--coordinator", coordinator],
            worker_env(2, loopback),
            tmp_path / f"process{p}.log",
        )
        for p in range(2)
    ]
    jobs.append((["--out", str(single)], worker_env(4), tmp_path / "single.log"))
    _run_all(jobs)

    checks = [json.loads((multi / f"checks_p{p}.json").read_text()) for p in range(2)]
    for p, c in enumerate(checks):
        assert (c["index"], c["count"], c["devices"], c["local"]) == (p, 2, 4, 2)
        assert c["global_shape"] == [8, 4]  # two local halves of 4 rows -> one global batch of 8
        assert c["assembled_ok"]  # ... holding the global batch's rows in order
        assert c["replicated"] and c["param_devices"] == 4
        assert "differ between processes" in c["replicate_error"] and "['w']" in c["replicate_error"]
        assert "['same']" not in c["replicate_error"]
        assert f"already called as process {p} of 2; cannot re-initialise as process {1 - p} of 2" in c["reinit_error"]
    ref_checks = json.loads((single / "checks_p0.json").read_text())
    assert (ref_checks["count"], ref_checks["devices"]) == (1, 4)

    p0, p1 = (np.load(multi / f"result_p{p}.npz") for p in range(2))
    ref = np.load(single / "result_p0.npz")
    assert len(ref["loss"]) == 5
    for k in ref.files:
        np.testing.assert_array_equal(p0[k], p1[k], err_msg=f"{k} differs between the two processes")
        np.testing.assert_allclose(p0[k], ref[k], rtol=1e-6, atol=1e-7, err_msg=f"{k}: 2 processes vs 1")
    assert np.abs(ref["w"] - ref["init_w"]).max() > 1e-2  # training moved the parameters


def test_initialize_rejects_partial_settings(monkeypatch):
    for name in (distributed.ENV_COORDINATOR, distributed.ENV_NUM_PROCESSES, distributed.ENV_PROCESS_ID):
        monkeypatch.delenv(name, raising=False)
    with pytest.raises(ValueError, match=r"partial: missing num_processes .*JAXTALK_NUM_PROCESSES.*, process_id"):
        distributed.initialize("127.0.0.1:1234")
    monkeypatch.setenv(distributed.ENV_COORDINATOR, "127.0.0.1:1234")
    monkeypatch.setenv(distributed.ENV_NUM_PROCESSES, "2")
    with pytest.raises(ValueError, match=r"missing process_id \(or \$JAXTALK_PROCESS_ID\)"):
        distributed.initialize()
    with pytest.raises(ValueError, match=r"process_id must be in \[0, 2\), got 2"):
        distributed.initialize(process_id=2)
    monkeypatch.setenv(distributed.ENV_PROCESS_ID, "one")
    with pytest.raises(ValueError, match="JAXTALK_PROCESS_ID must be an integer, got 'one'"):
        distributed.initialize()
    with pytest.raises(ValueError, match="num_processes must be >= 1, got 0"):
        distributed.initialize(num_processes=0, process_id=0)
    with pytest.raises(ValueError, match="must be 'host:port'"):
        distributed.initialize("localhost", process_id=0)


def test_process_info_single_process():
    assert distributed.process_info() == (0, 1)
