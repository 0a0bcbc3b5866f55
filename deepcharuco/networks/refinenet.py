"""RefineNet: 24x24 patch -> 4096-way softmax over the central 8x8 pixels at 8x resolution.

    patch (B, 1, 24, 24) in [0, 1]
      -> the VGG encoder of ChArUcoNet (with BatchNorm)     (B, 128, 3, 3)
      -> conv3x3 128 -> 128, then the bottleneck conv1x1 128 -> 8   (B, 8, 3, 3)
      -> flatten (72) -> linear -> 4096 logits = a 64 x 64 grid, row-major (row = y)

1.07 M parameters, 4.1 MB in float32, as the paper reports.

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
    widths: tuple[int, int, int, int] = (64, 64, 128, 128)
    head: int = 128
    bottleneck: int = 8
    batch_norm: bool = True  # see charuconet's docstring

    @classmethod
    def paper(cls) -> "RefineNetConfig":
        return cls()

    @classmethod
    def lite(cls) -> "RefineNetConfig":
        return cls(widths=(16, 32, 48, 64), head=64, bottleneck=8)

    def to_dict(self) -> dict:
        return {**asdict(self), "widths": list(self.widths)}

    @classmethod
    def from_dict(cls, data: dict) -> "RefineNetConfig":
        return cls(widths=tuple(int(w) for w in data["widths"]), head=int(data["head"]), bottleneck=int(data["bottleneck"]),
                   batch_norm=bool(data.get("batch_norm", False)))  # format 1 files before batch_norm had none


class RefineNet(nn.Module):
    """forward(patches (B, 1, 24, 24) in [0, 1]) -> logits (B, 4096) over the 64x64 sub-pixel grid."""

    def __init__(self, config: RefineNetConfig = RefineNetConfig()):
        super().__init__()
        self.config = config
        bn = config.batch_norm
        self.encoder = VGGEncoder(config.widths, batch_norm=bn)
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
