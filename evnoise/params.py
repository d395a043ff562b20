"""Noise-model parameters as an immutable, validated value object, and presets.

Units are part of every field's name. Presets are TOML files shipped in
``evnoise/presets/`` (``load_preset("evk3-hd")``) or any TOML file with the same keys.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import tomllib

from .errors import ParameterError

__all__ = ["NoiseParams", "load_preset", "list_presets", "preset_info", "PARAM_LIMITS"]

#: Largest value each parameter may take: where the physics of a pixel ends (and with it what the
#: kernels are verified for). A threshold of 20 asks the light to change by a factor e^20 ~ 5e8
#: (170 dB, beyond any sensor's dynamic range); a photoreceptor sees at most 1e12 photons or 1e6
#: lux-equivalent of offset per trial; background rates (leak, hot pixel) stay below 1e9/s (a thousand
#: per microsecond, evnoise's time resolution; the model caps them at one event per trial); dead times
#: and time constants stay within an hour; a log-normal spread of 10 already spans a factor e^20
#: between pixels one sigma apart.
PARAM_LIMITS = {
    "eps_pos": 20.0,
    "eps_neg": 20.0,
    "eps_sigma": 20.0,
    "bias_pr": 1e12,
    "photons_per_lux": 1e12,
    "dark_lux": 1e6,
    "trial_rate_hz": 1e6,
    "refractory_s": 3600.0,
    "leak_on_hz": 1e9,
    "leak_off_hz": 1e9,
    "leak_on_hz_per_lux": 1e9,
    "leak_off_hz_per_lux": 1e9,
    "leak_sigma": 10.0,
    "hot_pixel_fraction": 1.0,
    "hot_pixel_rate_hz": 1e9,
    "hot_pixel_sigma": 10.0,
    "hot_pixel_on_fraction": 1.0,
    "leak_regularity": 1.0,
    "pr_tau_s_at_1lux": 3600.0,
}


@dataclass(frozen=True)
class NoiseParams:
    """Parameters of evnoise's photon-noise model of an event-camera pixel.

    Parameters
    ----------
    eps_pos : float
        ON (positive) log-intensity contrast threshold, dimensionless, ``> 0``.
    eps_neg : float
        OFF (negative) log-intensity contrast threshold, dimensionless, ``> 0``.
    bias_pr : float
        Photoreceptor bias ``b_pr``, in photons per trial, ``>= 0``; added to the photon count
        before the logarithm.
    trial_rate_hz : float
        Trials per second, ``N`` in the paper (the photoreceptor's effective sampling rate);
        one trial lasts ``1 / trial_rate_hz`` seconds.
    photons_per_lux : float
        Mean photons per trial per lux of illuminance at the sensor, ``> 0``.
    dark_lux : float, optional
        Illuminance-equivalent offset (dark current, stray light) in lux, ``>= 0``; the mean
        photon count per trial is ``lam = photons_per_lux * (lux + dark_lux)``.
    refractory_s : float, optional
        Refractory period in seconds, ``>= 0`` (rounded up to whole microseconds when
        simulating): non-paralyzable dead time after every event.
    eps_sigma : float, optional
        Standard deviation of the per-pixel threshold mismatch, ``>= 0``: each pixel's
        ``eps_pos`` and ``eps_neg`` are drawn once (independently, normal truncated to ``> 0``)
        and fixed for the whole run.
    leak_on_hz, leak_off_hz : float, optional
        Background activity (leak) of a pixel in the dark, events/s of each polarity, ``>= 0``:
        events that are not photon-noise threshold crossings (see :mod:`evnoise.background`).
    leak_on_hz_per_lux, leak_off_hz_per_lux : float, optional
        Growth of the background rate with illuminance, events/s per lux, ``>= 0``: the rate of a
        pixel at ``lux`` is ``leak_*_hz + leak_*_hz_per_lux * lux`` (times its spread factor).
    leak_sigma : float, optional
        Per-pixel spread of the background rates, ``>= 0``: each pixel's rates are multiplied by a
        log-normal factor of mean 1 whose logarithm has standard deviation ``leak_sigma``, drawn
        once per run.
    hot_pixel_fraction : float, optional
        Fraction of pixels that are hot, ``0 <= f <= 1``, chosen once per run.
    hot_pixel_rate_hz : float, optional
        Mean extra event rate of a hot pixel (both polarities together), events/s, ``>= 0``.
    hot_pixel_sigma : float, optional
        Log-normal spread of the hot pixels' rates (standard deviation of the log), ``>= 0``.
    hot_pixel_on_fraction : float, optional
        Share of a hot pixel's events that are ON, ``0 <= q <= 1`` (default 0.5).
    leak_regularity : float, optional
        How regular a pixel's background arrivals are, ``0 <= r <= 1``: 0 (default) Poisson arrivals
        (memoryless), 1 periodic (every ``1 / l`` seconds after the pixel's last event, up to one trial
        of jitter), in between a fixed part ``r`` of the mean interval plus a geometric remainder. Real
        leak events are close to periodic (a DVS128's quiet-scene counts are less dispersed than
        Poisson); the mean rate is the same for every ``r`` when photon noise is absent.
    pr_tau_s_at_1lux : float, optional
        Photoreceptor time constant at 1 lux in seconds, ``>= 0``; it scales as
        ``1 / (lux + dark_lux)`` (bandwidth grows with photocurrent). In changing scenes the level
        a pixel compares follows the scene through this first-order low-pass filter; 0 (default)
        means an infinitely fast photoreceptor. Static pixels are not affected.

    Every field also has an upper limit, where the physics of a pixel ends (:data:`PARAM_LIMITS`:
    thresholds up to 20, photon counts up to 1e12 per trial, background rates up to 1e9/s, times up to
    an hour); a value beyond it raises :class:`~evnoise.ParameterError` naming the limit.

    All the terms after ``eps_sigma`` default to zero (no background, no hot pixels, no
    photoreceptor lag); with all of them zero the simulators' output is what it was without them.
    """

    eps_pos: float
    eps_neg: float
    bias_pr: float
    trial_rate_hz: float
    photons_per_lux: float
    dark_lux: float = 0.0
    refractory_s: float = 0.0
    eps_sigma: float = 0.0
    leak_on_hz: float = 0.0
    leak_off_hz: float = 0.0
    leak_on_hz_per_lux: float = 0.0
    leak_off_hz_per_lux: float = 0.0
    leak_sigma: float = 0.0
    hot_pixel_fraction: float = 0.0
    hot_pixel_rate_hz: float = 0.0
    hot_pixel_sigma: float = 0.0
    hot_pixel_on_fraction: float = 0.5
    leak_regularity: float = 0.0
    pr_tau_s_at_1lux: float = 0.0

    def __post_init__(self):
        rules = {
            "eps_pos": (False, "> 0"),
            "eps_neg": (False, "> 0"),
            "bias_pr": (True, ">= 0"),
            "trial_rate_hz": (False, "> 0"),
            "photons_per_lux": (False, "> 0"),
            "dark_lux": (True, ">= 0"),
            "refractory_s": (True, ">= 0"),
            "eps_sigma": (True, ">= 0"),
            "leak_on_hz": (True, ">= 0"),
            "leak_off_hz": (True, ">= 0"),
            "leak_on_hz_per_lux": (True, ">= 0"),
            "leak_off_hz_per_lux": (True, ">= 0"),
            "leak_sigma": (True, ">= 0"),
            "hot_pixel_fraction": (True, ">= 0"),
            "hot_pixel_rate_hz": (True, ">= 0"),
            "hot_pixel_sigma": (True, ">= 0"),
            "hot_pixel_on_fraction": (True, ">= 0"),
            "leak_regularity": (True, ">= 0"),
            "pr_tau_s_at_1lux": (True, ">= 0"),
        }
        for name, (zero_ok, text) in rules.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                try:
                    value = float(value)
                except (TypeError, ValueError):
                    raise ParameterError(f"NoiseParams.{name} must be a number, got {value!r}") from None
            value = float(value)
            if not math.isfinite(value) or value < 0 or (value == 0 and not zero_ok):
                raise ParameterError(f"NoiseParams.{name} must be finite and {text}, got {value!r}")
            object.__setattr__(self, name, value)
        for name, limit in PARAM_LIMITS.items():
            if getattr(self, name) > limit:
                why = " (one trial per microsecond at most)" if name == "trial_rate_hz" else ""
                raise ParameterError(f"NoiseParams.{name} must be <= {limit:g}{why}, got {getattr(self, name)!r}")

    # -- derived quantities -------------------------------------------------------------
    def photons_per_trial(self, lux):
        """Mean photon count per trial, ``lam = photons_per_lux * (lux + dark_lux)``."""
        return self.photons_per_lux * (lux + self.dark_lux)

    @property
    def has_background(self) -> bool:
        """True when any background term (leak or hot pixels) is on."""
        return (self.leak_on_hz > 0 or self.leak_off_hz > 0 or self.leak_on_hz_per_lux > 0
                or self.leak_off_hz_per_lux > 0 or (self.hot_pixel_fraction > 0 and self.hot_pixel_rate_hz > 0))

    @property
    def regular_background(self) -> bool:
        """True when background arrivals follow the regular timer (background on, ``leak_regularity > 0``)."""
        return self.leak_regularity > 0 and self.has_background

    @property
    def trial_us(self) -> float:
        """Duration of one trial in microseconds."""
        return 1e6 / self.trial_rate_hz

    @property
    def refractory_us(self) -> int:
        """Refractory period in whole microseconds (rounded up)."""
        return int(math.ceil(self.refractory_s * 1e6 - 1e-9))

    def replace(self, **changes) -> "NoiseParams":
        """A copy with some fields changed (validated again)."""
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, data: dict) -> "NoiseParams":
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - fields
        if unknown:
            raise ParameterError(f"unknown noise parameter(s): {', '.join(sorted(unknown))}")
        missing = {f.name for f in dataclasses.fields(cls) if f.default is dataclasses.MISSING} - set(data)
        if missing:
            raise ParameterError(f"missing noise parameter(s): {', '.join(sorted(missing))}")
        return cls(**data)


def list_presets() -> list[str]:
    """Names of the presets shipped with evnoise."""
    folder = resources.files("evnoise") / "presets"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def _read_toml(text: str, origin: str) -> dict:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ParameterError(f"preset {origin} is not valid TOML: {exc}") from None


def load_preset_document(name_or_path) -> dict:
    """The whole preset TOML document (parameters plus provenance) as a dict."""
    text = str(name_or_path)
    path = Path(text)
    if text.endswith(".toml") or path.exists():
        if not path.is_file():
            raise ParameterError(f"preset file not found: {path}")
        return _read_toml(path.read_text(encoding="utf-8"), str(path))
    resource = resources.files("evnoise") / "presets" / f"{text}.toml"
    if not resource.is_file():
        raise ParameterError(f"unknown preset {text!r}; shipped presets: {', '.join(list_presets())}")
    return _read_toml(resource.read_text(encoding="utf-8"), text)


def load_preset(name_or_path) -> NoiseParams:
    """Load a preset by name (``"evk3-hd"``) or from a TOML file path.

    The file holds a ``[params]`` table with :class:`NoiseParams` fields; other tables
    (``[provenance]``, ``[fit]``) describe where the numbers come from.
    """
    doc = load_preset_document(name_or_path)
    if "params" not in doc or not isinstance(doc["params"], dict):
        raise ParameterError(f"preset {name_or_path} has no [params] table")
    return NoiseParams.from_dict(doc["params"])


def preset_info(name_or_path) -> dict:
    """What a preset says about itself: ``{"name", "width", "height", "sensor", "summary", "path"}``.

    ``width``/``height`` (pixels) and ``sensor`` (its name) come from the preset's ``[sensor]``
    table, ``summary`` from ``provenance.summary`` (None where the file has none); ``path`` is the
    file's location (a string). Raises :class:`~evnoise.ParameterError` for an unknown preset.
    """
    doc = load_preset_document(name_or_path)
    text = str(name_or_path)
    if text.endswith(".toml") or Path(text).exists():
        path, name = str(Path(text)), Path(text).stem
    else:
        path, name = str(resources.files("evnoise") / "presets" / f"{text}.toml"), text
    sensor = doc.get("sensor") if isinstance(doc.get("sensor"), dict) else {}
    provenance = doc.get("provenance") if isinstance(doc.get("provenance"), dict) else {}
    width, height = sensor.get("width"), sensor.get("height")
    return {
        "name": name,
        "width": int(width) if isinstance(width, int) else None,
        "height": int(height) if isinstance(height, int) else None,
        "sensor": sensor.get("name"),
        "summary": provenance.get("summary"),
        "path": path,
    }
