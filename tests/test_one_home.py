"""Issue 13: each concept has one home; the old names are that one function, and it is right."""

import numpy as np
import pytest

from evnoise import radiometry
from evnoise.reconstruct import imaging
from generators import pairs


def test_srgb_names_are_one_function():
    assert imaging.srgb_encode is radiometry.srgb_encode
    assert pairs.linear_to_srgb is radiometry.srgb_encode
    assert imaging.srgb_decode(np.array([0.5])) == radiometry.srgb_to_linear(np.array([0.5]))


def test_srgb_encode_matches_colour_science():
    colour = pytest.importorskip("colour")
    v = np.linspace(0.0, 1.0, 1001)
    np.testing.assert_allclose(radiometry.srgb_encode(v), colour.models.eotf_inverse_sRGB(v), rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(imaging.srgb_decode(radiometry.srgb_encode(v)), v, atol=1e-12)
    np.testing.assert_array_equal(imaging.srgb_decode(np.array([-0.5, 1.5])), [0.0, 1.0])  # clipped


def test_block_sum_is_one_function():
    assert imaging.block_sum is radiometry.block_sum
    assert pairs.bin_sum is radiometry.block_sum
    a = np.arange(2 * 5 * 7).reshape(2, 5, 7)
    got = radiometry.block_sum(a, 2)
    want = np.array([[[a[c, 2 * i:2 * i + 2, 2 * j:2 * j + 2].sum() for j in range(3)] for i in range(2)]
                     for c in range(2)])
    np.testing.assert_array_equal(got, want)
