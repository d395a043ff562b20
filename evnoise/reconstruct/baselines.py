"""Baselines the U-Net must beat (NumPy/SciPy only).

(a) :func:`count_image`: the count image itself, rescaled: what a user sees without a
    reconstructor. ``mode="minmax"`` stretches ``ON + OFF`` to ``[0, 1]``; ``mode="affine"``
    is the best least-squares affine map of ``ON + OFF`` onto the target (an *oracle*: it uses
    the ground truth, so it is an upper bound of what any global rescaling can do).
(b) :class:`MLInversion`: per-pixel maximum-likelihood illuminance from the ON and OFF counts
    jointly, with the exact closed-form rates, then display-encoded like the targets. Counts
    of a binned pixel are modelled as independent Poisson variables with means
    ``binning^2 * window * rate_pol(lux)`` (all pixels of a bin at the same illuminance). Light
    spatial smoothing: the counts are smoothed with a normalised Gaussian before the
    inversion, which is exactly the maximum-likelihood estimate of a locally constant
    illuminance with Gaussian weights (the log-likelihood is linear in the counts).
"""

from __future__ import annotations

import math

import numpy as np

from .._checks import MAX_LUX, check_lux, check_positive
from ..errors import InputError, ParameterError
from ..params import NoiseParams
from .imaging import lux_to_display, srgb_decode

__all__ = ["count_image", "MLInversion"]


def _check_counts(counts) -> np.ndarray:
    c = np.asarray(counts)
    if c.ndim != 3 or c.shape[0] != 2 or c.shape[1] == 0 or c.shape[2] == 0:
        raise InputError(f"counts must have shape (2, H, W) [ON, OFF], got {c.shape}")
    c = c.astype(np.float64)
    if not np.isfinite(c).all() or (c < 0).any():
        raise InputError("counts must be finite and >= 0")
    return c


def count_image(counts, *, target=None, mode: str = "minmax") -> np.ndarray:
    """The total-count image ``ON + OFF`` mapped to ``[0, 1]`` (see the module docstring).

    Parameters
    ----------
    counts : array_like, shape (2, H, W)
        ON and OFF counts (finite, >= 0), binned or not.
    target : array_like, shape (H, W), optional
        Display-encoded ground truth in ``[0, 1]``; required by ``mode="affine"``, unused otherwise.
    mode : {"minmax", "affine"}, default "minmax"
        ``"minmax"`` stretches the total to ``[0, 1]`` (all zeros when it is constant); ``"affine"``
        fits the least-squares affine map of the total onto ``target`` and clips to ``[0, 1]``.

    Returns
    -------
    numpy.ndarray
        float64 image of shape ``(H, W)`` in ``[0, 1]``.
    """
    total = _check_counts(counts).sum(axis=0)
    if mode == "minmax":
        lo, hi = float(total.min()), float(total.max())
        return np.zeros_like(total) if hi == lo else (total - lo) / (hi - lo)
    if mode == "affine":
        if target is None:
            raise ParameterError("mode='affine' fits the target: give target")
        t = np.asarray(target, dtype=np.float64)
        if t.shape != total.shape:
            raise InputError(f"target shape {t.shape} does not match counts {total.shape}")
        x = total.ravel() - total.mean()
        var = float(x @ x)
        slope = float(x @ (t.ravel() - t.mean())) / var if var > 0 else 0.0
        return np.clip(t.mean() + slope * (total - total.mean()), 0.0, 1.0)
    raise ParameterError(f"mode must be 'minmax' or 'affine', got {mode!r}")


class MLInversion:
    """Per-pixel maximum-likelihood illuminance from binned ON/OFF counts.

    Parameters
    ----------
    params : NoiseParams
        Noise model (nominal thresholds; threshold mismatch is not modelled here).
    max_lux : float
        White level: the search grid covers ``[0, max_lux]`` and outputs are encoded as
        ``srgb_encode(lux / max_lux)``, like the dataset targets.
    binning : int
        Side of the count bins (``binning^2`` pixels share one count).
    grid_size : int
        Points of the illuminance grid, uniform in display value (resolution ``1 / (n - 1)``).
    smoothing_sigma : float
        Standard deviation in binned pixels of the Gaussian applied to the counts; 0 = none.
    count_step : float
        Smoothed counts are rounded to this step before the table lookup.
    """

    def __init__(self, params: NoiseParams, *, max_lux: float, binning: int = 2, grid_size: int = 1024,
                 smoothing_sigma: float = 0.7, count_step: float = 0.125):
        if not isinstance(params, NoiseParams):
            raise ParameterError(f"params must be a NoiseParams, got {type(params).__name__}")
        if not (isinstance(max_lux, (int, float)) and math.isfinite(max_lux) and 0 < max_lux <= MAX_LUX):
            raise ParameterError(f"max_lux must be finite, > 0 and at most {MAX_LUX:g} lux, got {max_lux!r}")
        if isinstance(binning, bool) or not isinstance(binning, int) or binning < 1:
            raise ParameterError(f"binning must be an integer >= 1, got {binning!r}")
        if not isinstance(grid_size, int) or grid_size < 2:
            raise ParameterError(f"grid_size must be an integer >= 2, got {grid_size!r}")
        if not (math.isfinite(smoothing_sigma) and smoothing_sigma >= 0):
            raise ParameterError(f"smoothing_sigma must be >= 0, got {smoothing_sigma!r}")
        if not (math.isfinite(count_step) and count_step > 0):
            raise ParameterError(f"count_step must be > 0, got {count_step!r}")
        self.params = params
        self.max_lux = float(max_lux)
        self.binning = binning
        self.smoothing_sigma = float(smoothing_sigma)
        self.count_step = float(count_step)
        self.display_grid = np.linspace(0.0, 1.0, grid_size)
        self._grids = {}
        self.lux_grid, self.rates = self._grid(self.max_lux)  # rates: (2, G) events/s per pixel

    def _grid(self, max_lux: float):
        """Illuminance grid and its rates for white level ``max_lux`` (a few are cached)."""
        key = float(max_lux)
        if key not in self._grids:
            if not (math.isfinite(key) and 0 < key <= MAX_LUX):
                raise ParameterError(f"max_lux must be finite, > 0 and at most {MAX_LUX:g} lux, got {max_lux!r}")
            from ..rates import expected_rate

            if len(self._grids) >= 64:
                self._grids.pop(next(iter(self._grids)))
            lux = srgb_decode(self.display_grid) * key
            self._grids[key] = (lux, expected_rate(lux, self.params))
        return self._grids[key]

    def expected_counts(self, window_s: float, max_lux: float | None = None) -> np.ndarray:
        """Mean counts ``(2, G)`` of one bin over the grid.

        Parameters
        ----------
        window_s : float
            Length of the counting window in seconds.
        max_lux : float, optional
            White level in lux of the grid; by default the constructor's ``max_lux``.

        Returns
        -------
        numpy.ndarray
            Expected ON (row 0) and OFF (row 1) counts of a ``binning x binning`` bin at each of the
            ``G = grid_size`` illuminances of the grid.
        """
        window_s = check_positive(window_s, "window_s", "seconds")
        rates = self._grid(self.max_lux if max_lux is None else max_lux)[1]
        return rates * (self.binning**2 * window_s)

    def lux(self, counts, window_s: float, *, max_lux: float | None = None) -> np.ndarray:
        """Maximum-likelihood illuminance ``(H, W)`` in lux from binned counts ``(2, H, W)``.

        Parameters
        ----------
        counts : array_like, shape (2, H, W)
            ON and OFF counts of ``binning x binning`` bins (finite, >= 0).
        window_s : float
            Length of the counting window in seconds (finite, > 0).
        max_lux : float, optional
            White level in lux for this call, overriding the constructor's (the search range), e.g.
            with a dataset whose pairs have their own ``lux_scale``.

        Returns
        -------
        numpy.ndarray
            float64 illuminance in lux of shape ``(H, W)``, each value a point of the grid in
            ``[0, max_lux]``.
        """
        c = _check_counts(counts)
        window_s = check_positive(window_s, "window_s", "seconds")
        white = self.max_lux if max_lux is None else float(max_lux)
        lux_grid = self._grid(white)[0]
        if self.smoothing_sigma > 0:
            from scipy.ndimage import gaussian_filter

            c = np.stack([gaussian_filter(ch, self.smoothing_sigma, mode="reflect") for ch in c])
        q = np.round(c / self.count_step).astype(np.int64)
        pairs, inverse = np.unique(q.reshape(2, -1).T, axis=0, return_inverse=True)
        mu = self.expected_counts(window_s, white)
        log_mu = np.log(np.maximum(mu, 1e-300))
        n = pairs.astype(np.float64) * self.count_step  # (U, 2)
        best = np.empty(len(pairs), dtype=np.int64)
        total_mu = mu.sum(axis=0)
        for lo in range(0, len(pairs), 2048):
            nn = n[lo:lo + 2048]
            ll = nn[:, :1] * log_mu[0] + nn[:, 1:] * log_mu[1] - total_mu
            best[lo:lo + 2048] = np.argmax(ll, axis=1)
        return lux_grid[best[inverse.ravel()]].reshape(c.shape[1:])

    def display(self, counts, window_s: float, *, max_lux: float | None = None) -> np.ndarray:
        """Display-encoded estimate in ``[0, 1]`` (same encoding as the dataset targets).

        Parameters
        ----------
        counts : array_like, shape (2, H, W)
            ON and OFF counts of ``binning x binning`` bins (finite, >= 0).
        window_s : float
            Length of the counting window in seconds (finite, > 0).
        max_lux : float, optional
            White level in lux for this call (search range and encoding); by default the constructor's.

        Returns
        -------
        numpy.ndarray
            float64 image of shape ``(H, W)``: ``srgb_encode(lux / max_lux)`` of :meth:`lux`.
        """
        white = self.max_lux if max_lux is None else float(max_lux)
        return lux_to_display(self.lux(counts, window_s, max_lux=white), white)

    __call__ = display

    def cramer_rao_std(self, lux, window_s: float) -> np.ndarray:
        """Cramér-Rao standard deviation (lux) of the per-bin estimate at ``lux`` (no smoothing; inf where the counts
        carry no information about the light).

        Parameters
        ----------
        lux : float or array_like
            Illuminance in lux (finite, >= 0), any shape.
        window_s : float
            Length of the counting window in seconds.

        Returns
        -------
        numpy.ndarray
            Standard deviation in lux, of the shape of ``lux`` (at least 1-D: a scalar gives shape ``(1,)``).
        """
        from ..rates import expected_rate

        lux = np.atleast_1d(check_lux(lux, ndim=None))
        h = 1e-4 * np.maximum(lux, 1e-2)
        scale = self.binning**2 * check_positive(window_s, "window_s", "seconds")
        mu = expected_rate(lux, self.params) * scale
        upper, lower = np.minimum(lux + h, MAX_LUX), np.maximum(lux - h, 0)  # within the light evnoise takes
        dmu = (expected_rate(upper, self.params) - expected_rate(lower, self.params)) * scale
        dmu /= upper - lower
        info = (dmu**2 / np.maximum(mu, 1e-300)).sum(axis=0)
        with np.errstate(divide="ignore"):  # no information (no events, or none that change with the light): inf
            return 1.0 / np.sqrt(info)
