"""The noise terms of the model, one module each, and their ordered registry.

A term (:class:`~evnoise.terms.base.NoiseTerm`) owns its :class:`~evnoise.NoiseParams` fields, its
per-pixel map (how it is drawn), its closed-form contribution, its kernel hooks and its calibration
bounds. The closed forms (:mod:`evnoise.rates`, :mod:`evnoise.mismatch`), every simulation tier, the
:class:`~evnoise.NoiseStream`, the plugins, the dataset generator and calibration ask the functions
below, which iterate :data:`TERMS` in order (the order fixes the order of the random draws of the maps,
and so the output: append new terms at the end).

Adding a term: one module here with a :class:`NoiseTerm` subclass and an instance, one line in
:data:`TERMS`, its fields in :class:`~evnoise.NoiseParams` (with their metadata), and its tests.
"""

from __future__ import annotations

from .bandwidth import BANDWIDTH
from .base import NoiseTerm
from .hot_pixels import HOT_PIXELS
from .leak import LEAK
from .memory import MEMORY
from .registry import (
    MAPS,
    MODEL,
    TERMS,
    active,
    background_on,
    bounds,
    draw_map,
    intensities,
    kernel_coefficients,
    kernel_model,
    map_needed,
    maps_needed,
    mean_intensities,
    register,
    regular_timer,
    term,
    unregister,
)
from .shot import SHOT
from .timer import TIMER

__all__ = ["NoiseTerm", "SHOT", "LEAK", "HOT_PIXELS", "TIMER", "BANDWIDTH", "MEMORY", "TERMS", "MAPS", "MODEL",
           "register", "unregister", "term", "active", "background_on",
           "regular_timer", "map_needed", "maps_needed", "draw_map", "intensities", "mean_intensities",
           "kernel_coefficients", "kernel_model", "bounds"]

#: The registered terms, in order (:data:`evnoise.terms.registry.TERMS`, the list every function here asks).
TERMS.extend([SHOT, LEAK, HOT_PIXELS, TIMER, BANDWIDTH, MEMORY])
