"""Speed of the three models in one place: per-chunk / per-turn / per-clip latency, FLOPs, and the
achieved fraction of the machine's matmul peak. ``jaxtalk bench`` and ``experiments/bench_*.py`` call
these functions.

Conventions (:mod:`jaxtalk.benchmarking`): compile time apart from run time, medians of repeats of
compiled programs, every run ``block_until_ready``-ed. Weights are random (speed does not depend on
them), drawn on the host from the parameter shapes so that the paper-size models do not spend minutes
compiling their initialisers. FLOPs come from XLA's cost analysis, which counts the body of a
``lax.scan`` once: a sampler's FLOPs are one model evaluation (with its CFG batch) times the steps, and
a train step's are scaled by :func:`jaxtalk.benchmarking.loop_trip_factor` (its matmul work with each
scan counted per iteration over that with each counted once).

Per model:

* :func:`toktalk_chunk` / :func:`toktalk_growth`: streaming latency of one chunk, and chunk 2 vs a
  late chunk of one stream.
* :func:`timar_stream`: per-turn latency of a streamed conversation; :func:`timar_turn`: one turn's
  latency and FLOPs; :func:`timar_head`: the diffusion head alone.
* :func:`ats_clip`: ATS DDIM on a clip; :func:`stm_frames`: STM frames per second on a mesh.
* :func:`run_benchmarks`: all of them, one matmul peak, one set of tables.

Training (:func:`run_train_benchmarks`, ``jaxtalk bench --train``): each model's recipe runs a few
steps on prepared data with a :class:`TrainProbe` watching the shared loop: the loop's own compiled
step timed, its FLOPs and memory from XLA, the loader's time per batch, and the loop's wall time per
step (the host's overhead is the difference).
"""

from __future__ import annotations

import dataclasses
import functools
import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from jaxtalk.train.observers import StepObserver

__all__ = [
    "random_params",
    "toktalk_chunk",
    "toktalk_growth",
    "timar_stream",
    "timar_turn",
    "timar_head",
    "ats_clip",
    "stm_frames",
    "with_peak",
    "BenchTable",
    "run_benchmarks",
    "BENCH_MODELS",
    "TRAIN_MODELS",
    "TrainProbe",
    "train_step",
    "recipe_setup",
    "run_train_benchmarks",
]

BENCH_MODELS = ("toktalk", "timar", "freetalk")
PyTree = Any


def random_params(init: Callable[[Any], PyTree], seed: int = 0) -> PyTree:
    """Parameters with the shapes ``init(key)`` would give, filled on the host.

    Normal weights scaled by ``1 / sqrt(fan_in)``; ``scale`` and ``std`` leaves 1, ``bias`` 0.

    Args:
        init: ``key -> params`` (only traced, with :func:`jax.eval_shape`).
        seed: NumPy seed.

    Returns:
        The parameter pytree (JAX arrays).
    """
    import jax
    import jax.numpy as jnp

    shapes = jax.eval_shape(init, jax.random.key(0))
    rng = np.random.default_rng(seed)

    def fill(path: Any, s: Any) -> Any:
        name = jax.tree_util.keystr(path)
        if name.endswith("['scale']") or name.endswith("['std']"):  # norm scales, standardisation spreads
            return jnp.ones(s.shape, s.dtype)
        if name.endswith("['bias']"):
            return jnp.zeros(s.shape, s.dtype)
        fan_in = int(np.prod(s.shape[:-1])) or 1
        return jnp.asarray(rng.normal(size=s.shape) / np.sqrt(fan_in), s.dtype)

    return jax.tree_util.tree_map_with_path(fill, shapes)


def _median_time(fn: Callable[[], Any], repeats: int) -> float:
    """Median seconds of ``repeats`` calls of ``fn``, each ``block_until_ready``-ed, after one untimed
    call: it waits for anything still queued on the device (JAX dispatches asynchronously), which the
    first timed call would otherwise include."""
    import jax

    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def _rate(flops: float | None, seconds: float) -> float | None:
    return None if flops is None else flops / seconds / 1e9


# ------------------------------------------------------------------------------------------ TokTalk
def toktalk_chunk(config: Any, name: str, repeats: int = 10) -> dict[str, Any]:
    """Latency of one streaming chunk of TokTalk (window full, compile excluded) and its FLOPs.

    Args:
        config: a :class:`~jaxtalk.models.toktalk.TokTalkConfig`.
        name: row label.
        repeats: timed runs (median).

    Returns:
        Row: ``window_frames``, ``chunk_s``, ``compile_s`` (first call), ``latency_s``, ``rtf``
        (latency / chunk duration), ``gflops`` per chunk and ``gflop_s`` achieved, ``weight_gb``: the
        decoder's weights read once per Euler step (the guided pair is one batch of 2) and
        ``weight_gb_s`` achieved (see :func:`with_peak`).
    """
    import jax
    import jax.numpy as jnp

    from jaxtalk.benchmarking import parameter_bytes_read, xla_flops
    from jaxtalk.models import toktalk as tt
    from jaxtalk.models.toktalk.model import Condition, velocity
    from jaxtalk.models.toktalk.sampling import default_grid

    params = random_params(lambda k: tt.init_params(config, k))
    rng = np.random.default_rng(0)
    ct = tt.tokens_per_chunk(config)
    style = jnp.asarray(rng.normal(size=(1, config.style_vector_dim)), jnp.float32)
    state = tt.init_stream(config, jax.random.key(0), batch=1)
    chunk = jnp.asarray(rng.normal(size=(1, ct, config.speech_dim)), jnp.float32)
    ts = jnp.asarray(default_grid(config), jnp.float32)
    t0 = time.perf_counter()
    state, out = tt.stream_step(params, config, state, chunk, style, ts=ts)
    jax.block_until_ready(out)
    compile_s = time.perf_counter() - t0
    step = functools.partial(tt.stream_step, params, config)
    for _ in range(config.window_frames // config.chunk_frames):  # fill the window
        state, out = step(state, chunk, style, ts=ts)
    latency = _median_time(lambda: step(state, chunk, style, ts=ts)[1], repeats)
    # One guided velocity evaluation (conditional + unconditional as a batch of 2) per Euler step.
    wf = config.window_frames
    cond = Condition(
        tokens=jnp.zeros((2, wf, config.speech_dim)), style=jnp.zeros((2, config.style_vector_dim)),
        known=jnp.zeros((2, wf, config.param_dim)), known_mask=jnp.zeros((2, wf), bool),
        keep=jnp.ones((2,)), mask=jnp.ones((2, wf), bool), chunked=jnp.ones((2,), bool),
    )
    x = jnp.zeros((2, wf, config.param_dim))
    guided = lambda p, x, c: velocity(p, config, x, jnp.full((2,), 0.5), c)  # noqa: E731
    per_eval = xla_flops(guided, params, x, cond)
    flops = None if per_eval is None else per_eval * config.sample_steps
    weight_gb = parameter_bytes_read(guided, params, x, cond) * config.sample_steps / 1e9
    duration = config.chunk_frames / config.fps
    return {
        "model": "TokTalk", "case": name, "window_frames": wf, "chunk_s": duration, "compile_s": compile_s,
        "latency_s": latency, "rtf": latency / duration,
        "gflops": None if flops is None else flops / 1e9, "gflop_s": _rate(flops, latency),
        "weight_gb": weight_gb, "weight_gb_s": weight_gb / latency,
    }


def toktalk_window(config: Any, name: str, repeats: int = 10) -> dict[str, Any]:
    """Time of one streaming chunk's computation (the sampler on a full window under the chunk mask,
    overlap inpainted) for ANY decoder: the causal one and the offline one (which may not stream, so
    its cost is measured on the same window outside the streaming engine).

    Returns:
        Row: ``decoder`` (causal / offline), ``window_frames``, ``compile_s``, ``latency_s``.
    """
    import jax
    import jax.numpy as jnp

    from jaxtalk.models import toktalk as tt
    from jaxtalk.models.toktalk.sampling import default_grid, generate_frames
    from jaxtalk.models.toktalk.streaming import overlap_window_mask

    params = random_params(lambda k: tt.init_params(config, k))
    rng = np.random.default_rng(0)
    w = config.window_frames
    tokens = jnp.asarray(rng.normal(size=(1, tt.tokens_per_chunk(config, w), config.speech_dim)), jnp.float32)
    style = jnp.asarray(rng.normal(size=(1, config.style_vector_dim)), jnp.float32)
    noise = jnp.asarray(rng.normal(size=(1, w, config.param_dim)), jnp.float32)
    known_mask = jnp.asarray(overlap_window_mask(config)[None])
    run = jax.jit(lambda p, tok, sty, z: generate_frames(
        p, config, tok, sty, z, jnp.asarray(default_grid(config), jnp.float32), jnp.float32(config.cfg_scale),
        known=z, known_mask=known_mask, mask=jnp.ones((1, w), bool), chunked=jnp.ones((), bool)))
    t0 = time.perf_counter()
    jax.block_until_ready(run(params, tokens, style, noise))
    compile_s = time.perf_counter() - t0
    latency = _median_time(lambda: run(params, tokens, style, noise), repeats)
    return {"model": "TokTalk", "case": name, "decoder": "causal" if config.causal else "offline",
            "window_frames": w, "compile_s": compile_s, "latency_s": latency}


def toktalk_growth(config: Any, chunks: int = 50, repeats: int = 10) -> dict[str, Any]:
    """Per-chunk latency at chunk 2 and at chunk ``chunks`` of one stream (the bounded window keeps
    them equal; a model that recomputes the whole prefix grows).

    Returns:
        ``{"chunk_2_s", "chunk_<n>_s", "ratio"}``.

    Raises:
        ValueError: ``chunks < 3``.
    """
    import jax
    import jax.numpy as jnp

    from jaxtalk.models import toktalk as tt

    if chunks < 3:
        raise ValueError(f"chunks must be >= 3, got {chunks}")
    params = random_params(lambda k: tt.init_params(config, k))
    rng = np.random.default_rng(1)
    ct = tt.tokens_per_chunk(config)
    style = jnp.asarray(rng.normal(size=(1, config.style_vector_dim)), jnp.float32)
    state = tt.init_stream(config, jax.random.key(0), batch=1)
    times = {}
    for i in range(1, chunks + 1):
        chunk = jnp.asarray(rng.normal(size=(1, ct, config.speech_dim)), jnp.float32)
        if i in (2, chunks):
            times[i] = _median_time(lambda: tt.stream_step(params, config, state, chunk, style)[1], repeats)
        state, out = tt.stream_step(params, config, state, chunk, style)
        jax.block_until_ready(out)
    return {"chunk_2_s": times[2], f"chunk_{chunks}_s": times[chunks], "ratio": times[chunks] / times[2]}


# ------------------------------------------------------------------------------------------ TIMAR
def _timar_inputs(config: Any, turns: int, seed: int = 0) -> tuple[Any, Any, Any]:
    import jax.numpy as jnp

    rng = np.random.default_rng(seed)
    t = turns * config.frames_per_turn
    return (jnp.asarray(rng.normal(size=(1, t, config.speech_dim)), jnp.float32),
            jnp.asarray(rng.normal(size=(1, t, config.param_dim)), jnp.float32),
            jnp.asarray(rng.normal(size=(1, t, config.speech_dim)), jnp.float32))


def timar_stream(config: Any, *, context: int = 7, turns: int = 12, repeats: int = 3,
                 cfg_scale: float = 1.5) -> tuple[float, list[float]]:
    """Per-turn latency (median over repeats) of a streamed conversation, compile excluded.

    Args:
        config: a :class:`~jaxtalk.models.timar.TimarConfig`.
        context: previous turns in the window (turns ``<= context`` use the KV cache, later ones slide).
        turns: turns streamed.
        repeats: timed passes.
        cfg_scale: guidance scale.

    Returns:
        ``(first call in seconds incl. compile, [median seconds of turn i])``.
    """
    import jax

    from jaxtalk.models.timar import init_params
    from jaxtalk.models.timar.streaming import init_stream, stream_step

    params = random_params(lambda k: init_params(config, k))
    f = config.frames_per_turn
    us, um, as_ = _timar_inputs(config, turns)
    per_turn: list[list[float]] = [[] for _ in range(turns)]
    first = 0.0
    for r in range(repeats + 1):
        state = init_stream(config, jax.random.key(r), context=context)
        for i in range(turns):
            sl = slice(i * f, (i + 1) * f)
            t0 = time.perf_counter()
            state, x = stream_step(params, config, state, us[:, sl], um[:, sl], as_[:, sl], cfg_scale=cfg_scale)
            jax.block_until_ready(x)
            dt = time.perf_counter() - t0
            if r == 0 and i == 0:
                first = dt
            elif r > 0:
                per_turn[i].append(dt)
    return first, [statistics.median(v) for v in per_turn]


def timar_turn(config: Any, name: str, *, context: int = 7, turn: int = 0, repeats: int = 3,
               sample_steps: int | None = None, count_flops: bool = True) -> dict[str, Any]:
    """One streamed turn of TIMAR with CFG (conditioning + DDIM): latency and FLOPs.

    ``turn <= context``: the window still fits (cached keys/values); ``turn > context``: the window
    slides and is recomputed. The choice is a ``lax.cond`` and XLA's cost analysis counts both
    branches, so the count fits the sliding turn (its expensive branch dominates) and over-counts a
    cached one: pass ``count_flops=False`` there.

    Returns:
        Row with ``compile_s``, ``latency_s``, ``rtf`` (latency / turn duration), ``gflops``, ``gflop_s``.
    """
    import jax
    import jax.numpy as jnp

    from jaxtalk.benchmarking import time_jitted, xla_flops
    from jaxtalk.models.timar import init_params
    from jaxtalk.models.timar.head import apply_head
    from jaxtalk.models.timar.sampling import sample_frames
    from jaxtalk.models.timar.streaming import _condition, init_stream

    steps = config.sample_steps if sample_steps is None else sample_steps
    params = random_params(lambda k: init_params(config, k))
    us, um, as_ = _timar_inputs(config, 1)
    state = init_stream(config, jax.random.key(0), context=context)._replace(turn=jnp.asarray(turn, jnp.int32))

    def condition(p: Any, s: Any, a: Any, b: Any, c: Any) -> Any:
        return _condition(p, config, s, a, b, c, True)[1]  # traceable (the public one checks values)

    def step(p: Any, s: Any, a: Any, b: Any, c: Any, k: Any) -> Any:
        z = condition(p, s, a, b, c)
        return sample_frames(p, config, z[:1], z[1:], k, cfg_scale=1.5, sample_steps=steps)

    args = (params, state, us, um, as_, jax.random.key(0))
    timing = time_jitted(step, *args, repeats=repeats, warmup=1)
    flops = None
    if count_flops:
        cond_flops = xla_flops(condition, *args[:-1])
        z = jnp.zeros((2, config.frames_per_turn, config.width))
        x = jnp.zeros((2, config.frames_per_turn, config.param_dim))
        t = jnp.zeros((2, config.frames_per_turn))
        head_flops = xla_flops(lambda p, z, x, t: apply_head(p["head"], config, z, x, t), params, z, x, t)
        flops = None if cond_flops is None or head_flops is None else cond_flops + steps * head_flops
    duration = config.frames_per_turn / 25
    return {
        "model": "TIMAR", "case": name, "compile_s": timing.compile_s, "latency_s": timing.run_median_s,
        "rtf": timing.run_median_s / duration, "gflops": None if flops is None else flops / 1e9,
        "gflop_s": _rate(flops, timing.run_median_s),
    }


def timar_head(steps: int, repeats: int = 3, config: Any = None) -> dict[str, Any]:
    """The diffusion head alone (default: the reference size, 1024 wide, K = 3, learned variance):
    one 25-frame turn with CFG.

    Returns:
        Row with ``steps``, ``compile_s``, ``latency_s``.
    """
    import jax

    from jaxtalk.benchmarking import time_jitted
    from jaxtalk.models.timar import TimarConfig, init_params
    from jaxtalk.models.timar.sampling import sample_frames

    cfg = TimarConfig.paper(num_layers=1) if config is None else config  # only the head is used
    params = random_params(lambda k: init_params(cfg, k))
    z = jax.random.normal(jax.random.key(1), (1, cfg.frames_per_turn, cfg.width))

    def fn(p: Any, zc: Any, zu: Any, k: Any) -> Any:
        return sample_frames(p, cfg, zc, zu, k, cfg_scale=1.5, sample_steps=steps)

    t = time_jitted(fn, params, z, z * 0.5, jax.random.key(2), repeats=repeats, warmup=1)
    return {"model": "TIMAR head", "steps": steps, "compile_s": t.compile_s, "latency_s": t.run_median_s}


# ------------------------------------------------------------------------------------------ FreeTalk
def ats_clip(config: Any, name: str, *, steps: int = 100, frames: int = 100, repeats: int = 3) -> dict[str, Any]:
    """ATS DDIM sampling of one clip of ``frames`` frames (25 fps): latency and FLOPs.

    FLOPs are one denoiser evaluation times the steps; the sampler encodes the audio memory once per
    clip, which this counts once per step (a small over-count).

    Returns:
        Row with ``clip_s``, ``steps``, ``compile_s``, ``latency_s``, ``rtf``, ``gflops``, ``gflop_s``,
        ``weight_gb`` (the denoiser's weights read once per step) and ``weight_gb_s``.
    """
    import jax
    import jax.numpy as jnp

    from jaxtalk.benchmarking import parameter_bytes_read, time_jitted, xla_flops
    from jaxtalk.models.freetalk import ats

    params = random_params(lambda k: ats.init_params(config, k))
    audio = np.random.default_rng(0).normal(size=(1, frames, config.speech_dim)).astype(np.float32)
    cond = ats.make_condition(config, audio, "happy", 2.0)
    sample = functools.partial(ats._sample, config=config, sample_steps=steps, noise=None, remat=False)
    timing = time_jitted(lambda p, c, k, e: sample(p, cond=c, key=k, eta=e), params, cond, jax.random.key(1),
                         jnp.float32(0.0), repeats=repeats, warmup=1)
    x = jnp.zeros((1, frames, config.motion_dim))
    denoise = lambda p, x, c: ats.ats_denoise(p, config, x, jnp.zeros((1,), jnp.int32), c)  # noqa: E731
    per_eval = xla_flops(denoise, params, x, cond)
    flops = None if per_eval is None else per_eval * steps
    weight_gb = parameter_bytes_read(denoise, params, x, cond) * steps / 1e9
    clip_s = frames / 25
    return {
        "model": "FreeTalk ATS", "case": name, "clip_s": clip_s, "steps": steps, "compile_s": timing.compile_s,
        "latency_s": timing.run_median_s, "rtf": timing.run_median_s / clip_s,
        "gflops": None if flops is None else flops / 1e9, "gflop_s": _rate(flops, timing.run_median_s),
        "weight_gb": weight_gb, "weight_gb_s": weight_gb / timing.run_median_s,
    }


def stm_frames(config: Any, name: str, *, resolution: str = "high", frames: int = 25, repeats: int = 3) -> dict[str, Any]:
    """STM decoding of ``frames`` landmark frames on the built-in face (mesh features precomputed).

    Returns:
        Row with ``vertices``, ``operators_s`` and ``mesh_features_s`` (per-mesh precompute),
        ``compile_s``, ``latency_s`` (per call), ``frames_per_s``, ``gflops``, ``gflop_s``.
    """
    import jax
    import jax.numpy as jnp

    from jaxtalk.benchmarking import time_jitted, xla_flops
    from jaxtalk.face import builtin_face
    from jaxtalk.models.freetalk import stm

    face = builtin_face(0, resolution=resolution)
    t0 = time.perf_counter()
    mesh = stm.prepare_mesh(np.asarray(face.template, np.float64), np.asarray(face.faces), config)
    operators_s = time.perf_counter() - t0
    params = stm.init_params(config, jax.random.key(0), mesh)
    features_fn = functools.partial(stm._mesh_features, config=config)
    feat = time_jitted(lambda p, m: features_fn(p, mesh=m), params, mesh, repeats=repeats)
    features = stm.stm_mesh_features(params, config, mesh)
    motion = jnp.asarray(0.004 * np.random.default_rng(0).normal(size=(frames, config.num_landmarks, 3)), jnp.float32)
    decode = functools.partial(stm._decode, config=config)

    def fn(p: Any, f: Any, d: Any, o: Any) -> Any:
        return decode(p, features=f, disp=d, ops=o)

    timing = time_jitted(fn, params, features, motion, mesh.ops, repeats=repeats)
    # Frames run in a lax.map, whose body XLA's cost analysis counts once: count one frame, scale.
    one_frame = xla_flops(fn, params, features, motion[:1], mesh.ops)
    flops = None if one_frame is None else one_frame * frames
    return {
        "model": "FreeTalk STM", "case": name, "vertices": mesh.num_vertices, "operators_s": operators_s,
        "mesh_features_s": feat.run_median_s, "compile_s": timing.compile_s, "latency_s": timing.run_median_s,
        "frames_per_s": frames / timing.run_median_s, "gflops": None if flops is None else flops / 1e9,
        "gflop_s": _rate(flops, timing.run_median_s),
    }


# ------------------------------------------------------------------------------------------ all
def _put_after(row: dict[str, Any], after: str, key: str, value: Any) -> dict[str, Any]:
    """``row`` with ``key: value`` right after ``after`` (at the end where the row has no ``after``)."""
    row = {k: v for k, v in row.items() if k != key}
    if after not in row:
        return {**row, key: value}
    keys = list(row)
    at = keys.index(after) + 1
    return {**{k: row[k] for k in keys[:at]}, key: value, **{k: row[k] for k in keys[at:]}}


def with_peak(rows: list[dict[str, Any]], peak_gflop_s: float, bandwidth_gb_s: float | None = None) -> list[dict[str, Any]]:
    """Rows expressed against the machine's limits measured in the same run.

    Adds ``of_peak`` = ``gflop_s / peak_gflop_s`` right after ``gflop_s`` (None where FLOPs are
    unknown). With ``bandwidth_gb_s``, rows that say how many bytes of weights they must read
    (``weight_gb``, ``weight_gb_s``) also get ``of_bandwidth`` = ``weight_gb_s / bandwidth_gb_s`` and
    ``of_roofline``: the roofline's time, the longer of the FLOPs at the peak and the weight bytes at
    the bandwidth, over the measured latency (1.0: as fast as either limit allows).
    """
    out = []
    for r in rows:
        row = _put_after(r, "gflop_s", "of_peak", None if r.get("gflop_s") is None else r["gflop_s"] / peak_gflop_s)
        if bandwidth_gb_s is not None and row.get("weight_gb_s") is not None:
            row = _put_after(row, "weight_gb_s", "of_bandwidth", row["weight_gb_s"] / bandwidth_gb_s)
            bound = max(row["weight_gb"] / bandwidth_gb_s, (row.get("gflops") or 0.0) / peak_gflop_s)
            row = _put_after(row, "of_bandwidth", "of_roofline", bound / row["latency_s"])
        out.append(row)
    return out


@dataclasses.dataclass
class BenchTable:
    """One printed table: a title and its rows."""

    title: str
    rows: list[dict[str, Any]]


def run_benchmarks(
    models: Sequence[str] = BENCH_MODELS,
    *,
    paper: bool = False,
    repeats: int = 5,
    configs: dict[str, Any] | None = None,
    echo: Callable[[str], None] = print,
) -> tuple[float, float, list[BenchTable]]:
    """The speed tables of the chosen models, with one matmul peak and memory bandwidth for all of them.

    Args:
        models: any of ``toktalk``, ``timar``, ``freetalk``.
        paper: also benchmark the paper-size presets (minutes of compilation on a CPU).
        repeats: timed runs per case.
        configs: replace the ``small`` configs (keys ``toktalk``, ``timar``, ``ats``, ``stm``), e.g.
            tiny ones for a smoke test.
        echo: progress lines.

    Returns:
        ``(matmul peak in GFLOP/s, memory bandwidth in GB/s, tables)``.

    Raises:
        ValueError: an unknown model name or ``repeats < 1``.
    """
    from jaxtalk.benchmarking import measure_matmul_peak, measure_memory_bandwidth
    from jaxtalk.models.freetalk.config import ATSConfig, STMConfig
    from jaxtalk.models.timar import TimarConfig
    from jaxtalk.models.toktalk import TokTalkConfig

    unknown = [m for m in models if m not in BENCH_MODELS]
    if unknown:
        raise ValueError(f"unknown benchmark model(s) {unknown}; expected some of {', '.join(BENCH_MODELS)}")
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    small = {"toktalk": TokTalkConfig.small(), "timar": TimarConfig.small(), "ats": ATSConfig.small(),
             "stm": STMConfig.small(), **(configs or {})}
    echo("measuring the float32 matmul peak and the memory bandwidth")
    peak = measure_matmul_peak() / 1e9
    bandwidth = measure_memory_bandwidth() / 1e9
    tables: list[BenchTable] = []
    few = max(1, repeats // 2)
    if "toktalk" in models:
        echo("TokTalk: streaming chunks")
        rows = [toktalk_chunk(small["toktalk"], "small, 0.4-s chunk", repeats)]
        if paper:
            rows.append(toktalk_chunk(TokTalkConfig.paper(context_frames=0, overlap_frames=0), "paper, 10 frames", few))
            rows.append(toktalk_chunk(TokTalkConfig.paper(context_frames=40), "paper, 50 frames", few))
        tables.append(BenchTable("TokTalk: one streaming chunk (Euler steps + CFG)", with_peak(rows, peak, bandwidth)))
    if "timar" in models:
        echo("TIMAR: streamed turns")
        cfg = small["timar"]
        context = min(7, cfg.max_turns - 1)
        rows = [timar_turn(cfg, f"small, turn 0 (cached, n={context})", context=context, turn=0, repeats=repeats,
                           count_flops=False),
                timar_turn(cfg, f"small, turn {context + 1} (window slides)", context=context, turn=context + 1,
                           repeats=repeats)]
        if paper:
            rows.append(timar_turn(TimarConfig.paper(), "paper, turn 8 (window slides, n=7)", turn=8, repeats=few))
        tables.append(BenchTable("TIMAR: one streamed 1-s turn (DDIM + CFG)", with_peak(rows, peak, bandwidth)))
    if "freetalk" in models:
        echo("FreeTalk: ATS clip, STM frames")
        rows = [ats_clip(small["ats"], "small", steps=s, repeats=few) for s in (10, 100)]
        if paper:
            rows.append(ats_clip(ATSConfig.paper(), "paper", steps=100, repeats=few))
        tables.append(BenchTable("FreeTalk ATS: DDIM on a 4-s clip", with_peak(rows, peak, bandwidth)))
        rows = [stm_frames(small["stm"], "small", repeats=repeats)]
        if paper:
            rows.append(stm_frames(STMConfig.paper(), "paper", repeats=few))
        tables.append(BenchTable("FreeTalk STM: 25 frames per call on the ~5.9k-vertex face", with_peak(rows, peak, bandwidth)))
    return peak, bandwidth, tables


# ------------------------------------------------------------------------------------------ training
TRAIN_MODELS = ("toktalk", "ats", "stm", "timar", "dualtalk")
TRAIN_PRESETS = ("small", "paper")
# The inference table that shows each training model's sampler.
SAMPLER_OF = {"toktalk": "toktalk", "ats": "freetalk", "stm": "freetalk", "timar": "timar"}


class _WindowDone(Exception):
    """Raised by :class:`TrainProbe` once its timed window is over: the benchmark needs no more steps
    (nor the run's final evaluation)."""


class TrainProbe(StepObserver):
    """Measures a real recipe run from inside the shared loop (a :class:`~jaxtalk.train.StepObserver`).

    * At the start: the loader's sustained rate, from the loop's own loader: the first batch (which
      builds the pipeline) and the read-ahead buffer's worth after it are drawn untimed, then
      ``loader_batches`` more back to back, timed together. Draws from a full buffer cost nothing,
      so timing the first few measures how full the buffer happened to be, not how fast it fills.
    * Before update 1: the loop's jitted step, on a copy of the loop's state and the first batch (put
      on the device first):
      ``lower`` + ``compile`` timed, XLA's cost analysis (FLOPs) and memory analysis, then
      ``repeats`` runs of the compiled step (after ``warmup``), each ``block_until_ready``-ed, the
      state chained from one to the next as in training. With ``profile_dir`` a
      :mod:`jax.profiler` trace of those runs is written there.
    * Updates ``loop_warmup + 1 .. loop_warmup + loop_steps`` of the loop itself: wall time from the
      finished update ``loop_warmup`` to the finished last one (the loop's batches, checks, metric
      fetches and dispatch included), after which it raises to stop the run.

    Attributes:
        result: what was measured (filled as the run goes).
    """

    def __init__(self, *, repeats: int = 5, warmup: int = 2, loop_warmup: int = 2, loop_steps: int = 10,
                 loader_batches: int = 20, profile_dir: Any = None) -> None:
        if min(repeats, loop_steps, loader_batches) < 1 or min(warmup, loop_warmup) < 0:
            raise ValueError("repeats, loop_steps and loader_batches must be >= 1, warm-ups >= 0")
        self.repeats, self.warmup = repeats, warmup
        self.loop_warmup, self.loop_steps = loop_warmup, loop_steps
        self.loader_batches = loader_batches
        self.profile_dir = profile_dir
        self.result: dict[str, Any] = {}
        self._t0: float | None = None

    @property
    def last_step(self) -> int:
        """The update after which the probe stops the run."""
        return self.loop_warmup + self.loop_steps

    def start(self, data_iter: Any) -> None:
        from jaxtalk.data.loader import PREFETCH_BATCHES

        for _ in range(1 + PREFETCH_BATCHES):  # builds grain's pipeline, then empties the read-ahead
            next(data_iter)
        t0 = time.perf_counter()
        for _ in range(self.loader_batches):
            next(data_iter)
        self.result["loader_s"] = (time.perf_counter() - t0) / self.loader_batches

    def before_step(self, step: int, state: Any, batch: Any, step_fn: Callable[..., Any]) -> None:
        import jax

        if step != 1:
            return
        copy = jax.tree.map(lambda x: x.copy(), state)  # the loop donates its own state
        # On the device once: the timed step is the computation; the loop's per-step transfer of the
        # host batch counts in its wall time (the host's share).
        batch = jax.device_put(batch)
        from jaxtalk.benchmarking import loop_trip_factor

        t0 = time.perf_counter()
        traced = step_fn.trace(copy, batch)
        compiled = traced.lower().compile()
        compile_s = time.perf_counter() - t0
        cost = compiled.cost_analysis()
        if isinstance(cost, (list, tuple)):
            cost = cost[0] if cost else None
        flops = float(cost["flops"]) if cost and "flops" in cost and float(cost["flops"]) >= 0 else None
        if flops is not None:  # XLA counts a scan's body once (STM decodes its window frame by frame)
            flops *= loop_trip_factor(traced.jaxpr)
        memory = compiled.memory_analysis()
        peak = None
        if memory is not None:
            peak = getattr(memory, "peak_memory_in_bytes", 0) or (
                memory.argument_size_in_bytes + memory.output_size_in_bytes + memory.temp_size_in_bytes
                - memory.alias_size_in_bytes)
        for _ in range(self.warmup):
            copy, metrics = compiled(copy, batch)
            jax.block_until_ready((copy, metrics))
        if self.profile_dir is not None:
            from pathlib import Path

            Path(self.profile_dir).mkdir(parents=True, exist_ok=True)
            jax.profiler.start_trace(str(self.profile_dir), create_perfetto_trace=True)
        runs = []
        try:
            for _ in range(self.repeats):
                t0 = time.perf_counter()
                copy, metrics = compiled(copy, batch)
                jax.block_until_ready((copy, metrics))
                runs.append(time.perf_counter() - t0)
        finally:
            if self.profile_dir is not None:
                jax.profiler.stop_trace()
        del copy
        leaves = jax.tree.leaves(batch)
        self.result.update(
            batch=int(leaves[0].shape[0]) if leaves and np.ndim(leaves[0]) else None,
            params_m=sum(int(np.size(p)) for p in jax.tree.leaves(state.params)) / 1e6,
            compile_s=compile_s, step_s=float(np.median(runs)), step_min_s=float(min(runs)),
            flops=flops, memory_gb=None if peak is None else peak / 2**30,
        )

    def after_step(self, step: int, state: Any, metrics: Any) -> None:
        import jax

        if step == self.loop_warmup:
            jax.block_until_ready((state, metrics))
            self._t0 = time.perf_counter()
        elif step == self.last_step:
            jax.block_until_ready((state, metrics))
            self.result["loop_step_s"] = (time.perf_counter() - self._t0) / self.loop_steps
            raise _WindowDone

    def close(self) -> None:
        """Nothing to release."""

    def row(self) -> dict[str, Any]:
        """The measured values as a benchmark row (without the fraction of peak).

        Returns:
            ``batch``, ``params_m`` (millions), ``step_s`` (median compiled step), ``gflops`` per
            step, ``gflop_s``, ``compile_s``, ``memory_gb`` (XLA's peak for the step), ``loop_step_s``
            (wall per step in the loop), ``host_s`` (loop minus compiled step) and ``host_share``
            (of the loop's step), ``loader_s`` per batch and ``loader_x`` (batches the loader makes
            in one compiled step).
        """
        r = self.result
        flops = r.get("flops")
        loop = r.get("loop_step_s")
        host = None if loop is None else loop - r["step_s"]
        return {
            "batch": r.get("batch"), "params_m": r.get("params_m"), "step_s": r["step_s"],
            "gflops": None if flops is None else flops / 1e9, "gflop_s": _rate(flops, r["step_s"]),
            "compile_s": r["compile_s"], "memory_gb": r.get("memory_gb"), "loop_step_s": loop, "host_s": host,
            "host_share": None if host is None else host / loop, "loader_s": r.get("loader_s"),
            "loader_x": r["step_s"] / r["loader_s"] if r.get("loader_s") else None,
        }


def _peak_rss_gb() -> float | None:
    """The process's peak resident memory so far, in GiB (None where the OS does not say)."""
    try:
        import resource
        import sys

        kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return kb / 2**30 if sys.platform == "darwin" else kb / 2**20
    except (ImportError, OSError):
        return None


def recipe_setup(model: str, preset: str, data: Any, overrides: Sequence[str] = ()) -> tuple[Callable[..., Any], Any, Any]:
    """What ``jaxtalk train MODEL --preset PRESET --set ...`` would train on ``data``.

    Args:
        model: a model of :data:`jaxtalk.runs.REGISTRY`.
        preset: a config preset.
        data: a :class:`~jaxtalk.data.loader.PreparedData` (input widths follow it unless set).
        overrides: ``key=value`` items for the config or the training settings.

    Returns:
        ``(recipe train function, model config, TrainSettings)``.

    Raises:
        ValueError: an unknown model or preset, or bad overrides.
    """
    from jaxtalk.runs import build_config, config_class, model_spec, parse_overrides, split_overrides

    spec = model_spec(model)
    train_fn, defaults = spec.train, spec.settings(preset)
    model_items, train_kw = split_overrides(model, overrides)
    explicit = parse_overrides(config_class(model), model_items)
    m = data.manifest
    widths = [f"{field}={m[key]:g}" if isinstance(m[key], float) else f"{field}={m[key]}"
              for field, key in model_spec(model).data_fields if m.get(key) is not None and field not in explicit]
    config = build_config(model, preset, [*widths, *model_items])
    return train_fn, config, dataclasses.replace(defaults, **train_kw)


def train_step(
    model: str,
    preset: str,
    data: Any,
    *,
    overrides: Sequence[str] = (),
    repeats: int = 5,
    loop_steps: int = 10,
    loop_warmup: int = 2,
    loader_batches: int = 20,
    profile_dir: Any = None,
) -> dict[str, Any]:
    """One training row: the model's recipe run for a few steps on ``data`` with a :class:`TrainProbe`.

    The model config is the preset plus ``overrides`` (``--set`` items; training settings such as
    ``batch_size`` included), its input widths following the data as in ``jaxtalk train``; the
    optimiser settings are the recipe's for the preset. The step timed is the loop's own jitted step
    (:func:`jaxtalk.train.make_train_step` of the recipe's loss), not a copy of it.

    Args:
        model: one of :data:`TRAIN_MODELS`.
        preset: ``small`` or ``paper`` (``tiny`` where the model has one).
        data: a :class:`~jaxtalk.data.loader.PreparedData`.
        overrides: ``key=value`` items for the config or the training settings.
        repeats: timed runs of the compiled step.
        loop_steps: updates of the loop timed for its wall time per step.
        loop_warmup: updates of the loop before those.
        loader_batches: batches timed from the loop's loader (after its read-ahead is emptied).
        profile_dir: write a :mod:`jax.profiler` trace of the timed compiled steps here.

    Returns:
        Row: ``model``, ``preset``, the :meth:`TrainProbe.row` values and ``rss_gb`` (the process's
        peak resident memory so far).

    Raises:
        ValueError: an unknown model or preset, or bad overrides.
    """
    import jax

    if model not in TRAIN_MODELS:
        raise ValueError(f"unknown training benchmark model {model!r}; expected one of {', '.join(TRAIN_MODELS)}")
    train_fn, config, settings = recipe_setup(model, preset, data, overrides)
    probe = TrainProbe(repeats=repeats, loop_warmup=loop_warmup, loop_steps=loop_steps,
                       loader_batches=loader_batches, profile_dir=profile_dir)
    steps = probe.last_step + 1
    from jaxtalk.runs import RunSettings
    from jaxtalk.train import LoopSettings

    run = RunSettings(steps=steps, batch_size=settings.batch_size, seed=0, window_frames=settings.window_frames or None,
                      loop=LoopSettings(progress=False), observers=[probe])
    try:
        train_fn(config, data, settings.optim(steps), key=jax.random.key(0), run=run)
    except _WindowDone:
        pass
    else:
        raise RuntimeError(f"{model} {preset}: the run ended before the probe's window")
    return {"model": model, "preset": preset, **probe.row(), "rss_gb": _peak_rss_gb()}


def run_train_benchmarks(
    models: Sequence[str] = TRAIN_MODELS,
    presets: Sequence[str] = ("small",),
    *,
    data: Any,
    peak_gflop_s: float,
    overrides: dict[str, Sequence[str]] | None = None,
    repeats: int = 5,
    loop_steps: int = 10,
    paper_batch: int | None = None,
    profile_dir: Any = None,
    echo: Callable[[str], None] = print,
) -> BenchTable:
    """The training table: one :func:`train_step` row per model and preset, with ``of_peak``.

    Args:
        models: any of :data:`TRAIN_MODELS`.
        presets: config presets, each run for every model.
        data: the prepared dataset every model trains on.
        peak_gflop_s: the float32 matmul peak measured in this process.
        overrides: ``--set`` items per model name (e.g. a smaller batch).
        repeats: timed compiled steps per row (``paper`` rows: half as many, at least 2).
        loop_steps: timed loop updates per row (``paper`` rows: a third as many, at least 3).
        paper_batch: the batch of the ``paper`` rows (None: the recipe's for the preset, e.g. TIMAR's
            32, which takes minutes per step on a CPU).
        profile_dir: a :mod:`jax.profiler` trace of each row's compiled steps in ``<dir>/<model>-<preset>``.
        echo: progress lines.

    Returns:
        The :class:`BenchTable`.

    Raises:
        ValueError: an unknown model name, or ``repeats`` / ``loop_steps`` < 1.
    """
    from pathlib import Path

    unknown = [m for m in models if m not in TRAIN_MODELS]
    if unknown:
        raise ValueError(f"unknown training benchmark model(s) {unknown}; expected some of {', '.join(TRAIN_MODELS)}")
    if repeats < 1 or loop_steps < 1:
        raise ValueError(f"repeats and loop_steps must be >= 1, got {repeats} and {loop_steps}")
    rows = []
    for preset in presets:
        for model in models:
            echo(f"training step: {model} {preset}")
            trace = None if profile_dir is None else Path(profile_dir) / f"{model}-{preset}"
            items = tuple((overrides or {}).get(model, ()))
            reps, loop = repeats, loop_steps
            if preset == "paper":  # seconds to minutes per step on a CPU: fewer of them
                reps, loop = max(2, repeats // 2), max(3, loop_steps // 3)
                items = items + ((f"batch_size={paper_batch}",) if paper_batch is not None else ())
            rows.append(train_step(model, preset, data, overrides=items, repeats=reps, loop_steps=loop,
                                   loop_warmup=1 if preset == "paper" else 2, profile_dir=trace))
    return BenchTable("Training: one train step (compiled, median) and the loop around it", with_peak(rows, peak_gflop_s))
