"""Live audio in pieces: the tokenizer stream gives exactly ``encode``'s tokens, each as soon as its audio
(and look-ahead) is in, at rates whose tokens are not whole numbers of log-mel frames too; TokTalk's
live stream gives exactly the offline streaming engine's frames over the whole audio, whatever the
pieces; ``jaxtalk stream`` on a WAV goes through it."""

from __future__ import annotations

import jax
import numpy as np
import pytest
import soundfile

from jaxtalk.audio import VQTokenizer

SR = 16000


def speechy(seconds: float, seed: int = 0) -> np.ndarray:
    """Bursts of tones and noise with pauses: tokens that change often."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(SR * seconds)) / SR
    envelope = (np.sin(2 * np.pi * 3 * t) > -0.2).astype(np.float32)
    tone = np.sin(2 * np.pi * (200 + 600 * (np.sin(2 * np.pi * 0.7 * t) + 1)) * t)
    return (0.3 * envelope * (tone + 0.3 * rng.standard_normal(t.size))).astype(np.float32)


@pytest.fixture(scope="module", params=[25, 30])
def tokenizer(request):
    # 25 Hz: four log-mel frames per token; 30 Hz: 3 1/3, so the groups' frame windows differ in phase.
    clips = [speechy(2.0, seed) for seed in range(3)]
    return VQTokenizer.fit(clips, rate=request.param, num_codes=12, width=8, seed=0, n_mels=32, stack=2)


@pytest.mark.parametrize("group", [1, 3])
def test_pieces_of_any_size_give_exactly_the_tokens_of_the_whole(tokenizer, group):
    audio = speechy(2.3, seed=7)
    want = tokenizer.encode(audio)
    rng = np.random.default_rng(group)
    stream = tokenizer.stream(group)
    ids, emb, pos = [], [], 0
    while pos < audio.size:
        n = int(rng.integers(1, 2500))
        got_ids, got_emb = stream.push(audio[pos:pos + n])
        pos += n
        assert got_ids.size % group == 0 and stream.tokens == sum(i.size for i in ids) + got_ids.size
        ids.append(got_ids)
        emb.append(got_emb)
    last_ids, last_emb = stream.finish()
    ids, emb = np.concatenate([*ids, last_ids]), np.concatenate([*emb, last_emb])
    np.testing.assert_array_equal(ids, want.ids)
    np.testing.assert_array_equal(emb, want.embeddings)
    assert stream.samples == 0 and stream.tokens == 0  # finished: ready for the next utterance


def test_a_group_comes_out_once_its_audio_and_lookahead_are_in_and_not_before(tokenizer):
    audio = speechy(1.0, seed=3)
    stream = tokenizer.stream(2)
    lookahead = round(tokenizer.lookahead_s * SR)  # the worst token's
    end = 2 * SR / tokenizer.rate  # the first group's window ends here
    need = stream.samples_needed
    assert end <= need <= end + lookahead and (tokenizer.rate != 25 or need == end + lookahead)
    assert stream.push(audio[: need - 1])[0].size == 0
    assert stream.samples_needed == 1
    ids, _ = stream.push(audio[need - 1:need])
    np.testing.assert_array_equal(ids, tokenizer.encode(audio).ids[:2])  # read nothing past `need`
    # Buffered audio stays bounded: only what later tokens still read is kept.
    stream.push(audio[need:])
    assert stream._buffer.size < 2 * SR / tokenizer.rate + tokenizer.n_fft


def test_bad_audio_is_refused_and_adds_nothing(tokenizer):
    stream = tokenizer.stream(1)
    stream.push(np.zeros(100, np.float32))
    with pytest.raises(ValueError, match="NaN"):
        stream.push(np.array([0.0, np.nan], np.float32))
    with pytest.raises(ValueError, match="mono"):
        stream.push(np.zeros((2, 2), np.float32))
    assert stream.samples == 100


@pytest.fixture(scope="module")
def live(trained_toktalk):
    from jaxtalk.models.toktalk.live import LiveModel
    from jaxtalk.runs import load_run

    return LiveModel.from_run(load_run(trained_toktalk.dir))


@pytest.mark.slow
def test_a_live_stream_equals_the_offline_engine_over_the_whole_audio_for_any_pieces(live, synthtalk_tiny):
    from jaxtalk.models import toktalk
    from jaxtalk.models.toktalk.live import frames_for_audio

    audio = np.asarray(synthtalk_tiny.audio(synthtalk_tiny.split("test")[1]), np.float32)[: int(SR * 2.37)]
    tokens = live.tokenizer.encode(audio).embeddings
    want = np.asarray(toktalk.stream(live.params, live.config, tokens[None], live.style, jax.random.key(4)))[0]
    want = want[: frames_for_audio(live.config, tokens.shape[0], audio.size)]
    stream = live.open(jax.random.key(4))
    for sizes in ([live.chunk_samples] * 40, [1234] * 40, [SR] * 3):
        pieces, pos = [], 0
        for n in sizes:
            if pos >= audio.size:
                break
            out = stream.push(audio[pos:pos + n])
            assert out.shape[0] % live.chunk_frames == 0 and out.shape[0] == stream.frames - sum(map(len, pieces))
            pieces.append(out)
            pos += n
        pieces.append(stream.finish())  # and the stream starts over, from the same key
        np.testing.assert_array_equal(np.concatenate(pieces), want)
    assert live.describe() == {"model": "toktalk", "fps": 25, "sample_rate": SR, "chunk_frames": 4,
                               "chunk_samples": 2560, "lookahead_samples": 40, "sample_steps": live.config.sample_steps}


@pytest.mark.slow
def test_a_live_streams_frames_so_far_stay_bitwise_when_the_later_audio_changes(live, synthtalk_tiny):
    audio = np.asarray(synthtalk_tiny.audio(synthtalk_tiny.split("test")[1]), np.float32)[: int(SR * 2.0)]
    cut = 4 * live.chunk_samples + live.lookahead_samples  # four chunks and their look-ahead are in
    other = audio.copy()
    other[cut:] = speechy((audio.size - cut) / SR, seed=7)[: audio.size - cut]
    emitted = {}
    for name, signal in (("same", audio), ("changed", other)):
        stream = live.open(jax.random.key(4))
        past = stream.push(signal[:cut])
        future = np.concatenate([stream.push(signal[cut:]), stream.finish()])
        emitted[name] = past, future
    assert emitted["same"][0].shape[0] == 4 * live.chunk_frames
    np.testing.assert_array_equal(emitted["changed"][0], emitted["same"][0])  # the past: bitwise the same
    assert not np.allclose(emitted["changed"][1], emitted["same"][1])  # the future follows the new audio


@pytest.mark.slow
def test_jaxtalk_stream_on_a_wav_runs_the_live_stream_chunk_by_chunk(live, trained_toktalk, synthtalk_tiny, tmp_path):
    from helpers import cli_ok

    from jaxtalk.data.formats import read_npz
    from jaxtalk.models import toktalk

    audio = np.asarray(synthtalk_tiny.audio(synthtalk_tiny.split("test")[0]), np.float32)[: int(SR * 1.01)]
    soundfile.write(tmp_path / "speech.wav", audio, SR, subtype="FLOAT")
    output = cli_ok(["stream", str(trained_toktalk.dir), str(tmp_path / "speech.wav"), "--out", str(tmp_path / "s.npz"),
                     "--seed", "2"])
    tokens = live.tokenizer.encode(audio).embeddings  # 13 tokens: 7 chunks, the last two after the audio's end
    want = np.asarray(toktalk.stream(live.params, live.config, tokens[None], live.style, jax.random.key(2)))[0][:25]
    np.testing.assert_array_equal(read_npz(tmp_path / "s.npz").params, want)
    lines = [line for line in output.splitlines() if line.startswith("chunk")]
    # Six pieces each complete a chunk (chunk k once 2560 (k + 1) + 40 samples are in); the seventh comes
    # with the utterance's end, from the audio's last 0.06 s padded with silence.
    assert [line.split(":")[0] for line in lines] == [f"chunk {i:3d}/7" for i in range(1, 8)]
    assert "2.5 ms of audio past its end" in output
