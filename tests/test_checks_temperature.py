"""jaxtalk.checks.check_temperature: the one check of a sampler's temperature."""

from __future__ import annotations

import numpy as np
import pytest

from jaxtalk.checks import check_temperature


def test_none_stands_for_the_samplers_default_and_a_value_is_kept():
    assert float(check_temperature(None, default=0.5)) == 0.5
    assert float(check_temperature(0.25, default=0.5)) == 0.25
    assert float(check_temperature(0.0)) == 0.0


def test_none_without_a_default_is_refused_naming_the_option():
    with pytest.raises(ValueError, match="--temperature is required"):
        check_temperature(None, name="--temperature")


@pytest.mark.parametrize("bad", [-0.1, float("nan"), float("inf"), np.ones(2)])
def test_negative_non_finite_or_non_scalar_temperatures_are_refused(bad):
    with pytest.raises(ValueError, match="temperature must be"):
        check_temperature(bad)
