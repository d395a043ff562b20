"""The interface every noise term implements (:class:`NoiseTerm`); see :mod:`evnoise.terms`."""

from __future__ import annotations

import dataclasses

import numpy as np


def lognormal_mean_one(gen, sigma: float, size):
    """Log-normal factors of mean 1 whose logarithm has standard deviation ``sigma`` (drawn from ``gen``)."""
    return np.exp(gen.normal(-0.5 * sigma * sigma, sigma, size=size))


class NoiseTerm:
    """One term of the noise model: its parameters, per-pixel maps, closed form, kernel hooks and bounds.

    A term is a stateless object; the registry (:data:`evnoise.terms.TERMS`) holds one instance of each,
    in order. Every hook has a neutral default, so a term overrides only what it changes.

    Attributes
    ----------
    name : str
        Short name (unique in the registry).
    fields : tuple of str
        The :class:`~evnoise.NoiseParams` fields the term owns.
    background : bool
        True when the term adds background intensity (events/s, :meth:`intensities`): the closed forms
        and kernels then add it to the photon noise as described in :mod:`evnoise.background`.
    modifies_background : bool
        True when the term only changes how the background arrives (it is on only where some background is).
    map_name : str or None
        The per-pixel map the term draws into (``"thresholds"``: ``[eps_on, eps_off]``;
        ``"background"``: ``[spread factor, hot rate in events/s]``), or None.
    """

    name = ""
    fields: tuple = ()
    background = False
    modifies_background = False
    map_name: str | None = None

    # -- parameters ------------------------------------------------------------------------
    def is_on(self, params) -> bool:
        """True when the term changes the model for ``params`` (default: any of its fields is > 0)."""
        return any(getattr(params, f) > 0 for f in self.fields)

    def bounds(self) -> dict:
        """``{field: (low, high)}`` of the term's parameters: their valid range (calibration's search range
        where the field's metadata gives one, ``fit_bounds``; ``None`` ends are set from the data)."""
        from ..params import NoiseParams

        meta = {f.name: f.metadata.get("evnoise", {}) for f in dataclasses.fields(NoiseParams)}
        out = {}
        for name in self.fields:
            m = meta.get(name, {})
            if m.get("fit_bounds") is not None:
                out[name] = tuple(m["fit_bounds"])
            else:
                from ..params import PARAM_LIMITS

                out[name] = (m.get("low", 0.0), m.get("high", PARAM_LIMITS.get(name)))
        return out

    # -- per-pixel maps --------------------------------------------------------------------
    def needs_map(self, params) -> bool:
        """True when a run must draw (or be given) the term's per-pixel map."""
        return False

    def draw_map(self, out: np.ndarray, params, gen) -> None:
        """Fill the term's channels of ``out`` (its map, flat ``(2, n)``): nominal values, then the draws
        from ``gen`` when the term draws (in a fixed order: turning a term off changes no other draw)."""

    # -- closed form -----------------------------------------------------------------------
    def intensities(self, lux, params, scale=None, hot=None):
        """Background intensities ``(l_on, l_off)`` events/s at ``lux`` of pixels with background maps
        ``scale``, ``hot`` (arrays matching ``lux``, or None for the nominal pixel); None: adds nothing."""
        return None

    def mean_intensities(self, lux, values):
        """Population-mean background intensities ``(l_on, l_off)`` events/s for parameter ``values``
        (a mapping from field names to floats or arrays that broadcast with ``lux``); None: adds nothing."""
        return None

    # -- kernel hooks ----------------------------------------------------------------------
    def coefficients(self, params, scale, hot):
        """The trial kernel's background coefficients ``(4, n)`` ``[l0_on, l1_on, l0_off, l1_off]``
        (events/s and events/s per lux) of pixels with maps ``scale``, ``hot``; None: adds nothing."""
        return None

    def kernel_model(self, params) -> dict:
        """Entries of the trial kernel's ``model`` tuple the term sets while on (:data:`evnoise.terms.MODEL`;
        an entry no term sets is 0)."""
        return {}

    def __repr__(self):
        return f"<noise term {self.name!r}: {', '.join(self.fields)}>"
