"""Fitting the noise model to measurements (importable as ``evnoise.calibration``)."""
