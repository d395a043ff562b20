"""Fitting the noise model to measurements (importable as ``evnoise.calibration``).

Typical use::

    from evnoise import calibration as cal
    meas = cal.read_measurements("rates.csv")            # or a flat-field listing (TOML/CSV)
    result = cal.calibrate(meas)                          # maximum likelihood, exact model
    print(result.summary())
    result.write_preset("my-camera.toml")                 # evnoise.load_preset("my-camera.toml")
    result.plot("my-camera-fit.png")

or ``evnoise calibrate MEASUREMENTS --out preset.toml``. From a recording of a still scene::

    fit = cal.fit_quiet([cal.quiet_window("rec.aedat", t_start_s, t_end_s)])
    print(fit.summary()); params = fit.to_params("davis346")

or ``evnoise calibrate rec.aedat --t-start A --t-end B --out cam.toml``. The EVK3-HD preset shipped with
evnoise is refitted by ``python -m evnoise.calibration.refit_evk3``.

Importing this package is cheap; SciPy, Numba kernels and matplotlib load on first use.
"""

from __future__ import annotations

from evnoise._lazy import lazy_attributes

_LAZY = {
    "Measurements": ".measurements",
    "MonitorTable": ".measurements",
    "rate_table": ".measurements",
    "count_table": ".measurements",
    "flat_field": ".measurements",
    "read_rate_table": ".measurements",
    "read_flat_fields": ".measurements",
    "read_measurements": ".measurements",
    "read_monitor_table": ".measurements",
    "grey_to_lux": ".measurements",
    "calibrate": ".fit",
    "CalibrationResult": ".result",
    "FIT_NAMES": ".fit",
    "population_rate": "evnoise.mismatch",  # properties of the noise model: they live in the core
    "nb_shape": "evnoise.mismatch",
    "threshold_distribution": "evnoise.mismatch",
    "plot_fit": ".plot",
    "QuietWindow": ".quiet",  # calibrate from a recording of a still scene
    "quiet_window": ".quiet",
    "fit_quiet": ".quiet",
    "compare_to_recording": ".quiet",
    "preset_toml": ".quiet",
    "GOODNESS_P": ".quiet",
    "check_verdict": ".quiet_checks",
    "failed_checks": ".quiet_checks",
    "write_text_atomic": ".preset",
}

__all__ = sorted(_LAZY)
__getattr__, __dir__ = lazy_attributes(__name__, _LAZY)
