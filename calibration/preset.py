"""Writing a calibration result as a preset TOML (readable by :func:`evnoise.load_preset`)."""

from __future__ import annotations

import dataclasses
import datetime as _dt
import json
import math
from pathlib import Path

from evnoise._version import __version__

__all__ = ["result_to_toml", "write_text_atomic", "toml_value"]


def toml_value(v, *, digits: int | None = 7) -> str:
    """One TOML value: numbers, booleans, strings, lists and flat dicts (inline tables).

    Floats are rounded to ``digits`` significant digits (``None``: exact round trip).
    """
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(float(v)) if digits is None else repr(float(f"{v:.{digits}g}"))
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=True)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x, digits=digits) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_key(k)} = {toml_value(x, digits=digits)}" for k, x in v.items()) + " }"
    if hasattr(v, "item"):  # numpy scalar
        return toml_value(v.item(), digits=digits)
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def _key(k: str) -> str:
    return k if k.replace("_", "").replace("-", "").isalnum() else json.dumps(k)


def toml_table(name: str, items: dict, *, digits: int | None = 7) -> list[str]:
    lines = [f"[{name}]"]
    for k, v in items.items():
        if v is None:
            continue
        lines.append(f"{_key(k)} = {toml_value(v, digits=digits)}")
    return lines


def result_to_toml(result, *, extra_provenance: dict | None = None, header: str | None = None) -> str:
    """The preset document of a :class:`~evnoise.calibration.CalibrationResult`."""
    p = result.params
    names = [f.name for f in dataclasses.fields(p)]  # every parameter, in NoiseParams' order
    lines = []
    if header:
        lines += [f"# {ln}" if ln else "#" for ln in header.splitlines()]
        lines.append("")
    lines += toml_table("params", {n: float(getattr(p, n)) for n in names}, digits=None)
    lines.append("")
    prov = {
        "source": result.measurements.source,
        "method": f"maximum likelihood, {result.method} closed form"
                  + (f", {result.distribution} counts per pixel" if result.measurements.kind == "flat-field" else ""),
        "measurements": f"{result.measurements.kind}, {result.measurements.n_levels} levels, "
                        f"{result.measurements.lux.min():.4g} to {result.measurements.lux.max():.4g} lux",
        "date": _dt.date.today().isoformat(),
        "evnoise_version": __version__,
    }
    lo, hi = float(result.measurements.lux.min()), float(result.measurements.lux.max())
    if 0.0 <= lo < hi:  # the light range the fit saw: evnoise simulate warns outside it (params.light_range_warning)
        prov["fitted_lux"] = [lo, hi]
        prov["fitted_lux_note"] = f"measured: the light levels of the {result.measurements.kind} measurements"
    if extra_provenance:
        prov.update(extra_provenance)
    lines += toml_table("provenance", prov)
    lines.append("")
    fit = {"free": list(result.free), "log_likelihood": float(result.loglik),
           "fit_status": getattr(result, "fit_status", "accepted"), "warnings": list(getattr(result, "warnings", []))}
    if getattr(result, "at_bound", None):
        fit["at_bound"] = dict(result.at_bound)
    lines += toml_table("fit", fit)
    lines.append("")
    lines += toml_table("fit.status", {n: result.status.get(n, "fixed") for n in names})
    lines.append("")
    lines += toml_table("fit.std_error", {n: float(result.std_error[n]) for n in result.free})
    lines.append("")
    lines += toml_table("fit.relative_error", {n: float(result.rel_error[n]) for n in result.free})
    lines.append("")
    gof = {k: (v if not isinstance(v, dict) else {a: float(b) for a, b in v.items()}) for k, v in result.gof.items()}
    lines += toml_table("fit.quality", gof)
    lines.append("")
    disp = {k: float(v) for k, v in result.dispersion.items() if isinstance(v, float)}
    if result.dispersion.get("summary"):
        disp["summary"] = result.dispersion["summary"]
    if disp:
        lines += toml_table("fit.dispersion", disp)
        lines.append("")
    lines += toml_table("fit.identifiability", {"findings": list(result.identifiability), "notes": list(result.notes)})
    lines.append("")
    return "\n".join(lines)


def write_text_atomic(path, text: str, *, overwrite: bool = False) -> Path:
    """Write a preset ``text`` to ``path`` through a temporary file and a rename (never half-written).

    Parameters
    ----------
    path : str or os.PathLike
        The file to write; its folder must exist.
    text : str
        The preset's TOML text, written as UTF-8.
    overwrite : bool, default False
        Replace an existing file; otherwise an existing ``path`` is an error.

    Returns
    -------
    pathlib.Path
        The path written.

    Raises
    ------
    evnoise.OutputError
        When the folder does not exist, ``path`` exists and ``overwrite`` is false, or the write fails.
    """
    from evnoise._atomic import write_text_atomic as _write

    return _write(path, text, overwrite=overwrite, what="preset")
