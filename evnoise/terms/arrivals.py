"""Background arrivals per trial, and the illuminance of a photon count (the one home of both; re-exported by
:mod:`evnoise.background`, whose module doc states the model)."""

from __future__ import annotations

import numpy as np


def arrival_shares(l_on, l_off, trial_rate_hz: float):
    """Per-trial background probabilities ``(a_on, a_off)``: ``a * l_on / l`` and ``a * l_off / l``."""
    l_all = l_on + l_off
    with np.errstate(divide="ignore", invalid="ignore"):
        # (1 - exp(-l / N)) / l, with its limit 1 / N at l = 0
        g = np.where(l_all > 0, -np.expm1(-l_all / trial_rate_hz) / np.where(l_all > 0, l_all, 1.0),
                     1.0 / trial_rate_hz)
    return g * l_on, g * l_off


def lux_of_photons(lam, params):
    """Illuminance ``lux`` back from mean photons per trial (``>= 0``)."""
    return np.maximum(np.asarray(lam, dtype=np.float64) / params.photons_per_lux - params.dark_lux, 0.0)
