"""Numba kernels of the dataset generators (no checking, no I/O; plain arrays in fixed units).

Compiled through :func:`evnoise._kernels._jit.kernel` (the same options as the core kernels)
and driven by one xoshiro256++ stream per call from :mod:`evnoise._kernels.rng`, so a call's
output depends only on its inputs and its 4-word key. Every kernel here runs on one thread:
the generators parallelise over shards, not inside a sample.
"""

from __future__ import annotations

import math

import numpy as np

from evnoise._kernels._jit import kernel
from evnoise._kernels.rng import seed_state, uniform

#: Columns of the per-level table of :func:`trial_counts_binned`.
T_P_NONE, T_P, T_RATIO, T_B0, T_Q_ON, T_FP = range(6)


@kernel
def trial_counts_binned(codes, table, n_full, frac, key, binning, out):
    """Binned ON/OFF counts of static pixels with i.i.d. trials (no dead time, no mismatch).

    A pixel fires in each of its ``n_full`` whole trials with probability ``p = p_on + p_off``
    and in one more, partial trial with probability ``frac * p`` (its event time is uniform
    within the trial and the window ends inside it); a firing is ON with probability
    ``q_on = p_on / p``. So the pixel's event count is ``N = Binomial(n_full, p) +
    Bernoulli(frac p)`` and ``ON | N ~ Binomial(N, q_on)``: exactly the count distribution of
    the trial model. ``N`` is drawn by inversion of its CDF (one uniform; most pixels stop at
    ``P(N = 0)``), then each of the ``N`` events picks its polarity.

    Parameters
    ----------
    codes : int32 (H, W)
        Index of each pixel's illuminance level into ``table``.
    table : float64 (K, 6)
        Per level (columns ``T_*``): ``P(N = 0)``, ``p``, ``p / (1 - p)``,
        ``b0 = (1 - p) ** n_full``, ``q_on``, ``frac * p``; one row per level keeps a pixel's
        lookups together.
    n_full : int
        Whole trials in the window.
    frac : float
        Fraction of the last, partial trial inside the window, ``[0, 1)``.
    key : uint64 (4,)
        Stream key.
    binning : int
        Counts are summed over ``binning x binning`` blocks; ``H`` and ``W`` are multiples.
    out : int64 (2, H // binning, W // binning)
        Zeroed on entry; receives the binned ``[ON, OFF]`` counts.
    """
    s = np.empty(4, dtype=np.uint64)
    seed_state(key, 0, s)
    height, width = codes.shape
    nf = float(n_full)
    k_max = n_full + 1 if frac > 0.0 else n_full
    recip = np.empty(n_full + 2)  # 1 / (k + 1): no division in the inversion loop
    for k in range(n_full + 2):
        recip[k] = 1.0 / (k + 1.0)
    for i in range(height):
        bi = i // binning
        for j in range(width):
            row = table[codes[i, j]]
            u = uniform(s)
            cdf = row[T_P_NONE]
            if u < cdf:
                continue
            # P(N = k + 1) = b_{k+1} (1 - fp) + b_k fp, with b_k the Binomial(n_full, p) pmf
            fp = row[T_FP]
            r = row[T_RATIO]
            b_k = row[T_B0]
            k = 0
            while k < k_max:
                b_next = b_k * (nf - k) * recip[k] * r
                k += 1
                cdf += b_next * (1.0 - fp) + b_k * fp
                b_k = b_next
                if u < cdf:
                    break
            q = row[T_Q_ON]
            on = 0
            for _ in range(k):
                if uniform(s) < q:
                    on += 1
            bj = j // binning
            out[0, bi, bj] += on
            out[1, bi, bj] += k - on


_TILE = 16


@kernel
def paint_leaves(img, covered, open_in_tile, cx, cy, radius, value, grad_x, grad_y, tex_amp, tex_kx, tex_ky,
                 tex_phase):
    """Paint disks front to back into the pixels not yet covered; returns the pixels painted.

    Leaf ``k`` is the disk of centre ``(cx[k], cy[k])`` (pixel units, x = column, y = row) and
    radius ``radius[k]``; its value at ``(x, y)`` is ``value[k] + grad_x[k] (x - cx[k]) +
    grad_y[k] (y - cy[k]) + tex_amp[k] sin(tex_kx[k] x + tex_ky[k] y + tex_phase[k])``. Leaves
    earlier in the arrays lie in front (occlude later ones): a pixel takes the value of the
    first leaf that covers it. ``open_in_tile[ty, tx]`` counts the uncovered pixels of each
    16 x 16 tile (updated here), so that tiles already covered are skipped.
    """
    height, width = img.shape
    painted = 0
    for k in range(cx.shape[0]):
        r = radius[k]
        r2 = r * r
        x0 = max(0, int(math.floor(cx[k] - r)))
        x1 = min(width - 1, int(math.ceil(cx[k] + r)))
        y0 = max(0, int(math.floor(cy[k] - r)))
        y1 = min(height - 1, int(math.ceil(cy[k] + r)))
        if x0 > x1 or y0 > y1:
            continue
        for ty in range(y0 // _TILE, y1 // _TILE + 1):
            for tx in range(x0 // _TILE, x1 // _TILE + 1):
                if open_in_tile[ty, tx] == 0:
                    continue
                ya = max(y0, ty * _TILE)
                yb = min(y1, ty * _TILE + _TILE - 1)
                xa = max(x0, tx * _TILE)
                xb = min(x1, tx * _TILE + _TILE - 1)
                for y in range(ya, yb + 1):
                    dy = y - cy[k]
                    for x in range(xa, xb + 1):
                        if covered[y, x]:
                            continue
                        dx = x - cx[k]
                        if dx * dx + dy * dy <= r2:
                            v = value[k] + grad_x[k] * dx + grad_y[k] * dy
                            if tex_amp[k] != 0.0:
                                v += tex_amp[k] * math.sin(tex_kx[k] * x + tex_ky[k] * y + tex_phase[k])
                            img[y, x] = v
                            covered[y, x] = True
                            open_in_tile[ty, tx] -= 1
                            painted += 1
    return painted


def tile_counts(height: int, width: int):
    """Uncovered pixels of each tile of an empty ``(height, width)`` image (for :func:`paint_leaves`)."""
    ny, nx = -(-height // _TILE), -(-width // _TILE)
    rows = np.minimum(_TILE, height - _TILE * np.arange(ny))
    cols = np.minimum(_TILE, width - _TILE * np.arange(nx))
    return np.ascontiguousarray(np.outer(rows, cols).astype(np.int64))


@kernel
def illuminance_levels(y, scale, gamma, inv_step, binning, codes, level_sums):
    """Quantised illuminance of a crop and its per-bin sums, in one pass.

    ``lux = scale * y ** gamma`` (``y`` relative linear luminance ``>= 0``), ``codes = floor(lux *
    inv_step + 0.5)`` (int32, clamped to ``2^31 - 2``), and ``level_sums[bi, bj]`` = the sum of the
    codes of each ``binning x binning`` block (int64; ``level_sums`` zeroed on entry).
    Returns the largest unclamped ``lux * inv_step`` (the caller rejects values above the clamp).
    """
    height, width = y.shape
    top = 0.0
    limit = 2147483646.0
    for i in range(height):
        bi = i // binning
        for j in range(width):
            v = y[i, j]
            if gamma != 1.0:
                v = v**gamma
            v = v * scale * inv_step
            if v > top:
                top = v
            c = math.floor(v + 0.5)
            if c > limit:
                c = limit
            codes[i, j] = np.int32(c)
            level_sums[bi, j // binning] += np.int64(c)
    return top


#: hash-table size of :func:`lzf_compress` (log2)
LZF_HLOG = 14
_LZF_MAX_OFF = 1 << 13  # back references reach at most 8192 bytes back
_LZF_MAX_REF = (1 << 8) + (1 << 3)  # and copy at most 264 bytes
_LZF_MAX_LIT = 1 << 5  # a literal run holds at most 32 bytes


@kernel
def _lzf_literals(src, start, stop, dst, op):
    """Write ``src[start:stop]`` as literal runs at ``dst[op:]``; the new ``op``, or -1 when it does not fit."""
    while start < stop:
        n = min(stop - start, _LZF_MAX_LIT)
        if op + 1 + n > dst.size:
            return -1
        dst[op] = n - 1
        op += 1
        for k in range(n):
            dst[op + k] = src[start + k]
        op += n
        start += n
    return op


@kernel
def lzf_compress(src, dst):
    """LZF-compress the bytes ``src`` (uint8) into ``dst`` (uint8); returns the size written, 0 if it does not fit.

    Writes the stream format of liblzf, which h5py's LZF filter (HDF5 filter 32000) decodes. Unlike
    the liblzf inside h5py, whose hash table is left uninitialised (its output then depends on what
    was on the C stack, so two identical runs wrote different bytes now and then), the table starts
    empty: the output depends only on ``src``. Greedy: at each position the most recent earlier
    position with the same 3-byte hash is tried, and the longest match there is taken.
    """
    n = src.size
    cap = dst.size
    mask = (1 << LZF_HLOG) - 1
    table = np.full(1 << LZF_HLOG, -1, dtype=np.int64)
    ip = 0
    lit = 0  # start of the bytes not yet written
    op = 0
    while ip + 2 < n:
        v = (np.int64(src[ip]) << 16) | (np.int64(src[ip + 1]) << 8) | np.int64(src[ip + 2])
        h = ((v * 2654435761) >> (24 - LZF_HLOG + 8)) & mask
        ref = table[h]
        table[h] = ip
        if (ref >= 0 and ip - ref <= _LZF_MAX_OFF and src[ref] == src[ip] and src[ref + 1] == src[ip + 1]
                and src[ref + 2] == src[ip + 2]):
            longest = min(_LZF_MAX_REF, n - ip)
            length = 3
            while length < longest and src[ref + length] == src[ip + length]:
                length += 1
            op = _lzf_literals(src, lit, ip, dst, op)
            if op < 0 or op + 3 > cap:
                return 0
            off = ip - ref - 1
            code = length - 2
            if code < 7:
                dst[op] = (code << 5) | (off >> 8)
                dst[op + 1] = off & 0xFF
                op += 2
            else:
                dst[op] = (7 << 5) | (off >> 8)
                dst[op + 1] = code - 7
                dst[op + 2] = off & 0xFF
                op += 3
            ip += length
            lit = ip
        else:
            ip += 1
    op = _lzf_literals(src, lit, n, dst, op)
    return max(op, 0)
