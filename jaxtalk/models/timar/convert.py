"""Convert a checkpoint of the public TIMAR code into jaxtalk parameters and a run folder.

The public code (``CoderChen01/towards-seamless-interaction``, ``model/timar.py``) saves
``{"model": state_dict, "model_ema": state_dict, "args": argparse.Namespace, ...}`` with
``torch.save``. This module reads it (``torch`` is an optional dependency, ``pip install
"jaxtalk[torch]"``, used only here), infers every size from the state dict, maps each tensor onto
jaxtalk's TIMAR in the public code's layout (:meth:`TimarConfig.reference`) and writes an ordinary
run folder that ``jaxtalk sample``, ``jaxtalk stream`` and ``jaxtalk eval`` open like a trained run.

The mapping, key by key (torch ``Linear`` weights are ``(out, in)``, Flax kernels ``(in, out)``):

====================================================  =============================================
public code                                           jaxtalk (``params["encoder"]`` / ``["head"]``)
====================================================  =============================================
``speech_projection``                                 ``speech_proj``
``motion_encoder.0`` / ``.2``                         ``motion_encoder.dense_0`` / ``dense_1``
``sep_tok_emb.weight`` (10, d_t)                      ``separators``
``fake_latent`` (1, d_t) / ``mask_token`` (1, 1, d)   ``fake_token`` / ``mask_token``
``z_proj`` / ``z_proj_ln``                            ``input_proj`` / ``in_norm``
``encoder_pos_embed_learned`` (1, 8 x 110, d)         ``pos_embed``
``encoder_blocks.i`` (timm ``Block``)                 ``block_i`` (fused ``qkv`` split into q/k/v)
``encoder_norm``                                      ``out_norm``
``decoder_embed`` / ``decoder_pos_embed_learned``     ``decoder_embed`` / ``decoder_pos_embed``
``decoder_blocks.i`` / ``decoder_norm``               ``decoder_block_i`` / ``decoder_norm``
``diffusion_pos_embed_learned`` (1, 8 x 110, d)       ``head_pos_embed``: its rows at the agent-motion
                                                      positions (the only ones the head reads)
``diffloss.net.*`` (MAR's ``SimpleMLPAdaLN``)         ``head.*``
====================================================  =============================================

Every key must be used exactly once and have the shape the inferred config expects; anything else
is refused with a message that names the key, before anything is written.
"""

from __future__ import annotations

import dataclasses
import json
import re
import shutil
import tempfile
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from jaxtalk.models.timar.config import NUM_SEPARATORS, TimarConfig
from jaxtalk.models.timar.tokens import turn_layout
from jaxtalk.types import PARAM_DIM

__all__ = [
    "TORCH_HINT",
    "HEADS_BY_MODEL",
    "REFERENCE_MODELS",
    "ReferenceCheckpoint",
    "ConversionResult",
    "read_checkpoint",
    "infer_config",
    "convert_state_dict",
    "read_stats",
    "write_converted_run",
    "convert_checkpoint",
]

TORCH_HINT = 'pip install "jaxtalk[torch]"'
# The public code's model factories (``model/timar.py``): width, encoder and decoder depth, attention
# heads and the LayerNorm epsilon of their blocks. The state dict records the sizes, not the heads or
# the epsilon, so a checkpoint's ``args.model`` must name one of these (or, for a model built by hand,
# ``args`` must state ``encoder_num_heads`` and ``norm_eps``).
REFERENCE_MODELS: dict[str, tuple[int, int, int, int, float]] = {
    "timar_base": (768, 12, 12, 12, 1e-6),
    "timar_large": (1024, 16, 16, 16, 1e-6),
    "timar_huge": (1280, 20, 20, 16, 1e-6),
}
HEADS_BY_MODEL = {name: spec[3] for name, spec in REFERENCE_MODELS.items()}
# Training arguments of the public code that change what the model computes and that jaxtalk does not
# implement, with the value that jaxtalk's TIMAR equals: a checkpoint stating another is refused.
UNSUPPORTED_ARGS: dict[str, Any] = {"mask_history_agent": False, "num_iter": 1, "l2r_order": False}
# The public evaluation (TUTORIAL.md): one MAR iteration of 5 respaced diffusion steps, no guidance.
PUBLISHED_SAMPLE_STEPS = 5

PyTree = Any


@dataclasses.dataclass(frozen=True)
class ReferenceCheckpoint:
    """What a public-code checkpoint holds, as NumPy.

    Attributes:
        path: the file read.
        model: the raw weights ``{key: float32 array}``.
        ema: the EMA weights, or None when the file has none.
        args: the training arguments (``vars(args)``; arrays as NumPy).
    """

    path: Path
    model: dict[str, np.ndarray]
    ema: dict[str, np.ndarray] | None
    args: dict[str, Any]


@dataclasses.dataclass(frozen=True)
class ConversionResult:
    """What :func:`convert_checkpoint` wrote.

    Attributes:
        run_dir: the run folder.
        config: the model config.
        weights: ``"ema"`` or ``"model"``.
        normalizer: ``"stats"`` (from a statistics file), ``"checkpoint"`` (the statistics saved in
            the checkpoint's args) or ``"identity"``.
        num_params: parameter count.
    """

    run_dir: Path
    config: TimarConfig
    weights: str
    normalizer: str
    num_params: int


def _import_torch() -> Any:
    try:
        import torch
    except ImportError:
        raise ValueError(f"reading a PyTorch checkpoint needs torch: {TORCH_HINT}") from None
    return torch


def _numpy(x: Any) -> Any:
    if hasattr(x, "detach"):
        return x.detach().cpu().float().numpy()
    return x


def read_checkpoint(path: str | Path) -> ReferenceCheckpoint:
    """Read a checkpoint file of the public TIMAR code (``torch.load``, tensors only).

    The file is unpickled with ``weights_only=True``: only tensors, containers, ``argparse.Namespace``
    and NumPy arrays (the code stores its motion statistics in ``args``) are accepted, so a
    checkpoint cannot run code while it is read.

    Args:
        path: a ``.pth`` file.

    Returns:
        :class:`ReferenceCheckpoint`.

    Raises:
        FileNotFoundError: no such file.
        ValueError: torch is missing (the message names ``pip install "jaxtalk[torch]"``), the file
            is truncated or not a PyTorch checkpoint, or it holds no ``model`` state dict.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"checkpoint not found: {str(path)!r}")
    torch = _import_torch()
    import argparse

    safe = [argparse.Namespace, np.ndarray, np.dtype]
    try:
        from numpy._core.multiarray import _reconstruct, scalar
    except ImportError:  # NumPy 1.x
        from numpy.core.multiarray import _reconstruct, scalar  # type: ignore[no-redef]
    safe += [_reconstruct, scalar]
    safe += [type(np.dtype(t)) for t in ("float32", "float64", "int64", "int32", "bool")]
    try:
        with torch.serialization.safe_globals(safe):
            raw = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # noqa: BLE001  (torch raises many kinds for a bad file)
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ValueError(f"{str(path)!r} is not a readable PyTorch checkpoint (truncated or corrupt?): {first}") from None
    if not isinstance(raw, dict) or not isinstance(raw.get("model"), dict):
        keys = sorted(raw)[:6] if isinstance(raw, dict) else type(raw).__name__
        raise ValueError(f"{str(path)!r} is not a checkpoint of the public TIMAR code: no 'model' state dict "
                         f"(found {keys})")

    def tensors(sd: dict[str, Any], which: str) -> dict[str, np.ndarray]:
        out = {}
        for k, v in sd.items():
            if not hasattr(v, "detach"):
                raise ValueError(f"{str(path)!r}: {which}[{k!r}] is not a tensor")
            out[k] = np.asarray(_numpy(v), np.float32)
        return out

    args = raw.get("args")
    args = vars(args) if isinstance(args, argparse.Namespace) else dict(args or {})
    ema = raw.get("model_ema")
    return ReferenceCheckpoint(
        path=path,
        model=tensors(raw["model"], "model"),
        ema=None if ema is None else tensors(ema, "model_ema"),
        args={k: _numpy(v) for k, v in args.items()},
    )


def _need(state: dict[str, np.ndarray], key: str) -> np.ndarray:
    if key not in state:
        raise ValueError(f"the state dict has no {key!r}: not a TIMAR checkpoint of the public code, or a variant "
                         "jaxtalk does not convert")
    return state[key]


def _count(state: dict[str, np.ndarray], prefix: str) -> int:
    idx = {int(m.group(1)) for k in state if (m := re.match(re.escape(prefix) + r"\.(\d+)\.", k))}
    if idx and idx != set(range(len(idx))):
        raise ValueError(f"the {prefix} blocks are not numbered 0..{len(idx) - 1}: {sorted(idx)}")
    return len(idx)


def infer_config(state: dict[str, np.ndarray], args: dict[str, Any]) -> TimarConfig:
    """The jaxtalk config of a public-code state dict: sizes from the tensors, the rest from ``args``.

    Args:
        state: the state dict (NumPy).
        args: the checkpoint's training arguments; used: ``model`` (the factory's attention heads and
            LayerNorm epsilon, its sizes checked against the tensors; or ``encoder_num_heads`` and
            ``norm_eps`` for a model built by hand), ``cfg`` (the default guidance), ``use_causal_attn``,
            ``motion_fps`` x ``chunk_second``,
            ``noise_schedule``, ``epsilon_pred``, ``clip_denoised``, and the training settings
            ``cond_drop_prob``, ``mask_ratio_min``, ``diffusion_batch_mul``, ``proj_dropout``.

    Returns:
        :meth:`TimarConfig.reference` at the checkpoint's sizes.

    Raises:
        ValueError: a missing key, an unsupported variant (MLP head, epsilon prediction, the FLAME
            clamp of ``--clip_denoised``, :data:`UNSUPPORTED_ARGS`), args that do not say the heads or
            the epsilon, or sizes that disagree (the message names the key).
    """
    if any(k.startswith("mlp_head.") for k in state):
        raise ValueError("the state dict has 'mlp_head.*' (a --use_mseloss model): jaxtalk converts the "
                         "diffusion-head TIMAR only")
    if args.get("epsilon_pred"):
        raise ValueError("args.epsilon_pred is set: jaxtalk's TIMAR head predicts x0 (predict_xstart) only")
    if args.get("clip_denoised"):
        raise ValueError("args.clip_denoised is set: jaxtalk's sampler has no FLAME clamp of the x0 estimate")
    token_width, speech_dim = _need(state, "speech_projection.weight").shape
    width = _need(state, "z_proj.weight").shape[0]
    param_dim = _need(state, "motion_encoder.0.weight").shape[1]
    if param_dim != PARAM_DIM:
        raise ValueError(f"motion_encoder.0.weight has {param_dim} input channels, jaxtalk's head motion has {PARAM_DIM}")
    depth = _count(state, "encoder_blocks")
    if depth == 0:
        raise ValueError("the state dict has no 'encoder_blocks.0.*' keys")
    decoder_depth = _count(state, "decoder_blocks")
    encoder_only = "decoder_embed.weight" not in state
    if encoder_only and decoder_depth:
        raise ValueError("the state dict has 'decoder_blocks.*' but no 'decoder_embed.weight'")
    if args.get("use_encoder_only") is not None and bool(args["use_encoder_only"]) != encoder_only:
        raise ValueError(f"args.use_encoder_only={args['use_encoder_only']} but the state dict "
                         f"{'has no' if encoder_only else 'has a'} decoder ('decoder_embed.weight')")
    if not encoder_only:
        dec_width = state["decoder_embed.weight"].shape[0]
        if dec_width != width:
            raise ValueError(f"decoder_embed.weight maps width {width} to {dec_width}: jaxtalk's encoder-decoder "
                             "variant keeps one width")
    for name, value in UNSUPPORTED_ARGS.items():
        if name in args and args[name] is not None and args[name] != value:
            raise ValueError(f"args.{name}={args[name]!r}: jaxtalk's TIMAR implements {name}={value!r} only")
    heads, norm_eps = _heads_and_epsilon(args, width, depth, decoder_depth, encoder_only)
    hidden = _need(state, "encoder_blocks.0.mlp.fc1.weight").shape[0]
    fps = int(args.get("motion_fps", 25)) * int(args.get("chunk_second", 1))
    positions = _need(state, "encoder_pos_embed_learned").shape[1]
    tpt = 4 * fps + NUM_SEPARATORS
    if positions % tpt:
        raise ValueError(f"encoder_pos_embed_learned has {positions} positions, not a whole number of "
                         f"{tpt}-token turns")
    head_width = _need(state, "diffloss.net.input_proj.weight").shape[0]
    head_out = _need(state, "diffloss.net.final_layer.linear.weight").shape[0]
    if head_out not in (PARAM_DIM, 2 * PARAM_DIM):
        raise ValueError(f"diffloss.net.final_layer.linear.weight has {head_out} outputs, expected "
                         f"{PARAM_DIM} or {2 * PARAM_DIM}")
    return TimarConfig.reference(
        width=int(width), num_layers=depth, num_heads=int(heads), mlp_ratio=hidden / width,
        architecture="encoder" if encoder_only else "encoder_decoder", decoder_layers=max(decoder_depth, 1),
        speech_dim=int(speech_dim), token_width=int(token_width), frames_per_turn=fps, max_turns=positions // tpt,
        head_width=int(head_width), head_blocks=_count(state, "diffloss.net.res_blocks"),
        learn_sigma=head_out == 2 * PARAM_DIM,
        attention="turn_causal" if args.get("use_causal_attn") else "bidirectional",
        schedule=str(args.get("noise_schedule", "cosine")),
        cfg_dropout=float(args.get("cond_drop_prob", 0.1)), mask_ratio_min=float(args.get("mask_ratio_min", 0.7)),
        diffusion_batch_mul=int(args.get("diffusion_batch_mul", 4)), dropout=float(args.get("proj_dropout", 0.1)),
        sample_steps=PUBLISHED_SAMPLE_STEPS, block_norm_epsilon=norm_eps,
        # The public code's --cfg is omega of (1 - omega) u + omega c; jaxtalk's weight is w = omega - 1.
        cfg_scale=float(args.get("cfg", 1.0)) - 1.0,
    )


def _heads_and_epsilon(args: dict[str, Any], width: int, depth: int, decoder_depth: int,
                       encoder_only: bool) -> tuple[int, float]:
    """The attention heads and block LayerNorm epsilon a checkpoint's ``args`` state: from the factory
    ``args.model`` names (whose sizes must be the tensors'), or stated outright for a model built by
    hand. Refused when neither says."""
    model = args.get("model")
    if model in REFERENCE_MODELS:
        f_width, f_enc, f_dec, heads, norm_eps = REFERENCE_MODELS[model]
        # The encoder-only variant stacks encoder_depth + decoder_depth blocks as its encoder.
        expected = (f_width, f_enc + f_dec, 0) if encoder_only else (f_width, f_enc, f_dec)
        if (width, depth, decoder_depth) != expected:
            raise ValueError(f"args.model={model!r} builds width {expected[0]} with {expected[1]} encoder and "
                             f"{expected[2]} decoder blocks, but the state dict has width {width} with {depth} and "
                             f"{decoder_depth}: the args do not describe these weights")
        if args.get("encoder_num_heads") not in (None, heads):
            raise ValueError(f"args.encoder_num_heads={args['encoder_num_heads']} disagrees with {model!r} ({heads})")
        return heads, norm_eps
    heads, norm_eps = args.get("encoder_num_heads"), args.get("norm_eps")
    if not heads or not norm_eps:
        missing = " and ".join(n for n, v in (("encoder_num_heads", heads), ("norm_eps", norm_eps)) if not v)
        raise ValueError(f"args.model={model!r} is not one of the public code's models "
                         f"({', '.join(REFERENCE_MODELS)}) and the args do not state its {missing}: "
                         "unknown number of attention heads or LayerNorm epsilon")
    return int(heads), float(norm_eps)


class _Reader:
    """Takes each key of a state dict once, checking its shape; reports what was never taken."""

    def __init__(self, state: dict[str, np.ndarray]) -> None:
        self.state = state
        self.used: set[str] = set()

    def take(self, key: str, shape: tuple[int, ...]) -> np.ndarray:
        value = _need(self.state, key)
        if key in self.used:
            raise ValueError(f"{key!r} read twice")  # a bug in the mapping, not in the file
        if tuple(value.shape) != tuple(shape):
            raise ValueError(f"{key!r} has shape {tuple(value.shape)}, the checkpoint's other tensors make it "
                             f"{tuple(shape)}")
        if not np.all(np.isfinite(value)):
            raise ValueError(f"{key!r} holds NaN or infinite values")
        self.used.add(key)
        return np.asarray(value, np.float32)

    def linear(self, key: str, n_in: int, n_out: int) -> dict[str, np.ndarray]:
        return {"kernel": self.take(f"{key}.weight", (n_out, n_in)).T.copy(), "bias": self.take(f"{key}.bias", (n_out,))}

    def norm(self, key: str, n: int) -> dict[str, np.ndarray]:
        return {"scale": self.take(f"{key}.weight", (n,)), "bias": self.take(f"{key}.bias", (n,))}

    def finish(self) -> None:
        extra = sorted(set(self.state) - self.used)
        if extra:
            more = f" (and {len(extra) - 1} more)" if len(extra) > 1 else ""
            raise ValueError(f"the state dict has a key jaxtalk's TIMAR does not use: {extra[0]!r}{more}")


def _block(r: _Reader, key: str, config: TimarConfig) -> dict[str, Any]:
    """One timm ViT ``Block`` (fused qkv with bias, pre-LN, GELU MLP) as a jaxtalk ``TransformerBlock``."""
    w, h = config.width, config.num_heads
    hd = w // h
    hidden = int(round(config.mlp_ratio * w))
    qkv_w = r.take(f"{key}.attn.qkv.weight", (3 * w, w))
    qkv_b = r.take(f"{key}.attn.qkv.bias", (3 * w,))
    # timm reshapes the fused output to (3, heads, head_dim): rows [i w, (i+1) w) are q, k, v.
    proj = {n: {"kernel": qkv_w[i * w:(i + 1) * w].T.reshape(w, h, hd).copy(),
                "bias": qkv_b[i * w:(i + 1) * w].reshape(h, hd).copy()}
            for i, n in enumerate(("query", "key", "value"))}
    out_w = r.take(f"{key}.attn.proj.weight", (w, w))
    proj["out"] = {"kernel": out_w.T.reshape(h, hd, w).copy(), "bias": r.take(f"{key}.attn.proj.bias", (w,))}
    return {
        "self_attention": {"norm": r.norm(f"{key}.norm1", w), "attention": proj},
        "feed_forward": {
            "norm": r.norm(f"{key}.norm2", w),
            "feed_forward": {"mlp": {"dense_0": r.linear(f"{key}.mlp.fc1", w, hidden),
                                     "dense_1": r.linear(f"{key}.mlp.fc2", hidden, w)}},
        },
    }


def convert_state_dict(state: dict[str, np.ndarray], config: TimarConfig) -> dict[str, Any]:
    """Map a public-code state dict onto jaxtalk's TIMAR parameters (see the module's table).

    Args:
        state: the state dict (NumPy float32).
        config: the config it converts to (:func:`infer_config`; must have the reference layout).

    Returns:
        ``{"encoder": ..., "head": ...}`` NumPy float32 parameters, the tree of
        :func:`~jaxtalk.models.timar.model.init_params` for ``config``.

    Raises:
        ValueError: a missing key, an unused key or a shape mismatch (naming the key), or a config
            without the reference layout.
    """
    if not (config.input_projection and config.norm_after_position and config.motion_encoder_final_relu):
        raise ValueError("convert_state_dict needs a config with the public code's layout (TimarConfig.reference)")
    if config.head != "diffusion":
        raise ValueError("the public code's checkpoints have a diffusion head")
    r = _Reader(state)
    w, ew, f = config.width, config.embed_width, config.frames_per_turn
    positions = config.max_turns * config.tokens_per_turn
    enc: dict[str, Any] = {
        "speech_proj": r.linear("speech_projection", config.speech_dim, ew),
        "motion_encoder": {"dense_0": r.linear("motion_encoder.0", config.param_dim, max(ew // 2, 1)),
                           "dense_1": r.linear("motion_encoder.2", max(ew // 2, 1), ew)},
        "separators": r.take("sep_tok_emb.weight", (NUM_SEPARATORS, ew)),
        "fake_token": r.take("fake_latent", (1, ew))[0],
        "mask_token": r.take("mask_token", (1, 1, w))[0, 0],
        "input_proj": r.linear("z_proj", ew, w),
        "in_norm": r.norm("z_proj_ln", w),
        "pos_embed": r.take("encoder_pos_embed_learned", (1, positions, w))[0],
        "out_norm": r.norm("encoder_norm", w),
    }
    for i in range(config.num_layers):
        enc[f"block_{i}"] = _block(r, f"encoder_blocks.{i}", config)
    if config.architecture == "encoder_decoder":
        enc["decoder_embed"] = r.linear("decoder_embed", w, w)
        enc["decoder_pos_embed"] = r.take("decoder_pos_embed_learned", (1, positions, w))[0]
        enc["decoder_norm"] = r.norm("decoder_norm", w)
        for i in range(config.decoder_layers):
            enc[f"decoder_block_{i}"] = _block(r, f"decoder_blocks.{i}", config)
    # The head reads the diffusion table only at agent-motion tokens: slot k's frames j sit at
    # k (4F + 10) + (first agent-motion position) + j.
    table = r.take("diffusion_pos_embed_learned", (1, positions, w))[0]
    am = turn_layout(f).agent_motion
    rows = (np.arange(config.max_turns)[:, None] * config.tokens_per_turn + am[None, :]).reshape(-1)
    enc["head_pos_embed"] = table[rows].copy()

    hw, p = config.head_width, "diffloss.net"
    head: dict[str, Any] = {
        "time_embed": {"hidden": r.linear(f"{p}.time_embed.mlp.0", 256, hw), "out": r.linear(f"{p}.time_embed.mlp.2", hw, hw)},
        "cond_embed": r.linear(f"{p}.cond_embed", w, hw),
        "input_proj": r.linear(f"{p}.input_proj", config.param_dim, hw),
        "final": {"modulation": r.linear(f"{p}.final_layer.adaLN_modulation.1", hw, 2 * hw),
                  "out": r.linear(f"{p}.final_layer.linear", hw, config.head_out_dim)},
    }
    for k in range(config.head_blocks):
        b = f"{p}.res_blocks.{k}"
        head[f"res_blocks_{k}"] = {
            "norm": r.norm(f"{b}.in_ln", hw),
            "mlp": {"dense_0": r.linear(f"{b}.mlp.0", hw, hw), "dense_1": r.linear(f"{b}.mlp.2", hw, hw)},
            "modulation": r.linear(f"{b}.adaLN_modulation.1", hw, 3 * hw),
        }
    r.finish()
    params = {"encoder": enc, "head": head}
    _check_tree(params, config)
    return params


def _check_tree(params: PyTree, config: TimarConfig) -> None:
    """The converted tree must be exactly :func:`init_params`' (structure and shapes)."""
    import jax

    from jaxtalk.models.timar.model import init_params

    want = jax.eval_shape(lambda: init_params(config, jax.random.key(0)))
    got_leaves = jax.tree_util.tree_flatten_with_path(params)[0]
    want_leaves = jax.tree_util.tree_flatten_with_path(want)[0]
    got = {jax.tree_util.keystr(k): v.shape for k, v in got_leaves}
    exp = {jax.tree_util.keystr(k): v.shape for k, v in want_leaves}
    if got != exp:
        diff = sorted(set(got) ^ set(exp)) or [k for k in exp if got[k] != exp[k]]
        raise ValueError(f"converted parameters do not match jaxtalk's TIMAR at {diff[0]}")


def read_stats(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """The public code's motion statistics file (``stat_flame.json``): 56-d mean and std.

    Reads ``exp`` (50), ``jawpose`` (3) and ``neck`` (3), each ``{"mean", "std"}``, as the code's
    ``load_stat_info`` does (std floored at float32 eps).

    Args:
        path: the JSON file.

    Returns:
        ``(mean, std)``, each ``(56,)`` float32.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not JSON, a missing group, or a group of the wrong width (naming file and key).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"statistics file not found: {str(path)!r}")
    try:
        stats = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"{str(path)!r} is not a JSON statistics file: {err}") from None
    means, stds = [], []
    for group, width in (("exp", 50), ("jawpose", 3), ("neck", 3)):
        for field, out in (("mean", means), ("std", stds)):
            try:
                value = np.asarray(stats[group][field], np.float32).reshape(-1)
            except (KeyError, TypeError, ValueError):
                raise ValueError(f"{str(path)!r} has no numeric {group}.{field} (expected the public code's "
                                 "stat_flame.json)") from None
            if value.shape != (width,):
                raise ValueError(f"{str(path)!r}: {group}.{field} has {value.size} values, expected {width}")
            if not np.all(np.isfinite(value)):
                raise ValueError(f"{str(path)!r}: {group}.{field} is not finite")
            out.append(value)
    return np.concatenate(means), np.maximum(np.concatenate(stds), np.finfo(np.float32).eps)


def _normalizer(ckpt: ReferenceCheckpoint, config: TimarConfig, stats: str | Path | None) -> tuple[Any, str]:
    from jaxtalk.models.timar.data import Normalizer

    speech = (np.zeros(config.speech_dim, np.float32), np.ones(config.speech_dim, np.float32))
    if stats is not None:
        mean, std = read_stats(stats)
        return Normalizer(*speech, mean, std), "stats"
    mean, std = ckpt.args.get("mean"), ckpt.args.get("std")
    if ckpt.args.get("do_norm") and mean is not None and std is not None:
        mean, std = np.asarray(mean, np.float32).reshape(-1), np.asarray(std, np.float32).reshape(-1)
        if mean.shape == std.shape == (PARAM_DIM,):
            return Normalizer(*speech, mean, np.maximum(std, np.finfo(np.float32).eps)), "checkpoint"
    if ckpt.args.get("do_norm"):
        warnings.warn(f"{ckpt.path.name} was trained with --do_norm but holds no usable statistics and no --stats "
                      "was given: the run's motion normaliser is the identity", stacklevel=3)
    else:
        warnings.warn("no --stats given: the run's motion normaliser is the identity (right for a model trained "
                      "without --do_norm, as the public commands do)", stacklevel=3)
    return Normalizer(*speech, np.zeros(PARAM_DIM, np.float32), np.ones(PARAM_DIM, np.float32)), "identity"


# What a converted run folder holds: a folder of exactly these is a previous output of `convert`.
_CONVERTED_NAMES = ("run.json", "config.json", "features.json", "checkpoint")


def _is_converted_run(out: Path) -> bool:
    """Whether ``out`` holds a run written by this converter (its ``run.json`` records the source)."""
    import json

    try:
        record = json.loads((out / "run.json").read_text())
    except (OSError, ValueError):
        return False
    return isinstance(record, dict) and isinstance(record.get("extra"), dict) and "converted" in record["extra"]


def _feature_folder(features: str) -> Path | None:
    """The encoder folder a ``wav2vec2:PATH`` / ``hubert:PATH`` spec reads (None: ``logmel``), the spec
    checked by the one parser ``prepare`` uses too (and the folder's existence)."""
    from jaxtalk.data.features import parse_audio_features

    path = parse_audio_features(features).path
    return None if path is None else Path(path)


def _check_out(out: Path, overwrite: bool, inputs: list[Any]) -> None:
    """Refuse, before any work, an ``--out`` this conversion may not replace (see
    :func:`jaxtalk.files.claim_folder`): one holding an input or the working folder, a user's
    folder, or an earlier conversion without ``overwrite``."""
    from jaxtalk.files import claim_folder

    claim_folder(out, inputs, ours=_CONVERTED_NAMES, previous_output=_is_converted_run(out), overwrite=overwrite)


def write_converted_run(
    out: str | Path,
    config: TimarConfig,
    params: PyTree,
    normalizer: Any,
    *,
    features: str,
    args: dict[str, Any] | None = None,
    source: str | Path = "converted",
    weights: str = "ema",
    normalizer_kind: str = "identity",
    overwrite: bool = False,
) -> Path:
    """Write converted TIMAR parameters as an ordinary jaxtalk run folder.

    The folder holds ``run.json`` (preset ``"reference"``, the training settings the checkpoint's
    args give), ``config.json``, ``features.json`` (``features`` as the speech front end, the
    config's speech width) and an orbax checkpoint at step 0 with the parameters (an identity
    optimiser: a converted run samples and evaluates; it is not a run to resume). It is written
    under a temporary name beside ``out`` and renamed into place.

    Args:
        out: the run folder.
        config: the model config.
        params: the parameters (:func:`convert_state_dict`).
        normalizer: the :class:`~jaxtalk.models.timar.data.Normalizer` of the run's inputs.
        features: the speech front end spec (``wav2vec2:PATH``).
        args: the checkpoint's training arguments (recorded; training settings from them).
        source: the checkpoint it came from (recorded).
        weights: ``"ema"`` or ``"model"`` (recorded).
        normalizer_kind: where the normaliser came from (recorded).
        overwrite: replace an earlier conversion at ``out``.

    Returns:
        The run folder.

    Raises:
        ValueError: an existing non-empty ``out`` without ``overwrite``, ``out`` a file, or an ``out``
            that holds the working folder, an input or files the converter did not write (never
            replaced, ``overwrite`` or not); a bad ``features`` spec.
        FileNotFoundError: the encoder folder ``features`` names does not exist.
    """
    import jax
    import optax

    from jaxtalk.runs import CONFIG_FILE, FEATURES_FILE, RUN_FILE, RunInfo, checkpoint_dir, model_spec, write_run
    from jaxtalk.train import create_train_state, save_checkpoint

    out, args, source = Path(out), dict(args or {}), Path(source)
    _check_out(out, overwrite, [_feature_folder(features)])
    spec = model_spec("timar")
    settings = dataclasses.replace(
        spec.settings("paper"),
        weight_decay=float(args.get("weight_decay", 0.02)), clip_norm=float(args.get("grad_clip", 3.0)),
        ema_decay=float(args.get("ema_rate", 0.9999)), batch_size=int(args.get("batch_size", 32)),
    )
    norm = normalizer
    extra = {"normalizer": norm.to_dict(), "num_turns": config.max_turns, "still": norm.motion_mean.tolist(),
             "converted": {"from": str(source.absolute()), "weights": weights, "normalizer": normalizer_kind,
                           "args_model": str(args.get("model"))}}
    from jaxtalk.data.features import parse_audio_features

    # The spec as `prepare` records it (the folder made absolute), so the run finds its encoder from anywhere.
    feature_record = {"audio": parse_audio_features(features).spec, "tokens": None, "token_rate": None, "token_dim": None,
                      "speech_dim": None, "turn_speech_dim": config.speech_dim}

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.converting-", dir=out.parent))
    try:
        train_state = create_train_state(jax.tree_util.tree_map(np.asarray, params), optax.identity(), jax.random.key(0))
        save_checkpoint(checkpoint_dir(tmp).absolute(), train_state,
                        metadata={"model": "timar", "converted_from": str(source.name), "weights": weights})
        write_run(tmp, "timar", config, None, settings.optim(1), seed=0, extra=extra, settings=settings,
                  info=RunInfo(preset="reference", data_spec=f"converted:{source.name}"), features=feature_record)
        assert (tmp / RUN_FILE).is_file() and (tmp / CONFIG_FILE).is_file() and (tmp / FEATURES_FILE).is_file()
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.replaced-", dir=out.parent))
            out.rename(old / out.name)
            tmp.rename(out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            tmp.rename(out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return out


def convert_checkpoint(
    checkpoint: str | Path,
    out: str | Path,
    *,
    features: str,
    stats: str | Path | None = None,
    ema: bool = True,
    overwrite: bool = False,
) -> ConversionResult:
    """Convert a public-code checkpoint into a jaxtalk run folder.

    Everything is read and checked before anything is written; the folder is written under a
    temporary name beside ``out`` and renamed into place, so a failure leaves ``out`` as it was.

    Args:
        checkpoint: the ``.pth`` file (``torch.save`` of ``model``, ``model_ema``, ``args``).
        out: the run folder to write.
        features: the speech front end the run's inputs come from, as ``jaxtalk prepare
            --features`` takes it (``wav2vec2:PATH``, the ``wav2vec2-large-960h-lv60-self`` folder;
            evaluation data must be prepared with the same spec).
        stats: the public code's ``stat_flame.json``: the run's motion normaliser (None: the
            statistics in the checkpoint's args if it was trained with ``--do_norm``, else identity,
            with a warning).
        ema: convert the EMA weights (``model_ema``, what the public evaluation loads); False: the
            raw ``model`` weights.
        overwrite: replace an earlier conversion at ``out`` (a folder holding an input or anything
            else is never replaced).

    Returns:
        :class:`ConversionResult`.

    Raises:
        FileNotFoundError: a missing checkpoint, statistics file or feature folder.
        ValueError: any bad input (see :func:`read_checkpoint`, :func:`infer_config`,
            :func:`convert_state_dict`, :func:`read_stats`), an existing ``out`` without
            ``overwrite``.
    """
    import jax

    out = Path(out)
    _check_out(out, overwrite, [checkpoint, stats, _feature_folder(features)])
    ckpt = read_checkpoint(checkpoint)
    if ema and ckpt.ema is None:
        raise ValueError(f"{str(ckpt.path)!r} has no 'model_ema' weights; pass --no-ema to convert the raw ones")
    weights = "ema" if ema else "model"
    state = ckpt.ema if ema else ckpt.model
    config = infer_config(state, ckpt.args)
    params = convert_state_dict(state, config)
    norm, norm_kind = _normalizer(ckpt, config, stats)
    num_params = int(sum(np.size(x) for x in jax.tree_util.tree_leaves(params)))

    write_converted_run(out, config, params, norm, features=features, args=ckpt.args, source=ckpt.path,
                        weights=weights, normalizer_kind=norm_kind, overwrite=overwrite)
    return ConversionResult(run_dir=out, config=config, weights=weights, normalizer=norm_kind, num_params=num_params)
