"""TokTalk's evaluation protocol (``jaxtalk eval`` on a TokTalk run; :attr:`jaxtalk.runs.ModelSpec.evaluate`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from jaxtalk.metrics.evaluation import EvalSettings, EvalTable, flame_face, method_rows, vertex_metrics

__all__ = ["evaluate"]


def _same_tokenizer(run: Any, data: Any) -> bool:
    """Whether the data's tokens come from the tokenizer the run was trained with (unknown: True)."""
    from jaxtalk.runs import TOKENIZER_FILE

    ours, theirs = (run.run_dir / TOKENIZER_FILE,
                    (data.root / data.manifest["tokenizer"]) if data.manifest.get("tokenizer") else None)
    if not ours.is_file() or theirs is None or not theirs.is_file():
        return True
    from jaxtalk.files import load_npz

    a, b = load_npz(ours), load_npz(theirs)
    return sorted(a) == sorted(b) and all(np.array_equal(a[k], b[k]) for k in a)


def evaluate(run: Any, data: Any, split: str, opts: EvalSettings, echo: Callable[[str], None]) -> tuple[int, list[EvalTable]]:
    """TokTalk on a split of prepared data: every clip with motion and tokens (up to ``max_clips``) streamed
    chunk by chunk in the speaking style of another clip of the same speaker (the run's default style when
    the speaker has none), posed on the built-in face or on FLAME, and scored by :func:`vertex_metrics`
    beside the mean pose, the oracle (where every clip has one) and the data's own jitter.

    Raises:
        ValueError: a split without a clip with motion and tokens, bad step counts.
    """
    import jax

    from jaxtalk.face import builtin_face
    from jaxtalk.metrics import jitter
    from jaxtalk.models import toktalk
    from jaxtalk.models.toktalk.model import frames_for_tokens

    config = run.config
    clips = [i for i in data.split(split) if data.clips[i]["tokens"]]
    if not clips:
        raise ValueError(f"split {split!r} of {data.root} has no clip with motion and tokens")
    chosen = clips[: opts.max_clips]
    by_speaker: dict[str, list[int]] = {}
    for i in data.split(split):
        by_speaker.setdefault(data.clips[i]["speaker"], []).append(i)
    if not _same_tokenizer(run, data):
        echo(f"warning: {data.root}'s tokens come from another tokenizer than the run's; the model reads them as "
             "its own token space")
    face, notes = flame_face(opts.flame) if opts.flame is not None else (builtin_face(0), [])
    for note in notes:
        echo(f"note: {note}")
    template = np.asarray(face.vertices(np.zeros(56, np.float32)))
    s = 4 * config.style_frames
    default_style = np.asarray(run.default_style(), np.float32)[:s]
    norm = run.params.get("norm", {}) if isinstance(run.params, dict) else {}
    mean_pose = np.asarray(norm["mean"] if "mean" in norm else data.motion_stats()["mean"], np.float32)
    key = jax.random.key(opts.seed)
    echo(f"streaming {len(chosen)} {split} clips of {data.root} with TokTalk (step {run.step})")
    step_counts = tuple(opts.sample_steps) or (config.sample_steps,)
    if any(isinstance(n, bool) or not isinstance(n, int) or n < 1 for n in step_counts):
        raise ValueError(f"sample steps must be positive integers, got {step_counts}")
    plural = lambda n: f"{n} step{'s' * (n > 1)}"  # noqa: E731
    variants = [(f"toktalk (streamed, {plural(n)})", "stream", n) for n in step_counts]
    if opts.offline:
        variants += [(f"toktalk (offline, {plural(n)})", "offline", n) for n in step_counts]
    per: dict[str, list[dict[str, float | None]]] = {name: [] for name, _, _ in variants}
    per.update({"mean pose": [], "oracle": [], "ground truth": []})
    frames = []
    for n, i in enumerate(chosen):
        rec = data.record(i, ("motion", "tokens", "oracle"))
        others = [j for j in by_speaker[data.clips[i]["speaker"]] if j != i]
        style = default_style
        if others:
            ref = np.asarray(data.record(others[0], ("motion",))["motion"], np.float32)[:s]
            style = ref if ref.shape[0] >= config.style_min_frames else default_style
        tokens = np.asarray(rec["tokens"], np.float32)[None]
        style_vec = toktalk.encode_style(run.params, config, style[None])
        t = min(frames_for_tokens(tokens.shape[1], config.token_rate, config.fps), rec["motion"].shape[0])
        gt = np.asarray(rec["motion"], np.float32)[:t]
        vg = np.asarray(face.vertices_seq(gt))
        for name, mode, steps in variants:
            if mode == "stream":
                out = toktalk.stream(run.params, config, tokens, style_vec, jax.random.fold_in(key, n),
                                     sample_steps=steps, temperature=opts.temperature)
            else:
                out = toktalk.sample(run.params, config, tokens, style_vec, jax.random.fold_in(key, n),
                                     sample_steps=steps, temperature=opts.temperature)
            pred = np.asarray(out, np.float32)[0][:t]
            scored = vertex_metrics(pred, gt, face, gt_vertices=vg, template=template)
            per[name].append(scored)
        per["mean pose"].append(vertex_metrics(np.broadcast_to(mean_pose, gt.shape).copy(), gt, face, gt_vertices=vg,
                                               template=template))
        if "oracle" in rec:
            oracle = np.asarray(rec["oracle"], np.float32)[:t]
            per["oracle"].append(vertex_metrics(oracle, gt, face, gt_vertices=vg, template=template))
        per["ground truth"].append({**{k: None for k in scored}, "jitter_mm": float(jitter(vg)) * 1e3})
        frames.append(t)
    if len(per["oracle"]) < len(frames):
        per["oracle"] = []  # the oracle row only when every clip has one
    on = "FLAME" if opts.flame is not None else "the built-in face"
    return len(chosen), [EvalTable(f"TokTalk on {split} ({data.root.name}), vertices on {on}", method_rows(per, frames))]
