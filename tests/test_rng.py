"""The kernels' random streams and samplers against independent implementations and SciPy."""

import math

import numpy as np
import pytest
from numba import njit
from scipy import stats

from evnoise._kernels import rng as R
from evnoise._run import stream_key

MASK = (1 << 64) - 1


def _rotl(x, k):
    return ((x << k) | (x >> (64 - k))) & MASK


def xoshiro256pp_reference(state, n):
    """Plain-Python xoshiro256++ (Blackman & Vigna), the obvious transcription of the algorithm."""
    s = list(state)
    out = []
    for _ in range(n):
        out.append((_rotl((s[0] + s[3]) & MASK, 23) + s[0]) & MASK)
        t = (s[1] << 17) & MASK
        s[2] ^= s[0]
        s[3] ^= s[1]
        s[1] ^= s[2]
        s[0] ^= s[3]
        s[2] ^= t
        s[3] = _rotl(s[3], 45)
    return out


@njit
def _draw_u64(state, n):
    out = np.empty(n, np.uint64)
    for i in range(n):
        out[i] = R.next_u64(state)
    return out


@njit
def _draw(key, index, kind, param, n):
    s = np.empty(4, np.uint64)
    R.seed_state(key, index, s)
    out = np.empty(n)
    for i in range(n):
        if kind == 0:
            out[i] = R.uniform(s)
        elif kind == 1:
            out[i] = R.poisson(s, param)
        else:
            out[i] = R.geometric(s, math.log1p(-param))
    return out


KEY = stream_key(np.random.default_rng(2024))


def test_xoshiro_matches_reference_transcription():
    state = np.array([1, 2, 3, 4], dtype=np.uint64)
    got = [int(v) for v in _draw_u64(state.copy(), 50)]
    assert got[0] == 41943041  # (rotl(1 + 4, 23) + 1)
    assert got == xoshiro256pp_reference([1, 2, 3, 4], 50)
    big = np.array([0xDEADBEEF12345678, 0x0123456789ABCDEF, 0xFFFFFFFFFFFFFFFF, 7], dtype=np.uint64)
    assert [int(v) for v in _draw_u64(big.copy(), 20)] == xoshiro256pp_reference([int(v) for v in big], 20)


def test_streams_differ_per_pixel_and_are_reproducible():
    a = _draw(KEY, 0, 0, 0.0, 1000)
    b = _draw(KEY, 1, 0, 0.0, 1000)
    assert not np.array_equal(a, b)
    assert np.array_equal(a, _draw(KEY, 0, 0, 0.0, 1000))
    assert abs(np.corrcoef(a, b)[0, 1]) < 5 / math.sqrt(1000)


def test_uniform_distribution():
    u = _draw(KEY, 3, 0, 0.0, 200_000)
    assert u.min() >= 0.0 and u.max() < 1.0
    assert stats.kstest(u, "uniform").pvalue > 1e-3


def _chi2_pvalue(samples, pmf_fn, support):
    observed = np.array([(samples == k).sum() for k in support], dtype=float)
    expected = pmf_fn(support) * samples.size
    rest_obs = samples.size - observed.sum()
    rest_exp = samples.size - expected.sum()
    keep = expected >= 5
    obs = np.append(observed[keep], rest_obs + observed[~keep].sum())
    exp = np.append(expected[keep], rest_exp + expected[~keep].sum())
    if exp[-1] < 5:  # fold a small remainder into the last bin
        obs[-2] += obs[-1]
        exp[-2] += exp[-1]
        obs, exp = obs[:-1], exp[:-1]
    return stats.chisquare(obs, exp * obs.sum() / exp.sum()).pvalue


@pytest.mark.parametrize("lam", [1e-3, 0.3, 4.0, 9.99, 10.0, 37.5, 2500.0])
def test_poisson_sampler_chi_square(lam):
    x = _draw(KEY, 11, 1, lam, 200_000)
    lo, hi = stats.poisson.ppf([1e-9, 1 - 1e-9], lam)
    support = np.arange(int(lo), int(hi) + 1)
    assert _chi2_pvalue(x, lambda k: stats.poisson.pmf(k, lam), support) > 1e-4


@pytest.mark.parametrize("p", [1e-4, 0.03, 0.5, 0.97])
def test_geometric_sampler_chi_square(p):
    x = _draw(KEY, 5, 2, p, 200_000)
    assert x.min() >= 1
    hi = stats.geom.ppf(1 - 1e-9, p)
    support = np.arange(1, int(hi) + 1)
    if support.size > 2000:  # bin a long support in quantile bins instead
        edges = np.unique(stats.geom.ppf(np.linspace(0, 1, 41)[1:-1], p))
        obs = np.bincount(np.searchsorted(edges, x, side="left"), minlength=edges.size + 1)
        cdf = np.concatenate([[0.0], stats.geom.cdf(edges, p), [1.0]])
        exp = np.diff(cdf) * x.size
        assert stats.chisquare(obs, exp).pvalue > 1e-4
    else:
        assert _chi2_pvalue(x, lambda k: stats.geom.pmf(k, p), support) > 1e-4


def test_geometric_edge_cases():
    s = np.empty(4, np.uint64)
    R.seed_state(KEY, 0, s)
    assert R.geometric(s, 0.0) == math.inf  # p = 0: never
    assert R.geometric(s, -math.inf) == 1.0  # p = 1: at once
