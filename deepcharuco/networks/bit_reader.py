"""BitReader: a rectified marker patch -> one logit per inner bit (white vs black), any marker size.

Patch geometry (`patch_points`): the square's marker is sampled on its own bit grid, so one
network reads 4x4 ... 7x7 markers alike: the (n + 2) x (n + 2) bit cells of the marker (one
black border cell each side, as OpenCV prints), plus `MARGIN_BITS` bit cells of context each
side (the paper ring, the edges of the neighbouring black squares a blur smears in), each
bit cell sampled at `SAMPLES_PER_BIT` x `SAMPLES_PER_BIT` points. A patch is
(G * S) x (G * S) pixels, G = n + 2 + 2 * MARGIN_BITS, S = SAMPLES_PER_BIT, row-major,
row = the square frame's y (down), column = its x (right).

    patch (B, 1, G*S, G*S), normalised per patch (`normalise_patches`)
      -> conv SxS stride S 1 -> W: one feature per bit cell (a conv at sample resolution before
         it doubled the CPU time: the reader runs on ~350 squares a frame)
      -> 4 residual conv3x3 W -> W, dilations 1, 2, 4, 1: every bit sees +-9 bit cells
         (a 12 px blur at 2 px per bit spans 6)
      -> conv1x1 W -> 1 -> the inner n x n cells: logits (B, n, n), > 0 = white

Training (train/bit_reader.py) first fits each logit as the log-likelihood ratio
log p(white) / p(black) (binary cross-entropy: a marker's log-likelihood is then, up to a constant,
sum_i (2 b_i - 1) * logit_i / 2), then fine-tunes on the score `marker_reader` uses: the cosine of
tanh(logit / 4) with the candidate's bit signs, softmax over the true marker and others.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.core.errors import ShapeError

MARGIN_BITS = 2
SAMPLES_PER_BIT = 3
SIZES = (4, 5, 6, 7)  # inner bits per side the reader is trained for (DICT_4X4 ... DICT_7X7, AprilTag 36h11 = 6)
FORMAT = "deepcharuco-bit-reader"
# Grey levels: a patch's spread is divided by at least this much, so an almost flat patch (a dark frame's
# 1-2 levels of contrast) keeps its real amplitude instead of having its quantisation noise blown up.
MIN_SPREAD = 0.5


@dataclass(frozen=True)
class BitReaderConfig:
    width: int = 16
    dilations: tuple[int, ...] = (1, 2, 4, 1)

    def to_dict(self) -> dict:
        return {**asdict(self), "dilations": list(self.dilations)}

    @classmethod
    def from_dict(cls, data: dict) -> "BitReaderConfig":
        return cls(width=int(data["width"]), dilations=tuple(int(d) for d in data["dilations"]))


def grid_cells(size: int) -> int:
    """Bit cells per patch side (G) for markers of ``size`` inner bits per side."""
    return size + 2 + 2 * MARGIN_BITS


def patch_side(size: int) -> int:
    """Patch pixels per side (G * S) for markers of ``size`` inner bits per side."""
    return grid_cells(size) * SAMPLES_PER_BIT


def patch_points(size: int, ratio: float) -> np.ndarray:
    """(P * P, 2) float64 (x, y) points in a square's unit frame, row-major: the patch's pixel centres.

    The marker (side ``ratio`` of the square, centred) spans (n + 2) bit cells; the patch extends
    `MARGIN_BITS` cells beyond it on each side."""
    cells = size + 2
    bit = ratio / cells
    start = 0.5 - ratio / 2 - MARGIN_BITS * bit
    side = patch_side(size)
    centres = start + (np.arange(side) + 0.5) * (bit / SAMPLES_PER_BIT)
    x, y = np.meshgrid(centres, centres)
    return np.stack([x.ravel(), y.ravel()], axis=1)


def normalise_patches(patches: np.ndarray) -> np.ndarray:
    """(B, P, P) grey levels -> (B, P, P) float32: minus each patch's mean, over max(its std, `MIN_SPREAD`).

    Brightness and contrast vary by 100x between the paper's darkness levels; the bits do not."""
    patches = np.asarray(patches, np.float32)
    mean = patches.mean(axis=(1, 2), keepdims=True)
    spread = np.maximum(patches.std(axis=(1, 2), keepdims=True), MIN_SPREAD)
    return (patches - mean) / spread


class _Residual(nn.Module):
    def __init__(self, width: int, dilation: int):
        super().__init__()
        self.conv = nn.Conv2d(width, width, 3, padding=dilation, dilation=dilation)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + torch.relu(self.conv(x))


class BitReader(nn.Module):
    """(B, 1, G*S, G*S) normalised patches of markers with ``size`` inner bits -> (B, n, n) bit logits."""

    def __init__(self, config: BitReaderConfig = BitReaderConfig()):
        super().__init__()
        self.config = config
        self.stem = nn.Sequential(nn.Conv2d(1, config.width, SAMPLES_PER_BIT, stride=SAMPLES_PER_BIT), nn.ReLU())
        self.body = nn.Sequential(*[_Residual(config.width, d) for d in config.dilations])
        self.head = nn.Conv2d(config.width, 1, 1)

    def forward(self, patches: torch.Tensor, size: int) -> torch.Tensor:
        side = patch_side(size)
        if patches.shape[-2:] != (side, side):
            raise ShapeError(f"BitReader: markers of {size} bits take {side}x{side} patches, got {tuple(patches.shape)}")
        logits = self.head(self.body(self.stem(patches)))[:, 0]  # (B, G, G)
        inner = MARGIN_BITS + 1
        return logits[:, inner:inner + size, inner:inner + size]


def save_bit_reader(model: BitReader, path: str | Path, training: dict | None = None) -> Path:
    """Write ``model`` as a small checkpoint (float16 weights: the reader ships in the package)."""
    path = Path(path)
    state = {k: v.detach().to(torch.float16) for k, v in model.state_dict().items()}
    temporary = path.with_name(path.name + ".tmp")
    torch.save({"format": FORMAT, "config": model.config.to_dict(), "state_dict": state,
                "training": training or {}}, temporary)
    temporary.replace(path)
    return path


def load_bit_reader(path: str | Path) -> BitReader:
    """A `BitReader` in eval mode, float32, from ``path`` (written by `save_bit_reader`)."""
    path = Path(path)
    if not path.is_file():
        raise DeepCharucoError(f"no bit reader weights at {path}: train them with python -m train.bit_reader "
                               f"--out {path}, or read markers with reader='sampled'")
    data = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise DeepCharucoError(f"{path} is not a bit reader checkpoint (format {FORMAT!r})")
    model = BitReader(BitReaderConfig.from_dict(data["config"]))
    model.load_state_dict({k: v.float() for k, v in data["state_dict"].items()})
    return model.eval()
