"""Shot (photon) noise: the paper's per-trial threshold comparison, with per-pixel threshold mismatch."""

from __future__ import annotations

from .base import NoiseTerm


class ShotNoise(NoiseTerm):
    """Photon noise of the threshold comparison (always on).

    Closed form: :func:`evnoise.event_probability` per polarity. Per-pixel map ``"thresholds"``
    ``[eps_on, eps_off]`` when ``eps_sigma > 0``: normal around ``eps_pos`` / ``eps_neg``, truncated to
    ``> 0`` by redrawing. Kernel model: bias, trial length, refractory period, photon scale, dark level.
    """

    name = "shot"
    fields = ("eps_pos", "eps_neg", "bias_pr", "trial_rate_hz", "photons_per_lux", "dark_lux", "refractory_s",
              "eps_sigma")
    map_name = "thresholds"

    def is_on(self, params) -> bool:
        return True

    def needs_map(self, params) -> bool:
        return params.eps_sigma > 0

    def draw_map(self, out, params, gen) -> None:
        out[0] = params.eps_pos
        out[1] = params.eps_neg
        if params.eps_sigma <= 0:
            return
        n = out.shape[1]
        for i, mean in enumerate((params.eps_pos, params.eps_neg)):
            draw = gen.normal(mean, params.eps_sigma, size=n)
            bad = draw <= 0
            while bad.any():
                draw[bad] = gen.normal(mean, params.eps_sigma, size=int(bad.sum()))
                bad = draw <= 0
            out[i] = draw

    def kernel_model(self, params) -> dict:
        return {"bias": float(params.bias_pr), "trial_us": float(params.trial_us),
                "refractory_us": float(params.refractory_us), "lux_per_photon": 1.0 / params.photons_per_lux,
                "dark_lux": float(params.dark_lux)}


SHOT = ShotNoise()
