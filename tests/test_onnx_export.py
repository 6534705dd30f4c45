"""The exported stream (``jaxtalk export-model``): its ONNX graphs, run by the reference host on onnxruntime,
against the library's own live stream.

* Fed the stream key's white noise, the host's frames equal :class:`~jaxtalk.models.toktalk.live.LiveStream`'s
  within 1e-4 over a sequence of chunks that fills the window, crosses the overlap and ends an utterance
  (the last chunk completed, the frames cropped), and over the next utterance after the reset.
* A planted change to one weight of ``step.onnx`` breaks that equality (the test can fail).
* The pieces: the tokenizer's fixed-shape group gives the streaming tokenizer's and ``encode``'s ids; a
  tokenizer whose groups fall on different phases of the log-mel hop is refused; the morph graph gives the
  server's ``morph`` output.
* The command: files and manifest; a folder holding other files, an earlier export without ``--overwrite``,
  a model without an export and a missing converter are refused with the reason.
"""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("jax2onnx")
onnx = pytest.importorskip("onnx")
pytest.importorskip("onnxruntime")

from helpers import cli_ok, cli_user_error  # noqa: E402

from jaxtalk.audio.tokenizer import VQTokenizer, group_tokens  # noqa: E402
from jaxtalk.export.onnx_host import OnnxStream  # noqa: E402
from jaxtalk.models.toktalk.config import TokTalkConfig  # noqa: E402
from jaxtalk.models.toktalk.live import LiveModel  # noqa: E402
from jaxtalk.models.toktalk.model import encode_style, init_params  # noqa: E402
from jaxtalk.models.toktalk.noise import frame_white_noise  # noqa: E402
from jaxtalk.models.toktalk.portable import export_stream  # noqa: E402

pytestmark = pytest.mark.slow


def _tokenizer(rate: float, width: int, floor_window: int = 7) -> VQTokenizer:
    rng = np.random.default_rng(0)
    return VQTokenizer(codebook=rng.standard_normal((64, 160)).astype(np.float32),
                       feature_mean=np.full(160, -5.0, np.float32), feature_scale=np.full(160, 3.0, np.float32),
                       embedding=rng.standard_normal((64, width)).astype(np.float32), rate=rate,
                       floor_window=floor_window)


def _speech(seconds: float, seed: int) -> np.ndarray:
    """Noise bursts of changing loudness (every 0.1 s), with silent stretches: tokens of many codes."""
    rng = np.random.default_rng(seed)
    n = int(seconds * 16000)
    level = np.repeat(rng.uniform(0, 0.3, n // 1600 + 1) * (rng.uniform(size=n // 1600 + 1) > 0.2), 1600)[:n]
    return (rng.standard_normal(n) * level).astype(np.float32)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """The tiny preset (random weights, a tokenizer with the noise-floor normaliser) exported."""
    config = TokTalkConfig.tiny()
    params = init_params(config, jax.random.key(0))
    clip = np.random.default_rng(1).standard_normal((1, 4 * config.style_frames, 56)).astype(np.float32) * 0.1
    model = LiveModel(params, config, _tokenizer(config.token_rate, config.speech_dim), encode_style(params, config, clip),
                      cfg_scale=1.0, temperature=0.5)
    folder = tmp_path_factory.mktemp("export")
    manifest = export_stream(model, folder, run_name="tiny")
    return model, folder, manifest


def _host_and_library(model, folder, key, utterances):
    """The same audio through the reference host (fed the key's white noise) and the library's live stream."""
    white = lambda first, frames: np.asarray(frame_white_noise(key, first, frames, 1, 56))[0]  # noqa: E731
    host, live = OnnxStream(folder, white=white), model.open(key)
    got, want = [], []  # per utterance
    for audio in utterances:
        pieces = [(host.push(audio[i:i + 2999]), live.push(audio[i:i + 2999]))  # pieces that are not chunks
                  for i in range(0, audio.size, 2999)]
        pieces.append((host.finish(), live.finish()))
        assert [g.shape for g, _ in pieces] == [w.shape for _, w in pieces]  # the same frames come out when
        got.append(np.concatenate([g for g, _ in pieces]))
        want.append(np.concatenate([w for _, w in pieces]))
    return got, want


def test_the_exported_stream_equals_the_library_stream_across_the_overlap_and_an_utterance_end(exported):
    model, folder, manifest = exported
    config = model.config
    # 5.2 s (13 chunks of 0.4 s: the 3-chunk window fills, every later chunk inpaints the overlap) ends with a
    # part chunk; then a second utterance after the reset.
    got, want = _host_and_library(model, folder, jax.random.key(3), [_speech(5.23, 0), _speech(1.7, 1)])
    assert [w.shape[0] for w in want] == [round(5.23 * config.fps), round(1.7 * config.fps)]
    got, want = np.concatenate(got), np.concatenate(want)
    np.testing.assert_allclose(got, want, atol=1e-4)
    assert np.abs(want).max() > 0.1  # real motion, not zeros
    assert manifest["chunk_frames"] == config.chunk_frames and manifest["sample_steps"] == config.sample_steps


def test_a_planted_change_to_one_weight_of_the_step_graph_breaks_the_equality(exported, tmp_path):
    import shutil

    from onnx import numpy_helper

    model, folder, _ = exported
    planted = tmp_path / "planted"
    shutil.copytree(folder, planted)
    graph = onnx.load(str(planted / "step.onnx"))
    weights = max(graph.graph.initializer, key=lambda t: int(np.prod(t.dims)))  # the largest weight matrix
    value = numpy_helper.to_array(weights).copy()
    value.flat[0] += 0.5
    weights.CopyFrom(numpy_helper.from_array(value, weights.name))
    onnx.save(graph, str(planted / "step.onnx"))
    got, want = _host_and_library(model, planted, jax.random.key(3), [_speech(3.0, 0)])
    assert np.abs(np.concatenate(got) - np.concatenate(want)).max() > 1e-3


def test_the_tokenizers_fixed_shape_group_gives_the_streaming_tokenizers_and_encodes_ids():
    tokenizer = _tokenizer(12.5, 32)
    stream = tokenizer.stream(5)
    layout = stream.layout()
    audio = _speech(3.0, 2)
    live = np.concatenate([stream.push(audio[i:i + 1234])[0] for i in range(0, audio.size, 1234)])
    history, ids, n = jnp.full((tokenizer.floor_window - 1, tokenizer.n_mels), jnp.inf), [], 0
    while (n + 1) * layout.hop_samples + layout.lookahead_samples <= audio.size:
        start = n * layout.hop_samples + layout.offset_samples
        window = np.zeros(layout.window_samples, np.float32)
        lo, hi = max(start, 0), min(start + layout.window_samples, audio.size)
        window[lo - start:hi - start] = audio[lo:hi]
        group, _, history = group_tokens(tokenizer, layout, jnp.asarray(window), history)
        ids.append(np.asarray(group))
        n += 1
    ids = np.concatenate(ids)
    assert ids.size == live.size >= 30 and len(set(ids.tolist())) > 3
    np.testing.assert_array_equal(ids, live)
    np.testing.assert_array_equal(ids, tokenizer.encode(audio).ids[: ids.size])


def test_a_group_that_is_not_whole_log_mel_hops_is_refused_a_fixed_layout():
    # 30 Hz tokens are 3.33 log-mel hops: one token's window starts on a different phase of the hop than the next.
    with pytest.raises(ValueError, match="not a whole number of 160-sample log-mel hops"):
        _tokenizer(30, 32).stream(1).layout()


def test_the_morph_graph_gives_the_servers_morph_output(exported):
    import onnxruntime

    from jaxtalk.face import builtin_face
    from jaxtalk.serve.outputs import MorphOutput

    _, folder, manifest = exported
    params = (np.random.default_rng(0).standard_normal((manifest["morph"]["frames"], 56)) * 0.3).astype(np.float32)
    morph = MorphOutput(builtin_face(0))
    _, want = morph.convert(morph.start(), params)
    got = onnxruntime.InferenceSession(str(folder / "morph.onnx")).run(None, {"params": params})[0]
    assert list(morph.channels) == manifest["morph"]["channels"]
    np.testing.assert_allclose(got, want, atol=1e-5)


def test_export_model_writes_the_graphs_manifest_host_and_refuses_to_write_over_other_files(trained_toktalk, tmp_path):
    out = tmp_path / "web"
    printed = cli_ok(["export-model", str(trained_toktalk.dir), "--out", str(out), "--no-page", "--sample-steps", "2"])
    assert "written frontend.onnx, step.onnx, morph.onnx, manifest.json and host.py" in printed
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["sample_steps"] == 2 and manifest["run"] == trained_toktalk.dir.name
    assert {"frontend.onnx", "step.onnx", "morph.onnx", "face.glb", "host.py"} <= {p.name for p in out.iterdir()}
    cli_user_error(["export-model", str(trained_toktalk.dir), "--out", str(out), "--no-page"], "pass --overwrite")
    cli_ok(["export-model", str(trained_toktalk.dir), "--out", str(out), "--no-page", "--overwrite"])
    other = tmp_path / "mine"
    other.mkdir()
    (other / "notes.txt").write_text("keep")
    cli_user_error(["export-model", str(trained_toktalk.dir), "--out", str(other)], "holds no earlier export")
    assert (other / "notes.txt").read_text() == "keep"
    cli_user_error(["export-model", str(trained_toktalk.dir), "--out", str(tmp_path / "x"), "--format", "tflite"],
                   "--format must be one of onnx")


def test_export_model_refuses_a_model_without_an_export_with_the_reason(trained_timar, tmp_path):
    cli_user_error(["export-model", str(trained_timar.dir), "--out", str(tmp_path / "web")], "TIMAR has no ONNX export (")


def test_every_model_either_exports_its_stream_or_says_why_not():
    from jaxtalk.runs import REGISTRY, model_spec

    for name in REGISTRY:
        spec = model_spec(name)
        assert (spec.export_stream is None) != (spec.export_refusal is None), name


def test_the_step_graphs_sampler_loop_carries_only_what_changes_from_step_to_step(exported):
    # The weights the Euler loop closes over are read from outside the loop (hoist_loop_constants), not carried
    # through it as state: the sample being transported and the step's counters are all that is carried.
    _, folder, _ = exported
    graph = onnx.load(str(folder / "step.onnx")).graph
    loops = [node for node in graph.node if node.op_type == "Loop"]
    assert len(loops) == 1
    body = next(a.g for a in loops[0].attribute if a.name == "body")
    carried = len(body.input) - 2
    assert 1 <= carried <= 4, carried
    assert not [n for n in body.node if n.op_type == "Identity" and n.input[0] in {i.name for i in body.input[2:]}]


def test_the_reference_host_refuses_a_folder_without_a_manifest_stereo_audio_and_nan(exported, tmp_path):
    _, folder, _ = exported
    with pytest.raises(FileNotFoundError, match="holds no manifest.json"):
        OnnxStream(tmp_path)
    host = OnnxStream(folder)
    with pytest.raises(ValueError, match="audio must be mono"):
        host.push(np.zeros((1600, 2), np.float32))
    with pytest.raises(ValueError, match="NaN or inf"):
        host.push(np.full(1600, np.nan, np.float32))
    with pytest.raises(ValueError, match=r"tokens must have shape \(n, 64\)"):
        host.push_tokens(np.zeros((5, 32), np.float32))


def test_the_exported_streams_past_frames_do_not_change_with_future_audio(exported):
    # Causality through the graphs: two recordings that agree for 2 s and then differ, each pushed whole (every
    # window could read the future), give bitwise the same frames for the chunks that the common 2 s complete
    # (as many as pushing the 2 s alone returns), and different frames after them.
    _, folder, _ = exported
    key = jax.random.key(5)
    white = lambda first, frames: np.asarray(frame_white_noise(key, first, frames, 1, 56))[0]  # noqa: E731
    common = _speech(2.0, 3)
    past = OnnxStream(folder, white=white).push(common).shape[0]
    whole = {}
    for seed in (4, 5):
        host = OnnxStream(folder, white=white)
        whole[seed] = np.concatenate([host.push(np.concatenate([common, _speech(2.0, seed)])), host.finish()])
    assert past >= 40
    np.testing.assert_array_equal(whole[4][:past], whole[5][:past])
    assert np.abs(whole[4][past:] - whole[5][past:]).max() > 1e-3


def test_an_export_that_fails_leaves_no_folder_behind(trained_toktalk, tmp_path, monkeypatch):
    import jaxtalk.viewer
    from jaxtalk.viewer import ViewerError

    def no_npm(folder, cache_dir=None):
        raise ViewerError("no npm here")

    monkeypatch.setattr(jaxtalk.viewer, "write_stream_page", no_npm)
    cli_user_error(["export-model", str(trained_toktalk.dir), "--out", str(tmp_path / "web"), "--sample-steps", "1"],
                   "no npm here")
    assert list(tmp_path.iterdir()) == []  # neither the folder nor the half-made one beside it
