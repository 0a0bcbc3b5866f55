"""RefineNet: 24x24 patch -> 4096-way softmax over the central 8x8 pixels at 8x resolution.

    patch (B, 1, 24, 24) in [0, 1]
      -> the VGG encoder of ChArUcoNet (with BatchNorm)     (B, 128, 3, 3)
      -> conv3x3 128 -> 128, then the bottleneck conv1x1 128 -> 8   (B, 8, 3, 3)
      -> flatten (72) -> linear -> 4096 logits = a 64 x 64 grid, row-major (row = y)

1.07 M parameters, 4.1 MB in float32, as the paper reports.

The ``fast`` architecture (``arch="fast"``, `RefineNetConfig.fast`) has the same output from a space-to-depth
encoder, for about a third of the ``lite`` width's multiply-adds and time on a CPU (issue 51; with the fast point
networks RefineNet had become a large share of the deep detector's frame):

    patch -> pixel_unshuffle by 2 (4 channels at 12x12) -> 2 x conv3x3 w1 -> max-pool (6x6)
          -> 2 x conv3x3 w2 -> max-pool (3x3) -> 2 x conv3x3 w3 -> the head and classifier above

The lossless rearrangement keeps every pixel for the sub-pixel answer; it spares the thin layers at 24x24 that are
memory-bound in ONNX Runtime (as ChArUcoNet's fast encoder does at full resolution).

Sub-pixel convention (OpenCV's: pixel centres at integers). The central 8x8 pixels of a
patch are 8..15, covering positions [7.5, 15.5) on each axis. Grid cell j (0..63) covers
[7.5 + j/8, 7.5 + (j+1)/8); a corner at ``offset`` is cell ``floor((offset - 7.5) * 8)`` and
the cell decodes to its centre ``7.5 + (j + 0.5) / 8``, so encode->decode errs by at most
1/16 px per axis. (Taking ``j / 8 + 8`` instead, as one public reimplementation does, is
half a pixel off.)
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import nn

from deepcharuco.networks.charuconet import VGGEncoder, conv
from deepcharuco.networks.offsets import CENTRE_LOW, GRID, PATCH, soft_argmax_offsets  # noqa: F401 (PATCH: API)


@dataclass(frozen=True)
class RefineNetConfig:
    widths: tuple[int, ...] = (64, 64, 128, 128)
    head: int = 128
    bottleneck: int = 8
    batch_norm: bool = True  # see charuconet's docstring
    arch: str = "vgg"  # "vgg": ``widths`` are the VGG encoder's 4 stages; "fast": the 3 stages after pixel_unshuffle

    @classmethod
    def paper(cls) -> "RefineNetConfig":
        return cls()

    @classmethod
    def lite(cls) -> "RefineNetConfig":
        return cls(widths=(16, 32, 48, 64), head=64, bottleneck=8)

    @classmethod
    def fast(cls) -> "RefineNetConfig":
        """The space-to-depth encoder (module docstring): 1.7 M multiply-adds a patch against lite's 5.9 M."""
        return cls(widths=(16, 32, 48), head=48, bottleneck=8, arch="fast")

    def __post_init__(self):
        if self.arch not in ARCHITECTURES:
            raise ValueError(f"RefineNet arch must be one of {ARCHITECTURES}, got {self.arch!r}")
        if len(self.widths) != (4 if self.arch == "vgg" else 3):
            raise ValueError(f"a {self.arch} RefineNet has {4 if self.arch == 'vgg' else 3} widths, got {self.widths}")

    def to_dict(self) -> dict:
        data = {**asdict(self), "widths": list(self.widths)}
        if self.arch == "vgg":  # files of the paper's encoder stay as they were before "arch" existed
            del data["arch"]
        return data

    @classmethod
    def from_dict(cls, data: dict) -> "RefineNetConfig":
        return cls(widths=tuple(int(w) for w in data["widths"]), head=int(data["head"]), bottleneck=int(data["bottleneck"]),
                   batch_norm=bool(data.get("batch_norm", False)),  # format 1 files before batch_norm had none
                   arch=str(data.get("arch", "vgg")))


ARCHITECTURES = ("vgg", "fast")
WIDTH_NAMES = ("paper", "lite", "fast")  # the named configurations, as train.refinenet's --width takes them


class FastPatchEncoder(nn.Module):
    """The ``fast`` encoder (module docstring): (B, 1, 24, 24) -> (B, widths[-1], 3, 3)."""

    def __init__(self, widths: tuple[int, int, int], batch_norm: bool = True):
        super().__init__()
        layers, channels = [nn.PixelUnshuffle(2)], 4
        for i, width in enumerate(widths):
            layers += [conv(channels, width, batch_norm=batch_norm), conv(width, width, batch_norm=batch_norm)]
            if i < len(widths) - 1:
                layers.append(nn.MaxPool2d(2, 2))
            channels = width
        self.layers = nn.Sequential(*layers)
        self.out_channels = channels

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.layers(x)


class RefineNet(nn.Module):
    """forward(patches (B, 1, 24, 24) in [0, 1]) -> logits (B, 4096) over the 64x64 sub-pixel grid."""

    def __init__(self, config: RefineNetConfig = RefineNetConfig()):
        super().__init__()
        self.config = config
        bn = config.batch_norm
        self.encoder = FastPatchEncoder(config.widths, bn) if config.arch == "fast" else \
            VGGEncoder(config.widths, batch_norm=bn)
        self.head = nn.Sequential(conv(self.encoder.out_channels, config.head, batch_norm=bn),
                                  conv(config.head, config.bottleneck, 1, batch_norm=bn))
        self.classifier = nn.Linear(config.bottleneck * (PATCH // 8) ** 2, GRID * GRID)

    def forward(self, patches: torch.Tensor) -> torch.Tensor:
        return self.classifier(torch.flatten(self.head(self.encoder(patches)), 1))


def offset_to_cell(offset: torch.Tensor) -> torch.Tensor:
    """(..., 2) corner offsets (x, y) in patch pixels -> (...) class index row * 64 + col.

    Offsets outside [7.5, 15.5) are clamped to the border cells."""
    cells = torch.clamp(torch.floor((offset - CENTRE_LOW) * 8), 0, GRID - 1).long()
    return cells[..., 1] * GRID + cells[..., 0]


def cell_to_offset(index: torch.Tensor) -> torch.Tensor:
    """(...) class indices -> (..., 2) offsets (x, y) of the cell centres in patch pixels."""
    index = index.long()
    col, row = index % GRID, index // GRID
    return torch.stack([col, row], dim=-1).to(torch.float32).add(0.5).div(8).add(CENTRE_LOW)


def decode_offsets(logits: torch.Tensor, soft_radius: int = 2) -> torch.Tensor:
    """(B, 4096) logits -> (B, 2) offsets as a CPU tensor: `offsets.soft_argmax_offsets` (numpy: for a detector's
    few patches PyTorch's thread pool costs more than the arithmetic, tens of milliseconds on a busy CPU)."""
    return torch.from_numpy(soft_argmax_offsets(logits, soft_radius))
