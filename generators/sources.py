"""Where scenes come from: image folders, image files, package photos, procedural images.

A *scene source* lists stable item ids (``items()``) and loads one item as relative linear
luminance (``load(item_id, context)`` -> ``(Y, kind)``, ``kind`` ``"display"`` for display-referred
images whose full-scale white is ``Y = 1``, ``"linear"`` for linear images whose values are
scaled by ``lux_scale``). Ids name the item independently of the machine (a file's name within
its folder, ``skimage/astronaut.png``, ``dead-leaves/000017``): every random choice about an item
derives from the global seed and its id, so the same id gets the same pairs anywhere.

Sources are small frozen dataclasses (picklable: they travel to worker processes and Dask
workers) and describe themselves with ``spec()`` for the manifest.

Photos shipped by installed packages (``PackagePhotos``; nothing is downloaded, nothing is
copied into evnoise) and their licences, as their packages state them:

=====================================  =====================================================
scikit-image ``skimage/data``          astronaut (public domain, NASA), brick (CC0), camera
                                       (CC0, Lav Varshney), chelsea (CC0, Stefan van der
                                       Walt), clock_motion (public domain, Stefan van der
                                       Walt), coffee (CC0, Rachel Michetti), coins (no known
                                       copyright restrictions, Brooklyn Museum), grass (CC0),
                                       gravel (CC0), hubble_deep_field (public domain, NASA),
                                       ihc (no known copyright restrictions, CMMI), retina
                                       (CC0, M. Häggström), rocket (public domain, SpaceX),
                                       text (public domain)
matplotlib ``mpl-data/sample_data``    grace_hopper.jpg (public domain, U.S. Navy photograph)
scikit-learn ``datasets/images``       china.jpg, flower.jpg (Creative Commons Attribution;
                                       see that folder's README.txt), if scikit-learn is installed
PyWavelets ``pywt/data``               ascent.npz (free to use; SciPy's ``ascent``), if installed
=====================================  =====================================================

Images of those packages whose licence their documentation does not state (e.g. scikit-image's
``moon``, ``page``, the Middlebury ``motorcycle`` pair, PyWavelets' old ``camera``) are left out.
"""

from __future__ import annotations

import importlib.util
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from evnoise.errors import InputError, ParameterError

from .procedural import DeadLeavesModel

__all__ = [
    "LoadContext",
    "FolderSource",
    "FilesSource",
    "PackagePhotos",
    "DeadLeaves",
    "PACKAGE_PHOTOS",
    "source_from_spec",
]


class LoadContext(NamedTuple):
    """What a source needs to know to load an item."""

    sensor_shape: tuple  # (H, W): procedural images are made at this size
    encoding: str  # transfer function of display-referred files
    clip_invalid: bool
    seed: int  # global seed (procedural sources derive their image from it and the id)


def _load_file(path, ctx: LoadContext):
    """``(Y, kind)`` of an image file, with evnoise's radiometry (same decoding as ``evnoise simulate``)."""
    from evnoise.radiometry import handle_invalid, load_luminance

    values, kind = load_luminance(path, ctx.encoding)
    return handle_invalid(values, os.fspath(path), ctx.clip_invalid), kind


@dataclass(frozen=True)
class FolderSource:
    """The image files of a folder (PNG, JPEG, TIFF, OpenEXR; not recursive), sorted naturally.

    Item ids are the file names. Files are read with evnoise's radiometry (as by
    ``evnoise simulate``); a file that cannot be read is skipped with its reason.

    Parameters
    ----------
    path : str or os.PathLike
        The folder (stored resolved to an absolute path).
    """

    kind = "folder"

    path: str

    def __post_init__(self):
        object.__setattr__(self, "path", os.fspath(Path(self.path).resolve()))

    def items(self) -> list:
        """The item ids: names of the folder's image files, sorted naturally.

        Returns
        -------
        list of str
            File names (not hidden, known image extension).

        Raises
        ------
        InputError
            The folder does not exist, cannot be listed or holds no image file.
        """
        from evnoise.radiometry import list_frames

        return [p.name for p in list_frames(self.path)]

    def load(self, item_id: str, ctx: LoadContext):
        """Relative linear luminance of one image file of the folder.

        Parameters
        ----------
        item_id : str
            The file's name in the folder, one of :meth:`items`.
        ctx : LoadContext
            Its ``encoding`` decodes display-referred files; with ``clip_invalid`` NaN, infinite or
            negative pixels are clipped rather than refused.

        Returns
        -------
        Y : numpy.ndarray
            Relative linear luminance, float64 ``(H, W)`` at the file's size.
        kind : str
            ``"display"`` (full-scale white is ``Y = 1``) or ``"linear"`` (scaled by ``lux_scale``).

        Raises
        ------
        InputError
            The file cannot be read or holds invalid pixels (without ``clip_invalid``).
        """
        return _load_file(Path(self.path) / item_id, ctx)

    def spec(self) -> dict:
        """What the manifest records of the source (:func:`source_from_spec` rebuilds it).

        Returns
        -------
        dict
            ``{"kind": "folder", "path": ...}``, the folder's absolute path.
        """
        return {"kind": self.kind, "path": self.path}


@dataclass(frozen=True)
class FilesSource:
    """Image files given one by one; item ids are the file names (which must differ).

    Parameters
    ----------
    paths : sequence of str or os.PathLike
        The files (stored resolved to absolute paths).
    """

    kind = "files"

    paths: tuple

    def __post_init__(self):
        paths = tuple(os.fspath(Path(p).resolve()) for p in self.paths)
        if not paths:
            raise InputError("FilesSource needs at least one file")
        names = [Path(p).name for p in paths]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise InputError(f"image files with the same name cannot be told apart in a dataset: {', '.join(dup)}")
        for p in paths:
            if not Path(p).is_file():
                raise InputError(f"image file not found: {p}")
        object.__setattr__(self, "paths", paths)

    def items(self) -> list:
        """The item ids: the files' names, in the order given.

        Returns
        -------
        list of str
            File names (without their folders).
        """
        return [Path(p).name for p in self.paths]

    def load(self, item_id: str, ctx: LoadContext):
        """Relative linear luminance of one of the files.

        Parameters
        ----------
        item_id : str
            The file's name, one of :meth:`items`.
        ctx : LoadContext
            Its ``encoding`` decodes display-referred files; with ``clip_invalid`` NaN, infinite or
            negative pixels are clipped rather than refused.

        Returns
        -------
        Y : numpy.ndarray
            Relative linear luminance, float64 ``(H, W)`` at the file's size.
        kind : str
            ``"display"`` (full-scale white is ``Y = 1``) or ``"linear"`` (scaled by ``lux_scale``).

        Raises
        ------
        InputError
            No file of that name in the source, or the file cannot be read or holds invalid pixels.
        """
        for p in self.paths:
            if Path(p).name == item_id:
                return _load_file(p, ctx)
        raise InputError(f"no file {item_id!r} in this source")

    def spec(self) -> dict:
        """What the manifest records of the source (:func:`source_from_spec` rebuilds it).

        Returns
        -------
        dict
            ``{"kind": "files", "paths": [...]}``, the files' absolute paths.
        """
        return {"kind": self.kind, "paths": list(self.paths)}


#: ``package -> (folder inside the package, file names)`` of the photos :class:`PackagePhotos` uses.
PACKAGE_PHOTOS = {
    "skimage": ("data", (
        "astronaut.png", "brick.png", "camera.png", "chelsea.png", "clock_motion.png", "coffee.png",
        "coins.png", "grass.png", "gravel.png", "hubble_deep_field.jpg", "ihc.png", "retina.jpg",
        "rocket.jpg", "text.png",
    )),
    "matplotlib": ("mpl-data/sample_data", ("grace_hopper.jpg",)),
    "sklearn": ("datasets/images", ("china.jpg", "flower.jpg")),
    "pywt": ("data", ("ascent.npz",)),
}


def _package_dir(name: str):
    """Folder of an installed package, found without importing it (``None`` when absent)."""
    try:
        spec = importlib.util.find_spec(name)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0])


@dataclass(frozen=True)
class PackagePhotos:
    """Natural photos that installed Python packages ship (read in place; nothing downloaded).

    Item ids are ``"<package>/<file>"``; only files present in the installed packages are
    listed (see the module docstring for the list and the licences).

    Parameters
    ----------
    packages : tuple of str
        Packages to look in (default: all of :data:`PACKAGE_PHOTOS`).
    """

    kind = "package-photos"

    packages: tuple = tuple(PACKAGE_PHOTOS)

    def __post_init__(self):
        unknown = [p for p in self.packages if p not in PACKAGE_PHOTOS]
        if unknown:
            raise ParameterError(f"unknown photo package(s) {unknown}; known: {', '.join(PACKAGE_PHOTOS)}")
        object.__setattr__(self, "packages", tuple(self.packages))

    def _path(self, item_id: str):
        package, _, name = item_id.partition("/")
        if package not in self.packages or name not in PACKAGE_PHOTOS[package][1]:
            raise InputError(f"{item_id!r} is not one of the package photos")
        root = _package_dir(package)
        if root is None:
            raise InputError(f"package {package} is not installed")
        return root / PACKAGE_PHOTOS[package][0] / name

    def items(self) -> list:
        """The item ids ``"<package>/<file>"`` of the photos present in the installed packages.

        Returns
        -------
        list of str
            Ids in the order of ``packages`` and of :data:`PACKAGE_PHOTOS`; packages not installed are
            passed over.

        Raises
        ------
        InputError
            None of the packages holds any of the photos.
        """
        out = []
        for package in self.packages:
            root = _package_dir(package)
            if root is None:
                continue
            folder, names = PACKAGE_PHOTOS[package]
            out.extend(f"{package}/{n}" for n in names if (root / folder / n).is_file())
        if not out:
            raise InputError("no package photos found: install scikit-image (pip install 'evnoise[train]') or "
                             "matplotlib")
        return out

    def load(self, item_id: str, ctx: LoadContext):
        """Relative linear luminance of one package photo.

        Parameters
        ----------
        item_id : str
            ``"<package>/<file>"``, one of :meth:`items`.
        ctx : LoadContext
            Its ``encoding`` decodes the photo (all are display-referred, 8 bits); with ``clip_invalid``
            invalid pixels are clipped rather than refused.

        Returns
        -------
        Y : numpy.ndarray
            Relative linear luminance, float64 ``(H, W)`` at the photo's size.
        kind : str
            ``"display"`` (full-scale white is ``Y = 1``).

        Raises
        ------
        InputError
            Not one of this source's photos, its package is not installed, or the file cannot be read.
        """
        path = self._path(item_id)
        if path.suffix == ".npz":
            from evnoise.radiometry import to_luminance

            try:
                with np.load(path) as data:
                    arr = np.asarray(data[data.files[0]])
            except Exception as exc:
                raise InputError(f"cannot read {path}: {exc}") from None
            if arr.dtype != np.uint8:
                arr = np.clip(np.rint(arr), 0, 255).astype(np.uint8)
            return to_luminance(arr, ctx.encoding, os.fspath(path))
        return _load_file(path, ctx)

    def spec(self) -> dict:
        """What the manifest records of the source (:func:`source_from_spec` rebuilds it).

        Returns
        -------
        dict
            ``{"kind": "package-photos", "packages": [...]}``.
        """
        return {"kind": self.kind, "packages": list(self.packages)}


@dataclass(frozen=True)
class DeadLeaves:
    """``count`` procedural dead-leaves images, made at the sensor size from the global seed.

    Item ids are ``"dead-leaves/000000"``, ``"dead-leaves/000001"``, ...; image ``k`` depends on
    the seed and its id only.

    Parameters
    ----------
    count : int
        Number of images.
    model : DeadLeavesModel, optional
        Parameters of the dead-leaves model.
    """

    kind = "dead-leaves"

    count: int
    model: DeadLeavesModel = field(default_factory=DeadLeavesModel)

    def __post_init__(self):
        if isinstance(self.count, bool) or not isinstance(self.count, (int, np.integer)) or self.count < 1:
            raise ParameterError(f"the number of procedural images must be an integer >= 1, got {self.count!r}")
        object.__setattr__(self, "count", int(self.count))

    def items(self) -> list:
        """The item ids ``"dead-leaves/000000"`` to ``"dead-leaves/<count - 1>"`` (six digits).

        Returns
        -------
        list of str
            ``count`` ids.
        """
        return [f"dead-leaves/{k:06d}" for k in range(self.count)]

    def load(self, item_id: str, ctx: LoadContext):
        """Make one dead-leaves image at the sensor size.

        Parameters
        ----------
        item_id : str
            The image's id, one of :meth:`items`; with ``ctx.seed`` it fixes the random draws.
        ctx : LoadContext
            Its ``sensor_shape`` is the image's size and its ``seed`` the global seed; ``encoding`` and
            ``clip_invalid`` are not used.

        Returns
        -------
        Y : numpy.ndarray
            Relative linear luminance, float64 ``(H, W)`` in ``[0, 1]``: the model's display image
            decoded with :func:`evnoise.radiometry.srgb_to_linear` (whatever ``ctx.encoding``).
        kind : str
            ``"display"`` (full-scale white is ``Y = 1``).
        """
        from evnoise.radiometry import srgb_to_linear

        from .pairs import source_generator
        from .procedural import dead_leaves

        display = dead_leaves(ctx.sensor_shape, source_generator(ctx.seed, item_id), self.model)
        return srgb_to_linear(display), "display"

    def spec(self) -> dict:
        """What the manifest records of the source (:func:`source_from_spec` rebuilds it).

        Returns
        -------
        dict
            ``{"kind": "dead-leaves", "count": ..., "model": {...}}``, the model as
            :meth:`DeadLeavesModel.to_dict` gives it.
        """
        return {"kind": self.kind, "count": self.count, "model": self.model.to_dict()}


def source_from_spec(spec: dict):
    """Rebuild a source from its ``spec()`` (as stored in a manifest)."""
    kind = spec.get("kind")
    if kind == "folder":
        return FolderSource(spec["path"])
    if kind == "files":
        return FilesSource(tuple(spec["paths"]))
    if kind == "package-photos":
        return PackagePhotos(tuple(spec["packages"]))
    if kind == "dead-leaves":
        model = dict(spec.get("model", {}))
        if "blur_px" in model:
            model["blur_px"] = tuple(model["blur_px"])
        return DeadLeaves(spec["count"], DeadLeavesModel(**model))
    raise ParameterError(f"unknown scene source kind {kind!r}")
