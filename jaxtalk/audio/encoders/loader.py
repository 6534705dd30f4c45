"""Hugging Face checkpoint directory -> :class:`EncoderConfig` + Flax params, without PyTorch.

A checkpoint directory holds ``config.json`` and the weights: ``model.safetensors`` (read with the
``safetensors`` NumPy API), a sharded ``model.safetensors.index.json``, or the legacy
``pytorch_model.bin`` (read only when PyTorch is installed). ``preprocessor_config.json``, when
present, says whether the waveform is normalised to zero mean / unit variance (``do_normalize``) and
its sampling rate.

Every parameter of the Flax model is looked up by its HF tensor name; the loader fails with one
message that lists every missing, unexpected or mis-shaped tensor. Task checkpoints
(``Wav2Vec2ForCTC``, ``HubertForSequenceClassification``, ``Wav2Vec2ForPreTraining``, ...) store the
encoder under ``wav2vec2.`` / ``hubert.``; their head tensors (``lm_head``, ``quantizer``,
``project_q``, ``classifier``, ...) lie outside the encoder and are skipped and listed in
``Checkpoint.ignored``, as is the training-only ``masked_spec_embed``.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from jaxtalk.audio.encoders.config import EncoderConfig
from jaxtalk.audio.encoders.wav2vec2 import Wav2Vec2Model

__all__ = [
    "Checkpoint",
    "load_checkpoint",
    "read_state_dict",
    "weight_files",
    "checkpoint_fingerprint",
    "params_from_state_dict",
    "params_to_state_dict",
    "save_checkpoint",
    "expected_param_shapes",
    "hf_tensor_names",
]

_SAFETENSORS = "model.safetensors"
_SAFETENSORS_INDEX = "model.safetensors.index.json"
_TORCH_BIN = "pytorch_model.bin"
_TORCH_BIN_INDEX = "pytorch_model.bin.index.json"
_PREFIX = {"wav2vec2": "wav2vec2.", "hubert": "hubert."}
# Tensors of the encoder module that inference does not use.
_UNUSED_ENCODER_TENSORS = ("masked_spec_embed", "encoder.pos_conv_embed.batch_norm.num_batches_tracked")
# Flax leaf name -> HF tensor leaf names (the first is what current transformers writes; the others
# are older spellings, e.g. the pre-parametrization weight norm of checkpoints on the Hub).
_LEAF_NAMES = {
    "kernel": ("weight",),
    "scale": ("weight",),
    "bias": ("bias",),
    "mean": ("running_mean",),
    "var": ("running_var",),
    "weight_g": ("parametrizations.weight.original0", "weight_g"),
    "weight_v": ("parametrizations.weight.original1", "weight_v"),
}


@dataclasses.dataclass(frozen=True)
class Checkpoint:
    """A loaded checkpoint.

    Attributes:
        config: the architecture.
        params: Flax params pytree for :class:`Wav2Vec2Model` (``{"params": ...}`` goes to ``apply``).
        normalize: whether the waveform must be normalised to zero mean / unit variance first
            (``do_normalize`` of ``preprocessor_config.json``; True, the HF feature-extractor
            default, when that file is absent).
        sample_rate: the rate the model was trained at (``sampling_rate``; 16000 when absent).
        ignored: HF tensor names that were present but not used (task heads, training-only).
        path: the checkpoint directory.
    """

    config: EncoderConfig
    params: dict[str, Any]
    normalize: bool
    sample_rate: int
    ignored: tuple[str, ...]
    path: Path


@functools.lru_cache(maxsize=16)
def expected_param_shapes(config: EncoderConfig) -> dict[str, Any]:
    """The Flax params pytree of ``config`` as ``jax.ShapeDtypeStruct`` leaves (no allocation).

    Cached per config (tracing the model costs a second or two); treat the result as read-only.
    """
    model = Wav2Vec2Model(config)
    dummy = jnp.zeros((1, config.receptive_field), jnp.float32)
    variables = jax.eval_shape(lambda: model.init(jax.random.key(0), dummy))
    return variables["params"]


def _flatten(tree: Mapping[str, Any], prefix: tuple[str, ...] = ()) -> dict[tuple[str, ...], Any]:
    out: dict[tuple[str, ...], Any] = {}
    for name, value in tree.items():
        if isinstance(value, Mapping):
            out.update(_flatten(value, (*prefix, name)))
        else:
            out[(*prefix, name)] = value
    return out


def _unflatten(flat: Mapping[tuple[str, ...], Any]) -> dict[str, Any]:
    tree: dict[str, Any] = {}
    for path, value in flat.items():
        node = tree
        for name in path[:-1]:
            node = node.setdefault(name, {})
        node[path[-1]] = value
    return tree


def _is_stacked(path: tuple[str, ...]) -> bool:
    return path[:2] == ("encoder", "layers")


def hf_tensor_names(path: tuple[str, ...], layer: int | None = None) -> tuple[str, ...]:
    """HF tensor names (current spelling first) for the Flax param at ``path``.

    Args:
        path: Flax param path, e.g. ``("feature_extractor", "conv_layers_0", "conv", "kernel")``.
        layer: for the scanned transformer layers (``("encoder", "layers", ...)``), which layer.

    Returns:
        e.g. ``("feature_extractor.conv_layers.0.conv.weight",)``.
    """
    modules = [re.sub(r"^conv_layers_(\d+)$", r"conv_layers.\1", p) for p in path[:-1]]
    if _is_stacked(path):
        if layer is None:
            raise ValueError(f"param {'/'.join(path)} is stacked over layers: pass layer")
        modules = ["encoder", "layers", str(layer), *modules[2:]]
    return tuple(".".join([*modules, leaf]) for leaf in _LEAF_NAMES[path[-1]])


def _to_flax(leaf: str, array: np.ndarray) -> np.ndarray:
    """PyTorch layout -> Flax layout for one tensor."""
    if leaf == "kernel" and array.ndim == 2:  # Linear (out, in) -> Dense (in, out)
        return array.T
    if leaf in ("kernel", "weight_v") and array.ndim == 3:  # Conv1d (out, in/g, k) -> (k, in/g, out)
        return array.transpose(2, 1, 0)
    if leaf == "weight_g":  # (1, 1, k): one gain per kernel tap (weight_norm dim=2)
        return array.reshape(-1)
    return array


def _torch_shape(leaf: str, shape: tuple[int, ...]) -> tuple[int, ...]:
    """The HF tensor shape that maps to a Flax leaf of ``shape`` (inverse of :func:`_to_flax`)."""
    if leaf == "kernel" and len(shape) == 2:
        return shape[::-1]
    if leaf in ("kernel", "weight_v") and len(shape) == 3:
        return shape[::-1]
    if leaf == "weight_g":
        return (1, 1, *shape)
    return shape


def params_from_state_dict(
    config: EncoderConfig,
    state_dict: Mapping[str, np.ndarray],
    *,
    dtype: Any = np.float32,
    source: str = "checkpoint",
) -> tuple[dict[str, Any], tuple[str, ...]]:
    """Map HF tensors by name into the Flax params of ``config``.

    Args:
        config: the architecture.
        state_dict: HF tensor name -> array (PyTorch layout), with or without the task-model prefix
            (``wav2vec2.`` / ``hubert.``).
        dtype: floating dtype of the returned params.
        source: how the checkpoint is named in error messages.

    Returns:
        ``(params, ignored)``: the params pytree (NumPy arrays) and the sorted names of the tensors
        that were skipped (task heads, ``masked_spec_embed``).

    Raises:
        ValueError: listing every missing, unexpected and mis-shaped tensor.
    """
    prefix = _PREFIX[config.model_type]
    encoder: dict[str, np.ndarray] = {}
    ignored: list[str] = []
    has_prefix = any(name.startswith(prefix) for name in state_dict)
    for name, array in state_dict.items():
        if has_prefix and not name.startswith(prefix):
            ignored.append(name)  # a task head outside the encoder
            continue
        short = name[len(prefix) :] if has_prefix else name
        if short in _UNUSED_ENCODER_TENSORS:
            ignored.append(name)
        else:
            encoder[short] = array
    shown = (lambda n: prefix + n) if has_prefix else (lambda n: n)

    used: set[str] = set()
    missing: list[str] = []
    misshaped: list[str] = []
    flat: dict[tuple[str, ...], np.ndarray] = {}
    for path, spec in _flatten(expected_param_shapes(config)).items():
        leaf = path[-1]
        layers = range(config.num_hidden_layers) if _is_stacked(path) else [None]
        per_layer_shape = tuple(spec.shape[1:]) if _is_stacked(path) else tuple(spec.shape)
        want = _torch_shape(leaf, per_layer_shape)
        pieces = []
        for layer in layers:
            candidates = hf_tensor_names(path, layer)
            found = next((c for c in candidates if c in encoder), None)
            if found is None:
                missing.append(shown(candidates[0]))
                continue
            used.add(found)
            array = np.asarray(encoder[found])
            if tuple(array.shape) != want:
                misshaped.append(f"{shown(found)}: shape {tuple(array.shape)}, expected {want}")
                continue
            pieces.append(_to_flax(leaf, array).astype(dtype))
        if len(pieces) == len(layers):
            flat[path] = np.stack(pieces) if _is_stacked(path) else pieces[0]
    unexpected = sorted(shown(n) for n in encoder if n not in used)
    problems = []
    if missing:
        problems.append(f"missing tensors ({len(missing)}): {', '.join(missing)}")
    if unexpected:
        problems.append(f"unexpected tensors ({len(unexpected)}): {', '.join(unexpected)}")
    if misshaped:
        problems.append(f"mis-shaped tensors ({len(misshaped)}): {'; '.join(misshaped)}")
    if problems:
        raise ValueError(
            f"{source} does not match its {config.model_type} config "
            f"(hidden_size={config.hidden_size}, layers={config.num_hidden_layers}): "
            + " | ".join(problems)
        )
    return _unflatten(flat), tuple(sorted(ignored))


def params_to_state_dict(config: EncoderConfig, params: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """Inverse of :func:`params_from_state_dict`: Flax params -> HF tensor names and layouts.

    Exports fine-tuned params back to the Hugging Face layout (current tensor spelling, no task
    prefix), e.g. for ``safetensors.numpy.save_file``.

    Args:
        config: the architecture.
        params: Flax params of :class:`Wav2Vec2Model`.

    Returns:
        HF tensor name -> NumPy array (PyTorch layout).
    """
    out: dict[str, np.ndarray] = {}
    for path, value in _flatten(params).items():
        leaf = path[-1]
        value = np.asarray(value)
        per_layer = list(enumerate(value)) if _is_stacked(path) else [(None, value)]
        for layer, array in per_layer:
            name = hf_tensor_names(path, layer)[0]
            out[name] = np.ascontiguousarray(
                np.reshape(_from_flax(leaf, array), _torch_shape(leaf, array.shape))
            )
    return out


def _from_flax(leaf: str, array: np.ndarray) -> np.ndarray:
    if leaf in ("kernel", "weight_v") and array.ndim in (2, 3):
        return array.T
    return array


def weight_files(path: str | os.PathLike[str]) -> list[Path]:
    """The weight files :func:`read_state_dict` reads from a checkpoint directory, in its order of
    preference: ``model.safetensors``, the shards of ``model.safetensors.index.json``,
    ``pytorch_model.bin``, the shards of ``pytorch_model.bin.index.json`` (an index file itself comes
    first, before its shards).

    Raises:
        FileNotFoundError: the directory, its weight files or a listed shard do not exist.
        ValueError: an unreadable shard index.
    """
    directory = Path(path)
    if not directory.is_dir():
        raise FileNotFoundError(f"checkpoint directory not found: {str(directory)!r}")
    for name, index in ((_SAFETENSORS, False), (_SAFETENSORS_INDEX, True), (_TORCH_BIN, False), (_TORCH_BIN_INDEX, True)):
        if (directory / name).is_file():
            return [directory / name, *_shards(directory / name)] if index else [directory / name]
    present = sorted(p.name for p in directory.iterdir())
    raise FileNotFoundError(
        f"{str(directory)!r} holds no weights: expected {_SAFETENSORS}, {_SAFETENSORS_INDEX}, "
        f"{_TORCH_BIN} or {_TORCH_BIN_INDEX}; found {present}"
    )


def read_state_dict(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Read every tensor of a checkpoint directory as NumPy arrays (PyTorch layout).

    Prefers ``model.safetensors`` (or its sharded index); falls back to ``pytorch_model.bin``
    (or its index), which needs PyTorch (see :func:`weight_files`).

    Raises:
        FileNotFoundError: the directory or its weight files do not exist.
        ImportError: only ``.bin`` weights and PyTorch (or ``safetensors``) is not installed.
        ValueError: an unreadable weight file.
    """
    files = [f for f in weight_files(path) if not f.name.endswith(".index.json")]
    if files[0].suffix == ".safetensors":
        return _read_safetensors(files)
    return _read_torch(files)


def checkpoint_fingerprint(path: str | os.PathLike[str]) -> str:
    """A short hash that changes when the files :func:`load_checkpoint` reads change: the name, size
    and modification time of ``config.json``, ``preprocessor_config.json`` (when present) and the
    weight files. Read from the file system alone (no weights are read), so it costs nothing next to
    loading a checkpoint of hundreds of megabytes; a copy of the same weights made later counts as
    another checkpoint.

    Raises:
        FileNotFoundError: see :func:`weight_files`.
    """
    import hashlib

    directory = Path(path)
    files = [directory / name for name in ("config.json", "preprocessor_config.json") if (directory / name).is_file()]
    stats = [(f.name, f.stat().st_size, f.stat().st_mtime_ns) for f in [*files, *weight_files(directory)]]
    return hashlib.sha1(json.dumps(stats).encode()).hexdigest()[:16]


def _shards(index_file: Path) -> list[Path]:
    try:
        weight_map = json.loads(index_file.read_text())["weight_map"]
    except (json.JSONDecodeError, KeyError, TypeError) as err:
        raise ValueError(f"{str(index_file)!r}: not a valid shard index ({err!r})") from err
    files = [index_file.parent / name for name in sorted(set(weight_map.values()))]
    for file in files:
        if not file.is_file():
            raise FileNotFoundError(f"shard {str(file)!r} listed in {index_file.name} not found")
    return files


def _read_safetensors(files: list[Path]) -> dict[str, np.ndarray]:
    try:
        from safetensors.numpy import load_file
    except ImportError as err:  # pragma: no cover - safetensors ships with the [encoders] extra
        raise ImportError(
            "reading model.safetensors needs the 'safetensors' package: pip install safetensors"
        ) from err
    tensors: dict[str, np.ndarray] = {}
    for file in files:
        try:
            tensors.update(load_file(str(file)))
        except Exception as err:  # safetensors raises its own error types
            raise ValueError(f"{str(file)!r}: cannot read safetensors file ({err})") from err
    return tensors


def _read_torch(files: list[Path]) -> dict[str, np.ndarray]:
    try:
        import torch
    except ImportError as err:
        raise ImportError(
            f"{str(files[0])!r} is a PyTorch pickle and PyTorch is not installed: install torch "
            "(pip install torch), or convert the checkpoint once to model.safetensors "
            "(transformers' save_pretrained(..., safe_serialization=True))"
        ) from err
    tensors: dict[str, np.ndarray] = {}
    for file in files:
        try:
            state = torch.load(str(file), map_location="cpu", weights_only=True)
        except Exception as err:
            raise ValueError(f"{str(file)!r}: cannot read PyTorch checkpoint ({err})") from err
        for name, tensor in state.items():
            if tensor.is_floating_point():
                tensor = tensor.to(torch.float32)  # bfloat16 has no NumPy dtype
            tensors[name] = tensor.numpy()
    return tensors


def _read_preprocessor(directory: Path) -> tuple[bool, int]:
    file = directory / "preprocessor_config.json"
    if not file.is_file():
        return True, 16_000
    try:
        cfg = json.loads(file.read_text())
    except json.JSONDecodeError as err:
        raise ValueError(f"{str(file)!r}: not valid JSON ({err})") from err
    rate = cfg.get("sampling_rate", 16_000)
    if not isinstance(rate, int) or rate <= 0:
        raise ValueError(f"{str(file)!r}: sampling_rate must be a positive integer, got {rate!r}")
    return bool(cfg.get("do_normalize", True)), rate


def load_checkpoint(path: str | os.PathLike[str], *, dtype: Any = np.float32) -> Checkpoint:
    """Load a Hugging Face wav2vec 2.0 / HuBERT checkpoint directory.

    Args:
        path: directory with ``config.json`` and ``model.safetensors`` (or ``pytorch_model.bin``).
        dtype: floating dtype of the params (float32 by default, whatever the file stores).

    Returns:
        :class:`Checkpoint`.

    Raises:
        FileNotFoundError: missing directory, ``config.json`` or weights.
        ImportError: ``.bin`` weights without PyTorch.
        ValueError: unknown architecture (``model_type`` not wav2vec2/hubert), unsupported
            options, or missing / unexpected / mis-shaped tensors.
    """
    directory = Path(path)
    if not directory.is_dir():
        raise FileNotFoundError(f"checkpoint directory not found: {str(directory)!r}")
    config = EncoderConfig.from_json(directory / "config.json")
    normalize, sample_rate = _read_preprocessor(directory)
    state = read_state_dict(directory)
    params, ignored = params_from_state_dict(config, state, dtype=dtype, source=repr(str(directory)))
    return Checkpoint(config, params, normalize, sample_rate, ignored, directory)


def save_checkpoint(
    path: str | os.PathLike[str],
    config: EncoderConfig,
    params: Mapping[str, Any],
    *,
    normalize: bool | None = None,
    sample_rate: int = 16_000,
) -> Path:
    """Write a Hugging Face checkpoint directory (``config.json`` + ``model.safetensors``).

    ``transformers`` loads it with ``Wav2Vec2Model.from_pretrained`` / ``HubertModel.from_pretrained``;
    use it to export fine-tuned params.

    Args:
        path: directory (created).
        config: the architecture.
        params: Flax params of :class:`Wav2Vec2Model`.
        normalize: when given, also write ``preprocessor_config.json`` with this ``do_normalize``.
        sample_rate: the ``sampling_rate`` written there.

    Returns:
        The directory.
    """
    from safetensors.numpy import save_file

    directory = Path(path)
    directory.mkdir(parents=True, exist_ok=True)
    (directory / "config.json").write_text(json.dumps(config.to_hf_dict(), indent=2) + "\n")
    save_file(params_to_state_dict(config, params), str(directory / _SAFETENSORS))
    if normalize is not None:
        preprocessor = {
            "feature_extractor_type": "Wav2Vec2FeatureExtractor",
            "do_normalize": bool(normalize),
            "sampling_rate": int(sample_rate),
            "feature_size": 1,
            "padding_value": 0.0,
            "return_attention_mask": config.feat_extract_norm == "layer",
        }
        (directory / "preprocessor_config.json").write_text(json.dumps(preprocessor, indent=2) + "\n")
    return directory
