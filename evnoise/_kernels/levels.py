"""Distinct values of a float64 array in one pass (exact: by bit pattern), for evaluate-once-and-scatter.

A static field has one value per pixel but often few distinct ones (a flat field one, an 8-bit image at
most 256): a per-pixel function that is evaluated element by element gives the same bits at a value
evaluated once and copied to every pixel that has it. :func:`distinct_levels` finds those values with
an open-addressing hash table keyed by the value's 64 bits (so ``0.0`` and ``-0.0`` are two levels, and
equal values are always one), and gives up as soon as there are more than a given number of them.
"""

from __future__ import annotations

import numpy as np

from ._jit import kernel

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)  # Fibonacci hashing multiplier (2**64 / golden ratio, odd)


@kernel
def distinct_levels(values, max_levels, levels, inverse):
    """Distinct values of ``values`` in order of first appearance, and each element's level index.

    Parameters
    ----------
    values : numpy.ndarray
        1-D contiguous float64 array (no NaN is expected; a NaN bit pattern is one more level).
    max_levels : int
        Give up past this many distinct values (``>= 1``).
    levels : numpy.ndarray
        float64 output of length ``>= max_levels``: the distinct values, first appearance first.
    inverse : numpy.ndarray
        int32 output of ``values``' length: ``levels[inverse[i]]`` has the bits of ``values[i]``.

    Returns
    -------
    int
        The number of distinct values, or ``-1`` when there are more than ``max_levels`` (the outputs
        are then partly written and meaningless).
    """
    n = values.shape[0]
    if n == 0:
        return 0
    shift = np.uint64(64)
    size = 1
    while size < 2 * max_levels:
        size *= 2
        shift -= np.uint64(1)
    mask = np.uint64(size - 1)
    keys = np.empty(size, dtype=np.uint64)
    slot_level = np.full(size, -1, dtype=np.int32)
    bits = values.view(np.uint64)
    n_levels = 0
    last_bits = bits[0] ^ np.uint64(1)  # not equal to the first value's bits
    last_level = np.int32(0)
    for i in range(n):
        b = bits[i]
        if b == last_bits:  # runs of one value (rows of a flat or smooth field) skip the table
            inverse[i] = last_level
            continue
        h = (b * _GOLDEN) >> shift  # shift <= 63: size >= 2
        while True:
            lv = slot_level[h]
            if lv < 0:
                if n_levels >= max_levels:
                    return -1
                keys[h] = b
                slot_level[h] = n_levels
                levels[n_levels] = values[i]
                lv = np.int32(n_levels)
                n_levels += 1
                break
            if keys[h] == b:
                break
            h = (h + np.uint64(1)) & mask
        inverse[i] = lv
        last_bits = b
        last_level = lv
    return n_levels


def find_levels(values: np.ndarray, max_levels: int):
    """``(levels, inverse)`` of the 1-D float64 array ``values`` (:func:`distinct_levels`), or None past ``max_levels``.

    ``levels`` is a contiguous float64 array of the distinct values, ``inverse`` int32 with
    ``levels[inverse]`` equal, bit for bit, to ``values``.
    """
    values = np.ascontiguousarray(values, dtype=np.float64)
    max_levels = max(1, int(max_levels))
    levels = np.empty(max_levels)
    inverse = np.empty(values.size, dtype=np.int32)
    count = distinct_levels(values, max_levels, levels, inverse)
    if count < 0:
        return None
    return levels[:count].copy(), inverse
