"""CSV event lists, through faery's CSV decoder (streamed).

One event per line, comma-separated, integer microseconds, polarity ``1`` (ON) / ``0`` (OFF).
The column order comes from ``csv_columns`` (``"x,y,p,t"``: the EvCamMOKE files have that order
and no header) or, without it, from a header line naming the columns (``t``/``timestamp``,
``x``, ``y``, ``p``/``polarity``/``on``). A file with neither is refused rather than guessed.
A header written by faery (``t,x@W,y@H,on``) gives the sensor size; otherwise pass ``sensor``, or
the events' extent is reported.
"""

from __future__ import annotations

from ..errors import InputError, ParameterError
from ._base import EventSource, decoder_error, from_faery, packets_in_window, require

_ALIASES = {
    "t": "t", "ts": "t", "t_us": "t", "time": "t", "timestamp": "t", "timestamp_us": "t",
    "x": "x", "y": "y",
    "p": "p", "pol": "p", "polarity": "p", "on": "p",
}


def parse_columns(text) -> dict[str, int]:
    """``"x,y,p,t"`` (or a list of names) -> ``{"t": 3, "x": 0, "y": 1, "p": 2}``; other names are skipped columns."""
    names = text.split(",") if isinstance(text, str) else list(text)
    out: dict[str, int] = {}
    for i, name in enumerate(n.strip().lower() for n in names):
        key = _ALIASES.get(name)
        if key is None:
            continue
        if key in out:
            raise ParameterError(f"--csv-columns names {key!r} twice: {text!r}")
        out[key] = i
    missing = [k for k in "txyp" if k not in out]
    if missing:
        raise ParameterError(f"--csv-columns must name the columns t, x, y and p (e.g. x,y,p,t); "
                             f"{', '.join(missing)} missing in {text!r}")
    return out


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


class CsvSource(EventSource):
    format = "csv"

    def __init__(self, path, *, sensor=None, csv_columns=None):
        super().__init__(path, sensor=sensor)
        require("faery", "CSV event files")
        with open(self.path, "rb") as fh:
            first = fh.readline().decode("utf-8", "replace").strip()
        if not first:
            raise InputError(f"{self.path}: empty CSV file (no events, no header)")
        tokens = [tok.strip() for tok in first.split(",")]
        self._has_header = not all(_is_number(tok) for tok in tokens)
        if csv_columns is not None:
            cols = parse_columns(csv_columns)
        elif self._has_header:
            try:
                cols = parse_columns([tok.split("@")[0] for tok in tokens])
            except ParameterError:
                raise InputError(f"{self.path}: the CSV header {first!r} does not name t, x, y and p; give the "
                                 f"column order with --csv-columns (e.g. x,y,p,t)") from None
        else:
            raise InputError(f"{self.path}: a CSV file without a header; give the column order with --csv-columns "
                             f"(e.g. --csv-columns x,y,p,t)")
        if max(cols.values()) >= len(tokens):
            raise InputError(f"{self.path}: the first line has {len(tokens)} columns; --csv-columns needs "
                             f"{max(cols.values()) + 1}")
        self._cols = cols
        self.meta = {"columns": ",".join(k for k, _ in sorted(cols.items(), key=lambda kv: kv[1])),
                     "header_line": self._has_header, "time_unit": "us"}
        header_shape = None
        if self._has_header:  # faery writes the sensor size into the header: t,x@W,y@H,on
            sizes = dict(tok.split("@", 1) for tok in tokens if "@" in tok)
            if sizes.get("x", "").isdigit() and sizes.get("y", "").isdigit():
                header_shape = (int(sizes["y"]), int(sizes["x"]))
        self._set_shape(header_shape)
        self._dims = (65535, 65535) if self.shape is None else (self.shape[1], self.shape[0])

    def _chunks(self, t_start_us, t_end_us):
        from faery.extension import csv

        c = self._cols
        try:
            with csv.Decoder(self.path, self._dims, self._has_header, ord(","), c["t"], c["x"], c["y"], c["p"], 0.0,
                             0, b"1", b"0", False) as dec:
                for packet in packets_in_window(dec, t_start_us, t_end_us):
                    yield from_faery(packet)
        except BaseException as exc:  # noqa: BLE001 - see decoder_error - faery raises plain exceptions
            raise decoder_error(self.path, "CSV events", exc) from None
