"""Event Stream ``.es`` (neuromorphic-paris), DVS and ATIS types, through faery.

The header holds the sensor size; y is flipped to evnoise's top-left origin as faery does
(Event Stream counts rows from the bottom). ATIS exposure measurements are dropped, change
detections kept. The ``generic`` and ``color`` types carry no polarity events and are refused.
Timestamps are delta-encoded, so a window is found by decoding from the start (stopping at
its end).
"""

from __future__ import annotations

from ..errors import InputError
from ._base import EventSource, decoder_error, packets_in_window, require, to_events


class EsSource(EventSource):
    format = "es"

    def __init__(self, path, *, sensor=None):
        super().__init__(path, sensor=sensor)
        require("faery", "Event Stream files")
        from faery.extension import es

        try:
            with es.Decoder(self.path, 0) as dec:
                kind, dims, version = dec.event_type, dec.dimensions, dec.version
        except BaseException as exc:  # noqa: BLE001 - see decoder_error
            raise decoder_error(self.path, "Event Stream", exc) from None
        if kind not in ("dvs", "atis"):
            raise InputError(f"{self.path}: Event Stream type {kind!r} holds no polarity events (dvs or atis needed)")
        self._kind = kind
        self._height = dims[1]
        self.meta = {"es_version": str(version), "event_type": kind}
        self._set_shape((dims[1], dims[0]))

    def _chunks(self, t_start_us, t_end_us):
        from faery.extension import es

        try:
            with es.Decoder(self.path, 0) as dec:
                atis = self._kind == "atis"
                packets = (p[~p["exposure"]] if atis else p for p in dec)  # ATIS: polarity events only
                for packet in packets_in_window(packets, t_start_us, t_end_us):
                    on = packet["polarity"] if atis else packet["on"]
                    yield to_events(packet["t"], packet["x"], (self._height - 1) - packet["y"].astype("i4"), on)
        except BaseException as exc:  # noqa: BLE001 - see decoder_error
            raise decoder_error(self.path, "Event Stream", exc) from None
