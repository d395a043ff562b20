"""Hot pixels: a random fraction of pixels with an extra, light-independent event rate."""

from __future__ import annotations

import numpy as np

from ..params import PARAM_LIMITS
from .base import NoiseTerm, lognormal_mean_one


class HotPixels(NoiseTerm):
    """``round(hot_pixel_fraction * H * W)`` pixels (without replacement) fire ``h`` events/s more, ``h``
    log-normal of mean ``hot_pixel_rate_hz`` (``sigma = hot_pixel_sigma``), ON with probability
    ``hot_pixel_on_fraction`` (map ``"background"`` channel 1: ``h``, 0 for ordinary pixels)."""

    name = "hot_pixels"
    fields = ("hot_pixel_fraction", "hot_pixel_rate_hz", "hot_pixel_sigma", "hot_pixel_on_fraction")
    background = True
    map_name = "background"

    def is_on(self, params) -> bool:
        return params.hot_pixels_on

    def needs_map(self, params) -> bool:
        return params.hot_pixel_fraction > 0

    def draw_map(self, out, params, gen) -> None:
        out[1] = 0.0
        if not self.is_on(params):
            return
        n = out.shape[1]
        n_hot = int(round(params.hot_pixel_fraction * n))
        if n_hot:
            idx = gen.choice(n, size=n_hot, replace=False)
            rates = np.full(n_hot, params.hot_pixel_rate_hz)
            if params.hot_pixel_sigma > 0:
                rates *= lognormal_mean_one(gen, params.hot_pixel_sigma, n_hot)
            # at most a rate's own limit (a thousand per microsecond): drawn maps pass the check of given ones
            out[1, idx] = np.minimum(rates, PARAM_LIMITS["hot_pixel_rate_hz"])

    def intensities(self, lux, params, scale=None, hot=None):
        if hot is None:
            return None  # the nominal pixel is not hot
        q = params.hot_pixel_on_fraction
        return hot * q, hot * (1.0 - q)

    def mean_intensities(self, lux, values):
        rate = values["hot_pixel_rate_hz"]
        hot = values["hot_pixel_fraction"] * (rate > 0) * rate
        q = values["hot_pixel_on_fraction"]
        return hot * q, hot * (1.0 - q)

    def coefficients(self, params, scale, hot):
        q = params.hot_pixel_on_fraction
        return hot * q, 0.0, hot * (1.0 - q), 0.0


HOT_PIXELS = HotPixels()
