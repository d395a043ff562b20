"""Background activity (leak): a per-polarity rate growing with light, spread across pixels.

``l = s * (leak_*_hz + leak_*_hz_per_lux * lux)`` events/s per polarity, ``s`` the pixel's log-normal
spread factor of mean 1 (``sigma = leak_sigma``; map ``"background"`` channel 0). See
:mod:`evnoise.background` for how the intensity shares the pixel's trials with the photon noise.
"""

from __future__ import annotations

from .base import NoiseTerm, lognormal_mean_one


class Leak(NoiseTerm):
    """Leak rates ``leak_on_hz``, ``leak_off_hz`` (+ ``*_per_lux``) and their spread ``leak_sigma``."""

    name = "leak"
    fields = ("leak_on_hz", "leak_off_hz", "leak_on_hz_per_lux", "leak_off_hz_per_lux", "leak_sigma")
    background = True
    map_name = "background"

    def is_on(self, params) -> bool:
        return (params.leak_on_hz > 0 or params.leak_off_hz > 0 or params.leak_on_hz_per_lux > 0
                or params.leak_off_hz_per_lux > 0)

    def needs_map(self, params) -> bool:
        # the spread factor belongs to the pixel: drawn whenever the background maps are drawn
        return params.leak_sigma > 0

    def draw_map(self, out, params, gen) -> None:
        out[0] = 1.0
        if params.leak_sigma > 0:
            out[0] = lognormal_mean_one(gen, params.leak_sigma, out.shape[1])

    def intensities(self, lux, params, scale=None, hot=None):
        # always an array of lux's shape (also at zero rates): the sum over terms broadcasts from it
        l_on = params.leak_on_hz + params.leak_on_hz_per_lux * lux
        l_off = params.leak_off_hz + params.leak_off_hz_per_lux * lux
        if scale is not None:
            l_on = l_on * scale
            l_off = l_off * scale
        return l_on, l_off

    def mean_intensities(self, lux, values):
        return (values["leak_on_hz"] + values["leak_on_hz_per_lux"] * lux,
                values["leak_off_hz"] + values["leak_off_hz_per_lux"] * lux)

    def coefficients(self, params, scale, hot):
        return (scale * params.leak_on_hz, scale * params.leak_on_hz_per_lux,
                scale * params.leak_off_hz, scale * params.leak_off_hz_per_lux)


LEAK = Leak()
