"""Data pipeline speed and memory: ``jaxtalk prepare`` throughput, the grain loader's windows/s per
model recipe beside that model's training step rate, and resident memory while streaming >= 2 GB.

1. Prepare: SynthTalk (``--size``, default small) is generated and exported to the generic layout in
   a temporary folder (not timed: that is the "user's data"), then ``prepare`` runs on that folder
   (timed: reading wav/npz, checks, features, landmarks, record encoding, ArrayRecord writes). Rows:
   log-mel on the whole corpus; on a subset of the monologue clips (``--hubert-minutes`` of audio,
   each row run cold, i.e. including the encoder's XLA compiles, then warm on a disjoint subset of the
   same length): log-mel again, HuBERT-base from ``--hubert PATH`` (a local Hugging Face folder,
   read with the optional ``safetensors``; "n/a" without one), and the HuBERT-base ARCHITECTURE with
   random weights (Flax init of ``EncoderConfig.base("hubert")``: 12 layers x 768, handed to
   ``prepare``'s own ``hubert:PATH`` path by redirecting ``SpeechEncoder.from_pretrained`` of a
   placeholder folder) -- its cost does not depend on the weights. Throughput is hours of audio per
   minute of wall time (audio = the clips' motion frames / 25 fps).
2. Loader vs step: for each recipe (TokTalk, TIMAR, ATS, STM; the ``small`` presets, widths from the
   data, windows as their ``train`` builds them) ``make_loader(..., batch_size)`` windows/s (after the
   first batch) and the jitted train step's rate on this CPU (``make_train_step`` of the recipe's
   loss and init, median of timed steps after compile) measured in the same run; needed windows/s =
   steps/s x batch, and the ratio loader / needed (the target is >= 5). ``nocache_win_s``: the
   same loader with ``cache_bytes=0`` (every window reads its records again: the loader before its
   cache, and what a dataset much larger than the cache gets). ``batch_sha1`` hashes the first
   batches (``same_batches``: equal with and without the cache), so a loader change can be checked
   to give bitwise identical windows.
3. Streaming memory: the prepared corpus's shards are replicated (renamed clips and speakers, every
   clip in the train split) into >= ``--stream-gb`` GB under a temporary folder; per recipe
   (``--stream-models``: TokTalk, which reads two clips per window, and ATS, whose decoded arrays
   outgrow the loader's cache) a fresh process iterates its loader over one full epoch (every record
   read, most many times), reporting resident memory (RSS, and the peak: VmHWM) at the start
   and after 25/50/75/100 % of it. The loader keeps at most ``jaxtalk.data.loader.CACHE_BYTES`` of
   decoded records, so RSS may rise by up to that much and then stays flat. The folder is deleted
   afterwards.

Timings are wall clock on a shared machine: every row carries the 1-minute load average.

Run: ``python experiments/bench_data.py [--quick] [--hubert PATH] [--out experiments/results/bench_data.json]``
(``--quick``: SynthTalk tiny, a 0.5-GB stream, fewer steps; a smoke run, not the target's numbers).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import hashlib
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from jaxtalk.benchmarking import machine_info, print_table, write_json

BATCH = 16
FPS = 25.0


def _load() -> float:
    return round(os.getloadavg()[0], 2)


def _audio_hours(data: Any) -> float:
    return sum(c["frames"] for c in data.clips) / FPS / 3600.0


# -- 1. prepare throughput ----------------------------------------------------------------------------


def _subset(src: Any, seconds_of: dict[str, float], seconds: float, skip: float = 0.0) -> Any:
    """Monologue entries (no partner needed) after ``skip`` seconds of them, ``seconds`` of audio."""
    picked, total, passed = [], 0.0, 0.0
    for e in src.entries:
        if e.requires_partner or e.partner is not None or e.name not in seconds_of:
            continue
        if passed < skip:
            passed += seconds_of[e.name]
            continue
        picked.append(e)
        total += seconds_of[e.name]
        if total >= seconds:
            break
    return dataclasses.replace(src, entries=tuple(picked))


@contextlib.contextmanager
def _random_hubert_base(folder: Path) -> Iterator[Path]:
    """``folder`` as a HuBERT-base checkpoint with random weights, while the context lasts.

    The weights are the Flax init of ``EncoderConfig.base("hubert")`` (12 layers x 768). They are not
    written to disk (that needs the optional ``safetensors``): ``SpeechEncoder.from_pretrained`` of
    this (empty) folder returns them, and everything else runs ``prepare``'s real ``hubert:PATH`` path.
    """
    import jax
    import jax.numpy as jnp

    from jaxtalk.audio.encoders import EncoderConfig, SpeechEncoder, Wav2Vec2Model

    config = EncoderConfig.base("hubert")
    assert (config.num_hidden_layers, config.hidden_size) == (12, 768)
    init = jax.jit(Wav2Vec2Model(config).init)  # eager Flax init would compile op by op
    params = init(jax.random.key(0), jnp.zeros((1, config.receptive_field)))["params"]
    encoder = SpeechEncoder(config, params, normalize=False)  # hubert-base-ls960 does not normalise
    folder.mkdir(parents=True, exist_ok=True)
    original = SpeechEncoder.__dict__["from_pretrained"]

    def from_pretrained(cls: Any, path: Any, **kwargs: Any) -> Any:
        if Path(path).resolve() == folder.resolve():
            return encoder
        return original.__func__(cls, path, **kwargs)

    SpeechEncoder.from_pretrained = classmethod(from_pretrained)
    try:
        yield folder
    finally:
        SpeechEncoder.from_pretrained = original


def _prepare_row(label: str, source: Any, out: Path, audio: str, note: str = "") -> tuple[dict, Any]:
    from jaxtalk.data.loader import PreparedData
    from jaxtalk.data.prepare import PrepareSettings, prepare

    load0 = _load()
    t0 = time.perf_counter()
    result = prepare(source, out, PrepareSettings(audio=audio), progress=False, echo=lambda s: None)
    wall = time.perf_counter() - t0
    data = PreparedData(out)
    hours = _audio_hours(data)
    size = sum((out / "shards" / s).stat().st_size for s in data.manifest["shards"])
    return {"features": label, "clips": result.clips, "audio_min": hours * 60, "wall_s": wall,
            "clips_per_s": result.clips / wall, "audio_h_per_min": hours / (wall / 60),
            "record_MB": size / 1e6, "load_1m": f"{load0}->{_load()}", "note": note}, data


def prepare_throughput(size: str, work: Path, hubert: str | None, minutes: float) -> tuple[list[dict], Path]:
    from jaxtalk.data import synthtalk
    from jaxtalk.data.sources import export_generic, open_source

    t0 = time.perf_counter()
    corpus = synthtalk.generate(size, seed=0, cache_dir=work / "synthtalk-cache")
    folder = export_generic(corpus, work / f"synthtalk-{size}")
    print(f"[prepare] SynthTalk {size} generated + exported in {time.perf_counter() - t0:.0f} s "
          f"(not timed) -> {folder}", flush=True)
    src = open_source(folder)
    rows = []
    row, full = _prepare_row("log-mel", src, work / "prep-logmel", "logmel", f"all of SynthTalk {size}")
    seconds_of = {c["name"]: c["frames"] / FPS for c in full.clips}
    rows.append(row)
    print(f"[prepare] log-mel: {row['audio_h_per_min']:.3g} audio-h/min (load {row['load_1m']})", flush=True)
    with _random_hubert_base(work / "hubert-base-random") as ckpt:
        kinds = [("log-mel", "logmel"),
                 ("HuBERT-base (local checkpoint)", f"hubert:{hubert}" if hubert else None),
                 ("HuBERT-base architecture, random weights", f"hubert:{ckpt}")]
        for label, audio in kinds:
            for phase, skip in (("cold", 0.0), ("warm", minutes * 60)):
                if audio is None:
                    rows.append({"features": label, "note": f"n/a: no local checkpoint (--hubert PATH), {phase}"})
                    continue
                sub = _subset(src, seconds_of, minutes * 60, skip)
                tag = label.split()[0].lower().replace("-", "") + ("-rand" if "random" in label else "")
                row, _ = _prepare_row(label, sub, work / f"prep-{tag}-{phase}", audio,
                                      f"{len(sub.entries)} monologue clips, {phase}"
                                      + (" (incl. XLA compiles)" if phase == "cold" else ""))
                rows.append(row)
                print(f"[prepare] {label} {phase}: {row['audio_h_per_min']:.3g} audio-h/min (load {row['load_1m']})",
                      flush=True)
    return rows, work / "prep-logmel"


# -- 2. loader vs train step --------------------------------------------------------------------------


def model_setups(data: Any) -> list[dict]:
    """Per model: config (small preset, widths from the data), recipe, params, loss, trainable."""
    import jax

    from jaxtalk.runs import build_config

    m = data.manifest
    out = []

    from jaxtalk.models.toktalk.loss import make_loss_fn as tok_loss_fn
    from jaxtalk.models.toktalk.model import init_params as tok_init
    from jaxtalk.models.toktalk.recipe import TokTalkWindows, default_window
    from jaxtalk.models.toktalk.recipe import base_trainable

    config = build_config("toktalk", "small", [f"speech_dim={m['token_dim']}", f"token_rate={m['token_rate']:g}"])
    window = default_window(config)
    params = tok_init(config, jax.random.key(0))
    # As the recipe's train sets it, except the fitted flow scale (values do not change the cost).
    params["norm"] = {**params["norm"], **{k: np.asarray(v) for k, v in data.motion_stats().items()}}

    out.append({"model": "toktalk", "recipe": TokTalkWindows(config, window, hop_frames=window // 4, seed=0),
                "params": params, "loss": tok_loss_fn(config), "trainable": base_trainable})

    from jaxtalk.models.timar.loss import make_loss_fn
    from jaxtalk.models.timar.model import init_params as timar_init
    from jaxtalk.models.timar.recipe import make_windows

    config = build_config("timar", "small", [f"speech_dim={m['turn_speech_dim']}"])
    out.append({"model": "timar", "recipe": make_windows(config, data), "params": timar_init(config, jax.random.key(0)),
                "loss": make_loss_fn(config), "trainable": None})

    from jaxtalk.models.freetalk import ats, stm
    from jaxtalk.models.freetalk.data import face_mesh
    from jaxtalk.models.freetalk.recipe import STM_MESHES, ATSWindows, STMWindows, fit_displacement_stats

    config = build_config("ats", "small", [f"speech_dim={m['speech_dim']}"])
    out.append({"model": "ats", "recipe": ATSWindows(min(config.max_frames, 50), fit_displacement_stats(data)),
                "params": ats.init_params(config, jax.random.key(0)), "loss": ats.make_loss_fn(config), "trainable": None})

    config = build_config("stm", "small")
    faces = tuple(face_mesh(i, kind, resolution="low") for i, kind in STM_MESHES)
    prepared = stm.prepare_meshes([(f.vertices, f.faces) for f in faces], config)
    out.append({"model": "stm", "recipe": STMWindows(faces, max(p.num_vertices for p in prepared)),
                "params": stm.init_params(config, jax.random.key(0), prepared[0]),
                "loss": stm.make_loss_fn(config, stm.stack_meshes(prepared)), "trainable": None})
    return out


def batch_digest(batches: list[dict[str, np.ndarray]]) -> str:
    h = hashlib.sha1()
    for b in batches:
        for k in sorted(b):
            a = np.ascontiguousarray(b[k])
            h.update(f"{k}{a.dtype}{a.shape}".encode())
            h.update(a.tobytes())
    return h.hexdigest()[:12]


def loader_rate(data: Any, recipe: Any, seconds: float, check_batches: int = 4, **kwargs: Any) -> dict:
    from jaxtalk.data.loader import make_loader

    load0 = _load()
    t0 = time.perf_counter()
    loader = make_loader(data, recipe, "train", BATCH, seed=0, shard=(0, 1), **kwargs)
    first = [next(loader) for _ in range(check_batches)]  # also warms readers and caches
    start_s = time.perf_counter() - t0
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        next(loader)
        n += 1
    wall = time.perf_counter() - t0
    return {"windows": loader.num_windows, "loader_win_s": n * BATCH / wall, "first_batches_s": start_s,
            "loader_load": f"{load0}->{_load()}", "batch_sha1": batch_digest(first), "_batch": first[0]}


def step_rate(setup: dict, batch: dict, repeats: int) -> dict:
    import jax

    from jaxtalk.train import create_train_state, make_optimizer, make_train_step, trainable_mask
    from jaxtalk.train.recipes import TrainSettings

    optim = TrainSettings().optim(1000)
    mask = trainable_mask(setup["params"], setup["trainable"])
    tx = make_optimizer(optim, mask)
    step = make_train_step(setup["loss"], tx, optim, mask=mask)
    state = create_train_state(setup["params"], tx, jax.random.key(1), ema=optim.ema_decay is not None)
    load0 = _load()
    t0 = time.perf_counter()
    state, metrics = step(state, batch)
    jax.block_until_ready(metrics)
    compile_s = time.perf_counter() - t0
    times: list[float] = []
    # One untimed step after the compile, then ``repeats`` (at least 3; fewer once 60 s are spent).
    while len(times) < repeats + 1 and (len(times) < 4 or sum(times[1:]) < 60):
        t0 = time.perf_counter()
        state, metrics = step(state, batch)  # a NumPy batch each step, as the training loop passes
        jax.block_until_ready(metrics)
        times.append(time.perf_counter() - t0)
    med = statistics.median(times[1:])
    return {"step_ms": med * 1e3, "timed_steps": len(times) - 1, "steps_per_s": 1 / med, "needed_win_s": BATCH / med,
            "compile_s": compile_s, "step_load": f"{load0}->{_load()}"}


def loader_vs_step(data: Any, seconds: float, repeats: int) -> list[dict]:
    rows = []
    for setup in model_setups(data):
        windows = len(setup["recipe"].table(data, "train"))
        if windows < BATCH:
            rows.append({"model": setup["model"], "recipe": type(setup["recipe"]).__name__, "windows": windows,
                         "note": f"n/a: fewer windows than one batch of {BATCH} (use a larger --size)"})
            continue
        lr = loader_rate(data, setup["recipe"], seconds)
        batch = lr.pop("_batch")
        # The same loader without its cache of decoded records: every window reads its records again
        # (what a dataset much larger than the cache gets; also the loader before the cache).
        raw = loader_rate(data, setup["recipe"], seconds, cache_bytes=0)
        raw.pop("_batch")
        sr = step_rate(setup, batch, repeats)
        row = {"model": setup["model"], "recipe": type(setup["recipe"]).__name__, **lr,
               "nocache_win_s": raw["loader_win_s"], "same_batches": raw["batch_sha1"] == lr["batch_sha1"], **sr}
        row["ratio"] = row["loader_win_s"] / row["needed_win_s"]
        row["ratio_nocache"] = row["nocache_win_s"] / row["needed_win_s"]
        row["ok_5x"] = row["ratio"] >= 5
        row["bench_peak_rss_MB"] = _peak_rss_mb()  # this whole process so far (the steps' XLA buffers)
        rows.append(row)
        print(f"[loader] {row['model']}: loader {row['loader_win_s']:.0f} win/s ({row['nocache_win_s']:.0f} without "
              f"cache), step {row['steps_per_s']:.3g}/s -> ratio {row['ratio']:.1f} (load {row['loader_load']} / "
              f"{row['step_load']})", flush=True)
    return rows


# -- 3. streaming memory ------------------------------------------------------------------------------


def build_stream_dataset(src: Path, out: Path, target_bytes: float) -> tuple[int, int]:
    """Replicate ``src``'s shards into ``out`` until the records reach ``target_bytes``.

    Copy ``r`` renames every clip ``<name>-r<r>`` (partners too) and speaker ``<spk>-r<r>`` and puts
    every clip in the train split, so one epoch reads every record. Returns (bytes, clips).
    """
    manifest = json.loads((src / "manifest.json").read_text())
    per_copy = sum((src / "shards" / s).stat().st_size for s in manifest["shards"])
    copies = int(np.ceil(target_bytes / per_copy))
    (out / "shards").mkdir(parents=True, exist_ok=True)
    clips, shards = [], []
    for r in range(copies):
        for s in manifest["shards"]:
            name = f"r{r:03d}-{s}"
            shutil.copyfile(src / "shards" / s, out / "shards" / name)
            shards.append(name)
        for c in manifest["clips"]:
            clips.append({**c, "name": f"{c['name']}-r{r}", "speaker": f"{c['speaker']}-r{r}", "split": "train",
                          "partner": f"{c['partner']}-r{r}" if c["partner"] else None, "shard": f"r{r:03d}-{c['shard']}"})
    stream = {**manifest, "shards": shards, "clips": clips,
              "splits": {s: ([c["name"] for c in clips] if s == "train" else []) for s in manifest["splits"]}}
    (out / "manifest.json").write_text(json.dumps(stream))
    for extra in ("tokenizer.npz",):
        if (src / extra).is_file():
            shutil.copyfile(src / extra, out / extra)
    return per_copy * copies, len(clips)


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


def _peak_rss_mb() -> float:
    """This process's peak RSS: VmHWM (ru_maxrss would carry over the parent's peak across exec)."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024 / 1e6
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e6


def _stream_recipe(data: Any, model: str, stats_file: str) -> Any:
    from jaxtalk.runs import build_config

    if model == "toktalk":
        from jaxtalk.models.toktalk.recipe import TokTalkWindows, default_window

        m = data.manifest
        config = build_config("toktalk", "small", [f"speech_dim={m['token_dim']}", f"token_rate={m['token_rate']:g}"])
        window = default_window(config)
        return TokTalkWindows(config, window, hop_frames=window // 4, seed=0)
    from jaxtalk.models.freetalk.data import DisplacementStats
    from jaxtalk.models.freetalk.recipe import ATSWindows

    # Statistics of the source corpus (fitting them here would load every landmark of the stream).
    stats = json.loads(Path(stats_file).read_text())
    return ATSWindows(50, DisplacementStats(np.asarray(stats["mean"], np.float32), np.asarray(stats["std"], np.float32)))


def stream_child(path: str, model: str, stats_file: str) -> None:
    """(Run in a fresh process.) One epoch of ``model``'s loader over ``path``; RSS as JSON lines."""
    from jaxtalk.data.loader import CACHE_BYTES, PreparedData, make_loader

    t0 = time.perf_counter()

    def report(stage: str, done: int, total: int) -> None:
        print(json.dumps({"model": model, "stage": stage, "windows": done, "of": total, "rss_MB": _rss_mb(),
                          "peak_rss_MB": _peak_rss_mb(), "elapsed_s": time.perf_counter() - t0, "load_1m": _load(),
                          "cache_MB": CACHE_BYTES / 1e6}), flush=True)

    data = PreparedData(path)
    recipe = _stream_recipe(data, model, stats_file)
    loader = make_loader(data, recipe, "train", BATCH, seed=0, num_epochs=1, shard=(0, 1))
    total = loader.num_windows // BATCH
    marks = {max(1, int(round(total * q))): f"{int(q * 100)}%" for q in (0.25, 0.5, 0.75)}
    report("start (opened, loader built)", 0, total * BATCH)
    done = 0
    for _ in loader:
        done += 1
        if done == 1:
            report("after first batch", BATCH, total * BATCH)
        if done in marks:
            report(f"after {marks[done]}", done * BATCH, total * BATCH)
    report("after 100% (epoch end)", done * BATCH, total * BATCH)


def streaming_memory(src: Path, work: Path, gigabytes: float, models: tuple[str, ...]) -> tuple[list[dict], dict]:
    from jaxtalk.data.loader import PreparedData
    from jaxtalk.models.freetalk.recipe import fit_displacement_stats

    stats = fit_displacement_stats(PreparedData(src))
    stats_file = work / "ats-stats.json"
    stats_file.write_text(json.dumps({"mean": stats.mean.tolist(), "std": stats.std.tolist()}))
    out = work / "stream"
    t0 = time.perf_counter()
    size, clips = build_stream_dataset(src, out, gigabytes * 1e9)
    print(f"[stream] built {size / 1e9:.2f} GB ({clips} clips) in {time.perf_counter() - t0:.0f} s", flush=True)
    rows, info = [], {"dataset_bytes": size, "clips": clips}
    try:
        for model in models:
            proc = subprocess.run([sys.executable, __file__, "--stream-child", str(out), model, str(stats_file)],
                                  capture_output=True, text=True, check=False)
            got = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
            if proc.returncode != 0 or not got:
                raise RuntimeError(f"streaming child ({model}) failed:\n{proc.stderr[-3000:]}")
            for r in got:
                r["dataset_GB"] = size / 1e9
            rows += got
            end, first = got[-1], got[1]
            info[model] = {"windows_per_s": end["windows"] / end["elapsed_s"], "peak_rss_MB": end["peak_rss_MB"],
                           "rss_growth_MB_first_batch_to_end": end["rss_MB"] - first["rss_MB"],
                           "rss_growth_MB_50_to_100": end["rss_MB"] - next(r["rss_MB"] for r in got if "50%" in r["stage"])}
            print(f"[stream] {model}: {info[model]}", flush=True)
    finally:
        shutil.rmtree(out, ignore_errors=True)
    return rows, info


# -- main ---------------------------------------------------------------------------------------------


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default=None, help="SynthTalk size to prepare (default small; tiny with --quick)")
    parser.add_argument("--hubert", default=None, help="local HuBERT-base checkpoint folder (config.json + weights)")
    parser.add_argument("--hubert-minutes", type=float, default=None, help="audio per HuBERT subset (default 1.5)")
    parser.add_argument("--loader-seconds", type=float, default=None, help="timed loader seconds per recipe")
    parser.add_argument("--repeats", type=int, default=None, help="timed train steps per model")
    parser.add_argument("--stream-gb", type=float, default=None, help="streamed dataset size (default 2.1)")
    parser.add_argument("--data", default=None, help="skip part 1 and use this prepared folder for parts 2-3")
    parser.add_argument("--parts", default="123")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--workdir", default=None, help="parent of the temporary folder (default /tmp)")
    parser.add_argument("--out", default="experiments/results/bench_data.json")
    parser.add_argument("--stream-models", default="toktalk,ats", help="recipes streamed in part 3")
    parser.add_argument("--stream-child", nargs=3, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.stream_child:
        stream_child(*args.stream_child)
        return
    q = args.quick
    size = args.size or ("tiny" if q else "small")
    minutes = args.hubert_minutes or (0.5 if q else 1.5)
    seconds = args.loader_seconds or (3.0 if q else 8.0)
    repeats = args.repeats or (3 if q else 8)
    gigabytes = args.stream_gb or (0.5 if q else 2.1)
    payload: dict[str, Any] = {"machine_info": machine_info(), "settings": {
        "size": size, "hubert": args.hubert, "hubert_minutes": minutes, "loader_seconds": seconds,
        "repeats": repeats, "stream_gb": gigabytes, "batch": BATCH, "quick": q}}
    work = Path(tempfile.mkdtemp(prefix="bench_data-", dir=args.workdir or "/tmp"))
    try:
        prepared = Path(args.data) if args.data else None
        if "1" in args.parts:
            rows, prepared_here = prepare_throughput(size, work, args.hubert, minutes)
            prepared = prepared or prepared_here
            print_table(rows, "1. prepare throughput (audio hours per wall minute)")
            payload["prepare"] = rows
        if prepared is None:
            raise SystemExit("parts 2-3 without part 1 need --data PREPARED_FOLDER")
        if "2" in args.parts:
            from jaxtalk.data.loader import PreparedData

            data = PreparedData(prepared)
            rows = loader_vs_step(data, seconds, repeats)
            print_table(rows, f"2. loader windows/s vs training need (batch {BATCH}; need ratio >= 5) on {data}")
            payload["loader"] = rows
        if "3" in args.parts:
            rows, info = streaming_memory(prepared, work, gigabytes, tuple(args.stream_models.split(",")))
            print_table(rows, f"3. resident memory over one epoch of {info['dataset_bytes'] / 1e9:.2f} GB of records "
                        f"({info['clips']} clips, all in train), in a fresh process per recipe")
            payload["stream"] = {"rows": rows, **info}
    finally:
        shutil.rmtree(work, ignore_errors=True)
    path = write_json(args.out, payload)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
