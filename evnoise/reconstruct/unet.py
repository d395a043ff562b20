"""A compact U-Net from noise-event rates to a display-encoded image (needs PyTorch).

Built from four small modules, in the manner of a denoising-diffusion U-Net without the time
embedding: :class:`ConvNormAct` (3x3 convolution, GroupNorm, SiLU), :class:`ResBlock` (two of
them and a residual path), :class:`Downsample` (pixel-unshuffle then 1x1 convolution, so no
information is thrown away) and :class:`Upsample` (nearest-neighbour then 3x3 convolution).

The network takes ``(N, C, H, W)`` with ``C`` = 2 (ON, OFF rates) or 1 (one polarity), one more
with the ML-estimate channel of :class:`~evnoise.reconstruct.InputSpec`, and returns ``(N, 1, H, W)``.
Inputs whose sides are not multiples of ``stem * 2 ** (levels - 1)`` are padded (replicate by
default) and the output is cropped back, so any size >= 1 works.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from ..errors import InputError, ParameterError
from ._torch import require_torch

torch = require_torch()
nn = torch.nn
F = torch.nn.functional

__all__ = ["UNetConfig", "UNet", "ConvNormAct", "ResBlock", "Downsample", "Upsample"]

PADDING_MODES = ("replicate", "reflect", "zeros", "none")


#: Largest value of each :class:`UNetConfig` setting read from a checkpoint or given by a user (far past
#: any network evnoise trains: its default has 16 base channels, 3 levels and one block per level).
UNET_LIMITS = {"in_channels": 64, "out_channels": 64, "base_channels": 4096, "blocks_per_level": 64,
               "groups": 4096, "stem": 16, "mult": 256, "levels": 10}
#: Most weights a :class:`UNetConfig` may describe, by :meth:`UNetConfig.parameter_bound` (at most 1 GB of
#: float32; the default network has 0.36 M): a checkpoint declaring base_channels=65536 or 100,000 blocks
#: per level would otherwise allocate without bound.
MAX_PARAMETERS = 250_000_000


@dataclass(frozen=True)
class UNetConfig:
    """Hyper-parameters of :class:`UNet` (stored in checkpoints).

    Parameters
    ----------
    in_channels : int
        Input channels: 2 for ON and OFF rates, 1 for a single polarity (one more with the
        ML-estimate channel).
    out_channels : int
        Output channels (1: a grayscale image).
    base_channels : int
        Feature channels at full resolution; level ``i`` has ``base_channels * channel_mults[i]``.
    channel_mults : tuple of int
        One multiplier per resolution level; ``len(channel_mults) - 1`` downsamplings.
    blocks_per_level : int
        Residual blocks per level on the way down (and up).
    groups : int
        GroupNorm groups (must divide every level's channel count).
    stem : int
        Space-to-depth factor of the stem: with ``stem = 2`` the input is pixel-unshuffled
        (``C`` -> ``4C`` channels at half resolution), the body runs at half resolution and
        the head pixel-shuffles back. Lossless, and about 4x cheaper at full resolution.
    padding : {"replicate", "reflect", "zeros", "none"}
        How inputs are padded to a multiple of :attr:`multiple` (``stem * 2 ** (levels - 1)``);
        ``"none"`` raises instead.
    """

    in_channels: int = 2
    out_channels: int = 1
    base_channels: int = 16
    channel_mults: tuple = (1, 2, 4)
    blocks_per_level: int = 1
    groups: int = 8
    stem: int = 1
    padding: str = "replicate"

    def __post_init__(self):
        mults = self.channel_mults
        if isinstance(mults, (str, bytes)) or not hasattr(mults, "__iter__"):
            raise ParameterError(f"UNetConfig.channel_mults must be a sequence of integers, got {mults!r}"[:200])
        mults = list(mults)
        if len(mults) > UNET_LIMITS["levels"]:
            raise ParameterError(f"UNetConfig.channel_mults may have at most {UNET_LIMITS['levels']} levels, "
                                 f"got {len(mults)}")
        if any(isinstance(m, bool) or not isinstance(m, int) for m in mults):
            raise ParameterError(f"UNetConfig.channel_mults must be integers >= 1, got {mults!r}"[:200])
        object.__setattr__(self, "channel_mults", tuple(int(m) for m in mults))
        for name in ("in_channels", "out_channels", "base_channels", "blocks_per_level", "groups", "stem"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ParameterError(f"UNetConfig.{name} must be an integer >= 1, got {value!r}")
            if value > UNET_LIMITS[name]:
                raise ParameterError(f"UNetConfig.{name} must be <= {UNET_LIMITS[name]}, got {value!r}")
        if not self.channel_mults or any(m < 1 or m > UNET_LIMITS["mult"] for m in self.channel_mults):
            raise ParameterError(f"UNetConfig.channel_mults must be integers from 1 to {UNET_LIMITS['mult']}, "
                                 f"got {self.channel_mults!r}")
        n = self.parameter_bound()
        if n > MAX_PARAMETERS:
            raise ParameterError(f"UNetConfig describes a network of about {n:,} parameters, more than the "
                                 f"{MAX_PARAMETERS:,} evnoise builds (base_channels {self.base_channels}, "
                                 f"channel_mults {list(self.channel_mults)}, blocks_per_level {self.blocks_per_level})")
        for m in self.channel_mults:
            if (self.base_channels * m) % self.groups:
                raise ParameterError(
                    f"UNetConfig.groups={self.groups} must divide every level's channels "
                    f"(base_channels * mult = {self.base_channels * m})"
                )
        if self.padding not in PADDING_MODES:
            raise ParameterError(f"UNetConfig.padding must be one of {PADDING_MODES}, got {self.padding!r}")

    def parameter_bound(self) -> int:
        """An upper bound on the number of weights of the :class:`UNet` this describes, from the
        configuration alone (checked before anything is allocated): per level of ``c`` channels,
        every 3x3 convolution of the blocks down and up (the ones up read ``2c``), their 1x1 skips,
        the resampling convolutions and the norms, rounded up to ``(6 blocks + 6) 9 c^2 + 64 c``."""
        chans = [self.base_channels * m for m in self.channel_mults]
        c_stem = self.stem * self.stem
        n = 9 * (self.in_channels * c_stem + 1) * chans[0] + 9 * (chans[0] + 1) * self.out_channels * c_stem
        for i, c in enumerate(chans):
            c_next = chans[i + 1] if i + 1 < len(chans) else c
            n += (6 * self.blocks_per_level + 6) * 9 * max(c, c_next) ** 2 + 64 * max(c, c_next)
        return n

    @property
    def multiple(self) -> int:
        """Input sides must be multiples of this (or are padded to one)."""
        return self.stem * 2 ** (len(self.channel_mults) - 1)

    def to_dict(self) -> dict:
        """The settings as plain values (the checkpoint's ``model`` entry).

        Returns
        -------
        dict
            Every field by name, ``channel_mults`` as a list; :meth:`from_dict` takes it back.
        """
        d = dataclasses.asdict(self)
        d["channel_mults"] = list(self.channel_mults)
        return d

    @classmethod
    def from_dict(cls, data: dict) -> "UNetConfig":
        """Rebuild a configuration from :meth:`to_dict`'s values, checked as the constructor checks them.

        Parameters
        ----------
        data : dict
            Field values by name; missing fields take their defaults.

        Returns
        -------
        UNetConfig
            The configuration.

        Raises
        ------
        ParameterError
            If ``data`` has a key that is not a field, or a value out of range.
        """
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - names
        if unknown:
            raise ParameterError(f"unknown U-Net setting(s): {', '.join(sorted(unknown))}")
        return cls(**data)


class ConvNormAct(nn.Module):
    """3x3 convolution, GroupNorm, SiLU."""

    def __init__(self, c_in: int, c_out: int, *, groups: int = 8):
        super().__init__()
        self.conv = nn.Conv2d(c_in, c_out, 3, padding=1)
        self.norm = nn.GroupNorm(groups, c_out)
        self.act = nn.SiLU()

    def forward(self, x):
        return self.act(self.norm(self.conv(x)))


class ResBlock(nn.Module):
    """Two :class:`ConvNormAct` with a residual path (1x1 convolution when channels change)."""

    def __init__(self, c_in: int, c_out: int, *, groups: int = 8):
        super().__init__()
        self.block1 = ConvNormAct(c_in, c_out, groups=groups)
        self.block2 = ConvNormAct(c_out, c_out, groups=groups)
        self.skip = nn.Conv2d(c_in, c_out, 1) if c_in != c_out else nn.Identity()

    def forward(self, x):
        return self.block2(self.block1(x)) + self.skip(x)


class Downsample(nn.Module):
    """Halve the resolution losslessly: pixel-unshuffle (C -> 4C) then a 1x1 convolution."""

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.unshuffle = nn.PixelUnshuffle(2)
        self.proj = nn.Conv2d(4 * c_in, c_out, 1)

    def forward(self, x):
        return self.proj(self.unshuffle(x))


class Upsample(nn.Module):
    """Double the resolution: nearest-neighbour upsampling then a 3x3 convolution."""

    def __init__(self, c_in: int, c_out: int):
        super().__init__()
        self.conv = nn.Conv2d(c_in, c_out, 3, padding=1)

    def forward(self, x):
        return self.conv(F.interpolate(x, scale_factor=2, mode="nearest"))


class UNet(nn.Module):
    """Compact U-Net: noise-event rates ``(N, C, H, W)`` -> display-encoded image ``(N, 1, H, W)``.

    All hyper-parameters are keyword-only (see :class:`UNetConfig`); ``UNet(config=cfg)`` builds
    from a config object. The output is not clamped: clamp to ``[0, 1]`` for display.
    """

    def __init__(self, *, config: UNetConfig | None = None, **settings):
        super().__init__()
        if config is not None and settings:
            raise ParameterError("give either config or keyword settings, not both")
        self.config = config if config is not None else UNetConfig(**settings)
        cfg = self.config
        widths = [cfg.base_channels * m for m in cfg.channel_mults]
        g = cfg.groups
        s = cfg.stem
        self.stem_in = nn.PixelUnshuffle(s) if s > 1 else nn.Identity()
        self.stem_out = nn.PixelShuffle(s) if s > 1 else nn.Identity()
        self.init_conv = nn.Conv2d(cfg.in_channels * s * s, widths[0], 3, padding=1)
        self.downs = nn.ModuleList()
        for i, w in enumerate(widths):
            blocks = nn.ModuleList(ResBlock(w, w, groups=g) for _ in range(cfg.blocks_per_level))
            down = Downsample(w, widths[i + 1]) if i + 1 < len(widths) else nn.Identity()
            self.downs.append(nn.ModuleList([blocks, down]))
        self.mid = ResBlock(widths[-1], widths[-1], groups=g)
        self.ups = nn.ModuleList()
        for i in reversed(range(len(widths))):
            w = widths[i]
            up = Upsample(widths[i + 1], w) if i + 1 < len(widths) else nn.Identity()
            blocks = nn.ModuleList(
                ResBlock(2 * w if j == 0 else w, w, groups=g) for j in range(cfg.blocks_per_level)
            )
            self.ups.append(nn.ModuleList([up, blocks]))
        self.final = nn.Conv2d(widths[0], cfg.out_channels * s * s, 1)

    def check_input(self, x):
        """Raise :class:`~evnoise.InputError` unless ``x`` is a float tensor ``(N, C, H, W)``.

        Parameters
        ----------
        x : torch.Tensor
            The network input: floating point, 4-D, ``C`` = ``config.in_channels``, no side of length
            0; with padding ``"none"`` its height and width multiples of ``config.multiple``.
        """
        if not torch.is_tensor(x) or not torch.is_floating_point(x):
            raise InputError("UNet input must be a floating-point torch tensor")
        if x.ndim != 4 or x.shape[1] != self.config.in_channels:
            raise InputError(
                f"UNet input must have shape (N, {self.config.in_channels}, H, W), got {tuple(x.shape)}"
            )
        if x.shape[0] == 0 or x.shape[2] == 0 or x.shape[3] == 0:
            raise InputError(f"UNet input is empty: shape {tuple(x.shape)}")
        m = self.config.multiple
        if self.config.padding == "none" and (x.shape[2] % m or x.shape[3] % m):
            raise InputError(
                f"UNet input height and width must be multiples of {m} with padding='none', "
                f"got {x.shape[2]}x{x.shape[3]}"
            )

    def forward(self, x):
        """The image of a batch of inputs (padded to :attr:`UNetConfig.multiple` and cropped back).

        Parameters
        ----------
        x : torch.Tensor
            Float input ``(N, C, H, W)`` (see :meth:`check_input`).

        Returns
        -------
        torch.Tensor
            ``(N, out_channels, H, W)``, not clamped.
        """
        self.check_input(x)
        h, w = x.shape[-2:]
        m = self.config.multiple
        ph, pw = (-h) % m, (-w) % m
        if ph or pw:
            mode = self.config.padding
            if mode == "reflect" and (ph >= h or pw >= w):
                mode = "replicate"  # reflection needs pad < size
            if mode == "zeros":
                x = F.pad(x, (0, pw, 0, ph))
            else:
                x = F.pad(x, (0, pw, 0, ph), mode=mode)
        x = self.init_conv(self.stem_in(x))
        skips = []
        for blocks, down in self.downs:
            for block in blocks:
                x = block(x)
            skips.append(x)
            x = down(x)
        x = self.mid(x)
        for up, blocks in self.ups:
            x = up(x)
            x = torch.cat([x, skips.pop()], dim=1)
            for block in blocks:
                x = block(x)
        x = self.stem_out(self.final(x))
        return x[..., :h, :w]

    def n_parameters(self) -> int:
        """Number of weights of the network.

        Returns
        -------
        int
            Elements of all its parameter tensors.
        """
        return sum(p.numel() for p in self.parameters())
