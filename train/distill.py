"""Distil a shipped ChArUcoNet (the teacher) into another architecture (the student, by default ``fast``) on frames
drawn in torch (`train.draw`): no renders needed, any device.

    python -m train.distill --teacher deepcharuco/weights/detector.pt --out runs/distill_paper --steps 60000
    python -m train.distill --out runs/distill_paper --resume          # continue exactly where it stopped
    python -m train.distill --teacher deepcharuco/weights/families/DICT_4X4.pt --family DICT_4X4 --out runs/distill_4x4
    python -m train.distill --points-only --out runs/distill_paper_points     # the paper's board, point head alone
    python -m train.distill ... --init runs/distill_4x4/best.pt --out runs/distill_4x4_inv  # a student's weights to start

Loss, on every 8x8 cell of every frame:

    T^2 KL(teacher || student) of the 65-way point softmax at temperature T       (--distill-weight)
    + cross-entropy on the exact point label (the drawn corner's pixel, or none)   (--label-weight)
    and where the teacher's ID head was trained (the paper's board; not a family model, ``heads: points``) and
    the student learns it (not with --points-only):
    + T^2 KL of the (N+1)-way ID softmax + cross-entropy on the exact ID label, the cells holding a corner
      weighted --id-positive-weight times.

Frames: the teacher's board (a family teacher, ``heads: points``: ``--boards`` random boards of the marker family
``--family`` names, which its checkpoint does not record) through random
poses and lenses onto photographs, noise and clutter, under the paper's augmentations, ``--inverted-p`` of them an
inverted print seen as the detector sees it (the frame inverted whole; `train.draw`). The batch
at step s is drawn from ``default_rng([seed, s])`` alone, so ``--resume`` continues bit for bit: the model,
AdamW's state and the step are in ``last.pt``; the learning rate is a function of the step (warm-up, cosine).

Validation every --val-every steps on --val-batches batches drawn once from --val-seed (other frames than any
training step's): the student's corners (cells at point confidence >= 0.5, within 3 px) against the exact labels
(recall, precision, F1) and against the teacher's corners (``recall_vs_teacher``, ``precision_vs_teacher``); the
teacher's own F1 against the labels (``teacher_f1``, the mark to reach); with ID heads, the paper's corner accuracy
of the student's decoded IDs (`deepcharuco.detection.metrics.match_corners`). The score
(F1 against the labels, averaged with the corner accuracy where there are IDs) keeps ``best.pt``. Checkpoints
(``last.pt``, every --checkpoint-minutes, at the end and on Ctrl-C / SIGTERM) are `deepcharuco.networks`
checkpoints: `load_charuconet` and ``deepcharuco export`` read them. ``log.csv`` has a row per
--log-every steps and per validation.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from deepcharuco.boards.board import BoardSpec
from deepcharuco.boards.dictionaries import MARKER_FAMILIES, dictionary_size
from deepcharuco.cli.common import output_folder, pick_device, run_command
from deepcharuco.core.detection import Detection
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.detection.metrics import match_corners
from deepcharuco.networks.cells import decode_cells, encode_cells, point_candidates
from deepcharuco.networks.charuconet import WIDTH_NAMES, ChArUcoNet, ChArUcoNetConfig, named_config
from deepcharuco.networks.checkpoint import (CheckpointError, id_head_trained, load_charuconet, read_checkpoint,
                                             save_checkpoint)
from deepcharuco.networks.onnx_bundle import is_bundle, read_bundle
from deepcharuco.networks.onnx_runner import _session
from deepcharuco.networks.runtime import float_onnx
from train.charuconet import POINT_CONFIDENCE, match_points
from train.augment import AugmentConfig
from train.draw import DrawConfig, FrameDrawer
from train.loop import _Stop, truncate_log

# Options --resume may change: they do not decide what the run computes.
RESUME_MAY_CHANGE = ("resume", "out", "steps", "quiet", "device", "threads", "checkpoint_minutes", "log_every")
# Options added since runs began: the value a run that began before had (what it computed then), and a new run's.
ADDED_SINCE = {"inverted_p": 0.0, "bits": 0, "min_brightness": 0.02, "max_tilt": 55.0}
NEW_RUN = {
    "inverted_p": 0.2,  # the family renders' share of inverted prints (`datagen.family`)
    "bits": 8,  # frames of a camera's grey levels
    "min_brightness": 0.005,  # the darkest frames at ~0.6^10 of the light: the paper's darkness k = 10
    "max_tilt": 55.0,  # degrees about each of the board's axes
}
METRICS = ("score", "f1", "recall", "precision", "recall_vs_teacher", "precision_vs_teacher", "corner_accuracy",
           "teacher_f1")


def parse_size(text: str, option: str) -> tuple[int, int]:
    parts = text.lower().split("x")
    if len(parts) != 2 or not all(p.isdigit() for p in parts) or any(int(p) <= 0 or int(p) % 8 for p in parts):
        raise DeepCharucoError(f"{option} {text!r}: give WIDTHxHEIGHT in positive multiples of 8, e.g. 160x120")
    return int(parts[0]), int(parts[1])


def family_boards(family: str, count: int, seed: int) -> list[BoardSpec]:
    """``count`` random boards of the marker ``family`` (3-12 squares a side, markers 0.6-0.8 of a square), each with
    the family's smallest dictionary that holds its markers; from ``seed``."""
    if family not in MARKER_FAMILIES:
        raise DeepCharucoError(f"--family {family!r} is no marker family: choose one of {', '.join(MARKER_FAMILIES)}")
    rng = np.random.default_rng([seed, 7])
    names = sorted(MARKER_FAMILIES[family], key=dictionary_size)
    boards = []
    while len(boards) < count:
        squares = rng.integers(3, 13, 2)
        markers = int(squares[0]) * int(squares[1]) // 2
        fits = [n for n in names if dictionary_size(n) >= markers]
        if not fits:
            continue
        square = 0.04
        boards.append(BoardSpec(squares_x=int(squares[0]), squares_y=int(squares[1]), square_length=square,
                                marker_length=square * float(rng.uniform(0.6, 0.8)), dictionary=fits[0]))
    return boards


class Distiller:
    """The teacher, the student, the drawer and the validation frames of one run (``args`` of `parse_args`)."""

    def __init__(self, args: argparse.Namespace, device: torch.device):
        self.args, self.device = args, device
        teacher, teacher_board, data = load_charuconet(args.teacher)
        self.teacher = teacher.to(device).eval()
        for parameter in self.teacher.parameters():
            parameter.requires_grad_(False)
        # On a CPU the teacher runs in ONNX Runtime, as the detector runs it: 1.3-2x PyTorch's speed here, and the
        # teacher's forward pass costs about what the student's whole step does.
        self.teacher_session = (_session(float_onnx(self.teacher), torch.get_num_threads())
                                if device.type == "cpu" else None)
        teacher_ids = id_head_trained(data)
        # --points-only: the point head alone from a teacher that has an ID head too (a student read by its markers)
        self.with_ids = teacher_ids and not args.points_only
        stored = BoardSpec.from_dict(data["board"])
        self.board = stored
        if not teacher_ids and not args.family:
            # A family model's stored board is its warm start's (the paper's board), not of its family.
            raise DeepCharucoError(f"--teacher {args.teacher} is a points-only (family) model: name the marker family "
                                   "it was trained on with --family (its model card says; e.g. --family DICT_4X4)")
        if teacher_ids and args.family:
            raise DeepCharucoError(f"--family: the teacher {args.teacher} was trained on one board ({stored}), whose "
                                   "corner IDs the student learns; --family is for points-only (family) teachers")
        boards = [stored] if teacher_ids else family_boards(args.family, args.boards, args.seed)
        self.size = parse_size(args.size, "--size")
        self.val_size = parse_size(args.val_size, "--val-size")
        self.drawer = FrameDrawer(boards, draw_config(args, self.size), device)
        torch.manual_seed(args.seed)
        self.student = ChArUcoNet(student_config(args, stored.num_corners)).to(device)
        self.id_weights = torch.full((stored.num_corners + 1,), float(args.id_positive_weight), device=device)
        self.id_weights[-1] = 1.0  # the dustbin
        self.val_frames = [self.drawer.draw(np.random.default_rng([args.val_seed, i]), args.batch_size, self.val_size)
                           for i in range(args.val_batches)]
        self.val_teacher = [[t.cpu() for t in self.teach(frames.image)] for frames in self.val_frames]

    @torch.no_grad()
    def teach(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The teacher's (point logits (B, 65, h, w), ID logits (B, N+1, h, w)) of ``image`` (B, 1, H, W)."""
        if self.teacher_session is None:
            return self.teacher(image)
        points, ids = self.teacher_session.run(None, {"image": image.numpy()})
        return torch.from_numpy(points), torch.from_numpy(ids)

    def batch(self, step: int):
        """The drawn frames of training step ``step`` and their exact cell labels (point (B, h, w), ID (B, h, w))."""
        frames = self.drawer.draw(np.random.default_rng([self.args.seed, step]), self.args.batch_size)
        return frames, *self.cell_labels(frames, self.size)

    def cell_labels(self, frames, size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
        width, height = size
        points, ids = [], []
        for corners, visible in zip(frames.corners, frames.visible):
            p, i = encode_cells(corners[:self.board.num_corners] if self.with_ids else corners,
                                visible[:self.board.num_corners] if self.with_ids else visible, height, width)
            points.append(p)
            ids.append(i if self.with_ids else np.full_like(i, self.board.num_corners))
        return (torch.from_numpy(np.stack(points)).to(self.device), torch.from_numpy(np.stack(ids)).to(self.device))

    def loss(self, frames, point_labels: torch.Tensor, id_labels: torch.Tensor) -> tuple[torch.Tensor, dict]:
        """The distillation loss of one batch (module docstring) and its terms."""
        args = self.args
        temperature = args.temperature
        teacher_points, teacher_ids = self.teach(frames.image)
        points, ids = self.student(frames.image)

        def kl(student: torch.Tensor, teacher: torch.Tensor) -> torch.Tensor:
            target = F.log_softmax(teacher / temperature, dim=1)
            mine = F.log_softmax(student / temperature, dim=1)
            return (target.exp() * (target - mine)).sum(dim=1).mean() * temperature**2

        terms = {"kl_points": kl(points, teacher_points), "ce_points": F.cross_entropy(points, point_labels)}
        if self.with_ids:
            terms["kl_ids"] = kl(ids, teacher_ids)
            terms["ce_ids"] = F.cross_entropy(ids, id_labels, weight=self.id_weights)
        total = sum((args.distill_weight if name.startswith("kl") else args.label_weight) * value
                    for name, value in terms.items())
        return total, {name: float(value.detach()) for name, value in terms.items()}

    @torch.inference_mode()
    def validate(self) -> dict:
        """METRICS on the validation frames (module docstring)."""
        self.student.eval()
        counts = dict.fromkeys(("matched", "found", "true", "t_matched", "t_found", "teacher_matched"), 0)
        accuracies = []
        for frames, (teacher_points, teacher_ids) in zip(self.val_frames, self.val_teacher):
            points, ids = (t.cpu() for t in self.student(frames.image))
            for k in range(len(points)):
                _, pixels, _ = point_candidates(points[k].numpy(), POINT_CONFIDENCE)
                _, teacher_pixels, _ = point_candidates(teacher_points[k].numpy(), POINT_CONFIDENCE)
                visible = frames.visible[k]
                truth = frames.corners[k][visible]
                counts["matched"] += match_points(pixels, truth)
                counts["teacher_matched"] += match_points(teacher_pixels, truth)
                counts["found"] += len(pixels)
                counts["t_found"] += len(teacher_pixels)
                counts["true"] += len(truth)
                counts["t_matched"] += match_points(pixels, teacher_pixels)
                if self.with_ids and frames.board[k] >= 0 and visible.any():
                    n = self.board.num_corners
                    detection = Detection(*decode_cells(points[k].numpy(), ids[k].numpy()))
                    accuracies.append(match_corners(detection, frames.corners[k][:n], visible[:n]).accuracy)
        self.student.train()
        ratio = lambda a, b: a / b if b else 0.0  # noqa: E731
        recall, precision = ratio(counts["matched"], counts["true"]), ratio(counts["matched"], counts["found"])
        f1 = ratio(2 * recall * precision, recall + precision)
        teacher_recall = ratio(counts["teacher_matched"], counts["true"])
        teacher_precision = ratio(counts["teacher_matched"], counts["t_found"])
        metrics = {"f1": f1, "recall": recall, "precision": precision,
                   "recall_vs_teacher": ratio(counts["t_matched"], counts["t_found"]),
                   "precision_vs_teacher": ratio(counts["t_matched"], counts["found"]),
                   "corner_accuracy": float(np.mean(accuracies)) if accuracies else float("nan"),
                   "teacher_f1": ratio(2 * teacher_recall * teacher_precision, teacher_recall + teacher_precision)}
        # No validation frame showing a corner (tiny --val-size) scores no IDs: 0, so that the score stays a number.
        metrics["score"] = (f1 + (metrics["corner_accuracy"] if accuracies else 0.0)) / 2 if self.with_ids else f1
        return metrics


def draw_config(settings, size: tuple[int, int]) -> DrawConfig:
    """The `DrawConfig` of a run's ``settings`` (parsed arguments, or a checkpoint's settings dict), frames of ``size``:
    options it does not give take a new run's values (`NEW_RUN`) where parsed, a run's of before where stored."""
    stored = isinstance(settings, dict)
    get = (lambda name: settings.get(name, ADDED_SINCE[name])) if stored else \
        (lambda name: NEW_RUN[name] if getattr(settings, name) is None else getattr(settings, name))
    return DrawConfig(size=size, inverted_p=float(get("inverted_p")), bits=int(get("bits")),
                      max_tilt_deg=float(get("max_tilt")),
                      augmentation=AugmentConfig(homography_p=0.0, min_brightness=float(get("min_brightness"))))


def student_config(args: argparse.Namespace, num_corners: int) -> ChArUcoNetConfig:
    """The student's configuration: ``--arch``'s, without batch normalisation where ``--init`` is an ONNX bundle (its
    convolutions hold their normalisation folded in; `warm_start`), on ``--resume`` too (its ``--init`` is the run's)."""
    config = named_config(args.arch, num_corners)
    return replace(config, batch_norm=False) if args.init and is_bundle(args.init) else config


# A points-only bundle (a family's) holds the point path alone: the encoder's 1/8 stem and the point head.
POINT_PATH = ("encoder.stem.", "point_head.")


def bundle_state(path: str) -> tuple[dict[str, torch.Tensor], bool]:
    """(the weights of the ONNX bundle ``path``'s ChArUcoNet by their PyTorch names, whether it holds the ID head
    too): its graph's initializers, named as the exporter found them in the model's state dict (a points-only graph
    was exported from `PointHeadOnly`, whose names start ``charuconet.``)."""
    import onnx
    from onnx import numpy_helper

    try:
        bundle = read_bundle(path)
    except DeepCharucoError as error:
        raise DeepCharucoError(f"--init: {error}") from None
    name = "charuconet.onnx" if "charuconet.onnx" in bundle.models else "charuconet_points.onnx"
    graph = onnx.load_from_string(bundle.models[name]).graph
    return {i.name.removeprefix("charuconet."): torch.from_numpy(numpy_helper.to_array(i).copy())
            for i in graph.initializer}, name == "charuconet.onnx"


def warm_start(student: ChArUcoNet, path: str, arch: str) -> None:
    """``student``'s weights from the student checkpoint ``path`` (a `train.distill` run's) of the same ``arch``, or
    from an ONNX bundle of one (the shipped fast networks': a ``student`` without batch normalisation,
    `student_config`; a points-only bundle leaves the ID head and its context branches as initialised); its
    optimizer state and step are not taken: the run's schedule starts at step 0."""
    if is_bundle(path):
        state, with_ids = bundle_state(path)
        try:
            missing, unexpected = student.load_state_dict(state, strict=False)
        except RuntimeError as error:
            first = str(error).splitlines()[1].strip() if len(str(error).splitlines()) > 1 else str(error)
            raise DeepCharucoError(f"--init {path}: its network is not a --arch {arch} ChArUcoNet ({first})") from None
        lacking = [k for k in missing if with_ids or k.startswith(POINT_PATH)]
        if unexpected or lacking:
            raise DeepCharucoError(f"--init {path}: its network is not a --arch {arch} ChArUcoNet (weights "
                                   f"{', '.join((unexpected or lacking)[:3])} {'left over' if unexpected else 'missing'})")
        return
    try:
        data = read_checkpoint(path, "charuconet")
    except CheckpointError as error:
        raise DeepCharucoError(f"--init: {error}") from None
    was = data.get("training", {}).get("settings", {}).get("arch")
    if data.get("training", {}).get("kind") != "distill" or was != arch:
        raise DeepCharucoError(f"--init {path}: not a student of --arch {arch} (a train.distill checkpoint"
                               f"{'' if was is None else ' of --arch ' + str(was)}); start without --init")
    try:
        student.load_state_dict(data["state_dict"])
    except RuntimeError as error:
        first = str(error).splitlines()[1].strip() if len(str(error).splitlines()) > 1 else str(error)
        raise DeepCharucoError(f"--init {path}: its weights do not fit this student ({first})") from None


def learning_rate(step: int, args: argparse.Namespace) -> float:
    """Linear warm-up to --lr, then cosine decay to 1 % of it at --steps."""
    if step < args.warmup:
        return args.lr * (step + 1) / args.warmup
    progress = min(1.0, (step - args.warmup) / max(1, args.steps - args.warmup))
    return args.lr * (0.01 + 0.99 * 0.5 * (1.0 + math.cos(math.pi * progress)))


def settings(args: argparse.Namespace) -> dict:
    return {k: v for k, v in vars(args).items()}


def run(args: argparse.Namespace, stop_at: int | None = None) -> dict:
    """Train (or resume) the run ``args`` describes; stop as on SIGTERM after step ``stop_at`` (tests). Returns
    the step reached, the best score, the last metrics and the signal that stopped it (None otherwise)."""
    device = pick_device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    out = Path(args.out)
    last_path = out / "last.pt"
    saved = None
    if args.resume:
        if not last_path.is_file():
            raise DeepCharucoError(f"--resume: no {last_path} to resume from (start without --resume)")
        saved = torch.load(last_path, map_location="cpu", weights_only=True)
        before = saved["training"]["settings"]
        for name in NEW_RUN:  # not given: the run's own
            if getattr(args, name) is None:
                setattr(args, name, before.get(name, ADDED_SINCE[name]))
        defaults = parser()  # an option added since the run started: the run had its default
        differs = [name for name, value in settings(args).items() if name not in RESUME_MAY_CHANGE
                   and before.get(name, ADDED_SINCE.get(name, defaults.get_default(name))) != value]
        if differs:
            raise DeepCharucoError(f"--resume: {', '.join('--' + n.replace('_', '-') for n in differs)} differ from "
                                   f"the run in {out} ({'; '.join(f'{n}: {before.get(n)!r} there' for n in differs)}); "
                                   "resume with its settings")
    elif last_path.exists():
        raise DeepCharucoError(f"{out} already holds a run (last.pt): pass --resume to continue it or choose another --out")
    for name, value in NEW_RUN.items():
        if getattr(args, name) is None:
            setattr(args, name, value)
    try:
        read_checkpoint(args.teacher, "charuconet")
    except CheckpointError as error:
        raise DeepCharucoError(f"--teacher: {error}") from None
    output_folder(out)
    distiller = Distiller(args, device)
    student = distiller.student
    optimizer = torch.optim.AdamW(student.parameters(), lr=args.lr, weight_decay=args.weight_decay)
    step, best, elapsed, metrics = 0, None, 0.0, {}
    if saved is None and args.init:
        warm_start(student, args.init, args.arch)
    if saved is not None:
        student.load_state_dict(saved["state_dict"])
        optimizer.load_state_dict(saved["training"]["optimizer"])
        step, best = saved["training"]["step"], saved["training"]["best"]
        elapsed, metrics = saved["training"]["seconds"], saved["training"]["metrics"]
        truncate_log(out / "log.csv", step)
    student.train()
    started = time.perf_counter()

    def save(path: Path) -> None:
        save_checkpoint(path, student, board=distiller.board, input_size=distiller.size,
                        heads="all" if distiller.with_ids else "points",
                        training={"step": step, "best": best, "settings": settings(args), "kind": "distill",
                                  "optimizer": optimizer.state_dict(), "metrics": metrics,
                                  "seconds": elapsed + time.perf_counter() - started})

    fields = ["step", "loss", "kl_points", "ce_points", "kl_ids", "ce_ids", "lr", "seconds", *METRICS]
    new_log = not (out / "log.csv").is_file()
    log_file = open(out / "log.csv", "a", newline="")
    writer = csv.DictWriter(log_file, fieldnames=fields, extrasaction="ignore")
    if new_log:
        writer.writeheader()
    if step == 0 and not args.quiet:
        print(f"teacher {args.teacher} ({'point and ID heads' if distiller.with_ids else 'point head'}), student "
              f"{args.arch}: {sum(p.numel() for p in student.parameters())} parameters; frames {args.size}", flush=True)
    last_save, session_start_step = time.perf_counter(), step
    with _Stop() as stop, tqdm(total=args.steps, initial=step, disable=args.quiet, unit="step",
                               mininterval=5) as bar:
        while step < args.steps and not stop.requested:
            frames, point_labels, id_labels = distiller.batch(step)
            for group in optimizer.param_groups:
                group["lr"] = learning_rate(step, args)
            loss, terms = distiller.loss(frames, point_labels, id_labels)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            step += 1
            bar.update(1)
            row = {"step": step, "loss": float(loss.detach()), **terms, "lr": learning_rate(step - 1, args),
                   "seconds": round(elapsed + time.perf_counter() - started, 1)}
            if step % args.val_every == 0 or step == args.steps:
                metrics = distiller.validate()
                row.update(metrics)
                if best is None or metrics["score"] > best:
                    best = metrics["score"]
                    save(out / "best.pt")
                if not args.quiet:
                    tqdm.write(f"validation at step {step}: " + ", ".join(f"{k} {v:.3f}" for k, v in metrics.items()))
            if step % args.log_every == 0 or "score" in row:
                writer.writerow(row)
                log_file.flush()
                rate = (time.perf_counter() - started) / max(1, step - session_start_step)
                eta = (args.steps - step) * rate
                bar.set_postfix_str(f"loss {row['loss']:.3f}")
                if not args.quiet:
                    tqdm.write(f"step {step}/{args.steps} loss {row['loss']:.4f} ("
                               + ", ".join(f"{k} {v:.3f}" for k, v in terms.items())
                               + f") lr {row['lr']:.2e} {rate:.2f} s/step ETA {eta / 3600:.1f} h", file=sys.stdout)
            if stop_at is not None and step >= stop_at:
                stop.requested = True
            if time.perf_counter() - last_save >= 60 * args.checkpoint_minutes:
                save(last_path)
                last_save = time.perf_counter()
        save(last_path)
    log_file.close()
    if stop.requested and stop_at is None:
        print(f"stopped at step {step}: {last_path} saved; rerun with --resume to continue")
    return {"step": step, "best": best, "metrics": metrics, "signal": stop.signal}


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m train.distill", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--teacher", default="deepcharuco/weights/detector.pt",
                   help="the teacher: a ChArUcoNet checkpoint or bundle (the paper's board: detector.pt; a family: "
                        "deepcharuco/weights/families/DICT_4X4.pt ...)")
    p.add_argument("--out", default="runs/distill", help="run folder (last.pt, best.pt, log.csv)")
    p.add_argument("--arch", choices=WIDTH_NAMES, default="fast", help="the student's architecture")
    p.add_argument("--steps", type=int, default=60000, help="optimizer steps in all (the cosine schedule's length)")
    p.add_argument("--batch-size", type=int, default=32)
    p.add_argument("--size", default="160x120", help="training frames WxH (multiples of 8)")
    p.add_argument("--lr", type=float, default=2e-3)
    p.add_argument("--weight-decay", type=float, default=1e-4)
    p.add_argument("--warmup", type=int, default=500, help="steps of linear learning-rate warm-up")
    p.add_argument("--temperature", type=float, default=2.0, help="softmax temperature of the distillation terms")
    p.add_argument("--distill-weight", type=float, default=1.0, help="weight of the KL terms (to the teacher)")
    p.add_argument("--label-weight", type=float, default=1.0, help="weight of the cross-entropy on the exact labels")
    p.add_argument("--id-positive-weight", type=float, default=10.0,
                   help="weight of the cells holding a corner in the ID cross-entropy (the shipped model's stage B)")
    p.add_argument("--points-only", action="store_true",
                   help="distil the point head alone, from a teacher whose ID head was trained too (the paper's "
                        "board): the student is a points-only model, which reads its board by its markers")
    p.add_argument("--family", default="",
                   help="a points-only (family) teacher: the marker family it was trained on (DICT_4X4, DICT_6X6, ...)")
    p.add_argument("--boards", type=int, default=64, help="a family teacher: random boards of its family drawn")
    p.add_argument("--inverted-p", type=float, default=None,
                   help="share of frames of an inverted print (a board file's inverted: true), seen as the detector "
                        "sees it: the frame inverted whole, a dark frame a washed-out bright one (default: 0.2, as the "
                        "family renders; --resume: the run's own, 0 for runs begun before this option)")
    p.add_argument("--bits", type=int, default=None,
                   help="frames rounded to this many bits, as a camera's (0: not rounded; default: 8; --resume: the "
                        "run's own, 0 for runs begun before this option)")
    p.add_argument("--min-brightness", type=float, default=None,
                   help="the darkest frames' share of the light (default: 0.005, the paper's darkness k = 10; "
                        "--resume: the run's own, 0.02 for runs begun before this option)")
    p.add_argument("--max-tilt", type=float, default=None,
                   help="the board's largest tilt about each of its axes, degrees (default: 55; --resume: the run's "
                        "own, 55 for runs begun before this option)")
    p.add_argument("--seed", type=int, default=0, help="seeds the student's initial weights and every training frame")
    p.add_argument("--init", default="",
                   help="start from this student's weights (a train.distill checkpoint of the same --arch, or its ONNX "
                        "bundle: the shipped fast networks', e.g. deepcharuco/weights/fast/detector.onnx, whose student "
                        "then has no batch normalisation), e.g. to train on new frames on from a run's best.pt; the "
                        "schedule starts at step 0")
    p.add_argument("--val-seed", type=int, default=1000, help="seeds the validation frames (not the training seed)")
    p.add_argument("--val-size", default="320x240", help="validation frames WxH")
    p.add_argument("--val-batches", type=int, default=8, help="validation batches (of --batch-size frames)")
    p.add_argument("--val-every", type=int, default=1000, help="steps between validations")
    p.add_argument("--checkpoint-minutes", type=float, default=5.0, help="minutes between last.pt saves")
    p.add_argument("--log-every", type=int, default=50, help="steps between log lines")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    p.add_argument("--device", default="auto", help="auto (CUDA, else MPS, else CPU), cpu, cuda, cuda:1, mps")
    p.add_argument("--resume", action="store_true", help="continue the run in --out exactly where it stopped")
    p.add_argument("--quiet", action="store_true", help="no progress bar or log lines")
    return p


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = parser()
    args = p.parse_args(argv)
    problems = [f"--{name.replace('_', '-')} must be >= {low}" for name, low in
                (("steps", 1), ("batch_size", 1), ("val_every", 1), ("val_batches", 1), ("log_every", 1),
                 ("boards", 1), ("warmup", 1), ("threads", 0)) if getattr(args, name) < low]
    problems += [f"--{name.replace('_', '-')} must be > 0" for name in
                 ("lr", "temperature", "checkpoint_minutes", "id_positive_weight") if getattr(args, name) <= 0]
    problems += [f"--{name.replace('_', '-')} must be >= 0" for name in ("distill_weight", "label_weight", "weight_decay")
                 if getattr(args, name) < 0]
    if args.inverted_p is not None and not 0 <= args.inverted_p <= 1:
        problems.append("--inverted-p must be within 0 and 1")
    if args.bits is not None and not 0 <= args.bits <= 16:
        problems.append("--bits must be within 0 (not rounded) and 16")
    if args.min_brightness is not None and not 0 < args.min_brightness <= 1:
        problems.append("--min-brightness must be within 0 (exclusive) and 1")
    if args.max_tilt is not None and not 0 <= args.max_tilt < 90:
        problems.append("--max-tilt must be within 0 and 90 (exclusive) degrees")
    for option in ("size", "val_size"):
        try:
            parse_size(getattr(args, option), "--" + option.replace("_", "-"))
        except DeepCharucoError as error:
            problems.append(str(error))
    if problems:
        p.error("; ".join(problems))
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)

    def body() -> int:
        result = run(args)
        if result["signal"] is not None:
            return 128 + result["signal"]
        print(f"step {result['step']}: best validation score {result['best']}")
        return 0

    return run_command(body)


if __name__ == "__main__":
    sys.exit(main())
