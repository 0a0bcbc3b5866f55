"""ChArUcoNet's forward pass alone, per image, by input size and batch size, on a device (PyTorch) and on the
CPU through ONNX Runtime: what a batched video path can gain, and how much of a frame the network is.

    python benchmarks/network.py [--device cuda] [--sizes 320x240,1280x720] [--batches 1,8,64] [--seconds 1]

Prints ms an image (the mean over ``--seconds`` of back-to-back calls after a warm-up; on a GPU each call is
synchronised, as the detector's copy back to the CPU is) and images a second. The network is the shipped
weights' ChArUcoNet (`Detector()`), with its ID head.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from deepcharuco.deep_detector import Detector
from evaluate.speed.machine import cpu_description, gpu_name


def parse_size(text: str) -> tuple[int, int]:
    width, _, height = text.partition("x")
    return int(width), int(height)


def per_call_seconds(call, seconds: float) -> float:
    """Mean seconds of ``call()`` over at least ``seconds`` (and 3 calls), after 2 warm-up calls."""
    for _ in range(2):
        call()
    count, started = 0, time.perf_counter()
    while count < 3 or time.perf_counter() - started < seconds:
        call()
        count += 1
    return (time.perf_counter() - started) / count


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", help="PyTorch device: cpu (default), cuda, ...")
    parser.add_argument("--sizes", default="320x240,640x480,1280x720", help="input sizes WxH (multiples of 8)")
    parser.add_argument("--batches", default="1,8,64", help="batch sizes (PyTorch only; ONNX Runtime runs 1)")
    parser.add_argument("--seconds", type=float, default=1.0, help="timing per cell (default: 1)")
    args = parser.parse_args()

    import torch

    detector = Detector(backend="torch", device=args.device)
    model = detector.charuconet.to(args.device).eval()
    if args.device == "cpu":
        model = model.to(memory_format=torch.channels_last)
    onnx = Detector(backend="onnx") if args.device == "cpu" else None
    name = gpu_name(args.device) if args.device != "cpu" else cpu_description()
    print(f"# ChArUcoNet {detector.weights.name}, PyTorch {torch.__version__} on {args.device} ({name})")
    print(f"{'size':>10s} {'batch':>6s} {'ms/image':>9s} {'images/s':>9s}")
    for size in [parse_size(s) for s in args.sizes.split(",")]:
        width, height = size
        for batch in [int(b) for b in args.batches.split(",")]:
            images = torch.rand(batch, 1, height, width, device=args.device)
            if args.device == "cpu":
                images = images.contiguous(memory_format=torch.channels_last)

            @torch.inference_mode()
            def call():
                points, ids = model(images)
                points[:, :1, :1, :1].cpu()  # the copy back synchronises, as the detector's does

            seconds = per_call_seconds(call, args.seconds) / batch
            print(f"{width}x{height:<5d} {batch:6d} {1000 * seconds:9.3f} {1 / seconds:9.1f}", flush=True)
        if onnx is not None:
            image = np.random.default_rng(0).random((1, 1, height, width), dtype=np.float32)
            seconds = per_call_seconds(lambda: onnx.runner.charuconet(image), args.seconds)
            print(f"{width}x{height:<5d} {'ORT 1':>6s} {1000 * seconds:9.3f} {1 / seconds:9.1f}", flush=True)


if __name__ == "__main__":
    main()
