"""Readers for published talking-head dataset layouts, all returning one ``MotionClip`` dataclass.

Supported layouts:

* **DualTalk** (``read_dualtalk``): one ``.npz`` per speaker and clip with tracked FLAME parameters,
  ``exp (T, 50)`` and ``pose (T, 6)`` (``pose[:, :3]`` global/neck rotation, ``pose[:, 3:]`` jaw,
  axis-angle), 25 fps, and the speaker's 16 kHz ``.wav`` beside it with the same stem. The clip is
  mapped to jaxtalk's 56-d layout ``[exp 50 | jaw 3 | neck 3] = concat(exp, pose[:, 3:], pose[:, :3])``.
  The conversation partner's audio (``..._speaker1`` <-> ``..._speaker2``) is found when present.
* **VOCASET** (``read_vocaset``), in the per-sequence layout used by FaceFormer/CodeTalker::

      root/vertices_npy/<subject>_<sentence>.npy   (T, V*3) or (T, V, 3) float vertices, 60 fps
      root/wav/<subject>_<sentence>.wav             the sentence's audio
      root/templates.pkl                            {subject: (V, 3) neutral template} (pickle)

  e.g. ``FaceTalk_170725_00137_TA_sentence01.npy`` (subject = stem up to the last ``_``). Templates
  may also be an ``.npz`` with one ``(V, 3)`` array per subject (no pickle). Sequences can be
  resampled to 25 fps on load (linear interpolation of vertex positions).
* **Generic npz** (``read_npz`` / ``save_npz``): ``fps`` (scalar, required) and at least one of
  ``params (T, 56)``, ``vertices (T, V, 3)``, ``features (T, D)``; optional ``template (V, 3)``,
  ``audio (samples,)`` with ``sample_rate``, or ``audio_path`` (relative to the npz's folder), ``name``.

Audio is loaded through ``jaxtalk.audio.load_audio`` (mono, 16 kHz); silent tracks are accepted
(a listener's channel can be silent).

Every ``.npz`` / ``.npy`` a user hands jaxtalk (these layouts, a command's motion, tokens, landmarks or
faces) is read by :func:`jaxtalk.files.load_npz` / :func:`~jaxtalk.files.load_npy`: never unpickled,
and whatever is wrong with a file (not a zip archive, not a NumPy file, object arrays, damage) is one
line naming it.
"""

from __future__ import annotations

import dataclasses
import os
import pickle
from pathlib import Path

import numpy as np
from jaxtyping import Float

from jaxtalk.files import load_npy, load_npz
from jaxtalk.types import AUDIO_SAMPLE_RATE, EXP_DIM, MOTION_FPS, PARAM_DIM

__all__ = [
    "MotionClip",
    "read_dualtalk",
    "read_vocaset",
    "read_vocaset_templates",
    "read_npz",
    "save_npz",
    "read_clip",
    "dualtalk_to_params56",
]

DUALTALK_FPS = 25.0
VOCASET_FPS = 60.0


@dataclasses.dataclass(frozen=True, eq=False)
class MotionClip:
    """One recorded (or generated) sequence: motion at ``fps`` and optionally its audio.

    At least one of ``params``, ``vertices``, ``features`` is set; all set ones share ``frames``.

    Attributes:
        name: identifier (the file stem by default).
        fps: motion frame rate.
        params: ``(frames, 56)`` head parameters ``[exp 50 | jaw 3 | neck 3]``, or None.
        vertices: ``(frames, verts, 3)`` mesh vertices, or None.
        template: ``(verts, 3)`` neutral mesh of the subject, or None.
        features: ``(frames, dim)`` any other per-frame stream, or None.
        audio: ``(samples,)`` mono float32 at ``sample_rate``, or None (not loaded / none).
        audio_path: where the audio lives, or None.
        sample_rate: rate of ``audio`` in Hz.
        partner_audio_path: the conversation partner's audio (DualTalk), or None.
        subject: speaker/subject identifier, or None.
    """

    name: str
    fps: float | int
    params: Float[np.ndarray, "frames 56"] | None = None
    vertices: Float[np.ndarray, "frames verts 3"] | None = None
    template: Float[np.ndarray, "verts 3"] | None = None
    features: Float[np.ndarray, "frames dim"] | None = None
    audio: Float[np.ndarray, " samples"] | None = None
    audio_path: Path | None = None
    sample_rate: int = AUDIO_SAMPLE_RATE
    partner_audio_path: Path | None = None
    subject: str | None = None

    def __post_init__(self):
        _check_clip_fields(
            self.name,
            self.fps,
            self.params,
            self.vertices,
            self.template,
            self.features,
            self.audio,
        )

    @property
    def num_frames(self) -> int:
        """Number of motion frames."""
        for value in (self.params, self.vertices, self.features):
            if value is not None:
                return int(value.shape[0])
        raise AssertionError("unreachable: __post_init__ requires a stream")

    @property
    def duration(self) -> float:
        """Motion duration in seconds."""
        return self.num_frames / self.fps

    def resampled(self, fps: float | int = MOTION_FPS, mode: str = "linear") -> MotionClip:
        """The clip with every motion stream converted to ``fps`` (see ``resample_features``).

        Output length is ``round(frames * fps / self.fps)``. Linear interpolation of axis-angle
        parameters is accurate for the small per-frame rotations of heads and jaws.
        """
        from jaxtalk.audio.framerate import default_num_frames, resample_features

        if fps == self.fps:
            return self
        count = default_num_frames(self.num_frames, self.fps, fps)

        def convert(stream):
            if stream is None:
                return None
            flat = stream.reshape(stream.shape[0], -1)
            out = resample_features(flat, self.fps, fps, num_frames=count, mode=mode)
            return np.asarray(out, dtype=stream.dtype).reshape(count, *stream.shape[1:])

        return dataclasses.replace(
            self,
            fps=float(fps),
            params=convert(self.params),
            vertices=convert(self.vertices),
            features=convert(self.features),
        )


def _check_clip_fields(name, fps, params, vertices, template, features, audio) -> None:
    # Plain (unannotated) so that readers can run it before MotionClip's typed __init__: bad files
    # then fail with this ValueError rather than a type-checker error.
    if not np.isfinite(fps) or fps <= 0:
        raise ValueError(f"{name}: fps must be positive, got {fps!r}")
    streams = {"params": params, "vertices": vertices, "features": features}
    present = {k: v for k, v in streams.items() if v is not None}
    if not present:
        raise ValueError(f"{name}: a MotionClip needs params, vertices or features")
    expected_ndim = {"params": 2, "vertices": 3, "features": 2}
    for key, value in present.items():
        if not isinstance(value, np.ndarray) or value.ndim != expected_ndim[key]:
            raise ValueError(
                f"{name}: {key} must be a {expected_ndim[key]}-D array, got "
                f"{getattr(value, 'shape', type(value))}"
            )
        if value.shape[0] == 0:
            raise ValueError(f"{name}: {key} has zero frames")
        if not np.all(np.isfinite(value)):
            raise ValueError(f"{name}: {key} contains NaN or inf values")
    if params is not None and params.shape[1] != PARAM_DIM:
        raise ValueError(f"{name}: params must be (frames, {PARAM_DIM}), got {params.shape}")
    if vertices is not None and vertices.shape[2] != 3:
        raise ValueError(f"{name}: vertices must be (frames, verts, 3), got {vertices.shape}")
    lengths = {k: v.shape[0] for k, v in present.items()}
    if len(set(lengths.values())) > 1:
        raise ValueError(f"{name}: streams disagree on the number of frames: {lengths}")
    if template is not None:
        verts = None if vertices is None else vertices.shape[1]
        if (
            template.ndim != 2
            or template.shape[1] != 3
            or (verts is not None and template.shape[0] != verts)
        ):
            raise ValueError(
                f"{name}: template must be (verts, 3) matching the vertices"
                f"{'' if verts is None else f' ({verts})'}, got {template.shape}"
            )
    if audio is not None and (audio.ndim != 1 or audio.size == 0):
        raise ValueError(f"{name}: audio must be a non-empty (samples,) array, got {audio.shape}")


def _make_clip(path: Path, **fields) -> MotionClip:
    """Validate the fields (ValueError naming the file) and build the clip."""
    try:
        _check_clip_fields(
            fields["name"],
            fields["fps"],
            *(fields.get(k) for k in ("params", "vertices", "template")),
            fields.get("features"),
            fields.get("audio"),
        )
    except ValueError as err:
        raise ValueError(f"{str(path)!r}: {err}") from err
    return MotionClip(**fields)


def _require_keys(data: dict, keys: tuple[str, ...], path: Path, layout: str) -> None:
    missing = [k for k in keys if k not in data]
    if missing:
        raise ValueError(
            f"{str(path)!r} is not a {layout} file: missing keys {missing} (found {sorted(data)})"
        )


def _float_array(value, what: str, path: Path, ndim: int) -> np.ndarray:
    array = np.asarray(value)
    if not np.issubdtype(array.dtype, np.number) or array.ndim != ndim:
        raise ValueError(
            f"{str(path)!r}: {what} must be a numeric {ndim}-D array, got {array.dtype} {array.shape}"
        )
    return array.astype(np.float32)


def _load_audio_beside(wav: Path | None, load: bool, require: bool, source: Path):
    from jaxtalk.audio.io import load_audio

    if wav is None or not wav.is_file():
        if require:
            raise FileNotFoundError(f"audio for {str(source)!r} not found: expected {str(wav)!r}")
        return None, None
    audio = load_audio(wav, AUDIO_SAMPLE_RATE, allow_silence=True) if load else None
    return audio, wav


def dualtalk_to_params56(
    exp: Float[np.ndarray, "frames 50"], pose: Float[np.ndarray, "frames 6"]
) -> Float[np.ndarray, "frames 56"]:
    """DualTalk's ``exp``/``pose`` to jaxtalk's ``[exp | jaw | neck]``.

    Jaw is ``pose[:, 3:]`` and neck (global head rotation) is ``pose[:, :3]``.
    """
    return np.concatenate([exp, pose[:, 3:6], pose[:, 0:3]], axis=1)


def read_dualtalk(
    path: str | os.PathLike,
    *,
    load_audio: bool = True,
    require_audio: bool = True,
    fps: float | int = DUALTALK_FPS,
) -> MotionClip:
    """Read one DualTalk ``.npz`` (and its same-stem ``.wav``) as 56-d parameters at 25 fps.

    Args:
        path: the ``.npz`` with ``exp (T, 50)`` and ``pose (T, 6)`` (other keys are ignored).
        load_audio: load the ``.wav`` into ``clip.audio`` (mono, 16 kHz).
        require_audio: raise if the ``.wav`` is missing (otherwise ``audio_path`` is None).
        fps: the tracks' frame rate (DualTalk: 25).

    Returns:
        ``MotionClip`` with ``params (T, 56)``, ``audio``/``audio_path`` and, when the other
        speaker's ``.wav`` exists, ``partner_audio_path``.

    Raises:
        FileNotFoundError: missing ``.npz``, or missing ``.wav`` with ``require_audio``.
        ValueError: missing keys, wrong shapes, mismatched lengths, NaN values.
    """
    path = Path(path)
    data = load_npz(path, what="motion file")
    _require_keys(data, ("exp", "pose"), path, "DualTalk")
    exp = _float_array(data["exp"], "exp", path, 2)
    pose = _float_array(data["pose"], "pose", path, 2)
    if exp.shape[1] != EXP_DIM or pose.shape[1] != 6:
        raise ValueError(
            f"{str(path)!r}: expected exp (T, {EXP_DIM}) and pose (T, 6), got {exp.shape}, {pose.shape}"
        )
    if exp.shape[0] != pose.shape[0]:
        raise ValueError(
            f"{str(path)!r}: exp has {exp.shape[0]} frames but pose has {pose.shape[0]}"
        )
    audio, wav = _load_audio_beside(path.with_suffix(".wav"), load_audio, require_audio, path)
    partner = None
    for own, other in (("_speaker1", "_speaker2"), ("_speaker2", "_speaker1")):
        if path.stem.endswith(own):
            candidate = path.with_name(path.stem[: -len(own)] + other + ".wav")
            partner = candidate if candidate.is_file() else None
    return _make_clip(
        path,
        name=path.stem,
        fps=float(fps),
        params=dualtalk_to_params56(exp, pose),
        audio=audio,
        audio_path=wav,
        partner_audio_path=partner,
    )


def read_vocaset_templates(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read VOCASET subject templates: ``templates.pkl`` (pickle, latin-1) or an ``.npz``.

    Pickle can run code when loaded: only read template files from a source you trust (the ``.npz``
    form is safe).

    Returns:
        ``{subject: (V, 3) float32}``.

    Raises:
        FileNotFoundError: missing file.
        ValueError: not a mapping of subjects to ``(V, 3)`` arrays.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"template file not found: {str(path)!r}")
    if path.suffix == ".npz":
        raw = load_npz(path, what="template file")
    else:
        try:
            with open(path, "rb") as handle:
                # VOCASET's pickle was written by Python 2: latin-1 decodes its NumPy buffers.
                raw = pickle.load(handle, encoding="latin1")
        except (pickle.UnpicklingError, EOFError, ValueError) as err:
            raise ValueError(f"{str(path)!r}: cannot unpickle templates ({err})") from err
    if not isinstance(raw, dict) or not raw:
        raise ValueError(f"{str(path)!r}: expected a non-empty {{subject: (V, 3) array}} mapping")
    out = {}
    for subject, template in raw.items():
        template = np.asarray(template)
        if template.ndim == 1 and template.size % 3 == 0:
            template = template.reshape(-1, 3)
        if template.ndim != 2 or template.shape[1] != 3:
            raise ValueError(
                f"{str(path)!r}: template of {subject!r} must be (V, 3), got {template.shape}"
            )
        out[str(subject)] = template.astype(np.float32)
    return out


def read_vocaset(
    path: str | os.PathLike,
    *,
    templates: str | os.PathLike | dict[str, np.ndarray] | None = None,
    wav_path: str | os.PathLike | None = None,
    fps: float | int = VOCASET_FPS,
    target_fps: float | int | None = MOTION_FPS,
    load_audio: bool = True,
    require_audio: bool = False,
) -> MotionClip:
    """Read one VOCASET-style vertex sequence (see the module docstring for the layout).

    Args:
        path: ``<root>/vertices_npy/<subject>_<sentence>.npy`` with ``(T, V*3)`` or ``(T, V, 3)``.
        templates: a templates file, an already-read ``{subject: (V, 3)}`` mapping, or None to use
            ``<root>/templates.pkl`` (or ``templates.npz``) when present.
        wav_path: the audio; default ``<root>/wav/<stem>.wav``.
        fps: the sequence's frame rate (VOCASET: 60).
        target_fps: resample to this rate (default 25, the motion rate); None keeps ``fps``.
        load_audio: load the audio into ``clip.audio``.
        require_audio: raise if the audio file is missing.

    Returns:
        ``MotionClip`` with ``vertices`` (and ``template``, ``subject``) at ``target_fps``.

    Raises:
        FileNotFoundError: missing sequence, templates file, or (with ``require_audio``) audio.
        ValueError: wrong shapes, NaN values, a subject absent from the templates, or a template
            whose vertex count differs from the sequence's.
    """
    path = Path(path)
    verts = load_npy(path, what="vertex sequence")
    if not np.issubdtype(verts.dtype, np.number):
        raise ValueError(f"{str(path)!r}: expected a numeric vertex array")
    if verts.ndim == 2 and verts.shape[1] % 3 == 0:
        verts = verts.reshape(verts.shape[0], -1, 3)
    if verts.ndim != 3 or verts.shape[2] != 3:
        raise ValueError(
            f"{str(path)!r}: expected (T, V*3) or (T, V, 3) vertices, got shape {verts.shape}"
        )
    root = path.parent.parent
    subject = path.stem.rsplit("_", 1)[0] if "_" in path.stem else path.stem
    if templates is None:
        found = [p for p in (root / "templates.pkl", root / "templates.npz") if p.is_file()]
        templates = found[0] if found else None
    template = None
    if templates is not None:
        table = templates if isinstance(templates, dict) else read_vocaset_templates(templates)
        if subject not in table:
            raise ValueError(
                f"{str(path)!r}: subject {subject!r} not in templates (have {sorted(table)[:10]})"
            )
        template = np.asarray(table[subject], dtype=np.float32)
        if template.shape != verts.shape[1:]:
            raise ValueError(
                f"{str(path)!r}: template of {subject!r} has shape {template.shape}, sequence has "
                f"{verts.shape[1]} vertices"
            )
    wav = Path(wav_path) if wav_path is not None else root / "wav" / f"{path.stem}.wav"
    audio, wav = _load_audio_beside(wav, load_audio, require_audio, path)
    clip = _make_clip(
        path,
        name=path.stem,
        fps=float(fps),
        vertices=verts.astype(np.float32),
        template=template,
        audio=audio,
        audio_path=wav,
        subject=subject,
    )
    return clip if target_fps is None else clip.resampled(target_fps)


def read_npz(path: str | os.PathLike, *, load_audio: bool = True) -> MotionClip:
    """Read a generic motion ``.npz`` (keys in the module docstring; written by ``save_npz``).

    Raises:
        FileNotFoundError: missing file, or a missing ``audio_path`` target when ``load_audio``.
        ValueError: no ``fps`` or no motion stream (lists the keys found), wrong shapes, NaN values,
            ``audio`` without ``sample_rate``.
    """
    path = Path(path)
    data = load_npz(path, what="motion file")
    _require_keys(data, ("fps",), path, "generic motion npz")
    if not any(k in data for k in ("params", "vertices", "features")):
        raise ValueError(
            f"{str(path)!r}: needs at least one of 'params', 'vertices', 'features' "
            f"(found {sorted(data)})"
        )
    fps = np.asarray(data["fps"])
    if fps.shape != () or not np.issubdtype(fps.dtype, np.number):
        raise ValueError(
            f"{str(path)!r}: 'fps' must be a numeric scalar, got {fps.dtype} {fps.shape}"
        )
    streams = {
        key: _float_array(data[key], key, path, ndim)
        for key, ndim in (("params", 2), ("vertices", 3), ("features", 2), ("template", 2))
        if key in data
    }
    audio, audio_path, sample_rate = None, None, AUDIO_SAMPLE_RATE
    if "audio" in data:
        _require_keys(data, ("sample_rate",), path, "generic motion npz with 'audio'")
        audio = _float_array(data["audio"], "audio", path, 1)
        sample_rate = int(data["sample_rate"])
    elif "audio_path" in data:
        audio_path = path.parent / str(data["audio_path"])
        audio, audio_path = _load_audio_beside(audio_path, load_audio, load_audio, path)
    name = str(data["name"]) if "name" in data else path.stem
    return _make_clip(
        path,
        name=name,
        fps=float(fps),
        audio=audio,
        audio_path=audio_path,
        sample_rate=sample_rate,
        **streams,
    )


def save_npz(path: str | os.PathLike, clip: MotionClip) -> Path:
    """Write a clip in the generic npz layout (``read_npz`` reads it back exactly).

    ``audio`` is stored inline when loaded, otherwise ``audio_path`` is stored relative to the npz's
    folder when possible (absolute otherwise).

    Returns:
        The path written.
    """
    path = Path(path)
    arrays: dict[str, np.ndarray] = {"fps": np.float64(clip.fps), "name": np.str_(clip.name)}
    for key in ("params", "vertices", "features", "template"):
        value = getattr(clip, key)
        if value is not None:
            arrays[key] = value
    if clip.audio is not None:
        arrays["audio"] = clip.audio
        arrays["sample_rate"] = np.int64(clip.sample_rate)
    elif clip.audio_path is not None:
        target = Path(clip.audio_path).resolve()
        try:
            arrays["audio_path"] = np.str_(target.relative_to(path.parent.resolve()))
        except ValueError:
            arrays["audio_path"] = np.str_(target)
    from jaxtalk.files import atomic_savez

    return atomic_savez(path, **arrays)


def read_clip(path: str | os.PathLike, **kwargs) -> MotionClip:
    """Read any supported layout, detected from the file: DualTalk npz (``exp``/``pose``), generic
    npz (``fps``), or a VOCASET ``.npy`` vertex sequence. ``kwargs`` go to the specific reader.

    Raises:
        FileNotFoundError: missing file.
        ValueError: an unrecognised file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"motion file not found: {str(path)!r}")
    if path.suffix == ".npy":
        return read_vocaset(path, **kwargs)
    if path.suffix == ".npz":
        keys = set(load_npz(path, what="motion file"))
        if {"exp", "pose"} <= keys:
            return read_dualtalk(path, **kwargs)
        if "fps" in keys:
            return read_npz(path, **kwargs)
        raise ValueError(f"{str(path)!r}: unrecognised npz layout (keys {sorted(keys)})")
    raise ValueError(
        f"{str(path)!r}: unsupported file type {path.suffix!r} (expected .npz or .npy)"
    )
