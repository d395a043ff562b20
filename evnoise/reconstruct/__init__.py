"""The reconstructor: a small PyTorch U-Net from noise-event counts to images (needs ``evnoise[train]``)."""
