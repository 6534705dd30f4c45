r"""Control: does a SynthTalk mouth that leads its sound by more (0.10-0.16 s instead of 0.04-0.08 s)
make the demo model lead on real speech? (The tracked jaw of the DualTalk clip leads the clip's loudness
by 3 frames; the demo model follows the loudness 1-3 frames late.)

Prepares small+mic with the wider lead, trains the demo's model on it (400 steps, seed 0), then run
experiments/real_voice.py on the run:

    python experiments/real_voice_lead.py PREPARED_DIR
    jaxtalk train toktalk --data PREPARED_DIR --preset small --set sample_steps=1 --steps 400 --out RUN
    python experiments/real_voice.py --real ../shared/data/dualtalk_demo \
        --out experiments/results/real_voice/lead_0.10-0.16.json RUN
"""
import sys

from jaxtalk.data.synthtalk import speakers

speakers.STYLE_RANGES["lead"] = (0.10, 0.16)

from jaxtalk.data import synthtalk  # noqa: E402
from jaxtalk.data.prepare import prepare  # noqa: E402
from jaxtalk.data.sources import synthtalk_source  # noqa: E402

# A custom spec (its own cache name), else small+mic's cache of the usual lead would be reused.
spec = synthtalk.SIZES["small+mic"].__class__(**{**synthtalk.SIZES["small+mic"].__dict__, "tokenizer_seconds": 1e9 - 1})
corpus = synthtalk.generate(spec, 0, cache_dir=".cache/synthtalk")
prepare(synthtalk_source(corpus, spec="synthtalk:small+mic:0 lead 0.10-0.16"), sys.argv[1], progress=False)
