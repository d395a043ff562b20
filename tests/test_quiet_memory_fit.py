"""The memory fit's likelihood (calibration/quiet/memory.py, issue 32 §2): against the memoryless closed form, against
a trial-by-trial forward recursion built from the model's comparisons in logs (independent of the chain's index
tables and of its steady-state formula), and, slow, a fit of the simulator's own events that finds the truth."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import poisson

import evnoise as ev
from evnoise.calibration.quiet import memory as qm
from evnoise.calibration.quiet import window as qw
from evnoise.events import EVENT_DTYPE
from evnoise.terms import memory
from evnoise.terms.arrivals import arrival_shares, lux_of_photons

K = 4.0
BASE = ev.load_preset("dvs128").replace(leak_regularity=0.0, hot_pixel_fraction=0.0, eps_sigma=0.0,
                                       refractory_s=0.0)


def _window(events, shape, duration_s):
    """A QuietWindow of ``events`` (structured: x, y, p, t in µs), as quiet_window gives it."""
    counts = np.zeros((2, *shape), dtype=np.int64)
    np.add.at(counts, (1 - events["p"].astype(np.int64), events["y"], events["x"]), 1)
    return qw.QuietWindow(counts, duration_s, source="test", events=qw.window_events(events, shape, 0))


def _events(rows, shape):
    """Structured events from ``(x, y, p, t_us)`` rows."""
    e = np.zeros(len(rows), dtype=EVENT_DTYPE)
    for i, (x, y, p, t) in enumerate(rows):
        e["x"][i], e["y"][i], e["p"][i], e["t"][i] = x, y, p, t
    return e[np.argsort(e["t"], kind="stable")]


def _trial_us():
    return 1e6 / BASE.trial_rate_hz


ROWS = [(0, 0, 1, 10), (0, 0, 0, 2 * _trial_us() + 5), (0, 0, 1, 9 * _trial_us() + 1), (1, 0, 0, 4 * _trial_us() + 7),
        (2, 1, 1, 30 * _trial_us() + 3)]
SHAPE = (2, 3)
DURATION_S = 40 * _trial_us() * 1e-6


def test_transition_matrices_sum_to_the_per_trial_probabilities():
    t = memory.level_tables(3.0, BASE.eps_pos, BASE.eps_neg, BASE.bias_pr, 0.4, a_on=1e-3, a_off=3e-4)
    e_on, e_off = qm.transition_matrices(t)
    np.testing.assert_allclose(e_on.sum(axis=1), t.p_on, rtol=1e-12, atol=1e-300)
    np.testing.assert_allclose(e_off.sum(axis=1), t.p_off, rtol=1e-12, atol=1e-300)


def test_memoryless_likelihood_is_the_independent_trials_closed_form():
    """``k = 0``, no spread: every trial is independent, ON with ``p_on``, OFF with ``p_off`` (the paper's exact
    probability with the background in a trial without photon event)."""
    w = _window(_events(ROWS, SHAPE), SHAPE, DURATION_S)
    values = dict(lam=40.0, k=0.0, leak_on_hz=2.0, leak_off_hz=0.7, sigma=0.0)
    got = qm.window_log_likelihood(values, w, BASE)
    ph_on = float(ev.event_probability(np.array([40.0]), BASE.eps_pos, BASE.bias_pr)[0])
    ph_off = float(ev.event_probability(np.array([40.0]), BASE.eps_neg, BASE.bias_pr)[0])
    a_on, a_off = arrival_shares(np.float64(2.0), np.float64(0.7), BASE.trial_rate_hz)
    p_on, p_off = ph_on + (1 - ph_on - ph_off) * a_on, ph_off + (1 - ph_on - ph_off) * a_off
    n_trials = math.floor(DURATION_S * BASE.trial_rate_hz)
    n_on = sum(r[2] for r in ROWS)
    n_off = len(ROWS) - n_on
    want = (n_on * math.log(p_on) + n_off * math.log(p_off)
            + (n_trials * SHAPE[0] * SHAPE[1] - len(ROWS)) * math.log1p(-p_on - p_off))
    # the state range leaves out 1e-17 of the Poisson mass per side
    assert got == pytest.approx(want, rel=1e-9)


def _reference_log_likelihood(values, rows, shape, n_trials):
    """Trial by trial: the chain built from the comparisons in logs over the state range, started in the
    per-trial chain's stationary law (power iteration), the forward vector multiplied trial by trial."""
    lam, k = values["lam"], values["k"]
    lo, n_s, _ = memory.state_range(lam)
    m = lo + np.arange(n_s)
    pmf = poisson.pmf(m, lam)
    b = BASE.bias_pr
    up = np.log(m[None, :] + b) - np.log(m[:, None] + b)  # row: reference, column: count
    on = up > BASE.eps_pos
    off = -up > BASE.eps_neg
    a_on, a_off = (float(x) for x in arrival_shares(np.float64(values["leak_on_hz"]),
                                                    np.float64(values["leak_off_hz"]), BASE.trial_rate_hz))
    fresh_on = (1 - k) * pmf * (pmf @ on)  # P(count j and a fresh reference beaten)
    fresh_off = (1 - k) * pmf * (pmf @ off)
    none = (1 - k) * pmf * (pmf @ (~on & ~off))
    e_on = fresh_on[None, :] + k * pmf[None, :] * on + a_on * (none[None, :] + k * pmf[None, :] * (~on & ~off))
    e_off = fresh_off[None, :] + k * pmf[None, :] * off + a_off * (none[None, :] + k * pmf[None, :] * (~on & ~off))
    stay = np.diag(1.0 - e_on.sum(axis=1) - e_off.sum(axis=1))
    chain = e_on + e_off + stay
    x = pmf / pmf.sum()
    for _ in range(20000):
        x = x @ chain
    total = 0.0
    for pix in range(shape[0] * shape[1]):
        mine = {math.floor(int(t) / _trial_us()): p for (xx, yy, p, t) in rows if yy * shape[1] + xx == pix}
        alpha = x.copy()
        for trial in range(n_trials):
            alpha = alpha @ (e_on if mine.get(trial) == 1 else e_off if trial in mine else stay)
        total += math.log(alpha.sum())
    return total


@pytest.mark.parametrize("k", [0.3, 0.9])
def test_memory_likelihood_against_a_trial_by_trial_reference(k):
    w = _window(_events(ROWS, SHAPE), SHAPE, DURATION_S)
    values = dict(lam=30.0, k=k, leak_on_hz=3.0, leak_off_hz=1.0, sigma=0.0)
    n_trials = math.floor(DURATION_S * BASE.trial_rate_hz)
    want = _reference_log_likelihood(values, ROWS, SHAPE, n_trials)
    assert qm.window_log_likelihood(values, w, BASE) == pytest.approx(want, rel=1e-8)


def test_memory_fit_refuses_dead_time_and_windows_without_events():
    w = _window(_events(ROWS, SHAPE), SHAPE, DURATION_S)
    with pytest.raises(ev.ParameterError, match="refractory"):
        qm.fit_memory([w], BASE.replace(refractory_s=1e-3))
    counts_only = qw.QuietWindow(w.counts, DURATION_S, source="counts")
    with pytest.raises(ev.InputError, match="no events"):
        qm.fit_memory([counts_only], BASE)


@pytest.mark.slow
def test_memory_fit_recovers_the_simulators_truth(tmp_path):
    """A 64 x 64 sensor with reset memory, photon noise at 3 photons per trial and a spread leak, simulated for
    10 s: the fit finds every parameter within K standard errors, and memory is told apart from none (~3 min)."""
    truth = dict(lam=3.0, k=0.4, leak_on_hz=0.01, leak_off_hz=0.003, sigma=0.6)
    params = BASE.replace(reset_memory=truth["k"], leak_on_hz=truth["leak_on_hz"], leak_off_hz=truth["leak_off_hz"],
                          leak_sigma=truth["sigma"])
    shape, duration_s = (64, 64), 10.0
    lux = float(lux_of_photons(truth["lam"], params))
    events = ev.simulate_events(np.full(shape, lux), params, duration_s, rng=3)
    w = qw.quiet_window(ev.write_events(tmp_path / "memory.h5", events, shape), 0.0, duration_s)
    fit = qm.fit_memory([w], BASE)
    assert fit.std_error is not None
    for name, value in truth.items():
        assert abs(fit.values[name] - value) < K * fit.std_error[name], (name, fit.values[name], value)
    assert fit.p_value < 1e-6
    back = fit.to_params(BASE)
    assert back.reset_memory == pytest.approx(fit.values["k"]) and back.leak_sigma == pytest.approx(fit.values["sigma"])
