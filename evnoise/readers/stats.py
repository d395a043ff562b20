"""What a recording's noise looks like: per-pixel counts and their statistics, streamed.

:func:`pixel_counts` accumulates ``(2, H, W)`` ON/OFF counts chunk by chunk (memory: the count
maps, never the events); :func:`noise_stats` turns them into the numbers ``evnoise info --stats``
prints; :func:`stats_png` draws the count maps and the per-pixel count histogram.
"""

from __future__ import annotations

import numpy as np

from .._budget import check_allocation
from ..errors import InputError, ParameterError
from ..events import polarity_index

#: Default hot-pixel rule: a pixel is hot when its count exceeds this many times the mean count
#: of the active pixels (and at least :data:`HOT_MIN_COUNT`).
HOT_FACTOR = 10.0
HOT_MIN_COUNT = 10
#: Quantiles of the per-pixel rate that are reported.
QUANTILES = (0.5, 0.9, 0.99)
#: Largest sensor side inferred from the events of a file whose header gives no size (the largest event
#: sensors are 1280 x 960): beyond, an event is taken as damage unless the caller gives the sensor size.
MAX_INFERRED_SIDE = 4096


def pixel_counts(chunks, shape=None):
    """ON/OFF counts ``(2, H, W)`` int64 and ``(n, t_first_us, t_last_us)`` from event chunks.

    Without ``shape`` the maps grow to the events' extent, up to :data:`MAX_INFERRED_SIDE` per side
    (a damaged file's stray coordinate would otherwise size gigabytes of maps). The maps' size (which a
    file's header declares) is checked against the memory budget before they are allocated.
    """
    height, width = shape if shape is not None else (1, 1)
    _check_maps(height, width)
    try:
        counts = np.zeros((2, height, width), dtype=np.int64)
    except MemoryError:
        raise _maps_memory_error(height, width) from None
    n, t_first, t_last = 0, None, None
    for chunk in chunks:
        xm, ym = int(chunk["x"].max()), int(chunk["y"].max())
        try:
            if shape is None and (xm >= width or ym >= height):
                new_h, new_w = max(height, ym + 1), max(width, xm + 1)
                if max(new_h, new_w) > MAX_INFERRED_SIDE:
                    raise InputError(f"an event at x = {xm}, y = {ym} in a file whose header gives no sensor size "
                                     f"lies beyond {MAX_INFERRED_SIDE} pixels (the largest side inferred from the "
                                     f"events; the file may be damaged): give sensor='WxH' if the sensor is that "
                                     f"large")
                _check_maps(new_h, new_w)
                grown = np.zeros((2, new_h, new_w), dtype=np.int64)
                grown[:, :height, :width] = counts
                counts, height, width = grown, new_h, new_w
            flat = polarity_index(chunk["p"]) * (height * width) + chunk["y"].astype(np.int64) * width + chunk["x"]
            counts += np.bincount(flat, minlength=2 * height * width).reshape(2, height, width)
        except MemoryError:
            raise _maps_memory_error(max(height, ym + 1), max(width, xm + 1)) from None
        n += int(chunk.size)
        if t_first is None:
            t_first = int(chunk["t"][0])
        t_last = int(chunk["t"][-1])
    return counts, (n, t_first, t_last)


def _address_space_left() -> int | None:
    """Bytes this process may still map under its address-space limit (``ulimit -v``), or None without one."""
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
        if soft == resource.RLIM_INFINITY:
            return None
        with open("/proc/self/statm") as fh:
            used = int(fh.read().split()[0]) * resource.getpagesize()
    except (ImportError, OSError, ValueError, IndexError):
        return None
    return max(0, soft - used)


def _check_maps(height: int, width: int) -> None:
    # the two int64 maps, plus one bincount of the same size while a chunk is added
    nbytes = 3 * 2 * int(height) * int(width) * 8
    what = f"ON/OFF count maps of a {width}x{height} sensor"
    hint = "give the real size with sensor='WxH' or raise EVNOISE_MAX_MEMORY"
    check_allocation(nbytes, what, hint=hint)
    left = _address_space_left()
    if left is not None and nbytes > left:
        raise InputError(f"{what} would need {nbytes / 2**30:.1f} GiB of memory, more than the {left / 2**30:.1f} GiB "
                         f"this process's address-space limit (ulimit -v) leaves; {hint}")


def _maps_memory_error(height: int, width: int) -> InputError:
    return InputError(f"out of memory for the ON/OFF count maps of a {width}x{height} sensor; give the real size "
                      f"with sensor='WxH'")


def noise_stats(counts, duration_s: float, *, hot_threshold: float | None = None) -> dict:
    """Statistics of per-pixel counts ``(2, H, W)`` over ``duration_s`` seconds.

    Returns a dict of plain numbers (units in the key names): ``events``, ``on_fraction``,
    ``rate_per_pixel_hz`` (``mean``, quantiles ``p50``/``p90``/``p99``, ``max``) over all
    pixels, ``active_pixel_fraction`` (pixels with at least one event), ``count_var_over_mean``
    (variance / mean of the per-pixel counts, all pixels; 1 for Poisson noise), and
    ``hot_pixels`` (``count``, ``event_share``, ``threshold_events``, ``rule``).

    The hot-pixel threshold is ``hot_threshold`` events when given, else
    ``max(HOT_MIN_COUNT, HOT_FACTOR x mean count of the active pixels)``; a pixel is hot when its
    count is above it.
    """
    counts = np.asarray(counts)
    if counts.ndim != 3 or counts.shape[0] != 2:
        raise InputError(f"counts must have shape (2, H, W), got {counts.shape}")
    if not (np.isfinite(duration_s) and duration_s > 0):
        raise ParameterError(f"the duration must be > 0 seconds to compute rates, got {duration_s!r}")
    total = counts.sum(axis=0).astype(np.float64).ravel()
    n = int(total.sum())
    n_on = int(counts[0].sum())
    out: dict = {"events": n, "on_fraction": (n_on / n) if n else None, "duration_s": float(duration_s),
                 "pixels": int(total.size)}
    rate = total / duration_s
    out["rate_per_pixel_hz"] = {"mean": float(rate.mean()),
                                **{f"p{int(round(q * 100))}": float(np.quantile(rate, q)) for q in QUANTILES},
                                "max": float(rate.max())}
    active = total > 0
    out["active_pixel_fraction"] = float(active.mean())
    mean = total.mean()
    out["count_var_over_mean"] = float(total.var() / mean) if mean > 0 else None
    if hot_threshold is not None:
        if not (np.isfinite(hot_threshold) and hot_threshold >= 0):
            raise ParameterError(f"hot_threshold must be >= 0 events, got {hot_threshold!r}")
        threshold, rule = float(hot_threshold), "given (hot_threshold)"
    else:
        mean_active = float(total[active].mean()) if active.any() else 0.0
        threshold = max(float(HOT_MIN_COUNT), HOT_FACTOR * mean_active)
        rule = f"count > max({HOT_MIN_COUNT}, {HOT_FACTOR:g} x mean count of active pixels)"
    hot = total > threshold
    out["hot_pixels"] = {"count": int(hot.sum()), "event_share": float(total[hot].sum() / n) if n else 0.0,
                         "threshold_events": threshold, "rule": rule}
    if n:
        cold = ~hot
        out["rate_per_pixel_hz_without_hot"] = float(total[cold].sum() / max(int(cold.sum()), 1) / duration_s)
    return out


#: the colour of the fewest events (1) on the count maps: this far up the magma map (its bottom is black, the
#: colour of "no events")
_LOWEST_COLOUR = 0.25


def count_colours(vmax: int):
    """``(cmap, norm)`` of the count maps of ``info --stats --png``: log scale from 1 to ``vmax`` events, a pixel
    with one event in a visible violet; pixels without events are masked and shown black (the axes' colour)."""
    import numpy as np
    from matplotlib import colormaps
    from matplotlib.colors import ListedColormap, LogNorm

    magma = colormaps["magma"]
    cmap = ListedColormap(magma(np.linspace(_LOWEST_COLOUR, 1.0, 256)), name="magma_from_violet")
    return cmap, LogNorm(vmin=1, vmax=max(int(vmax), 2))


def stats_png(path, counts, *, title: str = "", overwrite: bool = False) -> None:
    """ON and OFF count maps (log colour scale, black = no events) and the per-pixel count histogram (log y)."""
    import numpy as np

    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise InputError("the count-map PNG needs matplotlib: pip install 'evnoise[plot]'") from None
    from .._atomic import atomic_output

    counts = np.asarray(counts)
    total = counts.sum(axis=0)
    fig, axes = plt.subplots(1, 3, figsize=(15, 4.6), gridspec_kw={"width_ratios": [1, 1, 1.1]})
    cmap, norm = count_colours(int(counts.max()))
    for ax, img, label in zip(axes[:2], counts, ("ON", "OFF"), strict=True):
        im = ax.imshow(np.ma.masked_equal(img, 0), cmap=cmap, norm=norm, interpolation="nearest")
        ax.set_facecolor("black")
        ax.set_title(f"{label} events per pixel ({int(img.sum()):,} events)")
        ax.set_xlabel("x (px)")
        ax.set_ylabel("y (px)")
        fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, label="events (black: none)")
    ax = axes[2]
    flat = total.ravel()
    top = int(flat.max())
    bins = np.arange(0, top + 2) - 0.5 if top < 200 else np.unique(np.round(np.logspace(0, np.log10(top + 1), 80)))
    ax.hist(flat, bins=bins, color="0.3", log=True)
    ax.set_xlabel("events per pixel")
    ax.set_ylabel("pixels (log)")
    ax.set_title("per-pixel count histogram")
    if top >= 200:
        ax.set_xscale("symlog", linthresh=1)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    with atomic_output(path, overwrite=overwrite, what="PNG file") as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)
