"""Real synthesised speech with phoneme timings from eSpeak NG (a small ctypes binding).

``speak(text, voice="en-us", rate_wpm=175, pitch=50, pitch_range=50) -> Utterance``: eSpeak's audio
(22050 Hz, float32 in [-1, 1]) and its phoneme events, each an eSpeak phoneme mnemonic (stress marks
included, e.g. ``"'A:"``) with its start time in seconds, plus the time the audio ends.

The library and its data come from the ``espeakng-loader`` wheel. libespeak-ng keeps one global
synthesiser (voice, parameters, callback), so every call holds a module lock for its whole duration.
It also carries hidden state from one utterance to the next, so each call loads the library afresh
(initialised in synchronous mode with phoneme events), speaks, and unloads it again (about 5 ms), and
reseeds eSpeak's own noise generator: the same arguments give the same bytes, whatever was spoken
before. Variants built on the "klatt 6" (speechPlayer) engine draw from the C library's ``rand()``
instead and are not reproducible.
"""

from __future__ import annotations

import contextlib
import ctypes
import dataclasses
import functools
import os
import threading
from pathlib import Path

import numpy as np
from jaxtyping import Float

__all__ = ["SAMPLE_RATE", "RATE_RANGE", "Utterance", "speak", "has_variant", "version"]

SAMPLE_RATE = 22_050  # eSpeak NG's output rate
RATE_RANGE = (80, 450)  # words per minute, espeakRATE_MINIMUM / espeakRATE_MAXIMUM

# speak_lib.h
_AUDIO_OUTPUT_SYNCHRONOUS = 2
_INITIALIZE_PHONEME_EVENTS = 0x0001
_INITIALIZE_DONT_EXIT = 0x8000
_CHARS_UTF8 = 1
_POS_CHARACTER = 1
_EVENT_PHONEME = 7
_EE_OK, _EE_NOT_FOUND = 0, 2
_RATE, _VOLUME, _PITCH, _RANGE = 1, 2, 3, 4


class _EventId(ctypes.Union):
    _fields_ = [("number", ctypes.c_int), ("name", ctypes.c_char_p), ("string", ctypes.c_char * 8)]


class _Event(ctypes.Structure):
    # espeak_EVENT: ``audio_position`` is in ms from the start of the message; for a phoneme event
    # the union holds the mnemonic as char[8] (zero-terminated unless it needs all 8 bytes).
    _fields_ = [
        ("type", ctypes.c_int),
        ("unique_identifier", ctypes.c_uint),
        ("text_position", ctypes.c_int),
        ("length", ctypes.c_int),
        ("audio_position", ctypes.c_int),
        ("sample", ctypes.c_int),
        ("user_data", ctypes.c_void_p),
        ("id", _EventId),
    ]


_CALLBACK = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(ctypes.c_short), ctypes.c_int,
                             ctypes.POINTER(_Event))


@dataclasses.dataclass(frozen=True)
class Utterance:
    """What eSpeak said.

    Attributes:
        audio: ``(samples,)`` float32 in [-1, 1] at ``sample_rate``.
        sample_rate: eSpeak's rate (22050 Hz).
        phonemes: ``(mnemonic, start_s)`` of every phoneme event in time order. Mnemonics are
            eSpeak's phoneme names as reported (a leading ``'`` or ``,`` marks primary or secondary
            stress; ``_``, ``_:`` ... are pauses). Each phoneme lasts until the next one starts.
        end: seconds at which the last phoneme ends (the end of the audio).
    """

    audio: Float[np.ndarray, " samples"]
    sample_rate: int
    phonemes: tuple[tuple[str, float], ...]
    end: float


def _bind(lib: ctypes.CDLL) -> None:
    sigs = {
        "espeak_Initialize": ([ctypes.c_int, ctypes.c_int, ctypes.c_char_p, ctypes.c_int], ctypes.c_int),
        "espeak_SetSynthCallback": ([_CALLBACK], None),
        "espeak_SetVoiceByName": ([ctypes.c_char_p], ctypes.c_int),
        "espeak_SetParameter": ([ctypes.c_int, ctypes.c_int, ctypes.c_int], ctypes.c_int),
        "espeak_Synth": ([ctypes.c_char_p, ctypes.c_size_t, ctypes.c_uint, ctypes.c_int, ctypes.c_uint,
                          ctypes.c_uint, ctypes.c_void_p, ctypes.c_void_p], ctypes.c_int),
        "espeak_Synchronize": ([], ctypes.c_int),
        "espeak_Terminate": ([], ctypes.c_int),
        "espeak_Info": ([ctypes.c_void_p], ctypes.c_char_p),
    }
    for name, (args, res) in sigs.items():
        fn = getattr(lib, name)
        fn.argtypes, fn.restype = args, res


class _Collector:
    """Receives eSpeak's audio buffers and phoneme events (one synthesis at a time, under ``_LOCK``)."""

    def __init__(self) -> None:
        self.chunks: list[np.ndarray] = []
        self.events: list[tuple[str, int]] = []
        # Kept referenced for as long as a loaded library may call it.
        self.callback = _CALLBACK(self._on_synth)

    def _on_synth(self, wav, num_samples, events) -> int:
        if wav and num_samples > 0:
            self.chunks.append(np.ctypeslib.as_array(wav, (num_samples,)).copy())
        i = 0
        while events[i].type != 0:  # the list ends with espeakEVENT_LIST_TERMINATED
            ev = events[i]
            if ev.type == _EVENT_PHONEME:
                self.events.append((ev.id.string.decode("utf-8", errors="replace"), int(ev.audio_position)))
            i += 1
        return 0


_LOCK = threading.Lock()
_COLLECTOR = _Collector()


def _dlclose(handle: int) -> None:
    import _ctypes

    (getattr(_ctypes, "dlclose", None) or _ctypes.FreeLibrary)(handle)


@contextlib.contextmanager
def _fresh_library():
    """libespeak-ng loaded afresh, initialised, and unloaded again on exit.

    The synthesiser keeps state from one utterance to the next in C statics that no API call resets
    (the flutter phase of the pitch, the glottal cycle's phase, the automatic gain, the echo buffer):
    speaking the same text twice in one loaded library gives different samples and phoneme times
    (by about 1 ms). A fresh load starts every utterance from the same state (about 5 ms).
    """
    import espeakng_loader

    path = espeakng_loader.get_library_path()
    noload = getattr(os, "RTLD_NOLOAD", 0)
    if noload:
        try:
            resident = ctypes.CDLL(path, mode=noload)
        except OSError:
            resident = None
        if resident is not None:
            _dlclose(resident._handle)
            raise RuntimeError(
                f"{path} is already loaded by other code in this process; jaxtalk.audio.espeak needs to be "
                "its only user (it reloads the library for every utterance to make the output reproducible)")
    lib = ctypes.CDLL(path)
    try:
        _bind(lib)
        rate = lib.espeak_Initialize(_AUDIO_OUTPUT_SYNCHRONOUS, 0, str(_data_path()).encode(),
                                     _INITIALIZE_PHONEME_EVENTS | _INITIALIZE_DONT_EXIT)
        if rate != SAMPLE_RATE:
            raise RuntimeError(f"espeak_Initialize failed (returned {rate}) with data at {_data_path()}")
        lib.espeak_SetSynthCallback(_COLLECTOR.callback)
        try:
            yield lib
        finally:
            lib.espeak_Terminate()
    finally:
        handle = lib._handle
        del lib
        _dlclose(handle)


@functools.cache
def _data_path() -> Path:
    import espeakng_loader

    return Path(espeakng_loader.get_data_path())


def has_variant(variant: str) -> bool:
    """Whether eSpeak's data has a voice variant of this name (``m3``, ``f2``, ...)."""
    return (isinstance(variant, str) and bool(variant) and "/" not in variant and variant not in (".", "..")
            and (_data_path() / "voices" / "!v" / variant).is_file())


@functools.cache
def version() -> str:
    """eSpeak NG's version string (e.g. ``"1.52.0"``)."""
    with _LOCK, _fresh_library() as lib:
        return lib.espeak_Info(None).decode("utf-8", errors="replace")


def _check_int(name: str, value, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not lo <= value <= hi:
        raise ValueError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")
    return int(value)


def speak(text: str, *, voice: str = "en-us", rate_wpm: int = 175, pitch: int = 50,
          pitch_range: int = 50, volume: int = 100, seed: int = 0) -> Utterance:
    """Synthesise text with eSpeak NG and report when each phoneme starts.

    Args:
        text: what to say (UTF-8, read as plain text: no SSML, no ``[[phonemes]]``).
        voice: an eSpeak language (``"en-us"``, ``"de"``, ``"fr"``, ...), optionally with a voice
            variant: ``"en-us+m3"``, ``"de+f2"``.
        rate_wpm: speaking rate in words per minute, 80-450 (175 is eSpeak's normal).
        pitch: base pitch, 0-100 (50 normal; about an octave per 65).
        pitch_range: pitch range, 0-100 (0 monotone, 50 normal).
        volume: 0-200 (100 normal).
        seed: seeds eSpeak's noise generator (the same arguments give the same bytes).

    Returns:
        An :class:`Utterance`: audio at 22050 Hz and the phoneme events.

    Raises:
        ValueError: for empty text, an unknown language or variant, or a parameter out of range.
        RuntimeError: if the library fails to initialise or synthesise.
    """
    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"text must be a non-empty string, got {text!r}")
    if not isinstance(voice, str) or not voice or voice.count("+") > 1:
        raise ValueError(f"voice must be 'language' or 'language+variant', got {voice!r}")
    rate_wpm = _check_int("rate_wpm", rate_wpm, *RATE_RANGE)
    pitch = _check_int("pitch", pitch, 0, 100)
    pitch_range = _check_int("pitch_range", pitch_range, 0, 100)
    volume = _check_int("volume", volume, 0, 200)
    seed = _check_int("seed", seed, 0, 2**31 - 1)
    _, _, variant = voice.partition("+")
    if variant and not has_variant(variant):
        raise ValueError(f"unknown eSpeak voice variant {variant!r} in {voice!r} "
                         f"(variants are the files in {_data_path() / 'voices' / '!v'})")
    encoded = text.encode("utf-8")
    with _LOCK, _fresh_library() as lib:
        status = lib.espeak_SetVoiceByName(voice.encode("utf-8"))
        if status == _EE_NOT_FOUND:
            raise ValueError(f"unknown eSpeak voice {voice!r} (languages are e.g. en-us, en, de, fr, es)")
        if status != _EE_OK:
            raise RuntimeError(f"espeak_SetVoiceByName({voice!r}) failed with status {status}")
        for param, value in ((_RATE, rate_wpm), (_PITCH, pitch), (_RANGE, pitch_range), (_VOLUME, volume)):
            if lib.espeak_SetParameter(param, value, 0) != _EE_OK:
                raise RuntimeError(f"espeak_SetParameter({param}, {value}) failed")
        set_seed = getattr(lib, "espeak_ng_SetRandSeed", None)  # eSpeak NG >= 1.52
        if set_seed is not None:
            set_seed.argtypes, set_seed.restype = [ctypes.c_long], ctypes.c_int
            set_seed(seed)
        _COLLECTOR.chunks, _COLLECTOR.events = [], []
        try:
            status = lib.espeak_Synth(encoded, len(encoded) + 1, 0, _POS_CHARACTER, 0, _CHARS_UTF8, None, None)
            if status == _EE_OK:
                status = lib.espeak_Synchronize()
            chunks, events = _COLLECTOR.chunks, _COLLECTOR.events
        finally:
            _COLLECTOR.chunks, _COLLECTOR.events = [], []
    if status != _EE_OK:
        raise RuntimeError(f"espeak_Synth failed with status {status} for {text!r}")
    pcm = np.concatenate(chunks) if chunks else np.zeros(0, np.int16)
    if pcm.size == 0:
        raise ValueError(f"eSpeak produced no audio for {text!r} in voice {voice!r}")
    audio = (pcm.astype(np.float32) / 32768.0).astype(np.float32)
    end = pcm.size / SAMPLE_RATE
    # Events come in order; clamp to the audio (a final pause event sits at its very end).
    phonemes = tuple((name, min(ms / 1000.0, end)) for name, ms in events)
    return Utterance(audio=audio, sample_rate=SAMPLE_RATE, phonemes=phonemes, end=end)
