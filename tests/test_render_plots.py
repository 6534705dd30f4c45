"""Plots: sweep pivoting by hand, PNGs written with content, training-history parsing, errors."""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np
import pytest

from jaxtalk.render import pivot_sweep, plot_sweep, plot_sweep_lines, plot_training_curves, training_series
from jaxtalk.render.plots import _moving_average

RECORDS = [
    {"chunk": c, "steps": s, "lve": c / s, "latency_ms": 1.5 * c * s}
    for c in (16, 4, 8)
    for s in (8, 1, 2)
    if (c, s) != (8, 2)
]


def _history(num: int = 60):
    rng = np.random.default_rng(0)
    hist = [
        {"step": i, "loss": float(np.exp(-i / 15) + 0.01 * rng.random()), "metrics": {"grad_norm": 1.0 / i, "lr": 1e-3}}
        for i in range(1, num + 1)
    ]
    hist[19]["eval"] = {"loss": 0.5}
    hist.append({"step": num, "eval": {"loss": 0.2}, "time": 1.0})  # eval-only entry, as the loop writes
    return hist


def _check_png(path, min_size=(120, 120)):
    image = iio.imread(path)
    assert image.ndim == 3 and image.shape[0] >= min_size[1] and image.shape[1] >= min_size[0]
    # Not blank: many distinct colours (axes, text, data).
    assert len(np.unique(image.reshape(-1, image.shape[-1]), axis=0)) > 50
    return image


def test_pivot_sweep_by_hand():
    rows, cols, grid = pivot_sweep(RECORDS, row="chunk", col="steps", value="lve")
    assert rows == [4, 8, 16] and cols == [1, 2, 8]
    want = np.array([[4.0, 2.0, 0.5], [8.0, np.nan, 1.0], [16.0, 8.0, 2.0]])
    np.testing.assert_array_equal(grid, want)


def test_pivot_sweep_errors():
    with pytest.raises(ValueError, match="two records"):
        pivot_sweep(RECORDS + RECORDS[:1], row="chunk", col="steps", value="lve")
    with pytest.raises(ValueError, match="lacks"):
        pivot_sweep(RECORDS, row="chunk", col="cfg", value="lve")
    with pytest.raises(ValueError, match="not a number"):
        pivot_sweep([{"a": 1, "b": 1, "v": "x"}], row="a", col="b", value="v")
    with pytest.raises(ValueError, match="empty"):
        pivot_sweep([], row="a", col="b", value="v")


def test_sweep_plots_write_pngs(tmp_path):
    out = plot_sweep(tmp_path / "sweep.png", RECORDS, row="chunk", col="steps", metrics=["lve", "latency_ms"], title="t", dpi=60)
    wide = _check_png(out)
    single = _check_png(plot_sweep(tmp_path / "one.png", RECORDS, row="chunk", col="steps", metrics=["lve"], dpi=60))
    assert wide.shape[1] > 1.6 * single.shape[1]  # one panel per metric
    _check_png(plot_sweep_lines(tmp_path / "lines.png", RECORDS, x="steps", metrics=["lve"], group="chunk", log_x=True, dpi=60))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lines.png", "one.png", "sweep.png"]


def test_training_series_reads_the_loop_history():
    hist = _history()
    steps, loss = training_series(hist, "loss")
    assert steps.tolist() == list(range(1, 61)) and loss[0] == hist[0]["loss"]
    steps, gn = training_series(hist, "grad_norm")
    np.testing.assert_allclose(gn, 1.0 / steps)
    esteps, evals = training_series(hist, "loss", source="eval")
    assert esteps.tolist() == [20.0, 60.0] and evals.tolist() == [0.5, 0.2]
    with pytest.raises(ValueError, match="source"):
        training_series(hist, "loss", source="test")


def test_moving_average_by_hand():
    np.testing.assert_allclose(_moving_average(np.array([1.0, 3.0, 5.0, 7.0]), 2), [1.0, 2.0, 4.0, 6.0])
    np.testing.assert_allclose(_moving_average(np.array([2.0, 4.0]), 1), [2.0, 4.0])


def test_training_curves_png_and_errors(tmp_path):
    _check_png(plot_training_curves(tmp_path / "curves.png", _history(), metrics=["loss", "grad_norm", "lr"], dpi=60))
    with pytest.raises(ValueError, match="'nope' is not in the history; it has .*grad_norm"):
        plot_training_curves(tmp_path / "x.png", _history(), metrics=["nope"])
    with pytest.raises(ValueError, match="history is empty"):
        plot_training_curves(tmp_path / "x.png", [])
    with pytest.raises(ValueError, match=r"\.png"):
        plot_training_curves(tmp_path / "x.jpg", _history())
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="is a file, not a folder"):
        plot_sweep(tmp_path / "file" / "x.png", RECORDS, row="chunk", col="steps", metrics=["lve"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["curves.png", "file"]
