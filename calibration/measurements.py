"""Measurements to calibrate against: rate tables, flat-field recordings, monitor tables.

Three inputs, all reduced to one :class:`Measurements` object (one entry per illuminance level):

Rate table (CSV)
    One row per illuminance level, levels in increasing order, each once. Lines starting
    with ``#`` are comments; the first other line is the header. Columns:

    ``lux`` (or ``grey`` with a monitor table)
        Illuminance at the sensor in lux (``>= 0``), or the monitor's grey level.
    ``rate_on_hz, rate_off_hz``
        Mean noise-event rate per pixel, events/s; *or* ``count_on, count_off``: the total
        number of events over all pixels and the whole duration (then ``n_pixels`` and
        ``duration_s`` are required).
    ``n_pixels, duration_s`` (optional with rates)
        Pixels averaged and recording length in seconds. With them the rates are turned
        into counts and the fit is a likelihood on counts; without them the absolute count
        is unknown and uncertainties are scaled by the scatter of the residuals
        (quasi-likelihood).
    ``r_on, r_off`` (optional)
        Measured negative-binomial shape ``r`` of the per-pixel count over ``duration_s``
        (``var = mu + mu^2 / r``); needs ``duration_s``. Lets the fit determine ``eps_sigma``.

Flat-field listing (TOML or CSV)
    One recording of a uniformly lit sensor per level: events.h5 or any camera file evnoise reads
    (``sensor = "WxH"`` and ``csv_columns`` keys where the file needs them; a camera file's window
    is on its own clock and starts at its first event by default). TOML::

        [[level]]
        file = "flat_0.h5"        # relative to the listing's folder
        lux = 0.5                 # or grey = 40 with a monitor table
        # optional: duration_s, t_start_s, t_end_s, roi = [y0, y1, x0, x1]

    or CSV with columns ``file, lux`` (or ``grey``) and optionally ``duration_s, t_start_s,
    t_end_s``. Per-pixel counts of each polarity are taken over ``[t_start_s, t_end_s)``
    (default: the whole recording; its length from ``duration_s``, the file's ``t_end_us``
    attribute, or ``t_end_s - t_start_s``). A region ``roi`` selects the flat part of the
    field; the same file may be listed several times with different regions and lux values
    (an events.h5 with a mask of regions of known lux).

Monitor table (CSV ``grey, lux``)
    Illuminance measured at the camera for some grey levels of a monitor, grey strictly
    increasing and lux non-decreasing. Grey levels in the measurements are converted by
    :func:`grey_to_lux`.
"""

from __future__ import annotations

import csv
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from evnoise._checks import check_input_file, read_bounded_file
from evnoise.errors import InputError

__all__ = [
    "Measurements",
    "MonitorTable",
    "rate_table",
    "count_table",
    "flat_field",
    "read_rate_table",
    "read_flat_fields",
    "read_measurements",
    "read_monitor_table",
    "grey_to_lux",
]

#: Fewest illuminance levels any calibration accepts.
MIN_LEVELS = 3


@dataclass(frozen=True, eq=False)
class Measurements:
    """Noise measurements at several static illuminance levels (polarity index 0 = ON, 1 = OFF).

    Attributes
    ----------
    lux : numpy.ndarray (J,)
        Illuminance of each level in lux, strictly increasing.
    rate_hz : numpy.ndarray (2, J)
        Mean per-pixel noise-event rate, events/s.
    duration_s, n_pixels : numpy.ndarray (J,) or None
        Recording length in seconds and number of pixels of each level (``None``: unknown).
    nb_shape : numpy.ndarray (2, J) or None
        Measured negative-binomial shape ``r`` of the per-pixel count over ``duration_s``
        (for flat fields the moment estimate ``mean^2 / (var - mean)``; ``inf`` if not
        over-dispersed).
    pixel_counts : tuple of numpy.ndarray (2, n_j) or None
        Flat fields only: each level's per-pixel counts.
    pixel_ids : tuple of numpy.ndarray (n_j,) or None
        Flat fields only: a sensor-pixel identifier per column of ``pixel_counts``; equal ids
        at different levels are the same pixel (used for uncertainties that allow for each
        pixel's fixed thresholds).
    source : str
        Where the numbers come from (file names), for provenance.
    grey : numpy.ndarray (J,) or None
        Monitor grey levels, when the levels were given as grey.
    """

    lux: np.ndarray
    rate_hz: np.ndarray
    duration_s: np.ndarray | None = None
    n_pixels: np.ndarray | None = None
    nb_shape: np.ndarray | None = None
    pixel_counts: tuple | None = None
    pixel_ids: tuple | None = None
    source: str = ""
    grey: np.ndarray | None = None
    notes: tuple = field(default_factory=tuple)

    @property
    def n_levels(self) -> int:
        return int(self.lux.size)

    @property
    def kind(self) -> str:
        """``"flat-field"`` (per-pixel counts) or ``"table"`` (level means only)."""
        return "flat-field" if self.pixel_counts is not None else "table"

    @property
    def exposure_known(self) -> bool:
        return self.duration_s is not None and self.n_pixels is not None

    @property
    def counts(self) -> np.ndarray | None:
        """Total events over all pixels and the whole duration ``(2, J)`` (``None`` if unknown)."""
        if not self.exposure_known:
            return None
        return self.rate_hz * (self.duration_s * self.n_pixels)

    @property
    def has_dispersion(self) -> bool:
        return self.pixel_counts is not None or self.nb_shape is not None


# --------------------------------------------------------------------------------------
# validation helpers
# --------------------------------------------------------------------------------------
def _vector(values, name: str, where: str, *, positive=False, integer=False, allow_inf=False) -> np.ndarray:
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):  # OverflowError: an integer beyond the double range
        raise InputError(f"{where}: {name} must be numeric") from None
    if arr.ndim != 1:
        raise InputError(f"{where}: {name} must be one value per level, got shape {arr.shape}")
    bad = np.isnan(arr) | (~np.isfinite(arr) & (not allow_inf))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(f"{where}: {name} of level {i + 1} is {arr[i]}; it must be a finite number")
    low = (arr <= 0) if positive else (arr < 0)
    if low.any():
        i = int(np.flatnonzero(low)[0])
        raise InputError(f"{where}: {name} of level {i + 1} is {arr[i]:g}; it must be {'> 0' if positive else '>= 0'}")
    if integer and np.any(arr != np.round(arr)):
        i = int(np.flatnonzero(arr != np.round(arr))[0])
        raise InputError(f"{where}: {name} of level {i + 1} is {arr[i]:g}; it must be a whole number")
    return arr


def _check_levels(lux: np.ndarray, where: str, label: str = "lux") -> None:
    if lux.size < MIN_LEVELS:
        raise InputError(f"{where}: a calibration needs at least {MIN_LEVELS} illuminance levels, got {lux.size}")
    d = np.diff(lux)
    if np.any(d <= 0):
        i = int(np.flatnonzero(d <= 0)[0])
        what = "repeats" if d[i] == 0 else "is below"
        raise InputError(
            f"{where}: levels must be in strictly increasing {label}, each once; level {i + 2} "
            f"({label} = {lux[i + 1]:g}) {what} level {i + 1} ({label} = {lux[i]:g})"
        )


def _check_rates(rate: np.ndarray, where: str) -> None:
    if not np.any(rate > 0):
        raise InputError(f"{where}: no noise events at any level (all rates/counts are zero); nothing to fit")
    for k, name in enumerate(("ON", "OFF")):
        if not np.any(rate[k] > 0):
            raise InputError(
                f"{where}: no {name} events at any level; the {name} threshold cannot be determined"
            )


def rate_table(lux, rate_on_hz, rate_off_hz, *, n_pixels=None, duration_s=None, r_on=None, r_off=None,
               source: str = "table", grey=None) -> Measurements:
    """Measurements from per-pixel mean rates (events/s) at each illuminance (checked).

    Parameters
    ----------
    lux : array_like (J,)
        Illuminance of each level in lux, ``>= 0`` (strictly increasing unless ``grey`` is given).
    rate_on_hz, rate_off_hz : float or array_like (J,)
        Mean per-pixel ON and OFF noise-event rates, events per second, ``>= 0``; a scalar applies to
        every level. Each polarity needs a rate above zero at some level.
    n_pixels : int or array_like (J,), optional
        Number of pixels averaged at each level (whole numbers ``> 0``).
    duration_s : float or array_like (J,), optional
        Recording length of each level in seconds (``> 0``).
    r_on, r_off : array_like (J,), optional
        Measured negative-binomial shapes ``r`` of the per-pixel ON and OFF counts over ``duration_s``
        (``> 0``, ``inf`` allowed); both or neither, and they need ``duration_s``.
    source : str, default "table"
        Where the numbers come from, for provenance and error messages.
    grey : array_like (J,), optional
        Monitor grey levels the ``lux`` values were converted from; when given, the levels must be in
        strictly increasing grey instead.

    Returns
    -------
    Measurements
        The checked measurements.

    Notes
    -----
    ``n_pixels`` and ``duration_s`` (scalars or one per level) make the fit a likelihood on
    counts; without them uncertainties are scaled by the scatter of the residuals.
    """
    where = source or "table"
    lux = _vector(lux, "lux", where)
    j = lux.size
    label = "lux" if grey is None else "grey"
    _check_levels(lux if grey is None else np.asarray(grey, dtype=np.float64), where, label)
    rate = np.stack([_vector(np.broadcast_to(np.asarray(v, dtype=np.float64), (j,)) if np.ndim(v) == 0 else v,
                             name, where)
                     for v, name in ((rate_on_hz, "rate_on_hz"), (rate_off_hz, "rate_off_hz"))])
    if rate.shape != (2, j):
        raise InputError(f"{where}: rates must have one value per level ({j})")
    _check_rates(rate, where)
    dur = None if duration_s is None else _vector(np.broadcast_to(duration_s, (j,)), "duration_s", where, positive=True)
    npx = None if n_pixels is None else _vector(np.broadcast_to(n_pixels, (j,)), "n_pixels", where, positive=True,
                                                integer=True)
    shape = None
    if (r_on is None) != (r_off is None):
        raise InputError(f"{where}: give both r_on and r_off, or neither")
    if r_on is not None:
        if dur is None:
            raise InputError(f"{where}: measured NB shapes r_on, r_off need 'duration_s' (the counting window)")
        shape = np.stack([_vector(r_on, "r_on", where, positive=True, allow_inf=True),
                          _vector(r_off, "r_off", where, positive=True, allow_inf=True)])
        if shape.shape != (2, j):
            raise InputError(f"{where}: r_on, r_off must have one value per level ({j})")
    g = None if grey is None else np.asarray(grey, dtype=np.float64)
    return Measurements(lux=lux, rate_hz=rate, duration_s=dur, n_pixels=npx, nb_shape=shape, source=source, grey=g)


def count_table(lux, count_on, count_off, n_pixels, duration_s, *, r_on=None, r_off=None, source: str = "table",
                grey=None) -> Measurements:
    """Measurements from total event counts over ``n_pixels`` pixels and ``duration_s`` seconds.

    Parameters
    ----------
    lux : array_like (J,)
        Illuminance of each level in lux, ``>= 0`` (strictly increasing unless ``grey`` is given).
    count_on, count_off : array_like (J,)
        Total number of ON and OFF events of each level over all pixels and the whole duration
        (whole numbers ``>= 0``).
    n_pixels : int or array_like (J,)
        Number of pixels counted at each level (whole numbers ``> 0``).
    duration_s : float or array_like (J,)
        Recording length of each level in seconds (``> 0``).
    r_on, r_off : array_like (J,), optional
        Measured negative-binomial shapes ``r`` of the per-pixel ON and OFF counts over ``duration_s``;
        both or neither.
    source : str, default "table"
        Where the numbers come from, for provenance and error messages.
    grey : array_like (J,), optional
        Monitor grey levels the ``lux`` values were converted from, as in :func:`rate_table`.

    Returns
    -------
    Measurements
        The checked measurements, counts turned into per-pixel rates.
    """
    where = source or "table"
    lux_v = _vector(lux, "lux", where)
    j = lux_v.size
    counts = np.stack([_vector(count_on, "count_on", where), _vector(count_off, "count_off", where)])
    if counts.shape != (2, j):
        raise InputError(f"{where}: counts must have one value per level ({j})")
    if np.any(counts != np.round(counts)):
        raise InputError(f"{where}: counts must be whole numbers")
    dur = _vector(np.broadcast_to(duration_s, (j,)), "duration_s", where, positive=True)
    npx = _vector(np.broadcast_to(n_pixels, (j,)), "n_pixels", where, positive=True, integer=True)
    return rate_table(lux_v, counts[0] / (dur * npx), counts[1] / (dur * npx), n_pixels=npx, duration_s=dur,
                      r_on=r_on, r_off=r_off, source=source, grey=grey)


def flat_field(lux, pixel_counts, duration_s, *, pixel_ids=None, source: str = "flat fields",
               grey=None) -> Measurements:
    """Measurements from per-pixel counts of uniformly lit recordings, one per level.

    Parameters
    ----------
    lux : array_like (J,)
        Illuminance of each level in lux, strictly increasing.
    pixel_counts : sequence of J arrays
        Per-pixel counts of each level, shape ``(2, ...)`` ``[ON, OFF]`` (e.g. the
        ``(2, H, W)`` result of :func:`evnoise.count_events`), non-negative integers.
    duration_s : float or array_like (J,)
        Counting window of each level in seconds.
    pixel_ids : sequence of J integer arrays, optional
        Sensor-pixel identifier of each counted pixel (same pixel, same id at every level);
        default: position in the array, i.e. the same pixels at every level.
    source : str, default "flat fields"
        Where the counts come from (file names), for provenance and error messages.
    grey : array_like (J,), optional
        Monitor grey levels the ``lux`` values were converted from; when given, the levels must be in
        strictly increasing grey instead of lux.

    Returns
    -------
    Measurements
        Level means and the moment estimate of the negative-binomial shape, with the per-pixel counts
        and pixel ids kept.
    """
    where = source or "flat fields"
    lux = _vector(lux, "lux", where)
    j = lux.size
    _check_levels(lux if grey is None else np.asarray(grey, dtype=np.float64), where,
                  "lux" if grey is None else "grey")
    dur = _vector(np.broadcast_to(duration_s, (j,)), "duration_s", where, positive=True)
    if len(pixel_counts) != j:
        raise InputError(f"{where}: {len(pixel_counts)} count arrays for {j} levels")
    counts, ids = [], []
    for i, c in enumerate(pixel_counts):
        arr = np.asarray(c)
        if arr.ndim < 2 or arr.shape[0] != 2:
            raise InputError(f"{where}: counts of level {i + 1} must have shape (2, ...) [ON, OFF], got {arr.shape}")
        arr = arr.reshape(2, -1)
        if arr.shape[1] == 0:
            raise InputError(f"{where}: level {i + 1} has no pixels")
        if not np.issubdtype(arr.dtype, np.integer):
            if not (np.isfinite(arr).all() and np.all(arr == np.round(arr))):
                raise InputError(f"{where}: counts of level {i + 1} must be whole numbers")
        if np.any(arr < 0):
            raise InputError(f"{where}: counts of level {i + 1} are negative")
        counts.append(arr.astype(np.int64))
        if pixel_ids is None:
            ids.append(np.arange(arr.shape[1], dtype=np.int64))
        else:
            pid = np.asarray(pixel_ids[i], dtype=np.int64).ravel()
            if pid.size != arr.shape[1]:
                raise InputError(f"{where}: level {i + 1} has {arr.shape[1]} pixels but {pid.size} pixel ids")
            ids.append(pid)
    n_pix = np.array([c.shape[1] for c in counts], dtype=np.float64)
    mean = np.stack([c.mean(axis=1) for c in counts], axis=1)  # (2, J)
    rate = mean / dur
    _check_rates(rate, where)
    var = np.stack([c.var(axis=1, ddof=1) if c.shape[1] > 1 else np.zeros(2) for c in counts], axis=1)
    excess = var - mean
    with np.errstate(divide="ignore", invalid="ignore"):
        shape = np.where(excess > 0, mean**2 / np.where(excess > 0, excess, 1.0), np.inf)
    g = None if grey is None else np.asarray(grey, dtype=np.float64)
    return Measurements(lux=lux, rate_hz=rate, duration_s=dur, n_pixels=n_pix, nb_shape=shape,
                        pixel_counts=tuple(counts), pixel_ids=tuple(ids), source=source, grey=g)


# --------------------------------------------------------------------------------------
# monitor tables
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MonitorTable:
    """Measured illuminance at the camera for some grey levels of a monitor."""

    grey: np.ndarray
    lux: np.ndarray
    source: str = ""


#: Largest table read (a rate table of a million rows has tens of MB): a larger file is refused before it is read.
MAX_TABLE_BYTES = 256 << 20


def _read_csv_rows(path: Path) -> tuple[list[str], list[list[str]]]:
    # a pipe would block the read for ever and a device (/dev/zero) never ends: regular files of bounded size only
    data = read_bounded_file(path, max_bytes=MAX_TABLE_BYTES, missing="file", kind="a table (CSV)",
                             bound="a table of rates, counts or monitor levels may have")
    path = Path(path)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"cannot read {path}: {exc}") from None
    lines = [ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise InputError(f"{path}: empty table (no header)")
    try:
        rows = list(csv.reader(lines, skipinitialspace=True))
    except csv.Error as exc:  # e.g. a field longer than the csv module's limit (128 kB)
        raise InputError(f"{path}: not a table of rates or counts ({exc})") from None
    header = [h.strip().lower() for h in rows[0]]
    if len(set(header)) != len(header):
        raise InputError(f"{path}: duplicate column names in header {rows[0]}")
    body = rows[1:]
    for i, row in enumerate(body):
        if len(row) != len(header):
            raise InputError(f"{path}: row {i + 1} has {len(row)} values, the header has {len(header)} columns")
    return header, body


def _column(path, header, body, name, *, required=True):
    if name not in header:
        if required:
            raise InputError(f"{path}: missing column {name!r} (columns: {', '.join(header)})")
        return None
    k = header.index(name)
    out = np.empty(len(body))
    for i, row in enumerate(body):
        text = row[k].strip()
        try:
            out[i] = float(text) if text else math.nan
        except ValueError:
            raise InputError(f"{path}: row {i + 1}, column {name!r}: {text!r} is not a number") from None
    return out


def read_monitor_table(path) -> MonitorTable:
    """Read a ``grey, lux`` CSV (grey strictly increasing, lux finite, >= 0 and non-decreasing).

    Parameters
    ----------
    path : str or os.PathLike
        The CSV file, with columns ``grey`` and ``lux`` and at least two rows.

    Returns
    -------
    MonitorTable
        The table, its ``source`` the file's path.
    """
    path = Path(path)
    header, body = _read_csv_rows(path)
    grey = _column(path, header, body, "grey")
    lux = _column(path, header, body, "lux")
    where = str(path)
    grey = _vector(grey, "grey", where)
    lux = _vector(lux, "lux", where)
    if grey.size < 2:
        raise InputError(f"{where}: a monitor table needs at least 2 rows, got {grey.size}")
    d = np.diff(grey)
    if np.any(d <= 0):
        i = int(np.flatnonzero(d <= 0)[0])
        raise InputError(f"{where}: grey must be strictly increasing, each once; row {i + 2} (grey = "
                         f"{grey[i + 1]:g}) {'repeats' if d[i] == 0 else 'is below'} row {i + 1} (grey = {grey[i]:g})")
    if np.any(np.diff(lux) < 0):
        i = int(np.flatnonzero(np.diff(lux) < 0)[0])
        raise InputError(f"{where}: lux must not decrease with grey; row {i + 2} (lux = {lux[i + 1]:g}) is below "
                         f"row {i + 1} (lux = {lux[i]:g})")
    return MonitorTable(grey=grey, lux=lux, source=str(path))


def grey_to_lux(grey, table: MonitorTable, *, model: str = "interp", gamma: float = 2.2) -> np.ndarray:
    """Illuminance in lux of monitor grey levels.

    Parameters
    ----------
    grey : float or array_like
        Grey levels to convert (finite, ``>= 0``).
    table : MonitorTable
        Measured illuminance at the camera for some grey levels.
    model : {"interp", "gamma"}, default "interp"
        ``"interp"``: piecewise-linear interpolation in the linear intensity ``grey^gamma``
        between the table's points (no extrapolation: a grey level outside the table is an error).
        ``"gamma"``: the least-squares line ``lux = a grey^gamma + c`` through the table (the
        Noise2Image authors' mapping; values below 0 are an error).
    gamma : float, default 2.2
        The monitor's gamma (finite, ``> 0``).

    Returns
    -------
    numpy.ndarray
        Illuminance in lux, one per grey level (1-D, also for a scalar ``grey``).
    """
    g = _vector(np.atleast_1d(grey), "grey", "grey levels")
    if not (isinstance(gamma, (int, float)) and math.isfinite(gamma) and gamma > 0):
        raise InputError(f"gamma must be a finite number > 0, got {gamma!r}")
    x = g**gamma
    xt = table.grey**gamma
    if model == "interp":
        out_of_range = (g < table.grey[0]) | (g > table.grey[-1])
        if out_of_range.any():
            i = int(np.flatnonzero(out_of_range)[0])
            raise InputError(f"grey level {g[i]:g} is outside the monitor table's range "
                             f"[{table.grey[0]:g}, {table.grey[-1]:g}]")
        return np.interp(x, xt, table.lux)
    if model == "gamma":
        a, c = np.polyfit(xt, table.lux, 1)
        lux = a * x + c
        if np.any(lux < 0):
            i = int(np.flatnonzero(lux < 0)[0])
            raise InputError(f"the monitor's fitted line gives negative illuminance {lux[i]:g} lux at grey {g[i]:g}")
        return lux
    raise InputError(f"monitor model must be 'interp' or 'gamma', got {model!r}")


def _levels_from(path, header, body, monitor, monitor_model):
    """The lux column, or the grey column converted through the monitor table."""
    if "lux" in header:
        if "grey" in header:
            raise InputError(f"{path}: give either a 'lux' or a 'grey' column, not both")
        return _column(path, header, body, "lux"), None
    if "grey" in header:
        if monitor is None:
            raise InputError(f"{path}: levels are given as grey; a monitor table (grey -> lux) is needed")
        grey = _vector(_column(path, header, body, "grey"), "grey", str(path))
        _check_levels(grey, str(path), "grey")
        return grey_to_lux(grey, monitor, model=monitor_model), grey
    raise InputError(f"{path}: missing column 'lux' (or 'grey' with a monitor table)")


# --------------------------------------------------------------------------------------
# files
# --------------------------------------------------------------------------------------
def read_rate_table(path, *, monitor: MonitorTable | None = None, monitor_model: str = "interp") -> Measurements:
    """Read a rate table (CSV; schema in the module docstring).

    Parameters
    ----------
    path : str or os.PathLike
        The CSV file.
    monitor : MonitorTable, optional
        Converts a ``grey`` column to lux; required when the levels are given as grey.
    monitor_model : {"interp", "gamma"}, default "interp"
        How grey levels are converted, as in :func:`grey_to_lux`.

    Returns
    -------
    Measurements
        The table's measurements (from rates, or from counts when it has ``count_on, count_off`` columns).
    """
    path = Path(path)
    header, body = _read_csv_rows(path)
    lux, grey = _levels_from(path, header, body, monitor, monitor_model)
    col = lambda name, required=False: _column(path, header, body, name, required=required)  # noqa: E731
    npx, dur = col("n_pixels"), col("duration_s")
    r_on, r_off = col("r_on"), col("r_off")
    src = str(path)
    if "count_on" in header or "count_off" in header:
        if npx is None or dur is None:
            raise InputError(f"{path}: count columns need 'n_pixels' and 'duration_s' columns")
        return count_table(lux, col("count_on", True), col("count_off", True), npx, dur, r_on=r_on, r_off=r_off,
                           source=src, grey=grey)
    return rate_table(lux, col("rate_on_hz", True), col("rate_off_hz", True), n_pixels=npx, duration_s=dur,
                      r_on=r_on, r_off=r_off, source=src, grey=grey)


def _listing_entries(path: Path):
    """Entries ``dict(file, lux|grey, duration_s?, t_start_s?, t_end_s?, roi?)`` of a listing."""
    if path.suffix.lower() == ".toml":
        try:
            doc = tomllib.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise InputError(f"file not found: {path}") from None
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise InputError(f"{path} is not valid TOML: {exc}") from None
        except RecursionError:  # arrays nested past the recursion limit
            raise InputError(f"{path} is not a listing: its TOML nests too deeply") from None
        except ValueError as exc:  # an integer of more than 4300 digits
            raise InputError(f"{path} is not a listing: {str(exc).split(';')[0]}") from None
        levels = doc.get("level")
        if not isinstance(levels, list) or not levels or not all(isinstance(e, dict) for e in levels):
            raise InputError(f"{path}: expected [[level]] tables with file and lux (or grey)")
        allowed = {"file", "lux", "grey", "duration_s", "t_start_s", "t_end_s", "roi", "sensor", "csv_columns"}
        for i, e in enumerate(levels):
            unknown = set(e) - allowed
            if unknown:
                raise InputError(f"{path}: level {i + 1} has unknown key(s) {', '.join(sorted(unknown))}")
            if "file" not in e:
                raise InputError(f"{path}: level {i + 1} has no 'file'")
        return levels
    header, body = _read_csv_rows(path)
    if "file" not in header:
        raise InputError(f"{path}: a flat-field listing needs a 'file' column")
    entries = []
    k = header.index("file")
    for row in body:
        e = {"file": row[k].strip()}
        for name in ("lux", "grey", "duration_s", "t_start_s", "t_end_s"):
            if name in header:
                v = _column(path, header, [row], name)[0]
                if not math.isnan(v) or name in ("lux", "grey"):
                    e[name] = v
        entries.append(e)
    return entries


def _num(e, key, where):
    v = e.get(key)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise InputError(f"{where}: '{key}' must be a number, got {v!r}")
    try:
        v = float(v)
    except OverflowError:  # an integer beyond the double range
        v = math.inf
    if not math.isfinite(v) or v < 0:
        raise InputError(f"{where}: '{key}' must be finite and >= 0, got {v!r}")
    return v


def read_flat_fields(path, *, monitor: MonitorTable | None = None, monitor_model: str = "interp",
                     progress: bool = False) -> Measurements:
    """Per-pixel counts from a flat-field listing (TOML or CSV; schema in the module docstring).

    Parameters
    ----------
    path : str or os.PathLike
        The listing, TOML (``[[level]]`` tables) if its suffix is ``.toml``, otherwise CSV.
        Relative file names in it are relative to its folder.
    monitor : MonitorTable, optional
        Converts ``grey`` levels to lux; required when the levels are given as grey.
    monitor_model : {"interp", "gamma"}, default "interp"
        How grey levels are converted, as in :func:`grey_to_lux`.
    progress : bool, default False
        Show a progress bar over the recordings read.

    Returns
    -------
    Measurements
        Flat-field measurements, as from :func:`flat_field`.
    """
    from evnoise.events import count_events
    from evnoise.io import read_events

    path = Path(path)
    entries = _listing_entries(path)
    where = str(path)
    has_lux = ["lux" in e for e in entries]
    has_grey = ["grey" in e for e in entries]
    if all(has_lux) and not any(has_grey):
        lux = _vector([e["lux"] for e in entries], "lux", where)
        grey = None
    elif all(has_grey) and not any(has_lux):
        if monitor is None:
            raise InputError(f"{where}: levels are given as grey; a monitor table (grey -> lux) is needed")
        grey = _vector([e["grey"] for e in entries], "grey", where)
        _check_levels(grey, where, "grey")
        lux = grey_to_lux(grey, monitor, model=monitor_model)
    else:
        raise InputError(f"{where}: every level needs a lux value (or every level a grey value)")
    _check_levels(lux if grey is None else grey, where, "lux" if grey is None else "grey")
    counts, ids, durations, files = [], [], [], []
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(entries), desc="read flat fields", unit="file", leave=False)
    for i, e in enumerate(entries):
        lw = f"{where}, level {i + 1}"
        file = Path(str(e["file"]))
        if not file.is_absolute():
            file = path.parent / file
        t0 = _num(e, "t_start_s", lw)
        t1 = _num(e, "t_end_s", lw)
        dur = _num(e, "duration_s", lw)
        t0_us = 0 if t0 is None else int(round(t0 * 1e6))
        t1_us = None if t1 is None else int(round(t1 * 1e6))
        # any event file evnoise reads (events.h5 or a camera recording; sensor = "WxH" where its header has none)
        events, meta = read_events(file, None if t0 is None else t0_us, t1_us, sensor=e.get("sensor"),
                                   csv_columns=e.get("csv_columns"))
        if t0 is None and meta.get("format", "h5") != "h5" and events.size:
            t0_us = int(events["t"][0])  # a camera clock starts anywhere: count from the first event
        shape = meta.get("shape")
        if shape is None:
            raise InputError(f"{file}: the file does not record the sensor size; add sensor = \"WxH\" to its level")
        if t1_us is None:
            if dur is not None:
                t1_us = t0_us + int(round(dur * 1e6))
            elif meta.get("t_end_us") is not None:
                t1_us = int(meta["t_end_us"])
            else:
                raise InputError(f"{lw}: the recording's length is unknown; give 'duration_s' or 't_end_s'")
        if t1_us <= t0_us:
            raise InputError(f"{lw}: empty counting window [{t0_us}, {t1_us}) us")
        duration = (t1_us - t0_us) * 1e-6
        if dur is not None and abs(dur - duration) > 1e-6:
            raise InputError(f"{lw}: 'duration_s' = {dur} disagrees with 't_end_s' - 't_start_s' = {duration}")
        c = count_events(events, shape, t0_us, t1_us)
        height, width = shape
        roi = e.get("roi")
        if roi is not None:
            if not (isinstance(roi, list) and len(roi) == 4 and all(isinstance(v, int) for v in roi)):
                raise InputError(f"{lw}: 'roi' must be [y0, y1, x0, x1] (integers), got {roi!r}")
            y0, y1, x0, x1 = roi
            if not (0 <= y0 < y1 <= height and 0 <= x0 < x1 <= width):
                raise InputError(f"{lw}: 'roi' {roi} is outside the sensor (H, W) = {shape} or empty")
        else:
            y0, y1, x0, x1 = 0, height, 0, width
        yy, xx = np.mgrid[y0:y1, x0:x1]
        counts.append(c[:, y0:y1, x0:x1].reshape(2, -1))
        ids.append((yy * width + xx).ravel().astype(np.int64))
        durations.append(duration)
        files.append(str(e["file"]))
        if bar is not None:
            bar.update(1)
    if bar is not None:
        bar.close()
    return flat_field(lux, counts, np.array(durations), pixel_ids=ids, source=f"{where} ({', '.join(files)})",
                      grey=grey)


def read_measurements(path, *, monitor=None, monitor_model: str = "interp", progress: bool = False) -> Measurements:
    """Read a rate table or a flat-field listing (told apart by a ``file`` column / ``[[level]]``).

    Parameters
    ----------
    path : str or os.PathLike
        A rate table (CSV) or a flat-field listing (TOML, or CSV with a ``file`` column). An
        events.h5 file, a camera recording or an image is refused with a message saying what to give.
    monitor : MonitorTable or str or os.PathLike, optional
        A monitor table, or the path of a ``grey, lux`` CSV read with :func:`read_monitor_table`;
        required when the levels are given as grey.
    monitor_model : {"interp", "gamma"}, default "interp"
        How grey levels are converted, as in :func:`grey_to_lux`.
    progress : bool, default False
        Show a progress bar while a flat-field listing's recordings are read.

    Returns
    -------
    Measurements
        The measurements read.
    """
    path = check_input_file(path, missing="measurements", kind="a table or a listing file")
    if monitor is not None and not isinstance(monitor, MonitorTable):
        monitor = read_monitor_table(monitor)
    if path.suffix.lower() == ".toml":
        return read_flat_fields(path, monitor=monitor, monitor_model=monitor_model, progress=progress)
    suffix = path.suffix.lower()
    if suffix in (".h5", ".hdf5"):
        raise InputError(f"{path}: give a listing (TOML or CSV with file and lux columns) of the flat-field "
                         f"recordings, not a single events.h5 file")
    if suffix not in (".csv", ".txt", ".tsv", ""):
        from evnoise.formats import formats_for_suffix
        from evnoise.radiometry import IMAGE_EXTENSIONS

        if formats_for_suffix(suffix):  # a camera recording given without its still window
            raise InputError(f"{path} is an event recording, not a rate table: a quiet-scene calibration needs its "
                             f"still window, --t-start S --t-end S (seconds on the file's own clock; `evnoise info "
                             f"{path}` shows its span) or --window A:B")
        if suffix in IMAGE_EXTENSIONS:
            raise InputError(f"{path} is an image; calibrate takes a rate table (CSV), a flat-field listing (TOML or "
                             f"CSV) or a recording with --t-start/--t-end")
    header, _ = _read_csv_rows(path)
    if "file" in header:
        return read_flat_fields(path, monitor=monitor, monitor_model=monitor_model, progress=progress)
    return read_rate_table(path, monitor=monitor, monitor_model=monitor_model)
