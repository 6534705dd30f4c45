"""Multi-host (multi-process) start-up for data-parallel training.

Call :func:`initialize` once per process, before anything else touches JAX (``jax.devices()``,
any computation, :func:`jaxtalk.train.make_mesh`): JAX fixes its device list when its backend
starts, and only a backend started after ``jax.distributed.initialize`` sees the other processes'
devices. After it, ``jax.devices()`` lists every process's devices, :func:`jaxtalk.train.make_mesh`
spans them all, and :func:`jaxtalk.train.train` with that mesh trains one model on all of them:

* every process runs the same program (same ``loss_fn``, ``init_params``, ``key`` and config), so
  the replicated state is identical everywhere (:func:`jaxtalk.train.replicate` checks this);
* every process feeds its **own** part of each global batch: the batch size a process's loader
  yields is the per-process batch, and the global batch is ``per_process x process_count``. With
  :func:`jaxtalk.train.make_mesh`, process ``p`` holds rows ``[p * b, (p + 1) * b)`` of each global
  batch of ``b * process_count`` rows.

Example, two processes on one machine (CPU, two devices each)::

    JAXTALK_COORDINATOR=127.0.0.1:12345 JAXTALK_NUM_PROCESSES=2 JAXTALK_PROCESS_ID=0 python run.py &
    JAXTALK_COORDINATOR=127.0.0.1:12345 JAXTALK_NUM_PROCESSES=2 JAXTALK_PROCESS_ID=1 python run.py

with ``run.py`` calling ``jaxtalk.train.distributed.initialize()`` first.
"""

from __future__ import annotations

import os

import jax

__all__ = ["initialize", "process_info", "ENV_COORDINATOR", "ENV_NUM_PROCESSES", "ENV_PROCESS_ID"]

ENV_COORDINATOR = "JAXTALK_COORDINATOR"
ENV_NUM_PROCESSES = "JAXTALK_NUM_PROCESSES"
ENV_PROCESS_ID = "JAXTALK_PROCESS_ID"


def initialize(
    coordinator_address: str | None = None,
    num_processes: int | None = None,
    process_id: int | None = None,
) -> None:
    """Join this process to a multi-process JAX run (idempotent).

    Each setting comes from its argument, else from its environment variable
    (``JAXTALK_COORDINATOR``, ``JAXTALK_NUM_PROCESSES``, ``JAXTALK_PROCESS_ID``). Give all three or
    none: with none, ``jax.distributed.initialize`` detects the cluster itself (Slurm, Open MPI,
    TPU pods, ...). On CPU, cross-process collectives use gloo (unless another implementation,
    e.g. ``"mpi"``, was configured explicitly): without a CPU collectives implementation the
    processes would start but the gradient all-reduce across them would fail.

    A second call is a no-op (``jax.distributed.initialize`` itself refuses a second call), provided
    the settings it is given agree with the running ones.

    Args:
        coordinator_address: ``host:port`` of process 0's coordinator service, reachable from every
            process.
        num_processes: total number of processes (>= 1).
        process_id: this process's index, ``0 <= process_id < num_processes``.

    Raises:
        ValueError: only some of the three settings given (names the missing ones), a setting that
            is not a valid integer or out of range, or settings that differ from those of an
            earlier, successful call.
        RuntimeError: (from JAX) the JAX backend was already started in this process, e.g. by
            ``jax.devices()`` or any computation before this call.
    """
    coordinator, count, index = _resolve(coordinator_address, num_processes, process_id)

    if jax.distributed.is_initialized():
        # Compare only what was asked for; jax's own state is the truth for the rest.
        if count is not None and (count, index) != (jax.process_count(), jax.process_index()):
            raise ValueError(
                f"jaxtalk.train.distributed.initialize was already called as process "
                f"{jax.process_index()} of {jax.process_count()}; cannot re-initialise as process "
                f"{index} of {count}"
            )
        return

    # Must precede backend start-up: the CPU client reads this flag when it is created.
    if jax.config.jax_cpu_collectives_implementation is None:
        jax.config.update("jax_cpu_collectives_implementation", "gloo")

    if coordinator is None:
        jax.distributed.initialize()  # cluster auto-detection
    else:
        jax.distributed.initialize(coordinator_address=coordinator, num_processes=count, process_id=index)


def process_info() -> tuple[int, int]:
    """This process's index and the number of processes.

    ``(0, 1)`` in an ordinary single-process run. Starts the JAX backend, so in a multi-process run
    call it only after :func:`initialize`.

    Returns:
        ``(jax.process_index(), jax.process_count())``.
    """
    return jax.process_index(), jax.process_count()


def _resolve(
    coordinator_address: str | None, num_processes: int | None, process_id: int | None
) -> tuple[str | None, int | None, int | None]:
    """Merge arguments over environment variables and validate: all three settings or none."""
    coordinator = coordinator_address if coordinator_address is not None else os.environ.get(ENV_COORDINATOR) or None
    count = num_processes if num_processes is not None else _env_int(ENV_NUM_PROCESSES)
    index = process_id if process_id is not None else _env_int(ENV_PROCESS_ID)

    settings = {
        f"coordinator_address (or ${ENV_COORDINATOR})": coordinator,
        f"num_processes (or ${ENV_NUM_PROCESSES})": count,
        f"process_id (or ${ENV_PROCESS_ID})": index,
    }
    missing = [name for name, value in settings.items() if value is None]
    if missing and len(missing) < len(settings):
        raise ValueError(
            "multi-process settings are partial: missing "
            + ", ".join(missing)
            + "; give all three, or none to let jax.distributed.initialize detect the cluster"
        )
    if missing:
        return None, None, None
    # bool is an int subclass; True as a process count is surely a mistake.
    for name, value in (("num_processes", count), ("process_id", index)):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ValueError(f"{name} must be an int, got {value!r}")
    if count < 1:
        raise ValueError(f"num_processes must be >= 1, got {count}")
    if not 0 <= index < count:
        raise ValueError(f"process_id must be in [0, {count}), got {index}")
    if ":" not in coordinator:
        raise ValueError(f"coordinator_address must be 'host:port', got {coordinator!r}")
    return coordinator, count, index


def _env_int(name: str) -> int | None:
    """An integer environment variable (None when unset or empty)."""
    raw = os.environ.get(name, "").strip()
    if not raw:
        return None
    try:
        return int(raw)
    except ValueError:
        raise ValueError(f"environment variable {name} must be an integer, got {raw!r}") from None
