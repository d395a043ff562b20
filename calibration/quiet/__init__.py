"""Calibrating the background from a recording of a still scene (``evnoise calibrate REC --t-start A --t-end B``).

Modules, one per job: :mod:`.window` (a recording's per-pixel counts over a window), :mod:`.checks` (is a
window pure stationary noise?), :mod:`.counts` (the renewal count distribution), :mod:`.likelihood` (the
mixture likelihood and its maximisation), :mod:`.fit` (:func:`fit_quiet`, :class:`QuietFit`, the preset
document), :mod:`.goodness` (count histograms; a preset simulated against a recording) and :mod:`.plot`.
The names below are also reachable as ``evnoise.calibration.<name>``. Importing this package is cheap.
"""

from __future__ import annotations

from evnoise._lazy import lazy_attributes

_LAZY = {
    "QuietWindow": ".window",
    "quiet_window": ".window",
    "oscillating_pixels": ".window",
    "fit_quiet": ".fit",
    "QuietFit": ".fit",
    "preset_toml": ".fit",
    "GOODNESS_P": ".fit",
    "compare_to_recording": ".goodness",
    "simulate_window": ".goodness",
    "check_verdict": ".checks",
    "failed_checks": ".checks",
    "window_checks": ".checks",
}

__all__ = sorted(_LAZY)
__getattr__, __dir__ = lazy_attributes(__name__, _LAZY)
