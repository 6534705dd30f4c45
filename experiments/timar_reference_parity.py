"""TIMAR parity with the public reference code, number for number.

Builds the public code's ``TIMAR`` (``CoderChen01/towards-seamless-interaction``, ``model/timar.py``)
at a given size with random weights (every parameter drawn at random, including the ones the code
zero-initialises, so no stage passes trivially) and a small random wav2vec 2.0 in place of the
downloaded one, runs it, converts its state dict with :mod:`jaxtalk.models.timar.convert`, runs
jaxtalk on the same inputs and prints the largest difference at each stage:

* ``tokens``: the token embedding sequence entering the encoder (speech, motion, separators, the
  layout, the input projection and the mask token), 3 turns, 2 conversations;
* ``encoder``: the encoder output at every token (encoder-decoder: the decoder output), turn-causal;
* ``condition``: the diffusion head's condition at every agent frame (plus its positional table);
* ``head``: the diffusion head's raw output for given ``x_t``, ``t``, ``z``;
* ``mean`` / ``step std``: the reverse step's mean and standard deviation ``exp(log_variance / 2)``
  (the learned variance) at every step of the respaced 5-step schedule;
* ``turn speech``: the per-turn wav2vec 2.0 features (jaxtalk's ``prepare --features wav2vec2:PATH``
  front end on the reference's random wav2vec 2.0, against the reference's ``SpeechEncoder``; needs
  the ``safetensors`` package in jaxtalk's environment, the ``[encoders]`` extra, else not shown);
* ``sample turn 1`` / ``sample turn 2``: the public ``TIMAR.sample`` with CFG (scale 2, one MAR
  iteration, 5 ancestral steps, ``mask_history_agent`` as in the published evaluation) on two
  consecutive turns (the second with the first as history) against jaxtalk's ``stream_step`` given
  the same noises (torch's draws are recorded and passed through the samplers' noise hooks).

It exits non-zero when a deterministic stage differs by more than 1e-5 relative to its scale
(``max |a - b| / max(1, max |b|)``) or a sampled one by more than 1e-4.

Two interpreters: the reference runs under one with torch (it is never a jaxtalk dependency), jaxtalk
under jaxtalk's. The script re-runs itself under ``--torch-python`` for the reference half and reads
back an ``.npz``. Set-up, exactly as used for the numbers in the README::

    python3 -m venv /work/torchenv
    /work/torchenv/bin/pip install torch==2.13.0 numpy scipy tqdm transformers
    # the public code, e.g.
    git clone https://github.com/CoderChen01/towards-seamless-interaction /work/timar-ref
    python experiments/timar_reference_parity.py --reference-repo /work/timar-ref \\
        --torch-python /work/torchenv/bin/python --seed 0 --width 64 --depth 2 --heads 4

timm: the public code builds its blocks with ``timm.models.vision_transformer.Block``. timm imports
torchvision, and the CPU torch 2.13.0 does not load with the index's torchvision ("operator
torchvision::nms does not exist"), so when ``import timm`` fails the reference half puts
``experiments/timar_reference_standins`` first on its path: a minimal stand-in for timm's ``Block``
written to timm 1.0's definition (fused qkv with bias, pre-LN, exact GELU MLP, SDPA with the
additive mask) under timm's parameter names. The run prints which one it used.

``--save-fixture DIR`` stores the inputs, the reference's state dict and its outputs as one ``.npz``
(``tests/data/timar_reference/``; ``tests/test_timar_convert.py`` checks jaxtalk against it in CI
without torch).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
STANDINS = HERE / "timar_reference_standins"
TURNS = 3  # turns of the token / encoder stages
BATCH = 2
HEAD_ROWS = 16
CFG = 2.0
STEPS = 5
DETERMINISTIC_TOL = 1e-5
SAMPLED_TOL = 1e-4


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--reference-repo", required=True, type=Path, help="checkout of the public TIMAR code")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--width", type=int, default=64, help="encoder width (and token width)")
    p.add_argument("--depth", type=int, default=2, help="blocks: encoder-only: all of them; encoder-decoder: each half")
    p.add_argument("--heads", type=int, default=4)
    p.add_argument("--head-width", type=int, default=None, help="diffusion head width (default: --width)")
    p.add_argument("--speech-dim", type=int, default=48, help="wav2vec 2.0 hidden width of the random stand-in")
    p.add_argument("--max-turns", type=int, default=8, help="turns of the positional tables (max_context_time)")
    p.add_argument("--encoder-decoder", action="store_true", help="the MAE-style variant (no --use_encoder_only)")
    p.add_argument("--bidirectional", action="store_true", help="without --use_causal_attn")
    p.add_argument("--torch-python", default=sys.executable, help="interpreter with torch for the reference half")
    p.add_argument("--save-fixture", type=Path, default=None, help="write the reference's inputs/outputs here")
    p.add_argument("--torch-side", type=Path, default=None, help=argparse.SUPPRESS)
    return p


# --------------------------------------------------------------------------------------------------
# Reference half (torch only; no jax import)
# --------------------------------------------------------------------------------------------------


def _reference(args: argparse.Namespace) -> None:
    import importlib

    try:
        importlib.import_module("timm.models.vision_transformer")
        timm_used = "timm"
    except Exception:  # noqa: BLE001  (torchvision's operator error, or no timm)
        for name in [m for m in sys.modules if m == "timm" or m.startswith(("timm.", "torchvision"))]:
            del sys.modules[name]
        sys.path.insert(0, str(STANDINS))
        timm_used = "stand-in (experiments/timar_reference_standins)"
    sys.path.insert(0, str(args.reference_repo.resolve()))
    from functools import partial

    import torch
    import transformers

    torch.manual_seed(args.seed)
    w2v_config = transformers.Wav2Vec2Config(
        hidden_size=args.speech_dim, num_hidden_layers=2, num_attention_heads=4, intermediate_size=2 * args.speech_dim,
        conv_dim=(32,) * 7, do_stable_layer_norm=True, feat_extract_norm="layer", num_conv_pos_embeddings=16,
        num_conv_pos_embedding_groups=4, hidden_dropout=0.0, attention_dropout=0.0, activation_dropout=0.0,
        feat_proj_dropout=0.0, layerdrop=0.0, mask_time_prob=0.0,
    )
    w2v = transformers.Wav2Vec2Model(w2v_config).eval()
    transformers.Wav2Vec2Model.from_pretrained = classmethod(lambda cls, *a, **k: w2v)  # the "downloaded" one
    import model.timar as ref_timar  # noqa: E402  (the reference repository's package)

    width, depth = args.width, args.depth
    kwargs = dict(
        speech_snippet_embed_dim=args.speech_dim, token_embed_dim=width, encoder_embed_dim=width,
        decoder_embed_dim=width, encoder_num_heads=args.heads, decoder_num_heads=args.heads, mlp_ratio=4.0,
        norm_layer=partial(torch.nn.LayerNorm, eps=1e-6), use_causal_attn=not args.bidirectional,
        max_context_time=args.max_turns, diffloss_d=3, diffloss_w=args.head_width or width,
        num_sampling_steps=str(STEPS), use_encoder_only=not args.encoder_decoder,
    )
    if args.encoder_decoder:
        kwargs.update(encoder_depth=depth, decoder_depth=depth)
    else:  # the public encoder-only model stacks encoder_depth + decoder_depth blocks
        kwargs.update(encoder_depth=depth - depth // 2, decoder_depth=depth // 2)
    model = ref_timar.TIMAR(**kwargs)
    gen = torch.Generator().manual_seed(args.seed + 1)
    with torch.no_grad():  # every parameter random (the code zero-initialises the head's output layers)
        for name, p in model.named_parameters():
            if p.ndim >= 2 and "pos_embed" not in name:
                p.copy_(torch.randn(p.shape, generator=gen) / np.sqrt(p.shape[-1]))
            elif "norm" in name or "_ln" in name:
                base = 1.0 if name.endswith("weight") else 0.0
                p.copy_(base + 0.1 * torch.randn(p.shape, generator=gen))
            else:
                p.copy_(0.3 * torch.randn(p.shape, generator=gen))
    model.eval()
    out: dict[str, np.ndarray] = {}
    num = lambda t: t.detach().cpu().numpy().astype(np.float32)  # noqa: E731
    f = model.motion_fps * model.chunk_second
    rng = np.random.default_rng(args.seed + 2)

    # ---- speech features, recorded where the model computes them
    feats: list[np.ndarray] = []
    encode = model.speech_encoder.__class__.__call__

    def recording(self, chunk, num_frames):
        y = encode(self, chunk, num_frames)
        feats.append(num(y))
        return y

    model.speech_encoder.__class__.__call__ = recording

    with torch.no_grad():
        # ---- tokens and encoder over TURNS turns of BATCH conversations
        audio = torch.tensor(0.1 * rng.standard_normal((2, BATCH, TURNS * model.speech_frequency)), dtype=torch.float32)
        motion = torch.tensor(0.5 * rng.standard_normal((2, BATCH, TURNS * f, 56)), dtype=torch.float32)
        x, meta, _ = model.build_input_sequences(audio[0], motion[0], audio[1], motion[1])
        out["turn_speech"] = np.stack([feats[0].reshape(BATCH, TURNS, f, -1), feats[1].reshape(BATCH, TURNS, f, -1)])
        agent_frames = rng.random((TURNS, f)) < 0.6  # mask some agent frames (the same rows in both conversations)
        agent_frames[-1] = True
        mask = torch.zeros(x.shape[:2], dtype=torch.bool)
        am = meta["mask_agent_motion"][0].nonzero().squeeze(-1)
        mask[:, am[torch.tensor(agent_frames.reshape(-1))]] = True
        tokens = model.z_proj(x)
        tokens = torch.where(mask[..., None], model.mask_token.view(1, 1, -1), tokens) if not args.encoder_decoder else tokens
        out["tokens"] = num(tokens)
        t_len = x.shape[1]
        diff_pos = model.diffusion_pos_embed_learned[:, :t_len]
        if args.encoder_decoder:
            enc = model.forward_mae_encoder(x, mask, meta)
            z = model.forward_mae_decoder(enc, mask, meta)
        else:
            z = model.forward_encoder_only(x, mask, meta)
        out["encoder"] = num(z - diff_pos)
        out["condition"] = num(z[:, am])
        out["agent_frames"] = agent_frames
        out["inputs_motion"] = num(motion)

        # ---- the diffusion head and the reverse step for given x_t, t, z
        net = model.diffloss.net
        diff = model.diffloss.gen_diffusion
        hx = torch.randn(HEAD_ROWS, 56, generator=gen)
        hz = torch.randn(HEAD_ROWS, width, generator=gen)
        ht = torch.randint(0, 1000, (HEAD_ROWS,), generator=gen)
        out.update(head_x=num(hx), head_z=num(hz), head_t=ht.numpy().astype(np.int64), head=num(net(hx, ht, hz)))
        means, logvars = [], []
        for j in range(STEPS):
            pmv = diff.p_mean_variance(net, hx, torch.full((HEAD_ROWS,), j, dtype=torch.long), clip_denoised=False,
                                       model_kwargs=dict(c=hz))
            means.append(num(pmv["mean"]))
            logvars.append(num(pmv["log_variance"]))
        out["mean"], out["log_variance"] = np.stack(means), np.stack(logvars)

        # ---- two streamed turns of TIMAR.sample with CFG, recording torch's noise draws
        torch.Tensor.cuda = lambda self, *a, **k: self  # the code moves its noise to the GPU
        draws: list[np.ndarray] = []
        import model.diffloss as ref_diffloss
        import model.diffusion.gaussian_diffusion as ref_gd

        randn, randn_like = torch.randn, torch.randn_like

        def rec_randn(*a, **k):
            y = randn(*a, **k)
            draws.append(num(y))
            return y

        def rec_randn_like(t, *a, **k):
            y = randn_like(t, *a, **k)
            draws.append(num(y))
            return y

        ref_diffloss.torch.randn = rec_randn
        ref_gd.th.randn_like = rec_randn_like
        try:
            s_audio = torch.tensor(0.1 * rng.standard_normal((2, 2, model.speech_frequency)), dtype=torch.float32)
            s_motion = torch.tensor(0.5 * rng.standard_normal((2, f, 56)), dtype=torch.float32)
            history, samples, noise_turns = None, [], []
            feats.clear()
            for turn in range(2):
                draws.clear()
                y, history = model.sample(s_audio[0, turn][None], s_motion[turn][None], s_audio[1, turn][None], history,
                                          mask_history_agent=True, num_iter=1, cfg=CFG, cfg_schedule="linear",
                                          temperature=1.0)
                samples.append(num(y[0]))
                rows = draws[0].shape[0]  # x_T: the conditional half; the current turn's frames are the last f rows
                x_t = draws[0][rows - f:]
                steps = np.stack([d[rows - f: rows] for d in draws[1:]])
                noise_turns.append((x_t, steps))
        finally:
            ref_diffloss.torch.randn = randn
            ref_gd.th.randn_like = randn_like
        out["sample_speech"] = np.stack([np.stack([feats[2 * t][0], feats[2 * t + 1][0]]) for t in range(2)])
        out["sample_audio"] = num(s_audio)  # (speakers, turns, samples)
    with tempfile.TemporaryDirectory() as folder:  # the random wav2vec 2.0, for jaxtalk's front end
        w2v.save_pretrained(folder, safe_serialization=True)
        for name in ("config.json", "model.safetensors"):
            out[f"w2v/{name}"] = np.frombuffer((Path(folder) / name).read_bytes(), np.uint8)
        out["sample_user_motion"] = num(s_motion)
        out["sample_x_T"] = np.stack([n[0] for n in noise_turns])
        out["sample_step_noise"] = np.stack([n[1] for n in noise_turns])
        out["sample"] = np.stack(samples)

    state = {f"sd/{k}": num(v) for k, v in model.state_dict().items()}
    meta_json = json.dumps({
        "model": "custom", "encoder_num_heads": args.heads, "norm_eps": 1e-6, "use_causal_attn": not args.bidirectional,
        "use_encoder_only": not args.encoder_decoder, "noise_schedule": "cosine", "motion_fps": 25, "chunk_second": 1,
        "timm": timm_used, "seed": args.seed, "cfg": CFG, "steps": STEPS,
    })
    np.savez(args.torch_side, meta=np.asarray(meta_json), **out, **state)


# --------------------------------------------------------------------------------------------------
# jaxtalk half
# --------------------------------------------------------------------------------------------------


def load_reference(path: str | Path) -> tuple[dict, dict[str, np.ndarray], dict[str, np.ndarray]]:
    """``(args, state_dict, outputs)`` of a reference run's ``.npz`` (this script's output, or a fixture)."""
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    args = json.loads(str(data.pop("meta")))
    # Built by hand (no factory): every run of this script builds its blocks with eps 1e-6 (above),
    # which the committed fixtures' meta predates.
    args.setdefault("norm_eps", 1e-6)
    state = {k[3:]: v for k, v in data.items() if k.startswith("sd/")}
    outs = {k: v for k, v in data.items() if not k.startswith("sd/")}
    return args, state, outs


def jaxtalk_stages(
    args: dict, state: dict[str, np.ndarray], ref: dict[str, np.ndarray]
) -> dict[str, tuple[np.ndarray, np.ndarray, bool]]:
    """jaxtalk's value of every stage next to the reference's: ``{stage: (jaxtalk, reference, sampled)}``."""
    import jax
    import jax.numpy as jnp

    from jaxtalk.models.timar.convert import convert_state_dict, infer_config
    from jaxtalk.models.timar.encoder import TimarEncoder
    from jaxtalk.models.timar.head import apply_head
    from jaxtalk.models.timar.sampling import respaced_schedule
    from jaxtalk.models.timar.streaming import init_stream, stream_step
    from jaxtalk.models.timar.tokens import turn_layout
    from jaxtalk.masks import mask_to_bias
    from jaxtalk.samplers.diffusion import DiffusionState, _tables, ddpm_step
    from jaxtalk.samplers.flow import as_model

    config = infer_config(state, args)
    params = jax.tree_util.tree_map(jnp.asarray, convert_state_dict(state, config))
    f = config.frames_per_turn
    enc = TimarEncoder(config)
    call = lambda method, *a, **k: enc.apply({"params": params["encoder"]}, *a, method=method, **k)  # noqa: E731

    sp = jnp.asarray(ref["turn_speech"])  # (2, B, N, F, D)
    mo = jnp.asarray(ref["inputs_motion"].reshape(2, BATCH, TURNS, f, -1))
    agent_mask = jnp.broadcast_to(jnp.asarray(ref["agent_frames"]), (BATCH, TURNS, f))
    res: dict[str, tuple[np.ndarray, np.ndarray, bool]] = {}
    enc_dec = config.architecture == "encoder_decoder"
    tokens = call(TimarEncoder.embed, sp[0], mo[0], sp[1], mo[1], None if enc_dec else agent_mask, None)
    # Encoder-decoder: the reference's encoder drops the masked tokens, its input is every projected
    # token (agent frames from their motion); encoder-only: the masked agent frames hold the mask token.
    res["tokens"] = (np.asarray(tokens).reshape(ref["tokens"].shape), ref["tokens"], False)
    layout = turn_layout(f)
    visibility = jnp.asarray(layout.attention_mask(TURNS, causal=config.attention == "turn_causal"))
    masked_tokens = call(TimarEncoder.embed, sp[0], mo[0], sp[1], mo[1], agent_mask, None)
    if enc_dec:
        feats = call(TimarEncoder.encode_visible, masked_tokens, agent_mask, visibility)
        feats = call(TimarEncoder.decode, feats, agent_mask, visibility)
    else:
        feats = call(TimarEncoder.encode, masked_tokens, 0, mask_to_bias(visibility))
    res["encoder"] = (np.asarray(feats).reshape(ref["encoder"].shape), ref["encoder"], False)
    cond = call(TimarEncoder.head_condition, feats, 0)
    res["condition"] = (np.asarray(cond).reshape(ref["condition"].shape), ref["condition"], False)

    hx, hz, ht = (jnp.asarray(ref[k]) for k in ("head_x", "head_z", "head_t"))
    res["head"] = (np.asarray(apply_head(params["head"], config, hz, hx, ht.astype(jnp.float32))), ref["head"], False)
    schedule = respaced_schedule(config.schedule, config.num_timesteps, STEPS)
    tables = _tables(schedule.astype(jnp.float32), jnp.float32)  # sampling order: noisiest first
    apply_fn = as_model(jax.tree_util.Partial(lambda x, t, c: apply_head(params["head"], config, c, x, t)))
    means, logvars = [], []
    for j in range(STEPS):
        row = jax.tree_util.tree_map(lambda a, i=STEPS - 1 - j: a[i], tables)  # respaced index j
        kw = dict(apply_fn=apply_fn, cond=hz, variance="learned_range", prediction="x0")
        st = DiffusionState(x=hx, x0=jnp.zeros_like(hx))
        m = ddpm_step(st, row, jax.random.key(0), step_noise=jnp.zeros_like(hx), **kw).x
        one = ddpm_step(st, row, jax.random.key(0), step_noise=jnp.ones_like(hx), **kw).x
        means.append(np.asarray(m))
        logvars.append(np.asarray(one - m))
    res["mean"] = (np.stack(means), ref["mean"], False)
    # The step adds exp(log_variance / 2) x noise: with a unit noise the step's standard deviation is
    # read off exactly (compared on that scale: a log of a tiny std would amplify float32 rounding of
    # the mean). The last step (respaced index 0) adds no noise, so its variance is not observable.
    res["step std"] = (np.stack(logvars)[1:], np.exp(0.5 * ref["log_variance"][1:].astype(np.float64)), False)

    if "w2v/config.json" in ref and importlib.util.find_spec("safetensors") is not None:
        res["turn speech"] = (_jaxtalk_turn_speech(ref), np.moveaxis(ref["sample_speech"], 1, 0).reshape(2, 2 * f, -1), False)
    state_s = init_stream(config, jax.random.key(0), batch=1, context=config.max_turns - 1, guidance=True)
    for turn in range(2):
        speech = ref["sample_speech"][turn]  # (2 speakers, F, D)
        state_s, y = stream_step(
            params, config, state_s, speech[0][None], ref["sample_user_motion"][turn][None], speech[1][None],
            cfg_scale=ref_cfg(args), sample_steps=STEPS, sampler="ddpm", temperature=1.0,
            initial_noise=ref["sample_x_T"][turn][None], step_noise=ref["sample_step_noise"][turn][:, None],
        )
        res[f"sample turn {turn + 1}"] = (np.asarray(y[0]), ref["sample"][turn], True)
    return res


def _jaxtalk_turn_speech(ref: dict[str, np.ndarray]) -> np.ndarray:
    """jaxtalk's per-turn wav2vec 2.0 features (``prepare --features wav2vec2:PATH``) of the sampled
    turns' audio, ``(speakers, turns * 25, D)``, from the reference's random wav2vec 2.0 (saved in
    Hugging Face's format). The reference's ``SpeechEncoder`` takes the waveform as given (its data
    loader normalises whole recordings beforehand), so the folder says ``do_normalize: false``."""
    from jaxtalk.data.features import AudioFeatures

    with tempfile.TemporaryDirectory() as folder:
        for name in ("config.json", "model.safetensors"):
            (Path(folder) / name).write_bytes(ref[f"w2v/{name}"].tobytes())
        (Path(folder) / "preprocessor_config.json").write_text(json.dumps({"do_normalize": False, "sampling_rate": 16000}))
        features = AudioFeatures("wav2vec2", folder)
        audio = ref["sample_audio"]
        return np.stack([features.turn_speech(audio[s].reshape(-1), audio.shape[1]) for s in range(audio.shape[0])])


def ref_cfg(args: dict) -> float:
    """jaxtalk's guidance weight for the public code's ``--cfg`` omega (``u + omega (c - u)``): omega - 1."""
    return float(args.get("cfg", CFG)) - 1.0


def differences(stages: dict[str, tuple[np.ndarray, np.ndarray, bool]]) -> list[tuple[str, float, float, bool]]:
    """``(stage, max |diff|, relative, ok)`` per stage; relative = max |diff| / max(1, max |reference|)."""
    rows = []
    for name, (ours, theirs, sampled) in stages.items():
        if ours.shape != theirs.shape:
            raise ValueError(f"stage {name}: shapes differ, jaxtalk {ours.shape} vs reference {theirs.shape}")
        diff = float(np.max(np.abs(ours.astype(np.float64) - theirs)))
        rel = diff / max(1.0, float(np.max(np.abs(theirs))))
        rows.append((name, diff, rel, rel <= (SAMPLED_TOL if sampled else DETERMINISTIC_TOL)))
    return rows


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.torch_side is not None:
        _reference(args)
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "reference.npz"
        cmd = [args.torch_python, str(Path(__file__).resolve()), *(argv if argv is not None else sys.argv[1:]),
               "--torch-side", str(path)]
        if "--save-fixture" in cmd:  # the reference half does not write fixtures
            i = cmd.index("--save-fixture")
            del cmd[i:i + 2]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode:
            sys.stderr.write(proc.stderr[-4000:])
            print("error: the reference half failed (see above)", file=sys.stderr)
            return 2
        ref_args, state, outs = load_reference(path)
        if args.save_fixture is not None:
            args.save_fixture.mkdir(parents=True, exist_ok=True)
            name = f"{'encdec' if args.encoder_decoder else 'enc'}_w{args.width}_d{args.depth}_s{args.seed}.npz"
            import shutil

            shutil.copy(path, args.save_fixture / name)
            print(f"fixture: {args.save_fixture / name} ({(args.save_fixture / name).stat().st_size / 1e6:.1f} MB)")
    rows = differences(jaxtalk_stages(ref_args, state, outs))
    kind = "encoder-decoder" if args.encoder_decoder else "encoder-only"
    print(f"TIMAR parity: seed {args.seed}, width {args.width}, depth {args.depth}, heads {args.heads}, {kind}, "
          f"{'bidirectional' if args.bidirectional else 'turn-causal'}; timm: {ref_args['timm']}")
    print(f"{'stage':<16} {'max |diff|':>12} {'relative':>12}  ok")
    for name, diff, rel, ok in rows:
        print(f"{name:<16} {diff:12.3e} {rel:12.3e}  {'yes' if ok else 'NO'}")
    bad = [r[0] for r in rows if not r[3]]
    if bad:
        print(f"FAIL: {', '.join(bad)} above tolerance (1e-5 deterministic, 1e-4 sampled)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
