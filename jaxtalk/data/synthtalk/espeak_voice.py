"""SynthTalk phrases spoken by eSpeak NG: real synthesised speech in several languages and voices,
with the phones (and so the motion) timed by eSpeak's own phoneme events.

A phrase is 2-6 pseudo-words of 1-3 syllables spelled with letters the language pronounces
regularly (``LANGUAGES``), said by the speaker's fixed voice (``EspeakVoice``: language + variant,
base rate, pitch and pitch range) at the rate and pitch of the speaker's style and emotion. eSpeak
reports when each phoneme starts; each mnemonic maps to one to three SynthTalk phones (``MNEMONICS``:
diphthongs split in two vowels, the first longer; affricates to a stop + fricative; pauses to
silence), and the phrase is cut to run from its first phone's start to its last phone's end, so the
timeline, the audio and hence the articulation all follow eSpeak's timing. Pitch accents go on
vowels eSpeak stresses. A mnemonic outside the table raises: no sound is silently taken for silence.

eSpeak's audio is 22050 Hz; a phrase is resampled to the corpus rate (``resample_poly``) and placed
on the channel at its start, scaled like the source-filter voice (emotion energy x phrase arousal).

Planning a corpus needs every phrase's duration, which only synthesis tells; inside
``timing_cache(path)`` the phone timings are looked up in (and added to) a file, so a corpus loaded
from its disk cache does not synthesise its phrases again.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import functools
import math
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
from jaxtyping import Float

from jaxtalk.audio import espeak
from jaxtalk.audio.io import resample_audio
from jaxtalk.data.synthtalk.emotions import VoiceChange
from jaxtalk.data.synthtalk.phones import PHONE_INDEX, PHONES, SILENCE
from jaxtalk.data.synthtalk.script import Phrase, SpeechRequest, Timeline
from jaxtalk.data.synthtalk.speakers import EspeakVoice, SpeakerStyle
from jaxtalk.files import atomic_savez

__all__ = [
    "LANGUAGES",
    "MALE_VARIANTS",
    "FEMALE_VARIANTS",
    "MNEMONICS",
    "Orthography",
    "phones_of",
    "sample_voice",
    "phrase_text",
    "SpokenPhones",
    "spoken_phones",
    "make_phrase",
    "make_backchannel",
    "phrase_audio",
    "render",
    "timing_cache",
]


@dataclasses.dataclass(frozen=True)
class Orthography:
    """How pseudo-words are spelled in one language: syllable onsets, vowels, optional codas (each
    a list of spellings the language reads one way), and the listener responses ("yeah") it uses."""

    onsets: tuple[str, ...]
    vowels: tuple[str, ...]
    codas: tuple[str, ...]
    backchannels: tuple[str, ...]


def _o(onsets: str, vowels: str, codas: str, backchannels: str) -> Orthography:
    return Orthography(tuple(onsets.split()), tuple(vowels.split()), tuple(codas.split()),
                       tuple(backchannels.split("|")))


LANGUAGES: dict[str, Orthography] = {
    "en-us": _o("b d f g h k l m n p r s t v w y sh ch th j", "a e i o u ee oo ay oa", "m n l s t k p",
                "yeah|okay|right|uh huh|sure"),
    "en": _o("b d f g h k l m n p r s t v w y sh ch th j", "a e i o u ee oo ay oa", "m n l s t k p",
             "yeah|okay|right|uh huh|sure"),
    "de": _o("b d f g h k l m n p r s t w sch z j", "a e i o u ei au ie eu ä ö ü", "m n l s t k ch",
             "ja|genau|okay|stimmt"),
    "fr": _o("b d f g l m n p r s t v ch j", "a é i o ou u on an eu ai", "l r", "oui|ouais|d'accord|ah bon"),
    "es": _o("b d f g l m n p r s t ch ll j k", "a e i o u", "n s l r", "sí|vale|claro|ya"),
    "it": _o("b d f g l m n p r s t v z", "a e i o u", "n l r", "sì|certo|va bene|già"),
    "pt-br": _o("b d f g l m n p r s t v ch j", "a e i o u", "l r s", "sim|tá|claro|isso"),
    "nl": _o("b d f g h k l m n p r s t v w z", "a e i o u oe ij aa ee oo ui", "n l s t k",
             "ja|oké|precies|klopt"),
    "pl": _o("b d f g h k l m n p r s t w sz cz ż", "a e i o u y ó", "n l s t k", "tak|no|dobrze|jasne"),
    "id": _o("b d f g h k l m n p r s t w c j y", "a e i o u", "n l s t k m ng", "ya|oke|iya|betul"),
    "sw": _o("b d f g h k l m n p r s t v w ch j sh y", "a e i o u", "", "ndiyo|sawa|eeh|kweli"),
    "fi": _o("d h k l m n p r s t v j", "a e i o u ä ö y aa ii", "n l s t", "joo|niin|okei|totta"),
    "cs": _o("b d f h k l m n p r s t v z š č ž ch", "a e i o u y á é í ů", "n l s t k",
             "jo|ano|jasně|dobře"),
    "hu": _o("b d f g h k l m n p r s t v z sz cs zs j", "a e i o u á é ö ü ó ő ú", "n l s t k",
             "igen|jó|aha|persze"),
}
# eSpeak's voice variants (none uses the "klatt 6" engine, whose noise is not reproducible).
MALE_VARIANTS: tuple[str, ...] = ("m1", "m2", "m3", "m4", "m5", "m6", "m7", "m8")
FEMALE_VARIANTS: tuple[str, ...] = ("f1", "f2", "f3", "f4", "f5")

# eSpeak phoneme mnemonic (stress marks removed) -> SynthTalk phones. eSpeak names a phoneme the
# same way in every language it has (IPA in the comments); the few that differ are in _OVERRIDES.
# Nearest class by mouth shape first, then sound: rounded front vowels go to the rounded class,
# fricatives without a class of their own to the class of their place (x -> k, C/Z -> sh, h -> th: an
# open, unrounded mouth with broad noise), glides to their vowel (j -> i).
MNEMONICS: dict[str, str] = {
    # pauses (word gaps, clause ends, the glottal onset _!, Dutch's assimilated-stop pause !, the
    # glottal stop ?)
    "_": "sil", "_:": "sil", "_|": "sil", "_!": "sil", "!": "sil", "?": "sil",
    # open and central vowels
    "a": "a", "a:": "a", "aa": "a", "A": "a", "A:": "a", "A@": "a", "a#": "a", "a-": "a", "V": "a", "&": "a",
    "&~": "a", "A~": "a",
    # front mid and schwa-like vowels
    "e": "e", "e:": "e", "E": "e", "E:": "e", "E#": "e", "E2": "e", "E~": "e", "@": "e", "@2": "e",
    "@-": "e", "3": "e", "3:": "e", "e@": "e",
    # close front
    "i": "i", "i:": "i", "I": "i", "I#": "i", "I2": "i", ";": "i", "j": "i", "J^": "i",
    # rounded back and front-rounded mid vowels
    "o": "o", "o:": "o", "O": "o", "O:": "o", "O2": "o", "o@": "o", "O@": "o", "0": "o", "O~": "o", "Y": "o",
    "Y:": "o", "W": "o", "8": "o",
    # close rounded
    "u": "u", "u:": "u", "U": "u", "y": "u", "y:": "u", "y-": "u",
    # diphthongs and vowel sequences (first part longer)
    "aI": "a i", "ai": "a i", "&i": "a i", "aU": "a u", "au": "a u", "&y": "a u", "VU": "a u",
    "eI": "e i", "ei": "e i", "EI": "e i", "eU": "e u", "EU": "e u", "eu": "e u", "ey": "e u",
    "oU": "o u", "ou": "o u", "OI": "o i", "oI": "o i", "oi": "o i", "OY": "o u", "Wy": "o u", "Yi": "o i",
    "Yy": "o u", "i@": "i e", "i@3": "i e", "ie": "i e", "iU": "i u", "iu": "i u", "iy": "i u",
    "U@": "u e", "uI": "u i", "ui": "u i", "uo": "u o", "yY": "u o", "yi": "u i",
    "aI@": "a i e", "aI3": "a i e", "@L": "e l",
    # consonants
    "p": "p", "b": "b", "B": "b", "m": "m", "f": "f", "v": "v", "v#": "v", "T": "th", "D": "th",
    "h": "th", "t": "t", "t2": "t", "t;": "t", "c": "t", "t#": "d", "d": "d", "d;": "d", "J": "d",
    "s": "s", "s2": "s", "s#": "s", "z": "z", "n": "n", "n-": "n", "n^": "n", "N": "n", "l": "l", "l^": "l",
    "k": "k", "x": "k", "g": "g", "Q": "g", "S": "sh", "S;": "sh", "Z": "sh", "Z;": "sh", "C": "sh", "w": "w",
    "w2": "w", "r": "r", "r-": "r", "R": "r", "R2": "r", "R^": "r", "*": "r", "**": "r",
    # affricates: closure, then the fricative
    "tS": "t sh", "dZ": "d sh", "ts": "t s", "dz": "d z",
}
# Where a language uses a mnemonic for another sound: American English "0" is the unrounded /ɑ/,
# Polish "y" the unrounded /ɨ/.
_OVERRIDES: dict[str, dict[str, str]] = {"en-us": {"0": "a"}, "pl": {"y": "i"}}
_VOWEL_IDS = frozenset(PHONE_INDEX[v] for v in "aeiou")

_BASE_WPM = 170.0   # eSpeak words per minute of a speaker with style rate 1
_MAX_TRIES = 50     # redraws of a phrase eSpeak would read partly in another language
_FADE = 0.004       # s, raised-cosine fade at both ends of a phrase's audio
# Overall output scale: eSpeak's vowels (RMS about 0.13 at volume 100) to the level of the source-filter
# voice's (about 0.04).
_LEVEL = 0.3


@functools.cache
def _table(language: str) -> dict[str, tuple[int, ...]]:
    table = dict(MNEMONICS) | _OVERRIDES.get(language, {})
    return {k: tuple(PHONE_INDEX[p] for p in v.split()) for k, v in table.items()}


def _base(mnemonic: str) -> str:
    return mnemonic.lstrip("',")


def phones_of(mnemonic: str, language: str) -> tuple[str, ...]:
    """SynthTalk phones of one eSpeak phoneme mnemonic in a language.

    Args:
        mnemonic: as eSpeak reports it (a leading stress mark ``'`` or ``,`` is ignored).
        language: one of ``LANGUAGES``.

    Raises:
        ValueError: for a language not in ``LANGUAGES`` or a mnemonic with no entry.
    """
    return tuple(PHONES[i] for i in _phone_ids(mnemonic, language))


def _phone_ids(mnemonic: str, language: str) -> tuple[int, ...]:
    if language not in LANGUAGES:
        raise ValueError(f"unknown SynthTalk eSpeak language {language!r}; known: {sorted(LANGUAGES)}")
    ids = _table(language).get(_base(mnemonic))
    if ids is None:
        raise ValueError(f"eSpeak phoneme {mnemonic!r} ({language}) has no SynthTalk phone: add it to "
                         "jaxtalk.data.synthtalk.espeak_voice.MNEMONICS")
    return ids


def sample_voice(rng: np.random.Generator, style: SpeakerStyle, language: str) -> EspeakVoice:
    """A speaker's eSpeak voice: a variant of the gender the style's f0 suggests, eSpeak's pitch placed
    by that f0 within its gender's band, the rate by the style's rate, and a random pitch range.

    Args:
        rng: NumPy generator (consumed).
        style: the speaker's style (``f0``, ``rate``).
        language: one of ``LANGUAGES``.
    """
    if language not in LANGUAGES:
        raise ValueError(f"unknown SynthTalk eSpeak language {language!r}; known: {sorted(LANGUAGES)}")
    female = style.f0 >= 150.0
    pool = FEMALE_VARIANTS if female else MALE_VARIANTS
    variant = pool[int(rng.integers(len(pool)))]
    lo, hi = (150.0, 230.0) if female else (95.0, 150.0)
    rel = float(np.clip((style.f0 - lo) / (hi - lo), 0.0, 1.0))
    return EspeakVoice(language=language, variant=variant, wpm=_BASE_WPM * style.rate,
                       pitch=25.0 + 45.0 * rel, pitch_range=float(rng.uniform(35.0, 65.0)))


def phrase_text(rng: np.random.Generator, language: str) -> str:
    """2-6 pseudo-words of 1-3 syllables ([onset] vowel [coda]) in a language's spelling, ending in
    ".", "?" or "!"."""
    o = LANGUAGES[language]
    words = []
    for _ in range(int(rng.integers(2, 7))):
        word = ""
        for _ in range(int(rng.integers(1, 4))):
            if rng.random() < 0.8:
                word += o.onsets[int(rng.integers(len(o.onsets)))]
            word += o.vowels[int(rng.integers(len(o.vowels)))]
            if o.codas and rng.random() < 0.35:
                word += o.codas[int(rng.integers(len(o.codas)))]
        words.append(word)
    end = "." if (u := rng.random()) < 0.75 else ("?" if u < 0.9 else "!")
    return " ".join(words) + end


def _request(ev: EspeakVoice, text: str, voice: VoiceChange, arousal: float, seed: int,
             backchannel: bool) -> SpeechRequest:
    # eSpeak's pitch parameter is about logarithmic: +65 doubles the pitch (measured on a monotone vowel).
    pitch = ev.pitch + 65.0 * math.log2(voice.pitch)
    prange = ev.pitch_range * voice.pitch_range * arousal * (0.5 if backchannel else 1.0)
    wpm = ev.wpm * voice.rate * (0.9 if backchannel else 1.0)
    return SpeechRequest(text=text, voice=ev.name, rate_wpm=int(np.clip(round(wpm), *espeak.RATE_RANGE)),
                         pitch=int(np.clip(round(pitch), 0, 100)), pitch_range=int(np.clip(round(prange), 0, 100)),
                         seed=seed)


@dataclasses.dataclass(frozen=True)
class _Timing:
    names: tuple[str, ...]
    starts: np.ndarray  # (n,) s
    end: float


def _speak(req: SpeechRequest) -> espeak.Utterance:
    return espeak.speak(req.text, voice=req.voice, rate_wpm=req.rate_wpm, pitch=req.pitch,
                        pitch_range=req.pitch_range, seed=req.seed)


_TIMINGS: contextvars.ContextVar[dict[SpeechRequest, _Timing] | None] = contextvars.ContextVar(
    "espeak_timings", default=None)


def _timing(req: SpeechRequest) -> _Timing:
    store = _TIMINGS.get()
    if store is not None and req in store:
        return store[req]
    utt = _speak(req)
    timing = _Timing(tuple(n for n, _ in utt.phonemes), np.array([t for _, t in utt.phonemes]), utt.end)
    if store is not None:
        store[req] = timing
    return timing


@functools.cache
def _engine_id() -> str:
    from importlib.metadata import version

    return f"eSpeak NG {espeak.version()}, espeakng-loader {version('espeakng-loader')}"


def _load_timings(path: Path) -> dict[SpeechRequest, _Timing]:
    try:
        with np.load(path, allow_pickle=False) as z:
            if str(z["engine"]) != _engine_id():
                return {}
            text, voice, params = z["text"], z["voice"], z["params"]
            names, starts, offsets, ends = z["names"], z["starts"], z["offsets"], z["ends"]
    except (OSError, KeyError, ValueError):
        return {}  # unreadable or from another layout: synthesise again
    out = {}
    for k in range(len(text)):
        req = SpeechRequest(str(text[k]), str(voice[k]), *(int(x) for x in params[k]))
        out[req] = _Timing(tuple(str(names[k]).split(" ")) if str(names[k]) else (),
                           starts[offsets[k]:offsets[k + 1]].copy(), float(ends[k]))
    return out


def _save_timings(path: Path, store: dict[SpeechRequest, _Timing]) -> None:
    reqs = list(store)
    timings = [store[r] for r in reqs]
    if any(" " in n for t in timings for n in t.names):
        raise ValueError("an eSpeak phoneme mnemonic contains a space; the timing cache cannot store it")
    atomic_savez(
        path,
        engine=np.asarray(_engine_id()),
        text=np.asarray([r.text for r in reqs], dtype=str),
        voice=np.asarray([r.voice for r in reqs], dtype=str),
        params=np.asarray([[r.rate_wpm, r.pitch, r.pitch_range, r.seed] for r in reqs], dtype=np.int64).reshape(-1, 4),
        names=np.asarray([" ".join(t.names) for t in timings], dtype=str),
        starts=np.concatenate([t.starts for t in timings]) if timings else np.zeros(0),
        offsets=np.cumsum([0] + [len(t.starts) for t in timings]),
        ends=np.asarray([t.end for t in timings], dtype=np.float64),
    )


@contextlib.contextmanager
def timing_cache(path: str | os.PathLike | None) -> Iterator[None]:
    """Within the block, eSpeak phrase timings come from (and go to) a cache file.

    The file (``.npz``, written atomically at the end of the block when something was added) maps
    each request to eSpeak's phoneme events; it is used only if it was written by the same eSpeak
    build. ``path=None``: a cache in memory for the block only.
    """
    store = _load_timings(Path(path)) if path is not None and Path(path).is_file() else {}
    known = len(store)
    token = _TIMINGS.set(store)
    try:
        yield
    finally:
        _TIMINGS.reset(token)
    if path is not None and len(store) > known:
        _save_timings(Path(path), store)


def _switches_language(t: _Timing) -> bool:
    # eSpeak reads a word it knows from another language's dictionary in that language and says so
    # with a "(en)" event.
    return any(n.startswith("(") for n in t.names)


@dataclasses.dataclass(frozen=True)
class SpokenPhones:
    """eSpeak's phonemes as SynthTalk phones, cut to the span from the first to the last sound.

    Attributes:
        phones: ``(n,)`` int32 phone ids; ``durations (n,)`` seconds, summing to ``end - start``.
        stressed: ``(n,)`` bool, the first vowel of each phoneme eSpeak gives primary stress.
        start, end: seconds in eSpeak's audio where the first phone starts and the last one ends.
    """

    phones: np.ndarray
    durations: np.ndarray
    stressed: np.ndarray
    start: float
    end: float


def spoken_phones(names: tuple[str, ...], starts: np.ndarray, end: float, language: str) -> SpokenPhones:
    """Map eSpeak phoneme events (mnemonic, start) plus the end of the audio to SynthTalk phones.

    Leading and trailing pauses are cut; zero-length events are dropped; a phoneme of several phones
    is split (a diphthong 60/40, three parts 40/30/30, consonant pairs in halves).

    Raises:
        ValueError: for a mnemonic with no SynthTalk phone, or events out of time order.
    """
    bounds = np.append(np.asarray(starts, dtype=np.float64), end)
    if np.any(np.diff(bounds) < 0):
        raise ValueError(f"eSpeak phoneme events out of time order: {list(zip(names, bounds))}")
    ids = [_phone_ids(n, language) for n in names]
    sounding = [k for k, p in enumerate(ids) if p != (SILENCE,)]
    if not sounding:
        raise ValueError(f"eSpeak said no phoneme but pauses: {names}")
    first, last = sounding[0], sounding[-1]
    phones, durations, stressed = [], [], []
    for k in range(first, last + 1):
        dur = bounds[k + 1] - bounds[k]
        if dur <= 0:
            continue
        parts = ids[k]
        if len(parts) == 2 and parts[0] in _VOWEL_IDS:
            weights = (0.6, 0.4)
        elif len(parts) == 3:
            weights = (0.4, 0.3, 0.3)
        else:
            weights = (1.0 / len(parts),) * len(parts)
        for j, (p, w) in enumerate(zip(parts, weights)):
            phones.append(p)
            durations.append(dur * w)
            stressed.append(j == 0 and p in _VOWEL_IDS and names[k].startswith("'"))
    return SpokenPhones(np.asarray(phones, dtype=np.int32), np.asarray(durations), np.asarray(stressed),
                        float(bounds[first]), float(bounds[last + 1]))


def _phrase(rng: np.random.Generator, ev: EspeakVoice, voice: VoiceChange, arousal: float,
            backchannel: bool) -> Phrase:
    for _ in range(_MAX_TRIES):
        if backchannel:
            words = LANGUAGES[ev.language].backchannels
            text = words[int(rng.integers(len(words)))]
        else:
            text = phrase_text(rng, ev.language)
        req = _request(ev, text, voice, arousal, int(rng.integers(2**31 - 1)), backchannel)
        timing = _timing(req)
        if not _switches_language(timing):
            break
    else:
        raise RuntimeError(f"eSpeak kept reading {ev.language} pseudo-words in another language")
    sp = spoken_phones(timing.names, timing.starts, timing.end, ev.language)
    if backchannel:
        return Phrase(sp.phones, sp.durations, np.zeros(0), np.zeros(0), backchannel=True, speech=req)
    # Pitch accents on about a third of the stressed vowels (at least one per phrase).
    cand = np.flatnonzero(sp.stressed)
    if cand.size == 0:
        cand = np.flatnonzero(np.isin(sp.phones, list(_VOWEL_IDS)))
    if cand.size == 0:
        cand = np.arange(len(sp.phones))
    accented = rng.random(len(cand)) < 0.35
    accented[int(rng.integers(len(cand)))] = True
    pos = cand[accented]
    onsets = np.concatenate([[0.0], np.cumsum(sp.durations)[:-1]])
    offsets = onsets[pos] + 0.5 * sp.durations[pos]
    strengths = rng.uniform(0.6, 1.0, len(pos))
    return Phrase(sp.phones, sp.durations, offsets, strengths, arousal=arousal, speech=req)


def make_phrase(rng: np.random.Generator, style: SpeakerStyle, voice: VoiceChange, arousal: float = 1.0) -> Phrase:
    """A phrase of pseudo-words said by the speaker's eSpeak voice, timed by eSpeak.

    Args:
        rng: NumPy generator (consumed; eSpeak's own noise is seeded from it).
        style: an eSpeak speaker (``style.espeak`` set).
        voice: the emotion's voice change (rate, pitch, pitch range; energy is applied at render).
        arousal: the phrase's loudness and pitch-range factor.

    Raises:
        ValueError: for a source-filter speaker, or an eSpeak phoneme with no SynthTalk phone.
    """
    if style.espeak is None:
        raise ValueError("espeak_voice.make_phrase needs an eSpeak speaker (style.espeak is None)")
    return _phrase(rng, style.espeak, voice, arousal, backchannel=False)


def make_backchannel(rng: np.random.Generator, style: SpeakerStyle, voice: VoiceChange) -> Phrase:
    """A short listener response in the speaker's language ("yeah", "ja", "oui"...): a little slower
    and flatter than a phrase, no accents."""
    if style.espeak is None:
        raise ValueError("espeak_voice.make_backchannel needs an eSpeak speaker (style.espeak is None)")
    return _phrase(rng, style.espeak, voice, 1.0, backchannel=True)


def phrase_audio(req: SpeechRequest, duration: float, sample_rate: int = 16_000) -> Float[np.ndarray, " samples"]:
    """The audio of one eSpeak phrase at ``sample_rate``, cut like its phones.

    Args:
        req: what eSpeak says.
        duration: the phrase's duration in its timeline (checked against eSpeak's timing now).
        sample_rate: output rate.

    Returns:
        ``(round(duration * sample_rate),)`` float32, eSpeak's level, faded in and out over 4 ms.

    Raises:
        RuntimeError: if eSpeak's timing no longer gives ``duration`` (a different eSpeak build).
    """
    utt = _speak(req)
    language = req.voice.partition("+")[0]
    sp = spoken_phones(tuple(n for n, _ in utt.phonemes), np.array([t for _, t in utt.phonemes]), utt.end,
                       language)
    if abs((sp.end - sp.start) - duration) > 1e-6:
        raise RuntimeError(f"eSpeak's timing of {req.text!r} changed: {sp.end - sp.start:.4f} s, planned "
                           f"{duration:.4f} s (was the corpus planned with another eSpeak build?)")
    audio = resample_audio(utt.audio, utt.sample_rate, sample_rate).astype(np.float64)
    i0 = int(round(sp.start * sample_rate))
    n = int(round(duration * sample_rate))
    seg = np.zeros(n)
    piece = audio[i0:i0 + n]
    seg[:len(piece)] = piece
    h = min(int(_FADE * sample_rate), n // 2)
    if h:
        ramp = 0.5 * (1.0 - np.cos(np.pi * (np.arange(h) + 0.5) / h))
        seg[:h] *= ramp
        seg[n - h:] *= ramp[::-1]
    return seg.astype(np.float32)


def render(timeline: Timeline, voice: VoiceChange, rng: np.random.Generator,
           sample_rate: int = 16_000) -> Float[np.ndarray, " samples"]:
    """Render a timeline whose phrases are all eSpeak's.

    Args:
        timeline: an eSpeak speaker's channel.
        voice: the emotion's voice change (its energy scales the level; rate and pitch are already
            in each phrase's request).
        rng: generator for the noise floor (consumed).
        sample_rate: output rate.

    Returns:
        ``(round(duration * sample_rate),)`` float32 mono audio in [-1, 1].
    """
    if any(s is None for s in timeline.phrase_speech):
        raise ValueError("espeak_voice.render needs a timeline of eSpeak phrases only")
    n = int(round(timeline.duration * sample_rate))
    audio = np.zeros(n)
    for req, s, e, arousal in zip(timeline.phrase_speech, timeline.phrase_starts, timeline.phrase_ends,
                                  timeline.phrase_arousal):
        seg = phrase_audio(req, float(e - s), sample_rate)
        a0 = int(round(s * sample_rate))
        seg = seg[: max(n - a0, 0)]
        audio[a0:a0 + len(seg)] += seg * arousal
    audio *= _LEVEL * voice.energy
    # The same faint noise floor as the source-filter voice.
    audio += 1e-4 * rng.standard_normal(n)
    return np.clip(audio, -1.0, 1.0).astype(np.float32)

