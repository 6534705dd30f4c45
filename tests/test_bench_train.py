"""``jaxtalk bench --train`` and :func:`jaxtalk.bench.run_train_benchmarks`: every model's real train
step timed from inside a recipe run, its FLOPs, fraction of peak, loader and host overhead; the JSON;
the model and preset selection; ``--profile`` traces."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from jaxtalk import bench
from jaxtalk.cli import app
from jaxtalk.train.observers import trace_files

runner = CliRunner()

# Small presets cut to one block each side, batch 2: compile time is what these tests spend.
TINY = {
    "toktalk": ("batch_size=2", "num_mid_blocks=1"),
    "ats": ("batch_size=2", "num_layers=1"),
    "stm": ("batch_size=2", "encoder_blocks=1", "decoder_blocks=1"),
    "timar": ("batch_size=2", "num_layers=1", "head_blocks=1", "decoder_layers=1"),
    "dualtalk": ("batch_size=2", "num_layers=1", "lstm_layers=1"),
}
FIELDS = ("model", "preset", "batch", "params_m", "step_s", "gflops", "gflop_s", "of_peak", "compile_s", "memory_gb",
          "loop_step_s", "host_s", "host_share", "loader_s", "loader_x", "rss_gb")


@pytest.mark.slow
def test_every_model_has_a_complete_training_row(prepared_tiny):
    from jaxtalk.benchmarking import measure_matmul_peak

    peak = measure_matmul_peak(n=1024, repeats=3) / 1e9
    lines: list[str] = []
    table = bench.run_train_benchmarks(bench.TRAIN_MODELS, ("small",), data=prepared_tiny, peak_gflop_s=peak,
                                       overrides=TINY, repeats=2, loop_steps=2, echo=lines.append)
    assert [r["model"] for r in table.rows] == list(bench.TRAIN_MODELS) and len(lines) == len(bench.TRAIN_MODELS)
    for row in table.rows:
        assert tuple(row) == FIELDS, row
        assert row["preset"] == "small" and row["batch"] == 2
        assert row["gflops"] > 0 and row["step_s"] > 0 and row["compile_s"] > 0 and row["params_m"] > 0
        assert row["gflop_s"] == pytest.approx(row["gflops"] / row["step_s"])
        assert 0 < row["of_peak"] < 1.5, row
        assert row["memory_gb"] > 0 and row["loop_step_s"] > 0 and row["loader_s"] > 0
        assert row["host_s"] == pytest.approx(row["loop_step_s"] - row["step_s"])


@pytest.mark.slow
def test_bench_train_cli_writes_the_json_traces_and_keeps_to_the_selection(prepared_tiny, tmp_path):
    out, traces = tmp_path / "bench.json", tmp_path / "trace"
    result = runner.invoke(app, [
        "bench", "--train", "--model", "ats", "--preset", "small", "--no-sampling", "--repeats", "1",
        "--loop-steps", "2", "--set", "batch_size=2", "--set", "num_layers=1", "--data", "synthtalk:tiny",
        "--cache-dir", str(prepared_tiny.root.parent), "--profile", str(traces), "--out", str(out)])
    assert result.exit_code == 0, result.output
    payload = json.loads(out.read_text())
    assert set(payload["recorded"]) == {"date_utc", "command"}
    assert payload["machine_info"]["cpu_model"] and payload["machine_info"]["cpu_cores"] >= 1
    assert payload["matmul_peak_gflop_s"] > 0
    (table,) = payload["tables"]  # --no-sampling: the training table alone
    (row,) = table["rows"]
    assert tuple(row) == FIELDS and row["model"] == "ats" and row["preset"] == "small"
    assert payload["train"] == {"data": "synthtalk:tiny", "presets": ["small"], "models": ["ats"],
                                "set": ["batch_size=2", "num_layers=1"], "paper_batch": None}
    files = trace_files(traces / "ats-small")
    assert any(p.name.endswith(".xplane.pb") for p in files), files
    # The README's tables come from this JSON, the machine named.
    text = _bench_readme().performance_section(payload)
    assert payload["machine_info"]["cpu_model"] in text and "| ats | small | 2 |" in text


def _bench_readme():
    return _experiment("bench_readme")


def _experiment(name: str):
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "experiments" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_bench_selection_maps_models_and_presets(monkeypatch, tmp_path):
    from jaxtalk import benchmarking

    calls: dict[str, object] = {}

    def fake_train(models, presets, **kw):
        calls["train"] = (list(models), list(presets), kw["overrides"], kw["paper_batch"])
        return bench.BenchTable("train", [{"model": m, "gflop_s": 1.0} for m in models])

    def fake_sample(models, *, paper, **kw):
        calls["sample"] = (list(models), paper)
        return 10.0, 5.0, [bench.BenchTable("sample", [{"model": m} for m in models])]

    monkeypatch.setattr(bench, "run_train_benchmarks", fake_train)
    monkeypatch.setattr(bench, "run_benchmarks", fake_sample)
    monkeypatch.setattr(benchmarking, "measure_matmul_peak", lambda *a, **k: 10e9)
    monkeypatch.setattr(benchmarking, "measure_memory_bandwidth", lambda *a, **k: 5e9)
    monkeypatch.setattr("jaxtalk.data.loader.open_data", lambda *a, **k: None)
    out = tmp_path / "b.json"
    result = runner.invoke(app, ["bench", "--train", "--model", "freetalk", "--model", "dualtalk", "--paper",
                                 "--set", "batch_size=4", "--paper-batch", "2", "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert calls["train"] == (["ats", "stm", "dualtalk"], ["small", "paper"],
                              {m: ("batch_size=4",) for m in ("ats", "stm", "dualtalk")}, 2)
    assert calls["sample"] == (["freetalk"], True)  # ATS's and STM's sampler rows; DualTalk has none
    titles = [t["title"] for t in json.loads(out.read_text())["tables"]]
    assert titles == ["train", "sample"]

    calls.clear()
    result = runner.invoke(app, ["bench", "--train", "--model", "timar", "--preset", "paper", "--no-sampling",
                                 "--out", str(out)])
    assert result.exit_code == 0, result.output
    assert calls == {"train": (["timar"], ["paper"], {"timar": ()}, None)}


def test_bench_rows_use_the_better_of_the_peaks_measured_at_start_and_end(monkeypatch, tmp_path):
    from jaxtalk import benchmarking

    peaks = iter([10e9, 40e9])  # a slow spell at the start
    bandwidths = iter([6e9, 3e9])  # and one at the end
    monkeypatch.setattr(benchmarking, "measure_matmul_peak", lambda *a, **k: next(peaks))
    monkeypatch.setattr(benchmarking, "measure_memory_bandwidth", lambda *a, **k: next(bandwidths))
    monkeypatch.setattr(bench, "run_train_benchmarks",
                        lambda models, presets, **kw: bench.BenchTable(
                            "train", bench.with_peak([{"gflop_s": 8.0}], kw["peak_gflop_s"])))
    monkeypatch.setattr("jaxtalk.data.loader.open_data", lambda *a, **k: None)
    out = tmp_path / "b.json"
    result = runner.invoke(app, ["bench", "--train", "--model", "ats", "--no-sampling", "--out", str(out)])
    assert result.exit_code == 0, result.output
    payload = json.loads(out.read_text())
    assert payload["matmul_peaks_gflop_s"] == [10.0, 40.0] and payload["matmul_peak_gflop_s"] == 40.0
    assert payload["memory_bandwidths_gb_s"] == [6.0, 3.0] and payload["memory_bandwidth_gb_s"] == 6.0
    assert payload["tables"][0]["rows"][0]["of_peak"] == 0.2


@pytest.mark.parametrize("args, message", [
    (["--train", "--model", "wavenet"], "unknown benchmark model(s) ['wavenet']"),
    (["--profile", "x"], "--profile traces the train steps: add --train"),
    (["--preset", "paper"], "--preset and --set choose what --train trains"),
    (["--train", "--preset", "huge"], "--preset huge: expected small or paper"),
])
def test_bench_train_user_errors(args, message, tmp_path):
    result = runner.invoke(app, ["bench", *args, "--out", str(tmp_path / "x.json")])
    assert result.exit_code == 2 and message in result.output, result.output


def test_train_step_rejects_an_unknown_model(prepared_tiny):
    with pytest.raises(ValueError, match="unknown training benchmark model"):
        bench.train_step("wavenet", "small", prepared_tiny)


def test_train_profile_writes_a_trace_of_the_chosen_steps(prepared_tiny, tmp_path):
    from jaxtalk.commands.training import PROFILE_DIR

    run = tmp_path / "run"
    result = runner.invoke(app, [
        "train", "ats", "--data", "synthtalk:tiny", "--cache-dir", str(prepared_tiny.root.parent), "--out", str(run),
        "--steps", "3", "--set", "batch_size=2", "--set", "num_layers=1", "--no-progress", "--profile", "2:3"])
    assert result.exit_code == 0, result.output
    files = trace_files(run / PROFILE_DIR)
    assert any(p.name.endswith(".xplane.pb") for p in files), files
    assert any(p.name.endswith(".trace.json.gz") for p in files), files


@pytest.mark.parametrize("text, message", [
    ("3", "START:STOP"), ("a:b", "two step numbers"), ("0:2", "1 <= START <= STOP"), ("5:4", "1 <= START <= STOP")])
def test_profile_range_is_checked(text, message, tmp_path):
    from jaxtalk.train.observers import parse_step_range

    assert parse_step_range("2:5") == (2, 5)
    with pytest.raises(ValueError, match=message):
        parse_step_range(text)
    result = runner.invoke(app, ["train", "ats", "--out", str(tmp_path / "r"), "--profile", text])
    assert result.exit_code == 2 and message in result.output


def test_profile_outside_the_run_is_refused(prepared_tiny, tmp_path):
    result = runner.invoke(app, [
        "train", "ats", "--data", "synthtalk:tiny", "--cache-dir", str(prepared_tiny.root.parent),
        "--out", str(tmp_path / "run"), "--steps", "3", "--profile", "2:9"])
    assert result.exit_code == 2 and "outside the steps this run trains (1..3)" in result.output


@pytest.mark.slow
def test_device_check_trains_for_a_time_budget_and_streams(prepared_tiny):
    from jaxtalk.models.toktalk import TokTalkConfig

    check = _experiment("device_check")
    record = check.timar_train(4.0, preset="small", data="synthtalk:tiny", cache_dir=str(prepared_tiny.root.parent),
                               overrides=TINY["timar"])
    assert record["steps"] >= 1 and record["seconds"] >= 4.0 and record["first_step_s"] > 0
    assert record["batch"] == 2 and record["params_m"] > 0
    stream = check.toktalk_stream(2, configs={"tiny": TokTalkConfig.tiny()})
    (row,) = stream["rows"]
    assert row["latency_s"] > 0 and 0 < row["of_peak"] < 1.5 and stream["matmul_peak_gflop_s"] > 0


def test_paper_rows_take_the_paper_batch_and_fewer_steps(monkeypatch):
    seen = []

    def fake_step(model, preset, data, **kw):
        seen.append((model, preset, kw["overrides"], kw["repeats"], kw["loop_steps"], kw["loop_warmup"]))
        return {"model": model, "preset": preset, "gflop_s": 5.0}

    monkeypatch.setattr(bench, "train_step", fake_step)
    table = bench.run_train_benchmarks(["timar"], ("small", "paper"), data=None, peak_gflop_s=10.0,
                                       overrides={"timar": ("lr=1e-4",)}, repeats=6, loop_steps=12, paper_batch=2,
                                       echo=lambda line: None)
    assert seen == [("timar", "small", ("lr=1e-4",), 6, 12, 2), ("timar", "paper", ("lr=1e-4", "batch_size=2"), 3, 4, 1)]
    assert [r["of_peak"] for r in table.rows] == [0.5, 0.5]
    with pytest.raises(ValueError, match="unknown training benchmark model"):
        bench.run_train_benchmarks(["wavenet"], data=None, peak_gflop_s=1.0)
