"""What is said and when: phrases of CV(C) syllables with phone timings and pitch accents, laid out
on one speaker's timeline (silence fills every gap). A phrase spoken by eSpeak NG
(``espeak_voice.make_phrase``) carries what eSpeak is asked to say; its phones and durations are
eSpeak's own."""

from __future__ import annotations

import dataclasses

import numpy as np

from jaxtalk.data.synthtalk.emotions import VoiceChange
from jaxtalk.data.synthtalk.phones import CODAS, ONSETS, PHONE_INDEX, PHONES, SILENCE, VOWELS, recipe
from jaxtalk.data.synthtalk.speakers import SpeakerStyle

__all__ = ["SpeechRequest", "Phrase", "Timeline", "make_phrase", "make_backchannel", "layout_timeline"]

_DURATIONS = np.array([recipe(i).duration for i in range(len(PHONES))])
_BACKCHANNELS = (("m", "m"), ("i", "e", "a"), ("o", "k", "e"), ("a", "m"))


@dataclasses.dataclass(frozen=True)
class SpeechRequest:
    """What eSpeak NG is asked to say for one phrase (the arguments of ``jaxtalk.audio.espeak.speak``)."""

    text: str
    voice: str
    rate_wpm: int
    pitch: int
    pitch_range: int
    seed: int


@dataclasses.dataclass(frozen=True)
class Phrase:
    """One phrase before placement: phones with durations (s) and accents relative to its start.

    ``speech`` is None for SynthTalk's own synthesiser, else what eSpeak says (the audio of the phrase
    is then eSpeak's, cut to ``duration`` from its first phone on).
    """

    phones: np.ndarray          # (n,) int32
    durations: np.ndarray       # (n,) float64, seconds
    accent_offsets: np.ndarray  # (k,) float64, seconds from the phrase start
    accent_strengths: np.ndarray  # (k,) float64 in (0, 1]
    backchannel: bool = False
    arousal: float = 1.0  # loudness and pitch-range factor of the whole phrase (1 = the speaker's usual)
    speech: SpeechRequest | None = None

    @property
    def duration(self) -> float:
        return float(self.durations.sum())


@dataclasses.dataclass(frozen=True)
class Timeline:
    """One speaker's channel: contiguous phones covering ``[0, duration]`` plus prosodic events.

    Attributes:
        phones, starts, ends: ``(n,)`` phone ids and times in seconds; ``starts[0] == 0``,
            ``ends[-1] == duration``, no gaps (pauses are the silence phone).
        accents, accent_strengths: ``(k,)`` pitch-accent times (s) and strengths.
        phrase_starts, phrase_ends: ``(m,)`` times of each phrase; ``backchannel (m,)`` marks short
            listener responses ("mhm"), which are not turns.
        duration: seconds (a whole number of 25 fps frames).
        phrase_speech: ``(m,)`` each phrase's eSpeak request (None for source-filter phrases).
    """

    phones: np.ndarray
    starts: np.ndarray
    ends: np.ndarray
    accents: np.ndarray
    accent_strengths: np.ndarray
    phrase_starts: np.ndarray
    phrase_ends: np.ndarray
    backchannel: np.ndarray
    phrase_arousal: np.ndarray
    duration: float
    phrase_speech: tuple[SpeechRequest | None, ...] = ()

    def arousal_at(self, times: np.ndarray) -> np.ndarray:
        """The arousal of the phrase sounding at each time, 1 between phrases, ``(len(times),)``."""
        idx = np.searchsorted(self.phrase_starts, times, side="right") - 1
        inside = (idx >= 0) & (times < self.phrase_ends[np.maximum(idx, 0)])
        return np.where(inside, self.phrase_arousal[np.maximum(idx, 0)], 1.0)

    def speaking(self, times: np.ndarray) -> np.ndarray:
        """Whether a non-silence phone sounds at each time, ``(len(times),)`` bool."""
        idx = np.clip(np.searchsorted(self.ends, times, side="right"), 0, len(self.phones) - 1)
        return self.phones[idx] != SILENCE


def _scale(style: SpeakerStyle, voice: VoiceChange) -> float:
    return 1.0 / (style.rate * voice.rate)


def make_phrase(rng: np.random.Generator, style: SpeakerStyle, voice: VoiceChange) -> Phrase:
    """A random phrase of 2-6 words of 1-3 CV(C) syllables with one stress per word.

    Each word's stressed vowel is lengthened; about a third of the words carry a pitch accent (at
    least one per phrase), and the phrase-final vowel is lengthened.
    """
    # All draws up front (vectorised): a syllable is three slots [onset?, vowel, coda?].
    n_syl = rng.integers(1, 4, int(rng.integers(2, 7)))
    total = int(n_syl.sum())
    first = np.concatenate([[0], np.cumsum(n_syl)[:-1]])
    stressed_syl = first + np.floor(rng.random(len(n_syl)) * n_syl).astype(np.int64)
    slots = np.stack([
        np.where(rng.random(total) < 0.8, ONSETS[rng.integers(len(ONSETS), size=total)], -1),
        VOWELS[rng.integers(len(VOWELS), size=total)],
        np.where(rng.random(total) < 0.35, CODAS[rng.integers(len(CODAS), size=total)], -1),
    ], axis=1).reshape(-1)
    present = slots >= 0
    position = np.cumsum(present) - 1  # index in the phone list of each present slot
    ph = slots[present].astype(np.int32)
    st = position[3 * stressed_syl + 1]
    dur = _DURATIONS[ph] * _scale(style, voice) * rng.lognormal(0.0, 0.15, len(ph))
    dur[st] *= 1.35
    last_vowel = int(position[3 * total - 2])
    dur[last_vowel] *= 1.4
    accented = rng.random(len(st)) < 0.35
    accented[int(rng.integers(len(st)))] = True
    acc_pos = st[accented]
    onsets = np.concatenate([[0.0], np.cumsum(dur)[:-1]])
    offsets = onsets[acc_pos] + 0.5 * dur[acc_pos]
    strengths = rng.uniform(0.6, 1.0, len(acc_pos))
    return Phrase(ph, dur, offsets, strengths)


def make_backchannel(rng: np.random.Generator, style: SpeakerStyle, voice: VoiceChange) -> Phrase:
    """A short listener response ("mhm", "yeah", "okay"): no accents, soft."""
    words = _BACKCHANNELS[int(rng.integers(len(_BACKCHANNELS)))]
    ph = np.asarray([PHONE_INDEX[p] for p in words], dtype=np.int32)
    dur = _DURATIONS[ph] * _scale(style, voice) * rng.lognormal(0.0, 0.1, len(ph)) * 1.2
    return Phrase(ph, dur, np.zeros(0), np.zeros(0), backchannel=True)


def layout_timeline(phrases: list[Phrase], starts: list[float], duration: float) -> Timeline:
    """Place phrases at start times on a timeline of a given duration, silence in between.

    Args:
        phrases: phrases in time order.
        starts: their start times (s); phrases must not overlap each other.
        duration: total seconds; must cover the last phrase.

    Raises:
        ValueError: if phrases overlap or run past ``duration``.
    """
    ph_list, st_list, en_list = [], [], []
    acc, acc_s = [], []
    t = 0.0
    for phrase, s in zip(phrases, starts, strict=True):
        if s < t - 1e-9:
            raise ValueError(f"phrase starting at {s:.3f} s overlaps the previous one ending at {t:.3f} s")
        if s > t:
            ph_list.append(np.array([SILENCE], dtype=np.int32))
            st_list.append(np.array([t]))
            en_list.append(np.array([s]))
        ends = s + np.cumsum(phrase.durations)
        ph_list.append(phrase.phones)
        st_list.append(np.concatenate([[s], ends[:-1]]))
        en_list.append(ends)
        acc.append(s + phrase.accent_offsets)
        acc_s.append(phrase.accent_strengths)
        t = float(ends[-1])
    if t > duration + 1e-9:
        raise ValueError(f"phrases run to {t:.3f} s, past the timeline duration {duration:.3f} s")
    if duration > t:
        ph_list.append(np.array([SILENCE], dtype=np.int32))
        st_list.append(np.array([t]))
        en_list.append(np.array([duration]))
    p_starts = np.asarray(starts, dtype=np.float64)
    p_ends = p_starts + np.array([p.duration for p in phrases])
    return Timeline(
        phones=np.concatenate(ph_list).astype(np.int32),
        starts=np.concatenate(st_list),
        ends=np.concatenate(en_list),
        accents=np.concatenate(acc) if acc else np.zeros(0),
        accent_strengths=np.concatenate(acc_s) if acc_s else np.zeros(0),
        phrase_starts=p_starts,
        phrase_ends=p_ends,
        backchannel=np.array([p.backchannel for p in phrases], dtype=bool),
        phrase_arousal=np.array([p.arousal for p in phrases], dtype=np.float64),
        duration=float(duration),
        phrase_speech=tuple(p.speech for p in phrases),
    )
