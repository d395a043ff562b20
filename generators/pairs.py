"""One training pair: a crop of a scene, its illuminance, its noise-event counts and its image.

Randomness is keyed by identity, never by order. For global seed ``S`` and an item id ``I``
(hashed to four 32-bit words ``h(I)``):

* the procedural image of ``I``:            ``SeedSequence(S, spawn_key=(0, *h(I)))``
* crop ``c`` of ``I`` (position, brightness, contrast): ``SeedSequence(S, spawn_key=(1, *h(I), c))``
* the noise of crop ``c`` in window ``w`` µs: ``SeedSequence(S, spawn_key=(2, *h(I), c, w))``, reduced to
  a 63-bit integer *sample seed* (stored with the pair) from which all noise is drawn.

So a pair is the same whichever worker makes it, in whatever order, on whatever machine.

Scene and target. The fitted luminance ``Y`` (sensor size) of a display-referred source is
cropped and mapped to illuminance ``lux = max_lux * Y ** gamma`` (linear sources:
``lux_scale * Y ** gamma``), then quantised to steps of ``white_lux / 16383`` (a 14-bit
display of the scene); counts and image both come from this quantised illuminance. The image
is ``srgb_encode(mean_2x2(lux) / white_lux)`` clipped to ``[0, 1]``: what a person sees on a
display whose white is ``white_lux``; ``lux = srgb_decode(image) * white_lux`` recovers the
binned illuminance (where the image is below 1).

Counts. ``mode="counts"`` with no refractory period, no reset memory and no per-pixel draws (threshold
mismatch, background spread, hot pixels; a uniform background is fine) draws each
pixel's counts exactly from its i.i.d. trials (:func:`._kernels.trial_counts_binned`, with the
per-trial probabilities of each illuminance level from the exact closed form, evaluated once
per level); otherwise it calls :func:`evnoise.sample_counts`. ``mode="events"`` simulates the
event stream (:func:`evnoise.simulate_events`) and counts it. Counts are then summed over
``binning x binning`` blocks; a bin above 65535 saturates (and is counted).
"""

from __future__ import annotations

import hashlib
import math
import threading
from typing import NamedTuple

import numpy as np

from evnoise import terms
from evnoise._run import run_setup
from evnoise.errors import ParameterError
from evnoise.radiometry import block_sum, srgb_encode
from evnoise.terms.memory import memory_on

from .config import COUNT_MAX, LEVELS, PairConfig

__all__ = [
    "id_words",
    "source_generator",
    "crop_generator",
    "sample_seed",
    "CropDraw",
    "draw_crop",
    "crop_levels",
    "quantise",
    "display_image",
    "linear_to_srgb",
    "bin_sum",
    "CountSampler",
    "to_uint16",
]

_STREAM_SOURCE, _STREAM_CROP, _STREAM_NOISE = 0, 1, 2
#: The direct trial sampler inverts the count's CDF from ``(1 - p) ** n_full``, which must not
#: underflow: it is used while ``-n_full log(1 - p) <= _DIRECT_MAX_LOG`` (a mean count of at most
#: 500 events per pixel and window); beyond, :func:`evnoise.sample_counts` is used.
_DIRECT_MAX_LOG = 500.0


# --------------------------------------------------------------------------------------
# seeds
# --------------------------------------------------------------------------------------
def id_words(item_id: str) -> tuple:
    """Four 32-bit words of the SHA-256 of an item id (stable across machines and Python runs)."""
    digest = hashlib.sha256(str(item_id).encode("utf-8")).digest()
    return tuple(int.from_bytes(digest[i:i + 4], "little") for i in range(0, 16, 4))


def source_generator(seed: int, item_id: str) -> np.random.Generator:
    """Generator of a procedural source image."""
    return np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(_STREAM_SOURCE, *id_words(item_id))))


def crop_generator(seed: int, item_id: str, crop_index: int) -> np.random.Generator:
    """Generator of crop ``crop_index``'s position, brightness and contrast."""
    ss = np.random.SeedSequence(int(seed), spawn_key=(_STREAM_CROP, *id_words(item_id), int(crop_index)))
    return np.random.default_rng(ss)


def sample_seed(seed: int, item_id: str, crop_index: int, window_us: int) -> int:
    """The 63-bit seed of one pair's noise (stored with the pair)."""
    ss = np.random.SeedSequence(int(seed), spawn_key=(_STREAM_NOISE, *id_words(item_id), int(crop_index),
                                                      int(window_us)))
    return int(ss.generate_state(1, np.uint64)[0] >> np.uint64(1))


# --------------------------------------------------------------------------------------
# scene
# --------------------------------------------------------------------------------------
class CropDraw(NamedTuple):
    """Random choices of one crop: box ``(top, left, height, width)`` in fitted-sensor pixels,
    the illuminance scale (lux of ``Y = 1``) and the contrast exponent."""

    box: tuple
    scale_lux: float
    gamma: float


def _log_uniform(u: float, lo: float, hi: float) -> float:
    return lo if lo == hi else float(math.exp(math.log(lo) + u * (math.log(hi) - math.log(lo))))


def draw_crop(config: PairConfig, seed: int, item_id: str, crop_index: int, kind: str) -> CropDraw:
    """Position, brightness and contrast of a crop (the same draws whatever the options used)."""
    gen = crop_generator(seed, item_id, crop_index)
    u = gen.random(4)  # always four draws: top, left, brightness, contrast
    sh, sw = config.sensor_shape
    ch, cw = config.sample_shape
    top = min(int(u[0] * (sh - ch + 1)), sh - ch)
    left = min(int(u[1] * (sw - cw + 1)), sw - cw)
    lo, hi = config.max_lux if kind == "display" else config.lux_scale
    scale = _log_uniform(float(u[2]), lo, hi)
    gamma = _log_uniform(float(u[3]), *config.contrast)
    return CropDraw((top, left, ch, cw), scale, gamma)


def crop_levels(fitted_y: np.ndarray, draw: CropDraw, step_lux: float, binning: int):
    """Quantised illuminance of a crop: ``(codes, level_sums)``.

    ``codes`` (int32, crop size) are the illuminance levels ``round(lux / step_lux)`` of
    ``lux = scale_lux * Y ** gamma``; ``level_sums`` (int64, binned size) sum the codes of each
    ``binning x binning`` block. The quantised illuminance is ``codes * step_lux``.
    """
    from ._kernels import illuminance_levels

    top, left, h, w = draw.box
    y = fitted_y[top:top + h, left:left + w]
    codes = np.empty((h, w), dtype=np.int32)
    sums = np.zeros((h // binning, w // binning), dtype=np.int64)
    peak = illuminance_levels(y, float(draw.scale_lux), float(draw.gamma), 1.0 / step_lux, int(binning), codes, sums)
    if not math.isfinite(peak) or peak > np.iinfo(np.int32).max - 2:
        raise ParameterError(f"illuminance {peak * step_lux:.4g} lux is too bright for white_lux "
                             f"{step_lux * LEVELS:.4g} lux (more than 2^31 levels); raise white_lux")
    return codes, sums


def quantise(lux: np.ndarray, step_lux: float):
    """``(codes, lux_q)``: illuminance levels (int32) and the quantised illuminance (float64).

    The plain-NumPy equivalent of :func:`crop_levels` (``floor(lux / step + 0.5)``).
    """
    scaled = np.asarray(lux, dtype=np.float64) * (1.0 / step_lux)
    top = float(scaled.max()) if scaled.size else 0.0
    if top > np.iinfo(np.int32).max - 2:
        raise ParameterError(f"illuminance {top * step_lux:.4g} lux is too bright for white_lux "
                             f"{step_lux * LEVELS:.4g} lux (more than 2^31 levels); raise white_lux")
    codes = np.floor(scaled + 0.5).astype(np.int32)
    return codes, codes * step_lux


#: sRGB encoding (IEC 61966-2-1 OETF), clipped to ``[0, 1]``: :func:`evnoise.radiometry.srgb_encode`.
linear_to_srgb = srgb_encode


#: Sum over ``b x b`` blocks of the last two axes: :func:`evnoise.radiometry.block_sum` (kept as a name).
bin_sum = block_sum


def display_image(level_sums: np.ndarray, binning: int, step_lux: float, white_lux: float) -> np.ndarray:
    """The pair's image from :func:`crop_levels`' sums: ``srgb(mean_bxb(lux) / white_lux)``, float32."""
    mean = level_sums * (step_lux / (binning * binning * white_lux))
    return linear_to_srgb(mean).astype(np.float32)


# --------------------------------------------------------------------------------------
# counts
# --------------------------------------------------------------------------------------
class CountSampler:
    """Draws binned counts for one dataset's options; caches per-level tables (one per process).

    Parameters
    ----------
    config : PairConfig
        Dataset options (mode, binning, illuminance quantisation).
    threads : int
        Threads for :func:`evnoise.sample_counts` / :func:`evnoise.simulate_events` (the direct
        sampler runs on one thread). Results never depend on it.
    """

    def __init__(self, config: PairConfig, threads: int = 1):
        self.config = config
        self.params = config.noise_params
        self.threads = max(1, int(threads))
        self.step = config.lux_step
        p = self.params
        # per-pixel draws (threshold mismatch, background spread, hot pixels) go through sample_counts
        per_pixel = terms.maps_needed(p)
        # reset memory: trials are not independent, so counts come from sample_counts (the memory tier's events)
        self.direct = config.mode == "counts" and p.refractory_s == 0 and not per_pixel and not memory_on(p)
        self._levels = 0
        self._p_on = self._p_off = None
        self._n_tables: dict = {}
        self._lock = threading.Lock()

    @property
    def method(self) -> str:
        """Name of the sampler used (recorded in the manifest)."""
        if self.config.mode == "events":
            return "simulate_events+count_events"
        return "direct-trials" if self.direct else "sample_counts"

    def _ensure_levels(self, top_code: int):
        if top_code < self._levels:
            return
        from evnoise.rates import trial_probabilities

        n = max(LEVELS + 1, 1 << int(math.ceil(math.log2(top_code + 1))))
        lam = self.params.photons_per_trial(np.arange(n, dtype=np.float64) * self.step)
        p_on, p_off = trial_probabilities(lam, self.params)
        self._p_on = np.ascontiguousarray(p_on, dtype=np.float64)
        self._p_off = np.ascontiguousarray(p_off, dtype=np.float64)
        self._levels = n
        self._n_tables.clear()

    def _table(self, n_full: int, frac: float) -> np.ndarray:
        """Per-level table of :func:`._kernels.trial_counts_binned` for a window of ``n_full + frac`` trials."""
        key = (n_full, frac)
        table = self._n_tables.get(key)
        if table is None:
            p_on, p_off = self._p_on, self._p_off
            p = np.minimum(p_on + p_off, 1.0)
            with np.errstate(divide="ignore", invalid="ignore"):
                b0 = np.exp(n_full * np.log1p(-p))
                fp = frac * p
                table = np.stack([b0 * (1.0 - fp), p, p / (1.0 - p), b0, np.where(p > 0, p_on / p, 0.0), fp], axis=1)
            table = self._n_tables[key] = np.ascontiguousarray(table)
        return table

    def sample(self, codes: np.ndarray, window_us: int, seed: int) -> np.ndarray:
        """Binned counts ``(2, h, w)`` int64 ``[ON, OFF]`` of a crop over ``window_us`` microseconds.

        ``codes`` are the crop's illuminance levels (:func:`crop_levels`); ``seed`` the pair's seed.
        """
        b = self.config.binning
        low, top = int(codes.min()), int(codes.max())
        if low < 0:
            raise ParameterError(f"illuminance levels must be >= 0, got {low}")
        if self.direct:
            trials = window_us * 1e-6 * self.params.trial_rate_hz
            n_full = int(math.floor(trials))
            frac = trials - n_full
            with self._lock:  # Dask may run several shards in threads of one process
                self._ensure_levels(top)
                p_on, p_off = self._p_on, self._p_off
                table = self._table(n_full, frac)
            # largest per-trial probability over the levels between the darkest and brightest pixel
            p_max = float(np.max(p_on[low:top + 1] + p_off[low:top + 1]))
            if p_max < 1.0 and -n_full * math.log1p(-p_max) <= _DIRECT_MAX_LOG:
                from ._kernels import trial_counts_binned

                key = run_setup(codes.shape, self.params, key_seed=seed).key  # no maps: the key from the seed
                h, w = codes.shape
                out = np.zeros((2, h // b, w // b), dtype=np.int64)
                trial_counts_binned(np.ascontiguousarray(codes), table, n_full, frac, key, b, out)
                return out
        window_s = window_us * 1e-6
        lux_q = codes * self.step
        if self.config.mode == "events":
            from evnoise.events import count_events
            from evnoise.simulate import simulate_events

            events = simulate_events(lux_q, self.params, window_s, int(seed), threads=self.threads)
            counts = count_events(events, lux_q.shape, 0, window_us)
        else:
            from evnoise.simulate import sample_counts

            counts = sample_counts(lux_q, self.params, window_s, int(seed), threads=self.threads)
        counts = np.asarray(counts, dtype=np.int64)
        return counts if b == 1 else block_sum(counts, b, "counts")


def to_uint16(binned: np.ndarray):
    """``(counts uint16, saturated bins)``: counts above 65535 saturate at 65535."""
    over = binned > COUNT_MAX
    n_over = int(np.count_nonzero(over))
    if n_over:
        binned = np.minimum(binned, COUNT_MAX)
    return binned.astype(np.uint16), n_over
