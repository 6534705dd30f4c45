"""The accelerator checks behind ``experiments/device_check.sh``, on whatever device JAX finds.

    python experiments/device_check.py timar-train --seconds 120 --out experiments/results/device_check/timar.json
    python experiments/device_check.py toktalk-stream --out experiments/results/device_check/toktalk.json

* ``timar-train``: TIMAR's recipe (``paper`` preset by default) trained for a wall-clock budget on
  prepared data: steps done, the first step (compile included), steps/s after it, the loss curve.
* ``toktalk-stream``: TokTalk ``paper`` streaming chunks through the real ``stream_step``: the
  0.4-s chunk with a 10-frame window (TokTalk's published setting: 10 Euler steps + CFG; the paper
  reports 101 ms per chunk on an L40S) and with a 50-frame window, latency and fraction of peak.

Each writes JSON with the machine (device kind included), date and command.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from jaxtalk.train.observers import StepObserver


class _BudgetSpent(Exception):
    pass


class TimeBudget(StepObserver):
    """Stops a training run after ``seconds`` of wall time from its first step, timing it on the way.

    Attributes:
        record: ``first_step_s`` (compile included), ``steps``, ``steps_per_s`` after the first step,
            ``losses`` (one per ``every`` steps).
    """

    def __init__(self, seconds: float, every: int = 10) -> None:
        self.seconds, self.every = seconds, every
        self.record: dict[str, Any] = {"losses": []}
        self._t0 = self._t1 = 0.0

    def before_step(self, step: int, state: Any, batch: Any, step_fn: Any) -> None:
        if step == 1:
            self._t0 = time.perf_counter()

    def after_step(self, step: int, state: Any, metrics: Any) -> None:
        import jax

        if step == 1:
            jax.block_until_ready(state)
            self._t1 = time.perf_counter()
            self.record["first_step_s"] = self._t1 - self._t0
        if step % self.every == 0:
            self.record["losses"].append((step, float(metrics["loss"])))  # a sync every `every` steps
        if time.perf_counter() - self._t0 >= self.seconds:
            jax.block_until_ready(state)
            elapsed = time.perf_counter() - self._t1
            self.record.update(steps=step, seconds=time.perf_counter() - self._t0,
                               steps_per_s=(step - 1) / elapsed if step > 1 and elapsed > 0 else None)
            raise _BudgetSpent


def timar_train(seconds: float, *, preset: str = "paper", data: str = "synthtalk:tiny",
                cache_dir: str = ".cache/prepared", overrides: tuple[str, ...] = ()) -> dict[str, Any]:
    """TIMAR's recipe trained for ``seconds`` (see the module docstring).

    Returns:
        ``{"model", "preset", "batch", "params_m", "first_step_s", "steps", "seconds", "steps_per_s",
        "losses"}``.
    """
    import jax
    import numpy as np

    from jaxtalk.bench import recipe_setup
    from jaxtalk.data.loader import open_data
    from jaxtalk.models.timar import init_params
    from jaxtalk.runs import RunSettings
    from jaxtalk.train import LoopSettings

    prepared = open_data(data, cache_dir=cache_dir, progress=False)
    train_fn, config, settings = recipe_setup("timar", preset, prepared, overrides)
    budget = TimeBudget(seconds)
    steps = 1_000_000  # the budget ends the run
    try:
        result = train_fn(config, prepared, settings.optim(steps), key=jax.random.key(0),
                          run=RunSettings(steps=steps, batch_size=settings.batch_size, loop=LoopSettings(progress=False),
                                          observers=[budget]))
        raise RuntimeError(f"the run ended at step {int(result.state.step)} before the time budget")
    except _BudgetSpent:
        pass
    shapes = jax.eval_shape(lambda k: init_params(config, k), jax.random.key(0))
    params_m = sum(int(np.prod(s.shape)) for s in jax.tree.leaves(shapes)) / 1e6
    return {"model": "timar", "preset": preset, "batch": settings.batch_size, "params_m": params_m,
            "set": list(overrides), **budget.record}


def toktalk_stream(repeats: int = 20, configs: dict[str, Any] | None = None) -> dict[str, Any]:
    """TokTalk ``paper`` streaming chunks (see the module docstring).

    Args:
        repeats: timed chunks per case (median).
        configs: ``{case name: TokTalkConfig}`` instead of the two paper cases (for a quick test).

    Returns:
        ``{"matmul_peak_gflop_s", "memory_bandwidth_gb_s", "rows"}``; rows as
        :func:`jaxtalk.bench.toktalk_chunk` plus ``of_peak``, ``of_bandwidth`` and ``of_roofline``.
    """
    from jaxtalk.bench import toktalk_chunk, with_peak
    from jaxtalk.benchmarking import measure_matmul_peak, measure_memory_bandwidth
    from jaxtalk.models.toktalk import TokTalkConfig

    configs = configs or {"paper, 10-frame window": TokTalkConfig.paper(context_frames=0, overlap_frames=0),
                          "paper, 50-frame window": TokTalkConfig.paper(context_frames=40)}
    peak, bandwidth = measure_matmul_peak() / 1e9, measure_memory_bandwidth() / 1e9
    rows = [toktalk_chunk(config, name, repeats) for name, config in configs.items()]
    return {"matmul_peak_gflop_s": peak, "memory_bandwidth_gb_s": bandwidth, "rows": with_peak(rows, peak, bandwidth)}


def main() -> None:
    from jaxtalk.benchmarking import write_json

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="check", required=True)
    train = sub.add_parser("timar-train", help="TIMAR trained for a wall-clock budget")
    train.add_argument("--seconds", type=float, default=120.0)
    train.add_argument("--preset", default="paper")
    train.add_argument("--data", default="synthtalk:tiny")
    train.add_argument("--cache-dir", default=".cache/prepared")
    train.add_argument("--set", dest="overrides", action="append", default=[], help="KEY=VALUE (repeatable)")
    train.add_argument("--out", type=Path, required=True)
    stream = sub.add_parser("toktalk-stream", help="TokTalk paper streaming chunks")
    stream.add_argument("--repeats", type=int, default=20)
    stream.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    if args.check == "timar-train":
        payload = timar_train(args.seconds, preset=args.preset, data=args.data, cache_dir=args.cache_dir,
                              overrides=tuple(args.overrides))
    else:
        payload = toktalk_stream(args.repeats)
    print(payload)
    print(f"written to {write_json(args.out, payload)}")


if __name__ == "__main__":
    main()
