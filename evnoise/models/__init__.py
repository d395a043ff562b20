"""Reconstructor checkpoints shipped with evnoise (package data).

``evk3-hd.pt``: the default model of ``evnoise reconstruct`` for the ``evk3-hd`` preset,
made by ``python -m evnoise.reconstruct.pretrain`` (see benchmarks/RECONSTRUCTION.md);
``evnoise info evnoise/models/evk3-hd.pt`` prints its card.
"""
