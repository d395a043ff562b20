"""The renewal kernel (:func:`evnoise._kernels.simulate.renewal_window`) against a plain-Python transcription of its
rules, draw for draw: the gap to a pixel's next event is geometric in trials (``floor(log u / log1p(-p)) + 1``,
none when ``p = 0``, one trial when ``p = 1``), no trial before ``j_min``; its time is ``(trial + u) dt``; an event
inside the window draws its polarity; the first event beyond the window stays pending (dropped from
``discard_from_trial`` on). The kernel has a loop without the limits' branches for the common case (no timer, no
refractory period, ``-inf < log1p(-p) < -PLAIN_LOG1M_P``) beside its general one: the pixels below straddle that
boundary, so both loops and the hand-over between them are held to the same draws."""

import math

import numpy as np
import pytest

from evnoise._kernels import simulate as K
from test_rng import xoshiro256pp_reference

DT_US = 1e6 / 42.5
WIDTH = 5
#: log1p(-p) per pixel: ordinary, tiny and huge p, both sides of PLAIN_LOG1M_P, a subnormal (gaps that overflow to
#: inf), p = 0 and p = 1
LOG1M_P = np.array([math.log1p(-0.03), math.log1p(-0.5), math.log1p(-1e-6), -1.0001e-300, -0.9999e-300, -1e-310,
                    0.0, -math.inf, math.log1p(-0.9), math.log1p(-0.2)])
Q_ON = np.array([0.5, 0.3, 0.9, 0.5, 0.5, 0.5, 0.5, 0.7, 0.1, 0.5])


def _unit(r):
    return (r >> 11) * 2.0**-53


def _unit_pos(r):
    return ((r >> 11) + 1.0) * 2.0**-53


def reference_window(draws, l1p, q_on, lt, lta, jp, tau, j_min, w_end, discard_from, t0_us):
    """One pixel's events ``[(t_us, on)]`` and new state ``(lt, lta, jp, tau)``, drawing from the iterator
    ``draws`` of its stream's 64-bit outputs."""
    events = []
    while True:
        if math.isnan(tau):
            j_e = max(lt + 1.0, j_min)
            if l1p == 0.0:
                g = math.inf
            elif l1p == -math.inf:
                g = 1.0
            else:
                with np.errstate(over="ignore"):  # a subnormal p: the gap overflows to inf (no event ever)
                    g = float(np.floor(np.float64(math.log(_unit_pos(next(draws)))) / l1p) + 1.0)
            if g == math.inf:
                jp = tau = math.inf
                break
            jp = j_e + g - 1.0
            tau = (jp + _unit(next(draws))) * DT_US
        if tau >= w_end:
            break
        events.append((t0_us + math.floor(tau), _unit(next(draws)) < q_on))
        lta, lt, tau = tau, jp, math.nan
    if jp >= discard_from:
        tau = math.nan
    return events, (lt, lta, jp, tau)


def _kernel_window(states, fstate, j_min, w_end, discard_from, t0_us, start_cap):
    """The kernel over every pixel, its buffers starting at ``start_cap`` slots and growing by one slot each time
    it stops full (a stop at nearly every event when ``start_cap`` is 1)."""
    n_pix = LOG1M_P.size
    pix = np.arange(n_pix, dtype=np.int64)
    on = np.zeros(n_pix, np.int64)
    off = np.zeros(n_pix, np.int64)
    out = (np.empty(start_cap, np.int64), np.empty(start_cap, np.uint16), np.empty(start_cap, np.uint16),
           np.empty(start_cap, np.uint8))
    n = k = 0
    while True:
        n, k = K.renewal_window(WIDTH, pix, LOG1M_P, Q_ON, np.zeros((3, 0)), states, fstate, DT_US, 0.0, j_min,
                                w_end, discard_from, np.int64(t0_us), out, n, k, on, off, True)
        if k == n_pix:
            return tuple(a[:n] for a in out), on, off
        bigger = tuple(np.empty(a.size + 1, a.dtype) for a in out)
        for new, old in zip(bigger, out):
            new[:n] = old[:n]
        out = bigger


@pytest.mark.parametrize("start_cap", [1, 100_000])
def test_the_renewal_kernel_makes_the_draws_of_its_rules(start_cap):
    n_pix = LOG1M_P.size
    states = np.empty((n_pix, 4), np.uint64)
    K.seed_streams(np.array([11, 22, 33, 44], np.uint64), np.arange(n_pix, dtype=np.int64), states)
    draws = [iter(xoshiro256pp_reference([int(w) for w in states[i]], 10_000)) for i in range(n_pix)]
    fstate = np.zeros((n_pix, K.N_STATE))
    fstate[:, K.LAST_TRIAL] = -1.0
    fstate[:, K.LAST_TAU] = -math.inf
    fstate[:, K.PEND_TRIAL] = math.nan
    fstate[:, K.PEND_TAU] = math.nan
    ref = [(-1.0, -math.inf, math.nan, math.nan)] * n_pix
    # windows (j_min, w_end µs, discard_from, t0 µs): a jump of j_min past pending events, then a window whose
    # pending events from trial 400 on are dropped
    windows = [(0.0, 2e6, math.inf, 0), (0.0, 3.5e6, math.inf, 0), (300.0, 5e6, math.inf, 7), (300.0, 8e6, 400.0, 7)]
    total = 0
    for j_min, w_end, discard_from, t0 in windows:
        (t, x, y, p), on, off = _kernel_window(states, fstate, j_min, w_end, discard_from, t0, start_cap)
        expected = []
        for i in range(n_pix):
            events, ref[i] = reference_window(draws[i], LOG1M_P[i], Q_ON[i], *ref[i], j_min, w_end, discard_from, t0)
            expected += [(tt, i % WIDTH, i // WIDTH, int(o)) for tt, o in events]
            assert (on[i], off[i]) == (sum(o for _, o in events), sum(not o for _, o in events)), i
        assert list(zip(t.tolist(), x.tolist(), y.tolist(), p.tolist())) == expected
        cols = [K.LAST_TRIAL, K.LAST_TAU, K.PEND_TRIAL, K.PEND_TAU]
        np.testing.assert_array_equal(fstate[:, cols], np.array(ref))
        total += t.size
    for i in range(n_pix):  # the kernel's stream is where the reference's stopped: the next outputs agree
        assert xoshiro256pp_reference([int(w) for w in states[i]], 1)[0] == next(draws[i]), i
    # every kind of pixel did what it is there for
    assert total > 300
    # p = 1: an event in every trial, up to the window's end
    assert fstate[7, K.PEND_TRIAL] == fstate[7, K.LAST_TRIAL] + 1.0
    assert fstate[7, K.PEND_TAU] >= 8e6 > fstate[7, K.LAST_TAU]
    assert fstate[6, K.PEND_TRIAL] == math.inf and fstate[5, K.PEND_TRIAL] == math.inf  # p = 0; a gap beyond inf
    assert 0.0 < -LOG1M_P[4] < K.PLAIN_LOG1M_P < -LOG1M_P[3]
