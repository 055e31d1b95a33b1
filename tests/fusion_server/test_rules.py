"""Fusion rules: mean (default), max, noisy-or, and the registry."""

import numpy as np
import pytest

from fusion_server.rules import FUSION_RULES, get_fusion_rule


def stack(*values: int) -> np.ndarray:
    return np.array(values, dtype=np.uint8).reshape(len(values), 1, 1)


def test_mean_rounds_to_nearest_byte():
    assert get_fusion_rule("mean")(stack(100, 201))[0, 0] == 151  # 150.5 rounds half up
    assert get_fusion_rule("mean")(stack(255, 255, 255))[0, 0] == 255
    assert get_fusion_rule("mean")(stack(0, 0))[0, 0] == 0


def test_max_and_noisy_or():
    assert get_fusion_rule("max")(stack(10, 200, 30))[0, 0] == 200
    # 1 - (1 - 0.5)(1 - 0.5) = 0.75
    # 128/255 = 0.502: 1 - 0.498**2 = 0.752 -> byte 192
    assert int(get_fusion_rule("noisy-or")(stack(128, 128))[0, 0]) == 192
    assert get_fusion_rule("noisy-or")(stack(0, 0))[0, 0] == 0


@pytest.mark.parametrize("name", sorted(FUSION_RULES))
def test_every_rule_maps_one_layer_to_itself(name):
    layer = np.arange(256, dtype=np.uint8).reshape(1, 16, 16)
    np.testing.assert_array_equal(FUSION_RULES[name](layer), layer[0])


def test_unknown_rule_lists_the_valid_ones():
    with pytest.raises(ValueError, match="mean, max, noisy-or"):
        get_fusion_rule("median")
