"""Speed of the three models in one place: per-chunk / per-turn / per-clip latency, FLOPs, and the
achieved fraction of the machine's matmul peak. ``jaxtalk bench`` and ``experiments/bench_*.py`` call
these functions.

Conventions (:mod:`jaxtalk.benchmarking`): compile time apart from run time, medians of repeats of
compiled programs, every run ``block_until_ready``-ed. Weights are random (speed does not depend on
them), drawn on the host from the parameter shapes so that the paper-size models do not spend minutes
compiling their initialisers. FLOPs come from XLA's cost analysis, which counts the body of a
``lax.scan`` once: a sampler's FLOPs are one model evaluation (with its CFG batch) times the steps.

Per model:

* :func:`toktalk_chunk` / :func:`toktalk_growth`: streaming latency of one chunk, and chunk 2 vs a
  late chunk of one stream.
* :func:`timar_stream`: per-turn latency of a streamed conversation; :func:`timar_turn`: one turn's
  latency and FLOPs; :func:`timar_head`: the diffusion head alone.
* :func:`ats_clip`: ATS DDIM on a clip; :func:`stm_frames`: STM frames per second on a mesh.
* :func:`run_benchmarks`: all of them, one matmul peak, one set of tables.
"""

from __future__ import annotations

import dataclasses
import functools
import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

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
    import jax

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
        (latency / chunk duration), ``gflops`` per chunk and ``gflop_s`` achieved.
    """
    import jax
    import jax.numpy as jnp

    from jaxtalk.benchmarking import xla_flops
    from jaxtalk.models import toktalk as tt
    from jaxtalk.models.toktalk.model import Condition, velocity
    from jaxtalk.models.toktalk.sample import default_grid

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
    per_eval = xla_flops(lambda p, x, c: velocity(p, config, x, jnp.full((2,), 0.5), c), params, x, cond)
    flops = None if per_eval is None else per_eval * config.sample_steps
    duration = config.chunk_frames / config.fps
    return {
        "model": "TokTalk", "case": name, "window_frames": wf, "chunk_s": duration, "compile_s": compile_s,
        "latency_s": latency, "rtf": latency / duration,
        "gflops": None if flops is None else flops / 1e9, "gflop_s": _rate(flops, latency),
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
    from jaxtalk.models.toktalk.sample import default_grid, generate_frames
    from jaxtalk.models.toktalk.stream import overlap_window_mask

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
    from jaxtalk.models.timar.stream import init_stream, stream_step

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
    from jaxtalk.models.timar.sample import sample_frames
    from jaxtalk.models.timar.stream import _condition, init_stream

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
    from jaxtalk.models.timar.sample import sample_frames

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
        Row with ``clip_s``, ``steps``, ``compile_s``, ``latency_s``, ``rtf``, ``gflops``, ``gflop_s``.
    """
    import jax
    import jax.numpy as jnp

    from jaxtalk.benchmarking import time_jitted, xla_flops
    from jaxtalk.models.freetalk import ats

    params = random_params(lambda k: ats.init_params(config, k))
    audio = np.random.default_rng(0).normal(size=(1, frames, config.speech_dim)).astype(np.float32)
    cond = ats.make_condition(config, audio, "happy", 2.0)
    sample = functools.partial(ats._sample, config=config, sample_steps=steps, noise=None, remat=False)
    timing = time_jitted(lambda p, c, k, e: sample(p, cond=c, key=k, eta=e), params, cond, jax.random.key(1),
                         jnp.float32(0.0), repeats=repeats, warmup=1)
    x = jnp.zeros((1, frames, config.motion_dim))
    per_eval = xla_flops(lambda p, x, c: ats.ats_denoise(p, config, x, jnp.zeros((1,), jnp.int32), c), params, x, cond)
    flops = None if per_eval is None else per_eval * steps
    clip_s = frames / 25
    return {
        "model": "FreeTalk ATS", "case": name, "clip_s": clip_s, "steps": steps, "compile_s": timing.compile_s,
        "latency_s": timing.run_median_s, "rtf": timing.run_median_s / clip_s,
        "gflops": None if flops is None else flops / 1e9, "gflop_s": _rate(flops, timing.run_median_s),
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
def with_peak(rows: list[dict[str, Any]], peak_gflop_s: float) -> list[dict[str, Any]]:
    """Rows with ``of_peak`` = ``gflop_s / peak_gflop_s`` added (None where FLOPs are unknown)."""
    return [{**r, "of_peak": None if r.get("gflop_s") is None else r["gflop_s"] / peak_gflop_s} for r in rows]


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
) -> tuple[float, list[BenchTable]]:
    """The speed tables of the chosen models, with one matmul peak for all of them.

    Args:
        models: any of ``toktalk``, ``timar``, ``freetalk``.
        paper: also benchmark the paper-size presets (minutes of compilation on a CPU).
        repeats: timed runs per case.
        configs: replace the ``small`` configs (keys ``toktalk``, ``timar``, ``ats``, ``stm``), e.g.
            tiny ones for a smoke test.
        echo: progress lines.

    Returns:
        ``(matmul peak in GFLOP/s, tables)``.

    Raises:
        ValueError: an unknown model name or ``repeats < 1``.
    """
    from jaxtalk.benchmarking import measure_matmul_peak
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
    echo("measuring the float32 matmul peak")
    peak = measure_matmul_peak() / 1e9
    tables: list[BenchTable] = []
    few = max(1, repeats // 2)
    if "toktalk" in models:
        echo("TokTalk: streaming chunks")
        rows = [toktalk_chunk(small["toktalk"], "small, 0.4-s chunk", repeats)]
        if paper:
            rows.append(toktalk_chunk(TokTalkConfig.paper(context_frames=0, overlap_frames=0), "paper, 10 frames", few))
            rows.append(toktalk_chunk(TokTalkConfig.paper(context_frames=40), "paper, 50 frames", few))
        tables.append(BenchTable("TokTalk: one streaming chunk (Euler steps + CFG)", with_peak(rows, peak)))
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
        tables.append(BenchTable("TIMAR: one streamed 1-s turn (DDIM + CFG)", with_peak(rows, peak)))
    if "freetalk" in models:
        echo("FreeTalk: ATS clip, STM frames")
        rows = [ats_clip(small["ats"], "small", steps=s, repeats=few) for s in (10, 100)]
        if paper:
            rows.append(ats_clip(ATSConfig.paper(), "paper", steps=100, repeats=few))
        tables.append(BenchTable("FreeTalk ATS: DDIM on a 4-s clip", with_peak(rows, peak)))
        rows = [stm_frames(small["stm"], "small", repeats=repeats)]
        if paper:
            rows.append(stm_frames(STMConfig.paper(), "paper", repeats=few))
        tables.append(BenchTable("FreeTalk STM: 25 frames per call on the ~5.9k-vertex face", with_peak(rows, peak)))
    return peak, tables
