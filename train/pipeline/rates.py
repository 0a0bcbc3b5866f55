"""What the plan's ETA and budget are computed from: rates recorded in the run folder (``rates.json``) by earlier
stages or probes, and the probes that measure them (a few training steps, patches, two rendered frames)."""

from __future__ import annotations

import shlex
import subprocess
import sys
import time
from pathlib import Path

from train.pipeline.plan import ROOT, PipelineError
from train.pipeline.records import read_json, write_json


def load_rates(run: Path) -> dict:
    """Rates recorded by earlier stages or probes in this run folder (``rates.json``): {name: {value, source}}."""
    path = run / "rates.json"
    rates = read_json(path)
    if rates is None and path.is_file():
        print(f"note: {path} is damaged and is ignored (the rates are measured again)", file=sys.stderr)
    return rates or {}


def record_rate(run: Path | None, name: str, value: float, source: str) -> None:
    """Remember a measured rate for later plans (a resumed run's ETA); None: a run that writes nothing (--plan-only)."""
    if run is None:
        return
    rates = load_rates(run)
    rates[name] = {"value": float(value), "source": source}
    write_json(run / "rates.json", rates)


def probe_training_step(network: str, width: str, batch: int, size: tuple[int, int], device_name: str) -> float:
    """Seconds per optimizer step of ``network`` on random inputs (2 warm-up steps, then 3 timed): the trainer's
    cost without data loading, which runs in worker processes beside it."""
    import torch
    import torch.nn.functional as F

    from deepcharuco.cli.common import pick_device
    from deepcharuco.networks.charuconet import ChArUcoNet, ChArUcoNetConfig
    from deepcharuco.networks.refinenet import RefineNet, RefineNetConfig

    device = pick_device(device_name)
    if network == "charuconet":
        model = ChArUcoNet((ChArUcoNetConfig.lite if width == "lite" else ChArUcoNetConfig.paper)(16)).to(device)
        images = torch.rand(batch, 1, size[1], size[0], device=device)
        labels = torch.randint(0, 65, (batch, size[1] // 8, size[0] // 8), device=device)

        def loss() -> torch.Tensor:
            points, ids = model(images)
            return F.cross_entropy(points, labels) + F.cross_entropy(ids, labels % 17)
    else:
        model = RefineNet(RefineNetConfig.lite() if width == "lite" else RefineNetConfig.paper()).to(device)
        images = torch.rand(batch, 1, 24, 24, device=device)
        labels = torch.randint(0, 4096, (batch,), device=device)

        def loss() -> torch.Tensor:
            return F.cross_entropy(model(images), labels)
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-4)
    timings = []
    for step in range(5):
        started = time.perf_counter()
        optimizer.zero_grad()
        loss().backward()
        optimizer.step()
        if device.type == "cuda":
            torch.cuda.synchronize()
        if step >= 2:
            timings.append(time.perf_counter() - started)
    return float(sum(timings) / len(timings))


def probe_patches() -> float:
    """Seconds per synthetic RefineNet patch (500 made)."""
    import numpy as np

    from datagen.patches import synthetic_patches

    started = time.perf_counter()
    synthetic_patches(np.random.default_rng(0), 500)
    return (time.perf_counter() - started) / 500


def probe_render(render_args: list[str], scratch: Path) -> float:
    """Seconds per rendered frame: two frames rendered as the run will render them, one per shard; the time
    between the two shards' completion is one frame's (Blender's start-up left out)."""
    folder = scratch / "probe-render"
    command = [sys.executable, "-m", "datagen.render", *render_args, "--n", "2", "--shard-size", "1", "--out",
               str(folder), "--quiet"]
    started = time.perf_counter()
    result = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    total = time.perf_counter() - started
    if result.returncode != 0:
        raise PipelineError(f"measuring the render rate failed ({shlex.join(command)}): "
                            f"{(result.stderr.strip().splitlines() or ['no message'])[-1]}")
    shards = sorted(folder.glob("shard-*.h5"))
    between = shards[1].stat().st_mtime - shards[0].stat().st_mtime if len(shards) == 2 else 0.0
    return between if between > 0.01 else total / 2
