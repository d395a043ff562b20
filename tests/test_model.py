"""Closed forms against independent computations (mpmath, a plain double sum) and properties."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import evnoise as ev
from evnoise.testing import double_sum_event_probability, reference_log_event_probability

# A grid over the hard cases: lam -> 0, the paper's operating range, large lam; tiny and large
# thresholds; no bias and a huge bias. (lam, eps, bias)
GRID = [
    (lam, eps, b)
    for lam in (1e-12, 1e-6, 0.01, 0.2, 1.0, 5.0, 18.0, 100.0)
    for eps in (1e-4, 0.1, 0.904, 2.0, 5.0)
    for b in (0.0, 0.37, 1.7, 1e3)
] + [
    (1e3, 0.1, 0.0),
    (1e3, 1e-4, 1.7),
    (1e3, 0.5, 30.0),
    (5e3, 0.904, 1.7),
    (1e4, 1e-4, 0.0),
    (1e4, 0.05, 0.0),
    (1e4, 5.0, 1e3),
]


@pytest.fixture(scope="module")
def reference():
    return {case: reference_log_event_probability(*case) for case in GRID}


def _tolerance(log_ref):
    # relative error of p below ~1e-11 where p > 1e-300; relative error of log p beyond
    return 1e-12 + 1e-14 * abs(log_ref)


def test_log_probability_matches_mpmath_direct(reference):
    """Element-wise (small arrays use the direct windowed sum)."""
    for (lam, eps, b), ref in reference.items():
        got = float(ev.log_event_probability(lam, eps, b))
        assert abs(got - ref) <= _tolerance(ref), (lam, eps, b, got, ref)


def test_probability_relative_error_below_1e10_where_representable(reference):
    for (lam, eps, b), ref in reference.items():
        got = float(ev.event_probability(lam, eps, b))
        if ref > math.log(1e-300):
            assert got == pytest.approx(math.exp(ref), rel=1e-10), (lam, eps, b)
        elif ref < -746:
            assert got == 0.0


def test_table_path_matches_mpmath_and_direct(reference):
    """Large arrays with one (eps, bias) go through the adaptive Chebyshev table."""
    rng = np.random.default_rng(7)
    for eps, b in [(0.904, 1.7), (1e-4, 0.0), (2.0, 1e3), (0.1, 0.37)]:
        cases = [(lam, ref) for (lam, e, bb), ref in reference.items() if e == eps and bb == b]
        lam_grid = np.array([c[0] for c in cases])
        lam_rand = np.exp(rng.uniform(math.log(1e-12), math.log(3e4), 6000))
        lam = np.concatenate([lam_grid, lam_rand])
        table = ev.log_event_probability(lam, eps, b)
        for (lam_i, ref), got in zip(cases, table[: len(cases)]):
            assert abs(got - ref) <= _tolerance(ref), (lam_i, eps, b)
        # against the direct sum (element by element through small arrays)
        direct = np.array([float(ev.log_event_probability(x, eps, b)) for x in lam_rand[:600]])
        err = np.abs(table[len(cases):len(cases) + 600] - direct)
        assert np.all(err <= 1e-12 + 1e-14 * np.abs(direct))


def test_matches_plain_double_sum():
    for lam, eps, b in [(0.3, 0.5, 0.0), (2.0, 0.904, 1.7), (7.5, 0.25, 3.3), (30.0, 1.3, 0.1), (12.0, 0.05, 0.0)]:
        got = float(ev.event_probability(lam, eps, b))
        assert got == pytest.approx(double_sum_event_probability(lam, eps, b), rel=1e-11)


@pytest.mark.slow
@pytest.mark.parametrize("lam, eps, b", [(1e5, 0.01, 1.0), (1e5, 1e-4, 0.0), (1e6, 1e-4, 0.0), (3e5, 0.3, 0.0)])
def test_large_lambda_matches_mpmath(lam, eps, b):
    ref = reference_log_event_probability(lam, eps, b)
    assert abs(float(ev.log_event_probability(lam, eps, b)) - ref) <= _tolerance(ref)


def test_exact_limits():
    assert ev.event_probability(0.0, 0.9, 1.7) == 0.0
    assert ev.event_probability(0.0, 0.9, 0.0) == 0.0  # no photons, no event (n = n0 = 0)
    assert ev.log_event_probability(0.0, 0.9, 0.0) == -np.inf
    assert ev.event_probability(np.inf, 0.9, 1.7) == 0.0
    # lam -> 0 with b = 0: the event needs n >= 1 and n0 = 0, so p ~ lam
    assert float(ev.event_probability(1e-12, 0.5, 0.0)) == pytest.approx(1e-12, rel=1e-11)


def test_log_probability_finite_far_below_double_range():
    lp = ev.log_event_probability([1e4, 1e6, 1e-12], [5.0, 5.0, 5.0], [1e3, 1e3, 1e3])
    assert np.all(np.isfinite(lp)) and np.all(lp < -1e5)
    assert np.all(ev.event_probability([1e4, 1e6], 5.0, 1e3) == 0.0)


def test_gaussian_form_is_the_papers_eq3():
    from scipy.special import erf

    lam, eps, b = 7.3, 0.6, 1.7
    z = (lam + b) * (math.exp(eps) - 1) / math.sqrt(2 * lam * (1 + math.exp(2 * eps)))
    assert float(ev.event_probability(lam, eps, b, method="gaussian")) == pytest.approx(0.5 - 0.5 * erf(z), rel=1e-13)


def test_gaussian_limits_and_tail():
    import mpmath as mp

    g = lambda *a: float(ev.event_probability(*a, method="gaussian"))  # noqa: E731
    assert g(0.0, 0.9, 1.7) == 0.0
    assert g(0.0, 0.9, 0.0) == 0.5  # the continuous limit at lam = 0, b = 0
    assert g(np.inf, 0.9, 0.0) == 0.0
    lp = float(ev.log_event_probability(1e6, 5.0, 1e3, method="gaussian"))
    eps = mp.mpf(5)
    z = (mp.mpf(1e6) + 1000) * (mp.e**eps - 1) / mp.sqrt(2 * mp.mpf(1e6) * (1 + mp.e ** (2 * eps)))
    assert lp == pytest.approx(float(mp.log(mp.erfc(z) / 2)), rel=1e-12)
    # eps large: no overflow
    assert math.isfinite(float(ev.log_event_probability(10.0, 400.0, 1.0, method="gaussian")))


def test_gaussian_error_at_the_papers_operating_point():
    """The finding users need: eq. 3 is far from the exact form for lam ~ 0.2 .. 20."""
    lam = np.geomspace(0.2, 20, 25)
    exact = ev.event_probability(lam, 0.904, 1.7)
    gauss = ev.event_probability(lam, 0.904, 1.7, method="gaussian")
    rel = gauss / exact - 1
    assert rel.min() > 0.1 and rel.max() > 5  # overestimates everywhere, by ~14 % to ~900 %


def test_broadcasting_and_dtype():
    out = ev.event_probability(np.ones((3, 1)), np.array([0.5, 1.0]), 1.7)
    assert out.shape == (3, 2) and out.dtype == np.float64
    assert np.all(out[:, 0] > out[:, 1])


@pytest.mark.parametrize(
    "kwargs",
    [dict(lam=-1.0, eps=0.9), dict(lam=np.nan, eps=0.9), dict(lam=1.0, eps=0.0), dict(lam=1.0, eps=-0.1),
     dict(lam=1.0, eps=np.inf), dict(lam=1.0, eps=0.9, bias=-1.0), dict(lam=1.0, eps=0.9, bias=np.nan),
     dict(lam=[1.0, 2.0], eps=[0.9, 0.8, 0.7])],
)
def test_invalid_inputs_raise(kwargs):
    with pytest.raises(ev.ParameterError):
        ev.event_probability(**kwargs)


def test_invalid_method():
    with pytest.raises(ev.ParameterError, match="method"):
        ev.event_probability(1.0, 0.9, method="normal")


lams = st.floats(min_value=1e-12, max_value=3e3, allow_nan=False)
epss = st.floats(min_value=1e-4, max_value=5.0)
biases = st.floats(min_value=0.0, max_value=1e3)


@settings(max_examples=150, deadline=None)
@given(lams, epss, epss, biases)
def test_monotone_in_threshold(lam, e1, e2, b):
    lo, hi = sorted((e1, e2))
    p_lo, p_hi = ev.event_probability(lam, [lo, hi], b)
    assert 0.0 <= p_hi <= p_lo <= 0.5


@settings(max_examples=150, deadline=None)
@given(lams, epss, biases, biases)
def test_monotone_in_bias(lam, eps, b1, b2):
    lo, hi = sorted((b1, b2))
    p_lo, p_hi = ev.event_probability(lam, eps, [lo, hi])
    assert p_hi <= p_lo


@settings(max_examples=150, deadline=None)
@given(lams, epss, biases)
def test_log_and_linear_agree(lam, eps, b):
    lp = float(ev.log_event_probability(lam, eps, b))
    p = float(ev.event_probability(lam, eps, b))
    assert math.isfinite(lp)
    if lp > -700:
        assert p == pytest.approx(math.exp(lp), rel=1e-13)


@settings(max_examples=100, deadline=None)
@given(st.floats(min_value=0.0, max_value=1e6), epss, biases)
def test_gaussian_bounded(lam, eps, b):
    p = float(ev.event_probability(lam, eps, b, method="gaussian"))
    assert 0.0 <= p <= 0.5


def test_per_pixel_thresholds_on_shared_levels_match_the_windowed_sum():
    """Threshold-mismatch maps on a few lam levels use per-level tables; same values as element-wise."""
    from evnoise._kernels.poisson import log_event_probability_exact_array

    rng = np.random.default_rng(5)
    n = 20000
    lam = rng.choice(np.concatenate([np.geomspace(1e-6, 150, 40), [0.0, 500.0]]), n)
    eps = rng.normal(0.9, 0.2, n).clip(1e-3)
    for b in (0.0, 1.7, 300.0):
        got = ev.log_event_probability(lam, eps, b)
        ref = np.empty(n)
        log_event_probability_exact_array(lam, np.expm1(eps), np.full(n, b), ref)
        finite = np.isfinite(ref)
        assert np.array_equal(finite, np.isfinite(got))
        assert np.all(np.abs(got[finite] - ref[finite]) <= 1e-12 + 1e-14 * np.abs(ref[finite]))


@pytest.mark.long
def test_probability_alone_is_the_same_bits_in_any_batch_and_matches_the_windowed_sum():
    """``log_event_probability_alone`` (the trial tier's runs in a video): each value's bits do not depend on what
    else the call holds (uniform, narrowly and widely spread thresholds, 1 to 20,000 values, other values at the same
    lam), and equal the independent windowed sum to 1e-12."""
    from evnoise._kernels.poisson import log_event_probability_exact_array
    from evnoise.model import log_event_probability_alone

    rng = np.random.default_rng(11)
    n = 20000
    lam = rng.choice(np.concatenate([np.geomspace(1e-6, 3e4, 40), [0.0, 2e6]]), n)
    for eps in (0.2, np.full(n, 0.2), rng.normal(0.3, 0.05, n).clip(0.05), rng.uniform(0.01, 3.0, n)):
        tol = 2e-10 if np.ndim(eps) == 0 else 1e-12  # the table (scalar eps), ~1e-11 of p; else the exact sums
        for b in (0.0, 1.7):
            whole = log_event_probability_alone(lam, eps, b)
            ref = np.empty(n)
            log_event_probability_exact_array(lam, np.expm1(np.broadcast_to(eps, (n,))), np.full(n, b), ref)
            finite = np.isfinite(ref)
            assert np.array_equal(finite, np.isfinite(whole))
            assert np.all(np.abs(whole[finite] - ref[finite]) <= tol + tol * np.abs(ref[finite]))
            for size in (1, 7, 4096, 5000, 20000):
                pick = rng.choice(n, size, replace=False)
                part = eps if np.ndim(eps) == 0 else eps[pick]
                np.testing.assert_array_equal(log_event_probability_alone(lam[pick], part, b), whole[pick])


def test_underflowing_panels_skip_exactly_what_underflows():
    """Panels too rippled to tabulate skip, with one bound per panel, only values whose p is 0 in double."""
    from evnoise._kernels.poisson import log_event_probability_exact

    for eps, b in ((0.904, 1.7), (0.3, 0.0), (0.05, 20.0)):
        lam = np.geomspace(2e3, 1e6, 1500)
        p = ev.event_probability(lam, eps, b)
        ref = np.exp([log_event_probability_exact(x, math.expm1(eps), b) for x in lam])
        assert np.array_equal(p == 0, ref == 0), eps
        np.testing.assert_allclose(p, ref, rtol=1e-10, atol=0)


def test_panel_bound_bounds_log_p_over_the_panel():
    from evnoise._kernels.chebyshev import panel_log_bound
    from evnoise._kernels.poisson import log_event_probability_exact

    for c in (0.05, 0.5, 1.47, 4.0):
        for b in (0.0, 1.7, 50.0):
            for lo in (5.0, 300.0, 2e4):
                hi = lo * math.e
                bound = panel_log_bound(lo, hi, c, b)
                exact = max(log_event_probability_exact(x, c, b) for x in np.geomspace(lo, hi, 60))
                assert bound >= exact, (c, b, lo, bound, exact)


@pytest.mark.parametrize("lam, eps", [(1e12, 20.0), (3.6e299, 20.0), (1.1e306, 5.0), (5e307, 0.5)])
def test_log_p_is_finite_and_above_the_no_photon_term_as_documented(lam, eps):
    """With b = 0 the trial with no reference photon alone gives p >= exp(-lam) (1 - exp(-lam)): log p >= -lam, finite
    up to the documented lam (the docstring said "every 0 < lam < inf"; -inf comes beyond ~1e299 at eps = 20)."""
    value = ev.log_event_probability(lam, eps, 0.0)
    assert np.isfinite(value) and -lam * (1 + 1e-12) <= value < 0.0
