"""One run's set-up: the checks, the per-pixel maps and the kernel key, made once per public call.

Every entry point that simulates (:func:`evnoise.simulate_events` and its siblings, :class:`evnoise.NoiseStream`,
the tonic plugin, the dataset generator) makes one :class:`RunSetup` with :func:`run_setup`, at its public edge.
The draws from the caller's generator come in one fixed order -- the per-pixel maps of
:data:`evnoise.terms.MAPS` (thresholds, then background), then the kernel key -- and a map is drawn only
when a term asks for it (:func:`evnoise.terms.map_needed`), so turning a term off changes no other draw.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from . import terms
from ._checks import as_generator, check_params, check_thresholds

#: Words (uint64) of a simulator stream key (xoshiro256++ is keyed by 4 words and the pixel index).
KEY_WORDS = 4


def stream_key(rng=None, *, seed=None) -> np.ndarray:
    """The stream key of the simulator kernels: ``KEY_WORDS`` uint64 words (the one derivation).

    From a generator (``rng``, normalised by :func:`~evnoise._checks.as_generator`): ``KEY_WORDS`` draws of
    ``integers(0, 2**64)``, consuming it -- what every simulator draws after the per-pixel maps. From an
    integer ``seed`` instead (the dataset's direct binned-count path, which draws nothing before the key):
    ``SeedSequence(seed).generate_state(KEY_WORDS)``. The two are different keys for the same number; both
    are pinned by output digests.
    """
    if seed is not None:
        if rng is not None:
            raise ValueError("give rng or seed, not both")
        return np.random.SeedSequence(int(seed)).generate_state(KEY_WORDS, np.uint64)
    return _draw_key(as_generator(rng))


def _draw_key(gen: np.random.Generator) -> np.ndarray:
    return gen.integers(0, 2**64, size=KEY_WORDS, dtype=np.uint64, endpoint=False)


@dataclasses.dataclass(frozen=True, eq=False)
class RunSetup:
    """What a run draws before its kernels run (frozen; made by :func:`run_setup`).

    Attributes
    ----------
    shape : (H, W)
        Sensor size in pixels.
    params : NoiseParams
        The checked parameters.
    eps_on, eps_off : numpy.ndarray
        Per-pixel thresholds, flat ``(H * W,)`` (the nominal ones where nothing is drawn).
    background : (numpy.ndarray, numpy.ndarray) or None
        Per-pixel background maps, flat ``(scale, hot)`` (spread factor; hot rate in events/s), or None
        when every pixel has the nominal background.
    key : numpy.ndarray or None
        The kernel key (:func:`stream_key`), or None for a set-up made with ``draw_key=False``.
    gen : numpy.random.Generator or None
        The generator the maps and key were drawn from (for draws a run makes after them).
    """

    shape: tuple
    params: object
    eps_on: np.ndarray
    eps_off: np.ndarray
    background: tuple | None
    key: np.ndarray | None
    gen: np.random.Generator | None

    @property
    def n_pixels(self) -> int:
        return self.eps_on.size

    @property
    def thresholds(self) -> tuple:
        """``(eps_on, eps_off)`` flat."""
        return self.eps_on, self.eps_off

    def threshold_map(self) -> np.ndarray:
        """Per-pixel thresholds ``(2, H, W)``."""
        return np.stack([self.eps_on, self.eps_off]).reshape(2, *self.shape)

    def background_map(self) -> np.ndarray | None:
        """Per-pixel background maps ``(2, H, W)``, or None (the nominal background)."""
        if self.background is None:
            return None
        return np.stack(self.background).reshape(2, *self.shape)

    def keyed(self, gen: np.random.Generator) -> "RunSetup":
        """The same maps with a new key drawn from the generator ``gen`` (the tonic plugin: maps per sensor,
        key per sample)."""
        return dataclasses.replace(self, key=_draw_key(gen), gen=None)


def run_setup(shape, params, rng=None, *, thresholds=None, background=None, draw_key: bool = True,
              key_seed: int | None = None, before_draws=None) -> RunSetup:
    """Check a run's inputs and draw, in order, its thresholds, background maps and kernel key.

    Parameters
    ----------
    shape : (H, W)
        Sensor size (already checked by the caller).
    params : NoiseParams or str
        Parameters or a preset name (checked here).
    rng : numpy.random.Generator, int, SeedSequence or None
        Randomness (normalised here, once).
    thresholds, background : array_like, optional
        Given per-pixel maps ``(2, H, W)`` (checked here); each is drawn from ``rng`` when not given and a
        term needs it.
    draw_key : bool
        Draw the kernel key last (``False``: a set-up of maps only; :meth:`RunSetup.keyed` adds one).
    key_seed : int, optional
        Instead of ``rng``: the key straight from this seed (:func:`stream_key`), for runs that draw no map
        (the dataset's direct binned counts); a ``ValueError`` if ``params`` needs a per-pixel map.
    before_draws : callable, optional
        Called with the checked parameters before anything is drawn (a check of the run that needs them, such
        as its span in trials, refuses it with the caller's generator untouched).
    """
    from .background import check_background

    params = check_params(params)
    if before_draws is not None:
        before_draws(params)
    if key_seed is not None:
        if rng is not None or thresholds is not None or background is not None or terms.maps_needed(params):
            raise ValueError("key_seed is for runs without per-pixel maps or a generator")
        shape = tuple(int(s) for s in shape)
        n = int(np.prod(shape))
        return RunSetup(shape, params, np.full(n, params.eps_pos), np.full(n, params.eps_neg), None,
                        stream_key(seed=key_seed), None)
    gen = as_generator(rng)
    shape = tuple(int(s) for s in shape)
    n = int(np.prod(shape))
    if thresholds is not None:
        thr = check_thresholds(thresholds, shape)
    elif terms.map_needed("thresholds", params):
        thr = terms.draw_map("thresholds", shape, params, gen)
    else:
        thr = None
    if thr is None:
        eps_on, eps_off = np.full(n, params.eps_pos), np.full(n, params.eps_neg)
    else:
        eps_on, eps_off = np.ascontiguousarray(thr[0].ravel()), np.ascontiguousarray(thr[1].ravel())
    if background is not None:
        arr = check_background(background, shape)
    elif terms.map_needed("background", params):
        arr = terms.draw_map("background", shape, params, gen)
    else:
        arr = None
    bg = None if arr is None else (np.ascontiguousarray(arr[0].ravel()), np.ascontiguousarray(arr[1].ravel()))
    key = _draw_key(gen) if draw_key else None
    return RunSetup(shape, params, eps_on, eps_off, bg, key, gen)
