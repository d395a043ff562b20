"""Issue 33, item 3: certified Chebyshev panels of p for lam > 1e4 (evnoise._kernels.certified).

The reference is an independent mpmath sum (30 digits): ``sum_m pmf(m) P(N > k(m))`` over a window of
``m`` around the exponentially tilted peak, with the pmf by its ratio recurrence and the tails as cumulative
sums started from one regularised incomplete gamma function; the window's edge terms are checked to be
below 1e-40 of the sum. It shares nothing with the library but the definition of the thresholds
``k(m) = m + floor(c (m + b))`` (with the library's double ``c = expm1(eps)``).
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

mp = pytest.importorskip("mpmath")

import evnoise as ev  # noqa: E402
from evnoise import model  # noqa: E402
from evnoise._kernels import certified, chebyshev  # noqa: E402
from evnoise._kernels.poisson import log_event_probability_exact  # noqa: E402

U = 2.0**-53
EPS = (0.05, 0.1, 0.2, 0.5, 1.0, 2.0)
BIAS = (0.0, 1.7, 100.0, 1000.0)


def ref_log_p(lam: float, c: float, b: float, dps: int = 30) -> float:
    """log p in mpmath (see the module text)."""
    with mp.workdps(dps):
        L, cm, bm = mp.mpf(lam), mp.mpf(c), mp.mpf(b)
        a = 1.0 + c
        lo, hi = 0.0, 1.0  # tilt theta: lam (e^theta - a e^{-a theta}) = c b, only to place the window
        while lam * (math.exp(hi) - a * math.exp(-a * hi)) < c * b:
            hi *= 2.0
        for _ in range(100):
            mid = 0.5 * (lo + hi)
            if lam * (math.exp(mid) - a * math.exp(-a * mid)) < c * b:
                lo = mid
            else:
                hi = mid
        m0 = lam * math.exp(-a * lo)
        w = 25.0 * math.sqrt(m0) + 100.0
        m_lo, m_hi = max(0, int(m0 - w)), int(m0 + w)
        k = [m + int(mp.floor(cm * (m + bm))) for m in range(m_lo, m_hi + 1)]
        n_lo, top = min(m_lo, k[0] + 1), max(m_hi, k[-1] + 1)
        log_scale = n_lo * mp.log(L) - L - mp.loggamma(n_lo + 1)
        pm = [mp.mpf(1)]
        for n in range(n_lo + 1, top + 1):
            pm.append(pm[-1] * L / n)
        sf = [mp.mpf(0)] * (top - n_lo + 1)
        acc = mp.gammainc(top + 1, 0, L, regularized=True) / mp.exp(log_scale)  # P(N > top), scaled
        for n in range(top, n_lo - 1, -1):
            sf[n - n_lo] = acc
            acc += pm[n - n_lo]
        terms = [pm[m - n_lo] * sf[k[i] - n_lo] for i, m in enumerate(range(m_lo, m_hi + 1))]
        total = mp.fsum(terms)
        edge = max(terms[0] if m_lo > 0 else mp.mpf(0), terms[-1])
        assert edge < mp.mpf(10) ** -40 * total, "reference window too narrow"
        return float(mp.log(total) + 2 * log_scale)


def _ref_cache():
    store = {}

    def get(lam, eps, b):
        key = (lam, eps, b)
        if key not in store:
            store[key] = ref_log_p(lam, math.expm1(eps), b)
        return store[key]

    return get


REF = _ref_cache()
# lam points: below 1e4 (the log-spaced table), in each certified decade, and near the top of 1e6
LAM_FAST = (2.3e4 + 0.37, 1.37e5 + 0.11)
LAM_SLOW = (1.3e3 + 0.5, 8.1e3 + 0.21, 1.2e4 + 0.7, 4.4e5 + 0.3, 9.7e5 + 0.9)


def _exact_ok(got, want):
    """The exact sum's assumed error (certified.NODE_REL_ERR + NODE_ULPS u |log p|)."""
    return abs(got - want) <= certified.NODE_REL_ERR + certified.NODE_ULPS * U * abs(want)


def _panel_around(lam, c, b, s=certified.HALF_START):
    """A panel as the build lays them out (half-width s sqrt(lam)), with lam off its centre."""
    half = s * math.sqrt(lam)
    lo = lam - 0.7 * half
    return certified.certify_panel(lo, lo + 2.0 * half, c, b, certified.DEGREE)


def _check_point(lam, eps, b):
    c = math.expm1(eps)
    want = REF(lam, eps, b)
    exact = log_event_probability_exact(lam, c, b)
    assert _exact_ok(exact, want), (exact, want)
    if lam < certified.LAM_MIN:
        return want
    coef, par = _panel_around(lam, c, b)
    assert par[6] <= certified.CERT_TOL  # the proven part of the bound
    got = certified.evaluate_one(lam, 0, 1, par[None, :], coef[None, :])
    err = abs(got - want)
    assert err <= par[6] + par[7], (err, par[6], par[7])
    # where |log p| is moderate the whole certified bound is below 1e-10
    if abs(want) < 1000.0:
        assert par[6] + par[7] <= 1e-10 and err <= 1e-10
    return want


@pytest.mark.parametrize("eps", EPS)
@pytest.mark.parametrize("b", BIAS)
@pytest.mark.long
def test_certified_panels_against_mpmath(eps, b):
    """A panel around each lam: proven bound <= 1e-10, and the value within the bound of mpmath's."""
    logs = [_check_point(lam, eps, b) for lam in LAM_FAST]
    assert all(np.isfinite(logs))


@pytest.mark.slow
@pytest.mark.parametrize("eps", EPS)
@pytest.mark.parametrize("b", BIAS)
def test_certified_panels_against_mpmath_full_range(eps, b):
    """As above from lam = 1.3e3 to 9.7e5 (about 2-20 s per threshold and bias: the mpmath sums)."""
    for lam in LAM_SLOW:
        _check_point(lam, eps, b)


@pytest.mark.long
def test_grid_reaches_far_below_1e_minus_300():
    """The fast grid has points with log p < -690 (p < 1e-300), where only log space works."""
    logs = [REF(lam, eps, b) for eps in (0.5, 1.0, 2.0) for b in (0.0, 1000.0) for lam in LAM_FAST]
    assert sum(v < -690.0 for v in logs) >= 6 and min(logs) < -20000.0


def _table(eps, b):
    return chebyshev.LogPTable(math.expm1(eps), b, *model._TABLE_UNITS)


@pytest.fixture(autouse=True)
def certify_any_count(monkeypatch):
    """The tests below ask for few values; the table certifies a unit only for a call with
    ``CERT_MIN_VALUES`` values in it (test_small_calls_sum_exactly checks that rule itself)."""
    monkeypatch.setattr(chebyshev, "CERT_MIN_VALUES", 1)


@pytest.fixture
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("EVNOISE_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("EVNOISE_TABLE_CACHE", raising=False)
    return tmp_path / "cache" / "tables"


@pytest.mark.parametrize("eps, b", [(0.1, 1.7), (1.0, 100.0)])
def test_public_api_uses_certified_panels_and_matches_mpmath(eps, b, private_cache):
    """``log_event_probability`` on a table-sized array: values in certified panels, within their bound."""
    points = np.array([3.1e4 + 0.3, 3.9e4 + 0.6, 5.5e4 + 0.2])
    lam = np.concatenate([points, np.geomspace(2.3e4, 5.9e4, model.TABLE_MIN_SIZE)])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = ev.log_event_probability(lam, eps, b)
        p = ev.event_probability(lam, eps, b)
    table = model._table_for(float(np.expm1(eps)), b)
    panels = table.certified_panels()
    assert 10 in panels and all(coef is not None for coef, _ in panels[10])
    for x, g in zip(points, got[:3]):
        par = next(par for _, par in panels[10] if par[0] <= x <= par[1])
        assert abs(g - REF(float(x), eps, b)) <= par[6] + par[7]
    with np.errstate(under="ignore"):
        np.testing.assert_array_equal(p, np.exp(got))  # event_probability: the same path, exp of it


def test_every_built_panel_is_certified_and_measured_below_its_bound(private_cache):
    """A whole unit: contiguous panels, each with a proven bound <= 1e-10; the exact sum between the nodes
    agrees within bound + the exact sum's own error."""
    eps, b = 0.2, 1.7
    c = math.expm1(eps)
    panels = certified.build_unit(10, c, b)
    assert panels[0][1][0] <= math.exp(10) and panels[-1][1][1] >= math.exp(11)
    for (_, p0), (_, p1) in zip(panels, panels[1:]):
        assert p0[1] == p1[0]
    g = np.random.default_rng(4)
    for coef, par in panels:
        assert coef is not None and par[6] <= certified.CERT_TOL
        for x in g.uniform(par[0], par[1], 3):
            got = certified.evaluate_one(x, 0, 1, par[None, :], coef[None, :])
            exact = log_event_probability_exact(x, c, b)
            slack = certified.NODE_REL_ERR + certified.NODE_ULPS * U * abs(exact)
            assert abs(got - exact) <= par[6] + par[7] + slack


def _max_error(coef, par, c, b):
    xs = np.linspace(par[0], par[1], 201)
    return max(abs(certified.evaluate_one(x, 0, 1, par[None, :], coef[None, :]) - log_event_probability_exact(x, c, b))
               for x in xs)


@pytest.mark.parametrize("eps, b, lam", [(0.2, 1.7, 1e5), (0.05, 1000.0, 2e5), (2.0, 0.0, 3e4)])
def test_bound_holds_where_the_truncation_error_is_visible(eps, b, lam):
    """Panels too wide for 1e-10 (half-width 3.6 and 4.5 sqrt(lam)): the bound is not met, and the measured
    error is below it; where |log p| is small (so the exact sum is good to ~1e-14) the truncation error is
    visible at 4.5, over three times the error of a certified panel. (The bound is conservative: at 4.5 it is
    about 1e-5 against a measured ~1e-12.)"""
    c = math.expm1(eps)
    errors = {}
    for s in (certified.HALF_START, 3.6, 4.5):
        coef, par = _panel_around(lam, c, b, s)
        errors[s] = _max_error(coef, par, c, b)
        if s == certified.HALF_START:
            assert par[6] <= certified.CERT_TOL
        else:
            assert certified.CERT_TOL < par[6] < 1e-3
        assert errors[s] <= par[6] + par[7] + certified.NODE_REL_ERR + certified.NODE_ULPS * U * 2e4
    if eps < 1.0:
        assert errors[4.5] > 3.0 * errors[certified.HALF_START]
    _, par = _panel_around(lam, c, b, 12.0)
    assert not par[6] <= certified.CERT_TOL  # far too wide: refused


def test_unchanged_below_1e4_and_certified_from_1e4(private_cache, monkeypatch):
    """Below 1e4 the values are bit for bit those of the table without certification; from 1e4 on every value,
    in the units the log-spaced panels tabulate (1e4 .. e^10, and e^10 .. e^11 at eps = 2) as in those left to the
    exact sum, comes from a certified panel and is within its bound of the exact sum."""
    eps, b = 2.0, 1.7
    lam = np.concatenate([np.geomspace(30.0, 9999.0, 3000), np.geomspace(1e4, 2.2e5, 3000)])
    new = _table(eps, b)
    got = new.evaluate(lam)
    units = np.floor(np.log(lam)).astype(int)
    tabulated = np.array([not new._is_direct(int(u)) for u in units])
    monkeypatch.setattr(chebyshev, "CERT_LAST_UNIT", 0)
    monkeypatch.setenv("EVNOISE_TABLE_CACHE", "0")
    old = _table(eps, b).evaluate(lam)
    below = lam < 1e4
    assert np.array_equal(got[below].view(np.uint64), old[below].view(np.uint64))
    assert (tabulated & ~below).sum() > 500 and (~tabulated & ~below).sum() > 1000  # both kinds above 1e4
    assert not np.array_equal(got[tabulated & ~below], old[tabulated & ~below])  # the certified panels answer
    panels = new.certified_panels()
    c = math.expm1(eps)
    for x, g_ in zip(lam[~below][::37], got[~below][::37]):
        par = next(par for _, par in panels[int(math.floor(math.log(x)))] if par[0] <= x <= par[1])
        exact = log_event_probability_exact(x, c, b)
        assert abs(g_ - exact) <= par[6] + par[7] + certified.NODE_REL_ERR + certified.NODE_ULPS * U * abs(exact)


@pytest.mark.parametrize("eps, b", [(0.05, 0.0), (0.2, 1000.0), (1.0, 1.7)])
def test_tabulated_band_from_1e4_is_certified_against_mpmath(eps, b, private_cache):
    """From 1e4 to e^10 (= 2.2e4) the log-spaced panels tabulate log p for eps <= 1: a call with many values there
    gets certified panels; each point's value is within its panel's proven bound of mpmath's."""
    points = np.array([1.0e4 + 0.3, 1.47e4 + 0.71, 2.2e4 - 0.4])
    table = _table(eps, b)
    got = table.evaluate(np.concatenate([points, np.geomspace(1e4, 2.2e4, 500)]))
    assert not table._is_direct(9)
    panels = table.certified_panels()[9]
    assert all(coef is not None and par[6] <= certified.CERT_TOL for coef, par in panels)
    assert panels[0][1][0] <= 1e4 and panels[-1][1][1] >= math.exp(10)
    for x, g_ in zip(points, got[:3]):
        par = next(par for _, par in panels if par[0] <= x <= par[1])
        assert abs(g_ - REF(float(x), eps, b)) <= par[6] + par[7]


def test_fallback_panels_use_the_exact_sum(private_cache):
    """A panel left to the exact sum (no certificate) returns the exact sum's value, bit for bit."""
    eps, b = 0.1, 1.7
    table = _table(eps, b)
    lam = np.geomspace(2.3e4, 5.9e4, 400)
    table.evaluate(lam)
    table._certified[10] = [(None, par) for _, par in table._certified[10]]
    table._arrays = table._pack()
    got = table.evaluate(lam)
    c = math.expm1(eps)
    want = np.array([log_event_probability_exact(x, c, b) for x in lam])
    assert np.array_equal(got.view(np.uint64), want.view(np.uint64))


def test_certified_panels_are_cached_on_disk(private_cache, monkeypatch):
    """Built once, read back bit for bit by a new table; a tampered file (a bound above CERT_TOL) is refused."""
    eps, b = 0.5, 100.0
    lam = np.geomspace(2.3e4, 5.9e4, 500)
    built = _table(eps, b)
    first = built.evaluate(lam)

    def fail(*args, **kwargs):
        raise AssertionError("certified panels rebuilt although the cache holds them")

    with monkeypatch.context() as m:
        m.setattr(certified, "build_unit", fail)
        again = _table(eps, b).evaluate(lam)
    assert np.array_equal(first.view(np.uint64), again.view(np.uint64))
    arrays = certified.units_to_arrays(built.certified_panels())
    assert certified.arrays_to_units(arrays, -40, chebyshev.CERT_LAST_UNIT) is not None
    arrays["par"][0, 6] = 1.0
    assert certified.arrays_to_units(arrays, -40, chebyshev.CERT_LAST_UNIT) is None


def test_speed_path_evaluates_without_the_exact_sum(private_cache, monkeypatch):
    """Once built, a certified unit's values do not call the exact sum: the panels answer (checked by
    giving the table no fallback: every certified value is finite and equals the panel formula)."""
    eps, b = 0.3, 0.0
    table = _table(eps, b)
    lam = np.geomspace(2.3e4, 5.9e4, 5000)
    got = table.evaluate(lam)
    panels = table.certified_panels()[10]
    par = np.array([p for _, p in panels])
    coef = np.array([cf for cf, _ in panels])
    want = np.array([certified.evaluate_one(x, 0, len(panels), par, coef) for x in lam])
    assert np.isfinite(want).all()
    assert np.array_equal(got.view(np.uint64), want.view(np.uint64))


def test_small_calls_sum_exactly_and_large_ones_use_the_panels(private_cache, monkeypatch):
    """Certified panels cost seconds to build: a call with fewer than ``CERT_MIN_VALUES`` values in a direct
    unit gets the exact sum (bit for bit, nothing built), one with more gets the panels; the rule looks at the
    call only, so the same values give the same bits whatever the cache holds."""
    monkeypatch.setattr(chebyshev, "CERT_MIN_VALUES", 300)
    eps, b = 0.1, 1.7
    c = math.expm1(eps)
    few = np.geomspace(2.3e4, 5.9e4, 299)
    table = _table(eps, b)
    got = table.evaluate(few)
    assert table.certified_panels() == {}
    want = np.array([log_event_probability_exact(x, c, b) for x in few])
    assert np.array_equal(got.view(np.uint64), want.view(np.uint64))
    many = np.geomspace(2.3e4, 5.9e4, 300)
    got_many = table.evaluate(many)
    assert 10 in table.certified_panels()
    exact = np.array([log_event_probability_exact(x, c, b) for x in many])
    assert not np.array_equal(got_many.view(np.uint64), exact.view(np.uint64))  # the panels answered
    assert np.all(np.abs(got_many - exact) <= 2e-10 * np.maximum(1.0, np.abs(exact)))
    again = table.evaluate(few)  # the unit is built now: a small call still sums exactly
    assert np.array_equal(again.view(np.uint64), want.view(np.uint64))


def test_tabulated_unit_counts_distinct_values(private_cache, monkeypatch):
    """In a unit the log-spaced panels tabulate, a call is certified only with ``CERT_MIN_VALUES`` distinct values:
    a flat field evaluated pixel by pixel keeps the log-spaced values it gets once per distinct value (the scene
    path, test_scene_cost), bit for bit; distinct values get the certified panels."""
    monkeypatch.setattr(chebyshev, "CERT_MIN_VALUES", 300)
    eps, b = 0.1, 1.7
    repeated = np.repeat(np.geomspace(1.1e4, 2.1e4, 10), 100)
    distinct = np.geomspace(1.1e4, 2.1e4, 300)
    table = _table(eps, b)
    got_repeated = table.evaluate(repeated)
    assert table.certified_panels() == {}
    got_distinct = table.evaluate(distinct)
    assert 9 in table.certified_panels()
    with monkeypatch.context() as m:
        m.setattr(chebyshev, "CERT_LAST_UNIT", 0)
        m.setenv("EVNOISE_TABLE_CACHE", "0")
        plain = _table(eps, b)
        assert np.array_equal(got_repeated.view(np.uint64), plain.evaluate(repeated).view(np.uint64))
        tabulated = plain.evaluate(distinct)
    assert not np.array_equal(got_distinct, tabulated)
    assert np.array_equal(table.evaluate(repeated).view(np.uint64), got_repeated.view(np.uint64))  # built: same rule
    assert np.all(np.abs(got_distinct - tabulated) <= 1e-10 * np.abs(tabulated))


def test_values_below_1e4_certify_nothing(private_cache, monkeypatch):
    """Unit 9 straddles 1e4; a call whose values in it all lie below 1e4 (which no certified panel serves) builds
    no certified panels, however many it has."""
    monkeypatch.setattr(chebyshev, "CERT_MIN_VALUES", 300)
    table = _table(0.1, 1.7)
    table.evaluate(np.geomspace(8200.0, 9990.0, 400))
    assert table.certified_panels() == {}
