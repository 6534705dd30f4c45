"""Shared by the multi-process tests: gloo detection, a free loopback port, a clean worker
environment, and running several processes under one deadline (never a hanging test)."""

from __future__ import annotations

import os
import socket
import subprocess
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def gloo_available() -> bool:
    """Whether this jaxlib has gloo CPU collectives (two local processes can form one mesh)."""
    try:
        from jax._src.lib import _jax  # private, but the only place jaxlib exposes it
    except ImportError:
        return False
    return hasattr(_jax, "make_gloo_tcp_collectives")


def free_port() -> int:
    """A currently unused loopback TCP port (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def worker_env(device_count: int, extra: dict[str, str] | None = None) -> dict[str, str]:
    """This process's environment for a worker with ``device_count`` forced CPU devices."""
    env = {
        k: v
        for k, v in os.environ.items()
        # No inherited cluster settings (they would redirect initialize) and no proxies (gRPC to
        # the coordinator could be routed through one and hang).
        if not k.startswith(("JAXTALK_", "JAX_COORDINATOR", "JAX_PROCESS", "JAX_NUM_PROCESSES"))
        and "proxy" not in k.lower()
    }
    # The suite's XLA flags (tests/conftest.py) and the forced devices.
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={device_count}".strip()
    env.update({"XLA_FLAGS": flags, "JAX_PLATFORMS": "cpu"})
    env.update(extra or {})
    return env


def run_all(jobs: list[tuple[list[str], dict[str, str], Path]], deadline_s: float) -> None:
    """Start every ``(argv, env, log)`` job at once; wait for all under one deadline; on the first
    failure (or the deadline) fail the test with the logs and kill the rest."""
    procs = []
    try:
        for args, env, log in jobs:
            with open(log, "w") as f:  # to files, not pipes: a full pipe would block the process
                procs.append(subprocess.Popen(args, cwd=ROOT, env=env, stdout=f, stderr=subprocess.STDOUT))
        deadline = time.monotonic() + deadline_s
        logs = [log for _, _, log in jobs]
        pending = set(range(len(procs)))
        while pending:
            for i in sorted(pending):
                rc = procs[i].poll()
                if rc is None:
                    continue
                pending.discard(i)
                if rc != 0:
                    pytest.fail(f"{logs[i].name} exited with {rc}:\n{logs[i].read_text()[-4000:]}")
            if pending and time.monotonic() > deadline:
                pytest.fail(f"still running after {deadline_s} s: "
                            + "; ".join(f"{logs[i].name}: {logs[i].read_text()[-1500:]}" for i in sorted(pending)))
            time.sleep(0.1)
    finally:
        for proc in procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait(timeout=30)
