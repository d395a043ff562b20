"""Dataset generators (importable as ``evnoise.generators``): NE2I-style count/image pairs.

``make_dataset(sources, out_dir, PairConfig(...))`` turns scenes into training pairs for
Noise2Image-style reconstruction (paper section 5): per pixel ON and OFF noise-event counts of
a static scene over a time window, binned 2 x 2, paired with the scene's grey image. Pairs go
to HDF5 shards with a manifest; :class:`PairDataset` reads a split of them (also from
PyTorch's ``DataLoader`` with worker processes). Scene sources: image folders and files
(:class:`FolderSource`, :class:`FilesSource`), photos shipped by installed packages
(:class:`PackagePhotos`), and procedural dead-leaves images (:class:`DeadLeaves`).

The same seed gives the same bytes whatever the number of worker processes or a Dask cluster,
and an interrupted run resumes where it stopped. Command line: ``evnoise make-dataset``.

Examples
--------
A training set with no image collection, then a loader for it::

    from evnoise.generators import DeadLeaves, PackagePhotos, PairConfig, PairDataset, make_dataset

    config = PairConfig(crop_shape=(256, 256), crops_per_image=8, windows_s=(0.1, 0.25, 0.5, 1, 2),
                        max_lux=(6, 30), seed=1)
    make_dataset([DeadLeaves(500), PackagePhotos()], "ne2i-synthetic", config, progress=True)
    train = PairDataset("ne2i-synthetic", "train")   # torch.utils.data.DataLoader(train, ...)

(a script that uses worker processes needs the ``if __name__ == "__main__":`` guard).

Importing this package is cheap; the parts load on first use.
"""

from __future__ import annotations

from evnoise._lazy import lazy_attributes

_LAZY = {
    "PairConfig": ".config",
    "make_dataset": ".dataset",
    "plan_dataset": ".dataset",
    "DatasetResult": ".dataset",
    "load_manifest": ".dataset",
    "PairDataset": ".reader",
    "FolderSource": ".sources",
    "FilesSource": ".sources",
    "PackagePhotos": ".sources",
    "DeadLeaves": ".sources",
    "DeadLeavesModel": ".procedural",
    "dead_leaves": ".procedural",
    "linear_to_srgb": ".pairs",
    "summarise_dataset": ".summary",
}

__all__ = list(_LAZY)


__getattr__, __dir__ = lazy_attributes(__name__, _LAZY)
