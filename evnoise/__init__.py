"""evnoise: the photon noise of event cameras, modelled exactly and put to work.

Importing evnoise is cheap: the numerical parts (Numba kernels, SciPy) load on first use.
"""

from __future__ import annotations

from ._lazy import lazy_attributes
from ._version import __version__
from .errors import EvnoiseError, InputError, OutputError, ParameterError
from .events import EVENT_DTYPE, count_events, events_from_array, events_to_array, merge_events
from .params import NoiseParams, list_presets, load_preset

_LAZY = {
    "event_probability": "evnoise.model",
    "log_event_probability": "evnoise.model",
    "expected_rate": "evnoise.rates",
    "draw_thresholds": "evnoise.rates",
    "draw_background": "evnoise.background",
    "background_rate": "evnoise.background",
    "sample_counts": "evnoise.simulate",
    "simulate_events": "evnoise.simulate",
    "iter_events": "evnoise.simulate",
    "simulate_video": "evnoise.simulate",
    "iter_video": "evnoise.simulate",
    "NoiseStream": "evnoise.stream",
    "write_events": "evnoise.io",
    "read_events": "evnoise.io",
    "iter_event_chunks": "evnoise.readers",
    "open_events": "evnoise.readers",
    "EventWriter": "evnoise.io",
    "image_to_lux": "evnoise.radiometry",
    "read_image": "evnoise.radiometry",
    "Separator": "evnoise.separation",
    "separate_events": "evnoise.separation",
    "density_filter": "evnoise.separation",
    "activity_filter": "evnoise.separation",
    "iter_motion": "evnoise.motion",
    "reconstruct_video": "evnoise.reconstruct.video",
}

__all__ = [
    "__version__",
    "EVENT_DTYPE",
    "EvnoiseError",
    "InputError",
    "OutputError",
    "ParameterError",
    "NoiseParams",
    "count_events",
    "events_from_array",
    "events_to_array",
    "list_presets",
    "load_preset",
    "merge_events",
    *_LAZY,
]


#: submodules that are attributes of the package on first access (``evnoise.io.read_metadata``)
_SUBMODULES = ("io", "readers", "plugins", "simulate", "stream", "model", "rates", "background", "mismatch",
               "radiometry", "separation", "motion", "reconstruct")

__getattr__, __dir__ = lazy_attributes(__name__, _LAZY, _SUBMODULES)
