"""A network as serialized ONNX, as the runtime runs it and `deepcharuco.cli.export` writes it (PyTorch's exporter)."""

from __future__ import annotations

import io
import warnings
from dataclasses import dataclass

import torch

from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.networks.offsets import PATCH

OPSET = 17


class ExportError(DeepCharucoError):
    """An export that could not be written or does not reproduce PyTorch's outputs."""


@dataclass(frozen=True)
class NetworkSpec:
    """How to call one network: names and shapes of its inputs and outputs."""

    name: str
    input_name: str
    output_names: tuple[str, ...]
    dynamic_axes: dict
    check_shapes: tuple[tuple[int, ...], ...]  # inputs the check runs on


def network_specs(example_size: tuple[int, int]) -> dict[str, NetworkSpec]:
    """The two networks' interfaces; ``example_size`` (W, H) is the ChArUcoNet training size."""
    width, height = example_size
    return {
        "charuconet": NetworkSpec("charuconet", "image", ("point_logits", "id_logits"),
                                  {"image": {0: "batch", 2: "height", 3: "width"},
                                   "point_logits": {0: "batch", 2: "rows", 3: "cols"},
                                   "id_logits": {0: "batch", 2: "rows", 3: "cols"}},
                                  ((1, 1, height, width), (2, 1, 8 * (height // 16) + 8, width + 16))),
        "refinenet": NetworkSpec("refinenet", "patches", ("logits",),
                                 {"patches": {0: "batch"}, "logits": {0: "batch"}},
                                 ((1, 1, PATCH, PATCH), (16, 1, PATCH, PATCH))),
    }


def onnx_bytes(model: torch.nn.Module, example: torch.Tensor, spec: NetworkSpec) -> bytes:
    """``model`` as a serialized ONNX model (opset `OPSET`, the dynamic axes of ``spec``)."""
    try:
        import onnx  # noqa: F401  (torch's exporter needs it)
    except ImportError:
        raise ExportError("ONNX export needs the onnx package: pip install 'deepcharuco[export]' "
                          "(or pass --format torchscript)") from None
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the TorchScript-based exporter's deprecation notice
        # dynamo=False: the TorchScript-based exporter handles these plain conv nets with no extra
        # packages (the torch.export-based one needs onnxscript, which wants numpy 2).
        buffer = io.BytesIO()
        torch.onnx.export(model, (example,), buffer, dynamo=False, opset_version=OPSET,
                          input_names=[spec.input_name], output_names=list(spec.output_names),
                          dynamic_axes=spec.dynamic_axes)
    return buffer.getvalue()
