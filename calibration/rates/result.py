"""The result of a calibration: :class:`CalibrationResult` (summary, preset TOML, plot).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from evnoise.params import NoiseParams, parameter_specs

from ..measurements import Measurements
from .spec import FIT_NAMES


@dataclasses.dataclass(eq=False)
class CalibrationResult:
    """Fitted parameters with uncertainties, identifiability and goodness of fit.

    Attributes
    ----------
    params : NoiseParams
        The fitted parameters (fixed ones at their given values).
    method : str
        Closed form used (``"poisson"`` exact or ``"gaussian"`` eq. 3).
    free : tuple of str
        Parameters that were fitted.
    status : dict
        Per parameter: ``"fitted"``, ``"fitted (fit rejected)"``, ``"fixed"``, ``"fixed (assumed)"``,
        ``"not identified"`` or ``"at lower bound"``.
    std_error : dict
        Standard errors in the parameters' units (NaN where not available).
    rel_error : dict
        Standard errors of ``log(value)`` (relative uncertainties).
    cov_log : numpy.ndarray
        Covariance of the log-parameters of ``free`` (in that order).
    correlation : numpy.ndarray
        The corresponding correlation matrix.
    identifiability : list of str
        Findings in words (what is and is not constrained).
    gof : dict
        Goodness of fit (see :meth:`summary`).
    dispersion : dict
        Measured vs predicted NB shape per level (``r_measured``, ``r_model``, ``(2, J)``).
    measurements : Measurements
    fit_status : str
        ``"accepted"`` or ``"rejected"`` (the goodness of fit says the model does not describe
        the data; see :data:`REJECT_P`).
    warnings : list of str
        What a user must not miss: a rejected fit, parameters on a bound.
    at_bound : dict
        Parameters that ended on a bound: name -> ``"lower"`` or ``"upper"``.
    bounds : dict
        The bounds of the free parameters (natural units).
    profile : dict
        Rate tables with ``photons_per_lux`` free: its profile-likelihood range (``name``,
        ``best``, ``low``, ``high``, ``closed_low``, ``closed_high``: whether the likelihood falls
        by more than ``loglik_tolerance`` on that side; an open side means not identified).
    """

    params: NoiseParams
    method: str
    distribution: str
    free: tuple
    status: dict
    std_error: dict
    rel_error: dict
    cov_log: np.ndarray
    correlation: np.ndarray
    identifiability: list
    gof: dict
    dispersion: dict
    measurements: Measurements
    loglik: float
    notes: list = dataclasses.field(default_factory=list)
    seed: object = None
    fit_status: str = "accepted"
    warnings: list = dataclasses.field(default_factory=list)
    at_bound: dict = dataclasses.field(default_factory=dict)
    bounds: dict = dataclasses.field(default_factory=dict)
    profile: dict = dataclasses.field(default_factory=dict)

    def population_rate(self, lux) -> np.ndarray:
        """Fitted mean rate over pixels, events/s, ``(2, *lux.shape)`` (background included).

        Parameters
        ----------
        lux : float or array_like
            Illuminance in lux.

        Returns
        -------
        numpy.ndarray
            ``[ON, OFF]`` rates per pixel in events per second, shape ``(2, *lux.shape)``.
        """
        from evnoise.mismatch import population_rate

        return population_rate(lux, self.params, method=self.method)

    def rate_band(self, lux, *, n_sigma: float = 1.0):
        """``(rate, rel_sd)``: fitted population rate and its relative standard deviation (delta method).

        Parameters
        ----------
        lux : float or array_like
            Illuminance in lux.
        n_sigma : float, default 1.0
            Multiple of the standard deviation returned.

        Returns
        -------
        rate : numpy.ndarray
            ``[ON, OFF]`` rates in events per second, shape ``(2, *lux.shape)``, as :meth:`population_rate`.
        rel_sd : numpy.ndarray
            ``n_sigma`` times the standard deviation of ``log(rate)``, same shape, from the covariance of
            the free parameters that have an uncertainty (zeros when none has).
        """
        lux = np.asarray(lux, dtype=np.float64)
        rate = self.population_rate(lux)
        # parameters with an uncertainty (not those held on a bound, or not identified by a profile)
        idx = [i for i in range(len(self.free)) if np.isfinite(self.cov_log[i, i])]
        names = [self.free[i] for i in idx]
        if not names:
            return rate, np.zeros_like(rate)
        cov = self.cov_log[np.ix_(idx, idx)]
        jac = np.zeros((*rate.shape, len(names)))
        h = 1e-3
        for i, n in enumerate(names):
            v = getattr(self.params, n)
            up = self.params.replace(**{n: v * math.exp(h)})
            dn = self.params.replace(**{n: v * math.exp(-h)})
            from evnoise.mismatch import population_rate

            with np.errstate(divide="ignore", invalid="ignore"):
                jac[..., i] = (np.log(population_rate(lux, up, method=self.method))
                               - np.log(population_rate(lux, dn, method=self.method))) / (2 * h)
        jac = np.where(np.isfinite(jac), jac, 0.0)
        var = np.einsum("...i,ij,...j->...", jac, cov, jac)
        return rate, n_sigma * np.sqrt(np.maximum(var, 0.0))

    def summary(self) -> str:
        """A readable report: parameters, uncertainties, identifiability, fit quality, dispersion."""
        lines = [f"evnoise calibration ({self.method} closed form, {self.measurements.kind}: "
                 f"{self.measurements.n_levels} levels from {self.measurements.source})"]
        lines.append(f"fit status: {self.fit_status.upper()}")
        lines += [f"WARNING: {t}" for t in self.warnings]
        lines.append(f"{'parameter':<21} {'value':>13} {'std error':>11} {'rel':>7}  status")
        for n in FIT_NAMES:
            v = getattr(self.params, n)
            se = self.std_error.get(n, math.nan)
            rel = self.rel_error.get(n, math.nan)
            se_t = "" if not np.isfinite(se) else f"{se:11.4g}"
            rel_t = "" if not np.isfinite(rel) else f"{100 * rel:6.1f}%"
            lines.append(f"{n:<21} {v:13.6g} {se_t:>11} {rel_t:>7}  {self.status.get(n, 'fixed')}")
        bg = [s.name for s in parameter_specs()
              if s.group == "background" and (s.name in self.free or getattr(self.params, s.name) != s.default)]
        if bg:
            parts = []
            for n in bg:
                se = self.std_error.get(n, math.nan)
                err = f" +- {se:.2g}" if np.isfinite(se) else ""
                parts.append(f"{n} {getattr(self.params, n):.4g}{err} ({self.status.get(n, 'fixed')})")
            lines.append("background (rates in events/s per pixel): " + "; ".join(parts))
        if self.identifiability:
            lines.append("identifiability:")
            lines += [f"  - {t}" for t in self.identifiability]
        lines.append("goodness of fit:")
        for k, v in self.gof.items():
            lines.append(f"  {k}: {_fmt(v)}")
        if self.dispersion.get("summary"):
            lines.append("over-dispersion (NB shape r, measured vs threshold mismatch):")
            lines.append(f"  {self.dispersion['summary']}")
        lines += [f"note: {t}" for t in self.notes]
        return "\n".join(lines)

    def to_toml(self, *, extra_provenance: dict | None = None) -> str:
        """The preset document: ``[params]``, ``[provenance]``, ``[fit]`` tables.

        Parameters
        ----------
        extra_provenance : dict, optional
            More entries for the ``[provenance]`` table (they replace entries of the same name).

        Returns
        -------
        str
            The TOML text.
        """
        from ..preset import result_to_toml

        return result_to_toml(self, extra_provenance=extra_provenance)

    def write_preset(self, path, *, overwrite: bool = False, extra_provenance: dict | None = None):
        """Write the preset TOML atomically; returns the path.

        Parameters
        ----------
        path : str or os.PathLike
            The file to write; its folder must exist.
        overwrite : bool, default False
            Replace an existing file.
        extra_provenance : dict, optional
            More entries for the ``[provenance]`` table, as in :meth:`to_toml`.

        Returns
        -------
        pathlib.Path
            The path written.
        """
        from ..preset import write_text_atomic

        return write_text_atomic(path, self.to_toml(extra_provenance=extra_provenance), overwrite=overwrite)

    def plot(self, path, *, title: str | None = None, overwrite: bool = False, extra_curves=None,
             extra_r_curves=None):
        """Save a PNG of the data and the fitted curves (see :func:`evnoise.calibration.plot_fit`).

        Parameters
        ----------
        path : str or os.PathLike
            Output PNG.
        title : str, optional
            Title of the figure (default: ``"evnoise calibration: "`` and the measurements' source).
        overwrite : bool, default False
            Replace an existing file.
        extra_curves : list of dict, optional
            More curves on the rate panel: ``dict(label=..., lux=(n,), rate=(2, n), style="--")``.
        extra_r_curves : list of dict, optional
            More curves on the NB-shape panel: ``dict(label=..., lux=(n,), r=(2, n), style="--")``.

        Returns
        -------
        pathlib.Path
            The path written.
        """
        from .plot import plot_fit

        return plot_fit(self, path, title=title, overwrite=overwrite, extra_curves=extra_curves,
                        extra_r_curves=extra_r_curves)


def _fmt(v):
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)
