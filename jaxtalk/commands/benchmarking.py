"""``jaxtalk bench``: the speed tables of the models in one run (sampling, and with ``train`` each model's
train step in a real recipe run), with the machine's measured matmul peak and memory bandwidth beside
every row, written as one JSON file."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

__all__ = ["BenchOptions", "run_bench"]


@dataclasses.dataclass(frozen=True)
class BenchOptions:
    """Settings of :func:`run_bench` (``jaxtalk bench --help`` says what each does).

    Attributes:
        models: sampling: ``toktalk``, ``timar``, ``freetalk``; with ``train`` also ``ats``, ``stm``,
            ``dualtalk`` (``freetalk`` = ``ats`` + ``stm``); empty: all.
        paper: also the paper-size presets.
        repeats: timed runs per case (the median is reported).
        train: also time each model's train step.
        presets: with ``train``: the presets to train (``small``, ``paper``); empty: ``small`` (and
            ``paper`` with ``paper``).
        sampling: with ``train``: also the sampling tables of the chosen models.
        data: with ``train``: the prepared data the models train on.
        cache_dir: where ``synthtalk:`` data is prepared.
        overrides: with ``train``: ``KEY=VALUE`` config fields or training settings for every model.
        loop_steps: with ``train``: loop steps timed for the host overhead.
        paper_batch: with ``train``: the batch of the paper rows (None: the recipe's).
        profile: with ``train``: write a ``jax.profiler`` trace of each row's timed steps under this folder.
        out: the JSON (None: ``experiments/results/bench_all.json``, replaced only with ``overwrite``).
        overwrite: let the default ``out`` replace an existing file.
    """

    models: tuple[str, ...] = ()
    paper: bool = False
    repeats: int = 5
    train: bool = False
    presets: tuple[str, ...] = ()
    sampling: bool = True
    data: str = "synthtalk:tiny"
    cache_dir: Path = Path(".cache/prepared")
    overrides: tuple[str, ...] = ()
    loop_steps: int = 10
    paper_batch: int | None = None
    profile: Path | None = None
    out: Path | None = None
    overwrite: bool = False


def _families(models: Sequence[str]) -> dict[str, tuple[str, ...]]:
    """``{family: its models}`` among ``models`` (:attr:`jaxtalk.runs.ModelSpec.family`: ``freetalk``: ATS and STM),
    the names that stand for several models on the command line."""
    from jaxtalk.runs import model_spec

    families: dict[str, tuple[str, ...]] = {}
    for model in models:
        family = model_spec(model).family
        if family is not None:
            families[family] = (*families.get(family, ()), model)
    return families


def run_bench(opts: BenchOptions, *, echo: Callable[[str], None] = print) -> list[Any]:
    """Run the benchmarks, print each table and write the JSON.

    Returns:
        The tables (:class:`jaxtalk.bench.BenchTable`), every row with the fraction of the peak.

    Raises:
        ValueError: an unknown model or preset, ``--preset`` / ``--set`` / ``--profile`` without
            ``--train``, or an output that would replace a file.
    """
    from jaxtalk.bench import (BENCH_MODELS, SAMPLER_OF, TRAIN_MODELS, BenchTable, run_benchmarks, run_train_benchmarks,
                               with_peak)
    from jaxtalk.benchmarking import format_table, machine_info, measure_matmul_peak, measure_memory_bandwidth, write_json
    from jaxtalk.files import Output, claim_outputs

    if opts.profile is not None and not opts.train:
        raise ValueError("--profile traces the train steps: add --train")
    names = list(opts.models)
    if opts.train:
        families = _families(TRAIN_MODELS)
        wanted = [m for n in names for m in families.get(n, (n,))] or list(TRAIN_MODELS)
        unknown = [m for m in wanted if m not in TRAIN_MODELS]
        if unknown:
            raise ValueError(f"unknown benchmark model(s) {unknown}; expected some of {', '.join((*TRAIN_MODELS, *families))}")
        train_models = list(dict.fromkeys(wanted))
        sample_models = list(dict.fromkeys(SAMPLER_OF[m] for m in train_models if m in SAMPLER_OF)) if opts.sampling else []
        presets = list(dict.fromkeys(opts.presets or (["small", "paper"] if opts.paper else ["small"])))
        bad = [p for p in presets if p not in ("small", "paper")]
        if bad:
            raise ValueError(f"--preset {bad[0]}: expected small or paper")
        paper = opts.paper or "paper" in presets
    else:
        paper = opts.paper
        if opts.presets or opts.overrides:
            raise ValueError("--preset and --set choose what --train trains: add --train")
        family_of = {m: family for family, members in _families(TRAIN_MODELS).items() for m in members}
        sample_models = list(dict.fromkeys(family_of.get(n, n) for n in names)) or list(BENCH_MODELS)
        train_models, presets = [], []
    (out,) = claim_outputs([Output(opts.out or Path("experiments/results/bench_all.json"), named=opts.out is not None)],
                           overwrite=opts.overwrite)
    if sample_models:
        peak, bandwidth, tables = run_benchmarks(tuple(sample_models), paper=paper, repeats=opts.repeats, echo=echo)
    else:
        echo("measuring the float32 matmul peak and the memory bandwidth")
        peak, bandwidth, tables = measure_matmul_peak() / 1e9, measure_memory_bandwidth() / 1e9, []
    if train_models:
        from jaxtalk.data.loader import open_data

        prepared = open_data(opts.data, cache_dir=opts.cache_dir, progress=False)
        overrides = {m: opts.overrides for m in train_models}
        tables.insert(0, run_train_benchmarks(train_models, presets, data=prepared, peak_gflop_s=peak,
                                              overrides=overrides, repeats=opts.repeats, loop_steps=opts.loop_steps,
                                              paper_batch=opts.paper_batch, profile_dir=opts.profile, echo=echo))
    # The peak again at the end, and the better of the two for every row: on a shared machine one
    # measurement can land in a slow spell, which would put rows above 1.0 of "peak"
    # (docs/design-decisions.md).
    echo("measuring the float32 matmul peak and the memory bandwidth again")
    peaks = [peak, measure_matmul_peak() / 1e9]
    bandwidths = [bandwidth, measure_memory_bandwidth() / 1e9]
    peak, bandwidth = max(peaks), max(bandwidths)
    tables = [BenchTable(t.title, with_peak(t.rows, peak, bandwidth)) for t in tables]
    info = machine_info()
    echo(f"machine: {info['cpu_model']} ({info['cpu_cores']} cores, {info['backend']}, {info['device_kind']}), "
               f"load {info['load_avg_1m']}; float32 matmul peak {peak:.1f} GFLOP/s (start {peaks[0]:.1f}, end {peaks[1]:.1f}), "
               f"memory bandwidth {bandwidth:.1f} GB/s (start {bandwidths[0]:.1f}, end {bandwidths[1]:.1f})")
    for table in tables:
        echo(format_table(table.rows, title=table.title))
    payload: dict[str, Any] = {"matmul_peak_gflop_s": peak, "matmul_peaks_gflop_s": peaks,
                               "memory_bandwidth_gb_s": bandwidth, "memory_bandwidths_gb_s": bandwidths,
                               "tables": [{"title": t.title, "rows": t.rows} for t in tables]}
    if train_models:
        payload["train"] = {"data": opts.data, "presets": presets, "models": train_models, "set": list(opts.overrides),
                            "paper_batch": opts.paper_batch}
    write_json(out, payload)
    echo(f"written to {out}")
    return tables


