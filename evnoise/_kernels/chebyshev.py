"""Adaptive piecewise Chebyshev interpolation of ``log p(lam)`` in ``u = log(lam)``.

For fixed ``(eps, bias)`` the exact ``log p`` is analytic in ``u`` but not slowly varying
everywhere: the integer thresholds ``k(m) = m + floor(c (m + b))`` form a lattice, and once
the Poisson spread ``sqrt(lam)`` is comparable to the lattice's period the function carries
real ripples on a ``lam`` scale of about ``sqrt(lam)``. A fixed grid would either miss them
or cost too much, so panels are refined adaptively: a panel's series is accepted only if
it reproduces the exact kernel at check points between its nodes to within the tolerance,
otherwise it is halved (down to a minimum width, below which the panel is evaluated with
the exact kernel directly). Evaluation does a binary search for the panel and Clenshaw.

From ``lam = 1e4`` up to :data:`CERT_LAST_UNIT` a call with many values at or above 1e4 in a unit
(:data:`CERT_MIN_VALUES`; distinct ones in a tabulated unit) gets certified panels in ``lam`` there
(:mod:`evnoise._kernels.certified`: Chebyshev interpolation of a rescaled ``p`` with a proven error bound), in the
units left to the exact kernel and in those the log-spaced panels tabulate alike (from 1e4 to e^10 = 2.2e4, and to
e^11 for the largest thresholds): their checks between nodes are measured, not proven. Below 1e4, and for calls
with fewer values, the values are the log-spaced panels' or the exact sum's, bit for bit.
"""

from __future__ import annotations

import functools
import hashlib
import math
from pathlib import Path

import numpy as np
from numba import prange

from . import certified
from ._jit import kernel
from .bounds import chernoff_bracket, log_chernoff_bound
from .certified import clenshaw as _clenshaw
from .certified import dct as _coefficients
from .poisson import log_event_probability_exact

DEGREE = 16
MAX_DEPTH = 6  # smallest panel width 2**-6 in natural-log units of lam
# A panel is accepted when |series - exact| <= ABS_TOL + REL_TOL * |log p| at every check point.
ABS_TOL = 1e-13
REL_TOL = 1e-14
DIRECT = -1  # marker of a panel evaluated with the exact kernel
#: Fewer values than this are evaluated in one thread: waking the thread pool costs ~10 us on an idle machine
#: and milliseconds on a busy one, more than a few hundred table look-ups (the result is the same bit for bit).
SERIAL_BELOW = 1024
#: last unit of ``u = log lam`` whose direct panels are replaced by certified panels (lam < e^14 = 1.2e6):
#: above, a unit would cost a minute or more to certify, and stays with the exact sum (and the skip bound)
CERT_LAST_UNIT = 13
#: a direct unit's certified panels are used only for a call that asks for at least this many values in it:
#: building (or reading) them costs seconds once (2-6 s per unit here, then cached on disk), the exact sum
#: 0.1-1 ms per value, so a few hundred distinct levels (an 8-bit image, a preset curve) are summed exactly.
#: The rule looks at the call's own values only, never at what is cached, so the same values always give
#: the same bits. The values counted are the distinct ones the table is asked for (:mod:`evnoise.model`
#: evaluates a field once per distinct lam), since their number is what the exact sum's cost follows.
CERT_MIN_VALUES = 20_000


@kernel
def _exact_on_nodes(u_lo, u_hi, c, b, degree):
    out = np.empty(degree + 1)
    for k in range(degree + 1):
        x = math.cos(math.pi * (k + 0.5) / (degree + 1))
        u = 0.5 * (u_lo + u_hi) + 0.5 * (u_hi - u_lo) * x
        out[k] = log_event_probability_exact(math.exp(u), c, b)
    return out


@kernel
def _panel_ok(coef, u_lo, u_hi, c, b):
    """Check the series against the exact kernel midway between the nodes and at the ends."""
    n = coef.shape[0]
    for k in range(-1, n):
        if k < 0:
            x = 1.0
        elif k == n - 1:
            x = -1.0
        else:
            x = math.cos(math.pi * (k + 1.0) / n)  # between nodes k and k + 1
        u = 0.5 * (u_lo + u_hi) + 0.5 * (u_hi - u_lo) * x
        exact = log_event_probability_exact(math.exp(u), c, b)
        approx = _clenshaw(coef, x)
        if not abs(approx - exact) <= ABS_TOL + REL_TOL * abs(exact):
            return False
    return True


def build_unit_panel(unit: int, c: float, b: float):
    """Panels covering ``u`` in ``[unit, unit + 1)``: a list of ``(u_lo, u_hi, coef | None)``."""
    out = []
    stack = [(float(unit), float(unit + 1), 0)]
    while stack:
        u_lo, u_hi, depth = stack.pop()
        coef = _coefficients(_exact_on_nodes(u_lo, u_hi, c, b, DEGREE))
        if _panel_ok(coef, u_lo, u_hi, c, b):
            out.append((u_lo, u_hi, coef))
        elif depth >= MAX_DEPTH:
            # ripples finer than the smallest panel: the whole unit is evaluated exactly
            return [(float(unit), float(unit + 1), None)]
        else:
            mid = 0.5 * (u_lo + u_hi)
            stack.append((mid, u_hi, depth + 1))
            stack.append((u_lo, mid, depth + 1))
    out.sort(key=lambda p: p[0])
    return out


_CACHED = ("units", "unit_start", "bounds", "coef")


@functools.lru_cache(maxsize=1)
def _build_signature() -> dict:
    """What a table's bits depend on besides ``(c, b)``: the code that builds it and what compiles and runs it."""
    import platform
    import sys

    import llvmlite
    import llvmlite.binding as llvm
    import numba
    from numba.core import config

    here = Path(__file__).resolve().parent
    source = hashlib.sha256()
    for name in ("chebyshev.py", "certified.py", "poisson.py", "bounds.py", "_jit.py"):
        source.update((here / name).read_bytes())
    features = config.CPU_FEATURES if config.CPU_FEATURES is not None else llvm.get_host_cpu_features().flatten()
    from .._version import __version__

    return {"what": "evnoise log p Chebyshev table", "evnoise": __version__, "source": source.hexdigest(),
            "numpy": np.__version__, "numba": numba.__version__, "llvmlite": llvmlite.__version__,
            "machine": platform.machine(), "byteorder": sys.byteorder,
            "cpu": config.CPU_NAME or llvm.get_host_cpu_name(),
            "cpu_features": hashlib.sha256(features.encode()).hexdigest()[:16]}


def units_to_arrays(units: dict) -> dict:
    """Unit panels ``{unit: [(u_lo, u_hi, coef | None), ...]}`` as flat arrays (a direct panel: a row of NaN)."""
    keys = sorted(units)
    unit_start = np.zeros(len(keys) + 1, dtype=np.int64)
    bounds, coefs = [], []
    for i, u in enumerate(keys):
        unit_start[i + 1] = unit_start[i] + len(units[u])
        for u_lo, u_hi, coef in units[u]:
            bounds.append((u_lo, u_hi))
            coefs.append(np.full(DEGREE + 1, np.nan) if coef is None else coef)
    return {"units": np.array(keys, dtype=np.int64), "unit_start": unit_start,
            "bounds": np.array(bounds, dtype=np.float64).reshape(-1, 2),
            "coef": np.array(coefs, dtype=np.float64).reshape(-1, DEGREE + 1)}


def arrays_to_units(arrays: dict, first_unit: int, last_unit: int) -> dict | None:
    """:func:`units_to_arrays` undone, or None when the arrays are not a well-formed table of ``[first, last]``.

    Checked: dtypes and shapes; units increasing inside the table's range; each unit's panels cover
    ``[unit, unit + 1)`` contiguously in increasing order; a panel's coefficients are all finite, or the
    unit is one direct panel (all NaN).
    """
    units, start, bounds, coef = (arrays[k] for k in _CACHED)
    if not (units.dtype == np.int64 and start.dtype == np.int64 and bounds.dtype == np.float64
            and coef.dtype == np.float64 and units.ndim == 1 and start.shape == (units.size + 1,)
            and bounds.ndim == 2 and bounds.shape[1] == 2 and coef.shape == (bounds.shape[0], DEGREE + 1)):
        return None
    if units.size and not (units[0] >= first_unit and units[-1] <= last_unit and (np.diff(units) > 0).all()):
        return None
    if not (start[0] == 0 and start[-1] == bounds.shape[0] and (np.diff(start) > 0).all()
            and np.isfinite(bounds).all()):
        return None
    finite = np.isfinite(coef).all(axis=1)
    nan = np.isnan(coef).all(axis=1)
    out = {}
    for i, u in enumerate(units.tolist()):
        lo, hi = int(start[i]), int(start[i + 1])
        b = bounds[lo:hi]
        if not (b[0, 0] == u and b[-1, 1] == u + 1 and (b[:, 0] < b[:, 1]).all() and (b[1:, 0] == b[:-1, 1]).all()):
            return None
        if hi - lo == 1 and nan[lo]:
            out[u] = [(float(u), float(u + 1), None)]
        elif finite[lo:hi].all():
            out[u] = [(float(b[j, 0]), float(b[j, 1]), coef[lo + j].copy()) for j in range(hi - lo)]
        else:
            return None
    return out


class LogPTable:
    """Lazily built adaptive table of ``log p`` for one ``(c, b)`` over unit panels of ``u``.

    Built units are kept in evnoise's on-disk cache (:mod:`evnoise._cache`, keyed by ``(c, b)``, the
    table's range and :func:`_build_signature`), so that the next process reads them instead of
    building them; a table read back is the same, bit for bit, as one built.
    """

    def __init__(self, c: float, b: float, first_unit: int, last_unit: int):
        self.c = float(c)
        self.b = float(b)
        self.first_unit = first_unit
        self.last_unit = last_unit
        self._units: dict[int, list] = {}
        self._certified: dict[int, list] = {}
        self._arrays = None
        self._disk_read = False
        self._cert_disk_read = False

    def cache_key(self) -> dict:
        """The on-disk cache key of this table (:mod:`evnoise._cache`)."""
        return {**_build_signature(), "c": self.c.hex(), "b": self.b.hex(), "units": [self.first_unit, self.last_unit],
                "degree": DEGREE, "max_depth": MAX_DEPTH, "abs_tol": ABS_TOL.hex(), "rel_tol": REL_TOL.hex()}

    def certified_cache_key(self) -> dict:
        """The on-disk cache key of this table's certified panels."""
        return {**self.cache_key(), "what": "evnoise certified panels of p", "cert_degree": certified.DEGREE,
                "cert_tol": certified.CERT_TOL.hex(), "cert_lam_min": certified.LAM_MIN.hex(),
                "cert_last_unit": CERT_LAST_UNIT}

    def _read_cert_disk(self) -> dict:
        from .._cache import load_arrays

        try:
            arrays = load_arrays(self.certified_cache_key(), certified.CACHED)
            found = None if arrays is None else certified.arrays_to_units(arrays, self.first_unit, CERT_LAST_UNIT)
        except Exception:  # noqa: BLE001 -- whatever is wrong with a cached file, the panels are built instead
            found = None
        return found or {}

    def _write_cert_disk(self) -> None:
        from .._cache import save_arrays

        merged = {**self._read_cert_disk(), **self._certified}
        try:
            save_arrays(self.certified_cache_key(), certified.units_to_arrays(merged))
        except Exception:  # noqa: BLE001 -- the cache is only a speed-up
            pass

    def certifiable(self, unit: int) -> bool:
        """Whether ``unit`` (once built; direct or tabulated) gets certified panels (from ``LAM_MIN`` up)."""
        return unit in self._units and unit <= CERT_LAST_UNIT and math.exp(unit + 1) > certified.LAM_MIN

    def ensure_certified(self, units) -> None:
        """Build (or read from disk) the certified panels of the certifiable units among ``units``."""
        new = [u for u in units if self.certifiable(u) and u not in self._certified]
        if not new:
            return
        if not self._cert_disk_read:
            self._cert_disk_read = True
            for u, panels in self._read_cert_disk().items():
                if u not in self._certified and self.certifiable(u):
                    self._certified[u] = panels
            new = [u for u in new if u not in self._certified]
        for u in new:
            self._certified[u] = certified.build_unit(u, self.c, self.b)
        if new:
            self._write_cert_disk()
        self._arrays = self._pack()

    def certified_panels(self) -> dict:
        """``{unit: [(coef | None, par), ...]}`` of the certified panels built so far (see
        :data:`evnoise._kernels.certified.N_PAR`; ``par[6] + par[7]`` bounds the relative error of p)."""
        return dict(self._certified)

    def _read_disk(self) -> dict:
        from .._cache import load_arrays

        try:
            arrays = load_arrays(self.cache_key(), _CACHED)
            found = None if arrays is None else arrays_to_units(arrays, self.first_unit, self.last_unit)
        except Exception:  # noqa: BLE001 -- whatever is wrong with a cached file, the table is built instead
            found = None
        return found or {}

    def _write_disk(self) -> None:
        from .._cache import save_arrays

        merged = {**self._read_disk(), **self._units}  # keep what other processes added meanwhile
        try:
            save_arrays(self.cache_key(), units_to_arrays(merged))
        except Exception:  # noqa: BLE001 -- the cache is only a speed-up: a table that cannot be stored is kept in memory
            pass

    def ensure(self, units) -> None:
        """Build the unit panels in ``units`` (an iterable of ints) that are not built yet (or read them from disk)."""
        new = [u for u in units if self.first_unit <= u <= self.last_unit and u not in self._units]
        changed = False
        if new and not self._disk_read:
            self._disk_read = True
            for u, panels in self._read_disk().items():
                if u not in self._units:
                    self._units[u] = panels
                    changed = True
            new = [u for u in new if u not in self._units]
        for u in new:
            self._units[u] = build_unit_panel(u, self.c, self.b)
        if new:
            self._write_disk()
        if new or changed or self._arrays is None:
            self._arrays = self._pack()

    def _pack(self):
        n_units = self.last_unit - self.first_unit + 1
        unit_start = np.zeros(n_units + 1, dtype=np.int64)
        lo, coefs = [], []
        for i in range(n_units):
            panels = self._units.get(self.first_unit + i, [])
            unit_start[i + 1] = unit_start[i] + len(panels)
            for u_lo, u_hi, coef in panels:
                lo.append((u_lo, u_hi))
                coefs.append(np.full(DEGREE + 1, np.nan) if coef is None else coef)
        bounds = np.array(lo, dtype=np.float64).reshape(-1, 2)
        coef_arr = np.array(coefs, dtype=np.float64).reshape(-1, DEGREE + 1)
        direct = np.array([np.isnan(cf[0]) for cf in coefs], dtype=np.bool_)
        # a panel evaluated exactly gets a bound on log p over its whole range, so that values whose
        # probability underflows are skipped without a per-value bound (-inf: no bound computed)
        panel_bound = np.full(direct.size, math.inf)
        for i in np.flatnonzero(direct):
            panel_bound[i] = panel_log_bound(math.exp(bounds[i, 0]), math.exp(bounds[i, 1]), self.c, self.b)
        cert_start = np.zeros(n_units + 1, dtype=np.int64)
        pars, cert_coefs = [], []
        for i in range(n_units):
            cert = self._certified.get(self.first_unit + i, [])
            cert_start[i + 1] = cert_start[i] + len(cert)
            for cf, par in cert:
                pars.append(par)
                cert_coefs.append(np.full(certified.DEGREE + 1, np.nan) if cf is None else cf)
        cert_par = np.array(pars, dtype=np.float64).reshape(-1, certified.N_PAR)
        cert_coef = np.array(cert_coefs, dtype=np.float64).reshape(-1, certified.DEGREE + 1)
        return unit_start, bounds, coef_arr, direct, panel_bound, cert_start, cert_par, cert_coef

    def evaluate(self, lam: np.ndarray, skip_below: float = -math.inf, skip_min_lam: float = math.inf, *,
                 certified_panels: bool = True) -> np.ndarray:
        """``log p`` at the 1-D float64 array ``lam`` (units outside the table use the exact kernel).

        Where the exact kernel would be used (outside the table, or in a panel too rippled to
        tabulate) and ``lam > skip_min_lam``, a Chernoff bound is computed first and ``-inf``
        returned where it shows ``log p < skip_below``. Tabulated values cost no more than the
        bound, so they are returned as they are (``exp`` of them underflows to 0 all the same).
        ``certified_panels=False``: none, whatever the call holds, so that each value's bits depend on it alone
        (certified panels serve a unit with :data:`CERT_MIN_VALUES` values in the call).
        """
        valid = lam[(lam > 0) & np.isfinite(lam)]
        units = np.floor(np.log(valid))
        if not certified_panels:
            self.ensure(int(u) for u in np.unique(units))  # (units outside the table are left out there)
            units = units[:0]
        if units.size:
            lo = int(max(units.min(), self.first_unit))
            hi = int(min(units.max(), self.last_unit))
            if lo <= hi:
                present = np.bincount((np.clip(units, lo, hi) - lo).astype(np.int64), minlength=hi - lo + 1)
                wanted = [lo + int(i) for i in np.flatnonzero(present)]
                self.ensure(wanted)
                # certified panels where a unit has many values and (direct) is not skipped as a whole by its bound
                above = valid >= certified.LAM_MIN  # only these can use certified panels
                counted = np.bincount((np.clip(units[above], lo, hi) - lo).astype(np.int64), minlength=hi - lo + 1)
                many = {u for u in wanted if counted[u - lo] >= CERT_MIN_VALUES
                        and (self._is_direct(u) or _many_distinct(valid[above & (units == u)]))}
                need = [u for u in many if self.certifiable(u) and u not in self._certified
                        and not (self._is_direct(u) and self._unit_bound(u) < skip_below)]
                self.ensure_certified(need)
                certify = np.array([u in many for u in range(self.first_unit, self.last_unit + 1)], dtype=np.bool_)
            else:
                certify = np.zeros(self.last_unit - self.first_unit + 1, dtype=np.bool_)
        else:
            certify = np.zeros(self.last_unit - self.first_unit + 1, dtype=np.bool_)
        if self._arrays is None:
            self._arrays = self._pack()
        out = np.empty_like(lam)
        run = _evaluate_serial if lam.shape[0] < SERIAL_BELOW else _evaluate
        run(lam, *self._arrays, certify, self.first_unit, self.c, self.b, float(skip_below), float(skip_min_lam), out)
        return out

    def _is_direct(self, unit: int) -> bool:
        """Whether built ``unit`` is one panel left to the exact kernel (the log-spaced panels gave up there)."""
        panels = self._units[unit]
        return len(panels) == 1 and panels[0][2] is None

    def _unit_bound(self, unit: int) -> float:
        """The Chernoff bound on log p over a direct unit (as the evaluation uses it to skip the unit)."""
        return panel_log_bound(math.exp(unit), math.exp(unit + 1), self.c, self.b)


def _many_distinct(values: np.ndarray) -> bool:
    """Whether ``values`` hold at least :data:`CERT_MIN_VALUES` distinct ones. A tabulated unit is certified only
    then: a field with few distinct values (a flat field, an image) evaluated pixel by pixel keeps the values it
    gets when evaluated once per distinct value (:func:`evnoise.model.same_path_values`), and where it is not
    certified the log-spaced panels answer as fast (a direct unit counts every value: its other path is the exact
    sum, whose cost follows the values)."""
    from .levels import find_levels

    return CERT_MIN_VALUES <= 1 or find_levels(values, CERT_MIN_VALUES - 1) is None


@kernel
def panel_log_bound(lam_lo, lam_hi, c, b):
    """An upper bound on ``log p(lam)`` for every ``lam`` in ``[lam_lo, lam_hi]`` (``0 < lam_lo <= lam_hi``).

    The Chernoff bound ``lam g(theta) - theta c b`` with ``g(theta) = (e^theta - 1) + (e^{-a theta} - 1)``
    (see :func:`evnoise._kernels.bounds.log_chernoff_bound`) holds for every ``theta >= 0``; with one
    ``theta`` (the optimal one at ``lam_lo``) it is linear in ``lam``, so its larger end value bounds
    the whole interval.
    """
    a = 1.0 + c
    theta, _ = chernoff_bracket(lam_lo, c, b, 80)
    g = math.expm1(theta) + math.expm1(-a * theta)
    return max(lam_lo * g, lam_hi * g) - theta * (c * b)


@kernel
def _exact_or_skip(x, c, b, skip_below, skip_min_lam):
    if x > skip_min_lam and log_chernoff_bound(x, c, b) < skip_below:
        return -math.inf
    return log_event_probability_exact(x, c, b)


@kernel(inline=True)
def _evaluate_one(x, unit_start, bounds, coef, direct, panel_bound, cert_start, cert_par, cert_coef, certify,
                  first_unit, c, b, skip_below, skip_min_lam):
    """``log p`` at one ``x`` from the table (the body of :func:`_evaluate` and :func:`_evaluate_serial`)."""
    n_units = unit_start.shape[0] - 1
    if not x > 0.0 or x == math.inf:
        return -math.inf
    u = math.log(x)
    unit = int(math.floor(u)) - first_unit
    if unit < 0 or unit >= n_units or unit_start[unit] == unit_start[unit + 1]:
        return _exact_or_skip(x, c, b, skip_below, skip_min_lam)
    lo = unit_start[unit]
    hi = unit_start[unit + 1] - 1
    while lo < hi:  # last panel with u_lo <= u
        mid = (lo + hi + 1) // 2
        if bounds[mid, 0] <= u:
            lo = mid
        else:
            hi = mid - 1
    if direct[lo]:
        if panel_bound[lo] < skip_below:
            return -math.inf
        if certify[unit] and x >= certified.LAM_MIN:
            v = certified.evaluate_one(x, cert_start[unit], cert_start[unit + 1], cert_par, cert_coef)
            if not math.isnan(v):
                return v
        return _exact_or_skip(x, c, b, skip_below, skip_min_lam)
    if certify[unit] and x >= certified.LAM_MIN and cert_start[unit] < cert_start[unit + 1]:
        # a tabulated unit with certified panels: theirs (or, where a panel has no certificate, the exact sum)
        v = certified.evaluate_one(x, cert_start[unit], cert_start[unit + 1], cert_par, cert_coef)
        return v if not math.isnan(v) else log_event_probability_exact(x, c, b)
    u_lo = bounds[lo, 0]
    u_hi = bounds[lo, 1]
    t = (2.0 * u - u_lo - u_hi) / (u_hi - u_lo)
    return _clenshaw(coef[lo], t)


@kernel(parallel=True)
def _evaluate(lam, unit_start, bounds, coef, direct, panel_bound, cert_start, cert_par, cert_coef, certify, first_unit,
              c, b, skip_below, skip_min_lam, out):
    for i in prange(lam.shape[0]):
        out[i] = _evaluate_one(lam[i], unit_start, bounds, coef, direct, panel_bound, cert_start, cert_par, cert_coef,
                               certify, first_unit, c, b, skip_below, skip_min_lam)


@kernel
def _evaluate_serial(lam, unit_start, bounds, coef, direct, panel_bound, cert_start, cert_par, cert_coef, certify,
                     first_unit, c, b, skip_below, skip_min_lam, out):
    """:func:`_evaluate` in one thread (same body, same bits): for few values, where waking threads costs more."""
    for i in range(lam.shape[0]):
        out[i] = _evaluate_one(lam[i], unit_start, bounds, coef, direct, panel_bound, cert_start, cert_par, cert_coef,
                               certify, first_unit, c, b, skip_below, skip_min_lam)
