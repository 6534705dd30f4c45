"""PNG plots of sweeps and training curves (matplotlib's object API on the Agg canvas, never a GUI).

Figures are built with ``matplotlib.figure.Figure`` directly rather than ``pyplot``: no global
figure state, no backend selection, nothing that needs a display. Files are written atomically.

* ``plot_sweep``: heatmaps of a 2-D sweep, one panel per metric (e.g. chunk size x sampler steps ->
  lip vertex error and latency), cells annotated.
* ``plot_sweep_lines``: metric(s) against one swept value, one line per value of a grouping key.
* ``plot_training_curves``: loss (and other step metrics) against step from the training loop's
  history, with a moving average and the evaluation points.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from jaxtalk.files import atomic_output, check_output_path
from jaxtalk.types import Float

__all__ = ["pivot_sweep", "plot_sweep", "plot_sweep_lines", "plot_training_curves", "training_series"]


def _records(records: Sequence[Mapping[str, Any]], keys: Sequence[str]) -> list[Mapping[str, Any]]:
    recs = list(records)
    if not recs:
        raise ValueError("records is empty: nothing to plot")
    for i, r in enumerate(recs):
        missing = [k for k in keys if k not in r]
        if missing:
            raise ValueError(f"record {i} lacks {missing}; it has {sorted(r)}")
    return recs


def _sorted_unique(values: list[Any]) -> list[Any]:
    unique = list(dict.fromkeys(values))
    try:
        return sorted(unique)
    except TypeError:  # mixed types: keep first-seen order
        return unique


def pivot_sweep(
    records: Sequence[Mapping[str, Any]], *, row: str, col: str, value: str
) -> tuple[list[Any], list[Any], Float[np.ndarray, "rows cols"]]:
    """Arrange sweep records (one dict per run) into a grid ``value[row, col]``.

    Args:
        records: e.g. ``[{"chunk": 8, "steps": 4, "lve": 1.2, "latency_ms": 30.0}, ...]``.
        row: key whose sorted distinct values index the rows.
        col: key whose sorted distinct values index the columns.
        value: key of the number to place in the cells.

    Returns:
        ``(row_values, col_values, grid)`` with ``grid`` of shape ``(len(row_values), len(col_values))``;
        combinations missing from ``records`` are NaN.

    Raises:
        ValueError: for no records, a record lacking a key, two records for the same cell, or a
            non-numeric value.
    """
    recs = _records(records, (row, col, value))
    rows = _sorted_unique([r[row] for r in recs])
    cols = _sorted_unique([r[col] for r in recs])
    grid = np.full((len(rows), len(cols)), np.nan)
    seen: set[tuple[int, int]] = set()
    for r in recs:
        i, j = rows.index(r[row]), cols.index(r[col])
        if (i, j) in seen:
            raise ValueError(f"two records for {row}={r[row]!r}, {col}={r[col]!r}")
        seen.add((i, j))
        try:
            grid[i, j] = float(r[value])
        except (TypeError, ValueError):
            raise ValueError(f"{value}={r[value]!r} at {row}={r[row]!r}, {col}={r[col]!r} is not a number") from None
    return rows, cols, grid


def _figure(num_panels: int, panel_size: tuple[float, float]):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(panel_size[0] * num_panels, panel_size[1]), layout="constrained")
    axes = fig.subplots(1, num_panels, squeeze=False)[0]
    return fig, axes


def _save(fig, path: Path, dpi: int) -> Path:
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)
    return path


def plot_sweep(
    path: str | os.PathLike,
    records: Sequence[Mapping[str, Any]],
    *,
    row: str,
    col: str,
    metrics: Sequence[str],
    title: str | None = None,
    lower_is_better: bool | Sequence[bool] = True,
    dpi: int = 110,
) -> Path:
    """Heatmaps of a 2-D sweep, one panel per metric, each cell annotated with its value.

    Args:
        path: output PNG.
        records: one dict per run holding ``row``, ``col`` and every metric (see ``pivot_sweep``).
        row: swept key on the vertical axis (e.g. ``"chunk_frames"``).
        col: swept key on the horizontal axis (e.g. ``"sampler_steps"``).
        metrics: keys to plot (e.g. ``("lve", "latency_ms")``).
        title: figure title.
        lower_is_better: per metric (or one for all): the best cell is outlined in red, and the
            colour map runs from good (bright) to bad (dark).
        dpi: resolution.

    Returns:
        The written path.

    Raises:
        ValueError: for no metrics, a bad suffix, or bad records (see ``pivot_sweep``).
        FileNotFoundError, NotADirectoryError, PermissionError: if the directory cannot be written.
    """
    out = check_output_path(path, (".png",))
    metrics = list(metrics)
    if not metrics:
        raise ValueError("metrics is empty: nothing to plot")
    lower = [lower_is_better] * len(metrics) if isinstance(lower_is_better, bool) else list(lower_is_better)
    if len(lower) != len(metrics):
        raise ValueError(f"lower_is_better has {len(lower)} entries for {len(metrics)} metrics")
    grids = [pivot_sweep(records, row=row, col=col, value=m) for m in metrics]
    rows, cols = grids[0][0], grids[0][1]
    fig, axes = _figure(len(metrics), (0.9 * len(cols) + 2.2, 0.6 * len(rows) + 1.6))
    for ax, metric, (_, _, grid), low in zip(axes, metrics, grids, lower):
        finite = grid[np.isfinite(grid)]
        # Reversed map for lower-is-better, so the best cells are always the bright ones.
        image = ax.imshow(np.ma.masked_invalid(grid), cmap="viridis_r" if low else "viridis", aspect="auto")
        fig.colorbar(image, ax=ax, shrink=0.85)
        for i in range(len(rows)):
            for j in range(len(cols)):
                if np.isfinite(grid[i, j]):
                    r, g, b, _ = image.cmap(image.norm(grid[i, j]))
                    text_color = "black" if 0.299 * r + 0.587 * g + 0.114 * b > 0.5 else "white"
                    ax.text(j, i, f"{grid[i, j]:.3g}", ha="center", va="center", fontsize=8, color=text_color)
        if finite.size:
            best = np.unravel_index(np.nanargmin(grid) if low else np.nanargmax(grid), grid.shape)
            from matplotlib.patches import Rectangle

            ax.add_patch(Rectangle((best[1] - 0.5, best[0] - 0.5), 1, 1, fill=False, edgecolor="red", linewidth=2))
        ax.set_xticks(range(len(cols)), [str(c) for c in cols])
        ax.set_yticks(range(len(rows)), [str(r) for r in rows])
        ax.set_xlabel(col)
        ax.set_ylabel(row)
        ax.set_title(f"{metric} ({'lower' if low else 'higher'} is better)", fontsize=10)
    if title:
        fig.suptitle(title)
    return _save(fig, out, dpi)


def plot_sweep_lines(
    path: str | os.PathLike,
    records: Sequence[Mapping[str, Any]],
    *,
    x: str,
    metrics: Sequence[str],
    group: str | None = None,
    log_x: bool = False,
    title: str | None = None,
    dpi: int = 110,
) -> Path:
    """Line plots of metric(s) against one swept value, one line per value of ``group``.

    Args:
        path: output PNG.
        records: one dict per run holding ``x``, ``group`` (if given) and every metric.
        x: swept key on the horizontal axis (e.g. ``"cfg_scale"``).
        metrics: keys to plot, one panel each.
        group: optional key that splits the records into lines (e.g. ``"sampler"``).
        log_x: logarithmic horizontal axis.
        title: figure title.
        dpi: resolution.

    Returns:
        The written path.

    Raises:
        ValueError: for no metrics, a bad suffix, no records or records lacking a key.
        FileNotFoundError, NotADirectoryError, PermissionError: if the directory cannot be written.
    """
    out = check_output_path(path, (".png",))
    metrics = list(metrics)
    if not metrics:
        raise ValueError("metrics is empty: nothing to plot")
    recs = _records(records, [x, *metrics, *([group] if group else [])])
    groups = _sorted_unique([r[group] for r in recs]) if group else [None]
    fig, axes = _figure(len(metrics), (4.6, 3.4))
    for ax, metric in zip(axes, metrics):
        for g in groups:
            sel = [r for r in recs if group is None or r[group] == g]
            xs = np.array([float(r[x]) for r in sel])
            ys = np.array([float(r[metric]) for r in sel])
            order = np.argsort(xs, kind="stable")
            ax.plot(xs[order], ys[order], marker="o", label=None if g is None else f"{group}={g}")
        if log_x:
            ax.set_xscale("log")
        ax.set_xlabel(x)
        ax.set_ylabel(metric)
        ax.grid(alpha=0.3)
        if group:
            ax.legend(fontsize=8)
    if title:
        fig.suptitle(title)
    return _save(fig, out, dpi)


def training_series(history: Sequence[Mapping[str, Any]], metric: str, *, source: str = "train") -> tuple[np.ndarray, np.ndarray]:
    """Steps and values of one metric from the training loop's history.

    Args:
        history: ``TrainResult.history``: dicts with ``"step"`` and ``"loss"``/``"metrics"`` (training
            steps) and/or ``"eval"`` (evaluation steps).
        metric: ``"loss"`` or a key of ``"metrics"`` / ``"eval"``.
        source: ``"train"`` (``loss`` and ``metrics``) or ``"eval"`` (``eval``).

    Returns:
        ``(steps, values)`` as float arrays in history order (entries without the metric skipped).

    Raises:
        ValueError: for a ``source`` other than "train" or "eval".
    """
    if source not in ("train", "eval"):
        raise ValueError(f"source must be 'train' or 'eval', got {source!r}")
    steps, values = [], []
    for entry in history:
        if source == "eval":
            found = entry.get("eval", {}).get(metric)
        elif metric == "loss" and "loss" in entry:
            found = entry["loss"]
        else:
            found = entry.get("metrics", {}).get(metric)
        if found is not None and "step" in entry:
            steps.append(float(entry["step"]))
            values.append(float(found))
    return np.asarray(steps), np.asarray(values)


def _moving_average(values: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average; the first ``window - 1`` points average what is available."""
    csum = np.cumsum(np.concatenate([[0.0], values]))
    idx = np.arange(1, values.size + 1)
    lo = np.maximum(idx - window, 0)
    return (csum[idx] - csum[lo]) / (idx - lo)


def plot_training_curves(
    path: str | os.PathLike,
    history: Sequence[Mapping[str, Any]],
    *,
    metrics: Sequence[str] = ("loss",),
    smooth: int | None = None,
    log_y: bool | None = None,
    title: str | None = None,
    dpi: int = 110,
) -> Path:
    """Training curves: each metric against step (raw, faint; moving average, solid; eval, markers).

    Args:
        path: output PNG.
        history: the training loop's ``TrainResult.history`` (list of dicts with ``"step"``,
            ``"loss"``, ``"metrics"`` and, at evaluation steps, ``"eval"``).
        metrics: one panel per key: ``"loss"`` or keys of ``"metrics"`` (e.g. ``"grad_norm"``,
            ``"lr"``); an ``"eval"`` value of the same name is drawn on the same panel.
        smooth: moving-average window in steps (default: about 2% of the points, at least 1).
        log_y: logarithmic vertical axis (default: when every plotted value is positive and they
            span more than a factor of 20).
        title: figure title.
        dpi: resolution.

    Returns:
        The written path.

    Raises:
        ValueError: for an empty history, no metrics, a bad suffix, or a metric found nowhere in the
            history (the message lists the keys that are there).
        FileNotFoundError, NotADirectoryError, PermissionError: if the directory cannot be written.
    """
    out = check_output_path(path, (".png",))
    if not history:
        raise ValueError("history is empty: nothing to plot")
    metrics = list(metrics)
    if not metrics:
        raise ValueError("metrics is empty: nothing to plot")
    series = []
    for metric in metrics:
        train = training_series(history, metric)
        evals = training_series(history, metric, source="eval")
        if train[0].size == 0 and evals[0].size == 0:
            known = sorted(
                {"loss"} | {k for e in history for k in e.get("metrics", {})} | {k for e in history for k in e.get("eval", {})}
            )
            raise ValueError(f"metric {metric!r} is not in the history; it has {known}")
        series.append((metric, train, evals))
    fig, axes = _figure(len(metrics), (4.8, 3.4))
    for ax, (metric, (steps, values), (esteps, evalues)) in zip(axes, series):
        plotted = np.concatenate([values, evalues])
        plotted = plotted[np.isfinite(plotted)]
        if steps.size:
            window = smooth if smooth is not None else max(1, round(0.02 * steps.size))
            if window < 1:
                raise ValueError(f"smooth must be >= 1, got {smooth}")
            ax.plot(steps, values, color="C0", alpha=0.3, linewidth=0.8, label="train")
            if window > 1:
                ax.plot(steps, _moving_average(values, window), color="C0", linewidth=1.6, label=f"train (avg {window})")
        if esteps.size:
            ax.plot(esteps, evalues, color="C3", marker="o", linestyle="--", label="eval")
        use_log = log_y
        if use_log is None:
            use_log = bool(plotted.size and plotted.min() > 0 and plotted.max() / plotted.min() > 20)
        if use_log:
            ax.set_yscale("log")
        ax.set_xlabel("step")
        ax.set_ylabel(metric)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    if title:
        fig.suptitle(title)
    return _save(fig, out, dpi)
