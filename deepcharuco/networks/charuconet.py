"""ChArUcoNet: a SuperPoint-style encoder with a point head and a corner-ID head.

    image (B, 1, H, W), values in [0, 1]
      -> VGG encoder: 2 x conv3x3 per stage, 3 max-poolings       (B, C4, H/8, W/8)
      -> point head: conv3x3 -> conv1x1 -> 65 logits per cell     (64 pixel positions + dustbin)
      -> ID head:    conv3x3 -> conv1x1 -> N+1 logits per cell    (N corner IDs + dustbin, last)

At the paper's width (64, 64, 128, 128; heads 256) the network has 1.24 M parameters, 4.8 MB
in float32, as the paper reports. The `lite` width is for real time on a 2-core CPU.

The ``fast`` architecture (``arch="fast"``, `ChArUcoNetConfig.fast`) has the same outputs from another
encoder, built to cost a fifth of ``lite``'s multiply-adds and run 3x faster on a CPU:

    image -> pixel_unshuffle by 4 (16 channels at 1/4) -> conv3x3 w4 -> conv3x3 stride 2 to w8 (1/8)
          -> conv3x3 w8                                                   the trunk (B, w8, H/8, W/8)
    point head: conv3x3 -> conv1x1 -> 65 logits, on the trunk
    context:    trunk -> conv3x3 stride 2 w16 (1/16) -> conv3x3 stride 2 w32 (1/32), each projected by
                a conv1x1 to w8 and upsampled (nearest) back to 1/8, added to the trunk
    ID head:    conv3x3 -> conv1x1 -> N+1 logits, on the trunk plus context (an ID needs a marker's view)

Space-to-depth instead of thin full-resolution layers: with ONNX Runtime on a CPU the full-resolution
layers of few channels are memory-bound, and an XFeat-shaped stem ran only 1.9x faster than lite at
320x240 for 5x fewer multiply-adds (issue 51); `benchmarks/network.py --architectures` measures them.

Every 3x3 convolution is followed by batch normalisation (``batch_norm``, as in SuperPoint's
trainers; the paper does not say): without it these 10-layer plain networks collapsed here to
predicting the label marginals (all-dustbin cells, a uniform RefineNet grid) for the first
thousand steps at the learning rates that make CPU training affordable.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F
from torch import nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

from deepcharuco.core.errors import OptionError
from deepcharuco.networks.cells import CELL


@dataclass(frozen=True)
class ChArUcoNetConfig:
    """Architecture of a ChArUcoNet. ``arch`` "vgg" (the paper's): ``widths`` are the channels of the 4
    encoder stages; ``arch`` "fast": ``widths`` are the channels at 1/4, 1/8, 1/16 and 1/32 of the input
    (module docstring); ``head``: head channels."""

    num_corners: int = 16
    widths: tuple[int, int, int, int] = (64, 64, 128, 128)
    head: int = 256
    batch_norm: bool = True
    arch: str = "vgg"

    @classmethod
    def paper(cls, num_corners: int = 16) -> "ChArUcoNetConfig":
        return cls(num_corners=num_corners)

    @classmethod
    def lite(cls, num_corners: int = 16) -> "ChArUcoNetConfig":
        """About 1/10 of the paper's compute: for >= 30 fps at 320x240 on a 2-core CPU."""
        return cls(num_corners=num_corners, widths=(16, 32, 48, 64), head=96)

    @classmethod
    def fast(cls, num_corners: int = 16) -> "ChArUcoNetConfig":
        """A space-to-depth encoder (module docstring): 1/9 of lite's point-network multiply-adds (1/7 with the ID head)."""
        return cls(num_corners=num_corners, widths=FAST_WIDTHS, head=FAST_HEAD, arch="fast")

    def __post_init__(self):
        if self.arch not in ARCHITECTURES:
            raise ValueError(f"ChArUcoNet arch must be one of {ARCHITECTURES}, got {self.arch!r}")

    def to_dict(self) -> dict:
        data = {**asdict(self), "widths": list(self.widths)}
        if self.arch == "vgg":  # files of the paper's encoder stay as they were before "arch" existed
            del data["arch"]
        return data

    @classmethod
    def from_dict(cls, data: dict) -> "ChArUcoNetConfig":
        return cls(num_corners=int(data["num_corners"]), widths=tuple(int(w) for w in data["widths"]), head=int(data["head"]),
                   batch_norm=bool(data.get("batch_norm", False)),  # format 1 files before batch_norm had none
                   arch=str(data.get("arch", "vgg")))


ARCHITECTURES = ("vgg", "fast")
WIDTH_NAMES = ("paper", "lite", "fast")  # the named configurations, as train.*'s --width takes them
# Chosen by benchmarks/network.py --architectures (issue 51): see the module docstring.
FAST_WIDTHS = (24, 48, 64, 64)
FAST_HEAD = 48


def named_config(width: str, num_corners: int) -> ChArUcoNetConfig:
    """The configuration called ``width`` ("paper", "lite" or "fast") for a board of ``num_corners`` corners."""
    if width not in WIDTH_NAMES:
        raise ValueError(f"ChArUcoNet width must be one of {WIDTH_NAMES}, got {width!r}")
    return getattr(ChArUcoNetConfig, width)(num_corners)


def conv(in_channels: int, out_channels: int, kernel: int = 3, relu: bool = True, batch_norm: bool = False) -> nn.Sequential:
    """Convolution ('same' padding) [-> BatchNorm] [-> ReLU]."""
    layers = [nn.Conv2d(in_channels, out_channels, kernel, padding=kernel // 2, bias=not batch_norm)]
    if batch_norm:
        layers.append(nn.BatchNorm2d(out_channels))
    if relu:
        layers.append(nn.ReLU(inplace=True))
    return nn.Sequential(*layers)


class VGGEncoder(nn.Module):
    """SuperPoint's encoder: 4 stages of two 3x3 convolutions, max-pooling between them (/8)."""

    def __init__(self, widths: tuple[int, int, int, int], in_channels: int = 1, batch_norm: bool = False):
        super().__init__()
        stages, channels = [], in_channels
        for i, width in enumerate(widths):
            stage = [conv(channels, width, batch_norm=batch_norm), conv(width, width, batch_norm=batch_norm)]
            if i < len(widths) - 1:
                stage.append(nn.MaxPool2d(2, 2))
            stages.append(nn.Sequential(*stage))
            channels = width
        self.stages = nn.Sequential(*stages)
        self.out_channels = channels

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.stages(x)


class FastEncoder(nn.Module):
    """The ``fast`` encoder (module docstring): forward(image) -> trunk (B, w8, H/8, W/8); `context` adds the
    1/16 and 1/32 branches to a trunk for the ID head. H and W must be multiples of 8 (any, not of 32: the
    coarse maps are resized to the trunk's own size)."""

    def __init__(self, widths: tuple[int, int, int, int], batch_norm: bool = True):
        super().__init__()
        w4, w8, w16, w32 = widths
        self.stem = nn.Sequential(nn.PixelUnshuffle(4), conv(16, w4, batch_norm=batch_norm),
                                  strided(w4, w8, batch_norm), conv(w8, w8, batch_norm=batch_norm))
        self.down16 = strided(w8, w16, batch_norm)
        self.down32 = strided(w16, w32, batch_norm)
        self.project16 = nn.Conv2d(w16, w8, 1)
        self.project32 = nn.Conv2d(w32, w8, 1)
        self.out_channels = w8

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return self.stem(image)

    def context(self, trunk: torch.Tensor) -> torch.Tensor:
        coarse16 = self.down16(trunk)
        coarse32 = self.down32(coarse16)
        size = trunk.shape[-2:]
        return (trunk + F.interpolate(self.project16(coarse16), size=size, mode="nearest")
                + F.interpolate(self.project32(coarse32), size=size, mode="nearest"))


def strided(in_channels: int, out_channels: int, batch_norm: bool) -> nn.Sequential:
    """3x3 convolution of stride 2 (padding 1: output size ceil(n / 2)) [-> BatchNorm] -> ReLU."""
    layers = [nn.Conv2d(in_channels, out_channels, 3, stride=2, padding=1, bias=not batch_norm)]
    if batch_norm:
        layers.append(nn.BatchNorm2d(out_channels))
    return nn.Sequential(*layers, nn.ReLU(inplace=True))


class ChArUcoNet(nn.Module):
    """forward(image (B, 1, H, W) in [0, 1]) -> (point logits (B, 65, H/8, W/8), ID logits (B, N+1, H/8, W/8)).

    H and W must be multiples of 8.
    """

    def __init__(self, config: ChArUcoNetConfig = ChArUcoNetConfig()):
        super().__init__()
        self.config = config
        bn = config.batch_norm
        self.encoder = FastEncoder(config.widths, bn) if config.arch == "fast" else VGGEncoder(config.widths, batch_norm=bn)
        channels = self.encoder.out_channels
        self.point_head = nn.Sequential(conv(channels, config.head, batch_norm=bn), conv(config.head, CELL * CELL + 1, 1, relu=False))
        self.id_head = nn.Sequential(conv(channels, config.head, batch_norm=bn),
                                     conv(config.head, config.num_corners + 1, 1, relu=False))

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        features = self.encoder(image)
        context = self.encoder.context(features) if isinstance(self.encoder, FastEncoder) else features
        return self.point_head(features), self.id_head(context)

    def points(self, image: torch.Tensor) -> torch.Tensor:
        """The point logits of `forward` alone (B, 65, H/8, W/8), without the ID head's work (~8 % of the lite
        network's): for boards found by their markers, which never read the ID head."""
        return self.point_head(self.encoder(image))


class PointHeadOnly(nn.Module):
    """A ChArUcoNet whose forward is its `ChArUcoNet.points`: exports (ONNX, TorchScript) trace ``forward``."""

    def __init__(self, charuconet: ChArUcoNet):
        super().__init__()
        self.charuconet = charuconet

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        return self.charuconet.points(image)


def fold_batch_norm(model: nn.Module) -> nn.Module:
    """Fold every Conv2d -> BatchNorm2d pair into one Conv2d, in place, for inference: the same outputs
    (to float rounding) for less work. ``model`` must be in eval mode (running statistics)."""
    if model.training:
        raise OptionError("fold_batch_norm needs a model in eval mode: call model.eval() first")
    for module in model.modules():
        if isinstance(module, nn.Sequential):
            for i in range(len(module) - 1):
                if isinstance(module[i], nn.Conv2d) and isinstance(module[i + 1], nn.BatchNorm2d):
                    module[i] = fuse_conv_bn_eval(module[i], module[i + 1])
                    module[i + 1] = nn.Identity()
    return model
