"""ChArUcoNet's forward pass alone, per image, by input size and batch size, on a device (PyTorch) and on the
CPU through ONNX Runtime: what a batched video path can gain, and how much of a frame the network is.

    python benchmarks/network.py [--device cuda] [--sizes 320x240,1280x720] [--batches 1,8,64] [--seconds 1]

Prints ms an image (the mean over ``--seconds`` of back-to-back calls after a warm-up; on a GPU each call is
synchronised, as the detector's copy back to the CPU is) and images a second. The network is the shipped
weights' ChArUcoNet (`Detector()`), with its ID head.

    python benchmarks/network.py --architectures lite,fast[,fast:W4-W8-W16-W32-HEAD ...] [--sizes 320x240,1280x720]

compares architectures instead (issue 51): each with random weights (the time does not depend on them) and batch
norm folded, exported to ONNX as the runtime exports it, and run by ONNX Runtime on 2 threads and on 1, the point
network alone ("points": what boards read by their markers run) and with the ID head ("all"); multiply-adds (MACs)
counted from every convolution's shapes. ``fast:24-48-64-64-48`` names a fast variant by its widths and head.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from deepcharuco.detection.deep_detector import Detector
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


def architecture(name: str, num_corners: int = 16):
    """The ChArUcoNetConfig ``name`` stands for: "paper", "lite", "fast" or "fast:W4-W8-W16-W32-HEAD"."""
    from deepcharuco.networks.charuconet import ChArUcoNetConfig, named_config

    if name.startswith("fast:"):
        *widths, head = (int(v) for v in name[5:].split("-"))
        return ChArUcoNetConfig(num_corners=num_corners, widths=tuple(widths), head=head, arch="fast")
    return named_config(name, num_corners)


def count_macs(model, image) -> int:
    """Multiply-adds of one forward pass of ``model`` on ``image``, summed over its convolutions (from their
    output shapes, input channels and kernel sizes; the rest of the work is element-wise and not counted)."""
    import torch

    total = 0

    def hook(module, inputs, output):
        nonlocal total
        kernel = module.kernel_size[0] * module.kernel_size[1]
        total += output.numel() * kernel * module.in_channels // module.groups

    handles = [m.register_forward_hook(hook) for m in model.modules() if isinstance(m, torch.nn.Conv2d)]
    with torch.no_grad():
        model(image)
    for handle in handles:
        handle.remove()
    return total


def compare_architectures(names: list[str], sizes: list[tuple[int, int]], seconds: float) -> None:
    """MACs and ONNX Runtime ms of each architecture; the networks are timed interleaved, one call each in turn,
    and each reported by its median call, so that a busy machine slows them alike (the ratio column, to the
    first architecture, is the number to read)."""
    import torch
    from dataclasses import replace

    from deepcharuco.networks.charuconet import ChArUcoNet, PointHeadOnly, fold_batch_norm
    from deepcharuco.networks.onnx_export import network_specs, onnx_bytes
    from deepcharuco.networks.onnx_runner import _session

    print(f"# ChArUcoNet architectures, random weights, ONNX Runtime on {cpu_description()}; median ms a call, "
          f"interleaved; x: the first one's time / this one's")
    spec = network_specs((320, 240))["charuconet"]
    points_spec = replace(spec, output_names=spec.output_names[:1],
                          dynamic_axes={k: v for k, v in spec.dynamic_axes.items() if k != "id_logits"})
    networks = {}  # (name, heads) -> (torch module, {threads: session}, parameters)
    for name in names:
        torch.manual_seed(0)
        model = fold_batch_norm(ChArUcoNet(architecture(name)).eval())
        parameters = sum(p.numel() for p in model.parameters())
        for heads, net, net_spec in (("points", PointHeadOnly(model), points_spec), ("all", model, spec)):
            onnx = onnx_bytes(net, torch.zeros(1, 1, 240, 320), net_spec)
            networks[name, heads] = (net, {threads: _session(onnx, threads) for threads in (2, 1)}, parameters)
    print(f"{'network':>26s} {'heads':>6s} {'size':>10s} {'GMACs':>7s} {'params':>8s} {'ms 2 thr':>9s} {'x':>5s} "
          f"{'ms 1 thr':>9s} {'x':>5s}")
    for heads in ("points", "all"):
        for width, height in sizes:
            image = np.random.default_rng(0).random((1, 1, height, width), dtype=np.float32)
            keys = [key for key in networks if key[1] == heads]
            times = {(key, threads): [] for key in keys for threads in (2, 1)}
            for threads in (2, 1):
                for key in keys:  # warm-up
                    networks[key][1][threads].run(None, {"image": image})
                started = time.perf_counter()
                while time.perf_counter() - started < seconds * len(keys) or len(times[keys[0], threads]) < 5:
                    for key in keys:
                        begin = time.perf_counter()
                        networks[key][1][threads].run(None, {"image": image})
                        times[key, threads].append(time.perf_counter() - begin)
            median = {k: 1000 * float(np.median(v)) for k, v in times.items()}
            for key in keys:
                import torch

                macs = count_macs(networks[key][0], torch.zeros(1, 1, height, width))
                ratios = [median[keys[0], t] / median[key, t] for t in (2, 1)]
                print(f"{key[0]:>26s} {heads:>6s} {width}x{height:<5d} {macs / 1e9:7.3f} {networks[key][2] / 1e3:7.0f}k "
                      f"{median[key, 2]:9.2f} {ratios[0]:5.2f} {median[key, 1]:9.2f} {ratios[1]:5.2f}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", help="PyTorch device: cpu (default), cuda, ...")
    parser.add_argument("--sizes", default="320x240,640x480,1280x720", help="input sizes WxH (multiples of 8)")
    parser.add_argument("--batches", default="1,8,64", help="batch sizes (PyTorch only; ONNX Runtime runs 1)")
    parser.add_argument("--seconds", type=float, default=1.0, help="timing per cell (default: 1)")
    parser.add_argument("--architectures", default="",
                        help="compare these ChArUcoNet architectures instead (comma-separated: paper, lite, fast, "
                             "fast:W4-W8-W16-W32-HEAD), random weights, ONNX Runtime, MACs")
    args = parser.parse_args()
    if args.architectures:
        compare_architectures(args.architectures.split(","), [parse_size(s) for s in args.sizes.split(",")], args.seconds)
        return

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
