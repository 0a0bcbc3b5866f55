"""How the two networks run: PyTorch, or ONNX Runtime in float32 or int8 (CPU inference).

    backend     ChArUcoNet                               RefineNet
    "torch"     PyTorch, channels-last on CPU            PyTorch
    "onnx"      ONNX Runtime, float32                    ONNX Runtime, float32
    "onnx-int8" ONNX Runtime, int8 (the bundle's own,    ONNX Runtime, float32 (sub-pixel offsets
                quantised and accepted by                stay float: the patches are few and the
                `train.quantize`)                        refinement is what int8 would cost)
    "auto"      "onnx-int8" when the weights carry an accepted int8 model, else "onnx" when ONNX
                Runtime is installed, else "torch"; always "torch" on a GPU device

The float32 ONNX models are exported from the loaded networks in memory when the `Runner` is made
(about a second), so they always match the weights; the int8 model is stored inside the bundle
(``charuconet["int8"]``) with what it was calibrated and checked on. Both runners take and return
the same arrays, so the decoding never knows which one ran.

The ONNX Runtime side (`OnnxRunner`, its threads) is `deepcharuco.networks.onnx_runner`, which
needs no PyTorch: the `Detector` runs the shipped ONNX bundles with it where PyTorch is not installed.

Measured on this project's 2-core CPU (``python benchmarks/detect.py``): PyTorch's default NCHW
convolutions are the slowest path here, channels-last halves them, ONNX Runtime is faster still
and int8 (VNNI) faster again; the README's speed table has the numbers.
"""

from __future__ import annotations

import hashlib
import warnings
from concurrent.futures import Future
from dataclasses import replace
from typing import TYPE_CHECKING, Protocol

import numpy as np
import torch

from deepcharuco.core.checks import check_choice
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.networks.backends import BACKENDS
from deepcharuco.networks.charuconet import ChArUcoNet, PointHeadOnly
from deepcharuco.networks.onnx_export import network_specs, onnx_bytes
from deepcharuco.networks.onnx_runner import (  # noqa: F401 (re-exported: the runners' API in one place)
                                              BackgroundThread, OnnxRunner, network_threads, onnxruntime_available,
                                              )
from deepcharuco.networks.refinenet import PATCH, RefineNet

if TYPE_CHECKING:
    from deepcharuco.networks.onnx_bundle import OnnxBundle

INT8_KEY = "int8"  # in a ChArUcoNet checkpoint: {"onnx": bytes, "calibration": ..., "validation": ...}


class Runner(Protocol):
    """Runs the networks on CPU arrays; returns numpy arrays (`TorchRunner`, `onnx_runner.OnnxRunner`)."""

    name: str

    def charuconet(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """(1, 1, H, W) float32 in [0, 1], H and W multiples of 8 -> point logits (65, H/8, W/8), ID logits
        (N+1, H/8, W/8); None for the ID logits where the runner was made ``points_only``."""

    def refinenet(self, patches: np.ndarray) -> np.ndarray:
        """(B, 1, 24, 24) float32 in [0, 1] -> (B, 4096) logits."""

    def refinenet_in_background(self, patches: np.ndarray) -> Future | None:
        """`refinenet` started on a background thread on one core, for the caller to do other work on the
        other: the future of its logits; None where the runner cannot (PyTorch, one thread in all)."""


def weights_fingerprint(model: torch.nn.Module) -> str:
    """sha256 of a network's weights as loaded (batch norm folded): ties an int8 model to the float one it
    was quantised from, and keys the in-memory ONNX exports."""
    digest = hashlib.sha256()
    for name, tensor in model.state_dict().items():
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()



def check_fingerprint(bundle: "OnnxBundle") -> None:
    """`BundleError` where the weights named in ``bundle.json`` lie beside ``bundle`` and their network, as loaded, is
    not the one the bundle was exported from (``weights_sha256``, `weights_fingerprint`: retrained or replaced
    since). Without those weights there is nothing to compare; the bundle's own files are checked by their sha256
    when it is read (`onnx_bundle.read_bundle`)."""
    from deepcharuco.networks.checkpoint import load_charuconet
    from deepcharuco.networks.onnx_bundle import BundleError, bundle_fix

    recorded, name = bundle.meta.get("weights_sha256"), bundle.meta.get("weights")
    source = bundle.path.parent / str(name)
    if not recorded or not name or not source.is_file():
        return
    if weights_fingerprint(load_charuconet(source)[0]) != recorded:
        raise BundleError(f"{bundle.path} was exported from another network than {source} holds now (weights_sha256 "
                          f"differs: retrained or replaced since): {bundle_fix(bundle.path)}")

def int8_model(checkpoint: dict, fingerprint: str | None = None) -> bytes | None:
    """The accepted int8 ChArUcoNet (serialized ONNX) a checkpoint carries, or None; with ``fingerprint``
    (`weights_fingerprint` of the loaded float network) one quantised from other weights is ignored."""
    entry = checkpoint.get(INT8_KEY)
    if not isinstance(entry, dict) or not entry.get("onnx"):
        return None
    if fingerprint is not None and entry.get("weights_sha256") != fingerprint:
        warnings.warn("the int8 model in these weights was quantised from other float weights: ignored "
                      "(make a new one with python -m train.quantize)", stacklevel=3)
        return None
    return entry["onnx"]


def resolve_backend(backend: str, device: torch.device, checkpoint: dict) -> str:
    """The backend ``backend`` means for these weights on ``device`` (see the module's table)."""
    check_choice("backend", backend, BACKENDS)
    if backend == "auto":
        if device.type != "cpu" or not onnxruntime_available():
            return "torch"
        return "onnx-int8" if INT8_KEY in checkpoint else "onnx"
    if backend != "torch":
        if device.type != "cpu":
            raise DeepCharucoError(f"backend={backend!r} runs on the CPU: use backend='torch' for device {device}")
        if not onnxruntime_available():
            raise DeepCharucoError(f"backend={backend!r} needs ONNX Runtime: pip install onnxruntime "
                                   f"(or use backend='torch')")
        if backend == "onnx-int8" and INT8_KEY not in checkpoint:
            raise DeepCharucoError("these weights carry no int8 model: make one with python -m train.quantize "
                                   "(or use backend='onnx')")
    return backend


class TorchRunner:
    """PyTorch on ``device``; on CPU the networks run channels-last (NHWC), which oneDNN convolves about
    twice as fast as NCHW here."""

    name = "torch"

    def __init__(self, charuconet: ChArUcoNet, refinenet: RefineNet | None, device: torch.device,
                 points_only: bool = False):
        self.device = device
        self.points_only = points_only
        self.memory_format = torch.channels_last if device.type == "cpu" else torch.contiguous_format
        self._charuconet = charuconet.to(device, memory_format=self.memory_format)
        self._refinenet = None if refinenet is None else refinenet.to(device, memory_format=self.memory_format)

    def _tensor(self, array: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(array).to(self.device).contiguous(memory_format=self.memory_format)

    @torch.inference_mode()
    def charuconet(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        if self.points_only:
            return self._charuconet.points(self._tensor(image))[0].float().cpu().contiguous().numpy(), None
        points, ids = self._charuconet(self._tensor(image))
        return points[0].float().cpu().contiguous().numpy(), ids[0].float().cpu().contiguous().numpy()

    @torch.inference_mode()
    def refinenet(self, patches: np.ndarray) -> np.ndarray:
        return self._refinenet(self._tensor(patches)).float().cpu().numpy()

    def refinenet_in_background(self, patches: np.ndarray) -> None:
        return None  # PyTorch's intra-op pool is the process's: a second caller would only queue on it


_EXPORTS: dict[str, bytes] = {}  # weights fingerprint -> float32 ONNX: one export per process and weights


def float_onnx(model: ChArUcoNet | RefineNet, points_only: bool = False) -> bytes:
    """A loaded ChArUcoNet or RefineNet as float32 ONNX (exported once per process and weights); with
    ``points_only`` a ChArUcoNet without its ID head (one output, "point_logits")."""

    kind = "charuconet" if isinstance(model, ChArUcoNet) else "refinenet"
    points_only = points_only and kind == "charuconet"
    key = weights_fingerprint(model) + ("-points" if points_only else "")
    if key not in _EXPORTS:
        example = torch.zeros(1, 1, 240, 320) if kind == "charuconet" else torch.zeros(1, 1, PATCH, PATCH)
        spec = network_specs((320, 240))[kind]
        if points_only:
            spec = replace(spec, output_names=spec.output_names[:1],
                           dynamic_axes={k: v for k, v in spec.dynamic_axes.items() if k != "id_logits"})
        _EXPORTS[key] = onnx_bytes(PointHeadOnly(model.cpu()) if points_only else model.cpu(), example, spec)
    return _EXPORTS[key]


def make_runner(backend: str, charuconet: ChArUcoNet, refinenet: RefineNet | None, device: torch.device,
                checkpoint: dict, points_only: bool = False) -> Runner:
    """The `Runner` for ``backend`` (resolved by `resolve_backend`) over the loaded networks; ``points_only``:
    ChArUcoNet runs without its ID head (float backends; the int8 model is run whole) and returns None for it."""
    backend = resolve_backend(backend, device, checkpoint)
    if backend == "torch":
        return TorchRunner(charuconet, refinenet, device, points_only)
    refinenet_model = None if refinenet is None else float_onnx(refinenet)
    if backend == "onnx-int8":
        model = int8_model(checkpoint, weights_fingerprint(charuconet))
        if model is not None:
            return OnnxRunner(model, refinenet_model, name="onnx-int8")
    return OnnxRunner(float_onnx(charuconet, points_only), refinenet_model)
