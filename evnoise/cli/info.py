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
import os
from pathlib import Path
from typing import Callable

from ..errors import InputError

Detector = Callable[[Path], bool]
Summariser = Callable[[Path], dict]

#: kind name -> (detect, summarise), tried in insertion order
KINDS: dict[str, tuple[Detector, Summariser]] = {}


def register_kind(name: str, detect: Detector, summarise: Summariser) -> None:
    """Make ``evnoise info`` understand another kind of file."""
    KINDS[name] = (detect, summarise)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "info",
        help="summarise a file made by evnoise (events.h5, ...)",
        description="Summarise a file: for an events.h5 file the sensor size, duration, event counts "
        f"and rates, model parameters, seed and version. Known kinds: {', '.join(KINDS) or 'none'}.",
    )
    p.add_argument("file", metavar="FILE", help="the file to describe")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=run)


def detect_kind(path) -> str:
    """Name of the registered kind of ``path``; :class:`~evnoise.InputError` if none fits."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"file not found: {path}")
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
    info = summarise(args.file)
    if args.json:
        print(json.dumps(info, indent=2, default=str))
    else:
        print(format_summary(info))
    return 0


def format_summary(info: dict) -> str:
    """``label: value`` lines; nested dicts are indented below their label."""
    lines = []
    width = max((len(k) for k in info), default=0)
    for key, value in info.items():
        if isinstance(value, dict):
            lines.append(f"{key}:")
            inner = max((len(k) for k in value), default=0)
            lines.extend(f"  {k:<{inner}}  {_fmt(k, v)}" for k, v in value.items())
        else:
            lines.append(f"{key + ':':<{width + 1}}  {_fmt(key, value)}")
    return "\n".join(lines)


_COUNTS = {"events", "ON", "OFF"}


def _fmt(key, value) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    if key in _COUNTS and isinstance(value, int) and not isinstance(value, bool):
        return f"{value:,}"
    return str(value)


# --------------------------------------------------------------------------------------
# events.h5
# --------------------------------------------------------------------------------------
_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"


def _is_events_h5(path: Path) -> bool:
    if not path.is_file():
        return False
    try:
        with open(path, "rb") as fh:
            if fh.read(8) != _HDF5_MAGIC:
                return False
    except OSError:
        return False
    import h5py

    try:
        with h5py.File(path, "r") as f:
            group = f.get("events")
            return isinstance(group, h5py.Group) and all(k in group for k in "xytp")
    except OSError:
        return False


def _summarise_events(path: Path) -> dict:
    import numpy as np

    from ..io import READ_BLOCK, _event_datasets, _metadata, _open_h5

    with _open_h5(path) as f:
        ds = _event_datasets(f, path)
        meta = _metadata(f, ds)
        n = meta["n_events"]
        n_on = 0
        for lo in range(0, n, READ_BLOCK):
            n_on += int(np.count_nonzero(ds["p"][lo:lo + READ_BLOCK]))
        t_first = int(ds["t"][0]) if n else None
        t_last = int(ds["t"][n - 1]) if n else None
        compression = ds["t"].compression
    t_start = int(meta.get("t_start_us", 0))
    if "t_end_us" in meta:
        duration_s = (int(meta["t_end_us"]) - t_start) * 1e-6
    elif n:
        duration_s = (t_last - t_first + 1) * 1e-6
    else:
        duration_s = 0.0
    out = {"size": human_bytes(path.stat().st_size), "layout": "events.h5 (DSEC)"}
    shape = meta["shape"]
    out["sensor"] = f"{shape[1]}x{shape[0]}" if shape else "unknown (no width/height attributes)"
    out["events"] = n
    out["ON"] = n_on
    out["OFF"] = n - n_on
    out["duration_s"] = duration_s
    out["time_span_us"] = f"{t_first} .. {t_last}" if n else "no events"
    if shape and duration_s > 0:
        pixels = shape[0] * shape[1]
        out["rate_per_pixel_hz"] = {
            "total": n / (pixels * duration_s),
            "ON": n_on / (pixels * duration_s),
            "OFF": (n - n_on) / (pixels * duration_s),
        }
    if duration_s > 0:
        out["event_rate_hz"] = n / duration_s
    out["compression"] = compression or "none"
    for key in ("evnoise_version", "seed", "source", "preset", "method", "scene"):
        if key in meta:
            out[key] = meta[key]
    if isinstance(meta.get("params"), dict):
        out["params"] = meta["params"]
    skip = {"width", "height", "shape", "n_events", "t_offset", "time_unit", "t_end_us", "params", *out}
    extra = {k: _plain(v) for k, v in meta.items() if k not in skip}
    if meta.get("t_offset"):
        extra["t_offset"] = meta["t_offset"]
    if extra:
        out["attributes"] = extra
    return out


def _plain(value):
    if hasattr(value, "tolist"):
        return value.tolist()
    return value


def human_bytes(n: int) -> str:
    """``1234567`` -> ``'1.2 MB'`` (decimal units)."""
    for unit in ("B", "kB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n} B" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} TB"  # pragma: no cover


register_kind("events", _is_events_h5, _summarise_events)
