"""Per-pixel random streams for the Numba kernels (xoshiro256++ seeded by SplitMix64).

Every pixel owns a 4-word xoshiro256++ state derived from a 4-word key (drawn once from the
user's ``numpy.random.Generator``) and the pixel's flat index, so a pixel's stream does not
depend on how pixels are grouped into chunks, on the number of threads, or on how time is
cut into windows. The samplers below (uniform, geometric, Poisson) are tested against
SciPy's distributions in ``tests/test_rng.py``.
"""

from __future__ import annotations

import math

import numpy as np

from ._jit import kernel

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_U30 = np.uint64(30)
_U27 = np.uint64(27)
_U31 = np.uint64(31)
_U11 = np.uint64(11)
_U17 = np.uint64(17)
_U45 = np.uint64(45)
_U23 = np.uint64(23)
_U64 = np.uint64(64)
_TWO_M53 = 1.0 / 9007199254740992.0


@kernel
def _mix64(z):
    z = (z ^ (z >> _U30)) * _M1
    z = (z ^ (z >> _U27)) * _M2
    return z ^ (z >> _U31)


@kernel
def _rotl(x, k):
    return (x << k) | (x >> (_U64 - k))


@kernel
def seed_state(key, index, state):
    """Fill ``state[0:4]`` for stream ``index`` (uint64) from the 4-word ``key``."""
    z = key[0] ^ _mix64(key[1] + np.uint64(index) * _GOLDEN)
    z = z ^ _mix64(key[2] ^ _mix64(key[3] + np.uint64(index)))
    for i in range(4):
        z += _GOLDEN
        state[i] = _mix64(z)
    if state[0] == 0 and state[1] == 0 and state[2] == 0 and state[3] == 0:
        state[0] = _GOLDEN  # the all-zero state is the one forbidden state


@kernel(inline=True)
def xoshiro_step(s0, s1, s2, s3):
    """One xoshiro256++ step on a state held in four scalars: ``(output, s0, s1, s2, s3)``.

    A kernel that keeps its stream in scalars (registers) instead of a 4-word array draws several times faster:
    an array's words go through memory on every draw, since a store to any output array might alias them.
    """
    result = _rotl(s0 + s3, _U23) + s0
    t = s1 << _U17
    s2 ^= s0
    s3 ^= s1
    s1 ^= s2
    s0 ^= s3
    s2 ^= t
    s3 = _rotl(s3, _U45)
    return result, s0, s1, s2, s3


@kernel
def next_u64(s):
    result, s[0], s[1], s[2], s[3] = xoshiro_step(s[0], s[1], s[2], s[3])
    return result


@kernel(inline=True)
def unit(r):
    """The uniform double in [0, 1) of a 64-bit output ``r`` (its 53 high bits)."""
    return float(r >> _U11) * _TWO_M53


@kernel(inline=True)
def unit_pos(r):
    """The uniform double in (0, 1] of a 64-bit output ``r``."""
    return (float(r >> _U11) + 1.0) * _TWO_M53


@kernel
def uniform(s):
    """Uniform double in [0, 1) with 53 random bits."""
    return unit(next_u64(s))


@kernel
def uniform_pos(s):
    """Uniform double in (0, 1]."""
    return unit_pos(next_u64(s))


@kernel
def geometric(s, log1m_p):
    """Trials up to and including the first success, ``>= 1``; ``log1m_p = log1p(-p)``.

    Returns ``inf`` when ``p = 0`` (``log1m_p = 0``) and 1 when ``p = 1`` (``log1m_p = -inf``), without a draw.
    """
    g, s[0], s[1], s[2], s[3] = geometric_x(s[0], s[1], s[2], s[3], log1m_p)
    return g


@kernel(inline=True)
def geometric_x(s0, s1, s2, s3, log1m_p):
    """:func:`geometric` on a stream held in four scalars (:func:`xoshiro_step`): ``(g, s0, s1, s2, s3)``."""
    if log1m_p == 0.0:
        return math.inf, s0, s1, s2, s3
    if log1m_p == -math.inf:
        return 1.0, s0, s1, s2, s3
    r, s0, s1, s2, s3 = xoshiro_step(s0, s1, s2, s3)
    return geometric_of(r, log1m_p), s0, s1, s2, s3


@kernel(inline=True)
def geometric_of(r, log1m_p):
    """The geometric variate (trials up to and including the first success) of a 64-bit output ``r``, for
    ``-inf < log1m_p < 0``; no limits checked (:func:`geometric_x` checks them)."""
    return np.floor(math.log(unit_pos(r)) / log1m_p) + 1.0  # np.floor: a float, no int64 wrap


POISSON_NORMAL_LAM = 2.0**52  # from here on poisson draws the normal limit (see poisson_emlam)


@kernel
def poisson(s, lam):
    """Poisson variate (as a float): inversion below 10, Hormann's PTRS above."""
    return poisson_emlam(s, lam, math.exp(-lam) if lam < 10.0 else 0.0)


@kernel
def poisson_emlam(s, lam, emlam):
    """:func:`poisson` with ``emlam = exp(-lam)`` precomputed (used only when ``lam < 10``)."""
    if lam <= 0.0:
        return 0.0
    if lam >= POISSON_NORMAL_LAM:
        # beyond 2^52 a count no longer has unit resolution in a double and PTRS's acceptance test
        # cancels to noise (it could reject forever): the normal limit, exact to ~1/sqrt(lam)
        z = math.sqrt(-2.0 * math.log(uniform_pos(s))) * math.cos(2.0 * math.pi * uniform(s))
        return max(np.floor(lam + math.sqrt(lam) * z + 0.5), 0.0)
    if lam < 10.0:
        u = uniform(s)
        p = emlam
        cdf = p
        k = 0.0
        while u >= cdf:
            k += 1.0
            p *= lam / k
            cdf += p
            if p == 0.0 and cdf < u:  # rounding guard: u beyond the reachable cdf
                return k
        return k
    # PTRS: transformed rejection with squeeze (W. Hormann, 1993)
    slam = math.sqrt(lam)
    loglam = math.log(lam)
    b = 0.931 + 2.53 * slam
    a = -0.059 + 0.02483 * b
    inv_alpha = 1.1239 + 1.1328 / (b - 3.4)
    v_r = 0.9277 - 3.6224 / (b - 2.0)
    while True:
        u = uniform(s) - 0.5
        v = uniform(s)
        us = 0.5 - abs(u)
        k = np.floor((2.0 * a / us + b) * u + lam + 0.43)  # a float: math.floor's int64 wraps for lam > 2^63
        if us >= 0.07 and v <= v_r:
            return k
        if k < 0.0 or (us < 0.013 and v > us):
            continue
        if math.log(v) + math.log(inv_alpha) - math.log(a / (us * us) + b) <= (
            -lam + k * loglam - math.lgamma(k + 1.0)
        ):
            return k
