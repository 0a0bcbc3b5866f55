"""``python -m train.quantize``: an int8 ChArUcoNet for ONNX Runtime, accepted only if it is as accurate.

    python -m train.quantize --weights deepcharuco/weights/detector.pt --frames data/speed_validation \\
        --out deepcharuco/weights/detector.pt --force

1. exports the bundle's ChArUcoNet to float32 ONNX and quantises it statically (ONNX Runtime: int8
   per-channel weights, uint8 activations, QDQ), calibrating the activation ranges on ``--frames``
   (rendered frames, as they are and through the paper's blur and darkness effects, so dark inputs'
   small activations keep their resolution);
2. runs the paper's synthetic protocols (blur and darkness k = 0..10) on ``--frames`` with the
   float32 and the int8 network, decoded as `Detector()` decodes, and accepts the int8 model only
   if no level's accuracy drops by more than ``--max-drop`` (the speed issue's 0.01);
3. writes the bundle with the int8 model inside (``charuconet["int8"]``: the ONNX bytes, the
   fingerprint of the float weights it was made from, its calibration and its validation), which
   `Detector(backend="auto")` then runs.

``--frames`` must be validation frames (not the report's test set): they choose whether int8 is
shipped. Frame ``i`` of a render depends only on (seed, i), so the set is reproducible.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from datagen.shards import list_shards
from deepcharuco.cli.common import run_command
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.detection.deep_detector import Detector
from deepcharuco.detection.levels import network_input
from deepcharuco.networks.checkpoint import read_checkpoint, save_atomically
from deepcharuco.networks.runtime import INT8_KEY, float_onnx, onnxruntime_available, weights_fingerprint
from evaluate.paper.data import load_frames
from evaluate.paper.protocols import LEVELS, TestFrame, apply_effect, synthetic_curve

MAX_DROP = 0.01
CALIBRATION_EFFECTS = (("blur", 0), ("blur", 5), ("blur", 10), ("darkness", 3), ("darkness", 6), ("darkness", 9))


class QuantizeError(DeepCharucoError):
    """An int8 model that cannot be made or is not accurate enough."""


def calibration_inputs(frames: list[TestFrame]) -> list[np.ndarray]:
    """Every frame through every effect of `CALIBRATION_EFFECTS`: the ranges int8 must cover."""
    return [network_input(apply_effect(frame, effect, k).image) for frame in frames for effect, k in CALIBRATION_EFFECTS]


def quantize_charuconet(float_model: bytes, inputs: list[np.ndarray]) -> bytes:
    """Static int8 quantisation of a float32 ChArUcoNet (serialized ONNX) calibrated on ``inputs``."""
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    class Reader(CalibrationDataReader):
        def __init__(self):
            self._inputs = iter(inputs)

        def get_next(self):
            image = next(self._inputs, None)
            return None if image is None else {"image": image}

    with tempfile.TemporaryDirectory() as folder:
        source, prepared, quantised = (Path(folder) / name for name in ("float.onnx", "prepared.onnx", "int8.onnx"))
        source.write_bytes(float_model)
        quant_pre_process(str(source), str(prepared))
        quantize_static(str(prepared), str(quantised), Reader(), quant_format=QuantFormat.QDQ,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, per_channel=True)
        return quantised.read_bytes()


def protocol_accuracy(detector: Detector, frames: list[TestFrame], progress: tqdm) -> dict[str, list[float]]:
    """{"blur": accuracy per k, "darkness": ...} of the paper's synthetic protocols on ``frames``."""
    return {effect: [float(a) for a in synthetic_curve(detector, frames, effect, LEVELS, progress.update).accuracy]
            for effect in ("blur", "darkness")}


def quantize(weights: str | Path, frames_dir: str | Path, out: str | Path, *, max_frames: int = 60,
             calibration_frames: int = 20, max_drop: float = MAX_DROP, force: bool = False, quiet: bool = False) -> dict:
    """Make, check and store the int8 model (see the module's docstring); returns its validation record."""
    weights, out = Path(weights), Path(out)
    if not onnxruntime_available():
        raise QuantizeError("quantisation needs ONNX Runtime: pip install 'deepcharuco[export]'")
    if out.exists() and not force:
        raise QuantizeError(f"{out} exists: pass --force to replace it (or choose another --out)")
    bundle = torch.load(weights, map_location="cpu", weights_only=True)
    read_checkpoint(weights, "charuconet")  # a clear error for a file that is not our checkpoint
    if bundle.get("kind") != "bundle":
        raise QuantizeError(f"{weights} holds one network: quantise a bundle (python -m train.bundle makes one)")
    if not Path(frames_dir).is_dir() or not list_shards(frames_dir):
        raise QuantizeError(f"no shard-*.h5 files in {frames_dir}: render validation frames with python -m "
                            f"datagen.render --n 160 --seed 2000 --out {frames_dir} (a seed no training or test set uses)")
    float_detector = Detector(weights=weights, backend="onnx")
    frames = load_frames(frames_dir, float_detector.board, limit=max_frames)
    if len(frames) < calibration_frames:
        raise QuantizeError(f"{frames_dir} has {len(frames)} frames with the board, {calibration_frames} are needed to "
                            f"calibrate: render more (python -m datagen.render --seed 2000 --out {frames_dir})")
    fingerprint = weights_fingerprint(float_detector.charuconet)
    calibration = frames[:: max(1, len(frames) // calibration_frames)][:calibration_frames]
    int8 = quantize_charuconet(float_onnx(float_detector.charuconet), calibration_inputs(calibration))
    entry = {"onnx": int8, "weights_sha256": fingerprint,
             "calibration": {"frames": str(frames_dir), "count": len(calibration),
                             "effects": [f"{e} k={k}" for e, k in CALIBRATION_EFFECTS]}}
    bundle["charuconet"][INT8_KEY] = entry
    temporary = out.with_name(out.name + ".tmp")
    try:
        torch.save(bundle, temporary)  # loaded as users will load it; written to --out only if accepted
        int8_detector = Detector(weights=temporary, backend="onnx-int8")
        with tqdm(total=2 * 2 * len(LEVELS) * len(frames), unit="image", disable=quiet, desc="float32 vs int8") as bar:
            reference = protocol_accuracy(float_detector, frames, bar)
            candidate = protocol_accuracy(int8_detector, frames, bar)
        drops = {(effect, level): reference[effect][level] - candidate[effect][level]
                 for effect in reference for level in range(len(LEVELS))}
        (effect, level), worst = max(drops.items(), key=lambda item: item[1])
        entry["validation"] = {"frames": str(frames_dir), "count": len(frames), "float32": reference,
                               "int8": candidate, "largest_drop": worst, "max_drop": max_drop}
        if worst > max_drop:
            raise QuantizeError(
                f"int8 loses up to {worst:.3f} accuracy on {frames_dir} ({effect} k={LEVELS[level]}: "
                f"{reference[effect][level]:.3f} -> {candidate[effect][level]:.3f}; more than {max_drop}): not written; "
                f"keep backend='onnx'")
        save_atomically(bundle, out)  # now with its validation record
    finally:
        temporary.unlink(missing_ok=True)
    return entry["validation"]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m train.quantize", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--weights", default="deepcharuco/weights/detector.pt", help="bundle to quantise")
    parser.add_argument("--frames", required=True, help="folder of rendered validation shards (not the test set)")
    parser.add_argument("--out", required=True, help="bundle to write (the input's networks + the int8 model)")
    parser.add_argument("--max-frames", type=int, default=60, help="validation frames used")
    parser.add_argument("--calibration-frames", type=int, default=20, help="of those, frames that set the int8 ranges")
    parser.add_argument("--max-drop", type=float, default=MAX_DROP, help="largest accuracy drop accepted at any level")
    parser.add_argument("--force", action="store_true", help="replace --out if it exists")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)

    def body() -> None:
        record = quantize(args.weights, args.frames, args.out, max_frames=args.max_frames,
                          calibration_frames=args.calibration_frames, max_drop=args.max_drop, force=args.force,
                          quiet=args.quiet)
        for effect in ("blur", "darkness"):
            print(f"{effect:9s} float32 " + " ".join(f"{a:.3f}" for a in record["float32"][effect]))
            print(f"{'':9s} int8    " + " ".join(f"{a:.3f}" for a in record["int8"][effect]))
        print(f"largest drop {record['largest_drop']:+.3f} (<= {record['max_drop']}): int8 stored in {args.out}")

    return run_command(body)


if __name__ == "__main__":
    sys.exit(main())
