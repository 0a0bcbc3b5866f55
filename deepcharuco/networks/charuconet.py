"""ChArUcoNet: a SuperPoint-style encoder with a point head and a corner-ID head.

    image (B, 1, H, W), values in [0, 1]
      -> VGG encoder: 2 x conv3x3 per stage, 3 max-poolings       (B, C4, H/8, W/8)
      -> point head: conv3x3 -> conv1x1 -> 65 logits per cell     (64 pixel positions + dustbin)
      -> ID head:    conv3x3 -> conv1x1 -> N+1 logits per cell    (N corner IDs + dustbin, last)

At the paper's width (64, 64, 128, 128; heads 256) the network has 1.24 M parameters, 4.8 MB
in float32, as the paper reports. The `lite` width is for real time on a 2-core CPU.

Every 3x3 convolution is followed by batch normalisation (``batch_norm``, as in SuperPoint's
trainers; the paper does not say): without it these 10-layer plain networks collapsed here to
predicting the label marginals (all-dustbin cells, a uniform RefineNet grid) for the first
thousand steps at the learning rates that make CPU training affordable.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn
from torch.nn.utils.fusion import fuse_conv_bn_eval

from deepcharuco.core.errors import OptionError
from deepcharuco.networks.cells import CELL


@dataclass(frozen=True)
class ChArUcoNetConfig:
    """Architecture of a ChArUcoNet. ``widths``: channels of the 4 encoder stages; ``head``: head channels."""

    num_corners: int = 16
    widths: tuple[int, int, int, int] = (64, 64, 128, 128)
    head: int = 256
    batch_norm: bool = True

    @classmethod
    def paper(cls, num_corners: int = 16) -> "ChArUcoNetConfig":
        return cls(num_corners=num_corners)

    @classmethod
    def lite(cls, num_corners: int = 16) -> "ChArUcoNetConfig":
        """About 1/10 of the paper's compute: for >= 30 fps at 320x240 on a 2-core CPU."""
        return cls(num_corners=num_corners, widths=(16, 32, 48, 64), head=96)

    def to_dict(self) -> dict:
        return {**asdict(self), "widths": list(self.widths)}

    @classmethod
    def from_dict(cls, data: dict) -> "ChArUcoNetConfig":
        return cls(num_corners=int(data["num_corners"]), widths=tuple(int(w) for w in data["widths"]), head=int(data["head"]),
                   batch_norm=bool(data.get("batch_norm", False)))  # format 1 files before batch_norm had none


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


class ChArUcoNet(nn.Module):
    """forward(image (B, 1, H, W) in [0, 1]) -> (point logits (B, 65, H/8, W/8), ID logits (B, N+1, H/8, W/8)).

    H and W must be multiples of 8.
    """

    def __init__(self, config: ChArUcoNetConfig = ChArUcoNetConfig()):
        super().__init__()
        self.config = config
        bn = config.batch_norm
        self.encoder = VGGEncoder(config.widths, batch_norm=bn)
        channels = self.encoder.out_channels
        self.point_head = nn.Sequential(conv(channels, config.head, batch_norm=bn), conv(config.head, CELL * CELL + 1, 1, relu=False))
        self.id_head = nn.Sequential(conv(channels, config.head, batch_norm=bn),
                                     conv(config.head, config.num_corners + 1, 1, relu=False))

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        features = self.encoder(image)
        return self.point_head(features), self.id_head(features)

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
