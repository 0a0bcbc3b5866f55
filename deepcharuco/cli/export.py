"""Export both networks to TorchScript and ONNX, each checked numerically against PyTorch.

    deepcharuco export --weights runs/charuconet/best.pt --refine-weights runs/refinenet/best.pt --out exported/

writes, for each network present (ChArUcoNet always, RefineNet when weights for it are given
or the checkpoint is a bundle):

    charuconet.ts      TorchScript (torch.jit.load)        image (B, 1, H, W) float32 in [0, 1],
    charuconet.onnx    ONNX, opset 17, B/H/W dynamic        H, W multiples of 8 -> point (B, 65, H/8, W/8),
                                                            ids (B, N+1, H/8, W/8) logits
    refinenet.ts       TorchScript                          patches (B, 1, 24, 24) -> logits (B, 4096)
    refinenet.onnx     ONNX, B dynamic
    export.json        board, architectures, input/output names, and the measured differences

The outputs are the raw logits: decoding (`deepcharuco.networks.cells.decode_cells`,
`deepcharuco.networks.offsets.soft_argmax_offsets`) stays outside, as in the Python `Detector`.
Every file is run on random inputs at two sizes and compared with PyTorch; the export fails
if any logit differs by more than ``tolerance``.
ONNX files are run with onnxruntime when installed, otherwise with OpenCV's DNN module.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import warnings
from pathlib import Path

import numpy as np
import torch

from deepcharuco.cli.common import output_folder, run_command
from deepcharuco.core.files import write_atomic, write_together
from deepcharuco.networks.checkpoint import CheckpointError, load_charuconet, load_refinenet
from deepcharuco.networks.onnx_export import OPSET, ExportError, NetworkSpec, network_specs, onnx_bytes  # noqa: F401 (API)
from deepcharuco.networks.shipped import DEFAULT_WEIGHTS

FORMATS = ("torchscript", "onnx")
TOLERANCE = 1e-3  # on logits of magnitude ~10: float32 reassociation differences are ~1e-5


def export_torchscript(model: torch.nn.Module, example: torch.Tensor, path: Path) -> Path:
    """Trace ``model`` (no data-dependent control flow in either network) and save it."""
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # torch.jit's deprecation notice: the format itself is what users load
        traced = torch.jit.trace(model, example, check_trace=False)
        traced = torch.jit.freeze(traced.eval())
        torch.jit.save(traced, str(path))
    return path


def export_onnx(model: torch.nn.Module, example: torch.Tensor, spec: NetworkSpec, path: Path) -> Path:
    """Write ``model`` as ONNX with dynamic batch (and image size for ChArUcoNet)."""
    write_atomic(path, onnx_bytes(model, example, spec))
    return path


def run_torchscript(path: Path, inputs: np.ndarray) -> list[np.ndarray]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # torch.jit's deprecation notice
        module = torch.jit.load(str(path), map_location="cpu")
    with torch.no_grad():
        outputs = module(torch.from_numpy(inputs))
    outputs = outputs if isinstance(outputs, tuple) else (outputs,)
    return [o.numpy() for o in outputs]


def run_onnx(path: Path, inputs: np.ndarray, spec: NetworkSpec) -> tuple[list[np.ndarray], str]:
    """Outputs of the ONNX file and the runtime that produced them."""
    try:
        import onnxruntime
    except ImportError:
        onnxruntime = None
    if onnxruntime is not None:
        session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        return list(session.run(list(spec.output_names), {spec.input_name: inputs})), "onnxruntime"
    import cv2

    net = cv2.dnn.readNetFromONNX(str(path))
    net.setInput(inputs, spec.input_name)
    return list(net.forward(list(spec.output_names))), "opencv-dnn"


def compare(reference: list[np.ndarray], candidate: list[np.ndarray], what: str, tolerance: float) -> float:
    """Largest |difference| over all outputs; raises ExportError above ``tolerance``.

    (Within the tolerance, a decoder's argmax can only change where PyTorch's own top two are
    closer than 2 x tolerance: a tie either way.)"""
    if len(reference) != len(candidate):
        raise ExportError(f"{what}: {len(candidate)} outputs, PyTorch gives {len(reference)}")
    worst = 0.0
    for ref, got in zip(reference, candidate):
        if ref.shape != got.shape:
            raise ExportError(f"{what}: output shape {got.shape}, PyTorch gives {ref.shape}")
        worst = max(worst, float(np.abs(ref - got).max()))
    if worst > tolerance:
        raise ExportError(f"{what}: outputs differ from PyTorch's by up to {worst:.2e} (> {tolerance:.0e})")
    return worst


def export_network(model: torch.nn.Module, spec: NetworkSpec, out: Path, formats: tuple[str, ...],
                   seed: int = 0, tolerance: float = TOLERANCE) -> dict:
    """Write ``model`` in ``formats`` under ``out`` and check each; returns {format: {file, max_abs_diff, ...}}."""
    model = model.eval().cpu()
    rng = np.random.default_rng(seed)
    inputs = [rng.random(shape, dtype=np.float32) for shape in spec.check_shapes]
    with torch.no_grad():
        references = []
        for x in inputs:
            outputs = model(torch.from_numpy(x))
            references.append([o.numpy() for o in (outputs if isinstance(outputs, tuple) else (outputs,))])
    example = torch.from_numpy(inputs[0])
    results = {}
    for fmt in formats:
        if fmt == "torchscript":
            path = export_torchscript(model, example, out / f"{spec.name}.ts")
            runtime = "torch.jit"
            diffs = [compare(ref, run_torchscript(path, x), f"{path.name} on {x.shape}", tolerance)
                     for x, ref in zip(inputs, references)]
        elif fmt == "onnx":
            path = export_onnx(model, example, spec, out / f"{spec.name}.onnx")
            diffs = []
            for x, ref in zip(inputs, references):
                outputs, runtime = run_onnx(path, x, spec)
                diffs.append(compare(ref, outputs, f"{path.name} ({runtime}) on {x.shape}", tolerance))
        else:
            raise ExportError(f"unknown format {fmt!r}: choose from {FORMATS}")
        results[fmt] = {"file": path.name, "runtime_checked": runtime, "max_abs_diff": max(diffs),
                        "checked_shapes": [list(x.shape) for x in inputs]}
    return results


def export(weights: str | Path, out: str | Path, refine_weights: str | Path | None = None,
           formats: tuple[str, ...] = FORMATS, tolerance: float = TOLERANCE) -> dict:
    """Export ChArUcoNet from ``weights`` and RefineNet from ``refine_weights`` (or from ``weights`` if it is a
    bundle) into ``out``; returns (and writes as export.json) the manifest with the measured differences."""
    unknown = [f for f in formats if f not in FORMATS]
    if unknown or not formats:
        raise ExportError(f"formats must be among {FORMATS}, got {list(formats)}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    charuconet, board, checkpoint = load_charuconet(weights)
    input_size = tuple(checkpoint.get("input_size") or (320, 240))
    specs = network_specs(input_size)
    manifest = {"board": board.to_dict(), "input_size": list(input_size), "opset": OPSET, "networks": {}}
    manifest["networks"]["charuconet"] = {
        "config": charuconet.config.to_dict(), "input": specs["charuconet"].input_name,
        "outputs": list(specs["charuconet"].output_names),
        "exports": export_network(charuconet, specs["charuconet"], out, formats, tolerance=tolerance)}
    refinenet = None
    if refine_weights is not None:
        refinenet, _ = load_refinenet(refine_weights)
    else:
        try:
            refinenet, _ = load_refinenet(weights)
        except CheckpointError:
            pass  # a ChArUcoNet-only checkpoint: nothing more to export
    if refinenet is not None:
        manifest["networks"]["refinenet"] = {
            "config": refinenet.config.to_dict(), "input": specs["refinenet"].input_name,
            "outputs": list(specs["refinenet"].output_names),
            "exports": export_network(refinenet, specs["refinenet"], out, formats, tolerance=tolerance)}
    write_atomic(out / "export.json", json.dumps(manifest, indent=2) + "\n")
    return manifest


def write_onnx_bundle(weights: str | Path, refine_weights: str | Path | None = None, out: str | Path | None = None
                      ) -> Path:
    """Write the ONNX bundle of ``weights`` (`deepcharuco.networks.onnx_bundle`: the networks exported as the runtime
    exports them in memory, and the board, threshold and fingerprint) to ``out``, by default beside the weights
    (``NAME.pt`` -> ``NAME.onnx/``); its files are written whole, ``bundle.json`` last."""
    from deepcharuco.networks.onnx_bundle import FORMAT, META_FILE, MODELS, PointsOnlyBoard, bundle_path, file_sha256
    from deepcharuco.networks.runtime import float_onnx, int8_model, weights_fingerprint

    charuconet, board, checkpoint = load_charuconet(weights)
    points_only = isinstance(board, PointsOnlyBoard)
    models = {"charuconet_points.onnx": float_onnx(charuconet, points_only=True)}
    if not points_only:
        models["charuconet.onnx"] = float_onnx(charuconet)
    fingerprint = weights_fingerprint(charuconet)
    int8 = int8_model(checkpoint, fingerprint)
    if int8 is not None:
        models["charuconet_int8.onnx"] = int8
    try:
        models["refinenet.onnx"] = float_onnx(load_refinenet(refine_weights or weights)[0])
    except CheckpointError:
        if refine_weights is not None:
            raise
    meta = {"format": FORMAT, "board": (board.plain() if points_only else board).to_dict(),
            "heads": "points" if points_only else "all", "threshold": checkpoint.get("threshold"),
            **({"geometry": checkpoint["geometry"]} if checkpoint.get("geometry") else {}),
            **({"input_white": checkpoint["input_white"]} if checkpoint.get("input_white") else {}),
            "weights": Path(weights).name, "weights_sha256": fingerprint,
            "models_sha256": {name: hashlib.sha256(data).hexdigest() for name, data in models.items()},
            "weights_file_sha256": file_sha256(weights)}
    out = Path(out) if out is not None else bundle_path(weights)
    out.mkdir(parents=True, exist_ok=True)
    for stale in (name for name in MODELS if name not in models):
        (out / stale).unlink(missing_ok=True)
    write_together({out / name: data for name, data in models.items()})
    write_atomic(out / META_FILE, json.dumps(meta, indent=1) + "\n")
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="deepcharuco export", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--weights", default=None,
                        help="ChArUcoNet checkpoint or bundle (default: the shipped deepcharuco/weights/detector.pt)")
    parser.add_argument("--refine-weights", default=None, help="RefineNet checkpoint, when --weights is not a bundle")
    parser.add_argument("--out", default="exported", help="output folder")
    parser.add_argument("--format", nargs="+", choices=FORMATS, default=list(FORMATS), help="formats to write")
    parser.add_argument("--tolerance", type=float, default=TOLERANCE, help="largest allowed |logit difference|")
    parser.add_argument("--bundle", action="store_true",
                        help="write the ONNX bundle the runtime loads without PyTorch (NAME.pt -> NAME.onnx/ beside "
                             "it, or --out when given) instead of the checked exports")
    args = parser.parse_args(argv)

    weights = args.weights or DEFAULT_WEIGHTS

    def body() -> None:
        if args.bundle:
            out = None if args.out == parser.get_default("out") else args.out
            print(f"{write_onnx_bundle(weights, args.refine_weights, out)}: ONNX bundle of {weights}")
            return
        manifest = export(weights, output_folder(args.out), args.refine_weights, tuple(args.format), args.tolerance)
        for name, network in manifest["networks"].items():
            for fmt, result in network["exports"].items():
                print(f"{Path(args.out) / result['file']}: max |diff| vs PyTorch {result['max_abs_diff']:.1e} "
                      f"({result['runtime_checked']}, shapes {result['checked_shapes']})")
        print(f"{Path(args.out) / 'export.json'}: board and interfaces")

    return run_command(body)


if __name__ == "__main__":
    sys.exit(main())
