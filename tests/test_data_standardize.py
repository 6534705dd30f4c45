"""The per-channel standardiser: statistics by hand, masking, the floor, round trips and errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtalk.data.standardize import fit_standardizer, identity_standardizer, standardize, unstandardize


def test_statistics_match_hand_computed_values_and_ignore_masked_rows():
    x = np.array([[[1.0, 10.0], [3.0, 30.0], [99.0, -99.0]]])  # (1, 3, 2); the last frame is padding
    mask = np.array([[True, True, False]])
    stats = fit_standardizer(x, mask, floor=1e-3)
    np.testing.assert_allclose(stats["mean"], [2.0, 20.0])
    np.testing.assert_allclose(stats["std"], [1.0, 10.0])  # population std of {1, 3} and {10, 30}


def test_floor_is_relative_to_the_mean_spread():
    rng = np.random.default_rng(0)
    x = np.stack([rng.normal(size=500), 1e-6 * rng.normal(size=500)], axis=-1)
    stats = fit_standardizer(x, floor=0.1)
    assert stats["std"][1] == pytest.approx(0.1 * (x[:, 0].std() + x[:, 1].std()) / 2, rel=1e-5)


def test_round_trip_zero_mean_unit_spread_and_no_gradient_into_stats():
    rng = np.random.default_rng(1)
    x = (rng.normal(size=(4, 50, 3)) * [0.01, 1.0, 5.0] + [0.0, 2.0, -3.0]).astype(np.float32)
    stats = fit_standardizer(x, floor=1e-4)
    z = standardize(stats, jnp.asarray(x))
    np.testing.assert_allclose(np.asarray(z).reshape(-1, 3).mean(0), 0.0, atol=1e-5)
    np.testing.assert_allclose(np.asarray(z).reshape(-1, 3).std(0), 1.0, atol=1e-4)
    np.testing.assert_allclose(np.asarray(unstandardize(stats, z)), x, atol=1e-5)
    g = jax.grad(lambda s: jnp.sum(standardize(s, jnp.asarray(x))))({k: jnp.asarray(v) for k, v in stats.items()})
    assert all(float(jnp.abs(v).max()) == 0.0 for v in g.values())


def test_identity_standardizer_is_the_identity():
    x = jnp.arange(6.0).reshape(2, 3)
    np.testing.assert_array_equal(np.asarray(standardize(identity_standardizer(3), x)), np.asarray(x))


@pytest.mark.parametrize(
    ("x", "mask", "match"),
    [
        (np.zeros((1, 3)), None, "at least 2"),
        (np.array([[0.0], [np.nan], [1.0]]), None, "NaN"),
    ],
)
def test_bad_input_is_named(x, mask, match):
    with pytest.raises(ValueError, match=match):
        fit_standardizer(x, mask)


def test_mask_of_the_wrong_shape_is_rejected():
    # Under the jaxtyping import hook the annotation catches it first (TypeError); without it, our check.
    with pytest.raises((ValueError, TypeError), match="mask|batch"):
        fit_standardizer(np.zeros((4, 3)), np.ones((3,), bool))


def test_numpy_input_is_standardised_in_numpy_to_float32_rounding_of_jax():
    rng = np.random.default_rng(0)
    x = rng.normal(3.0, 2.0, (4, 7, 5)).astype(np.float32)
    stats = fit_standardizer(x.reshape(-1, 5))
    z = standardize(stats, x)
    assert isinstance(z, np.ndarray) and z.dtype == np.float32
    np.testing.assert_allclose(z, np.asarray(standardize(stats, jnp.asarray(x))), rtol=3e-7, atol=0)
    back = unstandardize(stats, z)
    assert isinstance(back, np.ndarray) and back.dtype == np.float32
    np.testing.assert_allclose(back, np.asarray(unstandardize(stats, jnp.asarray(z))), rtol=3e-7, atol=0)
