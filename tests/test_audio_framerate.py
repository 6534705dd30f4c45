"""Frame-rate conversion: hand-computed cases, a NumPy reference, causality, no recompilation."""

from __future__ import annotations

from fractions import Fraction

import jax
import numpy as np
import pytest

from jaxtalk.audio import default_num_frames, interpolation_plan, resample_features
from jaxtalk.audio.framerate import _blend

RAMP = np.array([[0.0], [10.0], [20.0], [30.0]], dtype=np.float32)


def test_upsample_hand_computed():
    # 12.5 Hz -> 25 fps: output frame j sits at input position j / 2.
    linear = resample_features(RAMP, 12.5, 25)
    np.testing.assert_array_equal(np.asarray(linear)[:, 0], [0, 5, 10, 15, 20, 25, 30, 30])
    previous = resample_features(RAMP, 12.5, 25, mode="previous")
    np.testing.assert_array_equal(np.asarray(previous)[:, 0], [0, 0, 10, 10, 20, 20, 30, 30])


def test_odd_ratio_hand_computed():
    # 60 -> 25 fps: output frame 1 at input position 2.4, frame 2 at 4.8.
    x = np.arange(12, dtype=np.float32)[:, None] ** 2
    out = np.asarray(resample_features(x, 60, 25, num_frames=3))[:, 0]
    np.testing.assert_allclose(out, [0.0, 0.6 * 4 + 0.4 * 9, 0.2 * 16 + 0.8 * 25], rtol=1e-6)
    prev = np.asarray(resample_features(x, 60, 25, num_frames=3, mode="previous"))[:, 0]
    np.testing.assert_array_equal(prev, [0.0, 4.0, 16.0])


def test_downsample_by_integer_factor_picks_frames():
    x = np.random.default_rng(0).standard_normal((101, 3)).astype(np.float32)
    for mode in ("linear", "previous"):
        out = np.asarray(resample_features(x, 100, 25, mode=mode))
        np.testing.assert_array_equal(out, x[::4][:25])


def test_default_num_frames():
    assert default_num_frames(101, 100, 25) == 25  # centred log-mel of 1 s -> 25 motion frames
    assert default_num_frames(25, 12.5, 25) == 50
    assert default_num_frames(50, 50, 25) == 25
    assert default_num_frames(3, 2, 3) == 5  # 4.5 rounds half up
    assert default_num_frames(1, 100, 25) == 1  # never zero


@pytest.mark.parametrize(("src", "dst"), [(60, 25), (29.97, 25), (50, 25), (7, 3), (12.5, 30)])
def test_linear_matches_numpy_interp(src, dst):
    rng = np.random.default_rng(1)
    x = rng.standard_normal((40, 5)).astype(np.float32)
    count = default_num_frames(40, src, dst) + 3  # a few frames past the end: held constant
    out = np.asarray(resample_features(x, src, dst, num_frames=count))
    t_in, t_out = np.arange(40) / src, np.arange(count) / dst
    ref = np.stack([np.interp(t_out, t_in, x[:, d]) for d in range(5)], axis=1)
    np.testing.assert_allclose(out, ref, atol=1e-5)


@pytest.mark.parametrize(
    ("src", "dst"), [(60, 25), (29.97, 25), (12.5, 25), (50, 25), (7, 3), (25, 25)]
)
def test_previous_takes_latest_frame_not_after_output_time(src, dst):
    count = 200
    lo, hi, weight = interpolation_plan(1000, src, dst, count, mode="previous")
    np.testing.assert_array_equal(lo, hi)
    assert np.all(weight == 0)
    # Brute force with exact rationals: time(lo[j]) <= t_j < time(lo[j] + 1).
    fs, fd = Fraction(str(float(src))), Fraction(str(float(dst)))
    for j in range(count):
        t = Fraction(j) / fd
        assert Fraction(int(lo[j])) / fs <= t < Fraction(int(lo[j]) + 1) / fs


def test_previous_is_causal():
    # Changing input frames later than an output frame's time never changes that output frame.
    rng = np.random.default_rng(2)
    x = rng.standard_normal((60, 4)).astype(np.float32)
    base = np.asarray(resample_features(x, 60, 25, mode="previous"))
    for cut in (7, 24, 41):  # input frame index from which the future is altered
        altered = x.copy()
        altered[cut:] += 100.0
        out = np.asarray(resample_features(altered, 60, 25, mode="previous"))
        visible = np.arange(base.shape[0]) / 25 < cut / 60  # outputs strictly before frame `cut`
        np.testing.assert_array_equal(out[visible], base[visible])
        assert not np.allclose(out[~visible], base[~visible])
    # Linear interpolation is not causal: it looks one input frame ahead.
    altered = x.copy()
    altered[3:] += 100.0
    lin = np.asarray(resample_features(altered, 60, 25, num_frames=2))
    assert not np.allclose(lin[1], np.asarray(resample_features(x, 60, 25, num_frames=2))[1])


def test_affine_streams_are_exact():
    t = np.arange(30) / 50.0
    x = np.stack([3.0 * t - 1.0, -2.0 * t], axis=1).astype(np.float32)
    out = np.asarray(resample_features(x, 50, 30, num_frames=17))
    t_out = np.arange(17) / 30.0
    np.testing.assert_allclose(out, np.stack([3.0 * t_out - 1.0, -2.0 * t_out], axis=1), atol=1e-5)


def test_other_rates_same_shapes_do_not_recompile():
    x = np.random.default_rng(3).standard_normal((30, 2)).astype(np.float32)
    resample_features(x, 60, 25, num_frames=12)
    before = _blend._cache_size()
    for src, dst in ((50, 25), (30, 12.5), (29.97, 24)):
        resample_features(x, src, dst, num_frames=12)
    assert _blend._cache_size() == before


def test_works_inside_jit():
    x = np.random.default_rng(4).standard_normal((20, 3)).astype(np.float32)
    inside = jax.jit(lambda a: resample_features(a, 50, 25, mode="previous"))(x)
    np.testing.assert_array_equal(
        np.asarray(inside), np.asarray(resample_features(x, 50, 25, mode="previous"))
    )


@pytest.mark.parametrize(
    ("x", "kwargs", "message"),
    [
        (np.zeros((0, 3), np.float32), {}, "empty"),
        (np.array([[np.nan]], np.float32), {}, "NaN"),
        (RAMP, {"mode": "nearest"}, "mode"),
        (RAMP, {"src_rate": 0}, "src_rate"),
        (RAMP, {"dst_rate": float("nan")}, "dst_rate"),
        (RAMP, {"num_frames": 0}, "num_frames"),
    ],
)
def test_bad_input_raises(x, kwargs, message):
    args = {"src_rate": 12.5, "dst_rate": 25, **kwargs}
    with pytest.raises(ValueError, match=message):
        resample_features(x, **args)


def test_wrong_rank_is_rejected():
    # The jaxtyping checker (tests) or resample_features' own check (library use) names the shape.
    with pytest.raises((TypeError, ValueError), match="frames.? dim"):
        resample_features(np.zeros(10, np.float32), 12.5, 25)
