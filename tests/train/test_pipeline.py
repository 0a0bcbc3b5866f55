"""train.pipeline: one command makes a model; it plans, resumes after a kill and refuses bad input.
Also the points-only training it relies on for family models (train.charuconet --heads points)."""

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

from conftest import ROOT, VIEW_POSES, make_view, needs_bpy, process_group
from datagen.shards import FrameLabels, write_shard
from deepcharuco import BoardSpec, DeepCharucoError
from deepcharuco.detection.deep_detector import Detector
from deepcharuco.detection.markers.placement import weak_confidence
from deepcharuco.networks import load_charuconet
from deepcharuco.networks.checkpoint import PointsOnlyBoard, read_checkpoint
from train.bundle import choose_threshold
from train.charuconet import ChArUcoNetTask, match_points
from train.loop import TrainConfig, train
from train.pipeline import checks, command, plan, rates, stages

SHIPPED = ROOT / "deepcharuco" / "weights" / "detector.pt"
SMALL_BOARD = BoardSpec(squares_x=4, squares_y=4, square_length=0.04, marker_length=0.03, dictionary="DICT_4X4_50")
# Rates as if recorded by an earlier run in the folder: the plan then needs no render probe (~15 s of Blender).
RECORDED = {"render_s_per_frame": 1.0, "charuconet_s_per_step": 0.5, "refinenet_s_per_step": 0.2,
            "patch_s_per_patch": 0.002}
TINY = ["--frames", "4", "--charuconet-steps", "30", "--refinenet-steps", "4", "--synthetic-patches", "200",
        "--eval-sequences", "1", "--eval-frames", "31", "--eval-images", "1", "--image-size", "160x120",
        "--samples", "2", "--batch-size", "2", "--workers", "0", "--device", "cpu", "--quiet"]


def seed_rates(run: Path) -> None:
    run.mkdir(parents=True, exist_ok=True)
    (run / "rates.json").write_text(json.dumps({k: {"value": v, "source": "test"} for k, v in RECORDED.items()}))


def pipeline_command(board_file: Path, run: Path) -> list[str]:
    return [sys.executable, "-m", "train.pipeline", "--board", str(board_file), "--out", str(run), *TINY]


HANG_S = 1800  # a hang guard for the processes these tests start, not a bound on their speed


def wait_for(condition, process: subprocess.Popen) -> None:
    """Until ``condition()``, however long a loaded machine takes; the process ending first, or hanging past
    `HANG_S` of waiting, fails the test."""
    waited = 0.0
    while not condition():
        if process.poll() is not None:
            raise AssertionError(f"the pipeline ended (code {process.returncode}) before the moment to stop it:\n"
                                 + process.stdout.read()[-3000:])
        assert waited < HANG_S, f"still waiting after {HANG_S} s: the pipeline hangs"
        time.sleep(0.1)
        waited += 0.1


# ------------------------------------------------------------------------------------------- end to end

@needs_bpy
def test_pipeline_end_to_end_survives_kills(tmp_path):
    """A tiny --board run: killed hard mid-render, stopped by SIGTERM mid-training, each time rerun with the
    same command; it finishes with a bundle Detector loads, a card with the evaluation's numbers, and a
    fourth run does nothing."""
    board_file = SMALL_BOARD.save(tmp_path / "board.yaml")
    run = tmp_path / "run"
    seed_rates(run)
    command = pipeline_command(board_file, run)
    renders = run / "data" / "renders"

    # 1. A preemption mid-render: the whole process group killed with SIGKILL after the first shard.
    with process_group(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) as first:
        wait_for(lambda: (renders / "shard-00000.h5").is_file(), first)
        os.killpg(first.pid, signal.SIGKILL)
        output = first.communicate()[0]
    assert "ETA:" in output and "1. render" in output and "8. card" in output and "reproduce: python -m train.pipeline" in output
    assert "rates: render_s_per_frame 1 (test)" in output  # recorded rates are used, not measured again
    assert not (run / "stages" / "render.json").exists()
    first_shard = (renders / "shard-00000.h5").stat().st_mtime_ns

    # 2. Rerun: the render resumes (its first shard kept); SIGTERM to the pipeline once ChArUcoNet checkpointed
    #    (30 steps, a checkpoint every 3: on a fast machine the trainer may just have finished, then a later stage stops).
    with process_group(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) as second:
        wait_for(lambda: (run / "charuconet" / "last.pt").is_file(), second)
        second.send_signal(signal.SIGTERM)  # to the pipeline alone: it passes it on to its stage
        output = second.communicate(timeout=HANG_S)[0]
    assert second.returncode == 143, output[-3000:]
    stopped = output.split("stopped during stage ")[1].split(":")[0]
    assert stopped in ("charuconet", "refinenet", "bundle"), output[-3000:]
    assert (renders / "shard-00000.h5").stat().st_mtime_ns == first_shard
    assert sorted(p.name for p in renders.glob("shard-*.h5")) == [f"shard-0000{i}.h5" for i in range(4)]
    assert (run / "stages" / "render.json").is_file() and not (run / "stages" / f"{stopped}.json").exists()

    # 3. Rerun: finished stages are skipped, a stopped trainer resumes from its last.pt, the rest runs.
    third = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    assert third.returncode == 0, third.stdout[-3000:] + third.stderr[-3000:]
    assert "== stage 1/8" not in third.stdout and "== stage 2/8" not in third.stdout
    if stopped in ("charuconet", "refinenet"):
        assert f"-m train.{stopped}" in third.stdout and " --resume" in third.stdout
    assert (renders / "shard-00000.h5").stat().st_mtime_ns == first_shard

    detector = Detector(board=SMALL_BOARD, weights=run / "detector.pt")
    assert detector.geometry == "repair" and detector.board.same_layout(SMALL_BOARD)
    onnx = Detector(board=SMALL_BOARD, weights=run / "detector.onnx")  # its ONNX bundle, written beside it
    assert onnx.charuconet is None and onnx.geometry == "repair" and onnx.threshold == detector.threshold
    bundle = read_checkpoint(run / "detector.pt", "charuconet")
    assert bundle["training"]["step"] <= 30 and "threshold" in bundle and "heads" not in bundle
    results = json.loads((run / "eval" / "results.json").read_text())["boards"]
    (name, result), = results.items()
    card = (run / "MODEL_CARD.md").read_text()
    assert "## Make it again" in card and "--frames 4 --charuconet-steps 30" in card
    assert f"| {name} | 1 | {result['summary']['deep']['k0']:.2f} / {result['summary']['opencv']['k0']:.2f} |" in card
    assert "chosen by `train.bundle --threshold auto` on the validation shards" in card

    # 4. Everything done: the plan says so and nothing runs again.
    fourth = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    assert fourth.returncode == 0 and "== stage" not in fourth.stdout
    assert fourth.stdout.count(" done\n") == 8

    # 5. Damage after the finish: a stage is done when its outputs read back, not when its marker exists.
    #    A cut-off detector.pt, a render shard deleted (as the truncated-shard error advises), a cut-off last.pt.
    cut_off(run / "detector.pt")
    (renders / "shard-00002.h5").unlink()
    cut_off(run / "charuconet" / "last.pt")
    fifth = subprocess.run(command, cwd=ROOT, capture_output=True, text=True)
    assert fifth.returncode == 0, fifth.stdout[-3000:] + fifth.stderr[-3000:]
    assert "Traceback" not in fifth.stderr
    assert f"{run / 'detector.pt'} is damaged" in fifth.stderr and "moved to detector.pt.damaged" in fifth.stderr
    assert f"{run / 'charuconet' / 'last.pt'} is damaged" in fifth.stderr
    assert "stage charuconet resumes from" in fifth.stderr and "its last good checkpoint" in fifth.stderr
    assert f"stage render is not done ({renders} holds 3 of the plan's 4 frames)" in fifth.stderr
    for number in (1, 5):  # render and bundle run again; the rest were verified and kept
        assert f"== stage {number}/8" in fifth.stdout, fifth.stdout[-3000:]
    assert "== stage 2/8" not in fifth.stdout and "== stage 7/8" not in fifth.stdout
    # ChArUcoNet trains on from its best.pt's step; when that was its last step there is nothing left to train.
    resumed_at = int(fifth.stderr.split("stage charuconet resumes from")[1].split("(step ")[1].split(")")[0])
    assert ("== stage 3/8" in fifth.stdout) == (resumed_at < 30)
    assert sorted(p.name for p in renders.glob("shard-*.h5")) == [f"shard-0000{i}.h5" for i in range(4)]
    assert read_checkpoint(run / "detector.pt", "charuconet")["threshold"] == bundle["threshold"]
    assert checks.checkpoint_step(run / "charuconet" / "last.pt") == 30

    # 6. datagen.patches stopped by SIGTERM (the pipeline passes it on) removes its staging folder.
    with process_group([sys.executable, "-m", "datagen.patches", "--renders", str(renders), "--out",
                        str(tmp_path / "patches"), "--synthetic", "2000000", "--seed", "0"], cwd=ROOT,
                       stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) as patches:
        wait_for(lambda: any(tmp_path.glob(".patches.tmp-*/*.h5")), patches)
        patches.send_signal(signal.SIGTERM)
        patches.communicate(timeout=HANG_S)
    assert patches.returncode == 143 and not list(tmp_path.glob(".patches.tmp-*"))


def cut_off(path: Path) -> None:
    """Cut a file to half its length, as a full disk or an interrupted copy leaves it."""
    data = path.read_bytes()
    path.write_bytes(data[:len(data) // 2])


# --------------------------------------------------------------------------------------------- refusals

def run_main(argv: list[str], capsys) -> tuple[int, str]:
    code = command.main(argv)
    return code, capsys.readouterr().err


def test_refusals_name_the_problem_and_the_fix(tmp_path, capsys, unwritable_dir):
    board_file = SMALL_BOARD.save(tmp_path / "board.yaml")
    out = ["--out", str(tmp_path / "run")]
    code, err = run_main(["--family", "DICT_9X9", *out], capsys)
    assert code == 2 and "unknown marker family 'DICT_9X9'" in err and "DICT_4X4" in err
    code, err = run_main(["--family", "DICT_4X4,DICT_6X6", *out], capsys)
    assert code == 2 and "one family per model" in err
    code, err = run_main(["--family", "DICT_4X4", "--board", str(board_file), *out], capsys)
    assert code == 2 and "exactly one of --family" in err and "not both" in err
    code, err = run_main(out, capsys)
    assert code == 2 and "exactly one of --family" in err
    for budget in ("6 hours", "h", "-1h", "0m"):
        code, err = run_main(["--board", str(board_file), f"--budget={budget}", *out], capsys)
        assert code == 2 and f"--budget {budget!r}" in err, err
    code, err = run_main(["--board", str(board_file), "--out", str(unwritable_dir / "run")], capsys)
    assert code == 2 and "--out" in err and "writ" in err
    (tmp_path / "file").write_text("")
    code, err = run_main(["--board", str(board_file), "--out", str(tmp_path / "file")], capsys)
    assert code == 2 and "is a file, not a folder" in err
    code, err = run_main(["--board", str(tmp_path / "missing.yaml"), *out], capsys)
    assert code == 2 and "missing.yaml" in err
    code, err = run_main(["--board", str(board_file), "--init", str(tmp_path / "nope.pt"), *out], capsys)
    assert code == 2 and "--init" in err and "'none'" in err
    code, err = run_main(["--board", str(board_file), "--eval-frames", "10", *out], capsys)
    assert code == 2 and "--eval-frames 10: give 31 or more" in err
    assert not (tmp_path / "run").exists()  # refused before anything was made


def make_pipeline(argv: list[str]) -> stages.Pipeline:
    args = command.build_parser().parse_args(argv)
    return stages.Pipeline(args, plan.check_target(args))


def test_resuming_with_other_settings_is_refused(tmp_path, capsys):
    board_file = SMALL_BOARD.save(tmp_path / "board.yaml")
    run = tmp_path / "run"
    first = make_pipeline(["--board", str(board_file), "--out", str(run), *TINY])
    first.sizes = plan.Sizes(**{**asdict(plan.FULL["all"]), **first.fixed_sizes()})
    first.save_plan()
    code, err = run_main(["--board", str(board_file), "--out", str(run), *TINY, "--seed", "5"], capsys)
    assert code == 2 and "holds a run made with other settings (seed)" in err and "choose another --out" in err
    code, err = run_main(["--board", str(board_file), "--out", str(run), *TINY, "--frames", "8"], capsys)
    assert code == 2 and "other settings (frames)" in err
    code, err = run_main(["--board", str(board_file), "--out", str(run), *TINY, "--shadow-edges", "0.4"], capsys)
    assert code == 2 and "other settings (shadow_edges)" in err  # its patches and RefineNet were made without


@needs_bpy
def test_plan_only_writes_nothing_and_damaged_records_are_said(tmp_path, capsys):
    """--plan-only measures and prints, and leaves the folder as it was: none made for a new --out, nothing
    added to an existing one. A cut-off plan.json is planned again (no --budget: the same sizes), a cut-off
    rates.json measured again; with --budget a damaged plan is refused with what to do."""
    board_file = SMALL_BOARD.save(tmp_path / "board.yaml")
    fresh = tmp_path / "new" / "run"
    code, err = run_main(["--board", str(board_file), "--out", str(fresh), *TINY, "--plan-only"], capsys)
    assert code == 0, err
    assert not (tmp_path / "new").exists()
    run = tmp_path / "run"
    first = make_pipeline(["--board", str(board_file), "--out", str(run), *TINY])
    first.sizes = plan.Sizes(**{**asdict(plan.FULL["all"]), **first.fixed_sizes()})
    first.save_plan()
    (run / "plan.json").write_text((run / "plan.json").read_text()[:40])
    (run / "rates.json").write_text('{"render_s_per_frame": {"val')
    before = {p.name: p.read_bytes() for p in run.iterdir()}
    code, err = run_main(["--board", str(board_file), "--out", str(run), *TINY, "--plan-only"], capsys)
    assert code == 0, err
    assert f"{run / 'plan.json'} is damaged (cut off or empty): planned again" in err
    assert f"{run / 'rates.json'} is damaged and is ignored" in err
    assert {p.name: p.read_bytes() for p in run.iterdir()} == before
    code, err = run_main(["--board", str(board_file), "--out", str(run), *TINY, "--budget", "2h", "--plan-only"], capsys)
    assert code == 2 and "plan.json is damaged" in err and "rerun with the sizes spelled out" in err
    assert "Traceback" not in err


def test_help_lists_defaults():
    text = command.build_parser().format_help()
    for shown in ("(default: 320x240)", "(default: lite)", "(default: shipped)", "(default: auto)", "(default: 40)",
                  "--budget", "--cluster {slurm,k8s}", "--family", "--board"):
        assert shown in text, shown
    assert "(default: None)" not in text


# ------------------------------------------------------------------------------------------ budgets

@pytest.mark.parametrize("text, seconds", [("6h", 21600), ("90m", 5400), ("1h30m", 5400), ("45s", 45), ("2.5h", 9000)])
def test_durations(text, seconds):
    assert plan.parse_duration(text) == seconds


def test_budget_shrinks_what_was_not_given_and_says_so():
    rates = {**plan.ASSUMED_RATES, "charuconet_s_per_step": 0.6, "refinenet_s_per_step": 0.05}
    full = plan.FULL["points"]
    assert sum(plan.eta_of(full, rates, 1, "points", False).values()) > 3600
    sizes, notes = plan.fit_to_budget(full, {"refinenet_steps": 1500}, rates, 3600, 1, "points", False)
    assert sum(plan.eta_of(sizes, rates, 1, "points", False).values()) <= 3600
    assert sizes.frames < full.frames and sizes.charuconet_steps < full.charuconet_steps
    assert sizes.refinenet_steps == 1500  # given on the command line: kept
    assert any(n.startswith("frames:") for n in notes) and any(n.startswith("charuconet steps:") for n in notes)
    unlimited, none = plan.fit_to_budget(full, {}, rates, None, 1, "points", False)
    assert unlimited == full and none == []
    with pytest.raises(plan.PipelineError, match="less than the smallest plan"):
        plan.fit_to_budget(full, {}, rates, 60, 1, "points", False)


def test_cluster_scripts_shard_the_render_and_run_training_under_torchrun(tmp_path, capsys):
    """--cluster slurm writes one job script per stage (absolute paths, the render an array over its shards, the
    trainers with their GPUs under torchrun); --cluster k8s the Indexed Job manifests. Nothing is run."""
    board_file = SMALL_BOARD.save(tmp_path / "board.yaml")
    run = tmp_path / "run"
    seed_rates(run)
    for kind in ("slurm", "k8s"):
        code = command.main(["--board", str(board_file), "--out", str(run), *TINY, "--cluster", kind,
                              "--num-shards", "4", "--nproc-per-node", "2", "--device", "cuda", "--time", "90"])
        assert code == 0, capsys.readouterr().err
    folder = run.resolve() / "cluster"
    render = (folder / "render.sbatch").read_text()
    assert f"#SBATCH --chdir={run.resolve()}" in render and "#SBATCH --time=1:30:00" in render
    assert '--stage render --shard-index "$SLURM_ARRAY_TASK_ID" --num-shards 4' in render
    assert f"--board {run.resolve() / 'board.yaml'}" in render and "--frames 4" in render
    training = (folder / "charuconet.sbatch").read_text()
    assert "#SBATCH --gres=gpu:2" in training and "--nproc-per-node 2" in training and "--stage charuconet" in training
    assert "--gres" not in (folder / "patches.sbatch").read_text()
    names = sorted(p.stem for p in folder.glob("*.sbatch"))
    assert names == sorted(["render", "patches", "charuconet", "refinenet", "bundle", "eval-data-4x4-dict_4x4_50",
                            "evaluate", "card"])
    job = (folder / "render-job.yaml").read_text()
    assert "completionMode: Indexed" in job and "completions: 4" in job and "parallelism: 4" in job
    assert "--shard-index $JOB_COMPLETION_INDEX --num-shards 4" in job and "kind: Job" in job
    train_job = (folder / "train-job.yaml").read_text()
    assert "--nproc-per-node 2" in train_job and "nvidia.com/gpu: 2" in train_job
    assert not (run / "stages").exists()  # written, nothing run
    trainer = make_pipeline(["--board", str(board_file), "--out", str(run), "--nproc-per-node", "2"])
    assert trainer.module("train.charuconet", torchrun=True)[:5] == ["torchrun", "--standalone", "--nproc-per-node", "2", "-m"]
    assert trainer.module("datagen.render")[1:] == ["-m", "datagen.render"]


# ------------------------------------------------------------------------------ points-only training

@pytest.fixture(scope="module")
def two_boards(tmp_path_factory, camera):
    """Two shards of two different boards (what family renders look like to the trainer)."""
    out = tmp_path_factory.mktemp("two-boards")
    for shard, board in enumerate((BoardSpec(), SMALL_BOARD)):
        views = [make_view(board, camera, **pose) for pose in VIEW_POSES[:3]]
        write_shard(out, shard, [FrameLabels(image=img, corners=c.astype(np.float32), visible=np.ones(len(c), bool),
                                             K=camera.K, rvec=r, tvec=t, meta={"has_board": True})
                                 for img, r, t, c in views], board, {})
    return out


def config(data, out, **kw):
    base = dict(data=str(data), out=str(out), steps=4, batch_size=3, lr=1e-3, warmup=1, width="lite", val_every=4,
                val_batches=1, checkpoint_every=4, log_every=1, workers=0, seed=1, quiet=True, val_fraction=0.5,
                heads="points")
    return TrainConfig(**{**base, **kw})


def test_points_only_training_marks_the_id_head_untrained(two_boards, tmp_path):
    cfg = config(two_boards, tmp_path, init=str(SHIPPED))
    task = ChArUcoNetTask(cfg)
    assert task.train_set.num_corners == 16 and task.train_set[0]["corners"].shape == (16, 2)
    result = train(task, cfg, "charuconet")
    assert result["step"] == 4 and 0.0 <= result["point_f1"] <= 1.0
    header = (tmp_path / "log.csv").read_text().splitlines()[0]
    assert header == "step,loss,lr,seconds,score,point_f1,point_recall,point_precision,val_loss,negative_detections"
    model, board, data = load_charuconet(tmp_path / "best.pt")
    assert data["heads"] == "points" and isinstance(board, PointsOnlyBoard) and not board.same_layout(board)
    assert not BoardSpec().same_layout(board)  # even the board stored with it: its ID head is not trusted
    assert Detector(weights=tmp_path / "best.pt", refine="none").geometry == "markers"
    assert Detector(board=BoardSpec(), weights=tmp_path / "best.pt", refine="none").geometry == "markers"
    with pytest.raises(DeepCharucoError, match="geometry='repair' decodes with the ID head"):
        Detector(board=BoardSpec(), weights=tmp_path / "best.pt", refine="none", geometry="repair")
    threshold, balance = choose_threshold(tmp_path / "best.pt", max_frames=6)
    # Read by markers: low thresholds too, each keeping weak cells below it that only fill in checked corners
    assert 0 < threshold < 1 and set(balance) == {0.01, 0.02, 0.03, 0.04, *np.round(np.arange(0.05, 0.951, 0.05), 2)}
    assert all(weak_confidence(t) < t for t in balance)


def test_points_only_options_are_checked(two_boards, tmp_path):
    with pytest.raises(Exception, match="rendered for"):  # both heads need one board's shards
        ChArUcoNetTask(config(two_boards, tmp_path, heads="all"))
    with pytest.raises(DeepCharucoError, match="--id-positive-weight weights the ID loss"):
        ChArUcoNetTask(config(two_boards, tmp_path, id_positive_weight=10.0))


def test_init_from_another_board_keeps_all_but_the_id_classifier(tmp_path, camera, capsys):
    views = [make_view(SMALL_BOARD, camera, **pose) for pose in VIEW_POSES[:2]]
    write_shard(tmp_path / "data", 0, [FrameLabels(image=img, corners=c.astype(np.float32), visible=np.ones(9, bool),
                                                   K=camera.K, rvec=r, tvec=t, meta={"has_board": True})
                                       for img, r, t, c in views], SMALL_BOARD, {})
    cfg = config(tmp_path / "data", tmp_path / "run", heads="all", steps=1, init=str(SHIPPED), id_positive_weight=10.0)
    task = ChArUcoNetTask(cfg)
    train(task, cfg, "charuconet")
    assert "its ID head classifies 16 corners, this board has 9" in capsys.readouterr().out
    _, board, _ = load_charuconet(tmp_path / "run" / "last.pt")
    assert board == SMALL_BOARD


def test_match_points_pairs_each_truth_once():
    truth = np.array([[10.0, 10.0], [20.0, 10.0]])
    assert match_points(np.array([[10.5, 10.0], [11.0, 10.0], [40.0, 40.0]]), truth) == 1
    assert match_points(np.array([[10.0, 12.9], [19.0, 10.0]]), truth) == 2
    assert match_points(np.zeros((0, 2)), truth) == 0


def test_family_plan_trains_the_point_head_on_family_renders_and_evaluates_unseen_boards(tmp_path, capsys):
    family = make_pipeline(["--family", "DICT_4X4", "--out", str(tmp_path / "run"), "--budget", "2h"])
    family.sizes, family.rates = plan.FULL["points"], {**plan.ASSUMED_RATES, **RECORDED}
    stages = {stage.name: stage for stage in family.stages()}
    assert list(family.eval_boards) == ["4x5 DICT_4X4_1000 inverted"]
    render, charuconet = " ".join(stages["render"].command), " ".join(stages["charuconet"].command)
    assert "--family DICT_4X4" in render and "--n 5000" in render and "--board" not in render
    assert "--heads points" in charuconet and "--id-positive-weight" not in charuconet and str(SHIPPED) in charuconet
    assert "eval-data 4x5 DICT_4X4_1000 inverted" in stages
    assert "--family DICT_4X4" in family.reproduce_command() and "--budget" not in family.reproduce_command()
    assert "--shadow-probability" not in render  # datagen.render's own unless given
    shadows = make_pipeline(["--family", "DICT_4X4", "--out", str(tmp_path / "shadows"), "--shadow-probability", "0.8"])
    assert "--shadow-probability 0.8" in " ".join(shadows.render_args())
    assert "--shadow-probability 0.8" in shadows.reproduce_command()
    five = make_pipeline(["--family", "DICT_5X5", "--out", str(tmp_path / "five")])
    assert "5x5 DICT_5X5_50 (the paper's)" in five.eval_boards and "11x8 DICT_5X5_1000" in five.eval_boards
    scratch = make_pipeline(["--board", str(SMALL_BOARD.save(tmp_path / "b.yaml")), "--out", str(tmp_path / "s"),
                             "--init", "none"])
    scratch.sizes, scratch.rates = plan.FULL["all"], family.rates
    names = [stage.name for stage in scratch.stages()]
    assert names[2:4] == ["charuconet-a", "charuconet-b"]  # the shipped recipe: plain loss, then the ID term weighted
    assert "--shadow-edges" not in " ".join(next(s for s in scratch.stages() if s.name == "patches").command)
    edges = make_pipeline(["--board", str(tmp_path / "b.yaml"), "--out", str(tmp_path / "e"), "--init", "none",
                           "--shadow-edges", "0.4"])
    edges.sizes, edges.rates = plan.FULL["all"], family.rates
    edge_stages = {stage.name: stage for stage in edges.stages()}
    assert "--shadow-edges 0.4" in " ".join(edge_stages["patches"].command) and "--shadow-edges 0.4" in edges.reproduce_command()
    assert all("--shadow-edges 0.4" in " ".join(edge_stages[name].command) for name in ("charuconet-a", "charuconet-b"))
    assert "--shadow-edges" not in " ".join(edge_stages["refinenet"].command)  # its patches carry them
    assert command.main(["--family", "DICT_4X4", "--out", str(tmp_path / "bad"), "--shadow-edges", "1.5"]) == 2
    assert "--shadow-edges 1.5: give a share of the crops and patches in [0, 1]" in capsys.readouterr().err


def test_zero_refinenet_steps_keep_the_initial_refinenet(tmp_path, capsys):
    """--refinenet-steps 0 (how the shipped DICT_4X4 model was made): no patches, no RefineNet stage, the initial
    weights' RefineNet bundled as it is; refused from scratch, where there is none to keep."""
    keep = make_pipeline(["--family", "DICT_4X4", "--out", str(tmp_path / "run"), "--frames", "100",
                          "--charuconet-steps", "50", "--refinenet-steps", "0", "--synthetic-patches", "0"])
    keep.sizes = plan.Sizes(**{**asdict(plan.FULL["points"]), **keep.fixed_sizes()})
    keep.rates = {**plan.ASSUMED_RATES, **RECORDED}
    stages = {stage.name: stage for stage in keep.stages()}
    assert "patches" not in stages and "refinenet" not in stages
    bundle = stages["bundle"].command
    assert bundle[bundle.index("--refinenet") + 1] == str(SHIPPED)
    assert bundle[bundle.index("--charuconet") + 1] == str(tmp_path / "run" / "charuconet" / "best.pt")
    assert "--refinenet-steps 0" in keep.reproduce_command()
    code, err = run_main(["--family", "DICT_4X4", "--out", str(tmp_path / "s"), "--init", "none",
                          "--refinenet-steps", "0"], capsys)
    assert code == 2 and "--refinenet-steps 0" in err and "--init shipped" in err
    code, err = run_main(["--family", "DICT_4X4", "--out", str(tmp_path / "s"), "--charuconet-steps", "0"], capsys)
    assert code == 2 and "--charuconet-steps 0: give a number >= 1" in err


def test_rate_probes_time_real_steps():
    """The probes run a real step of each network and make real patches, and return seconds (how many is the
    machine's business: no bound on wall-clock time here)."""
    for seconds in (rates.probe_training_step("charuconet", "lite", 1, (32, 24), "cpu"),
                    rates.probe_training_step("refinenet", "lite", 2, (24, 24), "cpu"), rates.probe_patches()):
        assert isinstance(seconds, float) and 0 < seconds < float("inf")


@pytest.mark.skipif(sys.platform != "linux", reason="parent-death signal is Linux's")
def test_a_stage_dies_with_a_killed_pipeline(tmp_path):
    """A SIGKILLed pipeline cannot pass the signal on: its stage must still stop (not train on, orphaned)."""
    script = (
        "import subprocess, sys, time\n"
        "from train.pipeline.run import stop_with_parent\n"
        "child = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(120)'], preexec_fn=stop_with_parent)\n"
        "print(child.pid, flush=True)\n"
        "time.sleep(120)\n"
    )
    with process_group([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, cwd=ROOT) as parent:
        child_pid = int(parent.stdout.readline())
        parent.kill()
        parent.wait()
        # The kernel signals the stage as its parent dies; it is gone within moments (100 polls: a hang guard).
        for _ in range(100):
            try:
                os.kill(child_pid, 0)
            except ProcessLookupError:
                return
            time.sleep(0.2)
    pytest.fail("the stage outlived its killed pipeline")  # (process_group has killed it now)
