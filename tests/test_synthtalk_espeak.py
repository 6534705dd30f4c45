"""SynthTalk's eSpeak NG speakers: byte-identical from a seed (in memory, from the disk cache, from
cached timings), phone timelines that are eSpeak's phoneme events, audio placed where the timeline
says, lips and jaw moving at the events' times, voices fixed per speaker, and a SynthTalk phone for
every phoneme every voice says."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.signal import resample_poly

from jaxtalk.audio import espeak
from jaxtalk.data import synthtalk
from jaxtalk.data.sources import open_source
from jaxtalk.data.synthtalk import espeak_voice, speakers
from jaxtalk.data.synthtalk.emotions import voice_change
from jaxtalk.layout import EXP_INDEX, JAW_OPEN_INDEX

SR = 16_000
FPS = 25


@pytest.fixture(scope="module")
def corpus():
    return synthtalk.generate("tiny+espeak", seed=0)


def _espeak_clips(corpus):
    return [c for c in corpus.clips if c.style.espeak is not None]


def _is_pause(name: str) -> bool:
    base = name.lstrip("',")
    return base.startswith("_") or base in ("!", "?")


def _events_on_clip(req, phrase_start):
    """eSpeak's phoneme events of a phrase as (mnemonic, start, end) on the clip's clock, from the first
    sound to the last: the phrase starts where its first non-pause phoneme starts."""
    u = espeak.speak(req.text, voice=req.voice, rate_wpm=req.rate_wpm, pitch=req.pitch,
                     pitch_range=req.pitch_range, seed=req.seed)
    names = [n for n, _ in u.phonemes]
    bounds = [t for _, t in u.phonemes] + [u.end]
    sounding = [k for k, n in enumerate(names) if not _is_pause(n)]
    first, last = sounding[0], sounding[-1]
    shift = phrase_start - bounds[first]
    events = [(names[k], bounds[k] + shift, bounds[k + 1] + shift) for k in range(first, last + 1)]
    return events, u, bounds[first], bounds[last + 1]


# ------------------------------------------------------------------------------ determinism/cache
def test_tiny_espeak_is_byte_identical_from_a_seed(corpus, tmp_path):
    fresh = synthtalk.generate("tiny+espeak", seed=0, cache_dir=tmp_path)
    assert fresh.fingerprint(tokens=False) == corpus.fingerprint(tokens=False)
    assert fresh.metadata() == corpus.metadata()
    bundle = tmp_path / f"synthtalk-v{synthtalk.VERSION}-tiny+espeak-seed0.npz"
    timings = tmp_path / f"synthtalk-v{synthtalk.VERSION}-tiny+espeak-seed0-espeak-timings.npz"
    assert bundle.is_file() and timings.is_file()
    # Planned from the cached timings (no synthesis) and rendered again: the same bytes.
    bundle.unlink()
    replanned = synthtalk.generate("tiny+espeak", seed=0, cache_dir=tmp_path)
    assert replanned.fingerprint(tokens=False) == corpus.fingerprint(tokens=False)
    # The data spec names the size, and loads it from the same cache.
    source = open_source("synthtalk:tiny+espeak:0", cache_dir=tmp_path)
    assert source.spec == "synthtalk:tiny+espeak:0" and len(source.entries) == len(corpus.clips)


def test_another_seed_gives_another_corpus_and_share_zero_is_the_plain_size(corpus):
    spec = dataclasses.replace(synthtalk.SIZES["tiny+espeak"], speakers=(2, 0, 0, 0), clips_per_speaker=1,
                               conversations=(0, 0, 0, 0))
    a, b = synthtalk.generate(spec, seed=1), synthtalk.generate(spec, seed=2)
    assert a.fingerprint(tokens=False) != b.fingerprint(tokens=False)
    assert synthtalk.SIZES["tiny"].espeak_share == 0.0
    assert dataclasses.replace(synthtalk.SIZES["tiny+espeak"], espeak_share=0.0) == synthtalk.SIZES["tiny"]
    with pytest.raises(ValueError, match="espeak_share"):
        synthtalk.generate(dataclasses.replace(spec, espeak_share=1.5))


# ----------------------------------------------------------------------------------- speakers
def test_espeak_speakers_per_split_keep_their_voice(corpus):
    spec = synthtalk.SIZES["tiny+espeak"]
    for split, n in zip(synthtalk.SPLITS, spec.speakers):
        voices = [s.style.espeak for s in corpus.speakers if s.split == split]
        assert sum(v is not None for v in voices) == math.floor(n * spec.espeak_share + 0.5)
    train = [s.style.espeak for s in corpus.speakers if s.split == "train" and s.style.espeak]
    assert len({v.language for v in train}) == len(train)  # a split cycles through the languages
    assert {v.variant[0] for v in train} == {"m", "f"}
    for clip in corpus.clips:
        voice = corpus.speakers[clip.speaker].style.espeak
        assert clip.style.espeak == voice
        tl = clip.timeline
        assert len(tl.phrase_speech) == len(tl.phrase_starts)
        if voice is None:
            assert all(r is None for r in tl.phrase_speech)
        else:
            assert all(r.voice == voice.name for r in tl.phrase_speech)
            assert voice.language in espeak_voice.LANGUAGES and espeak.has_variant(voice.variant)
            assert clip.to_dict()["style"]["espeak"]["language"] == voice.language
    for sp in corpus.speakers:  # the voice survives the style's JSON form
        assert speakers.SpeakerStyle.from_dict(sp.style.to_dict()) == sp.style


def test_rate_pitch_and_backchannels_follow_style_and_emotion():
    style = dataclasses.replace(speakers.sample_style(np.random.default_rng(3)), rate=1.0)
    style = dataclasses.replace(style, espeak=espeak_voice.sample_voice(np.random.default_rng(4), style, "es"))
    neutral = espeak_voice.make_phrase(np.random.default_rng(5), style, voice_change("neutral", 1))
    afraid = espeak_voice.make_phrase(np.random.default_rng(5), style, voice_change("afraid", 3))
    sad = espeak_voice.make_phrase(np.random.default_rng(5), style, voice_change("sad", 3))
    assert neutral.speech.text == afraid.speech.text == sad.speech.text  # the same draws
    assert afraid.speech.pitch > neutral.speech.pitch > sad.speech.pitch
    assert afraid.speech.rate_wpm > neutral.speech.rate_wpm > sad.speech.rate_wpm
    assert afraid.duration < neutral.duration < sad.duration  # eSpeak's own durations
    assert neutral.accent_offsets.size >= 1 and np.all(neutral.accent_offsets < neutral.duration)
    bc = espeak_voice.make_backchannel(np.random.default_rng(6), style, voice_change("neutral", 1))
    assert bc.backchannel and bc.accent_offsets.size == 0 and bc.duration < 1.0
    assert bc.speech.text in espeak_voice.LANGUAGES["es"].backchannels


# ------------------------------------------------------------------------- timing and motion
def test_phone_boundaries_are_espeak_event_times_and_the_audio_is_there(corpus):
    checked = 0
    for clip in _espeak_clips(corpus):
        tl, lang = clip.timeline, clip.style.espeak.language
        bounds = np.append(tl.starts, tl.duration)
        audio = corpus.audio(clip.index).astype(np.float64)
        for req, ps, pe in zip(tl.phrase_speech, tl.phrase_starts, tl.phrase_ends):
            events, u, t0, t1 = _events_on_clip(req, ps)
            assert pe - ps == pytest.approx(t1 - t0, abs=1e-9)
            inside = bounds[(bounds >= ps - 1e-9) & (bounds <= pe + 1e-9)]
            expected = np.unique([s for _, s, e in events if e > s] + [pe])
            # Every event boundary is a phone boundary; the others split a diphthong or an affricate.
            assert np.abs(inside[None, :] - expected[:, None]).min(1).max() < 1e-9
            extra = sum(len(espeak_voice.phones_of(n, lang)) - 1 for n, s, e in events if e > s)
            assert len(inside) == len(expected) + extra
            # The channel holds eSpeak's audio resampled to 16 kHz, its first sound at the phrase start.
            ref = resample_poly(u.audio.astype(np.float64), 320, 441)
            n, i0, a0 = int(round((t1 - t0) * SR)), int(round(t0 * SR)), int(round(ps * SR))
            x, y = audio[a0 + 80:a0 + n - 80], ref[i0 + 80:i0 + n - 80]
            gain = float(x @ y / (y @ y))
            assert gain > 0 and np.linalg.norm(x - gain * y) < 0.02 * np.linalg.norm(x)
            checked += 1
    assert checked >= 40


def test_lips_close_on_bilabials_and_jaw_opens_on_open_vowels_at_event_times(corpus):
    taus = np.round(np.arange(-0.1, 0.1001, 0.005), 3)
    lips, jaws, bilabial_on, open_on = [], [], [[] for _ in taus], [[] for _ in taus]
    hits, bilabial_jaw, open_jaw = [], [], []
    for clip in _espeak_clips(corpus):
        tl, lang, lead = clip.timeline, clip.style.espeak.language, clip.style.lead
        oracle = corpus.oracle(clip.index).astype(np.float64)
        t = np.arange(len(oracle)) / FPS
        lip, jaw = oracle[:, EXP_INDEX["lip_close"]], oracle[:, JAW_OPEN_INDEX]
        lips.append(lip - lip.mean())
        jaws.append(jaw - jaw.mean())
        bilabial, opened = [], []
        for req, ps in zip(tl.phrase_speech, tl.phrase_starts):
            events, *_ = _events_on_clip(req, ps)
            for name, s, e in events:
                phones = espeak_voice.phones_of(name, lang)
                # The mouth leads the sound: a phone sounding over [s, e] shapes it over [s, e] - lead.
                c = 0.5 * (s + e) - lead
                if phones in (("p",), ("b",), ("m",)):
                    bilabial.append((s - lead, e - lead))
                    if e - s >= 0.05:
                        win = (t >= c - 0.1) & (t <= c + 0.1)
                        hits.append(abs(t[win][np.argmax(lip[win])] - c) <= 0.5 * (e - s) + 0.04)
                        bilabial_jaw.append(np.interp(c, t, jaw))
                elif phones == ("a",):
                    opened.append((s - lead, e - lead))
                    if e - s >= 0.06:
                        open_jaw.append(np.interp(c, t, jaw))
        for k, tau in enumerate(taus):
            for spans, out in ((bilabial, bilabial_on), (opened, open_on)):
                sp = np.asarray(spans).reshape(-1, 2) + tau
                out[k].append(((t[:, None] >= sp[:, 0]) & (t[:, None] < sp[:, 1])).any(1).astype(np.float64))
    assert len(hits) >= 20 and len(open_jaw) >= 20
    # Each long bilabial closes the lips most within its (led) span, and the jaw is open on /a/-like vowels.
    assert np.mean(hits) >= 0.9
    assert np.mean(open_jaw) > np.mean(bilabial_jaw) + 0.08
    # Pooled over every clip: lip closure follows the bilabial events, and the jaw the open vowels, at
    # the lead and at no other lag (a timeline 10 ms off eSpeak's events moves the best lag by 10 ms).
    lips, jaws = np.concatenate(lips), np.concatenate(jaws)
    r_lips = [np.corrcoef(lips, np.concatenate(x))[0, 1] for x in bilabial_on]
    r_jaw = [np.corrcoef(jaws, np.concatenate(x))[0, 1] for x in open_on]
    assert taus[int(np.argmax(r_lips))] == 0.0 and max(r_lips) > 0.6
    assert abs(taus[int(np.argmax(r_jaw))]) <= 0.005 and max(r_jaw) > 0.4


# ------------------------------------------------------------------------------ phone mapping
# Phrases of the generator that say a language's rarest phonemes (found by sweeping thousands of them).
_RARE = {
    "en-us": ["shiru ru wivoalay", "voa jofoaswak fesaypo the", "wiaro loalfee choagut yoora repego goapmeeit",
              "medoonfoa wareemoa mayfekay leeldee", "os voasooa hujotop fepo jitepa", "thoat noaten?",
              "pada larimfi.", "taoat ee foropu oon."],
    "en": ["wiaro loalfee choagut yoora repego goapmeeit", "ootamdoal o tiwoa soabay hehis wethoal!"],
    "de": ["fächschesze seukkämreu"],
    "fr": ["é chima ta moni"],
    "it": ["uul umurpa odu"],
    "pt-br": ["lisamo ospe er vopi chanau", "so govos tur gepoe."],
    "pl": ["kotisry siy giba punmu."],
    "fi": ["kal pusossas sö ka"],
}


def _coverage_texts(language: str) -> list[str]:
    """Every onset + vowel syllable, every vowel pair, every vowel + coda, the listener responses,
    random phrases, and phrases found to say the language's rarest phonemes."""
    o = espeak_voice.LANGUAGES[language]
    syllables = [on + v for on in o.onsets for v in o.vowels]
    words = [syllables[k] + syllables[(k * 7 + 3) % len(syllables)] for k in range(len(syllables))]
    words += [o.onsets[k % len(o.onsets)] + v + w for k, (v, w) in enumerate(
        (v, w) for v in o.vowels for w in o.vowels)]
    words += [v + c for v in o.vowels for c in o.codas]
    words += [on + v + c for on, v, c in zip(o.onsets * 9, o.vowels * 9, o.codas * 9)]
    rng = np.random.default_rng(0)
    return ([" ".join(words[k:k + 12]) for k in range(0, len(words), 12)] + list(o.backchannels)
            + [espeak_voice.phrase_text(rng, language) for _ in range(10)] + _RARE.get(language, []))


def test_every_phoneme_of_every_voice_maps_to_a_synthtalk_phone():
    variants = espeak_voice.MALE_VARIANTS + espeak_voice.FEMALE_VARIANTS
    assert all(espeak.has_variant(v) for v in variants)
    said = set()
    for k, language in enumerate(espeak_voice.LANGUAGES):
        for j, text in enumerate(_coverage_texts(language)):
            voice = f"{language}+{variants[(k + j) % len(variants)]}"
            for name, _ in espeak.speak(text, voice=voice).phonemes:
                if name.startswith("("):
                    continue  # a word eSpeak reads in another language (such phrases are redrawn)
                phones = espeak_voice.phones_of(name, language)  # raises for a mnemonic not in the table
                assert 1 <= len(phones) <= 3 and all(p in synthtalk.PHONES for p in phones)
                said.add(name.lstrip("',"))
    assert said == set(espeak_voice.MNEMONICS)  # the table has no entry that no voice says
    # A voice variant changes how a phoneme sounds, not which phonemes are said.
    text = _coverage_texts("de")[0]
    names = {tuple(n for n, _ in espeak.speak(text, voice=f"de+{v}").phonemes) for v in variants}
    assert len(names) == 1
    with pytest.raises(ValueError, match="no SynthTalk phone"):
        espeak_voice.phones_of("xyz", "en")
    with pytest.raises(ValueError, match="unknown SynthTalk eSpeak language"):
        espeak_voice.phones_of("a", "tlh")


def test_mapping_splits_diphthongs_and_affricates_and_cuts_pauses():
    names = ("_", "_:", "'aI", "tS", "@", "_|", "m", "_:", "_")
    starts = np.array([0.0, 0.0, 0.05, 0.25, 0.35, 0.40, 0.45, 0.55, 0.7])
    sp = espeak_voice.spoken_phones(names, starts, 0.72, "en-us")
    assert [synthtalk.PHONES[p] for p in sp.phones] == ["a", "i", "t", "sh", "e", "sil", "m"]
    np.testing.assert_allclose(sp.durations, [0.12, 0.08, 0.05, 0.05, 0.05, 0.05, 0.1])
    assert sp.stressed.tolist() == [True, False, False, False, False, False, False]
    assert (sp.start, sp.end) == (0.05, 0.55)
    with pytest.raises(ValueError, match="no SynthTalk phone"):
        espeak_voice.spoken_phones(("m", "Xq"), np.array([0.0, 0.1]), 0.2, "en-us")
