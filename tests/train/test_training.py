"""The shared training loop: loss falls, resume is exact, SIGTERM checkpoints, refusals."""

import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import torch

from conftest import ROOT, process_group

from datagen.patches import synthetic_patches
from datagen.shards import FrameLabels, read_patch_shard, write_patch_shard, write_shard
from deepcharuco import BoardSpec, DeepCharucoError
from deepcharuco.detection.deep_detector import Detector
from deepcharuco.networks import load_charuconet, load_refinenet
from train.bundle import choose_threshold
from train.charuconet import ChArUcoNetTask
from train.loop import TrainConfig, train
from train.refinenet import RefineNetTask



@pytest.fixture(scope="module")
def patches(tmp_path_factory):
    out = tmp_path_factory.mktemp("patches")
    for shard in range(3):
        p, o = synthetic_patches(np.random.default_rng(shard), 256)
        write_patch_shard(out, shard, p, o, {"source": np.array(["synthetic"] * 256)}, {})
    return out


@pytest.fixture(scope="module")
def frames(tmp_path_factory, default_views):
    out = tmp_path_factory.mktemp("frames")
    for shard in range(2):
        write_shard(out, shard, [FrameLabels(image=img, corners=c.astype(np.float32), visible=np.ones(16, bool), K=np.eye(3),
                                             rvec=r, tvec=t, meta={"has_board": True}) for img, r, t, c in default_views],
                    BoardSpec(), {})
    return out


def config(data, out, **kw):
    base = dict(data=str(data), out=str(out), steps=40, batch_size=16, lr=3e-3, warmup=5, width="lite", val_every=20,
                val_batches=2, checkpoint_every=20, log_every=5, workers=0, seed=1, quiet=True, val_fraction=0.34)
    return TrainConfig(**{**base, **kw})


def test_refinenet_loss_falls(patches, tmp_path):
    # The Gaussian-target loss starts at ln 4096 = 8.32 and sits near it for ~100 steps before falling
    # (its floor is the target's entropy, ~4.2 at sigma 2): 300 steps show the fall.
    cfg = config(patches, tmp_path, steps=300, batch_size=32)
    result = train(RefineNetTask(cfg), cfg, "refinenet")
    losses = result["losses"]
    assert np.mean(losses[-10:]) < np.mean(losses[:10]) - 0.4, (losses[:10], losses[-10:])
    model, _ = load_refinenet(tmp_path / "best.pt")
    log = (tmp_path / "log.csv").read_text().splitlines()
    assert log[0] == "step,loss,lr,seconds,score,mean_error_px,p90_error_px" and len(log) == 1 + 60


def test_a_fast_refinenet_learns_from_its_teacher(patches, tmp_path):
    """--width fast with --teacher (the shipped lite RefineNet): the student's corners move onto the teacher's, and
    validation reports the teacher's own errors beside the student's."""
    from deepcharuco.networks.refinenet import decode_offsets
    from deepcharuco.networks.shipped import DEFAULT_WEIGHTS

    teacher, _ = load_refinenet(DEFAULT_WEIGHTS)
    images = np.concatenate([read_patch_shard(path)[0] for path in sorted(patches.glob("*.h5"))])
    val = torch.from_numpy(images[:256, None].astype(np.float32) / 255.0)
    cfg = config(patches, tmp_path, steps=200, batch_size=32, width="fast", teacher=str(DEFAULT_WEIGHTS),
                 distill_weight=4.0, lr=3e-3, warmup=20, val_every=100)
    task = RefineNetTask(cfg)
    with torch.no_grad():
        taught = decode_offsets(teacher(val))
        before = torch.linalg.norm(decode_offsets(task.model.eval()(val)) - taught, dim=1).mean()
        # the loss is the labels' term plus distill_weight T^2 KL(teacher || student)
        batch = {"image": val[:16], "offset": torch.from_numpy(
            np.concatenate([read_patch_shard(path)[1] for path in sorted(patches.glob("*.h5"))])[:16])}
        task.distill_weight = 0.0
        plain = task.loss(task.model, batch, torch.device("cpu"))
        task.distill_weight = 4.0
        student_log = torch.log_softmax(task.model(batch["image"]) / 2.0, dim=1)
        kl = torch.nn.functional.kl_div(student_log, torch.softmax(teacher(batch["image"]) / 2.0, dim=1),
                                        reduction="batchmean")
        assert kl > 0.1
        assert torch.isclose(task.loss(task.model, batch, torch.device("cpu")), plain + 4.0 * 4.0 * kl, rtol=1e-4)
    train(task, cfg, "refinenet")
    student, checkpoint = load_refinenet(tmp_path / "best.pt")
    assert checkpoint["config"]["arch"] == "fast"
    with torch.no_grad():
        after = torch.linalg.norm(decode_offsets(student(val)) - taught, dim=1).mean()
    assert after < 0.5 * before, (before, after)
    header = (tmp_path / "log.csv").read_text().splitlines()[0].split(",")
    assert header[-2:] == ["teacher_error_px", "teacher_p90_px"]


def test_the_charuconet_trainer_refuses_refinenet_options(frames, tmp_path):
    for option in ({"width": "fast"}, {"teacher": "deepcharuco/weights/detector.pt"}, {"temperature": 3.0}):
        with pytest.raises(DeepCharucoError, match="RefineNet"):
            ChArUcoNetTask(config(frames, tmp_path, **option))


def test_charuconet_loss_falls(frames, tmp_path):
    cfg = config(frames, tmp_path, steps=30, batch_size=4, val_every=15, checkpoint_every=15)
    result = train(ChArUcoNetTask(cfg), cfg, "charuconet")
    assert np.mean(result["losses"][-5:]) < 0.7 * np.mean(result["losses"][:5])
    _, board, checkpoint = load_charuconet(tmp_path / "last.pt")
    assert board == BoardSpec() and checkpoint["input_size"] == [320, 240] and checkpoint["training"]["step"] == 30


def test_charuconet_trains_on_crops_and_validates_on_whole_frames(frames, tmp_path):
    cfg = config(frames, tmp_path, steps=4, batch_size=4, val_every=4, checkpoint_every=4, crop="160x120")
    task = ChArUcoNetTask(cfg)
    task.train_set.set_epoch(0)
    assert task.train_set[0]["image"].shape == (1, 120, 160) and task.train_set[0]["points"].shape == (15, 20)
    assert task.val_set[0]["image"].shape == (1, 240, 320)
    assert train(task, cfg, "charuconet")["step"] == 4


def test_init_warm_starts_and_id_positive_weight_weighs_corner_cells(frames, tmp_path):
    first = config(frames, tmp_path / "a", steps=2, batch_size=2, val_every=2)
    train(ChArUcoNetTask(first), first, "charuconet")
    source = torch.load(tmp_path / "a" / "last.pt", weights_only=False)["state_dict"]
    warm = config(frames, tmp_path / "b", steps=1, batch_size=2, val_every=1, lr=1e-12, warmup=1,
                  init=str(tmp_path / "a" / "last.pt"), id_positive_weight=10.0)
    task = ChArUcoNetTask(warm)
    train(task, warm, "charuconet")
    started = torch.load(tmp_path / "b" / "last.pt", weights_only=False)["state_dict"]
    learned = [k for k in source if "running" not in k and "num_batches" not in k]  # a step in train mode moves BN statistics
    assert learned and all(torch.allclose(started[k], source[k], atol=1e-5) for k in learned)
    wrong_width = config(frames, tmp_path / "c", steps=1, width="paper", init=str(tmp_path / "a" / "last.pt"))
    with pytest.raises(DeepCharucoError, match="--init .* do not fit"):
        train(ChArUcoNetTask(wrong_width), wrong_width, "charuconet")
    with pytest.raises(DeepCharucoError, match="--label-sigma applies to RefineNet"):
        ChArUcoNetTask(config(frames, tmp_path / "d", label_sigma=0.5))
    # The ID term: corner cells count 10 times, the mean is over the weights (PyTorch's weighted mean).
    batch = {k: torch.stack([task.train_set[i][k] for i in range(2)]) for k in ("image", "points", "ids")}
    task.model.cpu()  # `train` leaves it on a GPU where there is one
    points, ids = task.model(batch["image"])
    per_cell = torch.nn.functional.cross_entropy(ids, batch["ids"], reduction="none")
    weights = torch.where(batch["ids"] < 16, 10.0, 1.0)
    expected = torch.nn.functional.cross_entropy(points, batch["points"]) + (per_cell * weights).sum() / weights.sum()
    assert torch.allclose(task.loss(task.model, batch, torch.device("cpu")), expected, atol=1e-5)


def test_bundle_keeps_both_networks_and_drops_optimizer_state(frames, patches, tmp_path):
    charuconet, refinenet = tmp_path / "c", tmp_path / "r"
    train(ChArUcoNetTask(c := config(frames, charuconet, steps=2, batch_size=2, val_every=2)), c, "charuconet")
    train(RefineNetTask(r := config(patches, refinenet, steps=2, val_every=2)), r, "refinenet")
    out = tmp_path / "weights" / "detector.pt"
    done = subprocess.run([sys.executable, "-m", "train.bundle", "--charuconet", str(charuconet / "last.pt"), "--refinenet",
                           str(refinenet / "last.pt"), "--out", str(out), "--note", "hardware=test", "--threshold", "0.17"],
                          cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    data = torch.load(out, weights_only=True)
    assert data["note"] == {"hardware": "test"} and "optimizer" not in data["charuconet"]["training"]
    assert data["charuconet"]["training"]["step"] == 2
    net, _, _ = load_charuconet(out)
    reference, _, _ = load_charuconet(charuconet / "last.pt")
    assert all(torch.equal(a, b) for a, b in zip(net.state_dict().values(), reference.state_dict().values()))
    load_refinenet(out)
    assert Detector(weights=out).threshold == 0.17 and Detector(weights=out, threshold=0.5).threshold == 0.5
    assert Detector(weights=charuconet / "last.pt", refine="none").threshold == 0.3  # nothing stored: the default
    threshold, balance = choose_threshold(charuconet / "last.pt")
    assert threshold in balance and balance[threshold] == max(balance.values())
    swapped = subprocess.run([sys.executable, "-m", "train.bundle", "--charuconet", str(refinenet / "last.pt"), "--refinenet",
                              str(refinenet / "last.pt"), "--out", str(tmp_path / "bad.pt")], cwd=ROOT, capture_output=True, text=True)
    assert swapped.returncode == 2 and "a charuconet was expected" in swapped.stderr and not (tmp_path / "bad.pt").exists()


def test_bundle_never_writes_into_the_package_unless_forced(frames, patches, tmp_path, unwritable_dir):
    charuconet, refinenet = tmp_path / "c", tmp_path / "r"
    train(ChArUcoNetTask(c := config(frames, charuconet, steps=1, batch_size=2, val_every=1)), c, "charuconet")
    train(RefineNetTask(r := config(patches, refinenet, steps=1, val_every=1)), r, "refinenet")

    def bundle(*extra):
        return subprocess.run([sys.executable, "-m", "train.bundle", "--charuconet", str(charuconet / "last.pt"),
                               "--refinenet", str(refinenet / "last.pt"), *map(str, extra)], cwd=ROOT, capture_output=True,
                              text=True)

    shipped = ROOT / "deepcharuco" / "weights" / "detector.pt"
    before = shipped.read_bytes() if shipped.exists() else None
    missing = bundle()
    assert missing.returncode == 2 and "--out" in missing.stderr
    inside = bundle("--out", "deepcharuco/weights/detector.pt")
    assert inside.returncode == 2 and "inside the installed deepcharuco package" in inside.stderr and "--force" in inside.stderr
    assert (shipped.read_bytes() if shipped.exists() else None) == before
    for out, message in ((tmp_path, "is a folder"), (unwritable_dir / "detector.pt", "cannot write there")):
        refused = bundle("--out", out)
        assert refused.returncode == 2 and message in refused.stderr and len(refused.stderr.strip().splitlines()) == 1
    forced = ROOT / "deepcharuco" / "weights" / f"test-force-{os.getpid()}.pt"
    try:
        assert bundle("--out", forced, "--force").returncode == 0 and forced.is_file()
    finally:  # the bundle beside it too: nothing of the test may stay in the package (it would ship)
        forced.unlink(missing_ok=True)
        shutil.rmtree(forced.with_suffix(".onnx"), ignore_errors=True)


def test_resume_is_exact(patches, tmp_path):
    whole = config(patches, tmp_path / "whole")
    train(RefineNetTask(whole), whole, "refinenet")
    half = config(patches, tmp_path / "split")
    assert train(RefineNetTask(half), half, "refinenet", stop_at=20)["step"] == 20
    rest = config(patches, tmp_path / "split", resume=True)
    train(RefineNetTask(rest), rest, "refinenet")
    a = torch.load(tmp_path / "whole" / "last.pt", weights_only=False)
    b = torch.load(tmp_path / "split" / "last.pt", weights_only=False)
    assert a["training"]["step"] == b["training"]["step"] == 40
    for key in a["state_dict"]:
        assert torch.equal(a["state_dict"][key], b["state_dict"][key]), key


def test_refusals(patches, tmp_path):
    cfg = config(patches, tmp_path, steps=5, val_every=5, checkpoint_every=5)
    with pytest.raises(DeepCharucoError, match="no .* to resume"):
        train(RefineNetTask(cfg), TrainConfig(**{**cfg.__dict__, "resume": True}), "refinenet")
    train(RefineNetTask(cfg), cfg, "refinenet")
    with pytest.raises(DeepCharucoError, match="--resume"):
        train(RefineNetTask(cfg), cfg, "refinenet")
    changed = TrainConfig(**{**cfg.__dict__, "resume": True, "lr": 0.1})
    with pytest.raises(DeepCharucoError, match="lr"):
        train(RefineNetTask(changed), changed, "refinenet")
    with pytest.raises(DeepCharucoError, match="--crop applies to ChArUcoNet"):
        RefineNetTask(TrainConfig(**{**cfg.__dict__, "crop": "16x16"}))
    with pytest.raises(DeepCharucoError, match="--id-positive-weight applies to ChArUcoNet"):
        RefineNetTask(TrainConfig(**{**cfg.__dict__, "id_positive_weight": 5.0}))
    with pytest.raises(DeepCharucoError, match="--shadow-edges applies to ChArUcoNet's crops.*datagen.patches"):
        RefineNetTask(TrainConfig(**{**cfg.__dict__, "shadow_edges": 0.3}))
    done = subprocess.run([sys.executable, "-m", "train.charuconet", "--shadow-edges", "1.5", "--out", str(tmp_path / "x")],
                          cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 2 and "--shadow-edges is a share of the crops, from 0 to 1" in done.stderr, done.stderr
    for bad in ("160", "161x120", "0x8", "axb"):
        done = subprocess.run([sys.executable, "-m", "train.charuconet", "--crop", bad, "--out", str(tmp_path / "x")],
                              cwd=ROOT, capture_output=True, text=True)
        assert done.returncode == 2 and "WIDTHxHEIGHT in positive multiples of 8" in done.stderr, done.stderr


@pytest.mark.parametrize("stop, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_ctrl_c_saves_and_resume_finishes(patches, tmp_path, stop, code):
    """SIGINT to the whole process group, as Ctrl-C sends it, DataLoader workers included (or SIGTERM, as a
    scheduler sends it): a checkpoint, and exit code 128 + the signal, so ``train && bundle`` stops there."""
    args = [sys.executable, "-m", "train.refinenet", "--data", str(patches), "--out", str(tmp_path), "--steps", "100000",
            "--batch-size", "16", "--width", "lite", "--workers", "1", "--checkpoint-every", "100000", "--val-every", "100000",
            "--log-every", "2", "--quiet"]
    # The trainer runs 100000 steps: it and its DataLoader worker must not outlive a failing test (process_group).
    with process_group(args, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as process:
        # Until two rows are logged, steps 2 and 4: training under way, its worker feeding it (no bound on how long
        # that takes: a loaded machine is slow, not wrong).
        while not (tmp_path / "log.csv").exists() or len((tmp_path / "log.csv").read_text().splitlines()) < 3:
            assert process.poll() is None, process.communicate()[1][-2000:]
            time.sleep(0.1)
        os.killpg(process.pid, stop)
        out, err = process.communicate(timeout=1800)  # a hang guard, not a speed bound
    assert process.returncode == code and "--resume" in out, err[-2000:]
    step = torch.load(tmp_path / "last.pt", weights_only=False)["training"]["step"]
    assert 0 < step < 100000
    done = _trainer(args[3:8] + [str(step + 3)] + args[9:] + ["--resume"])
    assert done.returncode == 0, done.stderr[-2000:]
    assert torch.load(tmp_path / "last.pt", weights_only=False)["training"]["step"] == step + 3


def _trainer(args: list[str], code: str | None = None) -> subprocess.CompletedProcess:
    """``python -m train.refinenet ARGS`` (or ``python -c CODE ARGS``) in its own process group, which is killed
    whatever happens to the test (a failed assertion, Ctrl-C, a timeout) so that no trainer outlives it."""
    command = [sys.executable, *(["-c", code] if code else ["-m", "train.refinenet"]), *args]
    with process_group(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as process:
        out, err = process.communicate(timeout=1800)  # a hang guard, not a speed bound
    return subprocess.CompletedProcess(command, process.returncode, out, err)


# The trainer SIGKILLed by itself as step 7 starts: after the checkpoint at step 4 and the log's rows of steps 5 and
# 6, before the next checkpoint: nothing of it runs after the signal (no handler, no finally, no flush).
KILLED_AT_7 = """
import os, signal, sys
import train.loop as loop
real = loop.learning_rate
def dying(step, config):
    if step == 6:
        os.kill(os.getpid(), signal.SIGKILL)
    return real(step, config)
loop.learning_rate = dying
from train.refinenet import main
sys.exit(main(sys.argv[1:]))
"""


def test_a_trainer_killed_with_sigkill_resumes_to_the_weights_of_an_uninterrupted_run(patches, tmp_path):
    def args(out):
        return ["--data", str(patches), "--out", str(out), "--steps", "8", "--batch-size", "16", "--lr", "3e-3",
                "--warmup", "2", "--width", "lite", "--val-every", "4", "--val-batches", "2", "--checkpoint-every", "4",
                "--log-every", "1", "--workers", "0", "--seed", "1", "--val-fraction", "0.34", "--quiet"]

    whole = _trainer(args(tmp_path / "whole"))
    assert whole.returncode == 0, whole.stderr[-2000:]
    killed = _trainer(args(tmp_path / "killed"), KILLED_AT_7)
    assert killed.returncode == -signal.SIGKILL, killed.stderr[-2000:]
    assert torch.load(tmp_path / "killed" / "last.pt", weights_only=False)["training"]["step"] == 4
    rows = (tmp_path / "killed" / "log.csv").read_text().splitlines()[1:]
    assert [int(row.split(",")[0]) for row in rows] == list(range(1, 7))  # steps 5 and 6 logged, then lost
    resumed = _trainer(args(tmp_path / "killed") + ["--resume"])
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    a = torch.load(tmp_path / "whole" / "last.pt", weights_only=False)
    b = torch.load(tmp_path / "killed" / "last.pt", weights_only=False)
    assert a["training"]["step"] == b["training"]["step"] == 8
    assert a["state_dict"].keys() == b["state_dict"].keys()
    for key in a["state_dict"]:
        assert torch.equal(a["state_dict"][key], b["state_dict"][key]), key
    for name in ("whole", "killed"):  # the steps the kill lost run again, and are logged once
        steps = [int(row.split(",")[0]) for row in (tmp_path / name / "log.csv").read_text().splitlines()[1:]]
        assert steps == list(range(1, 9)), (name, steps)


def test_resume_after_a_kill_logs_each_step_once(patches, tmp_path):
    """kill -9 after the checkpoint at step 20 and before the next: log.csv already holds steps 25..40, which
    --resume runs again; they must appear once."""
    run = tmp_path / "run"
    first = config(patches, run)
    train(RefineNetTask(first), first, "refinenet", stop_at=20)
    at_20 = (run / "last.pt").read_bytes()
    again = config(patches, run, resume=True)
    train(RefineNetTask(again), again, "refinenet")  # logs up to 40 and checkpoints there ...
    (run / "last.pt").write_bytes(at_20)  # ... but the kill came first: the checkpoint on disk is step 20's
    with open(run / "log.csv", "a") as log:
        log.write("45,0.12")  # and a row the kill cut in half
    train(RefineNetTask(again), again, "refinenet")
    rows = (run / "log.csv").read_text().splitlines()
    steps = [int(row.split(",")[0]) for row in rows[1:]]
    assert rows[0].startswith("step,loss") and steps == list(range(5, 41, 5)), steps


def test_resume_finds_a_moved_run_and_compares_paths_not_text(patches, tmp_path, monkeypatch):
    first = config(patches, tmp_path / "run")
    train(RefineNetTask(first), first, "refinenet", stop_at=20)
    (tmp_path / "run").rename(tmp_path / "moved")
    monkeypatch.chdir(tmp_path)  # the same data folder, named by a relative path with a trailing slash
    moved = config(os.path.relpath(patches, tmp_path) + "/", "moved/", resume=True)
    assert train(RefineNetTask(moved), moved, "refinenet", stop_at=30)["step"] == 30
    copy = tmp_path / "data-copy"  # the data folder moved too: recognised by its shards
    copy.mkdir()
    for shard in patches.glob("shard-*.h5"):
        (copy / shard.name).write_bytes(shard.read_bytes())
    elsewhere = config(copy, tmp_path / "moved", resume=True)
    assert train(RefineNetTask(elsewhere), elsewhere, "refinenet")["step"] == 40
    fewer = tmp_path / "fewer"  # another folder with other shards: another data set
    fewer.mkdir()
    (fewer / "shard-00000.h5").write_bytes((patches / "shard-00000.h5").read_bytes())
    other = config(fewer, tmp_path / "moved", resume=True, steps=50)
    with pytest.raises(DeepCharucoError, match="--resume: data differ"):
        train(RefineNetTask(other), other, "refinenet")


@pytest.mark.parametrize("device, message", [("foo", "is not a device: use auto, cpu, cuda"),
                                             ("cuda", "no CUDA GPU is usable here")])
def test_bad_device_is_refused_before_the_run_folder_is_made(patches, tmp_path, device, message):
    if device == "cuda" and torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    done = subprocess.run([sys.executable, "-m", "train.refinenet", "--data", str(patches), "--out", str(tmp_path / "run"),
                           "--device", device, "--steps", "2"], cwd=ROOT, capture_output=True, text=True)
    assert done.returncode == 2 and message in done.stderr and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert not (tmp_path / "run").exists()


def test_unwritable_or_file_out_is_a_one_line_error(patches, tmp_path, unwritable_dir):
    (tmp_path / "a-file").write_text("")
    for out, message in ((tmp_path / "a-file", "is a file, not a folder"), (unwritable_dir / "run", "cannot write there")):
        done = subprocess.run([sys.executable, "-m", "train.refinenet", "--data", str(patches), "--out", str(out),
                               "--steps", "2"], cwd=ROOT, capture_output=True, text=True)
        assert done.returncode == 2 and message in done.stderr and len(done.stderr.strip().splitlines()) == 1, done.stderr
