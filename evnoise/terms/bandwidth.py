"""Photoreceptor bandwidth: in changing scenes the compared level follows the light through a low-pass filter.

Time constant ``tau = pr_tau_s_at_1lux / (lux + dark_lux)`` (bandwidth grows with photocurrent); static
pixels are not affected, so it has no closed-form contribution. The trial kernel filters the level with
step ``1 - exp(-lam * pr_alpha)`` per trial (:func:`alpha_per_photon`).
"""

from __future__ import annotations

from .base import NoiseTerm


def alpha_per_photon(params) -> float:
    """``dt / (tau(lam) lam)``: the filter's step is ``1 - exp(-lam * this)`` (0 when the filter is off)."""
    if params.pr_tau_s_at_1lux <= 0:
        return 0.0
    # tau = pr_tau_s_at_1lux / (lux + dark_lux) = pr_tau_s_at_1lux * photons_per_lux / lam
    return (1.0 / params.trial_rate_hz) / (params.pr_tau_s_at_1lux * params.photons_per_lux)


class Bandwidth(NoiseTerm):
    """``pr_tau_s_at_1lux``: the photoreceptor's time constant at 1 lux (0: infinitely fast)."""

    name = "bandwidth"
    fields = ("pr_tau_s_at_1lux",)

    def kernel_model(self, params) -> dict:
        return {"pr_alpha": float(alpha_per_photon(params))}


BANDWIDTH = Bandwidth()
