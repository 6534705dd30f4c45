"""``jaxtalk eval RUN``: a trained run scored on a split of prepared data, next to baselines.

The data is the run's own prepared folder unless ``--data`` names another one (or
``synthtalk:SIZE``); it must carry the features the run was trained on (token width and rate for
TokTalk, the audio front end and its width for TIMAR and ATS), else a ``ValueError`` says which.
Each model is scored the way it is used:

* TokTalk: every clip of the split with motion and tokens (up to ``--max-clips``) is streamed chunk
  by chunk (the live engine, :func:`jaxtalk.models.toktalk.stream`) in the speaking style of another
  clip of the same speaker in the split (the run's default style when the speaker has none), and posed
  on the built-in face (``builtin_face(0)``), or on FLAME with ``--flame FILE`` (its lip and
  upper-face regions come from ``FLAME_masks.pkl`` beside FILE; without it LVE and FDD are left out,
  and MOD always is: FLAME has no mouth-opening vertex pairs). Columns: MSE of the 56-d parameters;
  LVE (mm^2: per frame the max over the lip vertices of the squared error, averaged); MVE (mm, mean
  vertex error); FDD (mm^2, signed upper-face dynamics deviation: positive when the prediction moves
  the upper face less than the truth); MOD (mm, mouth-opening distance); jitter (mm per frame^2, mean
  vertex acceleration).
* TIMAR: every conversation side of the split whose partner is prepared is streamed turn by turn
  (:func:`jaxtalk.models.timar.streaming.stream`, standardised with the run's normaliser; a
  partner without tracked motion is the run's still pose, as in training), and scored with the
  DualTalk benchmark (:func:`jaxtalk.metrics.conversation_metrics`) per group (exp, jaw, pose): FD,
  P-FD, MSE, SID (k-means fit on the ground truth) and rPCC, in the published scaling
  (``PUBLISHED_SCALE``, in each table's title). SID needs 40 frames per side; shorter sides leave it
  out.
* DualTalk baseline (``dualtalk`` runs): the same sides, normaliser and tables as TIMAR, each turn
  predicted from the window of its past turns (as many as the training window holds, less one) and
  the whole current turn (:func:`jaxtalk.models.dualtalk.predict_turns`).
* ATS: landmark displacements (68 landmarks on the built-in face, head pose removed, as ``prepare``
  computes them) are sampled for consecutive training-length windows of each clip (the last one flush
  with the clip's end) and de-standardised with the run's statistics. Columns: LVE (mm^2, the lip
  analogue on the 20 mouth landmarks 48-67), LE (mm, mean landmark error), jitter (mm per frame^2).
* STM: the split's motion (head pose removed) is rendered on each of the run's meshes; STM maps the
  true landmark displacements to vertex displacements, scored against the rendered vertices: MVE
  (mm), LVE (mm^2, the mesh's lip region), jitter (mm per frame^2).

Real voices (``--real-voice FOLDER``, TokTalk and TIMAR): every recording of FOLDER (``.wav``,
``.flac``...; any rate, mono or stereo), each optionally with its speaker's tracked motion beside it
(``STEM.npz`` holding DualTalk's ``pose (T, 6)``, jaw = ``pose[:, 3]``, or jaxtalk's ``params (T, 56)``,
jaw = ``params[:, 50]``, at 25 fps), is streamed through the run as ``jaxtalk stream`` does, and its
predicted jaw opening measured with :func:`jaxtalk.metrics.speech_sync.speech_sync`: against the
tracked jaw at lag 0 and at its best lag (positive: the prediction is late), beside the loudness
follower (the recording's log loudness against the tracked jaw, the baseline a lip-sync model must
beat); against the loudness itself; and the predicted jaw's mean over silent and speech frames (an
energy voice-activity detector). A ``mean`` row averages the recordings (the tracked-jaw columns over
those with tracked motion), and a last row gives the rest jaw: the jaw streamed on 3 s of digital
silence in the same style. Nothing is written beside the recordings.

Baselines: the mean pose, the training mean repeated (what a model that ignores its input scores:
TokTalk's motion standardiser, TIMAR's normaliser, ATS's displacement statistics); ``neutral`` (zero
displacement) for ATS and STM; and, where the records have one (SynthTalk), the generator's oracle, the
deterministic part of the motion (what a perfect model gets: blinks and sway are unpredictable). A
``ground truth`` row gives the data's own jitter. Per-clip metrics are averaged over clips weighted by
their frames (FDD: the plain mean over clips, as ``fdd_batch``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from jaxtalk.checks import check_temperature
from jaxtalk.data.recordings import MAX_LAG, Recording, read_recordings
from jaxtalk.metrics.landmarks import MOUTH_LANDMARKS, landmark_metrics
from jaxtalk.runs import LoadedRun, RunRecord, checkpoint_dir, load_run, model_spec, run_features

__all__ = ["EvalOptions", "EvalTable", "EvalReport", "evaluate_run", "open_eval_data", "check_eval_data",
           "vertex_metrics", "landmark_metrics", "MOUTH_LANDMARKS", "REST_SECONDS"]

# Fixed batch of ATS windows per sampler call (one compiled program for every clip).
_ATS_BATCH = 8
# Frames per STM decoder call (STM decodes frame by frame, so chunks of a fixed size compile once).
_STM_CHUNK = 50


@dataclasses.dataclass(frozen=True)
class EvalOptions:
    """Settings of :func:`evaluate_run`.

    Attributes:
        run_dir: a folder written by ``jaxtalk train`` (any model).
        data: a prepared folder or ``synthtalk:SIZE[:SEED]``; None: the run's own data.
        split: split of the data (``train``, ``val``, ``test``, ``ood``); None: ``test``.
        max_clips: at most this many clips (TokTalk, ATS, STM), conversation sides (TIMAR) or
            recordings (``real_voice``).
        seed: noise seed.
        flame: TokTalk: a FLAME 2020 model file to pose the parameters on instead of the built-in face.
        cache_dir: where ``synthtalk:`` data is prepared.
        best: evaluate the best-validated checkpoint (``checkpoint/best``) instead of the latest.
        sample_steps: TokTalk: Euler step counts, one streamed row each (empty: the config's).
        offline: TokTalk: also sample each clip offline in one pass (full attention), per step count.
        temperature: scale of the sampler's noise (TokTalk: the starting noise, None: the config's;
            TIMAR: MAR's temperature, None: 1). Refused for the models that take none.
        real_voice: TokTalk, TIMAR: a folder of real recordings (and tracked motion) to measure the
            predicted jaw on instead of prepared data (see the module docstring); TokTalk's
            ``sample_steps`` give one table each.
    """

    run_dir: Path
    data: str | None = None
    split: str | None = None
    max_clips: int = 8
    seed: int = 0
    flame: Path | None = None
    cache_dir: Path = Path(".cache/prepared")
    best: bool = False
    sample_steps: tuple[int, ...] = ()
    offline: bool = False
    temperature: float | None = None
    real_voice: Path | None = None


@dataclasses.dataclass
class EvalTable:
    """One printed table: a title and its rows (dicts with the same keys; None prints as ``-``)."""

    title: str
    rows: list[dict[str, Any]]


@dataclasses.dataclass
class EvalReport:
    """What :func:`evaluate_run` measured.

    Attributes:
        model: the run's model.
        run_dir: the run folder.
        step: the checkpoint step evaluated.
        data: the prepared folder evaluated on (``real_voice``: the recordings' folder).
        split: its split (None for real voices).
        items: clips (TokTalk, ATS, STM), conversation sides (TIMAR) or recordings evaluated.
        tables: the result tables.
    """

    model: str
    run_dir: str
    step: int
    data: str
    split: str | None
    items: int
    tables: list[EvalTable]

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


# ------------------------------------------------------------------------------------------- metrics


def vertex_metrics(pred: np.ndarray, gt: np.ndarray, face: Any, *, gt_vertices: np.ndarray | None = None,
                   template: np.ndarray | None = None) -> dict[str, float | None]:
    """TokTalk's columns for one ``(T, 56)`` track posed on ``face`` (see the module docstring).

    Args:
        pred: ``(T, 56)`` prediction.
        gt: ``(T, 56)`` ground truth.
        face: the face model; a metric whose region (``lips``; ``upper_face``; ``mouth_upper`` and
            ``mouth_lower``) it lacks is None.
        gt_vertices: ``face.vertices_seq(gt)`` when already computed.
        template: the neutral face ``(V, 3)`` (default: ``face`` at zero parameters).

    Returns:
        ``{"MSE", "LVE_mm2", "MVE_mm", "FDD_mm2", "MOD_mm", "jitter_mm"}``.

    Raises:
        ValueError: shapes differ.
    """
    from jaxtalk.metrics import fdd, jitter, lve, mod, mve

    if pred.shape != gt.shape:
        raise ValueError(f"prediction {pred.shape} and ground truth {gt.shape} differ in shape")
    regions = face.regions
    vp = np.asarray(face.vertices_seq(pred))
    vg = np.asarray(face.vertices_seq(gt)) if gt_vertices is None else gt_vertices
    if template is None:
        template = np.asarray(face.vertices(np.zeros(pred.shape[1], np.float32)))
    has_mouth = "mouth_upper" in regions and "mouth_lower" in regions
    return {
        "MSE": float(np.mean((pred - gt) ** 2)),
        "LVE_mm2": float(lve(vp, vg, regions["lips"])) * 1e6 if "lips" in regions else None,
        "MVE_mm": float(mve(vp, vg)) * 1e3,
        "FDD_mm2": float(fdd(vp, vg, template, regions["upper_face"])) * 1e6 if "upper_face" in regions else None,
        "MOD_mm": float(mod(vp, vg, regions["mouth_upper"], regions["mouth_lower"])) * 1e3 if has_mouth else None,
        "jitter_mm": float(jitter(vp)) * 1e3,
    }


def _average(per_item: Sequence[dict[str, float | None]], frames: Sequence[int],
             plain: tuple[str, ...] = ("FDD_mm2",)) -> dict[str, float | None]:
    """Frame-weighted means of per-clip metrics (keys in ``plain``: unweighted); None stays None."""
    weights = np.asarray(frames, np.float64)
    out: dict[str, float | None] = {}
    for key in per_item[0]:
        values = [m[key] for m in per_item]
        if any(v is None for v in values):
            out[key] = None
        elif key in plain:
            out[key] = float(np.mean(values))
        else:
            out[key] = float(np.sum(weights * np.asarray(values)) / weights.sum())
    return out


# ---------------------------------------------------------------------------------------------- data


def open_eval_data(record: RunRecord, spec: str | Path | None, cache_dir: str | Path = ".cache/prepared",
                   features: str | None = None) -> Any:
    """The prepared data to evaluate on: ``spec``, or the run's own (its folder, else its spec again).

    Args:
        record: the run's ``run.json``.
        spec: a prepared folder or ``synthtalk:SIZE[:SEED]``; None: the run's own data.
        cache_dir: where ``synthtalk:`` data is prepared.
        features: the run's speech front end (its ``features.json``'s ``audio``), with which
            ``synthtalk:`` data is prepared for a model that reads speech features (a folder keeps its
            own: :func:`check_eval_data` says when it is not the run's).

    Raises:
        FileNotFoundError: a folder that is not prepared.
    """
    from jaxtalk.data.loader import PreparedData, open_data
    from jaxtalk.data.prepare import MANIFEST

    spec = str(spec) if spec is not None else None
    path = record.data.get("path")
    if spec is None and path and (Path(path) / MANIFEST).is_file():
        return PreparedData(path)
    spec = spec if spec is not None else record.data["spec"]
    synthtalk_features = features if spec.startswith("synthtalk:") and model_spec(record.model).reads_speech else None
    return open_data(spec, cache_dir=cache_dir, progress=False, features=synthtalk_features)


def check_eval_data(record: RunRecord, features: dict[str, Any], data: Any) -> None:
    """Raise ValueError unless ``data`` carries the inputs the run was trained on.

    TokTalk: token width and rate; TIMAR and the DualTalk baseline: per-turn speech of the run's audio front
    end and width; ATS: per-frame speech likewise. Every model: 56-d motion.
    """
    m, cfg = data.manifest, record.config
    where = f"{data.root} (prepared from {m['source']['spec']})"
    if m.get("stats") is None:
        raise ValueError(f"{where} has no training split with motion; prepare it from data with 56-d motion")
    if record.model == "toktalk":
        if not m.get("token_dim"):
            raise ValueError(f"{where} has no token stream, the TokTalk run needs tokens of width {cfg['speech_dim']}")
        if m["token_dim"] != cfg["speech_dim"] or float(m["token_rate"]) != float(cfg["token_rate"]):
            raise ValueError(f"{where} has tokens of width {m['token_dim']} at {m['token_rate']:g} Hz, the run was "
                             f"trained on width {cfg['speech_dim']} at {cfg['token_rate']:g} Hz")
        return
    for field, key in model_spec(record.model).data_fields:  # the speech feature width of TIMAR, DualTalk, ATS
        width = cfg[field]
        if m["settings"]["audio"] != features.get("audio") or m.get(key) != width:
            raise ValueError(f"{where} has {m.get(key)}-d {m['settings']['audio']!r} speech features, the run was "
                             f"trained on {width}-d {features.get('audio')!r} features; prepare it with "
                             f"--features {features.get('audio')}")


def _same_tokenizer(run: LoadedRun, data: Any) -> bool:
    """Whether the data's tokens come from the tokenizer the run was trained with (unknown: True)."""
    from jaxtalk.runs import TOKENIZER_FILE

    ours, theirs = (run.run_dir / TOKENIZER_FILE,
                    (data.root / data.manifest["tokenizer"]) if data.manifest.get("tokenizer") else None)
    if not ours.is_file() or theirs is None or not theirs.is_file():
        return True
    from jaxtalk.files import load_npz

    a, b = load_npz(ours), load_npz(theirs)
    return sorted(a) == sorted(b) and all(np.array_equal(a[k], b[k]) for k in a)


def _flame_face(path: Path) -> tuple[Any, list[str]]:
    """FLAME posed for the metrics, with regions from ``FLAME_masks.pkl`` beside it; notes to print."""
    import pickle

    from jaxtalk.face import load_flame
    from jaxtalk.face.flame import _NoChumpyUnpickler

    masks_path = Path(path).with_name("FLAME_masks.pkl")
    regions: dict[str, np.ndarray] = {}
    if masks_path.is_file():
        with open(masks_path, "rb") as fh:
            try:
                masks = _NoChumpyUnpickler(fh, encoding="latin1").load()
            except (pickle.UnpicklingError, EOFError) as err:
                raise ValueError(f"{masks_path} is not a readable FLAME mask pickle: {err}") from None
        if "lips" in masks:
            regions["lips"] = np.asarray(masks["lips"])
        upper = [np.asarray(masks[k]).reshape(-1) for k in ("forehead", "eye_region") if k in masks]
        if upper:
            regions["upper_face"] = np.unique(np.concatenate(upper))
    face = load_flame(path, regions=regions)
    notes = ["FLAME has no mouth-opening vertex pairs: MOD left out"]
    if not regions:
        notes.append(f"no FLAME_masks.pkl beside {path}: LVE and FDD (lip and upper-face regions) left out")
    return face, notes


# -------------------------------------------------------------------------------------------- models


def _rows(per: dict[str, list[dict[str, float | None]]], frames: list[int], *, lead: dict[str, Any] | None = None,
          count: str = "clips") -> list[dict[str, Any]]:
    """One row per method with items: ``lead`` columns, method, item count, frames, the averages."""
    return [{**(lead or {}), "method": name, count: len(items), "frames": int(sum(frames)), **_average(items, frames)}
            for name, items in per.items() if items]


def _eval_toktalk(
    run: LoadedRun, data: Any, split: str, opts: EvalOptions, echo: Callable[[str], None]
) -> tuple[int, list[EvalTable]]:
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
    face, notes = _flame_face(opts.flame) if opts.flame is not None else (builtin_face(0), [])
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
    return len(chosen), [EvalTable(f"TokTalk on {split} ({data.root.name}), vertices on {on}", _rows(per, frames))]


_GROUP_COLUMNS = ("FD", "P-FD", "MSE", "SID", "rPCC")


def _eval_timar(
    run: LoadedRun, data: Any, split: str, opts: EvalOptions, echo: Callable[[str], None]
) -> tuple[int, list[EvalTable]]:
    import jax

    from jaxtalk.data.batching import fit_length
    from jaxtalk.metrics import CONVERSATION_GROUPS, PUBLISHED_SCALE, SID_CLUSTERS, conversation_metrics
    from jaxtalk.models.timar.data import Normalizer
    from jaxtalk.data.conversation import side_streams
    from jaxtalk.models.timar.recipe import agent_sides
    from jaxtalk.models.timar.streaming import stream

    # The DualTalk baseline is scored on the same sides, normaliser and context, predicting each turn
    # from a window of its past turns and the whole current turn instead of streaming.
    baseline = run.record.model == "dualtalk"
    title = "DualTalk baseline" if baseline else "TIMAR"
    config, extra = run.config, run.record.extra
    sides = agent_sides(data, split)
    if not sides:
        raise ValueError(f"split {split!r} of {data.root} has no conversation side (a clip with motion whose "
                         "partner's clip is prepared)")
    norm = Normalizer.from_dict(extra["normalizer"])
    still = np.asarray(extra.get("still", norm.motion_mean), np.float32)
    context = max(extra.get("num_turns", config.max_turns) - 1, 0)
    f = config.frames_per_turn
    key = jax.random.key(opts.seed)
    chosen = sides[: opts.max_clips]
    echo(f"{'predicting' if baseline else 'streaming'} {len(chosen)} {split} conversation sides of {data.root} "
         f"with {title} (step {run.step})")
    preds, gts, partners, oracles, still_partners, padded_frames = [], [], [], [], 0, 0
    for n, (i, j) in enumerate(chosen):
        # Scored over the agent's whole side (as far as the partner's motion goes); the model predicts
        # whole turns, and the frames after the last whole one repeat its last prediction (the paper's
        # protocol, TIMAR Sec. 4.4).
        side = side_streams(data, i, j, norm, still, f)
        if side is None:
            continue
        still_partners += side.still_partner
        padded_frames += side.padded_frames
        if baseline:
            from jaxtalk.models.dualtalk import predict_turns

            out = predict_turns(run.params, config, *side.streams, context=context)
        else:
            out = stream(run.params, config, *side.streams, jax.random.fold_in(key, n), context=context,
                         temperature=opts.temperature)
        total = side.truth.shape[0]
        preds.append(fit_length(norm.unmotion(np.asarray(out)[0]), total))
        gts.append(side.truth)
        partners.append(side.partner)
        oracles.append(side.oracle)
    if not preds:
        raise ValueError(f"split {split!r} of {data.root} has no conversation side of a whole {f}-frame turn")
    if padded_frames:
        echo(f"note: {padded_frames} frames after the sides' last whole {f}-frame turns repeat the last prediction "
             "(TIMAR's protocol)")
    if still_partners:
        echo(f"note: {still_partners} of {len(preds)} partners have no tracked motion; P-FD and rPCC use the run's "
             "still pose for them (as training did)")
    with_sid = min(g.shape[0] for g in gts) >= max(SID_CLUSTERS.values())
    if not with_sid:
        echo(f"note: a side is shorter than {max(SID_CLUSTERS.values())} frames: SID left out")
    label = "dualtalk (turn windows)" if baseline else "timar (streamed)"
    methods = {label: preds, "mean pose": [np.broadcast_to(norm.motion_mean, g.shape).astype(np.float32)
                                                        for g in gts]}
    if all(o is not None for o in oracles):
        methods["oracle"] = oracles
    scores = {name: conversation_metrics(list(p), gts, partners, scaled=True,
                                         sid_convention="fit_gt" if with_sid else None)
              for name, p in methods.items()}
    frames = int(sum(g.shape[0] for g in gts))
    tables = []
    for group in CONVERSATION_GROUPS:
        rows = []
        for name, m in scores.items():
            row: dict[str, Any] = {"method": name, "sides": len(gts), "frames": frames}
            for col in _GROUP_COLUMNS:
                row[col] = m.get(f"SID_fit_gt_{group}") if col == "SID" else m[f"{col}_{group}"]
            rows.append(row)
        scaling = ", ".join(f"{col} x{PUBLISHED_SCALE[f'{col}_{group}']:g}" for col in _GROUP_COLUMNS
                            if f"{col}_{group}" in PUBLISHED_SCALE)
        tables.append(EvalTable(f"{title} on {split} ({data.root.name}), {group}"
                                f"{' (' + scaling + ')' if scaling else ''}", rows))
    return len(gts), tables


def _eval_ats(
    run: LoadedRun, data: Any, split: str, opts: EvalOptions, echo: Callable[[str], None]
) -> tuple[int, list[EvalTable]]:
    import jax

    from jaxtalk.face import builtin_face
    from jaxtalk.data.batching import window_starts
    from jaxtalk.face.motion import landmark_motion, without_head_pose
    from jaxtalk.models.freetalk.data import DisplacementStats
    from jaxtalk.models.freetalk.emotions import NEUTRAL, emotion_ids
    from jaxtalk.models.freetalk.fit import FittedATS, sample_displacements

    extra = run.record.extra
    stats = DisplacementStats(mean=np.asarray(extra["stats"]["mean"], np.float32),
                              std=np.asarray(extra["stats"]["std"], np.float32))
    # A run trained on whole clips (window 0) is scored on whole clips, sampled one at a time (each up to
    # max_frames long: a longer clip in max_frames pieces); a windowed run on windows of its length.
    whole = int(extra["window"]) == 0
    window = run.config.max_frames if whole else int(extra["window"])
    clips = [i for i in data.split(split) if whole or data.clips[i]["frames"] >= window]
    if not clips:
        raise ValueError(f"split {split!r} of {data.root} has no clip of at least {window} frames (the run's window)")
    chosen = clips[: opts.max_clips]
    fitted = FittedATS(run.config, run.params, stats, [])
    face = builtin_face(0)
    recs, items = [], []  # items: (record index, start)
    for n, i in enumerate(chosen):
        rec = data.record(i, ("landmarks", "speech", "oracle"))
        if "landmarks" not in rec:
            raise ValueError(f"{data.root} has no landmark displacements (prepared without --landmarks)")
        if "oracle" in rec:
            rec["oracle_landmarks"] = landmark_motion(face, without_head_pose(rec.pop("oracle")))
        recs.append(rec)
        frames = rec["landmarks"].shape[0]
        items += ([(n, st) for st in range(0, frames, window)] if whole
                  else [(n, st) for st in window_starts(frames, window, window, pad_short=False)])
    lengths = [min(window, recs[n]["landmarks"].shape[0] - st, recs[n]["speech"].shape[0] - st) for n, st in items]
    echo(f"sampling {len(items)} {'whole clips (at most ' if whole else 'windows of '}{window} frames"
         f"{')' if whole else ''} from {len(chosen)} {split} clips of {data.root} with ATS (step {run.step})")
    key = jax.random.key(opts.seed)
    preds = []
    per_call = 1 if whole else _ATS_BATCH  # whole clips differ in length: one call each
    for b in range(0, len(items), per_call):
        batch = items[b:b + per_call]
        batch = batch + [batch[-1]] * (per_call - len(batch))  # one compiled shape
        audio = np.stack([recs[n]["speech"][st:st + lengths[b]] for n, st in batch]).astype(np.float32)
        emotion = np.concatenate([emotion_ids(data.clips[chosen[n]]["emotion"] or NEUTRAL, run.config.emotions)
                                  for n, _ in batch])
        intensity = np.asarray([data.clips[chosen[n]]["intensity"] if data.clips[chosen[n]]["intensity"] is not None
                                else 1.0 for n, _ in batch], np.float32)
        out = sample_displacements(fitted, audio, emotion, intensity, jax.random.fold_in(key, b))
        preds += list(np.asarray(out, np.float32)[: min(per_call, len(items) - b)])
    per: dict[str, list[dict[str, float | None]]] = {"ats (sampled)": [], "mean pose": [], "neutral": [], "oracle": [],
                                                     "ground truth": []}
    with_oracle = all("oracle_landmarks" in r for r in recs)
    for (n, st), pred, length in zip(items, preds, lengths):
        gt = recs[n]["landmarks"][st:st + length].astype(np.float32)
        per["ats (sampled)"].append(landmark_metrics(pred, gt))
        per["mean pose"].append(landmark_metrics(np.broadcast_to(stats.mean, gt.shape).copy(), gt))
        per["neutral"].append(landmark_metrics(np.zeros_like(gt), gt))
        if with_oracle:
            per["oracle"].append(landmark_metrics(recs[n]["oracle_landmarks"][st:st + length], gt))
        per["ground truth"].append({"LVE_mm2": None, "LE_mm": None, "jitter_mm": landmark_metrics(gt, gt)["jitter_mm"]})
    rows = _rows(per, lengths, count="windows")
    return len(chosen), [EvalTable(f"ATS on {split} ({data.root.name}, {len(chosen)} clips), 68 landmarks on the "
                                   "built-in face (head pose removed); LVE over the mouth landmarks 48-67", rows)]


def _eval_stm(
    run: LoadedRun, data: Any, split: str, opts: EvalOptions, echo: Callable[[str], None]
) -> tuple[int, list[EvalTable]]:
    from jaxtalk.metrics import jitter, lve, mve
    from jaxtalk.models.freetalk import stm
    from jaxtalk.models.freetalk.data import face_mesh, without_head_pose

    config, extra = run.config, run.record.extra
    clips = data.split(split)
    if not clips:
        raise ValueError(f"split {split!r} of {data.root} has no clip with motion")
    chosen = clips[: opts.max_clips]
    motions = [without_head_pose(np.asarray(data.record(i, ("motion",))["motion"], np.float32)) for i in chosen]
    frames = [m.shape[0] for m in motions]
    echo(f"mapping the true landmarks of {len(chosen)} {split} clips of {data.root} onto "
         f"{len(extra['meshes'])} meshes with STM (step {run.step})")
    rows = []
    for identity, kind in extra["meshes"]:
        fm = face_mesh(int(identity), kind, resolution=extra.get("resolution", "low"))
        mesh = stm.prepare_mesh(fm.vertices, fm.faces, config)
        features = stm.stm_mesh_features(run.params, config, mesh)
        lips = fm.region("lips")
        per: dict[str, list[dict[str, float | None]]] = {"stm": [], "neutral": [], "ground truth": []}
        for motion in motions:
            lms, verts = fm.motion(motion)
            t = lms.shape[0]
            pad = -t % _STM_CHUNK
            padded = np.concatenate([lms, np.zeros((pad, *lms.shape[1:]), np.float32)])
            pred = np.concatenate([np.asarray(stm.stm_decode(run.params, config, features,
                                                             padded[c:c + _STM_CHUNK], mesh))
                                   for c in range(0, t + pad, _STM_CHUNK)])[:t]
            for name, x in (("stm", pred), ("neutral", np.zeros_like(verts))):
                per[name].append({"MVE_mm": float(mve(x, verts)) * 1e3, "LVE_mm2": float(lve(x, verts, lips)) * 1e6,
                                  "jitter_mm": float(jitter(x)) * 1e3})
            per["ground truth"].append({"MVE_mm": None, "LVE_mm2": None, "jitter_mm": float(jitter(verts)) * 1e3})
        rows += _rows(per, frames, lead={"mesh": f"{fm.name} ({fm.vertices.shape[0]} v)"})
    return len(chosen), [EvalTable(f"STM on {split} ({data.root.name}): the true landmarks mapped to each training "
                                   "mesh (head pose removed)", rows)]


# ------------------------------------------------------------------------------------- real voices

# Seconds of digital silence streamed for the rest jaw (a TIMAR run: whole turns, at least this long).
REST_SECONDS = 3.0
_REAL_VOICE_MODELS = ("toktalk", "timar")


def _turn_frames(record: RunRecord) -> int:
    """Frames a run animates at a time at the least: a TIMAR turn, else one frame."""
    return int(record.config["frames_per_turn"]) if record.model == "timar" else 1


def _eval_real_voices(run: LoadedRun, recordings: list[Recording], opts: EvalOptions,
                      echo: Callable[[str], None]) -> tuple[int, list[EvalTable]]:
    from jaxtalk.commands.inference import SampleOptions, stream_audio
    from jaxtalk.data.recordings import mean_row, recording_sync, sync_row
    from jaxtalk.layout import JAW_OPEN_INDEX
    from jaxtalk.metrics.speech_sync import style_rest_jaw
    from jaxtalk.types import AUDIO_SAMPLE_RATE, MOTION_FPS

    model, turn = run.record.model, _turn_frames(run.record)
    if len(recordings) > opts.max_clips:
        echo(f"note: the first {opts.max_clips} of {len(recordings)} recordings (--max-clips)")
        recordings = recordings[: opts.max_clips]
    tracked = sum(r.tracked_jaw is not None for r in recordings)
    title = "TokTalk" if model == "toktalk" else "TIMAR"
    echo(f"streaming {len(recordings)} recordings of {opts.real_voice} ({tracked} with tracked motion) with "
         f"{title} (step {run.step})")
    rest_frames = -(-int(REST_SECONDS * MOTION_FPS) // turn) * turn
    silence = np.zeros(rest_frames * AUDIO_SAMPLE_RATE // MOTION_FPS, np.float32)
    silent = Recording(f"digital silence ({silence.shape[0] / AUDIO_SAMPLE_RATE:g} s)", Path(opts.real_voice),
                       silence, None, None)
    quiet = lambda line: None  # noqa: E731  (per-chunk times: `jaxtalk stream` prints them)
    style_note = ""
    if model == "toktalk":  # streamed in the run's default style: where its mouth rests is the target in silence
        style_rest = style_rest_jaw(np.asarray(run.default_style())[:, JAW_OPEN_INDEX])
        style_note = f"; the style clip rests at {style_rest:.3f} rad"

    variants = [(n, f", {n} step{'s' * (n > 1)}") for n in opts.sample_steps] or [(None, "")]
    tables = []
    for steps, label in variants:
        sample = SampleOptions(run_dir=opts.run_dir, input=Path(opts.real_voice), sample_steps=steps,
                               temperature=opts.temperature, seed=opts.seed, best=opts.best)
        rows = []
        for rec in recordings:
            pred = stream_audio(run, rec.audio, dataclasses.replace(sample, input=rec.path), echo=quiet)
            rows.append(sync_row(rec.name, "no" if rec.tracked_jaw is None else "yes", recording_sync(rec, pred)))
            r = rows[-1]
            echo(f"  {rec.name}: {r['frames']} frames" + (f", corr {r['corr']:.3f} (loudness follower "
                                                          f"{r['loudness_corr']:.3f})" if r["corr"] is not None else ""))
        rest = stream_audio(run, silence, sample, echo=quiet)
        rest_row = sync_row(silent.name, None, recording_sync(silent, rest))
        tables.append(EvalTable(f"{title} on real voices ({Path(opts.real_voice).name}{label}): predicted jaw "
                                "opening (rad) vs the tracked jaw and the loudness; lags in frames, positive = late"
                                + style_note, [*rows, mean_row(rows), rest_row]))
    return len(recordings), tables


_EVALUATORS = {"toktalk": _eval_toktalk, "timar": _eval_timar, "dualtalk": _eval_timar, "ats": _eval_ats,
               "stm": _eval_stm}


def evaluate_run(opts: EvalOptions, *, echo: Callable[[str], None] = print) -> EvalReport:
    """Score a trained run on a split of prepared data (see the module docstring).

    Args:
        opts: settings.
        echo: where progress lines and notes go.

    Returns:
        :class:`EvalReport` with the tables.

    Raises:
        FileNotFoundError: not a run, no checkpoint (not trained yet), a data folder that is not
            prepared, a missing ``--flame`` file.
        ValueError: an unknown split, a split without clips the model can use, ``max_clips < 1``,
            data whose features differ from the run's, ``--flame`` for a model other than TokTalk;
            with ``real_voice``: a run without a jaw (ATS, STM, the DualTalk baseline), options of
            prepared data, a bad folder or recording (:func:`jaxtalk.data.recordings.read_recordings`).
    """
    record = RunRecord.load(opts.run_dir)
    if record.model not in _EVALUATORS:
        raise ValueError(f"{opts.run_dir} is a {record.model!r} run; eval covers {', '.join(_EVALUATORS)}")
    if opts.max_clips < 1:
        raise ValueError(f"--max-clips must be >= 1, got {opts.max_clips}")
    if opts.real_voice is not None:
        if record.model not in _REAL_VOICE_MODELS:
            article = "an" if record.model[0] in "aeiou" else "a"
            raise ValueError(f"--real-voice streams recordings through toktalk and timar runs (their output has a "
                             f"jaw); {opts.run_dir} is {article} {record.model} run")
        given = [flag for flag, value in (("--data", opts.data), ("--split", opts.split), ("--flame", opts.flame),
                                          ("--offline", opts.offline or None)) if value is not None]
        if given:
            raise ValueError(f"{', '.join(given)}: not with --real-voice, which measures the recordings of "
                             f"{opts.real_voice}, not prepared data")
        if opts.sample_steps and record.model != "toktalk":
            raise ValueError("--sample-steps gives TokTalk one table per step count; a timar run streams with its own")
    if opts.flame is not None:
        if record.model != "toktalk":
            raise ValueError(f"--flame poses TokTalk's parameters on FLAME; {opts.run_dir} is a {record.model} run")
        if not Path(opts.flame).is_file():
            raise FileNotFoundError(f"FLAME model file not found: {str(opts.flame)!r}")
    if opts.temperature is not None:
        if record.model not in ("toktalk", "timar"):
            raise ValueError(f"--temperature scales TokTalk's and TIMAR's sampler noise; {opts.run_dir} is a "
                             f"{record.model} run")
        check_temperature(opts.temperature, name="--temperature")
    from jaxtalk.train import latest_checkpoint_step

    split = opts.split or "test"
    if opts.real_voice is None:
        data = open_eval_data(record, opts.data, opts.cache_dir, run_features(opts.run_dir).get("audio"))
        data.split(split)  # an unknown split: ValueError naming the known ones
    else:  # a bad folder or file is refused before the run is loaded
        recordings = read_recordings(opts.real_voice, min_frames=max(MAX_LAG + 3, _turn_frames(record)), echo=echo)
    if latest_checkpoint_step(checkpoint_dir(opts.run_dir)) is None:
        raise FileNotFoundError(f"{opts.run_dir} is not trained yet (no checkpoint in {checkpoint_dir(opts.run_dir)}); "
                                "train it with `jaxtalk train`")
    run = load_run(opts.run_dir, best=opts.best)
    if opts.real_voice is not None:
        items, tables = _eval_real_voices(run, recordings, opts, echo)
        return EvalReport(model=record.model, run_dir=str(opts.run_dir), step=run.step, data=str(opts.real_voice),
                          split=None, items=items, tables=tables)
    check_eval_data(record, run.features(), data)
    items, tables = _EVALUATORS[record.model](run, data, split, opts, echo)
    return EvalReport(model=record.model, run_dir=str(opts.run_dir), step=run.step, data=str(data.root),
                      split=split, items=items, tables=tables)
