"""Counts of pixels with their own thresholds, decided by brackets (issue 33, item 4).

With threshold mismatch every pixel of a static scene has its own per-trial probabilities, and
evaluating the closed form once per pixel costs one to two microseconds each (a sum over photon
counts), twenty times the rest of :func:`evnoise.sample_counts`. But a count does not need the
probability itself, only enough of it to decide the draws:

- on its fixed random stream a pixel's event sequence is a monotone function of its renewal inputs:
  each gap ``floor(log u / log1p(-p)) + 1`` shrinks as ``p`` grows, the refractory period's first
  eligible trial follows the previous event's time monotonically, and each polarity test ``u < q_on``
  flips one way as ``q_on`` grows. So when the renewal kernel's draws at both ends of a bracket of the
  pixel's ``(p, q_on)`` give the same ON and OFF counts, every value in between gives them too, draw for
  draw: the count is decided exactly, and equals what the per-pixel evaluation gives. Both ends are run
  in one pass over the stream, in lockstep (while both have their events inside the window they take the
  same draws), stopping as soon as they part (:func:`evnoise._kernels.mismatch.dual_counts`); the
  stream is seeded in the pass from the pixel's flat index, as :class:`evnoise._engine.PixelState` seeds it;
- ``p = sum_m pmf(m) P(N > k(m))`` with ``k(m) = m + floor(c (m + b))``, ``c = expm1(eps)``, falls as the
  threshold grows, and so does each ``k(m)`` as computed in floating point (a product and a floor, both
  monotone). On a lattice ``eps_j = j h`` (``h`` a fraction of the thresholds' spread, over
  :data:`LATTICE_SIGMAS` deviations either side of their mean) the sums at the two lattice points around
  a pixel's threshold bracket its ``p``: each light level tabulates ``pmf`` and the tails ``P(N > k)`` once
  and sums over a photon-count window whose left-out probability is bounded (and added to the upper ends)
  (:func:`evnoise._kernels.mismatch.level_sums`);
- a pixel whose two lattice ends part (a few per cent), or whose threshold lies beyond the lattice, takes
  its own sums from the same tables, at its own ``c`` (moved by a relative 1e-13 either way, for two
  libraries' ``expm1``): a bracket of relative width ~1e-9 that decides all but about one pixel in 1e8
  events. Those, thresholds beyond the tables (:data:`TABLE_SIGMAS`) and levels too bright to tabulate
  (millions of photons per trial) are evaluated by the closed form and run by the renewal kernel on their
  own streams (a pixel's stream is keyed by its flat index, so running a subset changes nothing). The
  closed form evaluated on such a subset sums each pixel's ``p`` on its own path (equal to the whole
  field's to ~1e-13, not always bit for bit), so a count there could differ from the plain path's only if
  a draw fell within ~1e-13 of one of its decisions: with the expected handful of such pixels per frame
  (none in the benchmark), never seen.

The ends are widened by :data:`~evnoise._kernels.mismatch.BRACKET_WIDEN` (relative) so that the rounding
of two separately computed sums (a few ulps times their number of terms, below 1e-13) cannot put a
pixel's computed value outside them; with background activity the ends combine both polarities' brackets
through the background's arrival shares, in which ``P_on`` grows with ``p_on`` and falls with ``p_off``.
Only used where it applies exactly (no background map of pixels' own, no regular timer, light levels
shared by many pixels); elsewhere :func:`evnoise.sample_counts` evaluates every pixel.
"""

from __future__ import annotations

import math
import threading

import numpy as np

from . import terms
from ._pool import map_in_threads

#: lattice points per standard deviation of the thresholds (finer: fewer pixels take their own sums, more sums
#: at lattice points)
LATTICE_PER_SIGMA = 16
#: the bracket is used only where each light level is shared by at least this many pixels on average
MIN_PIXELS_PER_LEVEL = 64
#: below this expected share of pixels decided by the lattice (many events per pixel: brackets too wide) the
#: plain path runs
MIN_DECIDED_SHARE = 0.5
#: the lattice spans the thresholds' range, at most this many standard deviations either side of their mean
LATTICE_SIGMAS = 3.5
#: the level tables cover the thresholds up to this many standard deviations either side of their mean
TABLE_SIGMAS = 8.0
#: the thresholds' spread is estimated on every this-many-th pixel
SPREAD_STRIDE = 8
#: the share of pixels the lattice decides is estimated on every this-many-th pixel
SHARE_STRIDE = 64
#: levels per task of the lattice sums (tasks are shared out among the threads as they finish)
LEVELS_PER_TASK = 8
#: relative margin on the extreme thresholds a level's table is built for (beyond the sums' own C_MARGIN)
_TABLE_C_MARGIN = 4e-13


def _background_shares(levels, params):
    """Per light level, the background's arrival shares ``(a_on, a_off)``, zeros without background.

    :func:`evnoise.background.with_background` is affine in the photon-noise probabilities,
    ``P = p + (1 - p_on - p_off) a``; its shares are what it returns at ``p_on = p_off = 0``."""
    if not terms.background_on(params):
        return np.zeros(levels.size), np.zeros(levels.size)
    from .background import lux_of_photons, with_background

    zero = np.zeros(levels.size)
    a_on, a_off = with_background(zero, zero, lux_of_photons(levels, params), params, None, None)
    return (np.ascontiguousarray(np.broadcast_to(a_on, levels.shape), dtype=np.float64),
            np.ascontiguousarray(np.broadcast_to(a_off, levels.shape), dtype=np.float64))


def _level_count(lam):
    from ._kernels.levels import find_levels

    return find_levels(lam, lam.size // MIN_PIXELS_PER_LEVEL)


#: what the last :func:`applies` of this thread found (its arrays, levels, thresholds' ranges), for the
#: :func:`bracketed_counts` that follows it on the same arrays
_last = threading.local()


def applies(lam, params, thresholds, background) -> bool:
    """Whether :func:`bracketed_counts` applies: per-pixel thresholds that differ in both polarities, no background
    maps, no regular timer, and light levels each shared by many pixels on average."""
    _last.found = None
    if background is not None or terms.regular_timer(params) or lam.size < 2 * MIN_PIXELS_PER_LEVEL:
        return False
    eps = [np.asarray(t) for t in thresholds]
    if any(e.size != lam.size for e in eps):
        return False
    ranges = []
    for e in eps:  # each polarity's lattice needs a spread, and positive thresholds
        lo, hi = e.min(), e.max()
        if not (lo > 0 and lo != hi and np.isfinite(hi)):
            return False
        ranges.append((float(lo), float(hi)))
    levels = _level_count(np.ravel(lam))
    if levels is None:
        return False
    _last.found = (lam, *thresholds, levels, ranges)
    return True


def _found(lam, thresholds):
    """``(levels, ranges)`` that :func:`applies` found for these very arrays, or None."""
    found = getattr(_last, "found", None)
    _last.found = None
    if found is None or found[0] is not lam or any(a is not b for a, b in zip(found[1:3], thresholds)):
        return None
    return found[3], found[4]


def _lattice(eps, e_min, e_max):
    """One polarity's lattice ``(h, j_first, n_cells, t_lo, t_hi)``: step ``h`` (:data:`LATTICE_PER_SIGMA` per
    standard deviation of the thresholds, estimated on every :data:`SPREAD_STRIDE`-th pixel), cells ``j_first <= j <
    j_first + n_cells`` over the thresholds' range clipped to :data:`LATTICE_SIGMAS` deviations around their mean
    (thresholds beyond take their own sums), and the range ``[t_lo, t_hi]`` of thresholds the level tables cover
    (every lattice point, and the thresholds up to :data:`TABLE_SIGMAS` deviations from the mean; one far beyond,
    which would lengthen every level's table, takes the closed form); None without a spread."""
    sub = eps[::SPREAD_STRIDE]
    mean, sd = float(sub.mean()), float(sub.std())
    if not sd > 0:
        mean, sd = float(eps.mean()), float(eps.std())
        if not sd > 0:
            return None
    h = sd / LATTICE_PER_SIGMA
    lo = max(e_min, mean - LATTICE_SIGMAS * sd)
    hi = min(e_max, mean + LATTICE_SIGMAS * sd)
    j_first = max(math.floor(lo / h) - 1.0, 0.0)
    n_cells = int(math.floor(hi / h) + 2.0 - j_first)
    t_lo = min(max(e_min, mean - TABLE_SIGMAS * sd), j_first * h)
    t_hi = max(min(e_max, mean + TABLE_SIGMAS * sd), (j_first + n_cells) * h)
    return h, j_first, n_cells, t_lo, t_hi


def bracketed_counts(lam, params, thresholds, key, duration_us: int, width: int, threads: int):
    """``(on, off, evaluated, exact)``: ON and OFF counts (flat, int64) of static pixels with photon counts
    ``lam`` per trial and per-pixel ``thresholds = (eps_on, eps_off)`` over ``duration_us``, bit for bit the counts
    of the renewal kernel run on every pixel's own closed-form inputs (module doc); how many pixels needed their
    own sums, and how many of those the closed form. None when the lattice would leave most pixels undecided
    (:data:`MIN_DECIDED_SHARE`: many events per pixel), for the caller's plain path. Check :func:`applies`
    first."""
    from ._engine import PixelState, map_chunks, renewal_step, static_inputs
    from ._kernels import mismatch as K

    n = lam.size
    found = _found(lam, thresholds)
    eps = [np.ascontiguousarray(t, dtype=np.float64).ravel() for t in thresholds]
    if found is None:  # not just checked by applies: find the levels and ranges here
        found = (_level_count(np.ravel(lam)), [(float(e.min()), float(e.max())) for e in eps])
        if found[0] is None:
            return None
    (levels, group), ranges = found
    n_levels = levels.size
    b = float(params.bias_pr)
    lattices = [_lattice(e, *r) for e, r in zip(eps, ranges)]
    if None in lattices:
        return None
    h = np.array([lat[0] for lat in lattices])
    j_first = np.array([lat[1] for lat in lattices])
    n_cells = np.array([lat[2] for lat in lattices], dtype=np.int64)
    # each level's table covers every threshold and lattice point, a little widened (the sums move c by C_MARGIN)
    c_min = np.expm1([lat[3] for lat in lattices]) * (1.0 - _TABLE_C_MARGIN)
    c_max = np.expm1([lat[4] for lat in lattices]) * (1.0 + _TABLE_C_MARGIN)
    geo = np.zeros((n_levels, 5), dtype=np.int64)
    t_tail = np.zeros((n_levels, 2))
    K.levels_geometry(levels, b, np.tile(c_min, (n_levels, 1)), np.tile(c_max, (n_levels, 1)), K.WINDOW_ATOL, geo,
                      t_tail)
    sizes = np.where(geo[:, 0] == K.LEVEL_TABLE, geo[:, 4] - geo[:, 1] + 1, 0)
    tab_off = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    pmf = np.empty(int(tab_off[-1]))
    sf = np.empty(int(tab_off[-1]))
    n_pts = int(n_cells.max()) + 1
    s_up = np.zeros((2, n_levels, n_pts))
    s_dn = np.zeros((2, n_levels, n_pts))
    kind = np.ascontiguousarray(geo[:, 0])
    tasks = [(g, min(g + LEVELS_PER_TASK, n_levels)) for g in range(0, n_levels, LEVELS_PER_TASK)]
    map_in_threads(lambda lo, hi: K.level_sums(lo, hi, levels, b, kind, geo, tab_off, pmf, sf, h, j_first, n_cells,
                                           K.WINDOW_ATOL, s_up, s_dn), tasks, threads)
    # each cell's bracket (upper, lower) in one place, for the pixels' lookups
    cells = np.zeros((2, n_levels, n_pts - 1, 2))
    cells[..., 0] = (s_up[:, :, :-1] + t_tail.T[:, :, None]) * (1.0 + K.BRACKET_WIDEN) + K.BRACKET_ABS
    cells[..., 1] = np.where(s_dn[:, :, 1:] > 1e-280, s_dn[:, :, 1:] * (1.0 - K.BRACKET_WIDEN), 0.0)
    a_on, a_off = _background_shares(levels, params)
    # a pixel is decided unless an event falls between its two ends: about exp(-trials (p_high - p_low)), estimated
    # on every SHARE_STRIDE-th pixel
    trials = duration_us / params.trial_us
    g = group[::SHARE_STRIDE]
    width_sum = np.zeros(g.size)
    for q, e in enumerate(eps):
        jj = np.floor(e[::SHARE_STRIDE] / h[q]) - j_first[q]
        inside = (jj >= 0) & (jj < n_cells[q])
        jj = np.where(inside, jj, 0).astype(np.int64)
        width_sum += np.where(inside, cells[q, g, jj, 0] - cells[q, g, jj, 1], 1.0)
    quiet = np.clip(1.0 - a_on[g] - a_off[g], 0.0, 1.0)
    if float(np.mean(np.exp(-trials * quiet * width_sum))) < MIN_DECIDED_SHARE:
        return None
    on = np.empty(n, dtype=np.int64)
    off = np.empty(n, dtype=np.int64)
    status = np.empty(n, dtype=np.uint8)
    inv_h = 1.0 / h
    key = np.ascontiguousarray(key, dtype=np.uint64)

    def run(lo, hi):
        return K.bracket_counts(lo, group[lo:hi], eps[0][lo:hi], eps[1][lo:hi], key, inv_h, h, j_first, n_cells,
                                cells, kind, geo, t_tail, tab_off, pmf, sf, b, a_on, a_off, float(params.trial_us),
                                float(params.refractory_us), float(duration_us), K.WINDOW_ATOL, on[lo:hi],
                                off[lo:hi], status[lo:hi])

    found = map_chunks(run, n, threads)
    evaluated = sum(f[0] for f in found)
    left = sum(f[1] for f in found)
    todo = np.flatnonzero(status == K.UNDECIDED) if left else np.zeros(0, dtype=np.int64)
    if todo.size:
        log1m_p, q_on, _, _ = static_inputs(lam[todo], params, eps[0][todo], eps[1][todo], None)
        parts = renewal_step(PixelState(todo, key, threads), width, log1m_p, q_on, params.trial_us,
                             params.refractory_us, 0, float(duration_us), math.inf, 0, threads, store=False)
        on[todo] = np.concatenate([p[4] for p in parts])
        off[todo] = np.concatenate([p[5] for p in parts])
    return on, off, evaluated, int(todo.size)
