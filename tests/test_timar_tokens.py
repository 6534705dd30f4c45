"""TIMAR turn layout: 110 tokens per 1-s turn, separators, interleave by hand, turn-causal mask."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.models.timar.config import TimarConfig
from jaxtalk.models.timar.tokens import SPANS, interleave, turn_layout


def test_layout_has_110_tokens_per_25_frame_turn_with_ten_separators():
    lay = turn_layout(25)
    assert lay.tokens == 110 == TimarConfig().tokens_per_turn
    assert sorted(lay.separator[lay.separator >= 0].tolist()) == list(range(10))
    assert np.array_equal(np.sort(lay.order), np.arange(110))
    # Each span is one contiguous run of 25 tokens in frame order, wrapped by its own separators.
    for s in range(len(SPANS)):
        pos = np.flatnonzero(lay.span == s)
        assert np.array_equal(pos, np.arange(pos[0], pos[0] + 25))
        assert np.array_equal(lay.frame[pos], np.arange(25))
        assert lay.separator[pos[0] - 1] == 1 + 2 * s and lay.separator[pos[-1] + 1] == 2 + 2 * s
    assert lay.separator[0] == 0 and lay.separator[-1] == 9
    assert np.array_equal(lay.agent_motion, np.flatnonzero(lay.span == 3))
    assert lay.user.shape == (50,) and set(lay.span[lay.user].tolist()) == {0, 1}


def test_interleave_places_every_token_by_hand():
    f, d = 3, 2
    # Token value encodes (span, frame) or (separator); a hand-written expected sequence.
    spans = [jnp.asarray([[10.0 * (s + 1) + j] * d for j in range(f)]).reshape(1, 1, f, d) for s in range(4)]
    seps = jnp.asarray([[-(k + 1.0)] * d for k in range(10)])
    out = np.asarray(interleave(*spans, seps))[0, 0, :, 0]
    expected = [-1, -2, 10, 11, 12, -3, -4, 20, 21, 22, -5, -6, 30, 31, 32, -7, -8, 40, 41, 42, -9, -10]
    assert out.tolist() == expected


def test_interleave_rejects_mismatched_spans_and_separator_table():
    x = jnp.zeros((1, 2, 25, 8))
    with pytest.raises(ValueError, match="one shape"):
        interleave(x, x, x, jnp.zeros((1, 2, 24, 8)), jnp.zeros((10, 8)))
    with pytest.raises(ValueError, match="separators"):
        interleave(x, x, x, x, jnp.zeros((9, 8)))
    with pytest.raises(ValueError, match="positive integer"):
        turn_layout(0)


def test_turn_causal_mask_matches_brute_force():
    lay = turn_layout(2)  # 18 tokens per turn
    m = lay.attention_mask(3)
    ids = lay.turn_ids(3)
    brute = np.array([[ids[k] <= ids[q] for k in range(len(ids))] for q in range(len(ids))])
    assert np.array_equal(m, brute)
    assert lay.attention_mask(3, causal=False).all()
    # Bidirectional inside a turn, nothing from the future.
    assert m[:18, :18].all() and not m[:18, 18:].any() and m[18:36, :36].all()
