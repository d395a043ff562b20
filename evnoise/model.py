"""Closed-form noise-event probability per trial (paper section 3, made exact).

One polarity fires in a trial when ``log(n + b) - log(n0 + b) > eps`` (ON: ``eps = eps_pos``;
OFF is the mirror image with ``eps_neg``, and since ``n`` and ``n0`` are i.i.d. in a static
scene it has the same probability function). Two closed forms:

``method="poisson"`` (default)
    The exact discrete probability ``sum_m Pois(m; lam) P(N > e^eps (m + b) - b)``. Evaluated
    by a windowed sum whose cost grows like ``sqrt(lam)``; for arrays with one ``(eps, bias)``
    an adaptive piecewise-Chebyshev table in ``log(lam)`` is built from that sum and
    verified against it panel by panel (absolute error in ``log p`` below
    ``1e-13 + 1e-14 |log p|`` at check points between its nodes, i.e. relative error below about 1e-11
    wherever ``p > 1e-300``; measured, not proven). From lam = 1e4 up to 1.2e6 (where the sum's ripples
    defeat that table from ~2e4 on), an array with many values there (20 000 in a unit of ``log lam``,
    distinct ones where the log-spaced table covers it) gets panels in ``lam`` with a proven error bound
    instead (``evnoise._kernels.certified``: relative error of p at most 1e-10 plus the exact sum's own
    ~128 ulp of ``log p`` carried through; table speed, millions of values per second); with fewer values
    the log-spaced table answers where it covers, the exact sum elsewhere.
    Built tables are kept in evnoise's cache folder (module ``evnoise._cache``; ``EVNOISE_TABLE_CACHE=0``
    turns that off), and a table-sized array with few distinct ``lam`` (a flat field, an 8-bit
    image) is evaluated once per value and scattered: the same bits either way.
``method="gaussian"``
    The paper's eq. 3, ``p = erfc(z) / 2`` with
    ``z = (lam + b)(e^eps - 1) / sqrt(2 lam (1 + e^{2 eps}))``, evaluated stably. Its limit at
    ``lam = 0`` is 0 for ``b > 0`` and the continuous-approximation value 1/2 for ``b = 0``.
"""

from __future__ import annotations

import math
import threading

import numpy as np

from .errors import ParameterError

METHODS = ("poisson", "gaussian")
TABLE_MIN_SIZE = 4096  #: below this many elements the direct sum is cheaper than a table
_TABLE_UNITS = (-40, 16)  # unit panels of log(lam) covered by tables: lam in [4e-18, 2.4e7)
_SKIP_CHECK_MIN_LAM = 100.0  # below this the exact sum is cheap: no bound needed
_LOG_TINY = -746.0  # exp(x) rounds to exactly 0 for every x below about -745.13
_tables: dict = {}
_tables_lock = threading.Lock()
#: A tabulated array is evaluated once per distinct ``lam`` when it has at most this many distinct values
#: (and at most half its size); 0 evaluates every element (what earlier versions did, same bits).
MAX_LEVELS = 1 << 16


def _as_float_array(x, name: str) -> np.ndarray:
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ParameterError(f"{name} must be numeric, got {x!r}") from exc
    return arr


def _check_inputs(lam, eps, bias, method: str):
    if method not in METHODS:
        raise ParameterError(f"method must be one of {METHODS}, got {method!r}")
    lam = _as_float_array(lam, "lam")
    eps = _as_float_array(eps, "eps")
    bias = _as_float_array(bias, "bias")
    if np.isnan(lam).any() or (lam < 0).any():
        bad = lam[np.isnan(lam) | (lam < 0)].flat[0]
        raise ParameterError(f"lam (mean photons per trial) must be >= 0 and not NaN, got {bad}")
    if not (np.isfinite(eps).all() and (eps > 0).all()):
        bad = eps[~(np.isfinite(eps) & (eps > 0))].flat[0]
        raise ParameterError(f"eps (log-intensity threshold) must be finite and > 0, got {bad}")
    if not (np.isfinite(bias).all() and (bias >= 0).all()):
        bad = bias[~(np.isfinite(bias) & (bias >= 0))].flat[0]
        raise ParameterError(f"bias (photoreceptor bias, photons) must be finite and >= 0, got {bad}")
    try:
        shape = np.broadcast_shapes(lam.shape, eps.shape, bias.shape)
    except ValueError as exc:
        raise ParameterError(
            f"lam, eps and bias do not broadcast: shapes {lam.shape}, {eps.shape}, {bias.shape}"
        ) from exc
    return lam, eps, bias, shape


def _gaussian_z(lam, eps, bias, shape):
    """Argument ``z`` of eq. 3, ``p = erfc(z) / 2``, with its limits at ``lam = 0`` and ``inf``."""
    lam, eps, bias = (np.broadcast_to(a, shape) for a in (lam, eps, bias))
    # c / sqrt(1 + e^{2 eps}) written without overflow for large eps
    slope = -np.expm1(-eps) / np.sqrt(2.0 * (1.0 + np.exp(-2.0 * eps)))
    z = np.empty(shape)
    pos = lam > 0
    root = np.sqrt(lam, where=pos, out=np.ones(shape))
    z[...] = (root + np.divide(bias, root, where=pos, out=np.zeros(shape))) * slope
    # lam = 0: z -> inf for bias > 0 (no event), z -> 0 for bias = 0 (continuous limit 1/2)
    z[~pos] = np.where(bias[~pos] > 0, np.inf, 0.0)
    return z


def _table_for(c: float, b: float):
    from ._kernels.chebyshev import LogPTable

    key = (c, b)
    with _tables_lock:
        table = _tables.get(key)
        if table is None:
            if len(_tables) > 64:
                _tables.clear()
            table = _tables[key] = LogPTable(c, b, *_TABLE_UNITS)
    return table


def _log_p_poisson(lam, eps, bias, shape, skip_below=None):
    """Exact log p. ``skip_below``: where a Chernoff bound shows ``log p < skip_below``, return -inf."""
    from ._kernels.poisson import log_event_probability_exact_array

    lam_b = np.ascontiguousarray(np.broadcast_to(lam, shape), dtype=np.float64).ravel()
    out = np.empty(lam_b.shape)
    uniform = eps.size == 1 or np.all(eps == eps.flat[0])
    uniform = uniform and (bias.size == 1 or np.all(bias == bias.flat[0]))
    if uniform and lam_b.size >= TABLE_MIN_SIZE and (skip_below is None or skip_below <= _LOG_TINY):
        with np.errstate(over="ignore"):
            c = float(np.expm1(eps.flat[0]))
        table = _table_for(c, float(bias.flat[0]))
        # The table evaluates element by element, so a field with few distinct lam (a flat field: one; an
        # 8-bit image: at most 256) is evaluated once per value and scattered: the same bits, less work.
        found = _levels(lam_b)
        values = lam_b if found is None else found[0]
        # The skip test (a Chernoff bound, ~100 exp per value) costs more than a table lookup, so the
        # table applies it only where it would fall back to the exact sum; a tabulated log p below
        # skip_below gives exp(log p) = 0 exactly as -inf does (skip_below <= _LOG_TINY), so p is unchanged.
        if skip_below is None:
            log_p = table.evaluate(values)
        else:
            log_p = table.evaluate(values, float(skip_below), _SKIP_CHECK_MIN_LAM)
        return (log_p if found is None else log_p[found[1]]).reshape(shape)
    todo = np.ones(lam_b.shape, dtype=bool)
    with np.errstate(over="ignore"):  # eps past ~709: c = inf, a threshold no count reaches (p = 0)
        c_b = np.ascontiguousarray(np.broadcast_to(np.expm1(eps), shape)).ravel()
    if bias.size == 1 or np.all(bias == bias.flat[0]):
        # per-pixel thresholds (mismatch) on shared lam levels: tabulate once per level
        todo &= ~_grouped(lam_b, c_b, float(bias.flat[0]), todo, out)
    if skip_below is not None:
        # only where the exact sum is costly (large lam) and p may be negligible is a bound worth
        # computing: a pre-filter on the Gaussian form's exponent z^2 (log p ~ -z^2) leaves out the
        # values that are nowhere near skip_below. Either way p is unchanged (a skipped value has
        # log p < skip_below <= _LOG_TINY, whose exp is 0), only the work differs.
        big = todo & (lam_b > _SKIP_CHECK_MIN_LAM)
        if big.any():
            z = _gaussian_z(lam_b, np.broadcast_to(eps, shape).ravel(), np.broadcast_to(bias, shape).ravel(),
                            lam_b.shape)
            big &= z * z > 0.5 * -skip_below
        big = np.flatnonzero(big)
        if big.size:
            from ._kernels.bounds import log_chernoff_bound_array

            b_big = np.ascontiguousarray(np.broadcast_to(bias, shape)).ravel()[big]
            bound = np.empty(big.size)
            log_chernoff_bound_array(np.ascontiguousarray(lam_b[big]), np.ascontiguousarray(c_b[big]), b_big, bound)
            skip = big[bound < skip_below]
            todo[skip] = False
            out[skip] = -np.inf
    b_b = np.ascontiguousarray(np.broadcast_to(bias, shape), dtype=np.float64).ravel()[todo]
    sub = np.empty(b_b.shape)
    log_event_probability_exact_array(np.ascontiguousarray(lam_b[todo]), np.ascontiguousarray(c_b[todo]),
                                      b_b, sub)
    out[todo] = sub
    return out.reshape(shape)


def _levels(lam: np.ndarray):
    """``(levels, inverse)`` of the flat ``lam`` when it has few distinct values (:data:`MAX_LEVELS`), else None."""
    cap = min(MAX_LEVELS, lam.size // 2)
    if cap < 1:
        return None
    from ._kernels.levels import find_levels

    return find_levels(lam, cap)


def same_path_values(levels, n_values: int) -> np.ndarray:
    """Distinct photon counts ``levels`` arranged so that the closed form treats them as it treats ``n_values`` values.

    For one ``(eps, bias)`` the closed form (:func:`event_probability`, :func:`log_event_probability`,
    ``method="poisson"``) evaluates each element on its own, by one of two paths chosen by the array's
    size: the exact sum for small arrays, the Chebyshev table (equal to the sum to ~1e-11, not bit for
    bit) from ``TABLE_MIN_SIZE`` elements on. A caller that evaluates a large field once per distinct
    value and scatters the results must keep the large array's path: this returns ``levels`` (1-D
    float64, non-empty) padded with copies of its last value up to ``TABLE_MIN_SIZE`` where the full
    array of ``n_values`` values takes the table path. The first ``levels.size`` results are then, bit
    for bit, those the values get inside the full array.

    Parameters
    ----------
    levels : numpy.ndarray
        1-D float64 photon counts per trial (typically distinct), at least one.
    n_values : int
        Size of the array whose evaluation path is to be kept.

    Returns
    -------
    numpy.ndarray
        1-D contiguous float64 array that starts with ``levels``.
    """
    levels = np.ascontiguousarray(levels, dtype=np.float64).ravel()
    if n_values >= TABLE_MIN_SIZE > levels.size:
        return np.concatenate([levels, np.full(TABLE_MIN_SIZE - levels.size, levels[-1])])
    return levels


def _grouped(lam, c, b, todo, out) -> np.ndarray:
    """Fill ``out`` (log p) where lam repeats enough for the grouped path; returns the mask of done."""
    from ._kernels.poisson import GROUPED_MAX_LAM

    done = np.zeros(lam.shape, dtype=bool)
    cand = np.flatnonzero(todo & (lam > 0) & (lam <= GROUPED_MAX_LAM))
    if cand.size < TABLE_MIN_SIZE:
        return done
    levels, inverse = np.unique(lam[cand], return_inverse=True)
    if levels.size * 8 > cand.size:
        return done  # mostly distinct lam values: nothing to share
    p = _grouped_values(levels, inverse, c[cand], b, np.full(2, np.nan))
    good = p > 1e-280  # NaN (terms ran past the level's table) is not good either
    with np.errstate(divide="ignore"):
        out[cand[good]] = np.log(p[good])
    done[cand[good]] = True
    return done


def _grouped_values(levels, inverse, c, b: float, c_range) -> np.ndarray:
    """:func:`evnoise._kernels.poisson.event_probability_grouped` of ``levels[inverse]`` with thresholds ``c``."""
    from ._kernels.poisson import event_probability_grouped

    order = np.argsort(inverse, kind="stable")
    starts = np.searchsorted(inverse[order], np.arange(levels.size + 1))
    p = np.empty(inverse.size)
    event_probability_grouped(levels, starts.astype(np.int64), order.astype(np.int64), np.ascontiguousarray(c),
                              b, p, np.ascontiguousarray(c_range, dtype=np.float64))
    return p


#: :func:`log_event_probability_alone` sums with tables spanning thresholds ``[k, k + 1) * ALONE_EPS_BIN``
ALONE_EPS_BIN = 0.05


def log_event_probability_alone(lam, eps, bias: float) -> np.ndarray:
    """Log p of each element from its own ``lam`` and ``eps`` alone: the same bits whatever else the call holds.

    :func:`log_event_probability` takes the faster of several paths, equal to ~1e-11 but not bit for bit, by the
    array's size and by how many values share a ``lam``; a caller whose output must not depend on how its values
    are batched (the trial tier's runs in a video, whatever the windows) uses this instead. One ``eps`` for all
    (a scalar): the Chebyshev table without certified panels (the exact sum where it does not tabulate); one per
    value: the sum of :func:`evnoise._kernels.poisson.event_probability_grouped` (its relative tolerance 1e-17)
    with tables that span a fixed bin of thresholds (:data:`ALONE_EPS_BIN` wide) at each ``lam``, the windowed
    exact sum where that cannot serve. So a value's bits depend on the path its caller chose (scalar or array
    ``eps``) and on the value alone.

    Parameters
    ----------
    lam : numpy.ndarray
        1-D photons per trial (``>= 0``).
    eps : numpy.ndarray or float
        Thresholds (``> 0``): one for all (a scalar) or one per ``lam``.
    bias : float
        Photoreceptor bias in photons per trial.

    Returns
    -------
    numpy.ndarray
        float64 log p, as ``lam``.
    """
    from ._kernels.poisson import GROUPED_MAX_LAM, log_event_probability_exact_array

    lam = np.ascontiguousarray(lam, dtype=np.float64).ravel()
    if lam.size == 0:
        return np.empty(0)
    if np.ndim(eps) == 0 and float(eps) < 700.0:  # (past it c overflows: the sum's p = 0 below)
        found = _levels(lam)  # each distinct lam once (a hash: no sort where the values are few)
        values, back = found if found is not None else (lam, None)
        with np.errstate(over="ignore"):  # eps past ~709: c = inf
            c = float(np.expm1(float(eps)))
        log_p = _table_for(c, float(bias)).evaluate(values, certified_panels=False)
        return log_p if back is None else log_p[back]
    eps = np.ascontiguousarray(np.broadcast_to(np.asarray(eps, dtype=np.float64), lam.shape)).ravel()
    # each distinct (lam, eps) once, its result scattered
    if np.all(eps == eps[0]):
        lam, back = np.unique(lam, return_inverse=True)
        eps = np.full(lam.size, eps[0])
    else:
        pairs, back = np.unique(np.stack([lam, eps], axis=1), axis=0, return_inverse=True)
        lam, eps = np.ascontiguousarray(pairs[:, 0]), np.ascontiguousarray(pairs[:, 1])
    with np.errstate(over="ignore"):  # eps past ~709: c = inf (p = 0, the exact sum's)
        c = np.expm1(eps)
        low = np.floor(eps / ALONE_EPS_BIN)
        c_lo, c_hi = np.expm1(low * ALONE_EPS_BIN), np.expm1((low + 1.0) * ALONE_EPS_BIN)
    out = np.full(lam.size, np.nan)
    ok = (lam > 0) & (lam <= GROUPED_MAX_LAM) & (c >= c_lo) & (c <= c_hi) & (c_hi <= GROUPED_MAX_LAM)
    for k in np.unique(low[ok]):
        cand = np.flatnonzero(ok & (low == k))
        levels, inverse = np.unique(lam[cand], return_inverse=True)
        p = _grouped_values(levels, inverse.ravel(), c[cand], float(bias), np.array([c_lo[cand[0]], c_hi[cand[0]]]))
        good = p > 1e-280  # NaN (terms ran past the level's table) is not good either
        out[cand[good]] = np.log(p[good])
    todo = np.flatnonzero(np.isnan(out))
    if todo.size:
        sub = np.empty(todo.size)
        log_event_probability_exact_array(np.ascontiguousarray(lam[todo]), np.ascontiguousarray(c[todo]),
                                          np.full(todo.size, float(bias)), sub)
        out[todo] = sub
    return out[back.ravel()]


def log_event_probability(lam, eps, bias=0.0, *, method: str = "poisson") -> np.ndarray:
    """Natural log of the per-trial probability of one polarity's noise event.

    Parameters
    ----------
    lam : array_like
        Mean photon count per trial (dimensionless, ``>= 0``; ``inf`` allowed).
    eps : array_like
        Log-intensity contrast threshold (dimensionless, ``> 0``).
    bias : array_like, optional
        Photoreceptor bias ``b_pr`` in photons per trial (``>= 0``).
    method : {"poisson", "gaussian"}
        Exact discrete form or the paper's Gaussian approximation (eq. 3).

    Returns
    -------
    numpy.ndarray or numpy.float64
        float64 array of the broadcast shape, or a ``numpy.float64`` when every input is a
        scalar (as numpy's functions do); finite however small the probability (far below 1e-300) for
        ``0 < lam`` up to ~1e299 at ``eps = 20`` (~1e306 at ``eps = 5``; a pixel sees at most 1e12 photons per
        trial), ``-inf`` beyond and where the probability is exactly 0.
    """
    lam, eps, bias, shape = _check_inputs(lam, eps, bias, method)
    if method == "gaussian":
        from scipy.special import log_ndtr

        # log(erfc(z) / 2) = log Phi(-sqrt(2) z), accurate in the far tail
        return _scalar_if_0d(log_ndtr(-math.sqrt(2.0) * _gaussian_z(lam, eps, bias, shape)))
    return _scalar_if_0d(_log_p_poisson(lam, eps, bias, shape))


def _scalar_if_0d(values):
    """A 0-d result as ``numpy.float64`` (numpy's convention for scalar inputs), else the array."""
    values = np.asarray(values, dtype=np.float64)
    return values[()] if values.ndim == 0 else values


def event_probability(lam, eps, bias=0.0, *, method: str = "poisson") -> np.ndarray:
    """Per-trial probability that one polarity fires in a static scene.

    ``P(log(n + b) - log(n0 + b) > eps)`` for ``n, n0 ~ Poisson(lam)`` i.i.d. (strict inequality).

    Parameters
    ----------
    lam : array_like
        Mean photon count per trial (dimensionless, ``>= 0``; ``inf`` allowed).
    eps : array_like
        Log-intensity contrast threshold (dimensionless, finite, ``> 0``).
    bias : array_like, optional
        Photoreceptor bias ``b_pr`` in photons per trial (finite, ``>= 0``; default 0).
    method : {"poisson", "gaussian"}
        Exact discrete form or the paper's Gaussian approximation (eq. 3), as in :func:`log_event_probability`.

    Returns
    -------
    numpy.ndarray or numpy.float64
        float64 array of the broadcast shape, or a ``numpy.float64`` when every input is a scalar
        (values that are below the smallest double underflow to 0 without a warning).
    """
    lam, eps, bias, shape = _check_inputs(lam, eps, bias, method)
    if method == "gaussian":
        from scipy.special import erfc

        return _scalar_if_0d(0.5 * erfc(_gaussian_z(lam, eps, bias, shape)))
    return _scalar_if_0d(np.exp(_log_p_poisson(lam, eps, bias, shape, skip_below=-760.0)))
