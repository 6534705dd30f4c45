"""SynthTalk: jaxtalk's built-in procedural speech + 3D face motion corpus (spec:
``shared/design/SYNTHTALK.md``).

``generate(size="tiny"|"small"|"full"|"tiny+espeak"|"small+espeak", seed=0, cache_dir=None) ->
SynthTalkCorpus``. Modules: ``phones`` (inventory, acoustic recipes, visemes), ``emotions`` (EmoVOCA
face + voice effects), ``speakers`` (styles, in- and out-of-distribution), ``script`` (phrases and
timelines), ``speech`` (source-filter synthesis), ``espeak_voice`` (phrases spoken and timed by eSpeak
NG, and the mapping of its phonemes to SynthTalk's), ``motion`` (coarticulation, prosody, listener
reactions, stochastic parts), ``conversation`` (turn-taking, turn arousal, rendering), ``dyadic``
(delayed mimicry and the shared mood of conversations), ``ceiling`` (what context can explain),
``corpus`` (splits, cache, tokens, geometry).
"""

from jaxtalk.data.synthtalk.corpus import (
    SIZES,
    SPLITS,
    TOKEN_STREAMS,
    TOPOLOGIES,
    VERSION,
    ClipInfo,
    SizeSpec,
    Speaker,
    SynthTalkCorpus,
    generate,
)
from jaxtalk.data.synthtalk.dyadic import DEFAULT_EFFECTS, DyadicEffects
from jaxtalk.data.synthtalk.emotions import EMOTIONS
from jaxtalk.data.synthtalk.phones import PHONES
from jaxtalk.data.synthtalk.speakers import SpeakerStyle

__all__ = [
    "generate",
    "SynthTalkCorpus",
    "ClipInfo",
    "Speaker",
    "SpeakerStyle",
    "SizeSpec",
    "SIZES",
    "SPLITS",
    "TOKEN_STREAMS",
    "TOPOLOGIES",
    "VERSION",
    "EMOTIONS",
    "PHONES",
    "DyadicEffects",
    "DEFAULT_EFFECTS",
]
