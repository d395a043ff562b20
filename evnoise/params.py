"""Noise-model parameters as an immutable, validated value object, and presets.

Units are part of every field's name. Presets are TOML files shipped in
``evnoise/presets/`` (``load_preset("evk3-hd")``) or any TOML file with the same keys.
"""

from __future__ import annotations

import collections.abc
import dataclasses
import functools
import json
import math
import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import NamedTuple

from .errors import ParameterError

__all__ = ["NoiseParams", "load_preset", "list_presets", "preset_info", "LightRange", "preset_light_range",
           "light_range_warning", "light_outside_range", "LIGHT_WARNING_SHARE", "PARAM_LIMITS", "ParameterSpec",
           "parameter_specs", "parameter_names", "parameter_spec", "names_in_group", "names_with_fit_role",
           "fit_bounds", "GROUPS", "FIT_ROLES"]

#: Groups of parameters (:attr:`ParameterSpec.group`), in order.
GROUPS = ("threshold", "photoreceptor", "timing", "background")
#: How calibration treats a parameter (:attr:`ParameterSpec.fit_role`): ``"core"`` fitted by default;
#: ``"optional"`` fitted when asked (``eps_sigma`` also by default when the data carry dispersion);
#: ``"floor"`` a background floor, fitted by default when the data have a dark level; ``"growth"`` the
#: background's growth with lux, fitted only when asked; ``"spread"`` how the background differs between
#: pixels, fitted only from flat fields and only when asked; ``"never"`` not identified by static data,
#: never fitted; ``"unmodelled"`` not modelled by the calibration likelihood, never fitted.
FIT_ROLES = ("core", "optional", "floor", "growth", "spread", "never", "unmodelled")


@dataclass(frozen=True)
class ParameterSpec:
    """What evnoise knows about one field of :class:`NoiseParams` (its field metadata, read by
    :func:`parameter_specs`).

    Attributes
    ----------
    name : str
        The field's name (units are part of it).
    unit : str
        Its unit: ``"1"`` (dimensionless), ``"photons/trial"``, ``"photons/trial/lux"``, ``"lux"``,
        ``"Hz"``, ``"Hz/lux"`` or ``"s"``.
    group : str
        What part of the pixel it describes (one of :data:`GROUPS`).
    default : float or None
        The dataclass default (None for a required field).
    low : float
        Lower limit of a valid value.
    low_inclusive : bool
        Whether ``low`` itself is valid (``>= low``) or not (``> low``).
    high : float
        Largest valid value: where the physics of a pixel ends (:data:`PARAM_LIMITS`).
    high_note : str
        Why, where the limit needs saying (appended to the error message), else ``""``.
    fit_role : str
        How calibration treats it (one of :data:`FIT_ROLES`).
    fit_bounds : tuple or None
        ``(low, high)`` of the calibration search in natural units; ``None`` entries are set from the
        data; ``None`` as a whole: never searched (``fit_role == "unmodelled"``).
    fit_start : float
        Starting value of the calibration search where nothing else gives one.
    fit_low : str
        What ending on the fit's lower bound means: ``"zero"`` the bound stands for 0 and the value is
        reported as 0; ``"ok"`` an ordinary result, not flagged; ``"flag"`` flagged.
    """

    name: str
    unit: str
    group: str
    default: float | None
    low: float
    low_inclusive: bool
    high: float
    high_note: str
    fit_role: str
    fit_bounds: tuple | None
    fit_start: float
    fit_low: str

    @property
    def low_text(self) -> str:
        """The lower limit as the error message says it: ``"> 0"`` or ``">= 0"``."""
        return f"{'>=' if self.low_inclusive else '>'} {self.low:g}"


def _param(unit, group, *, high, positive=False, default=dataclasses.MISSING, high_note="", fit_role,
           fit_bounds=None, fit_start=None, fit_low="flag", low=0.0):
    """A :class:`NoiseParams` field carrying its :class:`ParameterSpec` entries as metadata."""
    meta = {"unit": unit, "group": group, "low": float(low), "low_inclusive": not positive, "high": float(high),
            "high_note": high_note, "fit_role": fit_role, "fit_bounds": fit_bounds,
            "fit_start": fit_start, "fit_low": fit_low}
    return dataclasses.field(default=default, metadata={"evnoise": meta})


# The upper limits (``high``) are where the physics of a pixel ends (and with it what the kernels are
# verified for). A threshold of 20 asks the light to change by a factor e^20 ~ 5e8 (170 dB, beyond any
# sensor's dynamic range); a photoreceptor sees at most 1e12 photons or 1e6 lux-equivalent of offset per
# trial; background rates (leak, hot pixel) stay below 1e9/s (a thousand per microsecond, evnoise's time
# resolution; the model caps them at one event per trial); dead times and time constants stay within an
# hour; a log-normal spread of 10 already spans a factor e^20 between pixels one sigma apart.
# The fit bounds (natural units; None: set from the data by the calibration, see
# evnoise.calibration.rates.spec): trial_rate_hz from the highest rate (p < 1/2), photons_per_lux so that
# the brightest level has 1e-3 to LAM_MAX photons per trial, dark_lux from 1e-6 to 10 times the brightest
# level, refractory_s below half the shortest mean interval between events, the background rates from the
# highest measured rate.
_RATE_HZ = 1e9
_TIME_S = 3600.0
_SPREAD = 10.0


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
    reset_memory : float, optional
        Reset memory ``k``, ``0 <= k <= 1``: the share of trials in which a pixel compares its photon count
        against the count it stored at its last event, instead of a fresh reference sample (the paper's
        memoryless model, ``k = 0``, the default). With ``k > 0`` a pixel that fired ON stored a high level and
        tends to fire OFF next: consecutive events alternate in polarity, as in real quiet pixels (see
        :mod:`evnoise.terms.memory`, which says what runs it: every simulator, with or without the regular
        background timer; the closed form is the nominal pixel's).
    hot_pixel_regularity : float, optional
        How regular the background arrivals of a *hot* pixel are, ``0 <= r <= 1`` as ``leak_regularity``;
        ``-1`` (the default) means the same as ``leak_regularity`` (one regularity for every pixel); it applies to
        the hot pixels of the drawn map or of a map given as ``background=``. Real
        sensors' hot pixels can be Poisson while the ordinary pixels' leak is close to periodic (the quiet-scene
        calibration's ``hot_regularity="on"`` fits both; calibration/README.md).

    Notes
    -----
    Every field also has an upper limit, where the physics of a pixel ends (:data:`PARAM_LIMITS`:
    thresholds up to 20, photon counts up to 1e12 per trial, background rates up to 1e9/s, times up to
    an hour); a value beyond it raises :class:`~evnoise.ParameterError` naming the limit.

    All the terms after ``eps_sigma`` default to off: zero (no background, no hot pixels, no
    photoreceptor lag, no reset memory), except ``hot_pixel_on_fraction`` (0.5) and ``hot_pixel_regularity``
    (-1), which only shape the events of hot pixels; with them off the simulators' output is what it was
    without them.
    """

    eps_pos: float = _param("1", "threshold", high=20.0, positive=True, fit_role="core",
                            fit_bounds=(1e-3, 5.0), fit_start=0.5)
    eps_neg: float = _param("1", "threshold", high=20.0, positive=True, fit_role="core",
                            fit_bounds=(1e-3, 5.0), fit_start=0.5)
    bias_pr: float = _param("photons/trial", "photoreceptor", high=1e12, fit_role="core",
                            fit_bounds=(1e-6, 1e4), fit_start=1.0, fit_low="ok")
    trial_rate_hz: float = _param("Hz", "timing", high=1e6, positive=True, fit_role="core",
                                  high_note=" (one trial per microsecond at most)",
                                  fit_bounds=(None, 5e5), fit_start=100.0)
    photons_per_lux: float = _param("photons/trial/lux", "photoreceptor", high=1e12, positive=True,
                                    fit_role="core", fit_bounds=(None, None), fit_start=1.0)
    dark_lux: float = _param("lux", "photoreceptor", high=1e6, default=0.0, fit_role="core",
                             fit_bounds=(None, None), fit_start=0.1, fit_low="ok")
    refractory_s: float = _param("s", "timing", high=_TIME_S, default=0.0, fit_role="optional",
                                 fit_bounds=(1e-8, None), fit_low="ok")
    eps_sigma: float = _param("1", "threshold", high=20.0, default=0.0, fit_role="optional",
                              fit_bounds=(1e-3, 1.5), fit_low="ok")
    leak_on_hz: float = _param("Hz", "background", high=_RATE_HZ, default=0.0, fit_role="floor",
                               fit_bounds=(None, None), fit_low="zero")
    leak_off_hz: float = _param("Hz", "background", high=_RATE_HZ, default=0.0, fit_role="floor",
                                fit_bounds=(None, None), fit_low="zero")
    leak_on_hz_per_lux: float = _param("Hz/lux", "background", high=_RATE_HZ, default=0.0, fit_role="growth",
                                       fit_bounds=(None, None), fit_low="zero")
    leak_off_hz_per_lux: float = _param("Hz/lux", "background", high=_RATE_HZ, default=0.0, fit_role="growth",
                                        fit_bounds=(None, None), fit_low="zero")
    leak_sigma: float = _param("1", "background", high=_SPREAD, default=0.0, fit_role="spread",
                               fit_bounds=(1e-3, 3.0), fit_low="zero")
    hot_pixel_fraction: float = _param("1", "background", high=1.0, default=0.0, fit_role="spread",
                                       fit_bounds=(1e-6, 0.5), fit_low="zero")
    hot_pixel_rate_hz: float = _param("Hz", "background", high=_RATE_HZ, default=0.0, fit_role="spread",
                                      fit_bounds=(None, None))
    hot_pixel_sigma: float = _param("1", "background", high=_SPREAD, default=0.0, fit_role="spread",
                                    fit_bounds=(1e-3, 3.0), fit_low="zero")
    hot_pixel_on_fraction: float = _param("1", "background", high=1.0, default=0.5, fit_role="spread",
                                          fit_bounds=(1e-3, 0.999))
    leak_regularity: float = _param("1", "background", high=1.0, default=0.0, fit_role="unmodelled")
    pr_tau_s_at_1lux: float = _param("s", "photoreceptor", high=_TIME_S, default=0.0, fit_role="never",
                                     fit_bounds=(1e-9, 1e3))
    reset_memory: float = _param("1", "timing", high=1.0, default=0.0, fit_role="unmodelled")
    hot_pixel_regularity: float = _param("1", "background", high=1.0, default=-1.0, low=-1.0,
                                         fit_role="unmodelled")

    def __post_init__(self):
        specs = parameter_specs()
        tied = self.hot_pixel_regularity
        if isinstance(tied, (int, float)) and not isinstance(tied, bool) and tied < 0 and tied != -1:
            raise ParameterError("NoiseParams.hot_pixel_regularity must be -1 (the same as leak_regularity) or "
                                 f"between 0 and 1, got {tied!r}")
        for spec in specs:
            name, value = spec.name, getattr(self, spec.name)
            try:  # an int beyond the double range (a TOML integer of 400 digits) overflows
                if isinstance(value, (str, bytes)) or type(value).__name__ in ("bool", "bool_"):  # true is no 1.0
                    raise TypeError
                value = float(value)
            except (TypeError, ValueError, OverflowError):
                raise ParameterError(f"NoiseParams.{name} must be a number, got {_short_repr(value)}") from None
            if not math.isfinite(value) or value < spec.low or (value == spec.low and not spec.low_inclusive):
                raise ParameterError(f"NoiseParams.{name} must be finite and {spec.low_text}, got {value!r}")
            object.__setattr__(self, name, value)
        for spec in specs:
            if getattr(self, spec.name) > spec.high:
                raise ParameterError(f"NoiseParams.{spec.name} must be <= {spec.high:g}{spec.high_note}, "
                                     f"got {getattr(self, spec.name)!r}")

    # -- derived quantities -------------------------------------------------------------
    def photons_per_trial(self, lux):
        """Mean photon count per trial, ``lam = photons_per_lux * (lux + dark_lux)``.

        Parameters
        ----------
        lux : float or array_like
            Illuminance at the sensor in lux (not checked here).

        Returns
        -------
        float or numpy.ndarray
            ``lam`` of the same shape as ``lux``, photons per trial.
        """
        return self.photons_per_lux * (lux + self.dark_lux)

    @property
    def has_background(self) -> bool:
        """True when any background term (leak or hot pixels) is on."""
        return (self.leak_on_hz > 0 or self.leak_off_hz > 0 or self.leak_on_hz_per_lux > 0
                or self.leak_off_hz_per_lux > 0 or self.hot_pixels_on)

    @property
    def hot_pixels_on(self) -> bool:
        """True when hot pixels are drawn and fire (``hot_pixel_fraction > 0`` and ``hot_pixel_rate_hz > 0``)."""
        return self.hot_pixel_fraction > 0 and self.hot_pixel_rate_hz > 0

    @property
    def hot_regularity(self) -> float:
        """The regularity of a hot pixel's background: ``hot_pixel_regularity``, or ``leak_regularity`` where that
        is ``-1`` (tied, the default)."""
        return self.leak_regularity if self.hot_pixel_regularity < 0 else self.hot_pixel_regularity

    @property
    def regular_background(self) -> bool:
        """True when background arrivals follow the regular timer (background on, and ``leak_regularity > 0`` or
        hot pixels with a regularity > 0 of their own)."""
        return self.has_background and (self.leak_regularity > 0 or (self.hot_pixels_on and self.hot_regularity > 0))

    @property
    def trial_us(self) -> float:
        """Duration of one trial in microseconds."""
        return 1e6 / self.trial_rate_hz

    @property
    def refractory_us(self) -> int:
        """Refractory period in whole microseconds (rounded up)."""
        return int(math.ceil(self.refractory_s * 1e6 - 1e-9))

    def replace(self, **changes) -> "NoiseParams":
        """A copy with some fields changed (validated again).

        Parameters
        ----------
        **changes
            New values of fields, by name (``eps_sigma=0.05``); an unknown name is a :class:`TypeError`, an
            invalid value a :class:`~evnoise.ParameterError`.

        Returns
        -------
        NoiseParams
            The copy; ``self`` is unchanged.
        """
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        """Every field by name, as a new dict (what :meth:`from_dict` takes back).

        Returns
        -------
        dict
            ``{field name: float value}``, in field order.
        """
        return dataclasses.asdict(self)

    def to_json(self) -> str:
        """The fields as a JSON object, keys sorted (how event files store a :class:`NoiseParams` attribute).

        Returns
        -------
        str
            JSON text of :meth:`to_dict`.
        """
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, data: dict) -> "NoiseParams":
        """Parameters from a mapping of field names to values (a preset's ``[params]`` table, :meth:`to_dict`).

        Parameters
        ----------
        data : Mapping
            Field names (strings) and their values; every field without a default must be there, and an unknown
            name is a :class:`~evnoise.ParameterError`.

        Returns
        -------
        NoiseParams
            The validated parameters.
        """
        if not isinstance(data, collections.abc.Mapping) or not all(isinstance(k, str) for k in data):
            raise ParameterError(f"noise parameters must be a table of names and values, got {_short_repr(data)}")
        fields = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - fields
        if unknown:
            raise ParameterError(f"unknown noise parameter(s): {', '.join(sorted(unknown))}")
        missing = {f.name for f in dataclasses.fields(cls) if f.default is dataclasses.MISSING} - set(data)
        if missing:
            raise ParameterError(f"missing noise parameter(s): {', '.join(sorted(missing))}")
        return cls(**data)


@functools.cache
def parameter_specs() -> tuple[ParameterSpec, ...]:
    """Every parameter of :class:`NoiseParams` with its unit, limits, group and fit range, in field order.

    Returns
    -------
    tuple of ParameterSpec
        Frozen records read from the fields' metadata: the one home of these facts (validation,
        :data:`PARAM_LIMITS`, calibration's bounds and the command line's lists derive from it).
    """
    out = []
    for f in dataclasses.fields(NoiseParams):
        meta = f.metadata["evnoise"]
        default = None if f.default is dataclasses.MISSING else f.default
        out.append(ParameterSpec(name=f.name, default=default,
                                 **{k: v for k, v in meta.items() if k != "fit_start"},
                                 fit_start=meta["fit_start"] if meta["fit_start"] is not None else default))
    return tuple(out)


def parameter_names() -> tuple[str, ...]:
    """Names of the fields of :class:`NoiseParams`, in order."""
    return tuple(s.name for s in parameter_specs())


def parameter_spec(name: str) -> ParameterSpec:
    """The :class:`ParameterSpec` of parameter ``name``; raises :class:`~evnoise.ParameterError` if unknown."""
    for spec in parameter_specs():
        if spec.name == name:
            return spec
    raise ParameterError(f"unknown noise parameter {name!r}; parameters: {', '.join(parameter_names())}")


def names_in_group(group: str) -> tuple[str, ...]:
    """Names of the parameters in ``group`` (one of :data:`GROUPS`), in field order."""
    if group not in GROUPS:
        raise ParameterError(f"unknown parameter group {group!r}; groups: {', '.join(GROUPS)}")
    return tuple(s.name for s in parameter_specs() if s.group == group)


def names_with_fit_role(*roles: str) -> tuple[str, ...]:
    """Names of the parameters whose :attr:`ParameterSpec.fit_role` is one of ``roles``, in field order."""
    for role in roles:
        if role not in FIT_ROLES:
            raise ParameterError(f"unknown fit role {role!r}; roles: {', '.join(FIT_ROLES)}")
    return tuple(s.name for s in parameter_specs() if s.fit_role in roles)


def fit_bounds(name: str) -> tuple | None:
    """Bounds ``(low, high)`` of the calibration search for ``name`` (``None`` entries are set from the
    data; ``None`` where the parameter is never searched)."""
    return parameter_spec(name).fit_bounds


#: Largest value each parameter may take (``name -> limit``; read-only, from :func:`parameter_specs`).
PARAM_LIMITS = MappingProxyType({s.name: s.high for s in parameter_specs()})


def list_presets() -> list[str]:
    """Names of the presets shipped with evnoise."""
    folder = resources.files("evnoise") / "presets"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def _read_toml(text: str, origin: str) -> dict:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ParameterError(f"preset {origin} is not valid TOML: {exc}") from None
    except RecursionError:  # arrays nested beyond Python's recursion limit
        raise ParameterError(f"preset {origin} is not a preset: its TOML nests too deeply") from None
    except ValueError as exc:  # e.g. an integer longer than Python converts (4300 digits)
        raise ParameterError(f"preset {origin} is not a preset: {str(exc).split(';')[0][:200]}") from None


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

    Parameters
    ----------
    name_or_path : str or os.PathLike
        A shipped preset's name (:func:`list_presets`), or the path of a TOML file (a name ending in ``.toml``
        or an existing path).

    Returns
    -------
    NoiseParams
        The preset's parameters.
    """
    doc = load_preset_document(name_or_path)
    if "params" not in doc or not isinstance(doc["params"], dict):
        raise ParameterError(f"preset {name_or_path} has no [params] table")
    params = NoiseParams.from_dict(doc["params"])
    _LOADED[params] = (_preset_label(name_or_path), _light_range_of(doc))
    return params


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


# --------------------------------------------------------------------------------------
# the light range a preset was fitted or measured on
# --------------------------------------------------------------------------------------
class LightRange(NamedTuple):
    """Illuminance range (lux at the sensor) a preset was fitted or measured on, from its
    ``[provenance] fitted_lux = [lo, hi]``; ``note`` says where it comes from (``"assumed: ..."`` where
    the data do not say) and ``meaning`` what leaving it means for the rates."""

    lo: float
    hi: float
    note: str
    meaning: str = ""

    @property
    def assumed(self) -> bool:
        return self.note.startswith("assumed")


#: parameters returned by :func:`load_preset` -> (preset label, its LightRange or None); equal
#: parameters are the same preset for this purpose
_LOADED: dict = {}


def _preset_label(name_or_path) -> str:
    text = str(name_or_path)
    return Path(text).stem if text.endswith(".toml") or Path(text).exists() else text


def _short_repr(value, limit: int = 80) -> str:
    """``repr(value)``, cut to ``limit`` characters (a 400-digit integer in an error line)."""
    if isinstance(value, int) and value.bit_length() > 3 * limit:  # repr of a huge int is long (or refused)
        return f"an integer of about {value.bit_length() * math.log10(2):.0f} digits"
    text = repr(value)
    return text if len(text) <= limit else text[:limit] + "..."


def _light_range_of(doc: dict):
    provenance = doc.get("provenance") if isinstance(doc.get("provenance"), dict) else {}
    value = provenance.get("fitted_lux")
    if not (isinstance(value, list) and len(value) == 2
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)):
        return None
    try:
        lo, hi = float(value[0]), float(value[1])
    except OverflowError:  # an integer beyond the double range
        lo = hi = math.nan
    if not (0.0 <= lo < hi < math.inf):
        raise ParameterError("preset provenance.fitted_lux must be [lo, hi] lux with 0 <= lo < hi, got "
                             f"{_short_repr(value)}")
    return LightRange(lo, hi, str(provenance.get("fitted_lux_note", "")),
                      str(provenance.get("fitted_lux_meaning", "")))


@functools.lru_cache(maxsize=None)
def _shipped_ranges() -> tuple:
    """``((params, name, LightRange | None), ...)`` of the shipped presets."""
    out = []
    for name in list_presets():
        doc = load_preset_document(name)
        if isinstance(doc.get("params"), dict):
            out.append((NoiseParams.from_dict(doc["params"]), name, _light_range_of(doc)))
    return tuple(out)


def _find_preset(preset):
    """``(label, LightRange | None)`` of a preset name/path or of parameters made from a preset;
    ``(None, None)`` for parameters that match no loaded or shipped preset."""
    if isinstance(preset, NoiseParams):
        if preset in _LOADED:
            return _LOADED[preset]
        for params, name, light in _shipped_ranges():
            if params == preset:
                return name, light
        return None, None
    return _preset_label(preset), _light_range_of(load_preset_document(preset))


def preset_light_range(preset) -> LightRange | None:
    """The illuminance range (lux) a preset was fitted or measured on: ``LightRange(lo, hi, note, meaning)``,
    or None where the preset records none.

    ``preset`` is a preset name (``"dvs128"``), a TOML path, or :class:`NoiseParams` made from a preset
    (by :func:`load_preset`, or equal to a shipped preset); parameters of no known preset give None.
    """
    return _find_preset(preset)[1]


def light_range_warning(preset, lux_min: float, lux_max: float, *, factor: float = 2.0,
                        outside_share: float | None = None) -> str | None:
    """One line saying that a scene spanning ``lux_min .. lux_max`` lux leaves the range the preset was
    fitted on by more than ``factor`` (above ``hi * factor`` or, where ``lo > 0``, below ``lo / factor``);
    None inside it, or for a preset (or parameters) with no recorded range. ``outside_share`` (the share
    of the scene's pixels outside, if the caller counted them with :func:`light_outside_range`) is named
    in the line.

    ``evnoise simulate`` logs it as a warning when at least :data:`LIGHT_WARNING_SHARE` of the pixels lie
    outside (a few black pixels in a photograph do not); library callers may do the same before simulating.
    """
    name, light = _find_preset(preset)
    if light is None:
        return None
    lux_min, lux_max = float(lux_min), float(lux_max)
    above = lux_max > light.hi * factor
    below = light.lo > 0.0 and lux_min < light.lo / factor
    if not (above or below):
        return None
    kind = "the assumed range" if light.assumed else "the range"
    meaning = light.meaning or "its rates there are extrapolated"
    share = "" if outside_share is None else f" ({100 * outside_share:.3g} % of its pixels)"
    return (f"the scene spans {lux_min:.3g} .. {lux_max:.3g} lux, more than x{factor:g} outside {kind}{share} "
            f"preset {name} was fitted on ({light.lo:.3g} .. {light.hi:.3g} lux): {meaning}")


#: share of a scene's pixels outside a preset's light range (by more than x2) from which ``evnoise simulate`` warns
LIGHT_WARNING_SHARE = 0.01


def light_outside_range(preset, lux, *, factor: float = 2.0) -> tuple:
    """``(outside, total)``: how many pixels of ``lux`` lie more than ``factor`` outside the light range
    ``preset`` was fitted on, of how many (``(0, lux.size)`` for a preset with no recorded range). ``preset`` may
    be its :class:`LightRange` (:func:`preset_light_range`'s), for a caller that counts frame after frame."""
    import numpy as np

    light = preset if isinstance(preset, LightRange) else _find_preset(preset)[1]
    lux = np.asarray(lux)
    if light is None:
        return 0, int(lux.size)
    outside = lux > light.hi * factor
    if light.lo > 0.0:
        outside |= lux < light.lo / factor
    return int(np.count_nonzero(outside)), int(lux.size)
