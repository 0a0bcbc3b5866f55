"""One training loop for both networks: step-based, seeded, resumable to the exact sample.

- Sample order: epoch e visits the training set in ``default_rng([seed, e]).permutation``,
  cut into batches; augmentation is seeded per (seed, epoch, index) in the dataset. So the
  batch at global step s is a pure function of (seed, s), and ``--resume`` continues with
  exactly the batches an uninterrupted run would have seen, restoring model, optimizer,
  scheduler and AMP scaler state.
- AdamW, linear warm-up then cosine decay; AMP (bfloat16/float16 autocast) on CUDA.
- Checkpoints: ``last.pt`` every ``checkpoint_every`` steps, at the end and on SIGINT/SIGTERM
  (the command then exits with 130/143, as a shell does for a process the signal ended, so
  ``train && bundle`` stops there); ``best.pt`` on the best validation score; both are
  `deepcharuco.networks` checkpoints with the training state under ``training``.
- Logs: ``log.csv`` (step, loss, lr, validation metrics ...), TensorBoard if installed, tqdm.
  ``--resume`` first cuts ``log.csv`` back to the checkpoint's step: the steps after it (logged
  before a kill) are run again and would otherwise appear twice.
- A run folder is found by ``--out`` and may be moved: ``--resume`` takes its settings from
  ``last.pt`` and compares the data folder by its resolved path or, failing that, its shards.
- Multi-GPU: run under ``torchrun``; each rank takes every world_size-th sample of a batch.
"""

from __future__ import annotations

import csv
import io
import math
import os
import signal
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Protocol

import numpy as np
import torch
from tqdm import tqdm

from deepcharuco.cli.common import output_folder
from deepcharuco.cli.common import pick_device  # noqa: F401 - the trainers' --device, shared with the report
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.networks.checkpoint import read_checkpoint, save_checkpoint

# Options --resume may change: they do not decide the run's result (out: the folder may move; steps:
# train longer than first planned), or are compared by what they name (data, init, teacher) in `_path_differs`.
RESUME_MAY_CHANGE = ("resume", "quiet", "workers", "device", "steps", "out")
COMPARED_AS_PATHS = ("data", "init", "teacher")


@dataclass
class TrainConfig:
    """Shared settings; every field is a command-line option (``--batch-size`` ...)."""

    data: str = ""
    out: str = ""
    steps: int = 20000
    batch_size: int = 32
    lr: float = 1e-3
    weight_decay: float = 1e-4
    warmup: int = 500
    width: str = "paper"  # "paper" or "lite"; RefineNet also "fast"
    init: str = ""  # start from these weights (a checkpoint of the same network), fresh optimizer and schedule
    id_positive_weight: float = 1.0  # ChArUcoNet: weight of corner cells in the ID cross-entropy; 1 = plain mean
    heads: str = "all"  # ChArUcoNet: "all" (point + ID heads) or "points" (point head alone: any boards, a family model)
    label_sigma: float = 2.0  # RefineNet: Gaussian target width in grid cells (1/8 px); 0 = one-hot
    teacher: str = ""  # RefineNet: distil from this RefineNet (checkpoint or bundle) besides the labels
    distill_weight: float = 1.0  # RefineNet: weight of the teacher's term (T^2 KL) beside the labels' term
    temperature: float = 2.0  # RefineNet: the softmax temperature T of the teacher's term
    crop: str = ""  # ChArUcoNet: train on random WxH crops ("160x120"); "" = whole frames
    shadow_edges: float = 0.0  # ChArUcoNet: share of crops with a cast shadow's edge through a corner
    val_fraction: float = 0.1
    val_every: int = 1000
    val_batches: int = 50
    checkpoint_every: int = 500
    log_every: int = 20
    workers: int = 2
    seed: int = 0
    device: str = "auto"
    amp: bool = True
    resume: bool = False
    quiet: bool = False


class Task(Protocol):
    """What differs between the two trainers."""

    model: torch.nn.Module
    train_set: torch.utils.data.Dataset
    val_set: torch.utils.data.Dataset
    higher_is_better: bool
    metric_names: tuple[str, ...]  # what validate returns, "score" first

    def loss(self, model: torch.nn.Module, batch: dict, device: torch.device) -> torch.Tensor: ...

    def validate(self, model: torch.nn.Module, batches: list[dict], device: torch.device) -> dict: ...

    def checkpoint_kwargs(self) -> dict: ...




def learning_rate(step: int, config: TrainConfig) -> float:
    """Linear warm-up to ``lr``, then cosine decay to 1 % of it at ``steps``."""
    if step < config.warmup:
        return config.lr * (step + 1) / config.warmup
    progress = min(1.0, (step - config.warmup) / max(1, config.steps - config.warmup))
    return config.lr * (0.01 + 0.99 * 0.5 * (1.0 + math.cos(math.pi * progress)))


def batch_indices(step: int, size: int, config: TrainConfig, rank: int = 0, world: int = 1) -> list[int]:
    """Dataset indices of the batch at global ``step`` (this rank's share under DDP)."""
    per_epoch = max(1, size // config.batch_size)
    epoch, position = divmod(step, per_epoch)
    order = np.random.default_rng([config.seed, epoch]).permutation(size)
    batch = order[position * config.batch_size:(position + 1) * config.batch_size]
    return batch[rank::world].tolist()


def collate(samples: list[dict]) -> dict:
    return {key: torch.stack([s[key] for s in samples]) if isinstance(samples[0][key], torch.Tensor)
            else torch.tensor([s[key] for s in samples]) for key in samples[0]}


class _Stop:
    """SIGINT/SIGTERM ask for a checkpoint and a clean exit at the end of the current step; ``signal``
    remembers which (None: not stopped by a signal)."""

    def __init__(self):
        self.requested = False
        self.signal: int | None = None
        self._previous = {}

    def __enter__(self):
        for sig in (signal.SIGINT, signal.SIGTERM):
            self._previous[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame):
        self.requested = True
        self.signal = signum

    def __exit__(self, *exc):
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def _ignore_stop_signals(worker_id: int) -> None:
    """DataLoader workers leave SIGINT/SIGTERM to the main process: Ctrl-C (or a kill of the process group)
    reaches them too, and a worker dying of it would abort the run before the main process checkpoints."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)


def data_shards(folder: str | Path) -> list[list]:
    """What a data folder holds, to recognise it after a move: [file name, size in bytes] of each shard."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    return [[p.name, p.stat().st_size] for p in sorted(folder.glob("shard-*.h5"))]


def _path_differs(name: str, saved: dict, config: TrainConfig) -> bool:
    """Whether option ``name`` (a path) names something else than in the saved run: the same resolved
    path is the same; so is, for --data, a folder holding the same shards (a moved data folder)."""
    given, before = getattr(config, name), saved["config"].get(name, "")
    if not given and not before:
        return False
    if not given or not before:
        return True
    resolved = saved.get("resolved", {}).get(name) or str(Path(before).resolve())
    if str(Path(given).resolve()) == resolved:
        return False
    return not (name == "data" and saved.get("data_shards") and saved["data_shards"] == data_shards(given))


def truncate_log(path: Path, step: int) -> None:
    """Cut ``log.csv`` back to the rows of steps <= ``step`` (and drop a line a kill left half-written)."""
    if not path.is_file():
        return
    rows = list(csv.reader(io.StringIO(path.read_text())))
    if not rows:
        return
    header, kept = rows[0], [rows[0]]
    for row in rows[1:]:
        if len(row) == len(header) and row[0].isdigit() and int(row[0]) <= step:
            kept.append(row)
    buffer = io.StringIO()
    csv.writer(buffer, lineterminator="\r\n").writerows(kept)  # csv.DictWriter's default line ends
    temporary = path.with_name(f".{path.name}.tmp")
    temporary.write_text(buffer.getvalue(), newline="")
    temporary.replace(path)


def train(task: Task, config: TrainConfig, kind: str, stop_at: int | None = None) -> dict:
    """Run ``task`` to ``config.steps`` (or stop as on SIGTERM at step ``stop_at``); returns the step,
    the best validation score, this run's losses, the last validation metrics and ``signal``: the
    signal that stopped it (None otherwise)."""
    device = pick_device(config.device)  # before the run folder is made: a bad --device leaves nothing
    out = output_folder(config.out)
    world = int(os.environ.get("WORLD_SIZE", 1))
    rank = int(os.environ.get("RANK", 0))
    if world > 1 and not torch.distributed.is_initialized():
        torch.distributed.init_process_group("nccl" if device.type == "cuda" else "gloo")
    model = task.model.to(device)
    optimizer = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    use_amp = config.amp and device.type == "cuda"
    scaler = torch.amp.GradScaler("cuda", enabled=use_amp)
    step, best, history = 0, None, []
    last_path = out / "last.pt"
    if config.resume:
        if not last_path.is_file():
            raise DeepCharucoError(f"--resume: no {last_path} to resume from (start without --resume)")
        state = torch.load(last_path, map_location="cpu", weights_only=False)
        saved = state["training"]["config"]
        differs = [f.name for f in fields(TrainConfig) if f.name not in RESUME_MAY_CHANGE + COMPARED_AS_PATHS
                   and saved.get(f.name, f.default) != getattr(config, f.name)]
        differs += [name for name in COMPARED_AS_PATHS if _path_differs(name, state["training"], config)]
        if differs:
            raise DeepCharucoError(f"--resume: {', '.join(differs)} differ from the run in {out} "
                                   f"({'; '.join(f'{n}: {saved.get(n)!r} there' for n in differs)}); resume with its settings")
        model.load_state_dict(state["state_dict"])
        optimizer.load_state_dict(state["training"]["optimizer"])
        scaler.load_state_dict(state["training"]["scaler"])
        step, best = state["training"]["step"], state["training"]["best"]
        if rank == 0:
            truncate_log(out / "log.csv", step)
    elif last_path.exists():
        raise DeepCharucoError(f"{out} already holds a run (last.pt): pass --resume to continue it or choose another --out")
    elif config.init:
        _load_init(model, config.init, kind)
    shards_here = data_shards(config.data)
    net = torch.nn.parallel.DistributedDataParallel(model) if world > 1 else model
    torch.manual_seed(config.seed + step)

    def save(path: Path, metrics: dict | None = None) -> None:
        if rank != 0:
            return
        save_checkpoint(path, model, **task.checkpoint_kwargs(), training={
            "step": step, "best": best, "config": asdict(config), "optimizer": optimizer.state_dict(),
            "scaler": scaler.state_dict(), "metrics": metrics or {}, "kind": kind,
            "resolved": {name: str(Path(getattr(config, name)).resolve()) for name in COMPARED_AS_PATHS
                         if getattr(config, name)},
            "data_shards": shards_here})

    log_path = out / "log.csv"
    log_file = open(log_path, "a", newline="")
    writer = None
    board = _tensorboard(out) if rank == 0 else None
    loader_args = dict(num_workers=config.workers, collate_fn=collate, persistent_workers=False,
                       worker_init_fn=_ignore_stop_signals if config.workers else None)
    metrics: dict = {}
    started = time.perf_counter()
    with _Stop() as stop, tqdm(total=config.steps, initial=step, disable=config.quiet or rank != 0, unit="step") as bar:
        while step < config.steps and not stop.requested:
            span = min(config.checkpoint_every - step % config.checkpoint_every, config.steps - step)
            batches = [batch_indices(s, len(task.train_set), config, rank, world) for s in range(step, step + span)]
            loader = torch.utils.data.DataLoader(_EpochView(task.train_set), **loader_args,
                                                 batch_sampler=_EpochBatches(batches, step, config, len(task.train_set)))
            for batch in loader:
                model.train()
                for group in optimizer.param_groups:
                    group["lr"] = learning_rate(step, config)
                with torch.autocast(device.type, dtype=torch.bfloat16 if use_amp else torch.float32, enabled=use_amp):
                    loss = task.loss(net, batch, device)
                optimizer.zero_grad(set_to_none=True)
                scaler.scale(loss).backward()
                scaler.step(optimizer)
                scaler.update()
                step += 1
                bar.update(1)
                row = {"step": step, "loss": float(loss.detach()), "lr": learning_rate(step - 1, config),
                       "seconds": round(time.perf_counter() - started, 2)}
                if step % config.val_every == 0 or step == config.steps:
                    metrics = _validate(task, model, config, device)
                    row.update(metrics)
                    score = metrics["score"]
                    if best is None or (score > best if task.higher_is_better else score < best):
                        best = score
                        save(out / "best.pt", metrics)
                if rank == 0 and (step % config.log_every == 0 or "score" in row):
                    if writer is None:
                        writer = csv.DictWriter(log_file, fieldnames=["step", "loss", "lr", "seconds", *task.metric_names])
                        if log_path.stat().st_size == 0:
                            writer.writeheader()
                    writer.writerow(row)
                    log_file.flush()
                    if board:
                        for key, value in row.items():
                            if key != "step":
                                board.add_scalar(key, value, step)
                    bar.set_postfix(loss=f"{row['loss']:.3f}", **({"val": f"{metrics['score']:.3f}"} if metrics else {}))
                history.append(row["loss"])
                if stop_at is not None and step >= stop_at:
                    stop.requested = True
                if stop.requested or step >= config.steps:
                    break
            save(last_path, metrics)
    log_file.close()
    if stop.requested and rank == 0:
        print(f"stopped at step {step}: {last_path} saved; rerun with --resume to continue")
    return {"step": step, "best": best, "losses": history, **metrics, "signal": stop.signal}


class _EpochView(torch.utils.data.Dataset):
    """Forwards (epoch, index) pairs to the dataset so augmentation sees the right epoch in any worker."""

    def __init__(self, dataset):
        self.dataset = dataset

    def __len__(self):
        return len(self.dataset)

    def __getitem__(self, key):
        epoch, index = key
        if hasattr(self.dataset, "set_epoch"):
            self.dataset.set_epoch(epoch)
        return self.dataset[index]


class _EpochBatches:
    """A batch sampler over precomputed batches, tagging each index with its epoch."""

    def __init__(self, batches: list[list[int]], first_step: int, config: TrainConfig, size: int):
        per_epoch = max(1, size // config.batch_size)
        self.batches = [[((first_step + k) // per_epoch, i) for i in batch] for k, batch in enumerate(batches)]

    def __iter__(self):
        return iter(self.batches)

    def __len__(self):
        return len(self.batches)


# ChArUcoNet's ID classifier: its size is the board's corner count, so it is the one layer a warm start
# from another board's weights cannot take (the rest of the network is board-agnostic).
ID_CLASSIFIER = "id_head.1."


def _load_init(model: torch.nn.Module, path: str, kind: str) -> None:
    """Warm start: the weights of the ``kind`` checkpoint (or bundle) at ``path``, which must fit ``model``;
    a ChArUcoNet of a board with another corner count gives all but its ID classifier, which starts fresh."""
    data = read_checkpoint(path, kind)
    state = data["state_dict"]
    own = model.state_dict()
    other_board = [k for k in state if k.startswith(ID_CLASSIFIER) and k in own and state[k].shape != own[k].shape]
    if kind == "charuconet" and other_board:
        state = {**state, **{k: own[k] for k in other_board}}
        print(f"--init {path}: its ID head classifies {data['config']['num_corners']} corners, this board has "
              f"{model.config.num_corners}; its ID classifier starts fresh, the rest is warm-started")
    try:
        model.load_state_dict(state)
    except RuntimeError as error:
        raise DeepCharucoError(f"--init {path}: its weights ({data['config']}) do not fit this run's network "
                               f"(check --width): {str(error).splitlines()[0]}") from None


def _validate(task: Task, model: torch.nn.Module, config: TrainConfig, device: torch.device) -> dict:
    size = len(task.val_set)
    indices = list(range(min(size, config.val_batches * config.batch_size)))
    batches = [collate([task.val_set[i] for i in indices[k:k + config.batch_size]])
               for k in range(0, len(indices), config.batch_size)]
    model.eval()
    with torch.inference_mode():
        return task.validate(model, batches, device)


def _tensorboard(out: Path):
    try:
        from torch.utils.tensorboard import SummaryWriter
    except Exception:  # tensorboard is optional
        return None
    return SummaryWriter(str(out / "tensorboard"))
