"""Provenance scripts: how the shipped presets and the recorded comparisons were made.

Each is run as ``python -m evnoise.calibration.scripts.<name>`` (``refit_evk3``, ``refit_evk4``,
``fit_dvs128``, ``dispersion_evk3``, ``iebcs_ratios``, ``slow_csv``, ``quiet_timing``, ``memory_fit``); the
library never imports them.
Their outputs (figures, JSON summaries) are kept next to the library, in ``calibration/``.
"""
