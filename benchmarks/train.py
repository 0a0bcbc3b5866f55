"""Training throughput on this machine: images/s for ChArUcoNet and RefineNet, paper and lite widths, in one run.

    python benchmarks/train.py [--seconds 20] [--batch 16] [--patch-batch 256] [--data data/renders]

Each configuration runs full optimizer steps (forward, the trainers' cross-entropy losses,
backward, AdamW) on random inputs of the training shapes (320x240 frames, 24x24 patches),
after two warm-up steps, for about ``--seconds``. With ``--data``, the data pipeline (shard
reading + the paper's augmentation + cell targets, one process) is timed too, since on a
small CPU it can be the bottleneck rather than the network. Prints images/s, the lite/paper
ratio, and what 20,000 steps at the default batch size would take.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

# This script shares its name with the `train` package: keep its own folder from shadowing it.
sys.path = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

import torch  # noqa: E402
import torch.nn.functional as F  # noqa: E402

from deepcharuco.networks.charuconet import CELL, ChArUcoNet, ChArUcoNetConfig  # noqa: E402
from deepcharuco.networks.refinenet import GRID, PATCH, RefineNet, RefineNetConfig  # noqa: E402
from train.loop import TrainConfig  # noqa: E402


def charuconet_step_inputs(batch: int, width: int, height: int, num_corners: int, generator: torch.Generator):
    image = torch.rand(batch, 1, height, width, generator=generator)
    points = torch.randint(0, CELL * CELL + 1, (batch, height // CELL, width // CELL), generator=generator)
    ids = torch.randint(0, num_corners + 1, (batch, height // CELL, width // CELL), generator=generator)
    return image, points, ids


def images_per_second(model: torch.nn.Module, make_batch, loss_fn, batch: int, seconds: float) -> float:
    """Full training steps for about ``seconds`` after two warm-up steps."""
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=1e-4)
    model.train()
    inputs = make_batch()

    def step():
        optimizer.zero_grad(set_to_none=True)
        loss_fn(model, *inputs).backward()
        optimizer.step()

    for _ in range(2):
        step()
    steps, started = 0, time.perf_counter()
    while time.perf_counter() - started < seconds or steps < 3:
        step()
        steps += 1
    return steps * batch / (time.perf_counter() - started)


def charuconet_loss(model, image, points, ids):
    point_logits, id_logits = model(image)
    return F.cross_entropy(point_logits, points) + F.cross_entropy(id_logits, ids)


def refinenet_loss(model, patches, cells):
    return F.cross_entropy(model(patches), cells)


def pipeline_images_per_second(data: str, seconds: float) -> float:
    from train.augment import AugmentConfig
    from train.dataset import FrameDataset, split_shards

    from datagen.shards import ShardReader

    paths, _ = split_shards(data, 0.0)
    dataset = FrameDataset(paths, ShardReader(paths[0]).board, AugmentConfig(), seed=0)
    count, started = 0, time.perf_counter()
    while time.perf_counter() - started < seconds and count < len(dataset):
        dataset[count]
        count += 1
    return count / (time.perf_counter() - started)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=20.0, help="timed seconds per configuration (default: 20)")
    parser.add_argument("--batch", type=int, default=16, help="ChArUcoNet frames per step (default: 16)")
    parser.add_argument("--patch-batch", type=int, default=256, help="RefineNet patches per step (default: 256)")
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--threads", type=int, default=0, help="torch threads (default 0: torch's choice)")
    parser.add_argument("--data", default=None, help="shard folder: also time the data pipeline (default: skip)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    default_batch, default_steps = TrainConfig.batch_size, TrainConfig.steps
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads; ChArUcoNet {args.width}x{args.height} "
          f"batch {args.batch}, RefineNet {PATCH}x{PATCH} batch {args.patch_batch}")
    generator = torch.Generator().manual_seed(0)
    results = {}
    for width in ("paper", "lite"):
        torch.manual_seed(0)
        config = getattr(ChArUcoNetConfig, width)(16)
        results["charuconet", width] = images_per_second(
            ChArUcoNet(config), lambda: charuconet_step_inputs(args.batch, args.width, args.height, 16, generator),
            charuconet_loss, args.batch, args.seconds)
        results["refinenet", width] = images_per_second(
            RefineNet(getattr(RefineNetConfig, width)()),
            lambda: (torch.rand(args.patch_batch, 1, PATCH, PATCH, generator=generator),
                     torch.randint(0, GRID * GRID, (args.patch_batch,), generator=generator)),
            refinenet_loss, args.patch_batch, args.seconds)
    for (network, width), rate in results.items():
        batch = default_batch
        hours = default_steps * batch / rate / 3600
        print(f"{network:10s} {width:5s}: {rate:8.1f} images/s   ({default_steps} steps x batch {batch}: {hours:.2f} h)")
    for network in ("charuconet", "refinenet"):
        print(f"{network}: lite / paper = {results[network, 'lite'] / results[network, 'paper']:.2f}x images/s")
    if args.data:
        rate = pipeline_images_per_second(args.data, args.seconds)
        print(f"data pipeline (1 process, augmentation on): {rate:.1f} images/s; "
              f"ChArUcoNet paper / pipeline = {results['charuconet', 'paper'] / rate:.2f}")


if __name__ == "__main__":
    main()
