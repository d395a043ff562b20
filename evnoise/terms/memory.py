"""Reset memory (``reset_memory > 0``): after an event a pixel compares against the level it stored then.

The paper's per-trial model is memoryless: every trial compares a fresh photon count ``n ~ Poisson(lam)``
with a fresh reference ``n0 ~ Poisson(lam)``. A real pixel stores the (noisy) level it reset at, so after
an ON event, stored high, the next crossing tends to be OFF: quiet pixels alternate polarity (93 % of
consecutive events opposite in real recordings, 50 % in the memoryless model; issue 32).

Model (static pixels). A pixel's state is its *stored count* ``m``: the photon count ``n`` of the trial of
its last event (at ``t = 0``: drawn from the steady state, :func:`initial_law`). In each trial
``n ~ Poisson(lam)`` and, with probability ``k = reset_memory``, the reference is the stored ``m``; else
(probability ``1 - k``) it is a fresh ``n0 ~ Poisson(lam)``, as in the paper. ON when
``log(n + b) - log(ref + b) > eps_pos``, OFF when ``log(ref + b) - log(n + b) > eps_neg``; an event stores
``m = n``. ``k = 0`` is exactly the memoryless model (the state is never read; the simulators then run their
memoryless paths unchanged); ``k = 1``: every comparison is against the stored level.

Per trial from state ``m`` (``k_on(i) = i + floor(expm1(eps_pos) (i + b))``, the exact kernel's thresholds,
and ``k_off`` alike):

    P_on(m)  = (1 - k) p_on  + k P(N > k_on(m)),      p_on  = P(N > k_on(N0))     (the paper's exact p)
    P_off(m) = (1 - k) p_off + k P(k_off(N) < m),     p_off = P(N0 > k_off(N))

single Poisson tails per state, and the new state's law is a Poisson pmf times a tail: after a fresh ON
``P(n = j) ∝ Poisson(j) P(k_on(N0) < j)``, after a stored ON ``∝ Poisson(j) 1{j > k_on(m)}`` (OFF alike).
So the event sequence is a Markov renewal process: the gap is geometric in eligible trials with
``P(m) = P_on(m) + P_off(m)`` (plus the refractory period, as in the memoryless tiers: the mean time from
an event in state ``m`` to the next is ``R + dt / P(m)``), the polarity and the next state are drawn from
the state's laws. :func:`memory_statistics` evaluates the stationary rate, ON share, polarity-transition
matrix and inter-event intervals per polarity pair from the stationary law of the embedded chain (a
linear solve); :mod:`evnoise._kernels.memory` simulates it event by event.

Truncation (the tail bound). Counts are restricted to ``lo <= n, n0, m <= hi`` around ``lam``
(:func:`state_range`): the tables describe the model in which a count outside that range never fires
an event. That model and the full one coincide unless some trial's ``n`` or ``n0`` falls outside the
range, which has probability at most ``2 * tail_mass`` per trial; so over ``J`` pixel-trials the two
models' event streams (coupled) differ with probability at most ``2 J tail_mass``.
``tail_mass <= 1e-17`` per side while the range fits :data:`MAX_STATES` states (``lam`` up to about
3e4); beyond, the range is the ``MAX_STATES`` counts around ``lam`` and ``tail_mass`` (reported by
:func:`memory_statistics`) grows (2e-6 at ``lam = 1e5``); there events need
counts tens of standard deviations from ``lam`` for any ``eps`` above ``~5 / sqrt(lam)`` and the rate is 0.

Supported: :func:`evnoise.simulate_events` / :func:`evnoise.iter_events` of static scenes (``method="trials"``:
trial by trial, :func:`evnoise._kernels.simulate.trial_window`, the reference for this tier), changing scenes
(:func:`evnoise.simulate_video` / :func:`evnoise.iter_video`: static pixels here, changing ones trial by trial,
every pixel started in the steady state of the first frame's light), and
:class:`evnoise.NoiseStream` (light held per interval: each pixel keeps its stored count across intervals
and through changes of light, its level's tables widened to hold it; the v2e plugin runs on it) and the
tonic plugin (each sample starts in the steady state), and :func:`evnoise.sample_counts` (the counts of
those events; its Poisson / negative-binomial variants about :func:`memory_statistics`' rate) with the dataset
generator's counts mode, all with threshold mismatch (``eps_sigma > 0`` or given ``thresholds``: pixels are
grouped by chain, :func:`pixel_groups`). :func:`evnoise.expected_rate` gives :func:`memory_statistics`' rate
(the nominal pixel's). The regular background timer (``leak_regularity``, ``hot_pixel_regularity``) runs with
memory in every simulator (:func:`evnoise.simulate_events` / ``iter_events``, both tiers, ``simulate_video``,
``sample_counts``, :class:`evnoise.NoiseStream` and so the v2e plugin, the tonic plugin) and in
``expected_rate``: from state ``m`` the next event comes after ``min(G, L)`` eligible trials, ``G`` the photon
gap, ``L`` the timer's (photons first on a tie), a timer event storing the count of a trial without photon
event; the closed form is the chain with a per-state background (:func:`with_timer`), the renewal kernel draws
both gaps (:func:`evnoise._kernels.memory.memory_window`), the trial kernel runs its own timer (started from the
steady-state age given the stored state, :func:`evnoise._kernels.memory.initial_stored`); a stream keeps a
pixel's pending timer arrival across intervals (moved with a change of its intensity); :func:`memory_iei_cdf`
gives the intervals' distribution (:func:`_timer_iei_cdf`). Refused with :class:`~evnoise.ParameterError`:
per-pixel rates or Poisson counts for pixels whose thresholds or background differ (the closed form is the
nominal pixel's).

Threshold mismatch. A pixel's chain reads its thresholds only through the threshold counts ``k_on(m)``,
``k_off(m)`` over its light's states, so pixels whose thresholds give the same counts share one chain, exactly
(:func:`threshold_classes`); with a 3 % mismatch most pixels still get a chain of their own (a
346 x 260 davis346 sensor: 24 000 chains at 0.01 lux, 80 000 at 0.5 lux; a spread leak alone does that too),
each with tables of its own (set-up about 1 ms per pixel at tens
of photons per trial, a few ms at thousands; :data:`MAX_TABLE_STATES` bounds the total). A still scene or a video
whose chains pass it (``evk4`` at 1280 x 720 with its mismatch: 624 000 chains at 2 lux) runs in the trial tier with
each chain's start computed on its own, without tables (:mod:`evnoise._kernels.memory_start`: the law of the table
path for many chains, to rounding, and its draws, so the same events as ``method="trials"`` with tables but where a
uniform falls within a rounding of a law's step, about 1e-16 per pixel); :class:`evnoise.NoiseStream` goes on
trial by trial where its tables would pass it (at its first interval or a change of light); not with the regular
timer, ``method="renewal"`` or the tonic transform, which refuse it.

Background (Poisson: the ``leak_*`` rates and hot pixels, :func:`level_background` for the nominal pixel; the
simulators group pixels by ``(lam, background, thresholds)``, :func:`pixel_groups`, so hot pixels and a spread leak
(``leak_sigma``) have chains of their own; :func:`memory_statistics` is the nominal pixel's). As in the
memoryless model (:mod:`evnoise.background`) a trial without photon event has a background event with
probability ``a = a_on + a_off``, ON with probability ``a_on / a``. The
pixel then resets to the level of that trial: it stores the trial's count ``n``, whose law given state ``m``
and no photon event is

    P(n = j, no photon event | m) = (1 - k) Poisson(j) P(fresh reference not beaten | j)
                                    + k Poisson(j) 1{idx_off(m) < j < idx_on(m)}

(``none_fresh`` plus the stored branch not beaten). Per trial ``P_on(m) + (1 - P(m)) a_on`` (OFF alike), so the
chain keeps its form: two more branches of the embedded chain (:func:`_after`), two more in the kernel's event
draw. With ``a = 0`` the tables, and the event streams, are those of the model without background, bit for bit.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from .base import NoiseTerm

#: Most states (counts) of one light level: bounds the kernel's tables and the stationary solve of
#: :func:`memory_statistics` (and its dense fallback, an ``S x S`` matrix of 72 MB).
MAX_STATES = 3001
#: Up to this many states :func:`memory_statistics` solves densely (beyond: GMRES with the chain's structure).
DENSE_STATES = 600
#: Poisson mass per side left outside the state range when it fits in :data:`MAX_STATES`.
TAIL_MASS = 1e-17
#: Up to this many distinct light levels a simulation computes each level's stationary rate (its expected
#: events); beyond, an estimate sizes its windows.
EXACT_RATE_LEVELS = 64
#: Most table entries (states over all light levels) one simulation builds (136 bytes each in the tables, 2.7 GB at
#: the limit; building them takes about 100-200 MB more, :data:`ITERATE_BLOCK_STATES`).
MAX_TABLE_STATES = 20_000_000


class ResetMemory(NoiseTerm):
    """``reset_memory``: the share of trials that compare against the level stored at the last event (0: none)."""

    name = "memory"
    fields = ("reset_memory",)

    def kernel_model(self, params) -> dict:
        # the trial kernel's share of comparisons against the stored count (the trial tier: changing scenes)
        return {"memory": float(params.reset_memory)}


MEMORY = ResetMemory()


def memory_on(params) -> bool:
    """True when ``params`` has reset memory (``reset_memory > 0``)."""
    return getattr(params, "reset_memory", 0.0) > 0


def unsupported(params, thresholds=None, background=None, per_pixel: bool = True) -> list:
    """What the reset-memory model does not cover for ``params`` (checked :class:`~evnoise.NoiseParams`), in words
    (empty: all of it is covered; see the module doc). ``per_pixel``: whether the caller handles a background or
    thresholds that differ between pixels (hot pixels, ``leak_sigma``, threshold mismatch, given maps: the
    simulators group pixels by their chain, and cover everything); a closed form for one pixel or the population
    does not."""
    missing = []
    if not per_pixel:
        if params.eps_sigma > 0 or thresholds is not None:
            missing.append("threshold mismatch (eps_sigma > 0 or given thresholds)")
        if background is not None:
            missing.append("given background maps")
        if params.hot_pixels_on:
            missing.append("hot pixels (hot_pixel_*)")
        if params.has_background and params.leak_sigma > 0:
            missing.append("a background that differs between pixels (leak_sigma > 0)")
    return missing


def pixel_groups(lam, params, background=None, thresholds=None, class_spans=None):
    """Pixels grouped by their chain: ``(levels, a_on, a_off, regularity, group, eps)``, the distinct chains'
    photons per trial, per-trial background arrival probabilities (:func:`level_background`), the regular timer's
    regularity (:func:`evnoise.terms.timer.pixel_regularity`, hot pixels may have their own; 0 without the timer)
    and thresholds ``eps = (eps_on, eps_off)``, and each pixel's index ``group`` into them. ``background``: the
    run's flat ``(scale, hot)`` maps (:class:`evnoise._run.RunSetup`) or None (every pixel the nominal one).
    ``thresholds``: the run's flat per-pixel ``(eps_on, eps_off)`` or None (the nominal ones). A background spread
    over pixels (``leak_sigma > 0``) makes every pixel a group of its own (see :data:`MAX_TABLE_STATES`).

    Thresholds that differ between pixels (mismatch) split a light level only where the chain differs: the chain
    reads a threshold through its counts ``k(m) = m + floor(expm1(eps) (m + b))`` over the level's states
    (:func:`threshold_classes`), so pixels whose thresholds give the same counts share a chain exactly.
    ``class_spans``: ``{lam: (lo, n_states)}``, the states over which they must agree (default
    :func:`state_range`'s; :class:`evnoise.NoiseStream` widens them to hold counts stored under another light)."""
    lam = np.asarray(lam, dtype=np.float64).ravel()
    if thresholds is None:
        eps_on, eps_off = np.full(lam.shape, params.eps_pos), np.full(lam.shape, params.eps_neg)
    else:
        eps_on, eps_off = (np.asarray(x, dtype=np.float64).ravel() for x in thresholds)
    lam_levels, lam_index = np.unique(lam, return_inverse=True)
    lam_index = lam_index.ravel()
    if background is None:
        a_on, a_off = (x[lam_index] for x in level_background(lam_levels, params))
    else:
        a_on, a_off = level_background(lam, params, *background)
    class_on = np.zeros(lam.size, dtype=np.int64)
    class_off = np.zeros(lam.size, dtype=np.int64)
    if not (np.all(eps_on == eps_on[0]) and np.all(eps_off == eps_off[0])):
        order = np.argsort(lam_index, kind="stable")
        bounds = np.searchsorted(lam_index[order], np.arange(lam_levels.size + 1))
        for j, level in enumerate(lam_levels):
            sel = order[bounds[j]:bounds[j + 1]]
            lo, n_states = (class_spans or {}).get(float(level)) or state_range(float(level))[:2]
            class_on[sel] = threshold_classes(eps_on[sel], lo, n_states, params.bias_pr)
            class_off[sel] = threshold_classes(eps_off[sel], lo, n_states, params.bias_pr)
    reg = 0.0
    if params.regular_background:
        from .timer import pixel_regularity

        reg = pixel_regularity(params, None if background is None else background[1])
    reg = np.broadcast_to(np.asarray(reg, dtype=np.float64), lam.shape)
    rows, first, group = np.unique(np.stack([lam, a_on, a_off, class_on, class_off, reg], axis=1), axis=0,
                                   return_index=True, return_inverse=True)
    # each group's thresholds: those of its first pixel (all of its pixels have the same counts)
    return (np.ascontiguousarray(rows[:, 0]), np.ascontiguousarray(rows[:, 1]), np.ascontiguousarray(rows[:, 2]),
            np.ascontiguousarray(rows[:, 5]), np.ascontiguousarray(group.ravel(), dtype=np.int64),
            (np.ascontiguousarray(eps_on[first]), np.ascontiguousarray(eps_off[first])))


def chain_plan(lam, params, background=None, thresholds=None):
    """What the chains of pixels at ``lam`` photons per trial are before any table is built: ``(groups, timer,
    states)``, :func:`pixel_groups`' tuple, the chains' regular timer (:func:`chain_timer`) and the states their
    tables would hold (:func:`table_states`, what :data:`MAX_TABLE_STATES` bounds)."""
    groups = pixel_groups(lam, params, background, thresholds)
    levels, a_on, a_off, reg, _, _ = groups
    return groups, chain_timer(a_on, a_off, reg, params), table_states(levels)


def level_spans(levels, range_of=None):
    """The distinct light levels of ``levels`` (photons per trial, one entry per chain or pixel) and their states:
    ``(which, lam, lo, n_states)``, ``which`` (int64, per entry) indexing ``lam`` (the distinct levels, sorted) and
    their :func:`state_range` ``lo``, ``n_states`` (int64; each computed once; ``range_of``: a function standing in
    for :func:`state_range`, e.g. one that remembers)."""
    range_of = state_range if range_of is None else range_of
    lam, which = np.unique(np.asarray(levels, dtype=np.float64), return_inverse=True)
    ranges = np.array([range_of(x)[:2] for x in lam.tolist()], dtype=np.int64).reshape(-1, 2)
    return which.ravel().astype(np.int64), lam, ranges[:, 0].copy(), ranges[:, 1].copy()


def table_states(levels) -> int:
    """The states the tables of chains at ``levels`` (photons per trial, one entry per chain) hold."""
    which, _, _, n_states = level_spans(levels)
    return int(n_states[which].sum())


def too_many_states(n_chains: int, states: int, why: str = ""):
    """The :class:`~evnoise.ParameterError` of a scene whose ``n_chains`` chains need ``states`` table states, more
    than :data:`MAX_TABLE_STATES` (``why``: what else keeps them from running, appended)."""
    from ..errors import ParameterError

    return ParameterError(f"reset_memory > 0: this scene's {n_chains:,} distinct chains (light levels, and pixels "
                          f"whose thresholds or background differ) need {states:,} table states, more than "
                          f"{MAX_TABLE_STATES:,}{why}; use fewer distinct illuminance values (e.g. quantise lux), a "
                          f"smaller sensor, or no threshold mismatch / leak spread")


def still_chains(lam, params, background=None, thresholds=None, plan=None, refused_why="", done=None):
    """The chains of pixels at ``lam`` photons per trial (flat; ``background``, ``thresholds`` as in
    :func:`pixel_groups`), ready for the kernels: ``(levels, group, tables, rates, timer)``, ``tables`` the
    ``(table, itable, offsets, sizes)`` of :func:`kernel_tables`, ``rates`` its per-chain rates, ``timer`` the
    chains' regular timer (:func:`chain_timer`, None: none). ``plan``: :func:`chain_plan`'s, when the caller has
    it; ``refused_why``, ``done``: as :func:`kernel_tables`'."""
    (levels, a_on, a_off, reg, group, eps), timer, _ = (chain_plan(lam, params, background, thresholds)
                                                        if plan is None else plan)
    *tables, rates = kernel_tables(levels, params, background=(a_on, a_off), thresholds=eps, timer=timer,
                                   refused_why=refused_why, done=done)
    return levels, group, tuple(tables), rates, timer


def chain_timer(a_on, a_off, regularity, params):
    """The regular background timer of chains with per-trial background arrival probabilities ``a_on``, ``a_off``
    and ``regularity`` (arrays, one entry per chain): ``(3, chains)``, the timer's fixed part ``d`` (trials),
    ``log1p(-a2)`` (:func:`evnoise.terms.timer.timer_shape`, from the intensity ``-log1p(-a) N`` that gives the
    arrival probability ``a = a_on + a_off``) and the share of ON arrivals; or None when no chain has one.
    ``d = inf`` where a chain's background is Poisson (regularity 0, the timer's law then, or no background):
    the tables hold that background (:func:`kernel_tables`)."""
    from .timer import timer_shape

    a_on = np.asarray(a_on, dtype=np.float64)
    a_off = np.asarray(a_off, dtype=np.float64)
    a = a_on + a_off
    reg = np.broadcast_to(np.asarray(regularity, dtype=np.float64), a.shape)
    has = (a > 0) & (reg > 0)
    if not has.any():
        return None
    with np.errstate(divide="ignore"):
        l_all = np.where(has, -np.log1p(-np.minimum(a, 1.0)) * params.trial_rate_hz, 0.0)
    d, log1m_a2 = timer_shape(np.where(np.isfinite(l_all), l_all, 1e300), 1.0 / params.trial_rate_hz,
                              np.where(has, reg, 0.0))
    share_on = np.where(a > 0, a_on / np.where(a > 0, a, 1.0), 0.0)
    return np.ascontiguousarray(np.stack([np.where(has, d, math.inf), np.where(has, log1m_a2, 0.0), share_on]))


def with_timer(t, a_on: float, a_off: float, d: float, log1m_a2: float):
    """The tables ``t`` of a chain whose background (``a_on``, ``a_off``) arrives by the regular timer (``d``,
    ``log1m_a2``: :func:`chain_timer`), as a chain with a per-state background: from state ``m`` the next event
    comes after ``min(G, L)`` eligible trials (``G`` geometric with the photon probability ``p(m)``, ``L`` the
    timer; photons first on a tie), so the event is a photon one with probability ``p(m) E[min(G, L)]`` and the
    mean sojourn is ``E[min(G, L)]`` trials (:func:`evnoise.terms.timer.timer_mean_min`, the fixed part's
    fraction mixed). Per-state arrival probabilities ``a(m)`` with ``p + (1 - p) a = 1 / E[min]`` give the chain
    (:func:`_stationary`), the rates and mean intervals (:func:`level_statistics`) and the steady state
    (:func:`initial_law`) of that process; its interval distribution is not geometric (:func:`_timer_iei_cdf`)."""
    from .timer import timer_mean_min

    p = t.photon_event
    with np.errstate(divide="ignore"):
        log1m_p = np.log1p(-p)
    d0 = math.floor(d)
    phi = d - d0
    e_min = ((1.0 - phi) * timer_mean_min(log1m_p, p, d0, log1m_a2)
             + phi * timer_mean_min(log1m_p, p, d0 + 1.0, log1m_a2))
    photon_first = np.minimum(p * e_min, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        a_eff = np.where(p < 1.0, (1.0 - photon_first) / (e_min * np.where(p < 1.0, 1.0 - p, 1.0)), 0.0)
        photon_on = np.where(p > 0, (t.p_fresh_on + t.stored_on) / np.where(p > 0, p, 1.0), 0.0)
    share_on = a_on / (a_on + a_off) if a_on + a_off > 0 else 0.0  # chain_timer gives a timer only where a > 0
    # the sojourn up to a photon event, and up to a timer one: E[G; G <= L] and E[L; L < G]
    by_photon = ((1.0 - phi) * _photon_first_mean(log1m_p, p, d0, log1m_a2)
                 + phi * _photon_first_mean(log1m_p, p, d0 + 1.0, log1m_a2))
    by_timer = np.maximum(e_min - by_photon, 0.0)
    return dataclasses.replace(t, a_on=a_eff * share_on, a_off=a_eff * (1.0 - share_on),
                               gap_on=photon_on * by_photon + share_on * by_timer,
                               gap_off=(1.0 - photon_on) * by_photon + (1.0 - share_on) * by_timer)


def _photon_first_mean(log1m_p, p, d, log1m_a2):
    """``E[G 1{G <= d + G2}]`` for a whole ``d`` (``G`` geometric with ``p``, ``G2`` with ``a2``; arrays): the sum
    over ``g <= d`` is ``(1 - q^d (1 + d p)) / p``, beyond ``p q^d (d / (1 - q c) + 1 / (1 - q c)^2)`` with ``c = 1 -
    a2`` (``1 - q c = -expm1(log q + log c)``); 1 where ``p = 1``, 0 where ``p = 0``."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        live = (p > 0) & (p < 1)
        lq = np.where(live, log1m_p, -1.0)
        p_s = np.where(live, p, 1.0)
        q_d = np.exp(d * lq)
        head = np.maximum((-np.expm1(d * lq) - d * p_s * q_d) / p_s, 0.0)  # ~ p d^2 / 2 for p d small: rounding
        one_m_qc = -np.expm1(lq + log1m_a2)
        tail = p_s * q_d * (d / one_m_qc + 1.0 / one_m_qc**2)
    return np.where(live, head + tail, np.where(p >= 1.0, 1.0, 0.0))


#: Most threshold-count breakpoints :func:`threshold_classes` sorts per light level; beyond, each distinct
#: threshold is a class of its own.
MAX_BREAKPOINTS = 1_000_000


def _expm1(eps: float) -> float:
    """``expm1(eps)``, ``inf`` beyond float64 (a threshold no count reaches) rather than ``OverflowError``."""
    return math.inf if eps > 709.0 else math.expm1(eps)


def threshold_factors(eps) -> np.ndarray:
    """``expm1(eps)`` of each threshold (array), as the chains' tables take it (``inf`` beyond float64): the factor
    ``c`` of the threshold counts ``k(m) = m + floor(c (m + b))``."""
    return np.array([_expm1(e) for e in np.asarray(eps, dtype=np.float64).ravel().tolist()], dtype=np.float64)


def threshold_classes(eps, lo: int, n_states: int, bias: float) -> np.ndarray:
    """Class of each threshold ``eps`` (array) such that two thresholds share a class only if they give the same
    threshold counts ``k(m) = m + floor(expm1(eps) (m + bias))`` at every state ``m = lo .. lo + n_states - 1``
    (:func:`evnoise._kernels.poisson.threshold_count`, what the chain's tables read). ``floor(c x)`` changes
    where ``c`` passes ``j / x``: the classes are the intervals between those breakpoints, each checked with the
    kernel's arithmetic at its smallest and largest threshold (counts are monotone in ``c``): in a class that fails
    it (float rounding beside a breakpoint) every distinct threshold is a class of its own; with more than
    :data:`MAX_BREAKPOINTS` breakpoints every distinct threshold is one."""
    distinct, exact = np.unique(np.asarray(eps, dtype=np.float64), return_inverse=True)
    exact = exact.ravel()
    distinct = np.array([_expm1(e) for e in distinct.tolist()])  # as level_tables computes it
    if distinct.size == 1:
        return exact
    x = lo + np.arange(n_states, dtype=np.float64) + bias
    x = x[x > 0]  # m + b = 0: k = m whatever the threshold
    j_lo, j_hi = np.floor(distinct[0] * x), np.floor(distinct[-1] * x)
    if not (np.all(np.isfinite(j_hi)) and float((j_hi - j_lo).sum()) <= MAX_BREAKPOINTS):
        return exact
    if distinct.size * x.size <= float((j_hi - j_lo).sum()):
        # fewer counts than breakpoints (few thresholds, many photons): compare the counts themselves, computed
        # as the kernel does (threshold_count: floor(c (m + b)))
        counts = np.floor(distinct[:, None] * x[None, :])
        return np.unique(counts, axis=0, return_inverse=True)[1].ravel()[exact]
    steps = (j_hi - j_lo).astype(np.int64)
    xs = np.repeat(x, steps)
    js = np.repeat(j_lo, steps) + 1.0 + (np.arange(xs.size) - np.repeat(np.cumsum(steps) - steps, steps))
    breaks = np.unique(js / xs)
    cls = np.unique(np.searchsorted(breaks, distinct, side="right"), return_inverse=True)[1].ravel()
    # each class's counts at its smallest and largest threshold, computed as the kernel does: where float rounding
    # near a breakpoint makes them differ, each threshold of that class is a class of its own
    ends = np.flatnonzero(np.diff(cls, prepend=-1, append=cls[-1] + 1))
    first, last = ends[:-1], ends[1:] - 1
    step = max(1, 4_000_000 // max(x.size, 1))
    split = np.zeros(first.size, dtype=bool)
    for a in range(0, first.size, step):
        low = np.floor(distinct[first[a:a + step], None] * x)
        high = np.floor(distinct[last[a:a + step], None] * x)
        split[a:a + step] = (low != high).any(axis=1)
    alone = split[cls]
    cls = np.where(alone, first.size + np.arange(distinct.size), cls)
    return cls[exact]


def level_background(levels, params, scale=None, hot=None):
    """Per-trial background arrival probabilities ``(a_on, a_off)`` at the light levels ``levels`` (photons per
    trial; :mod:`evnoise.background`; with the regular timer, the intensities' per-trial probabilities that
    :func:`chain_timer` turns into the timer), 0 without background: the nominal pixel's, or with ``scale``,
    ``hot`` (arrays like ``levels``) each pixel's of the background maps."""
    from .arrivals import arrival_shares, lux_of_photons
    from .registry import background_on, intensities

    lam = np.atleast_1d(np.asarray(levels, dtype=np.float64))
    if not background_on(params):
        return np.zeros(lam.shape), np.zeros(lam.shape)
    l_on, l_off = intensities(lux_of_photons(lam, params), params, scale, hot)
    a_on, a_off = arrival_shares(np.broadcast_to(l_on, lam.shape), np.broadcast_to(l_off, lam.shape),
                                 params.trial_rate_hz)
    return np.asarray(a_on, dtype=np.float64), np.asarray(a_off, dtype=np.float64)


# --------------------------------------------------------------------------------------------------
# the states of one light level
# --------------------------------------------------------------------------------------------------
def _log_cumsum(log_x):
    """``log(cumsum(exp(log_x)))`` without overflow or underflow (``-inf`` entries allowed)."""
    top = np.max(log_x)
    if not np.isfinite(top):
        return np.full_like(log_x, -np.inf)
    with np.errstate(divide="ignore"):
        return np.log(np.cumsum(np.exp(log_x - top))) + top


def state_range(lam: float):
    """``(lo, n_states, tail_mass)``: the counts ``lo .. lo + n_states - 1`` kept around ``lam``.

    The smallest range with at most :data:`TAIL_MASS` of ``Poisson(lam)`` below and above it, or, when that
    needs more than :data:`MAX_STATES` counts, the ``MAX_STATES`` counts centred on ``floor(lam)``;
    ``tail_mass`` is the Poisson mass outside the range (module doc: the truncation's bound). Remembered per
    ``lam`` (a Poisson tail sum, ~0.1-0.2 ms: the chains of one light level, a pixel each with threshold mismatch,
    and a stream's intervals ask for the same levels again and again).
    """
    return _state_range(float(lam))


@functools.lru_cache(maxsize=4096)
def _state_range(lam: float):
    from .._kernels.memory import fill_counts

    if lam <= 0.0:
        return 0, 1, 0.0
    half = int(min(math.ceil(12.0 * math.sqrt(lam) + 40.0), 4 * MAX_STATES))
    centre = int(math.floor(lam))
    c_lo = max(0, centre - half)
    n_c = centre + half - c_lo + 1
    log_p = np.empty(n_c)
    scratch = np.empty(n_c)
    fill_counts(lam, float(c_lo), n_c, 0.0, 0.0, 0.0, log_p, scratch, scratch)
    below = _log_cumsum(log_p)  # log P(c_lo <= N <= i)
    above = _log_cumsum(log_p[::-1])[::-1]  # log P(i <= N <= c_hi)
    limit = math.log(TAIL_MASS)
    # lo: the largest count with P(N < lo) <= TAIL_MASS; hi: the smallest with P(N > hi) <= TAIL_MASS
    ok_lo = np.flatnonzero(np.concatenate([[-np.inf], below[:-1]]) <= limit)
    i_lo = int(ok_lo[-1]) if ok_lo.size else 0
    ok_hi = np.flatnonzero(np.concatenate([above[1:], [-np.inf]]) <= limit)
    i_hi = int(ok_hi[0]) if ok_hi.size else n_c - 1
    if i_hi - i_lo + 1 > MAX_STATES:
        i_lo = max(0, centre - c_lo - MAX_STATES // 2)
        i_hi = min(n_c - 1, i_lo + MAX_STATES - 1)
        inside = np.logaddexp.reduce(log_p[i_lo:i_hi + 1])
        tail = float(-np.expm1(min(inside, 0.0)))
    else:
        with np.errstate(divide="ignore"):
            parts = [below[i_lo - 1] if i_lo > 0 else -np.inf, above[i_hi + 1] if i_hi + 1 < n_c else -np.inf]
        tail = float(np.exp(np.logaddexp(*parts)))
    return c_lo + i_lo, i_hi - i_lo + 1, tail


@dataclasses.dataclass(frozen=True)
class LevelTables:
    """The reset-memory chain of one light level (module doc), over states ``m = lo + s``, ``s < n_states``.

    Attributes
    ----------
    k : float
        The reset memory.
    lo, n_states : int
        The states.
    tail_mass : float
        Poisson mass outside them (:func:`state_range`).
    pmf : numpy.ndarray
        ``P(N = m)``.
    head, tail : numpy.ndarray
        ``P(lo <= N <= m)`` and ``P(m <= N <= hi)``.
    idx_on, idx_off : numpy.ndarray (int64)
        First state above the ON threshold of ``m`` (``n_states``: none) and last state ``j`` with
        ``k_off(j) < m`` (``-1``: none).
    fresh_on, fresh_off : numpy.ndarray
        ``(1 - k) Poisson(j) P(fresh reference beaten)``: the joint law of the new state and a fresh event.
    p_fresh_on, p_fresh_off : float
        Their sums (``(1 - k)`` times the paper's ``p_on``, ``p_off`` of the truncated model).
    stored_on, stored_off : numpy.ndarray
        ``k P(N > k_on(m))`` and ``k P(k_off(N) < m)`` per state.
    none_fresh : numpy.ndarray
        ``(1 - k) Poisson(j) P(fresh reference not beaten)``: the joint law of the trial's count ``j`` and no
        fresh event (with the stored branch's ``k Poisson(j)`` on ``idx_off(m) < j < idx_on(m)``, the law of the
        count of a trial without photon event: what a background event stores).
    a_on, a_off : float or numpy.ndarray
        Per-trial background arrival probabilities (0: none): a trial without photon event has a background
        event with probability ``a_on + a_off``, ON with probability ``a_on / (a_on + a_off)``; per state with the
        regular timer (:func:`with_timer`).
    gap_on, gap_off : numpy.ndarray or None
        With the regular timer (:func:`with_timer`), per state ``E[T 1{next event ON}]`` and OFF alike, in eligible
        trials (the sojourn and the next polarity are not independent then); None: they are (``q_on / P``).
    """

    k: float
    lo: int
    n_states: int
    tail_mass: float
    pmf: np.ndarray
    head: np.ndarray
    tail: np.ndarray
    idx_on: np.ndarray
    idx_off: np.ndarray
    fresh_on: np.ndarray
    fresh_off: np.ndarray
    p_fresh_on: float
    p_fresh_off: float
    stored_on: np.ndarray
    stored_off: np.ndarray
    none_fresh: np.ndarray
    a_on: float = 0.0
    a_off: float = 0.0
    gap_on: np.ndarray | None = None
    gap_off: np.ndarray | None = None

    @property
    def photon_event(self) -> np.ndarray:
        """Per-trial probability of a photon-noise event of each state (at most 1)."""
        return np.minimum(self.p_fresh_on + self.stored_on + self.p_fresh_off + self.stored_off, 1.0)

    def probabilities(self, a_on, a_off):
        """Per-trial ``(P_on, P_off)`` of each state with background arrival probabilities ``a_on``, ``a_off``
        (scalars, or ``(G, 1)`` arrays for ``G`` pixels of this level with backgrounds of their own): photon noise,
        then background in a trial without photon event."""
        photon_on = self.p_fresh_on + self.stored_on
        photon_off = self.p_fresh_off + self.stored_off
        if np.all(np.asarray(a_on) == 0.0) and np.all(np.asarray(a_off) == 0.0):
            return photon_on, photon_off
        quiet = 1.0 - self.photon_event
        return photon_on + quiet * a_on, photon_off + quiet * a_off

    @property
    def p_on(self) -> np.ndarray:
        """Per-trial ON probability of each state (photon noise, then background in a trial without)."""
        return self.probabilities(self.a_on, self.a_off)[0]

    @property
    def p_off(self) -> np.ndarray:
        """Per-trial OFF probability of each state (photon noise, then background in a trial without)."""
        return self.probabilities(self.a_on, self.a_off)[1]

    @property
    def p_event(self) -> np.ndarray:
        """Per-trial event probability of each state (at most 1)."""
        return np.minimum(self.p_on + self.p_off, 1.0)


def kernel_tables(levels, params, spans=None, background=None, thresholds=None, timer=None, refused_why="",
                  done=None):
    """The kernel's tables of the light levels ``levels`` (photons per trial) of one run.

    ``spans``: optional ``(lo, n_states)`` per level replacing :func:`state_range`'s (a wider range, holding
    stored counts of another light: :class:`evnoise.NoiseStream`). ``background``: optional ``(a_on, a_off)`` per
    level (:func:`pixel_groups`), else the nominal pixel's (:func:`level_background`). ``thresholds``: optional
    ``(eps_on, eps_off)`` per level (:func:`pixel_groups`), else the nominal ones. ``timer``: the levels' regular
    background timer (:func:`chain_timer`) or None: a level with one has tables of photon noise alone (its
    background is the kernel's timer) and the steady state and rate of :func:`with_timer`; without it every
    background is Poisson (also that of parameters with a regular timer: pass ``timer`` for those).

    Returns ``(table, itable, offsets, sizes, rates)``: float rows ``ROW_*`` and integer rows ``ROW_IDX_*`` of
    :mod:`evnoise._kernels.memory` over all levels' states (level ``g``'s at ``offsets[g] .. + sizes[g]``) and
    each level's rate (events/s, both polarities): the stationary rate for up to :data:`EXACT_RATE_LEVELS`
    levels, beyond the rate of the iterated law of the initial state (:data:`ITERATED_STEPS`), which sizes windows
    and buffers and is what a run says it expects.
    Raises :class:`~evnoise.ParameterError` when the tables would pass :data:`MAX_TABLE_STATES` (``refused_why``:
    appended to its message, what the caller cannot do instead). ``done``: optional, called with the number of
    levels whose tables are written, as they are (a progress bar: many chains take about 0.5 ms each).
    """
    from .._kernels import memory as km

    if spans is None:
        which, _, lo, n_states = level_spans(levels)
        ranges = list(zip(lo[which].tolist(), n_states[which].tolist()))
    else:
        ranges = list(spans)
    sizes = np.array([r[1] for r in ranges], dtype=np.int64)
    total = int(sizes.sum())
    if total > MAX_TABLE_STATES:
        raise too_many_states(len(levels), total, refused_why)
    offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
    table = np.empty((km.N_ROWS, total))
    itable = np.empty((2, total), dtype=np.int64)
    rates = np.empty(len(levels))
    dt_s = 1.0 / params.trial_rate_hz
    refr_s = params.refractory_us * 1e-6
    bg_on, bg_off = level_background(levels, params) if background is None else background
    n_levels = len(levels)
    eps_on, eps_off = ((np.full(n_levels, params.eps_pos), np.full(n_levels, params.eps_neg)) if thresholds is None
                       else thresholds)
    exact = len(levels) <= EXACT_RATE_LEVELS

    def chain_of(g):
        return (float(levels[g]), None if spans is None else tuple(ranges[g][:2]), float(eps_on[g]),
                float(eps_off[g]))

    def timed(g):
        return timer is not None and timer[0, g] < math.inf

    def with_background(g, base):  # group g's chain with its background (Poisson, or the timer's per state)
        if timed(g):
            return with_timer(base, float(bg_on[g]), float(bg_off[g]), float(timer[0, g]), float(timer[1, g]))
        return dataclasses.replace(base, a_on=float(bg_on[g]), a_off=float(bg_off[g]))

    def write(g, base):  # group g's rows but the initial law's; returns its tables with its background
        t = with_background(g, base)
        cols = slice(offsets[g], offsets[g] + sizes[g])
        p = t.p_event
        with np.errstate(divide="ignore"):
            # the kernel draws the photon gap from this; a timer's arrivals are its own draws
            table[km.ROW_LOG1M_P, cols] = np.log1p(-(t.photon_event if timed(g) else p))
        table[km.ROW_FRESH_ON, cols] = t.p_fresh_on
        table[km.ROW_FRESH_OFF, cols] = t.p_fresh_off
        table[km.ROW_STORED_ON, cols] = t.stored_on
        table[km.ROW_STORED_OFF, cols] = t.stored_off
        table[km.ROW_CUM_FRESH_ON, cols] = np.cumsum(t.fresh_on)
        table[km.ROW_CUM_FRESH_OFF, cols] = np.cumsum(t.fresh_off)
        table[km.ROW_TAIL, cols] = t.tail
        table[km.ROW_HEAD, cols] = t.head
        itable[km.ROW_IDX_ON, cols] = t.idx_on
        itable[km.ROW_IDX_OFF, cols] = t.idx_off
        quiet = 0.0 if timed(g) else 1.0 - t.photon_event
        table[km.ROW_BG_ON, cols] = quiet * t.a_on
        table[km.ROW_BG_OFF, cols] = quiet * t.a_off
        table[km.ROW_CUM_NONE, cols] = np.cumsum(t.none_fresh)
        table[km.ROW_K_HEAD, cols] = t.k * t.head
        return t, p

    def build(chain):
        return level_tables(chain[0], chain[2], chain[3], params.bias_pr, params.reset_memory, span=chain[1])

    if exact:  # a few levels: each group's stationary law by a linear solve; chains shared across backgrounds
        shared = {}
        for g in range(n_levels):
            chain = chain_of(g)
            base = shared.get(chain)
            if base is None:
                base = shared[chain] = build(chain)
            t, _ = write(g, base)
            stationary = _stationary(t)
            r_on, r_off, *_ = level_statistics(t, dt_s, refr_s, stationary)
            rates[g] = r_on + r_off
            _write_initial(table, slice(offsets[g], offsets[g] + sizes[g]), t, stationary[0], dt_s, refr_s)
        return table, itable, offsets, sizes, rates
    # Many chains: each group's initial law from the iterated embedded chain, the chains of one level and state
    # range in blocks of ITERATE_BLOCK groups (stacked: row i is chain i's own computation, bit for bit, whatever
    # the block). Groups are taken level by level and chain by chain, so a chain's photon-noise tables live only
    # while its groups' block does: the peak holds the final tables and one block's, not every chain's.
    order = sorted(range(n_levels), key=lambda g: (chain_of(g), g))
    alive, block, block_states = {}, [], 0

    def flush():
        chains = [chain for _, chain in block]
        together = alive[chains[0]] if len(set(chains)) == 1 else _stack_tables([alive[c] for c in chains])
        if any(timed(g) for g, _ in block):  # per-state backgrounds, (G, S)
            own = [with_background(g, alive[chain]) for g, chain in block]
            a_on = np.stack([np.broadcast_to(t.a_on, (t.n_states,)) for t in own])
            a_off = np.stack([np.broadcast_to(t.a_off, (t.n_states,)) for t in own])
        else:
            a_on = np.asarray(bg_on, dtype=np.float64)[[g for g, _ in block]][:, None]
            a_off = np.asarray(bg_off, dtype=np.float64)[[g for g, _ in block]][:, None]
        laws = _embedded_iterate(together, ITERATED_STEPS, a_on, a_off)
        for i, (g, chain) in enumerate(block):
            t = with_background(g, alive[chain])
            _write_initial(table, slice(offsets[g], offsets[g] + sizes[g]), t, laws[i], dt_s, refr_s)
            rates[g] = _rate_of_law(t, laws[i], dt_s, refr_s)
        if done is not None:
            done(len(block))
        block.clear()

    for g in order:
        chain = chain_of(g)
        if block and (block[-1][1][:2] != chain[:2] or len(block) == ITERATE_BLOCK
                      or block_states + sizes[g] > ITERATE_BLOCK_STATES):
            flush()
            block_states = 0
            alive = {c: alive[c] for c in (chain,) if c in alive}  # the others are not needed again
        if chain not in alive:
            alive[chain] = build(chain)
        write(g, alive[chain])
        block.append((g, chain))
        block_states += int(sizes[g])
    if block:
        flush()
    return table, itable, offsets, sizes, rates


def _rate_of_law(t: LevelTables, pi, dt_s: float, refr_s: float) -> float:
    """The rate (events/s) of a chain whose embedded law is ``pi``: ``1 / (R + dt sum pi / P)``
    (:func:`level_statistics`' formula; states that never fire left out, 0 when no state fires)."""
    p = t.p_on + t.p_off
    live = p > 0
    trials = float((np.asarray(pi)[live] / p[live]).sum())
    return 1.0 / (refr_s + dt_s * trials) if trials > 0 else 0.0


def _write_initial(table, cols, t: LevelTables, pi, dt_s: float, refr_s: float) -> None:
    """The rows ``ROW_CUM_INIT`` and ``ROW_DEAD`` of one group (:func:`initial_law` of its embedded law ``pi``)."""
    from .._kernels import memory as km

    weight, dead = initial_law(t, pi, dt_s, refr_s)
    table[km.ROW_CUM_INIT, cols] = np.cumsum(weight)
    table[km.ROW_DEAD, cols] = dead


#: Beyond :data:`EXACT_RATE_LEVELS` levels the embedded stationary law of :func:`initial_law` is this many steps
#: of the embedded chain from ``Poisson(lam)`` (each ``O(S log S)``), not a linear solve. So the start of such a run
#: (threshold mismatch, a leak spread, many light levels) is the steady state only up to the chain's mixing:
#: total-variation distance from :func:`_stationary`'s law below 1e-7 for ``k <= 0.9`` at tens of photons per trial,
#: 1e-8 to 5e-5 for ``k = 0.3`` at 640 to 3000, but 5e-3 for ``k = 0.9`` and up to 7e-2 for ``k >= 0.99`` at
#: hundreds to thousands of photons per trial (measured, eps 0.1-0.5; 400 steps would not close the last ones).
ITERATED_STEPS = 40
#: Chains of one light level iterated together (:func:`_embedded_iterate`; ``(block, S)`` arrays): at most this
#: many ...
ITERATE_BLOCK = 2048
#: ... and at most this many states in all (unless one chain alone has more): the block's tables, stacked, and the
#: iteration's arrays take a few hundred bytes per state, so this bounds :func:`kernel_tables`' memory beyond its
#: final tables to about 100 MB.
ITERATE_BLOCK_STATES = 250_000


def _embedded_iterate(t: LevelTables, steps: int, a_on=None, a_off=None) -> np.ndarray:
    """The embedded chain's law after ``steps`` events from a state drawn from ``Poisson(lam)`` (normalised):
    the stationary law of :func:`_stationary` up to the chain's mixing after ``steps`` steps. With ``a_on``,
    ``a_off`` (``(G, 1)``) the laws ``(G, S)`` of ``G`` chains of this level with backgrounds of their own."""
    if a_on is None:
        a_on, a_off = t.a_on, t.a_off
    p_on, p_off = t.probabilities(a_on, a_off)
    p = p_on + p_off
    live = p > 0
    p_safe = np.where(live, p, 1.0)
    x = np.broadcast_to(t.pmf / t.pmf.sum(), np.broadcast_shapes(np.shape(p), np.shape(a_on)[:-1] + (t.n_states,)))
    done = np.zeros(x.shape[:-1] + (1,), dtype=bool)  # a chain whose law vanished: Poisson(lam), as it started
    index = _after_index(t)
    for _ in range(steps):
        w = np.where(live, x / p_safe, 0.0)
        after_on, after_off = _after(t, w, w, a_on, a_off, index)
        x_new = after_on + after_off + np.where(live, 0.0, x)
        total = x_new.sum(axis=-1, keepdims=True)
        done = done | ~(total > 0)
        x = np.where(done, t.pmf / t.pmf.sum(), x_new / np.where(done, 1.0, total))
    return x


def initial_law(t: LevelTables, pi: np.ndarray, dt_s: float, refr_s: float):
    """The steady state of a pixel at a trial start (``t = 0``): ``(weight, dead)`` per state ``m``.

    The pixel is a Markov renewal process: ``pi`` is the embedded chain's stationary law (:func:`_stationary`:
    the state ``m`` after an event, which governs the sojourn to the next event), and a sojourn from state ``m``
    is ``T_m = R + V + dt (G - 1 + U)``: the refractory period ``R``, ``V`` uniform on ``(0, dt]`` up to the
    start of the first eligible trial (the event's time is uniform in its trial), ``G`` geometric with ``P(m)``
    eligible trials, ``U`` the uniform time of the event in its trial; ``E[T_m] = R + dt / P(m)``. Counting the
    trial starts inside sojourns: ``R / dt`` of them (mean; the phase of the event is uniform) fall in the dead
    time, and ``G`` (all of the eligible trials, up to the event's own start) not. So at a trial start:

        P(state m)          = pi_m E[T_m] / sum_j pi_j E[T_j]        (``weight``, unnormalised)
        P(dead | m)         = R / E[T_m] = R P(m) / (R P(m) + dt)    (``dead``)

    given dead, the time since the last event is uniform on ``(0, R)`` (the event's phase is uniform); given
    not dead, the eligible trials left up to and including the event's are again geometric with ``P(m)``
    (length-biased ``G`` and a uniform position in it), i.e. the pixel runs as if its first eligible trial were
    trial 0. A state with ``P(m) = 0`` and ``pi_m > 0`` never fires again: then the steady state is ``pi`` on
    those states (rate 0). ``pi`` summing to 0 falls back to ``Poisson(lam)``.
    """
    p = t.p_on + t.p_off
    live = p > 0
    pi = np.clip(np.asarray(pi, dtype=np.float64), 0.0, None)
    if not pi.sum() > 0:
        pi = t.pmf
    absorbed = (pi > 0) & ~live
    if absorbed.any():
        weight = np.where(absorbed, pi, 0.0)
    else:
        weight = np.where(live, pi * (refr_s / dt_s + 1.0 / np.where(live, p, 1.0)), 0.0)
    dead = np.where(live, refr_s * p / (refr_s * p + dt_s), 0.0)
    return weight / weight.sum(), dead


def level_tables(lam: float, eps_on: float, eps_off: float, bias: float, k: float, span=None, a_on: float = 0.0,
                 a_off: float = 0.0) -> LevelTables:
    """The chain of a pixel with ``lam`` photons per trial, thresholds ``eps_on``, ``eps_off``, bias ``bias``
    (photons per trial) and reset memory ``k`` (module doc); ``span = (lo, n_states)`` widens the states
    beyond :func:`state_range`'s (which it must contain); ``a_on``, ``a_off``: per-trial background arrival
    probabilities (:func:`level_background`)."""
    from .._kernels.memory import fill_counts

    lo, n_s, tail_mass = state_range(lam)
    if span is not None:
        lo, n_s = int(span[0]), int(span[1])
    log_p = np.empty(n_s)
    k_on = np.empty(n_s)
    k_off = np.empty(n_s)
    fill_counts(float(lam), float(lo), n_s, _expm1(eps_on), _expm1(eps_off), float(bias), log_p, k_on, k_off)
    pmf = np.exp(log_p)
    m = lo + np.arange(n_s, dtype=np.float64)
    head = np.cumsum(pmf)
    tail = np.cumsum(pmf[::-1])[::-1]
    tail_ext = np.append(tail, 0.0)
    head_ext = np.append(head, 0.0)  # index -1 reads the 0 at the end
    idx_on = np.searchsorted(m, k_on, side="right").astype(np.int64)
    idx_off = (np.searchsorted(k_off, m, side="left") - 1).astype(np.int64)
    beaten_on = head_ext[np.searchsorted(k_on, m, side="left") - 1]  # P(k_on(N0) < j)
    beaten_off = tail_ext[np.searchsorted(m, k_off, side="right")]  # P(N0 > k_off(j))
    fresh_on = (1.0 - k) * pmf * beaten_on
    fresh_off = (1.0 - k) * pmf * beaten_off
    none_fresh = (1.0 - k) * pmf * np.maximum(head[-1] - beaten_on - beaten_off, 0.0)
    return LevelTables(float(k), lo, n_s, tail_mass, pmf, head, tail, idx_on, idx_off, fresh_on, fresh_off,
                       float(fresh_on.sum()), float(fresh_off.sum()), k * tail_ext[idx_on], k * head_ext[idx_off],
                       none_fresh, float(a_on), float(a_off))


# --------------------------------------------------------------------------------------------------
# closed form
# --------------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class MemoryStatistics:
    """Stationary statistics of static pixels with reset memory (:func:`memory_statistics`).

    Arrays have the shape of ``lux``; ``[a, b]`` indices are polarities (0 OFF, 1 ON, as in events' ``p``).

    Attributes
    ----------
    rate_hz : numpy.ndarray (2, ...)
        Events/s per pixel ``[ON, OFF]`` (refractory period included).
    on_share : numpy.ndarray
        Share of ON events (NaN where there are none).
    transition : numpy.ndarray (2, 2, ...)
        ``transition[a, b]``: probability that an event of polarity ``a`` is followed by one of polarity ``b``.
    p_opposite : numpy.ndarray
        Probability that consecutive events have opposite polarities.
    iei_mean_s : numpy.ndarray (2, 2, ...)
        Mean interval (s) from an event of polarity ``a`` to the next event when that is of polarity ``b``.
    tail_mass : numpy.ndarray
        Poisson mass outside the state range per count (the truncation's bound, module doc).
    """

    rate_hz: np.ndarray
    on_share: np.ndarray
    transition: np.ndarray
    p_opposite: np.ndarray
    iei_mean_s: np.ndarray
    tail_mass: np.ndarray


def _stationary(t: LevelTables):
    """``(pi, p)``: the stationary law of the state at an event's start (embedded chain) and ``P(m)``.

    ``pi`` solves ``pi T = pi``, ``sum pi = 1`` with ``T(m, j) = E(m, j) / P(m)``; a state with ``P(m) = 0``
    never fires again (absorbing). Up to :data:`DENSE_STATES` states a dense solve; beyond, GMRES on
    ``pi - pi T + u sum(pi) = u`` (``u`` uniform; its solution sums to 1 and is stationary) with the chain's
    O(S log S) product (:func:`_after`), checked by its residual (a dense solve if GMRES falls short).
    """
    n_s = t.n_states
    p = t.p_on + t.p_off
    live = p > 0
    p_safe = np.where(live, p, 1.0)

    def step(x):  # the row vector x T
        w = np.where(live, x / p_safe, 0.0)
        a_on, a_off = _after(t, w, w)
        return a_on + a_off + np.where(live, 0.0, x)

    pi = None
    if n_s > DENSE_STATES:
        from scipy.sparse.linalg import LinearOperator, gmres

        u = np.full(n_s, 1.0 / n_s)
        op = LinearOperator((n_s, n_s), matvec=lambda x: x - step(x) + u * x.sum(), dtype=np.float64)
        x, _ = gmres(op, u, rtol=1e-13, atol=0.0, restart=100, maxiter=20)
        x = np.clip(x, 0.0, None)
        if x.sum() > 0:
            x /= x.sum()
            if np.abs(x - step(x)).sum() <= 1e-10:
                pi = x
    if pi is None:
        j = np.arange(n_s)
        # m_t[j, m] = T(m, j): (1 - k) fresh laws + k Poisson(j) on the stored branches' ranges
        m_t = (j[:, None] >= t.idx_on[None, :]).astype(np.float64)
        m_t += j[:, None] <= t.idx_off[None, :]
        m_t *= (t.k * t.pmf)[:, None]
        m_t += (t.fresh_on + t.fresh_off)[:, None]
        if np.any(t.a_on > 0.0) or np.any(t.a_off > 0.0):  # background events store a count of a trial without
            # photon event (a per-state background, the timer's, multiplies by the column m)
            quiet = (j[:, None] > t.idx_off[None, :]) & (j[:, None] < t.idx_on[None, :])
            m_t += (t.a_on + t.a_off) * (t.none_fresh[:, None] + (t.k * t.pmf)[:, None] * quiet)
        m_t[:, live] /= p[live]
        m_t[:, ~live] = 0.0
        m_t[j[~live], j[~live]] = 1.0  # absorbing
        m_t[j, j] -= 1.0
        m_t[-1, :] = 1.0
        rhs = np.zeros(n_s)
        rhs[-1] = 1.0
        try:
            pi = np.linalg.solve(m_t, rhs)
        except np.linalg.LinAlgError:
            pi = np.linalg.lstsq(m_t, rhs, rcond=None)[0]
        pi = np.clip(pi, 0.0, None)
        total = pi.sum()
        pi = pi / total if total > 0 else pi
    return pi, p


def _after(t: LevelTables, w_on, w_off, a_on=None, a_off=None, index=None):
    """Per state ``j``: ``sum_m w_on(m) E_on(m, j)`` and ``sum_m w_off(m) E_off(m, j)`` (``w = pi / P``),
    the stationary laws of the state just after an ON and an OFF event (unnormalised), in O(S log S).

    ``w_on``, ``w_off``: ``(S,)``, or ``(G, S)`` for ``G`` chains of this level that differ in their background
    ``a_on``, ``a_off`` (``(G, 1)``; default: the tables' own) or, tables stacked by :func:`_stack_tables`, in
    their thresholds too. ``index``: :func:`_after_index` of ``t`` (computed here when not given)."""
    k = t.k
    a_on = t.a_on if a_on is None else a_on
    a_off = t.a_off if a_off is None else a_off
    a, b, top, inside, gather = _after_index(t) if index is None else index
    zero = np.zeros(np.shape(w_on)[:-1] + (1,))
    # ON: stored branch reaches j from the m with idx_on(m) <= j (idx_on nondecreasing: a prefix of m)
    c_on = np.concatenate([zero, np.cumsum(w_on, axis=-1)], axis=-1)
    after_on = t.fresh_on * w_on.sum(axis=-1, keepdims=True) + k * t.pmf * gather(c_on, a)
    # OFF: from the m with idx_off(m) >= j (a suffix)
    c_off = np.concatenate([zero, np.cumsum(w_off, axis=-1)], axis=-1)
    after_off = t.fresh_off * w_off.sum(axis=-1, keepdims=True) + k * t.pmf * (c_off[..., -1:] - gather(c_off, b))
    def quiet(c):
        # background in a trial without photon event stores that trial's count j: fresh branch not beaten, or the
        # stored one not beaten, i.e. idx_off(m) < j < idx_on(m): the m in [a, b) (both indices nondecreasing);
        # ``c``: cumulative sums over m of the weights
        return t.none_fresh * c[..., -1:] + k * t.pmf * np.where(inside, gather(c, top) - gather(c, a), 0.0)

    if np.shape(a_on)[-1:] == (t.n_states,) and t.n_states > 1:
        # a background per state m (the regular timer's, :func:`with_timer`): the sums weighted by it
        after_on = after_on + quiet(np.concatenate([zero, np.cumsum(w_on * a_on, axis=-1)], axis=-1))
        after_off = after_off + quiet(np.concatenate([zero, np.cumsum(w_off * a_off, axis=-1)], axis=-1))
    elif np.any(np.asarray(a_on) > 0.0) or np.any(np.asarray(a_off) > 0.0):
        after_on = after_on + a_on * quiet(c_on)
        after_off = after_off + a_off * quiet(c_off)
    return after_on, after_off


def _after_index(t: LevelTables):
    """What :func:`_after` reads of the tables' structure, the same at every step: ``(a, b, top, inside, gather)``,
    the first state past each ``j``'s ON prefix and OFF suffix, and ``gather(c, i)`` = ``c[..., i]`` (per row for
    tables stacked by :func:`_stack_tables`: ``i`` then indexes the flattened ``(G, S + 1)`` cumulative sums)."""
    j = np.arange(t.n_states)
    if t.idx_on.ndim == 1:
        a = np.searchsorted(t.idx_on, j, side="right")
        b = np.searchsorted(t.idx_off, j, side="left")
        gather = _gather_last
    else:
        rows, n_s = t.idx_on.shape
        shift = (np.arange(rows, dtype=np.int64) * (n_s + 3))[:, None]  # rows apart: one sorted array
        query = (j + 1 + shift).ravel()
        start = np.arange(rows, dtype=np.int64)[:, None] * n_s
        # ... and as indices into the flattened (G, S + 1) cumulative sums, where row g's start at g (S + 1)
        row = np.arange(rows, dtype=np.int64)[:, None] * (n_s + 1)
        a = np.searchsorted((t.idx_on + 1 + shift).ravel(), query, side="right").reshape(rows, -1) - start + row
        b = np.searchsorted((t.idx_off + 1 + shift).ravel(), query, side="left").reshape(rows, -1) - start + row
        gather = _gather_flat
    return a, b, np.maximum(b, a), b > a, gather


def _gather_last(c, index):
    return c[..., index]


def _gather_flat(c, index):
    return c.reshape(-1)[index]


#: The fields of :class:`LevelTables` that differ between chains of one light level whose thresholds differ.
_PER_CHAIN = ("idx_on", "idx_off", "fresh_on", "fresh_off", "stored_on", "stored_off", "none_fresh")


def _stack_tables(tables: list) -> LevelTables:
    """Chains of one light level and state range with thresholds of their own as one :class:`LevelTables` whose
    per-chain fields are ``(G, S)`` (``p_fresh_*``: ``(G, 1)``), for :func:`_embedded_iterate`: row ``i`` is
    chain ``i``'s own computation, bit for bit."""
    first = tables[0]
    stacked = {name: np.stack([getattr(t, name) for t in tables]) for name in _PER_CHAIN}
    for name in ("p_fresh_on", "p_fresh_off"):
        stacked[name] = np.array([[getattr(t, name)] for t in tables])
    return dataclasses.replace(first, **stacked)


def level_statistics(t: LevelTables, dt_s: float, refr_s: float, stationary=None):
    """The statistics of one level (trial length ``dt_s``, refractory period ``refr_s``; ``stationary``: the
    ``(pi, p)`` of :func:`_stationary` when the caller has it already).

    Returns ``(rate_on, rate_off, transition (2, 2), iei_mean_s (2, 2), weights (2, 2, S), p)``: events/s, the
    polarity-transition matrix, the mean intervals per pair, and the mixture weights over the state after the
    first event and the per-state event probabilities of the inter-event intervals (:func:`memory_iei_cdf`)."""
    pi, p = _stationary(t) if stationary is None else stationary
    live = p > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(live, pi / np.where(live, p, 1.0), np.where(pi > 0, np.inf, 0.0))  # trials per event
        mean_trials = float(w.sum())
        gap_s = refr_s + dt_s * mean_trials
        rate = 1.0 / gap_s if np.isfinite(gap_s) and gap_s > 0 else 0.0
        w_fin = np.where(np.isfinite(w), w, 0.0)
        share_on = float((w_fin * t.p_on).sum())
        after_on, after_off = _after(t, w_fin, w_fin)
        q_on = np.where(live, t.p_on / np.where(live, p, 1.0), 0.0)
        q_off = np.where(live, t.p_off / np.where(live, p, 1.0), 0.0)
        weights = np.empty((2, 2, t.n_states))
        for a, after in ((1, after_on), (0, after_off)):
            weights[a, 1] = after * q_on
            weights[a, 0] = after * q_off
        mass = weights.sum(axis=2)
        transition = mass / mass.sum(axis=1, keepdims=True)
        if t.gap_on is None:  # the sojourn is independent of the next polarity: E[T | j] = 1 / P(j) trials
            iei = refr_s + dt_s * (weights * np.where(live, 1.0 / np.where(live, p, 1.0), np.inf)).sum(axis=2) / mass
        else:  # the regular timer: E[T 1{next b} | j] of with_timer
            iei = np.empty((2, 2))
            for a, after in ((1, after_on), (0, after_off)):
                for b, gap in ((1, t.gap_on), (0, t.gap_off)):
                    iei[a, b] = refr_s + dt_s * (after * gap).sum() / mass[a, b]
    return rate * share_on, rate * (1.0 - share_on) if rate > 0 else 0.0, transition, iei, weights, p


def memory_statistics(lux, params) -> MemoryStatistics:
    """Stationary rate, ON share, polarity transitions and mean intervals of static pixels with reset memory.

    Parameters
    ----------
    lux : float or array_like
        Illuminance at the sensor in lux (``>= 0``).
    params : NoiseParams or str
        Model parameters (``reset_memory`` may be 0: the memoryless model, evaluated the same way). Threshold
        mismatch is not part of this closed form (nominal thresholds); the background is the nominal pixel's
        (uniform Poisson ``leak_*`` rates; spread factor 1, not hot).

    Returns
    -------
    MemoryStatistics
        Arrays with the shape of ``lux`` (module doc: the model, its Markov renewal closed form and the
        truncation bound). Cost: one linear solve over up to :data:`MAX_STATES` states per distinct level.
    """
    from .._checks import check_params

    params = check_params(params)
    lux = np.asarray(lux, dtype=np.float64)
    lam = np.asarray(params.photons_per_trial(lux), dtype=np.float64)
    levels, inverse = np.unique(lam.ravel(), return_inverse=True)
    out = {name: np.empty((len(levels),) + shape) for name, shape in
           (("rate", (2,)), ("share", ()), ("trans", (2, 2)), ("opp", ()), ("iei", (2, 2)), ("tail", ()))}
    dt_s = 1.0 / params.trial_rate_hz
    refr_s = params.refractory_us * 1e-6
    bg_on, bg_off = level_background(levels, params)
    timer = _nominal_timer(bg_on, bg_off, params)
    for i, level in enumerate(levels):
        t = level_tables(level, params.eps_pos, params.eps_neg, params.bias_pr, params.reset_memory,
                         a_on=bg_on[i], a_off=bg_off[i])
        if timer is not None and timer[0, i] < math.inf:
            t = with_timer(t, float(bg_on[i]), float(bg_off[i]), float(timer[0, i]), float(timer[1, i]))
        r_on, r_off, trans, iei, weights, _ = level_statistics(t, dt_s, refr_s)
        out["rate"][i] = (r_on, r_off)
        total = r_on + r_off
        out["share"][i] = r_on / total if total > 0 else math.nan
        out["trans"][i] = trans
        # a polarity that never fires (an ON-only background in the dark) has no transitions of its own
        opp_on = trans[1, 0] * r_on if r_on > 0 else 0.0
        opp_off = trans[0, 1] * r_off if r_off > 0 else 0.0
        out["opp"][i] = (opp_on + opp_off) / total if total > 0 else math.nan
        out["iei"][i] = iei
        out["tail"][i] = t.tail_mass

    def shaped(a, lead=()):
        a = a[inverse]
        a = np.moveaxis(a, 0, -1) if lead else a
        return a.reshape(lead + lux.shape)

    return MemoryStatistics(shaped(out["rate"], (2,)), shaped(out["share"]), shaped(out["trans"], (2, 2)),
                            shaped(out["opp"]), shaped(out["iei"], (2, 2)), shaped(out["tail"]))


def _timer_iei_cdf(t, x, weights, d: float, log1m_a2: float, share_on: float) -> np.ndarray:
    """:func:`memory_iei_cdf` with the regular timer: ``x`` (trials, ``(T,)``) is ``K - 1 + U1 + U2`` with ``K =
    min(G, L)`` the eligible trials to the next event. Per state ``j`` the cumulative ``C(m) = P(K <= m, photon
    first)`` is ``1 - q^m`` up to the timer's fixed part ``D`` and ``1 - q^D + p q^D (1 - (q c)^(m - D)) / (1 - q c)``
    beyond (``c = 1 - a2``); ``P(K <= m, timer first) = a2 q^(D + 1) (1 - (q c)^(m - D)) / (1 - q c)`` beyond ``D``
    (ties to the photons), mixed over ``D = floor(d)`` and ``floor(d) + 1``. A photon event is ON with the state's
    photon share, a timer event with ``share_on``; the triangular ``U1 + U2`` is added as in the geometric case.
    ``weights``: :func:`level_statistics`' (their sum over the next polarity is the law of the state after ``a``)."""
    p = np.minimum(t.photon_event, 1.0)[:, None]  # (S, 1)
    with np.errstate(divide="ignore", invalid="ignore", under="ignore", over="ignore"):
        live = p > 0
        lq = np.where(p < 1.0, np.log1p(-np.where(p < 1.0, p, 0.0)), -np.inf)
        photon_on = np.where(live, (t.p_fresh_on + t.stored_on)[:, None] / np.where(live, p, 1.0), 0.0)
        one_m_qc = -np.expm1(lq + log1m_a2)
        a2 = -math.expm1(log1m_a2)

        def q_pow(m):  # q^m for whole m >= 0 (q^0 = 1 also where q = 0)
            return np.where(m > 0, np.exp(m * lq), 1.0)

        def cumulative(m):  # (photon first, timer first): P(K <= m, ...) per state, for whole m (T,)
            m = np.maximum(m, 0.0)[None, :]
            photon, timer = 0.0, 0.0
            d0 = math.floor(d)
            for dd, w in ((d0, 1.0 - (d - d0)), (d0 + 1.0, d - d0)):
                if w == 0.0:
                    continue
                beyond = m > dd
                k = np.where(beyond, m - dd, 0.0)
                rest = np.where(beyond, -np.expm1(k * (lq + log1m_a2)) / one_m_qc, 0.0)  # sum of (q c)^h, h < k
                q_d = q_pow(np.float64(dd))
                photon = photon + w * np.where(beyond, -np.expm1(dd * lq) + p * q_d * rest, -np.expm1(m * lq))
                timer = timer + w * np.where(beyond, a2 * q_d * np.where(p < 1.0, np.exp(lq), 0.0) * rest, 0.0)
            return np.where(m > 0, photon, 0.0), np.where(m > 0, timer, 0.0)

        n = np.floor(x)
        f = x - n
        f1 = 1.0 - 0.5 * (1.0 - f) ** 2  # P(U1 + U2 <= 1 + f)
        f0 = 0.5 * f**2  # P(U1 + U2 <= f)
        c_prev, c_n, c_next = cumulative(n - 1.0), cumulative(n), cumulative(n + 1.0)
        cdf = [np.where(x[None, :] < 0, 0.0, c_prev[i] + (c_n[i] - c_prev[i]) * f1 + (c_next[i] - c_n[i]) * f0)
               for i in (0, 1)]  # (S, T) photon first, timer first
        after = weights.sum(axis=1)  # (2, S): the law of the state after an event of polarity a (unnormalised)
        out = np.empty((2, 2, x.size))
        for b, photon_share, timer_share in ((1, photon_on, share_on), (0, 1.0 - photon_on, 1.0 - share_on)):
            per_state = photon_share * cdf[0] + timer_share * cdf[1]
            out[:, b] = np.einsum("as,st->at", after, per_state) / weights[:, b].sum(axis=1)[:, None]
    return np.clip(out, 0.0, 1.0)


def _nominal_timer(bg_on, bg_off, params):
    """:func:`chain_timer` of the nominal pixel (not hot: ``leak_regularity``) at levels with these backgrounds."""
    if not params.regular_background:
        return None
    return chain_timer(bg_on, bg_off, params.leak_regularity, params)


def memory_iei_cdf(t_s, lux: float, params) -> np.ndarray:
    """CDF of the interval from an event of polarity ``a`` to the next when that is of polarity ``b``.

    Returns ``(2, 2, len(t_s))``: ``[a, b]`` polarities (0 OFF, 1 ON), at times ``t_s`` (seconds, exact up to the
    microsecond rounding of emitted timestamps). Given the state ``j`` after the first event the interval is
    ``R + dt (G - 1 + U1 + U2)``, ``G`` geometric with ``P(j)``, ``U1``, ``U2`` uniform (the uniform times of the two
    events in their trials; the refractory period's mean skip is exactly ``R``), independent of the next
    polarity; the CDF is the mixture over ``j`` weighted by the stationary law of the states after ``a``
    events and ``P(b | j)``. With the regular background timer ``G`` is ``min(G, L)`` and the next polarity
    depends on which came first (:func:`_timer_iei_cdf`).
    """
    from .._checks import check_params

    params = check_params(params)
    lam = float(params.photons_per_trial(float(lux)))
    bg_on, bg_off = level_background([lam], params)
    timer = _nominal_timer(bg_on, bg_off, params)
    t = level_tables(lam, params.eps_pos, params.eps_neg, params.bias_pr, params.reset_memory, a_on=bg_on[0],
                     a_off=bg_off[0])
    timed = timer is not None and timer[0, 0] < math.inf
    if timed:
        t = with_timer(t, float(bg_on[0]), float(bg_off[0]), float(timer[0, 0]), float(timer[1, 0]))
    dt_s = 1.0 / params.trial_rate_hz
    refr_s = params.refractory_us * 1e-6
    *_, weights, p = level_statistics(t, dt_s, refr_s)
    x = (np.atleast_1d(np.asarray(t_s, dtype=np.float64)) - refr_s) / dt_s  # G - 1 + U1 + U2
    if timed:
        return _timer_iei_cdf(t, x, weights, float(timer[0, 0]), float(timer[1, 0]), float(timer[2, 0]))
    n = np.floor(x)
    f = x - n
    q = 1.0 - p
    with np.errstate(divide="ignore", invalid="ignore", under="ignore"):
        lq = np.log1p(-np.minimum(p, 1.0))[:, None]  # (S, 1)
        qn1 = np.exp(np.where(n[None, :] >= 1, (n[None, :] - 1.0) * lq, 0.0))  # q^(n - 1)
        qn = np.where(n[None, :] >= 0, qn1 * np.where(n[None, :] >= 1, q[:, None], 1.0), 0.0)  # q^n
        pp = p[:, None]
        cdf = (np.where(n[None, :] >= 1, 1.0 - qn1, 0.0)
               + np.where(n[None, :] >= 1, pp * qn1 * (1.0 - 0.5 * (1.0 - f[None, :]) ** 2), 0.0)
               + np.where(n[None, :] >= 0, pp * qn * 0.5 * f[None, :] ** 2, 0.0))
        cdf = np.where(x[None, :] < 0, 0.0, cdf)
        mass = weights.sum(axis=2)
        out = np.einsum("abs,st->abt", weights, cdf) / mass[:, :, None]
    return np.clip(out, 0.0, 1.0)
