"""Threshold mismatch as a property of the core model: ``expected_rate(mismatch="mean")``.

The population mean over pixels (exact sum over the steps of p in the threshold) is compared with
an independent Monte Carlo: thresholds drawn per pixel with ``draw_thresholds`` and each pixel's
own rate from ``expected_rate(..., thresholds=...)``, averaged; tolerance k standard errors.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import evnoise as ev

PARAMS = ev.NoiseParams(eps_pos=0.30, eps_neg=0.35, bias_pr=1.7, trial_rate_hz=40.0, photons_per_lux=10.0,
                        eps_sigma=0.05)


@pytest.mark.parametrize("lux", [0.5, 2.0, 10.0])
def test_mean_over_mismatch_matches_monte_carlo_over_drawn_thresholds(lux):
    n = 40_000
    thresholds = ev.draw_thresholds((1, n), PARAMS, rng=7)
    per_pixel = ev.expected_rate(np.full((1, n), lux), PARAMS, thresholds=thresholds)[:, 0, :]  # (2, n)
    mc_mean = per_pixel.mean(axis=1)
    mc_se = per_pixel.std(axis=1, ddof=1) / np.sqrt(n)
    exact = ev.expected_rate(np.array([lux]), PARAMS, mismatch="mean")[:, 0]
    assert np.all(mc_se > 0)
    assert np.all(np.abs(exact - mc_mean) < 4 * mc_se), (exact, mc_mean, mc_se)
    # and the mean really differs from the nominal pixel's rate here (the option matters)
    nominal = ev.expected_rate(np.array([lux]), PARAMS)[:, 0]
    assert np.any(np.abs(exact - nominal) > 8 * mc_se)


def test_mean_equals_nominal_without_mismatch():
    params = dataclasses.replace(PARAMS, eps_sigma=0.0)
    lux = np.array([[0.0, 0.3], [3.0, 30.0]])
    np.testing.assert_allclose(ev.expected_rate(lux, params, mismatch="mean"), ev.expected_rate(lux, params),
                               rtol=1e-12, atol=0)


def test_bad_mismatch_option_and_thresholds_with_mean_are_errors():
    with pytest.raises(ev.ParameterError, match="mismatch must be"):
        ev.expected_rate(1.0, PARAMS, mismatch="average")
    with pytest.raises(ev.ParameterError, match="do not pass thresholds"):
        ev.expected_rate(np.ones((1, 2)), PARAMS, thresholds=np.full((2, 1, 2), 0.3), mismatch="mean")


def test_calibration_uses_the_core_population_rate():
    from evnoise import calibration, mismatch

    assert calibration.population_rate is mismatch.population_rate
    assert calibration.nb_shape is mismatch.nb_shape
