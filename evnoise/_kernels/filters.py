"""Signal/noise event filters over time-sorted streams (unchecked kernels).

Plain arrays in fixed units: times in int64 microseconds, coordinates as integers, per-pixel
state arrays indexed ``[y, x]`` (and ``[channel, y, x]``). Events are processed strictly in
index order, so a stream cut into chunks gives the same result as the whole stream, as long
as the caller carries the state (the arrays passed in and the indices returned) from one
call to the next. No checking happens here: see :mod:`evnoise.separation`.
"""

from __future__ import annotations

import numpy as np

from ._jit import kernel


@kernel(inline=True)
def _window_add(counts, x, y, p, j, delta, per_polarity):
    c = p[j] if per_polarity else 0
    counts[c, y[j], x[j]] += delta


@kernel
def density_pass(t, x, y, p, counts, lo, hi, start, t_complete, final, window_us, lookahead_us, radius,
                 per_polarity, threshold, density, is_signal):
    """Spatio-temporal event density of events ``start ..`` of a buffer, with a sliding window.

    The density of event ``i`` is the number of *other* events ``j`` of the buffer with
    ``|x_j - x_i| <= radius``, ``|y_j - y_i| <= radius`` and
    ``t_i - window_us <= t_j <= t_i + lookahead_us`` (and ``p_j == p_i`` if ``per_polarity``).
    ``counts`` (C, H, W) holds the per-pixel number of events of the buffer range ``[lo, hi)``
    (channel ``p`` if ``per_polarity``, else channel 0): it is the sliding window, updated by
    adding events at ``hi`` and removing them at ``lo`` as ``i`` advances.

    Event ``i`` is decided only if its whole window is in the buffer: ``final`` (the stream has
    ended) or ``t_i + lookahead_us < t_complete`` (every event earlier than ``t_complete`` has
    been pushed). Writes ``density[i]`` and ``is_signal[i] = density >= threshold`` for the
    decided events and returns ``(lo, hi, next)``, ``next`` being the first undecided event.
    """
    n = t.shape[0]
    height = counts.shape[1]
    width = counts.shape[2]
    i = start
    while i < n:
        ti = t[i]
        if not final and ti + lookahead_us >= t_complete:
            break
        while hi < n and t[hi] <= ti + lookahead_us:
            _window_add(counts, x, y, p, hi, 1, per_polarity)
            hi += 1
        while t[lo] < ti - window_us:
            _window_add(counts, x, y, p, lo, -1, per_polarity)
            lo += 1
        c = p[i] if per_polarity else 0
        xi = np.int64(x[i])
        yi = np.int64(y[i])
        y0 = max(yi - radius, 0)
        y1 = min(yi + radius + 1, height)
        x0 = max(xi - radius, 0)
        x1 = min(xi + radius + 1, width)
        d = np.int64(-1)  # the event itself is in the window
        for yy in range(y0, y1):
            for xx in range(x0, x1):
                d += counts[c, yy, xx]
        density[i] = d
        is_signal[i] = d >= threshold
        i += 1
    return lo, hi, i


@kernel
def activity_pass(t, x, y, last_t, radius, window_us, is_signal):
    """Background-activity filter: an event is signal if a *neighbouring* pixel fired recently.

    Event ``i`` is signal when some pixel other than its own, within ``radius`` in x and y,
    has its last event at ``t_i - window_us`` or later; then ``last_t[y_i, x_i] = t_i``.
    ``last_t`` (H, W) int64 is the per-pixel state (initialise it far in the past).
    """
    n = t.shape[0]
    height = last_t.shape[0]
    width = last_t.shape[1]
    for i in range(n):
        ti = t[i]
        xi = np.int64(x[i])
        yi = np.int64(y[i])
        y0 = max(yi - radius, 0)
        y1 = min(yi + radius + 1, height)
        x0 = max(xi - radius, 0)
        x1 = min(xi + radius + 1, width)
        found = False
        limit = ti - window_us
        for yy in range(y0, y1):
            for xx in range(x0, x1):
                if (yy != yi or xx != xi) and last_t[yy, xx] >= limit:
                    found = True
                    break
            if found:
                break
        is_signal[i] = found
        last_t[yi, xi] = ti


# --------------------------------------------------------------------------------------
# motion masks and moving windows (per time step, over the pixel grid)
# --------------------------------------------------------------------------------------
@kernel
def dense_mask(signal, radius, threshold, disc_dy, disc_dx, out):
    """Motion mask from per-pixel signal counts, touching only pixels near signal events.

    ``out[q]`` (pre-cleared) becomes True where some pixel ``d`` with a box sum of ``signal``
    over ``|dy|, |dx| <= radius`` reaching ``threshold`` lies at an offset ``(disc_dy, disc_dx)``
    from ``q`` (the dilation by a symmetric structuring element). Pixels outside the sensor
    count as zero, as in ``scipy.ndimage``. Returns the number of dense pixels.
    """
    height, width = signal.shape
    density = np.zeros((height, width), dtype=np.int64)
    n_nz = 0
    for yy in range(height):
        for xx in range(width):
            if signal[yy, xx] != 0:
                n_nz += 1
    ys = np.empty(n_nz, dtype=np.int64)
    xs = np.empty(n_nz, dtype=np.int64)
    k = 0
    for yy in range(height):
        for xx in range(width):
            v = signal[yy, xx]
            if v != 0:
                ys[k] = yy
                xs[k] = xx
                k += 1
                for y2 in range(max(yy - radius, 0), min(yy + radius + 1, height)):
                    for x2 in range(max(xx - radius, 0), min(xx + radius + 1, width)):
                        density[y2, x2] += v
    # dense pixels lie within radius of a non-zero pixel: visit only those
    n_dense = 0
    for k in range(n_nz):
        for y2 in range(max(ys[k] - radius, 0), min(ys[k] + radius + 1, height)):
            for x2 in range(max(xs[k] - radius, 0), min(xs[k] + radius + 1, width)):
                if density[y2, x2] >= threshold:
                    density[y2, x2] = -1  # visit once
                    n_dense += 1
                    for j in range(disc_dy.shape[0]):
                        y3 = y2 + disc_dy[j]
                        x3 = x2 + disc_dx[j]
                        if 0 <= y3 < height and 0 <= x3 < width:
                            out[y3, x3] = True
    return n_dense


@kernel
def window_skip(total, static_steps, ring_counts, ring_static, noise, mask, drop_old):
    """One step of the "skip" moving window, in place, for every pixel.

    ``total`` (2, H, W) and ``static_steps`` (H, W) are the running sums over the window;
    ``ring_counts`` (2, H, W) and ``ring_static`` (H, W) are the ring slots of the step that
    leaves the window (subtracted when ``drop_old``) and receive this step's kept counts
    (``noise`` where not ``mask``, else 0) and static flag.
    """
    height, width = mask.shape
    for yy in range(height):
        for xx in range(width):
            m = mask[yy, xx]
            for c in range(2):
                kept = 0 if m else noise[c, yy, xx]
                old = ring_counts[c, yy, xx] if drop_old else 0
                total[c, yy, xx] += kept - old
                ring_counts[c, yy, xx] = kept
            old_s = ring_static[yy, xx] if drop_old else False
            static_steps[yy, xx] += (0 if m else 1) - (1 if old_s else 0)
            ring_static[yy, xx] = not m
