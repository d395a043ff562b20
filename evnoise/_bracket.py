"""Counts of pixels with their own thresholds, decided by brackets (issue 33, item 4).

With threshold mismatch every pixel of a static scene has its own per-trial probabilities, and
evaluating the closed form once per pixel costs about a microsecond each (a sum over photon
counts), twenty times the rest of :func:`evnoise.sample_counts`. But a count does not need the
probability itself, only enough of it to decide the draws:

- ``p`` is a survival function of the threshold (non-increasing in ``eps``), so on a lattice
  ``eps_j = j h`` the values at the two lattice points around a pixel's threshold bracket its ``p``
  (``h`` a fraction of the thresholds' spread; the lattice is shared by every pixel of a light level,
  so its values cost one closed-form evaluation per (level, lattice point), not per pixel);
- on its fixed random stream a pixel's event sequence is a monotone function of its renewal inputs:
  each gap ``floor(log u / log1p(-p)) + 1`` shrinks as ``p`` grows, the refractory period's first
  eligible trial follows the previous event's time monotonically, and each polarity test ``u < q_on``
  flips one way as ``q_on`` grows. So when the renewal kernel run at both ends of the bracket (same
  streams) gives the same ON and OFF counts, every ``p`` in between gives them too, draw for draw:
  the count is decided exactly, and equals what the per-pixel evaluation gives;
- the pixels whose two ends differ (a few per cent) are evaluated exactly and run again on their own
  streams (a pixel's stream is keyed by its flat index, so running a subset changes nothing).

The brackets are widened by :data:`WIDEN` (relative) so that the rounding of two separately computed
sums (a few ulps times their number of terms, below 1e-13) cannot put a pixel's computed value
outside them; with background activity the ends combine both polarities' brackets through the
background's arrival shares, in which ``P_on`` grows with ``p_on`` and falls with ``p_off``. Only used
where it applies exactly (no background map of pixels' own, no regular timer, light levels shared by
many pixels); elsewhere :func:`evnoise.sample_counts` evaluates every pixel.
"""

from __future__ import annotations

import math

import numpy as np

from . import terms
from ._engine import PixelState, renewal_step

#: lattice points per standard deviation of the thresholds (finer: fewer undecided pixels, more lattice values)
LATTICE_PER_SIGMA = 16
#: relative widening of every bracket end (far above the rounding of the closed form's sums)
WIDEN = 1e-9
#: the bracket is used only where each light level is shared by at least this many pixels on average
MIN_PIXELS_PER_LEVEL = 64
#: below this expected share of decided pixels (many events per pixel: brackets too wide) the plain path runs
MIN_DECIDED_SHARE = 0.5


def _lattice_index(eps: np.ndarray, h: float) -> np.ndarray:
    """``j`` with ``j h <= eps <= (j + 1) h`` in floating point (the products as computed)."""
    j = np.floor(eps / h)
    for _ in range(4):  # the division may round across a lattice point: step back inside
        low = j * h > eps
        high = (j + 1.0) * h < eps
        if not (low.any() or high.any()):
            break
        j = j - low + high
    return j


def _lattice_probabilities(levels, group, j, h, bias):
    """Photon-noise ``p`` at the lattice points ``j h`` and ``(j + 1) h`` of each pixel's level: ``(p_at_j,
    p_at_j1)``, evaluated once per distinct (level, lattice point)."""
    from .model import event_probability

    n_lattice = int(j.max() - j.min()) + 2
    j0 = j.min()
    code_j = (group * n_lattice + (j - j0)).astype(np.int64)  # (level, lattice point) -> one integer
    used = np.zeros(int(group.max() + 1) * n_lattice + 1, dtype=bool)  # dense: no sort of a million codes
    used[code_j] = True
    used[code_j + 1] = True
    nodes = np.flatnonzero(used)
    slot = np.cumsum(used) - 1  # code -> its node's position
    # the point 0 stands for its limit from above, p(0+) >= p(eps) (the threshold counts there are those of
    # any eps > 0 small enough, e.g. the smallest positive double's)
    node_eps = np.maximum((nodes % n_lattice + j0) * h, np.finfo(np.float64).tiny)
    values = event_probability(levels[nodes // n_lattice], node_eps, bias)
    values = np.concatenate([values[slot[code_j]], values[slot[code_j + 1]]])
    return values[: j.size], values[j.size:]


def _background_shares(levels, group, params):
    """Per pixel, the background's arrival shares ``(a_on, a_off)`` (evaluated once per light level), or None.

    :func:`evnoise.background.with_background` is affine in the photon-noise probabilities,
    ``P = p + (1 - p_on - p_off) a``; its shares are what it returns at ``p_on = p_off = 0``."""
    if not terms.background_on(params):
        return None
    from .background import lux_of_photons, with_background

    zero = np.zeros(levels.size)
    a_on, a_off = with_background(zero, zero, lux_of_photons(levels, params), params, None, None)
    return a_on[group], a_off[group]


def _ends(shares, on_bracket, off_bracket):
    """The renewal inputs at the two ends: ``((log1m_p, q_on) low, (log1m_p, q_on) high, sure)``; ``sure``
    marks pixels whose upper end fires at every trial (their draws differ in kind: left undecided)."""
    (on_lo, on_hi), (off_lo, off_hi) = on_bracket, off_bracket
    corners = []
    for a, b in ((on_lo, off_lo), (on_hi, off_hi), (on_hi, off_lo), (on_lo, off_hi)):
        if shares is not None:  # with_background's affine form (see _background_shares)
            quiet = 1.0 - a - b
            a, b = a + quiet * shares[0], b + quiet * shares[1]
        corners.append((a, b))
    totals = [a + b for a, b in corners]
    p_low = np.minimum.reduce(totals) * (1.0 - WIDEN)
    p_high = np.maximum.reduce(totals) * (1.0 + WIDEN)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = [np.where(t > 0, a / np.where(t > 0, t, 1.0), 0.5) for (a, _), t in zip(corners, totals)]
    q_low = np.clip(np.minimum.reduce(q) * (1.0 - WIDEN), 0.0, 1.0)
    q_high = np.clip(np.maximum.reduce(q) * (1.0 + WIDEN), 0.0, 1.0)
    sure = p_high >= 1.0
    low = (np.log1p(-np.where(sure, 0.0, p_low)), q_low)
    high = (np.log1p(-np.where(sure, 0.0, p_high)), q_high)
    return low, high, sure


def _counts(state, width, log1m_p, q_on, params, duration_us, threads):
    parts = renewal_step(state, width, log1m_p, q_on, params.trial_us, params.refractory_us, 0, float(duration_us),
                         math.inf, 0, threads, store=False)
    return np.concatenate([p[4] for p in parts]), np.concatenate([p[5] for p in parts])


def applies(lam, params, thresholds, background) -> bool:
    """Whether :func:`bracketed_counts` applies: per-pixel thresholds that differ in both polarities, no background
    maps, no regular timer, and light levels each shared by many pixels on average."""
    if background is not None or terms.regular_timer(params) or lam.size < 2 * MIN_PIXELS_PER_LEVEL:
        return False
    eps = [np.asarray(t) for t in thresholds]
    if any(e.size != lam.size or e.min() == e.max() for e in eps):  # each polarity's lattice needs a spread
        return False
    if np.unique(lam).size * MIN_PIXELS_PER_LEVEL > lam.size:
        return False
    return bool(all(np.all(e > 0) for e in eps))


def bracketed_counts(lam, params, thresholds, key, duration_us: int, width: int, threads: int):
    """``(on, off, undecided)``: ON and OFF counts (flat, int64) of static pixels with photon counts ``lam`` per
    trial and per-pixel ``thresholds = (eps_on, eps_off)`` over ``duration_us``, bit for bit the counts of the
    renewal kernel run on every pixel's own closed-form inputs (module doc), and how many pixels needed their
    own evaluation. None when the brackets would leave most pixels undecided (:data:`MIN_DECIDED_SHARE`: many
    events per pixel), for the caller's plain path. Check :func:`applies` first."""
    from ._engine import static_inputs

    eps = [np.ascontiguousarray(t, dtype=np.float64).ravel() for t in thresholds]
    levels, group = np.unique(lam, return_inverse=True)
    group = group.ravel().astype(np.float64)
    brackets = []
    for e in eps:
        spread = float(e.std())
        h = spread / LATTICE_PER_SIGMA
        j = _lattice_index(e, h)
        p_at_j, p_at_j1 = _lattice_probabilities(levels, group, j, h, params.bias_pr)
        brackets.append((p_at_j1, p_at_j))  # (low, high): p falls as eps grows
    low, high, sure = _ends(_background_shares(levels, group.astype(np.int64), params), *brackets)
    # a pixel is decided unless an event falls between its two ends: about exp(-trials (p_high - p_low))
    trials = duration_us / params.trial_us
    spread = -np.expm1(high[0] - low[0]) * np.exp(low[0])  # p_high - p_low from log(1 - p) at both ends
    if float(np.mean(np.exp(-trials * spread))) < MIN_DECIDED_SHARE:
        return None
    state = PixelState(np.arange(lam.size), key, threads)
    streams = state.states.copy()
    on_low, off_low = _counts(state, width, *low, params, duration_us, threads)
    state.restart(streams)  # the same draws at the other end
    on, off = _counts(state, width, *high, params, duration_us, threads)
    todo = np.flatnonzero((on_low != on) | (off_low != off) | sure)
    if todo.size:
        log1m_p, q_on, _, _ = static_inputs(lam[todo], params, eps[0][todo], eps[1][todo], None)
        on[todo], off[todo] = _counts(PixelState(todo, key, threads), width, log1m_p, q_on, params, duration_us,
                                      threads)
    return on, off, todo.size
