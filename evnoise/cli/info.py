"""``evnoise info FILE``: what a file holds (events.h5 now; datasets and models are added later).

Kinds of file are registered in :data:`KINDS`: ``name -> (detect, summarise)``, where
``detect(path) -> bool`` is cheap (magic bytes, a manifest name, a quick look inside) and
``summarise(path) -> dict`` returns ``{label: value}`` in display order (values are plain
JSON types). The first kind whose ``detect`` is true wins. To add a kind, call
:func:`register_kind` from this module (import the heavy parts inside the two functions),
e.g. ``register_kind("dataset", _is_dataset, _summarise_dataset)``.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Callable

from .._budget import human_bytes
from ..errors import InputError, ParameterError

Detector = Callable[[Path], bool]
Summariser = Callable[[Path], dict]

#: kind name -> (detect, summarise), tried in insertion order
KINDS: dict[str, tuple[Detector, Summariser]] = {}


def register_kind(name: str, detect: Detector, summarise: Summariser) -> None:
    """Make ``evnoise info`` understand another kind of file."""
    KINDS[name] = (detect, summarise)


def register(subparsers) -> None:
    from . import _options as opt

    p = subparsers.add_parser(
        "info",
        help=f"summarise a file: events.h5 or a camera recording ({opt.event_suffixes()}), a dataset, a model",
        description="Summarise a file: for an event file (evnoise's events.h5 or a camera recording) the "
        "sensor size, duration, event counts and rates, and the header's facts (model parameters, seed and "
        "version for evnoise's files); with --stats the noise statistics of the recording. "
        f"Known kinds: {', '.join(KINDS) or 'none'}.",
    )
    p.add_argument("file", metavar="FILE", help="the file to describe")
    opt.add_json_output(p, help="print the summary as JSON (numbers as numbers, units in the keys)")
    ev = p.add_argument_group("event files")
    opt.add_sensor(ev, help="sensor size, e.g. 640x480, for files whose header has none (EVT 2.0, CSV, N-CARS "
                   ".dat) or a wrong one")
    opt.add_t_start(ev, help="start of the time window, seconds on the file's clock")
    opt.add_t_end(ev, help="end of the time window (exclusive), seconds on the file's clock")
    opt.add_csv_columns(ev)
    ev.add_argument("--stats", action="store_true",
                    help="noise statistics: rate per pixel (mean, quantiles), ON fraction, active pixels, "
                    "variance/mean of per-pixel counts, hot pixels")
    ev.add_argument("--hot-threshold", type=float, metavar="N",
                    help="--stats: a pixel is hot above N events (default: 10 x the mean count of active pixels, "
                    "at least 10)")
    opt.add_png(ev, help="--stats: also write a PNG of the ON/OFF count maps and the per-pixel count histogram")
    opt.add_overwrite(ev, help="replace an existing --png file")
    p.set_defaults(func=run)


_EVENT_FLAGS = ("sensor", "t_start", "t_end", "csv_columns", "hot_threshold", "png")


def detect_kind(path) -> str:
    """Name of the registered kind of ``path``; :class:`~evnoise.InputError` if none fits."""
    from .._checks import check_input_file

    path = check_input_file(path, missing="file", kind="a file or a dataset folder", folders=True)
    for name, (detect, _) in KINDS.items():
        if detect(path):
            return name
    raise InputError(f"{path}: not a kind of file evnoise knows ({', '.join(KINDS)})")


def summarise(path) -> dict:
    """``{"file": ..., "kind": ..., ...}`` for any registered kind of file."""
    path = Path(path)
    kind = detect_kind(path)
    return {"file": os.fspath(path), "kind": kind, **KINDS[kind][1](path)}


def run(args) -> int:
    path = Path(args.file)
    from ._paths import refuse_writing_inputs

    refuse_writing_inputs([("--png", getattr(args, "png", None))], [("the input file", path)])
    kind = detect_kind(path)
    given = [f"--{k.replace('_', '-')}" for k in _EVENT_FLAGS if getattr(args, k, None) is not None]
    if getattr(args, "stats", False):
        given.append("--stats")
    if kind == "events":
        if (args.png or args.hot_threshold is not None) and not args.stats:
            raise ParameterError("--png and --hot-threshold go with --stats")
        info = {"file": os.fspath(path), "kind": kind,
                **summarise_events(path, sensor=args.sensor, t_start=args.t_start, t_end=args.t_end,
                                   csv_columns=args.csv_columns, stats=args.stats, hot_threshold=args.hot_threshold,
                                   png=args.png, overwrite=args.overwrite)}
        info = _in_flags(info, getattr(args, "cli_flags", {}))
    else:
        if given:
            raise ParameterError(f"{', '.join(given)}: only for event files; {path} is a {kind}")
        info = summarise(path)
    if args.json:
        print(json.dumps(info, indent=2, default=_plain))
    else:
        print(format_summary(info))
    return 0


#: summary entries whose text the library words with Python names (``given (hot_threshold)``)
_WORDED = {"rule", "columns_from", "note"}


def _in_flags(info, flags: dict):
    """``info`` with the Python names in the library's notes (:data:`_WORDED`) written as info's flags."""
    from ._options import flag_names

    if isinstance(info, dict):
        return {k: flag_names(v, flags) if k in _WORDED and isinstance(v, str) else _in_flags(v, flags)
                for k, v in info.items()}
    return info


def format_summary(info: dict, indent: str = "") -> str:
    """``label: value`` lines; nested dicts are indented below their label."""
    lines = []
    width = max((len(k) for k in info), default=0)
    for key, value in info.items():
        if isinstance(value, dict):
            lines.append(f"{indent}{key}:")
            lines.append(format_summary(value, indent + "  "))
        else:
            lines.append(f"{indent}{key + ':':<{width + 1}}  {_fmt(key, value)}")
    return "\n".join(line for line in lines if line)


_COUNTS = {"events", "ON", "OFF", "count", "pixels"}
#: times on the file's clock (often Unix time, 1.6e9 s): printed to the microsecond
_CLOCK = {"t_start_s", "t_end_s"}


def _fmt(key, value) -> str:
    if key == "size_bytes" and isinstance(value, int):
        return f"{value:,} ({human_bytes(value)})"
    if value is None:
        return "-"
    if key in _CLOCK and isinstance(value, float):
        from .._clock import seconds_text

        return seconds_text(value)
    if isinstance(value, float):
        return f"{value:.6g}"
    if key in _COUNTS and isinstance(value, int) and not isinstance(value, bool):
        return f"{value:,}"
    return str(value)


# --------------------------------------------------------------------------------------
# event files: evnoise's events.h5 and camera recordings
# --------------------------------------------------------------------------------------
def _is_event_file(path: Path) -> bool:
    from ..readers import is_event_file

    return is_event_file(path)


def summarise_events(path, *, sensor=None, t_start=None, t_end=None, csv_columns=None, stats: bool = False,
                     hot_threshold=None, png=None, overwrite: bool = False) -> dict:
    """Summary of an event file (any format :mod:`evnoise.readers` opens): plain JSON numbers, units in keys."""
    from ..formats import clock_note, describe
    from ..readers import open_events, time_window
    from ..readers.stats import noise_stats, pixel_counts, stats_png

    path = Path(path)
    a_us, b_us = time_window(t_start, t_end)
    if png is not None:
        from ..io import open_output_path

        open_output_path(png, overwrite=overwrite, what="PNG file")
    src = open_events(path, sensor=sensor, csv_columns=csv_columns)
    out: dict = {"format": describe(src.format), "size_bytes": path.stat().st_size}
    meta = dict(src.meta)
    with src:
        counts, (n, t_first, t_last) = pixel_counts(src.chunks(a_us, b_us), src.shape)
    n_on = int(counts[0].sum())
    shape = src.shape
    if shape is not None:
        out["sensor"] = f"{shape[1]}x{shape[0]}"
        out["sensor_from"] = {"header": "the file's header", "sensor": "--sensor", "format": "the format (fixed size)"}[
            src.shape_from]
    else:
        extent = f"{counts.shape[2]}x{counts.shape[1]}" if n else "no events"
        out["sensor"] = None
        out["sensor_note"] = (f"the header has no sensor size; the events span {extent} (x, y from 0); "
                              f"give --sensor WxH")
    if n == 0 and (a_us is not None or b_us is not None):
        logging.getLogger(__name__).warning(
            "%s: no events in the window; camera clocks do not start at 0 (a DVS128 file at tens of seconds, an "
            "AEDAT 4 file at the Unix time): `evnoise info %s` without --t-start/--t-end gives the file's first and "
            "last event's time (t_first_us, t_last_us)", path, path)
    out["events"] = n
    out["ON"] = n_on
    out["OFF"] = n - n_on
    out["on_fraction"] = n_on / n if n else None
    out["t_first_us"] = t_first
    out["t_last_us"] = t_last
    clock = clock_note(src.format)
    if clock is not None:
        out["clock"] = clock
    # evnoise's own clock starts at 0 and the file stores its end; a shifted (t_offset) or camera clock
    # has neither, and the recording spans first to last event
    t_end_attr = meta.get("t_end_us") if src.format == "h5" and not meta.get("t_offset") else None
    if a_us is not None and b_us is not None:
        duration_us = b_us - a_us
    elif t_end_attr is not None and b_us is None:
        duration_us = int(t_end_attr) - (a_us if a_us is not None else int(meta.get("t_start_us", 0)))
    elif n:
        start = a_us if a_us is not None else t_first
        end = b_us if b_us is not None else t_last
        own = src.format == "h5" and not meta.get("t_offset")
        duration_us = end - start + (1 if own and a_us is None and b_us is None else 0)
    else:
        duration_us = 0
    out["duration_s"] = duration_us * 1e-6
    if a_us is not None or b_us is not None:
        out["window_s"] = {"t_start_s": None if a_us is None else a_us * 1e-6,
                           "t_end_s": None if b_us is None else b_us * 1e-6}
    if shape is not None and duration_us > 0:
        pixels_s = shape[0] * shape[1] * duration_us * 1e-6
        out["rate_per_pixel_hz"] = {"total": n / pixels_s, "ON": n_on / pixels_s, "OFF": (n - n_on) / pixels_s}
    if duration_us > 0:
        out["event_rate_hz"] = n / (duration_us * 1e-6)
    if stats:
        if shape is None:
            raise InputError(f"{path}: --stats needs the sensor size, which the header does not give; "
                             f"add --sensor WxH (the events span {counts.shape[2]}x{counts.shape[1]})")
        if duration_us <= 0:
            raise InputError(f"{path}: no time span to compute rates over (fewer than two distinct timestamps)")
        st = noise_stats(counts, duration_us * 1e-6, hot_threshold=hot_threshold)
        out["stats"] = {k: v for k, v in st.items() if k not in ("events", "duration_s")}
        if png is not None:
            from .._clock import seconds_text

            window = "" if "window_s" not in out else \
                f", t {seconds_text((a_us if a_us is not None else t_first) * 1e-6)}" \
                f"-{seconds_text((b_us if b_us is not None else t_last) * 1e-6)} s"
            stats_png(png, counts, title=f"{path.name}{window}: {n:,} events, {out['duration_s']:.6g} s",
                      overwrite=overwrite)
            out["png"] = os.fspath(png)
    if src.format == "h5":
        _h5_details(path, meta, out)
    else:
        header = {k: _plain(v) for k, v in meta.items() if v is not None}
        if "evnoise_version" in header:  # written by evnoise (.aedat4 keeps its attributes)
            for key in ("evnoise_version", "seed", "source", "preset", "method", "scene", "params"):
                if key in header:
                    out[key] = header.pop(key)
        if header:
            out["header"] = header
    return out


def _h5_details(path, meta, out):
    """evnoise's attributes of an events.h5 file (parameters, seed, version, ...)."""
    import h5py

    with h5py.File(path, "r") as f:
        out["compression"] = f["events/t"].compression or "none"
    for key in ("evnoise_version", "seed", "source", "preset", "method", "scene"):
        if key in meta:
            out[key] = meta[key]
    if isinstance(meta.get("params"), dict):
        out["params"] = meta["params"]
    skip = {"width", "height", "shape", "n_events", "t_offset", "time_unit", "t_end_us", "params", "header_sensor",
            *out}
    extra = {k: _plain(v) for k, v in meta.items() if k not in skip}
    if meta.get("t_offset"):
        extra["t_offset_us"] = meta["t_offset"]
    if extra:
        out["attributes"] = extra


def _plain(value):
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, (tuple, set)):
        return list(value)
    return value


register_kind("events", _is_event_file, lambda path: summarise_events(path))
