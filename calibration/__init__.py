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
evnoise is refitted by ``python -m evnoise.calibration.scripts.refit_evk3``.

Layout: :mod:`.rates` (the rate-table / flat-field fit), :mod:`.quiet` (the quiet-window fit), shared
:mod:`.measurements` (reading the inputs), :mod:`.preset` (writing preset TOML) and ``_progress`` (phase
lines); :mod:`.scripts` holds the provenance scripts behind the shipped presets (never imported here).

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
    "calibrate": ".rates.fit",  # the rate-table / flat-field fit
    "CalibrationResult": ".rates.result",
    "FIT_NAMES": ".rates.spec",
    "plot_fit": ".rates.plot",
    "population_rate": "evnoise.mismatch",  # properties of the noise model: they live in the core
    "nb_shape": "evnoise.mismatch",
    "threshold_distribution": "evnoise.mismatch",
    "QuietWindow": ".quiet.window",  # calibrate from a recording of a still scene
    "quiet_window": ".quiet.window",
    "fit_quiet": ".quiet.fit",
    "preset_toml": ".quiet.fit",
    "GOODNESS_P": ".quiet.fit",
    "compare_to_recording": ".quiet.goodness",
    "check_verdict": ".quiet.checks",
    "failed_checks": ".quiet.checks",
    "write_text_atomic": ".preset",
}

__all__ = sorted(_LAZY)
__getattr__, __dir__ = lazy_attributes(__name__, _LAZY)
