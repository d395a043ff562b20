"""Fitting the noise model to a rate table or flat fields (``evnoise calibrate MEASUREMENTS``).

Modules, one per job: :mod:`.fit` (:func:`calibrate`), :mod:`.spec` (the parameters' fit roles, bounds
and starting values, from :func:`evnoise.params.parameter_specs`, and the constants of the method),
:mod:`.likelihood` (the likelihood of each kind of data), :mod:`.search` (stand-in pre-fits, local fits,
ridge walk, continuation, profile), :mod:`.uncertainty` (information, sandwich, profile intervals,
identifiability, goodness of fit, verdict), :mod:`.result` (:class:`CalibrationResult`) and :mod:`.plot`.
The inputs are read by :mod:`evnoise.calibration.measurements`. The names below are also reachable as
``evnoise.calibration.<name>``. Importing this package is cheap.
"""

from __future__ import annotations

from evnoise._lazy import lazy_attributes

_LAZY = {
    "calibrate": ".fit",
    "CalibrationResult": ".result",
    "FIT_NAMES": ".spec",
    "plot_fit": ".plot",
}

__all__ = sorted(_LAZY)
__getattr__, __dir__ = lazy_attributes(__name__, _LAZY)
