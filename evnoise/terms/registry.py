"""The registry of noise terms and the functions that ask every registered term (re-exported by
:mod:`evnoise.terms`, whose module doc says how to add a term).

:data:`TERMS` is filled by the package when it is imported; a term module may import this one (the
reset-memory closed form asks for the background intensities) without importing the package that imports it.
"""

from __future__ import annotations

import numpy as np

from .base import NoiseTerm
from .timer import TIMER

#: The registered terms, in order.
TERMS: list[NoiseTerm] = []  # filled by evnoise.terms (its __init__), in order

#: The per-pixel maps a run may draw, in draw order (each ``(2, H, W)``).
MAPS = ("thresholds", "background")

#: Entries of the trial kernel's ``model`` tuple, in the kernel's order (:func:`kernel_model`).
MODEL = ("bias", "trial_us", "refractory_us", "lux_per_photon", "dark_lux", "pr_alpha", "regularity", "memory")


def register(new: NoiseTerm) -> None:
    """Append ``new`` to :data:`TERMS` (its name must be new)."""
    if any(t.name == new.name for t in TERMS):
        raise ValueError(f"a noise term named {new.name!r} is already registered")
    TERMS.append(new)


def unregister(name: str) -> None:
    """Remove the term called ``name`` from :data:`TERMS`."""
    TERMS[:] = [t for t in TERMS if t.name != name]


def term(name: str) -> NoiseTerm:
    """The registered term called ``name``."""
    for t in TERMS:
        if t.name == name:
            return t
    raise KeyError(name)


def background_on(params) -> bool:
    """True when a term adds background intensity for ``params`` (for the built-in terms this is
    :attr:`NoiseParams.has_background`)."""
    return any(t.background and t.is_on(params) for t in TERMS)


def active(params) -> list:
    """The terms that are on for ``params``, in order (one that modifies the background only with some)."""
    bg = background_on(params)
    return [t for t in TERMS if t.is_on(params) and (bg or not t.modifies_background)]


def regular_timer(params) -> bool:
    """True when background arrivals follow the regular timer (:class:`~evnoise.terms.timer.RegularTimer`)."""
    return TIMER in active(params)


def map_needed(name: str, params) -> bool:
    """True when a run with ``params`` must have the per-pixel map ``name`` (drawn unless given).

    The background map only matters when some background is on; then it is drawn when one of its
    terms asks (every term of the map then draws its share, in registry order).
    """
    users = [t for t in TERMS if t.map_name == name]
    if name == "background" and not background_on(params):
        return False
    return any(t.needs_map(params) for t in users)


def maps_needed(params) -> bool:
    """True when a run with ``params`` has any per-pixel map (the per-pixel paths of the simulators)."""
    return any(map_needed(name, params) for name in MAPS)


def draw_map(name: str, shape, params, gen) -> np.ndarray:
    """Per-pixel map ``name`` ``(2, *shape)`` drawn from ``gen`` (unchecked: callers check their inputs)."""
    n = int(np.prod(shape))
    out = np.zeros((2, n))
    for t in TERMS:
        if t.map_name == name:
            t.draw_map(out, params, gen)
    return out.reshape(2, *shape)


def _sum_pairs(pairs):
    l_on = l_off = None
    for pair in pairs:
        if pair is None:
            continue
        if l_on is None:
            l_on, l_off = pair
        else:
            l_on, l_off = l_on + pair[0], l_off + pair[1]
    return l_on, l_off


def intensities(lux, params, scale=None, hot=None):
    """Background intensities ``(l_on, l_off)`` events/s at ``lux``: the sum over the terms.

    ``scale``, ``hot``: the background map's channels (arrays that broadcast with ``lux``) or None for
    the nominal pixel. Every background term is asked, on or not (zero rates add zeros).
    """
    l_on, l_off = _sum_pairs(t.intensities(lux, params, scale, hot) for t in TERMS if t.background)
    if l_on is None:
        l_on = l_off = np.zeros(np.shape(lux))
    return np.asarray(l_on, dtype=np.float64), np.asarray(l_off, dtype=np.float64)


def mean_intensities(lux, values):
    """Population-mean background intensities ``(l_on, l_off)`` events/s (spread factor 1 on average, hot
    pixels weighted by their fraction) for parameter ``values``.

    ``values`` maps :class:`~evnoise.NoiseParams` field names to floats or arrays (e.g. one value per
    candidate of a calibration search, ``vals[name][:, None]``) that broadcast with ``lux`` (lux).
    This is the calibration's additive stand-in ``nu ~ N p + l``.
    """
    l_on, l_off = _sum_pairs(t.mean_intensities(lux, values) for t in TERMS if t.background)
    if l_on is None:
        l_on = l_off = np.zeros(np.shape(lux))
    return l_on, l_off


def kernel_coefficients(params, bg, sel) -> np.ndarray:
    """``(4, n)`` ``[l0_on, l1_on, l0_off, l1_off]`` of the trial kernel for pixels ``sel``: ``l = l0 + l1 * lux``
    (``(4, 0)`` without background). ``bg``: the run's flat ``(scale, hot)`` maps or None. Where hot pixels have
    a timer regularity of their own (:func:`evnoise.terms.timer.pixel_regularity`) a fifth row holds each
    pixel's regularity."""
    if not background_on(params):
        return np.zeros((4, 0))
    if bg is None:
        scale, hot = np.ones(sel.size), np.zeros(sel.size)
    else:
        scale, hot = bg[0][sel], bg[1][sel]
    rows = None
    for t in TERMS:
        c = t.coefficients(params, scale, hot) if t.background else None
        if c is not None:
            rows = list(c) if rows is None else [a + b for a, b in zip(rows, c)]
    if regular_timer(params):
        from .timer import pixel_regularity

        reg = pixel_regularity(params, hot)
        if np.ndim(reg):
            rows.append(reg)
    rows = [np.broadcast_to(np.asarray(r, dtype=np.float64), (sel.size,)) for r in rows]
    return np.ascontiguousarray(np.stack(rows))


def kernel_model(params) -> tuple:
    """The trial kernel's ``model`` tuple (:data:`MODEL` order), each entry set by the term that owns it."""
    entries = {}
    for t in active(params):
        entries.update(t.kernel_model(params))
    return tuple(float(entries.get(name, 0.0)) for name in MODEL)


def bounds() -> dict:
    """``{field: (low, high)}`` of every registered term's parameters (:meth:`NoiseTerm.bounds`)."""
    out = {}
    for t in TERMS:
        out.update(t.bounds())
    return out
