"""N-MNIST / N-Caltech101 ``.bin`` (ATIS saccades, 34x34 for N-MNIST), through tonic.

5-byte records (x, y, polarity and a 23-bit timestamp); tonic's ``read_mnist_file`` decodes
them and unwraps the timestamp overflow markers. The format has no header: the sensor is
34x34 (N-MNIST) unless ``sensor`` says otherwise (N-Caltech101 recordings are larger). Files
are small (one digit, ~0.3 s), so they are read whole.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ._base import EventSource, decoder_error, to_events, tonic_io

#: Sensor of the N-MNIST recordings (W, H).
NMNIST_SENSOR = (34, 34)

_DTYPE = np.dtype([("x", np.int64), ("y", np.int64), ("t", np.int64), ("p", np.int64)])


class NmnistSource(EventSource):
    format = "nmnist"

    def __init__(self, path, *, sensor=None):
        super().__init__(path, sensor=sensor)
        size = self.path.stat().st_size
        if size % 5:
            raise InputError(f"cannot read {self.path} as N-MNIST: {size} bytes is not a whole number of 5-byte "
                             f"events (truncated file?)")
        self.meta = {"note": "N-MNIST has no header; 34x34 assumed unless sensor= is given"}
        self._set_shape((NMNIST_SENSOR[1], NMNIST_SENSOR[0]), source="format")
        self.meta.pop("header_sensor", None)

    def _chunks(self, t_start_us, t_end_us):
        tio = tonic_io()
        try:
            raw = tio.read_mnist_file(str(self.path), dtype=_DTYPE)
        except BaseException as exc:  # noqa: BLE001 - see decoder_error
            raise decoder_error(self.path, "N-MNIST", exc) from None
        if raw.size:
            yield to_events(raw["t"], raw["x"], raw["y"], raw["p"])
