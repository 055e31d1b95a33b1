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


def test_mean_counts_only_the_layers_covering_a_cell_and_falls_back_where_none_does():
    values = np.stack([np.full((2, 2), 200, np.uint8), np.zeros((2, 2), np.uint8)])
    covered = np.ones((2, 2, 2), dtype=bool)
    covered[1, 0, 0] = False  # the second UAV does not see cell (0, 0): its zero must not count
    covered[:, 1, 1] = False  # nobody's footprint holds (1, 1): the tile-level mean of both layers
    fused = get_fusion_rule("mean")(values, covered)
    assert fused[0, 0] == 200
    assert fused[0, 1] == 100 and fused[1, 1] == 100
    np.testing.assert_array_equal(get_fusion_rule("mean")(values, np.ones_like(covered)), np.full((2, 2), 100))


@pytest.mark.parametrize("name", sorted(FUSION_RULES))
def test_every_rule_ignores_a_non_covering_layer(name):
    values = np.stack([np.full((1, 1), 120, np.uint8), np.full((1, 1), 250, np.uint8)])
    covered = np.array([[[True]], [[False]]])
    assert FUSION_RULES[name](values, covered)[0, 0] == 120
    with pytest.raises(ValueError, match="does not match"):
        FUSION_RULES[name](values, covered[:, :, :0])
