"""Reset-memory chains of a run's pixels in the trial tier (:mod:`evnoise.terms.memory`): their tables where they
fit :data:`~evnoise.terms.memory.MAX_TABLE_STATES` (:class:`MemoryChains`), else each chain's start computed on its
own (:class:`OwnChainStarts`). Shared by :mod:`evnoise.simulate` (videos, still scenes beyond the table budget) and
:class:`evnoise.NoiseStream`."""

from __future__ import annotations

import threading

import numpy as np

from . import terms
from ._engine import PixelState, map_chunks, progress_bar


class MemoryChains:
    """The reset-memory chains of a changing scene's pixels (:mod:`evnoise.terms.memory`): each pixel's chain at
    the first frame's light (the scene before the video starts: each pixel's stored count is drawn from its steady
    state there; the first frame's distinct values, not the interpolated first trial's, so that pixels share chains
    as in a still scene), grouped as :func:`~evnoise.terms.memory.pixel_groups` does over the whole sensor.
    ``group`` (per flat pixel) indexes ``tables`` (:func:`~evnoise.terms.memory.kernel_tables`, without the rates)
    and ``rates`` (events/s)."""

    def __init__(self, lam_start, params, bg, eps_on, eps_off, plan=None):
        from .terms.memory import level_spans, still_chains

        levels, self.group, self.tables, self.rates, self.timer = still_chains(lam_start, params, bg,
                                                                               (eps_on, eps_off), plan)
        which, _, lo, _ = level_spans(levels)  # chains share light levels
        self.lo = lo[which].astype(np.float64)

    def start_trials(self, state: PixelState, group, dt, refr_us, threads, bg_rows, lam_first, model,
                     progress=False):
        """The trial tier's pixels ``state`` (chains ``group``, background rows ``bg_rows`` of the trial kernel,
        photons per trial ``lam_first`` at trial 0, its ``model``: :data:`evnoise.terms.MODEL`) start in their
        steady state: stored count, the dead time of a last event before ``t = 0``, the regular timer's first
        arrival (:func:`evnoise._kernels.memory.initial_stored`). ``progress``: not used (the tables are built)."""
        from ._kernels.memory import initial_stored

        table, _, offsets, sizes = self.tables
        timer = np.zeros((3, 0)) if self.timer is None else self.timer
        lux_per_photon, dark_lux, regularity = (float(model[terms.MODEL.index(name)])
                                                for name in ("lux_per_photon", "dark_lux", "regularity"))

        def run(lo, hi):
            initial_stored(state.states[lo:hi], state.fstate[lo:hi], group[lo:hi], offsets, sizes, self.lo, table,
                           float(dt), float(refr_us), timer, np.ascontiguousarray(bg_rows[:, lo:hi]),
                           np.ascontiguousarray(lam_first[lo:hi]), lux_per_photon, dark_lux, regularity)

        map_chunks(run, state.pix.size, threads)


class OwnChainStarts:
    """Reset-memory chains too many for tables (their states pass :data:`~evnoise.terms.memory.MAX_TABLE_STATES`:
    a large sensor with threshold mismatch has nearly a chain per pixel). Their pixels all run in the trial tier,
    which needs of a chain only its start: computed chain by chain when the pixels start and not kept
    (:mod:`evnoise._kernels.memory_start`: the law the tables would give, to rounding, and the same draws, so the
    events are those of the table path's trial tier, to rounding). ``group``, ``rates`` as :class:`MemoryChains`';
    no ``tables``. ``plan``:
    :func:`~evnoise.terms.memory.chain_plan`'s (without a regular timer: refused by the caller)."""

    tables = None
    timer = None

    def __init__(self, params, plan, threads):
        from ._kernels.memory_start import chain_rates, level_pmf
        from .terms.memory import ITERATED_STEPS, level_spans, threshold_factors

        (levels, a_on, a_off, _, self.group, (eps_on, eps_off)), _, _ = plan
        level, lam, lo, n_s = level_spans(levels)
        at = np.concatenate([[0], np.cumsum(n_s)[:-1]]).astype(np.int64)
        pmf = np.empty(int(n_s.sum()))
        for lv in range(lam.size):  # each light level's Poisson pmf once, for all its chains
            level_pmf(float(lam[lv]), float(lo[lv]), int(n_s[lv]), pmf[at[lv]:at[lv] + n_s[lv]])
        self._levels = (pmf, level, lo.astype(np.float64), n_s, at)
        self._chains = tuple(np.ascontiguousarray(a, dtype=np.float64) for a in (threshold_factors(eps_on),
                                                                                 threshold_factors(eps_off), a_on,
                                                                                 a_off))
        self._model = (float(params.bias_pr), float(params.reset_memory), 1.0 / params.trial_rate_hz,
                       params.refractory_us * 1e-6)
        self.rates = np.empty(len(levels))
        b, k, dt_s, refr_s = self._model
        by_level = np.argsort(level, kind="stable").astype(np.int64)  # a level's chains together

        def run(i, j):  # the chains by_level[i:j]
            chain_rates(*self._levels, *self._chains, b, k, dt_s, refr_s, ITERATED_STEPS, by_level[i:j], self.rates)

        map_chunks(run, len(levels), threads)

    def start_trials(self, state: PixelState, group, dt, refr_us, threads, bg_rows, lam_first, model,
                     progress=False):
        """As :meth:`MemoryChains.start_trials` (no regular timer here); ``progress``: a bar over the chains (the
        starts of a megapixel sensor take tens of seconds)."""
        from ._kernels.memory_start import start_pixels
        from .terms.memory import ITERATED_STEPS

        # pixels by (light level, chain): a chain's pixels together, a level's chains together (iterated together)
        level = self._levels[1]
        group = np.asarray(group, dtype=np.int64)
        order = np.lexsort((group, level[group])).astype(np.int64)
        by_chain = group[order]
        first = np.flatnonzero(np.concatenate([[True], by_chain[1:] != by_chain[:-1]])) if order.size else order
        chains = by_chain[first]
        first = np.append(first, order.size).astype(np.int64)
        b, k, dt_s, refr_s = self._model

        bar = progress_bar(int(chains.size), progress, "memory starts", unit="chains")
        lock = threading.Lock()  # chunks finish in worker threads

        def run(i, j):  # the pixels of chains[i:j]
            start_pixels(*self._levels, *self._chains, b, k, ITERATED_STEPS, dt_s, refr_s, float(dt), float(refr_us),
                         chains[i:j], first[i:j + 1], order, state.states, state.fstate)
            if bar is not None:
                with lock:
                    bar.update(j - i)

        map_chunks(run, chains.size, threads)
        if bar is not None:
            bar.close()


#: Why chains too many for tables cannot run with the regular background timer.
TIMER_NEEDS_TABLES = (" and they have the regular background timer (leak_regularity or hot_pixel_regularity > 0), "
                      "which the trial tier's start without tables does not cover")
#: Why a scene whose chains are too many for tables cannot run with ``method="renewal"``.
RENEWAL_NEEDS_TABLES = (" for the renewal tier (method='auto' or 'trials' runs them trial by trial, without "
                        "tables)")


def memory_chains(lam_start, params, bg, eps_on, eps_off, threads, plan=None, renewal=False):
    """The reset-memory chains of a run's pixels at ``lam_start``: :class:`MemoryChains` (tables) where their states
    fit :data:`~evnoise.terms.memory.MAX_TABLE_STATES`, else :class:`OwnChainStarts` (every pixel in the trial
    tier), or a :class:`~evnoise.ParameterError` when the chains also have the regular timer or the caller asked for
    the renewal tier (``renewal``)."""
    from .terms.memory import MAX_TABLE_STATES, chain_plan, too_many_states

    plan = chain_plan(lam_start, params, bg, (eps_on, eps_off)) if plan is None else plan
    if plan[2] <= MAX_TABLE_STATES:
        return MemoryChains(lam_start, params, bg, eps_on, eps_off, plan)
    if renewal:
        raise too_many_states(len(plan[0][0]), plan[2], RENEWAL_NEEDS_TABLES)
    if plan[1] is not None:
        raise too_many_states(len(plan[0][0]), plan[2], TIMER_NEEDS_TABLES)
    return OwnChainStarts(params, plan, threads)
