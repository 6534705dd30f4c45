"""The eSpeak NG binding: audio, phoneme events and their timing against the audio, reproducibility,
the rate and pitch parameters, and errors."""

from __future__ import annotations

import numpy as np
import pytest

from jaxtalk.audio import espeak

SR = espeak.SAMPLE_RATE


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x, dtype=np.float64)))) if x.size else 0.0


def _segments(u: espeak.Utterance) -> list[tuple[str, float, float]]:
    bounds = [t for _, t in u.phonemes] + [u.end]
    return [(n, s, e) for (n, s), e in zip(u.phonemes, bounds[1:])]


def test_speak_gives_audio_and_phoneme_events_in_time_order_inside_it():
    u = espeak.speak("papa, mama", voice="en-us")
    assert u.sample_rate == SR == 22050
    assert u.audio.dtype == np.float32 and u.audio.ndim == 1 and u.audio.size > 0.4 * SR
    assert np.all(np.isfinite(u.audio)) and np.abs(u.audio).max() <= 1.0 and _rms(u.audio) > 0.01
    assert u.end == pytest.approx(u.audio.size / SR)
    times = np.array([t for _, t in u.phonemes])
    assert len(times) >= 8 and np.all(np.diff(times) >= 0) and times[0] >= 0 and times[-1] <= u.end
    assert all(isinstance(n, str) and n for n, _ in u.phonemes)


def test_a_known_word_gives_its_phonemes():
    u = espeak.speak("mama", voice="en-us")
    # eSpeak's mnemonics, primary stress marked with "'"; pauses ("_", "_:") close the utterance.
    assert [n for n, _ in u.phonemes if not n.startswith("_")] == ["m", "'A:", "m", "a#"]
    u = espeak.speak("papa", voice="es")
    assert [n for n, _ in u.phonemes if not n.startswith("_")] == ["p", "'a", "p", "a"]


def test_event_times_fall_on_the_matching_sounds():
    u = espeak.speak("papa, mama", voice="en-us")
    seg = _segments(u)
    loud = [_rms(u.audio[int(s * SR):int(e * SR)]) for n, s, e in seg if n.lstrip("'") in ("A:", "@", "a#")]
    # A /p/'s first 60 % is its closure: near silence before the burst.
    closures = [_rms(u.audio[int(s * SR):int((s + 0.6 * (e - s)) * SR)]) for n, s, e in seg if n == "p"]
    pauses = [_rms(u.audio[int(s * SR):int(e * SR)]) for n, s, e in seg if n == "_:" and e - s > 0.05]
    assert len(loud) == 4 and len(closures) == 2 and len(pauses) == 1
    assert min(loud) > 0.05
    assert max(closures) < 0.3 * min(loud)
    assert pauses[0] < 0.01 * min(loud)
    # Before the first phoneme eSpeak adds silence; the first vowel starts loud at its event.
    first_vowel = next(s for n, s, e in seg if n == "'A:")
    assert _rms(u.audio[: int(seg[0][1] * SR)]) < 0.01
    assert _rms(u.audio[int(first_vowel * SR):int((first_vowel + 0.03) * SR)]) > 0.05


def test_the_same_arguments_give_the_same_bytes_whatever_was_said_before():
    text = "bami tolu kenapo"
    a = espeak.speak(text, voice="en-us+f2")  # f2 is breathy: eSpeak's noise generator is used
    espeak.speak("etwas ganz anderes", voice="de+m3", rate_wpm=300, pitch=90)
    b = espeak.speak(text, voice="en-us+f2")
    assert a.audio.tobytes() == b.audio.tobytes() and a.phonemes == b.phonemes
    c = espeak.speak(text, voice="en-us+f2", seed=1)
    assert c.phonemes == a.phonemes and c.audio.tobytes() != a.audio.tobytes()


def _f0(x: np.ndarray) -> float:
    # Autocorrelation peak between 50 and 500 Hz.
    x = x - x.mean()
    ac = np.correlate(x, x, "full")[x.size - 1:]
    lo, hi = SR // 500, SR // 50
    return SR / (lo + int(np.argmax(ac[lo:hi])))


def test_rate_and_pitch_change_the_speech():
    text = "mama lima nomi"
    slow, fast = espeak.speak(text, rate_wpm=100), espeak.speak(text, rate_wpm=300)
    assert slow.end > 1.8 * fast.end
    assert [n for n, _ in slow.phonemes] == [n for n, _ in fast.phonemes]

    def vowel_f0(u):
        n, s, e = next(seg for seg in _segments(u) if seg[0].startswith("'"))  # the stressed vowel
        return _f0(u.audio[int(s * SR):int(e * SR)])

    # A long monotone vowel (range 0): eSpeak's pitch scale is about an octave per 65, so 80 apart is
    # about x2.4 (59 and 142 Hz).
    low, high = espeak.speak("maaaa", pitch=10, pitch_range=0), espeak.speak("maaaa", pitch=90, pitch_range=0)
    assert 2.0 < vowel_f0(high) / vowel_f0(low) < 3.0


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"text": ""}, "text"),
    ({"text": "   "}, "text"),
    ({"voice": "xx-nowhere"}, "unknown eSpeak voice 'xx-nowhere'"),
    ({"voice": "en-us+nosuchvariant"}, "variant 'nosuchvariant'"),
    ({"voice": "en+m1+f2"}, "voice"),
    ({"rate_wpm": 50}, "rate_wpm"),
    ({"pitch": 101}, "pitch"),
    ({"pitch_range": -1}, "pitch_range"),
    ({"volume": 300}, "volume"),
])
def test_errors_name_the_problem(kwargs, match):
    args = {"text": "hello"} | kwargs
    with pytest.raises(ValueError, match=match):
        espeak.speak(args.pop("text"), **args)
    assert espeak.speak("ok").audio.size > 0  # the library is usable after an error


def test_variants_are_voice_files():
    assert espeak.has_variant("m3") and espeak.has_variant("f2")
    assert not espeak.has_variant("nope") and not espeak.has_variant("../voices") and not espeak.has_variant("")
    assert espeak.version().count(".") >= 1
