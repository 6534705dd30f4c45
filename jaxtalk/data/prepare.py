"""``jaxtalk prepare SRC --out DATA``: every clip read, checked and turned into model inputs once,
written as sharded ArrayRecord files plus a manifest that the grain loader reads.

Layout of ``DATA``::

    manifest.json          source, feature settings and their hash, fps, clips (name, speaker,
                           split, frames, partner, emotion, intensity, where its records are),
                           splits, normalisation statistics, token rate/width, feature widths
    shards/NNNNN.array_record   each clip as consecutive records, each one array as a .npy: first
                           the arrays that are not per frame, then its per-frame arrays cut into
                           chunks of ``chunk_frames`` (25) frames, chunk by chunk
    shards/NNNNN.json      the shard's clip entries (name, content hash, settings hash, sums,
                           first record, array names, chunk count)
    tokenizer.npz          the VQ tokenizer fitted on the training split (``--tokens vq``)
    report.csv             every clip that was skipped: file, reason

A record holds ``motion (T, 56)`` (or ``vertices (T, V, 3)`` + ``template``), ``speech (T, D)``,
``turn_speech (turns*25, D)``, ``landmarks (T, 68, 3)`` (displacements on the built-in face, for
FreeTalk), ``tokens (Tt, W)`` and ``oracle (T, 56)`` where known; T is at 25 fps. The per-frame arrays
(:data:`FRAME_KEYS`) are stored in chunks, one array per record, so that a window reads the arrays it
needs in the chunks it overlaps, not the whole clip: on data larger than the loader's cache every
window is read from disk, and reading and unzipping a clip's whole record (an .npz of every array,
format 1) per window made ATS's loader slower than five times its step.

Incremental and resumable: each shard is written under a temporary name and renamed, then its
``.json`` index (also atomically); a run killed half way keeps every finished shard. A second run
re-reads only clips whose content hash (their files' bytes) or feature settings changed; the
manifest is rewritten at the end of every run.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import io
import json
import os
import re
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from jaxtalk.data.features import SAMPLES_PER_FRAME, TURN_FRAMES, AudioFeatures, parse_audio_features
from jaxtalk.data.sources import BadClip, ClipEntry, RawClip, Source, check_clip, open_source
from jaxtalk.files import atomic_output, atomic_write_text
from jaxtalk.types import AUDIO_SAMPLE_RATE, MOTION_FPS

__all__ = ["PrepareSettings", "PrepareResult", "prepare", "MANIFEST", "REPORT", "FORMAT_VERSION", "FRAME_KEYS",
           "CHUNK_FRAMES", "is_current", "encode_array", "decode_array", "encode_clip", "record_positions", "clip_record"]

MANIFEST = "manifest.json"
REPORT = "report.csv"
SHARDS = "shards"
TOKENIZER = "tokenizer.npz"
# 2: a record per array, per-frame arrays cut in chunks of CHUNK_FRAMES frames (1: an .npz per clip).
FORMAT_VERSION = 2
# The arrays with one row per 25-fps frame, stored in chunks; every other array is stored whole.
FRAME_KEYS = ("motion", "vertices", "oracle", "speech", "landmarks")
# One second: a 50-frame window (ATS) reads 2-3 chunks, a 100-frame one (TokTalk) 4-5, and a clip of
# a few hundred frames is still read in one call of a dozen records.
CHUNK_FRAMES = 25
SPLITS = ("train", "val", "test", "ood")


@dataclasses.dataclass(frozen=True)
class PrepareSettings:
    """What ``prepare`` computes (everything that changes a record is in :meth:`digest`).

    Attributes:
        audio: ``logmel`` (default), ``hubert:PATH`` or ``wav2vec2:PATH`` (kept with ``PATH`` made
            absolute: the manifest and the runs trained on it name the checkpoint from anywhere).
        tokens: ``auto`` (the clips' own token files when the source has them, else ``vq``), ``clip``,
            ``vq`` (a VQ tokenizer fitted on the training split, as SynthTalk's streams are made) or
            ``none``.
        vq_rate, vq_width, vq_codes: the VQ token stream (TokTalk's base stream: 12.5 Hz x 64).
        min_frames: shortest usable clip in 25-fps frames (default one 1-s turn).
        val_fraction, test_fraction: shares of speakers drawn into val / test where the layout
            gives no splits (a layout with train but no val gives val_fraction of its train speakers).
        split_seed: seed of those draws.
        landmarks: compute 68-landmark displacements through the built-in face (FreeTalk's ATS).
    """

    audio: str = "logmel"
    tokens: str = "auto"
    vq_rate: float = 12.5
    vq_width: int = 64
    vq_codes: int = 256
    min_frames: int = TURN_FRAMES
    val_fraction: float = 0.1
    test_fraction: float = 0.1
    split_seed: int = 0
    landmarks: bool = True

    def __post_init__(self) -> None:
        if self.tokens not in ("auto", "clip", "vq", "none"):
            raise ValueError(f"tokens must be auto, clip, vq or none, got {self.tokens!r}")
        if self.min_frames < 1:
            raise ValueError(f"min_frames must be >= 1, got {self.min_frames}")
        if not (0 <= self.val_fraction < 1 and 0 <= self.test_fraction < 1 and self.val_fraction + self.test_fraction < 1):
            raise ValueError(f"val/test fractions must be in [0, 1) with a sum < 1, "
                             f"got {self.val_fraction}, {self.test_fraction}")
        # Frozen: the checked, canonical spelling is set once here.
        object.__setattr__(self, "audio", parse_audio_features(self.audio).spec)

    def digest(self) -> str:
        """Hash of the settings that decide a record or whether a clip is kept (splits are not part of
        a record: they are redrawn on every run). With a speech encoder it also covers the
        checkpoint's files (:meth:`~jaxtalk.data.features.AudioFeatures.fingerprint`): other weights
        in the same folder make other features. Log-mel settings hash as they always have.

        Raises:
            FileNotFoundError: the encoder's checkpoint files are gone.
        """
        keys = ("audio", "tokens", "vq_rate", "vq_width", "vq_codes", "landmarks", "min_frames")
        values = {k: getattr(self, k) for k in keys}
        checkpoint = parse_audio_features(self.audio).fingerprint()
        if checkpoint is not None:
            values["checkpoint"] = checkpoint
        return hashlib.sha1(json.dumps(values, sort_keys=True).encode()).hexdigest()[:16]


@dataclasses.dataclass
class PrepareResult:
    """What :func:`prepare` did.

    Attributes:
        out: the prepared folder.
        clips: clips in the manifest.
        new: clips prepared by this run (the rest were kept from an earlier run).
        skipped: ``(file, reason)`` of every clip left out.
        seconds: wall time.
    """

    out: Path
    clips: int
    new: int
    skipped: list[tuple[str, str]]
    seconds: float


def encode_array(array: np.ndarray) -> bytes:
    """One array as the bytes of a ``.npy`` file: what a record holds."""
    buf = io.BytesIO()
    np.save(buf, np.asarray(array), allow_pickle=False)
    return buf.getvalue()


# The header ``np.save`` writes for a plain array: {'descr': '<f4', 'fortran_order': False, 'shape': (50, 56), }
_NPY_HEADER = re.compile(r"\{'descr': '([<>|=][a-zA-Z][0-9]*)', 'fortran_order': (False|True), 'shape': \(([0-9, ]*)\), \}\s*")


def decode_array(buf: bytes, *, copy: bool = True) -> np.ndarray:
    """The array of a record (:func:`encode_array`), parsed without ``ast``; ``copy=False``: a
    read-only view of ``buf`` (for a caller that copies it anyway).

    NumPy parses the header with ``ast.literal_eval``, and CPython before 3.11.8 / 3.12.1 keeps the
    AST converter's recursion depth per interpreter, not per thread (gh-106905): grain's prefetch
    threads decoding records while another thread parses Python (an import, ``literal_eval``) fail
    with "SystemError: AST constructor recursion depth mismatch". Records only hold plain arrays, so
    their headers are read with a regular expression (anything else falls back to NumPy).
    """
    if buf[:6] == b"\x93NUMPY" and buf[6] in (1, 2, 3):
        size, start = (int.from_bytes(buf[8:10], "little"), 10) if buf[6] == 1 else (int.from_bytes(buf[8:12], "little"), 12)
        m = _NPY_HEADER.fullmatch(buf[start:start + size].decode("latin1"))
        if m is not None:
            dtype = np.dtype(m[1])
            shape = tuple(int(v) for v in m[3].replace(" ", "").split(",") if v)
            flat = np.frombuffer(buf, dtype, count=int(np.prod(shape, dtype=np.int64)), offset=start + size)
            array = flat.reshape(shape, order="F" if m[2] == "True" else "C")
            return array.copy() if copy else array
    return np.lib.format.read_array(io.BytesIO(buf), allow_pickle=False)


def encode_clip(arrays: dict[str, np.ndarray], chunk_frames: int = CHUNK_FRAMES) -> tuple[list[bytes], dict[str, Any]]:
    """A clip's records and their layout (see :func:`record_positions`).

    Returns:
        ``(records, layout)``: one record per array that is not per frame (``layout["head"]``, in
        order), then, chunk by chunk (``layout["chunks"]`` of them), one record per per-frame array
        (``layout["framed"]``, in order) holding its rows ``[k * chunk_frames, (k + 1) * chunk_frames)``.
        An array shorter than the clip has empty rows in its last chunks, so concatenating an
        array's chunks gives it back exactly.
    """
    if chunk_frames < 1:
        raise ValueError(f"chunk_frames must be >= 1, got {chunk_frames}")
    head = [k for k in arrays if k not in FRAME_KEYS]
    framed = [k for k in arrays if k in FRAME_KEYS]
    frames = max((arrays[k].shape[0] for k in framed), default=0)
    chunks = max(-(-frames // chunk_frames), 1)
    records = [encode_array(arrays[k]) for k in head]
    records += [encode_array(arrays[k][c * chunk_frames:(c + 1) * chunk_frames]) for c in range(chunks) for k in framed]
    return records, {"head": head, "framed": framed, "chunks": chunks}


def record_positions(clip: dict[str, Any], keys: Sequence[str], chunks: Sequence[int]) -> list[tuple[str, int, int]]:
    """``(key, chunk, record index)`` of the records holding ``keys`` of a clip entry (its ``index``,
    ``head``, ``framed``): each head key once (chunk -1), each per-frame key in every chunk of
    ``chunks``; keys the clip does not have are left out."""
    head, framed = clip["head"], clip["framed"]
    out = [(k, -1, clip["index"] + head.index(k)) for k in keys if k in head]
    base = clip["index"] + len(head)
    out += [(k, c, base + c * len(framed) + framed.index(k)) for c in chunks for k in keys if k in framed]
    return out


def _to_motion_rate(x: np.ndarray, fps: float) -> np.ndarray:
    if fps == MOTION_FPS:
        return x
    from jaxtalk.audio.framerate import default_num_frames, resample_features

    count = default_num_frames(x.shape[0], fps, MOTION_FPS)
    flat = x.reshape(x.shape[0], -1)
    return np.asarray(resample_features(flat, fps, MOTION_FPS, num_frames=count), np.float32).reshape(count, *x.shape[1:])


def clip_record(raw: RawClip, features: AudioFeatures, *, tokenizer: Any = None, landmarks: bool = True) -> dict[str, np.ndarray]:
    """The prepared arrays of one checked clip (see the module docstring).

    Args:
        raw: a clip that passed :func:`~jaxtalk.data.sources.check_clip`.
        features: the audio front end.
        tokenizer: a ``VQTokenizer`` to encode the audio with (replaces the clip's own tokens), or None.
        landmarks: add landmark displacements (needs ``params``).
    """
    out: dict[str, np.ndarray] = {}
    if raw.params is not None:
        out["motion"] = _to_motion_rate(raw.params.astype(np.float32), raw.fps)
    if raw.vertices is not None:
        out["vertices"] = _to_motion_rate(raw.vertices.astype(np.float32), raw.fps)
        if raw.template is not None:
            out["template"] = raw.template.astype(np.float32)
    if raw.oracle is not None:
        out["oracle"] = _to_motion_rate(raw.oracle.astype(np.float32), raw.fps)
    frames = next((v.shape[0] for k, v in out.items() if k in ("motion", "vertices")), None)
    audio = raw.audio.astype(np.float32)
    if frames is None:  # audio-only clip: as many frames as the audio covers
        frames = max(int(round(audio.size / SAMPLES_PER_FRAME)), 1)
    out["speech"] = features.speech(audio, frames)
    turns = frames // TURN_FRAMES
    if turns:
        out["turn_speech"] = features.turn_speech(
            np.pad(audio, (0, max(turns * TURN_FRAMES * SAMPLES_PER_FRAME - audio.size, 0))), turns)
    if landmarks and "motion" in out:
        from jaxtalk.face import builtin_face
        from jaxtalk.face.motion import landmark_motion, without_head_pose

        out["landmarks"] = landmark_motion(builtin_face(0), without_head_pose(out["motion"]))
    if tokenizer is not None:
        out["tokens"] = np.asarray(tokenizer.encode(audio).embeddings, np.float32)
    elif raw.tokens is not None:
        out["tokens"] = raw.tokens.astype(np.float32)
    return out


def _assign_splits(entries: Sequence[ClipEntry], settings: PrepareSettings) -> dict[str, str]:
    """Split per clip: the layout's where it has one; else speaker-disjoint seeded draws by group."""
    given = {e.name: e.split for e in entries if e.split is not None}
    for name, split in given.items():
        if split not in SPLITS:
            raise ValueError(f"clip {name!r} has split {split!r}; expected one of {', '.join(SPLITS)}")
    rng = np.random.default_rng(settings.split_seed)
    out = dict(given)
    free = sorted({e.split_group for e in entries if e.split is None})
    if free:
        order = [free[i] for in_ in [rng.permutation(len(free))] for i in in_]
        n_val, n_test = int(round(settings.val_fraction * len(order))), int(round(settings.test_fraction * len(order)))
        if len(order) >= 3:
            n_val, n_test = max(n_val, 1 if settings.val_fraction else 0), max(n_test, 1 if settings.test_fraction else 0)
        group_split = {g: ("val" if k < n_val else "test" if k < n_val + n_test else "train") for k, g in enumerate(order)}
        out.update({e.name: group_split[e.split_group] for e in entries if e.split is None})
    if given and "val" not in given.values() and settings.val_fraction:
        # A layout with train but no val: hold out a share of the training groups for validation.
        groups = sorted({e.split_group for e in entries if out[e.name] == "train"})
        take = max(int(round(settings.val_fraction * len(groups))), 1) if len(groups) > 1 else 0
        chosen = {groups[i] for i in rng.permutation(len(groups))[:take]}
        out.update({e.name: "val" for e in entries if out[e.name] == "train" and e.split_group in chosen})
    return out


def _read_checked(entry: ClipEntry, settings: PrepareSettings, names: set[str]) -> RawClip:
    if entry.requires_partner and entry.partner not in names:
        raise BadClip(f"missing partner: conversation side {entry.partner!r} is not in the dataset")
    try:
        raw = entry.read()
    except BadClip:
        raise
    except FileNotFoundError as err:
        raise BadClip(f"missing file: {err}") from None
    except Exception as err:  # noqa: BLE001 - any reader failure is this clip's problem, reported
        raise BadClip(f"unreadable: {type(err).__name__}: {err}") from None
    # DualTalk's audio-only sides are partners, not training clips: motion is optional for them.
    check_clip(raw, min_frames=settings.min_frames, motion_required=not (entry.requires_partner and raw.num_frames == 0))
    return raw


def _existing(shard_dir: Path, digest: str) -> dict[str, dict[str, Any]]:
    """Clip entries of finished shards of this settings digest and format; other shards (another
    digest, or an older format, prepared again) and leftovers removed."""
    kept: dict[str, dict[str, Any]] = {}
    if not shard_dir.is_dir():
        return kept
    indexed = set()
    for index in sorted(shard_dir.glob("[0-9]*.json")):
        info = json.loads(index.read_text())
        shard = index.with_suffix(".array_record")
        if info.get("settings") != digest or info.get("format") != FORMAT_VERSION or not shard.is_file():
            index.unlink()
            shard.unlink(missing_ok=True)
            continue
        indexed.add(shard.name)
        for clip in info["clips"]:
            kept[clip["name"]] = {**clip, "shard": shard.name}
    for leftover in list(shard_dir.glob("*.array_record")) + list(shard_dir.glob(".*")):
        if leftover.name not in indexed:
            leftover.unlink()  # a shard whose index was never written: an interrupted run
    return kept


def _write_shard(shard_dir: Path, number: int, records: list[tuple[dict, tuple[list[bytes], dict]]], digest: str) -> str:
    from array_record.python.array_record_module import ArrayRecordWriter

    name = f"{number:05d}.array_record"
    with atomic_output(shard_dir / name) as tmp:
        # Uncompressed: ArrayRecord's default (zstd) saves only ~25% on float features and doubles the
        # loader's cost of reading a record.
        writer = ArrayRecordWriter(str(tmp), "group_size:1,uncompressed")
        clips, index = [], 0
        for meta, (parts, layout) in records:
            for data in parts:
                writer.write(data)
            clips.append({**meta, **layout, "index": index})
            index += len(parts)
        writer.close()
    atomic_write_text(shard_dir / f"{number:05d}.json",
                      json.dumps({"settings": digest, "format": FORMAT_VERSION, "clips": clips}))
    return name


def _fit_tokenizer(entries: Sequence[ClipEntry], splits: dict[str, str], settings: PrepareSettings,
                   names: set[str], out: Path, digest: str) -> Any:
    """The VQ tokenizer of the training split (reused from ``out`` when its settings match)."""
    from jaxtalk.audio import VQTokenizer

    path = out / TOKENIZER
    tag = out / f"{TOKENIZER}.settings"
    if path.is_file() and tag.is_file() and tag.read_text() == digest:
        return VQTokenizer.load(path)
    piece, pieces, total = 4 * AUDIO_SAMPLE_RATE, [], 0.0
    # The training split's audio; a dataset without one (evaluation only) uses all of its clips.
    use = "train" if "train" in splits.values() else None
    for e in entries:
        if (use is not None and splits.get(e.name) != use) or total >= 600:  # 10 min fit a 256-code book well
            continue
        try:
            audio = _read_checked(e, settings, names).audio
        except BadClip:
            continue
        usable = audio[: audio.size // piece * piece]
        pieces += list(usable.reshape(-1, piece))
        total += usable.size / AUDIO_SAMPLE_RATE
    if not pieces:
        return None
    tok = VQTokenizer.fit(pieces, rate=settings.vq_rate,
                          num_codes=min(settings.vq_codes, len(pieces) * int(4 * settings.vq_rate)),
                          width=settings.vq_width, seed=settings.split_seed)
    tok.save(path)
    atomic_write_text(tag, digest)
    return tok


def is_current(out: str | os.PathLike) -> bool:
    """``out`` holds a finished preparation in this jaxtalk's format (an older one is prepared again:
    ``prepare`` keeps nothing of it but the tokenizer)."""
    try:
        return json.loads((Path(out) / MANIFEST).read_text()).get("format") == FORMAT_VERSION
    except (OSError, ValueError, AttributeError):
        return False


def _is_prepared_folder(out: Path) -> bool:
    """``out`` holds a preparation: jaxtalk's manifest, or shard indices of an interrupted run."""
    return is_current(out) or any((out / SHARDS).glob("[0-9]*.json"))


def claim_prepared_folder(out: Path, src: Source, *, overwrite: bool = False) -> None:
    """Check, before any work, that ``prepare`` may write into ``out``.

    ``out`` may not be the dataset folder itself (its ``tokenizer.npz`` or ``metadata`` could be
    replaced, and a later scan would read the shards). A folder that holds a preparation already
    (a jaxtalk ``manifest.json``, or the ``shards/`` of a run killed before writing it) is
    continued; in any other folder an existing file under one of the names ``prepare`` writes is a
    user's file, kept unless ``overwrite``.

    Raises:
        jaxtalk.files.OutputError: as above, naming the file and the option.
    """
    from jaxtalk.files import Output, OutputError, claim_outputs

    spec = Path(str(src.spec))
    if src.layout != "synthtalk" and spec.is_dir() and out.resolve() == spec.resolve():
        raise OutputError(f"--out {str(out)!r} is the dataset folder itself; prepare into another folder")
    ours = _is_prepared_folder(out)
    names = (MANIFEST, REPORT, TOKENIZER, f"{TOKENIZER}.settings")
    claim_outputs([Output(out / name) for name in names], overwrite=overwrite or ours)


def prepare(
    source: Source | str | os.PathLike,
    out: str | os.PathLike,
    settings: PrepareSettings = PrepareSettings(),
    *,
    strict: bool = False,
    shard_clips: int = 64,
    progress: bool = True,
    echo: Callable[[str], None] = print,
    overwrite: bool = False,
) -> PrepareResult:
    """Prepare a dataset folder (or SynthTalk) into ``out`` (see the module docstring).

    Args:
        source: a :class:`~jaxtalk.data.sources.Source` or what ``open_source`` accepts.
        out: the prepared folder (created; an earlier preparation there is continued).
        settings: features and splits.
        strict: stop at the first bad clip with an error naming it (default: skip and report).
        shard_clips: clips per ArrayRecord shard.
        progress: show a progress bar with clips/s.
        echo: where the summary goes.
        overwrite: let the prepared folder's files replace existing files of the same names in an
            ``out`` that is not a prepared folder (see :func:`claim_prepared_folder`).

    Returns:
        :class:`PrepareResult`.

    Raises:
        BadClip: with ``strict``, the first bad clip (its file and reason).
        ValueError: a source without one usable clip, or bad settings.
        jaxtalk.files.OutputError: ``out`` is the dataset folder itself, or would replace a user's file.
    """
    from tqdm.auto import tqdm

    start = time.perf_counter()
    src = source if isinstance(source, Source) else open_source(source)
    out = Path(out)
    claim_prepared_folder(out, src, overwrite=overwrite)
    shard_dir = out / SHARDS
    shard_dir.mkdir(parents=True, exist_ok=True)
    features = parse_audio_features(settings.audio)
    tokens_mode = settings.tokens
    if tokens_mode == "auto":
        has_tokens = src.layout == "synthtalk" or (src.layout == "generic" and (Path(src.spec) / "tokens.json").is_file())
        tokens_mode = "clip" if has_tokens else "vq"
    digest = hashlib.sha1(f"{settings.digest()}:{tokens_mode}".encode()).hexdigest()[:16]
    splits = _assign_splits(src.entries, settings)
    names = {e.name for e in src.entries}
    done = _existing(shard_dir, digest)
    tokenizer = _fit_tokenizer(src.entries, splits, settings, names, out, digest) if tokens_mode == "vq" else None
    if tokens_mode == "vq" and tokenizer is None:
        # Say first whether the clips are bad at all: a folder of unreadable clips is not a tokenizer problem.
        skipped = []
        for entry in src.entries:
            try:
                _read_checked(entry, settings, names)
            except BadClip as err:
                skipped.append((str(entry.files[0]) if entry.files else entry.name, str(err)))
        _write_report(out, skipped)
        if len(skipped) == len(src.entries):
            raise ValueError(_rejected_message(src, skipped, out))
        raise ValueError(f"no training clip has 4 s of readable audio to fit the VQ tokenizer on ({len(skipped)} of "
                         f"{len(src.entries)} clips rejected, listed in {out / REPORT}); add longer clips, or pass "
                         "--tokens none to prepare without TokTalk tokens")
    if tokens_mode == "clip" and src.tokenizer is not None:
        # The tokenizer that made the clips' tokens: kept so a trained model can tokenise new audio.
        src.tokenizer().save(out / TOKENIZER)

    skipped: list[tuple[str, str]] = []
    buffer: list[tuple[dict, tuple[list[bytes], dict]]] = []
    number = max((int(p.stem) for p in shard_dir.glob("[0-9]*.json")), default=-1) + 1
    new = 0
    good: dict[str, str] = {}  # content hash of every clip that is usable in this run
    fresh: set[str] = set()  # the clips prepared by this run
    bar = tqdm(src.entries, desc="prepare", unit="clip", disable=not progress)
    for entry in bar:
        chash = entry.content_hash()
        if entry.name in done and done[entry.name]["hash"] == chash:
            good[entry.name] = chash
            continue
        where = str(entry.files[0]) if entry.files else entry.name
        try:
            raw = _read_checked(entry, settings, names)
            if tokens_mode == "clip" and raw.tokens is None:
                raise BadClip("no token file (<clip>.tokens.npy) while the dataset's other clips have one")
            arrays = clip_record(raw, features, tokenizer=tokenizer, landmarks=settings.landmarks)
        except BadClip as err:
            if strict:
                raise BadClip(f"{where}: {err}") from None
            skipped.append((where, str(err)))
            continue
        motion = arrays.get("motion")
        meta = {
            "name": entry.name, "hash": chash,
            "frames": int(arrays["speech"].shape[0]), "has_motion": motion is not None,
            "has_vertices": "vertices" in arrays,
            "tokens": int(arrays["tokens"].shape[0]) if "tokens" in arrays else 0,
            "sum": motion.sum(0, dtype=np.float64).tolist() if motion is not None else None,
            "sumsq": np.square(motion, dtype=np.float64).sum(0).tolist() if motion is not None else None,
        }
        buffer.append((meta, encode_clip(arrays)))
        new += 1
        good[entry.name] = chash
        fresh.add(entry.name)
        if len(buffer) >= shard_clips:
            _write_shard(shard_dir, number, buffer, digest)
            number, buffer = number + 1, []
        bar.set_postfix(skipped=len(skipped), refresh=False)
    bar.close()
    if buffer:
        _write_shard(shard_dir, number, buffer, digest)
    new -= _drop_partnerless(src.entries, good, skipped, fresh)
    kept_tokenizer = tokenizer is not None or (tokens_mode == "clip" and src.tokenizer is not None)
    manifest = _write_manifest(out, src, settings, tokens_mode, digest, splits, features, kept_tokenizer, good)
    _write_report(out, skipped)
    n = len(manifest["clips"])
    if n == 0:
        raise ValueError(_rejected_message(src, skipped, out))
    result = PrepareResult(out=out, clips=n, new=new, skipped=skipped, seconds=time.perf_counter() - start)
    counts = {s: len(v) for s, v in manifest["splits"].items() if v}
    echo(f"prepared {n} clips ({new} new, {n - new} kept) in {result.seconds:.1f} s -> {out}; splits {counts}")
    if skipped:
        echo(f"skipped {len(skipped)} bad clip(s), listed in {out / REPORT}:")
        for where, why in skipped[:10]:
            echo(f"  {where}: {why}")
        if len(skipped) > 10:
            echo(f"  ... and {len(skipped) - 10} more")
    return result


def _rejected_message(src: Source, skipped: list[tuple[str, str]], out: Path) -> str:
    """One line for a dataset none of whose clips is usable: how many, the commonest reason, and the
    layout the folder looks like when that explains it."""
    from collections import Counter

    from jaxtalk.data.sources import layout_hint

    if not skipped:
        return f"no usable clip in {src.spec}"
    reason, count = Counter(why for _, why in skipped).most_common(1)[0]
    hint = layout_hint(src.spec) if src.layout != "synthtalk" else None
    return (f"every clip of {src.spec} was rejected ({len(skipped)} read as the {src.layout} layout; {count} of "
            f"them: {reason}; all listed in {out / REPORT})" + (f"; {hint}" if hint else ""))


def _drop_partnerless(entries: Sequence[ClipEntry], good: dict[str, str], skipped: list[tuple[str, str]],
                      fresh: set[str]) -> int:
    """Leave out every conversation side (``requires_partner``) whose partner was skipped as a bad clip.

    Its partner is listed but unusable (e.g. a DualTalk side with motion whose partner has no wav): the
    side is reported as a missing partner, like one whose partner is absent. Repeated until stable
    (a dropped side may be another clip's partner); ``good`` and ``skipped`` are updated in place, and
    ``skipped`` is put back in source order.

    Returns:
        How many of the dropped clips were prepared by this run (``fresh``).
    """
    order = {e.name: k for k, e in enumerate(entries)}
    reasons = {}
    changed = True
    while changed:
        changed = False
        for e in entries:
            if e.requires_partner and e.name in good and e.partner not in good:
                del good[e.name]
                where = str(e.files[0]) if e.files else e.name
                reasons[e.name] = (where, f"missing partner: conversation side {e.partner!r} was skipped as a bad clip")
                changed = True
    if reasons:
        skipped.extend(reasons.values())
        name_of = {(str(e.files[0]) if e.files else e.name): e.name for e in entries}
        skipped.sort(key=lambda row: order.get(name_of.get(row[0]), len(order)))
    return len(fresh & set(reasons))


def _write_manifest(out: Path, src: Source, settings: PrepareSettings, tokens_mode: str, digest: str,
                    splits: dict[str, str], features: AudioFeatures, tokenizer: bool,
                    good: dict[str, str]) -> dict[str, Any]:
    by_name = {e.name: e for e in src.entries}
    shard_dir = out / SHARDS
    shard_names = sorted(p.with_suffix(".array_record").name for p in shard_dir.glob("[0-9]*.json"))
    current = _existing(shard_dir, digest)
    # The newest record of each clip still in the source (an edited clip has an old and a new one).
    clips = []
    for name, meta in sorted(current.items()):
        entry = by_name.get(name)
        # Only a record of the clip's current content: a clip removed from the source, or edited into
        # a bad clip this run (its older record is still on disk), is left out.
        if entry is None or good.get(name) != meta["hash"]:
            continue
        clips.append({
            "name": name, "speaker": entry.speaker, "split": splits[name], "frames": meta["frames"],
            "has_motion": meta["has_motion"], "has_vertices": meta["has_vertices"], "tokens": meta["tokens"],
            "partner": entry.partner, "emotion": entry.emotion, "intensity": entry.intensity,
            "shard": meta["shard"], "index": meta["index"], "head": meta["head"], "framed": meta["framed"],
            "chunks": meta["chunks"], "hash": meta["hash"],
            "sum": meta["sum"], "sumsq": meta["sumsq"],
        })
    present = {c["name"] for c in clips}
    for c in clips:
        if c["partner"] not in present:
            c["partner"] = None
    train = [c for c in clips if c["split"] == "train" and c["has_motion"]]
    stats = None
    if train:
        count = sum(c["frames"] for c in train)
        mean = np.sum([c["sum"] for c in train], axis=0) / count
        var = np.maximum(np.sum([c["sumsq"] for c in train], axis=0) / count - mean**2, 0.0)
        stats = {"motion_mean": mean.tolist(), "motion_std": np.sqrt(var).tolist(), "frames": int(count)}
    sample = _first_record(shard_dir, clips)
    manifest = {
        "format": FORMAT_VERSION,
        "source": {"spec": src.spec, "layout": src.layout},
        "settings": {**dataclasses.asdict(settings), "tokens": tokens_mode},
        "settings_hash": digest,
        "fps": MOTION_FPS,
        "chunk_frames": CHUNK_FRAMES,
        "sample_rate": AUDIO_SAMPLE_RATE,
        "turn_frames": TURN_FRAMES,
        "speech_dim": int(sample["speech"].shape[1]) if "speech" in sample else None,
        "turn_speech_dim": int(sample["turn_speech"].shape[1]) if "turn_speech" in sample else None,
        "token_dim": int(sample["tokens"].shape[1]) if "tokens" in sample else None,
        "token_rate": _token_rate(src, tokens_mode, settings),
        "tokenizer": TOKENIZER if tokenizer else None,
        "shards": [s for s in shard_names if any(c["shard"] == s for c in clips)],
        "clips": [{k: v for k, v in c.items() if k not in ("sum", "sumsq")} for c in clips],
        "splits": {s: [c["name"] for c in clips if c["split"] == s] for s in SPLITS},
        "stats": stats,
    }
    atomic_write_text(out / MANIFEST, json.dumps(manifest, indent=1))
    return manifest


def _token_rate(src: Source, mode: str, settings: PrepareSettings) -> float | None:
    if mode == "vq":
        return float(settings.vq_rate)
    if mode == "clip":
        if src.layout == "synthtalk":
            from jaxtalk.data.synthtalk.corpus import TOKEN_STREAMS

            return float(TOKEN_STREAMS["A"][0])
        return float(json.loads((Path(src.spec) / "tokens.json").read_text())["rate"])
    return None


def _first_record(shard_dir: Path, clips: list[dict]) -> dict[str, np.ndarray]:
    from array_record.python.array_record_module import ArrayRecordReader

    if not clips:
        return {}
    c = clips[0]
    reader = ArrayRecordReader(str(shard_dir / c["shard"]))
    try:  # every array once (the first chunk of the per-frame ones), for its width
        where = record_positions(c, c["head"] + c["framed"], range(1))
        return {k: decode_array(data) for (k, _, _), data in zip(where, reader.read([i for _, _, i in where]))}
    finally:
        reader.close()


def _write_report(out: Path, skipped: list[tuple[str, str]]) -> None:
    buf = io.StringIO()
    writer = csv.writer(buf)
    writer.writerow(["file", "reason"])
    writer.writerows(skipped)
    atomic_write_text(out / REPORT, buf.getvalue())
