"""An array of illuminances gives exactly what a loop of scalar calls gives.

``expected_rate(lux, params, mismatch="mean")`` (:func:`evnoise.mismatch.population_rate`) and
:func:`evnoise.mismatch.nb_shape` compute each level's threshold atoms on their own (nothing shared
across levels that grows with the brightest one), so the array call must agree bit for bit with the
scalar calls, element by element, for every shape of ``lux``. Timings are not asserted here.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import evnoise as ev
from evnoise.mismatch import level_statistics, nb_shape, population_rate

LUX = np.geomspace(0.01, 100.0, 11)


def _loop(func, lux, *args, **kwargs):
    """``func`` called on each element of ``lux`` (float), stacked as ``(2, *lux.shape)``."""
    flat = [func(float(v), *args, **kwargs) for v in np.ravel(lux)]
    return np.stack(flat, axis=-1).reshape(2, *np.shape(lux))


@pytest.mark.parametrize("preset", ["davis346", "evk4", "evk3-hd"])
def test_expected_rate_mean_array_equals_scalar_loop(preset):
    array = ev.expected_rate(LUX, preset, mismatch="mean")
    loop = _loop(ev.expected_rate, LUX, preset, mismatch="mean")
    assert array.shape == (2, LUX.size) and array.dtype == np.float64
    assert np.array_equal(array, loop)
    assert np.all(np.isfinite(array)) and np.all(array > 0)


def test_population_rate_2d_with_zero_and_repeats_equals_scalar_loop():
    lux = np.array([[0.0, 0.3, 100.0], [3.0, 0.3, 0.01]])
    array = population_rate(lux, "davis346")
    assert array.shape == (2, 2, 3)
    assert np.array_equal(array, _loop(population_rate, lux, "davis346"))


@pytest.mark.parametrize("method", ["poisson", "gaussian"])
def test_nb_shape_and_level_statistics_array_equal_scalar_loop(method):
    params = dataclasses.replace(ev.load_preset("davis346"), refractory_s=0.0)
    lux = LUX[::2]
    assert np.array_equal(nb_shape(lux, params, 0.5, method=method),
                          _loop(nb_shape, lux, params, 0.5, method=method))
    stats = level_statistics(lux, params, method=method)
    for j, v in enumerate(lux):
        one = level_statistics(float(v), params, method=method)
        assert np.array_equal(stats.log_m1[:, j], one.log_m1[:, 0])
        assert np.array_equal(stats.log_m2[:, j], one.log_m2[:, 0])
        for k in range(2):
            assert np.array_equal(stats.log_p[k][j], one.log_p[k][0])
            assert np.array_equal(stats.mass[k][j], one.mass[k][0])
