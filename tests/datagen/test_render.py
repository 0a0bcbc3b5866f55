"""The Blender pipeline end to end (renders small frames with Cycles; ~1-2 minutes in all).

Label truth, determinism across worker counts, resume after a kill, the schema, negatives,
and the CLI's refusals.
"""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from conftest import ROOT, process_group

from datagen.frames import frame_rng
from datagen.inspect import main as inspect_main
from datagen.scene import SceneConfig, sample_scene
from datagen.shards import ShardReader, list_shards
from deepcharuco import BoardSpec, OpenCVDetector

pytest.importorskip("bpy", reason="the renderer needs the [render] extra (bpy)")
SMALL = ["--width", "160", "--height", "120", "--samples", "2", "--quiet"]


def render(*args, check=True, **kwargs):
    result = subprocess.run([sys.executable, "-m", "datagen.render", *map(str, args)], cwd=ROOT,
                            capture_output=True, text=True, **kwargs)
    if check and result.returncode != 0:
        raise AssertionError(f"datagen.render failed ({result.returncode}):\n{result.stderr[-3000:]}")
    return result


def all_frames(directory):
    frames = []
    for path in list_shards(directory):
        reader = ShardReader(path)
        frames += [reader[i] for i in range(len(reader))]
        reader.close()
    return frames


def seed_with_a_negative(n: int) -> int:
    """A run seed whose first n frames include a negative (scene sampling is cheap, no render)."""
    board = BoardSpec()
    for seed in range(1000):
        if any(not sample_scene(frame_rng(seed, i), board.size_m, SceneConfig(width=160, height=120)).board_present
               for i in range(n)):
            return seed
    raise AssertionError("no negative in 1000 seeds")


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """6 frames in 3 shards of 2, rendered by 2 workers."""
    out = tmp_path_factory.mktemp("reference")
    seed = seed_with_a_negative(6)
    render("--n", 6, "--shard-size", 2, "--seed", seed, "--workers", 2, "--out", out, *SMALL)
    return out, seed


def test_label_truth_on_clean_renders(tmp_path):
    """OpenCV + cornerSubPix agrees with the rendered labels: < 0.1 px median, < 0.3 px p95."""
    render("--n", 3, "--shard-size", 3, "--clean", "--seed", 11, "--out", tmp_path, "--quiet")
    detector = OpenCVDetector(BoardSpec(), refine="subpix")
    errors = []
    for frame in all_frames(tmp_path):
        detection = detector.detect(frame.image)
        for corner_id, corner in zip(detection.ids, detection.corners):
            assert frame.visible[corner_id], "OpenCV found a corner the labels call invisible"
            errors.append(np.linalg.norm(corner - frame.corners[corner_id]))
        assert frame.meta["blur_px"] == 0.0 and frame.meta["lux"] >= 300
    errors = np.array(errors)
    assert len(errors) >= 30, f"OpenCV found only {len(errors)} corners in 3 clean frames"
    assert np.median(errors) < 0.1 and np.percentile(errors, 95) < 0.3, (np.median(errors), np.percentile(errors, 95))


def test_schema_and_negatives(reference):
    out, seed = reference
    index = json.loads((out / "index.json").read_text())
    assert index["frames"] == 6 and [s["file"] for s in index["shards"]] == ["shard-00000.h5", "shard-00001.h5", "shard-00002.h5"]
    with h5py.File(out / "shard-00000.h5") as f:
        assert f["images"].dtype == np.uint8 and f["images"].shape == (2, 120, 160)
        assert f["images"].chunks == (1, 120, 160) and f["images"].compression == "gzip"
        assert f["corners"].dtype == np.float32 and f["corners"].shape == (2, 16, 2)
        assert f["visible"].dtype == bool and f["K"].shape == (2, 3, 3)
        assert f["rvec"].shape == (2, 3) and f["tvec"].shape == (2, 3)
        assert BoardSpec.from_json(f.attrs["board"]) == BoardSpec()
        assert tuple(f.attrs["image_size"]) == (160, 120) and f.attrs["schema_version"] == 1
        assert json.loads(f.attrs["generator"])["args"]["seed"] == seed
        for key in ("seed", "frame", "lux", "exposure_s", "gain", "blur_px", "has_board", "board_kind", "shake"):
            assert f["meta"][key].shape == (2,), key
    frames = all_frames(out)
    assert [f.meta["frame"] for f in frames] == list(range(6))
    negatives = [f for f in frames if not f.meta["has_board"]]
    assert negatives, "the fixture's seed was chosen to hold a negative"
    for frame in negatives:
        assert np.all(np.isnan(frame.corners)) and not frame.visible.any() and frame.meta["distractors"] >= 1
    for frame in frames:
        assert frame.image.std() > 1.0  # not blank
        if frame.meta["has_board"]:
            assert np.all(np.isfinite(frame.corners)) and frame.K[0, 0] > 0
            inside = (frame.corners[:, 0] >= -0.5) & (frame.corners[:, 0] < 159.5) & (frame.corners[:, 1] >= -0.5) & (frame.corners[:, 1] < 119.5)
            assert not np.any(frame.visible & ~inside)


def test_same_seed_same_pixels_whatever_the_workers(reference, tmp_path):
    out, seed = reference
    render("--n", 6, "--shard-size", 3, "--seed", seed, "--workers", 1, "--out", tmp_path, *SMALL)  # other sharding too
    for a, b in zip(all_frames(out), all_frames(tmp_path), strict=True):
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.corners, b.corners)
        np.testing.assert_array_equal(a.visible, b.visible)
    other = render("--n", 2, "--shard-size", 2, "--seed", seed + 1, "--out", tmp_path / "other", *SMALL)
    assert other.returncode == 0
    assert not np.array_equal(all_frames(tmp_path / "other")[0].image, all_frames(out)[0].image)


HANG_S = 1800  # a hang guard for the renders these tests start, not a bound on their speed


def wait_for_a_shard(process: subprocess.Popen, folder: Path, poll_s: float = 0.1) -> None:
    """Until ``folder`` holds a complete shard, however long a loaded machine takes; the render ending first (or
    hanging past `HANG_S`) fails the test."""
    waited = 0.0
    while not (folder.exists() and list_shards(folder)):
        assert process.poll() is None, f"the render ended (code {process.returncode}) before its first shard"
        assert waited < HANG_S, f"no shard after {HANG_S} s: the render hangs"
        time.sleep(poll_s)
        waited += poll_s


def test_resume_after_a_kill_completes_without_duplicates(reference, tmp_path):
    out, seed = reference
    args = ["--n", 6, "--shard-size", 2, "--seed", seed, "--out", tmp_path, *SMALL]
    with process_group([sys.executable, "-m", "datagen.render", *map(str, args)], cwd=ROOT,
                       stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) as process:
        wait_for_a_shard(process, tmp_path)
        os.killpg(process.pid, signal.SIGKILL)  # the whole process group, workers included, mid-shard
        process.wait()
    killed_with = [p.name for p in list_shards(tmp_path)]
    assert 1 <= len(killed_with) < 3
    refused = render(*args, check=False)
    assert refused.returncode == 2 and "--resume" in refused.stderr
    render(*args, "--resume")
    assert [p.name for p in list_shards(tmp_path)] == ["shard-00000.h5", "shard-00001.h5", "shard-00002.h5"]
    assert not [p for p in tmp_path.iterdir() if ".tmp-" in p.name]
    for a, b in zip(all_frames(out), all_frames(tmp_path), strict=True):
        np.testing.assert_array_equal(a.image, b.image)
    mismatch = render("--n", 6, "--shard-size", 2, "--seed", seed + 5, "--out", tmp_path, "--resume", *SMALL, check=False)
    assert mismatch.returncode == 2 and "seed" in mismatch.stderr


def test_ctrl_c_stops_the_render_with_exit_130_and_says_how_to_go_on(reference, tmp_path):
    """Ctrl-C (SIGINT to the process group, as a terminal sends it) is a stop, not a failure: exit code 130,
    one line saying what was kept and how to finish, no traceback, no temporaries."""
    out, seed = reference
    args = ["--n", 6, "--shard-size", 2, "--seed", seed, "--out", tmp_path, *SMALL]
    # SIGINT at its default: a test run started in the background (nohup, &) passes it on ignored, and Python then
    # never raises KeyboardInterrupt.
    with process_group([sys.executable, "-m", "datagen.render", *map(str, args)], cwd=ROOT,
                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                       preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL)) as process:
        wait_for_a_shard(process, tmp_path)
        os.killpg(process.pid, signal.SIGINT)
        err = process.communicate(timeout=HANG_S)[1]
    assert process.returncode == 130, err[-2000:]
    assert "stopped: " in err and "complete shard(s) kept in" in err and "--resume to finish" in err
    assert "Traceback" not in err and not [p for p in tmp_path.iterdir() if ".tmp-" in p.name]


def worker_pids(parent: int) -> list[int]:
    """The render worker processes of ``parent`` (spawned children, not multiprocessing's resource tracker)."""
    children = Path(f"/proc/{parent}/task/{parent}/children").read_text().split()
    return [int(c) for c in children
            if b"spawn_main" in Path(f"/proc/{c}/cmdline").read_bytes() and b"resource_tracker" not in Path(f"/proc/{c}/cmdline").read_bytes()]


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="finds the worker through /proc (Linux)")
def test_a_killed_worker_ends_the_run_with_a_clear_error(tmp_path):
    """kill -9 of a worker (what the out-of-memory killer does): the parent does not wait forever, says
    what happened, keeps the complete shards, removes the dead worker's temporary file; --resume finishes."""
    args = ["--n", 8, "--shard-size", 1, "--seed", 3, "--out", tmp_path, *SMALL]
    # SIGINT at its default: a test run started in the background (nohup, &) passes it on ignored, and Python then
    # never raises KeyboardInterrupt.
    with process_group([sys.executable, "-m", "datagen.render", *map(str, args)], cwd=ROOT,
                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                       preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL)) as process:
        wait_for_a_shard(process, tmp_path, poll_s=0.02)
        for pid in worker_pids(process.pid):
            os.kill(pid, signal.SIGKILL)
        _, err = process.communicate(timeout=HANG_S)
    assert process.returncode == 2 and "killed by SIGKILL" in err and "--resume" in err, err[-2000:]
    assert len(err.strip().splitlines()) == 1, err  # one line, no traceback
    kept = list_shards(tmp_path)
    assert 1 <= len(kept) < 8 and f"{len(kept)} complete shard(s) kept" in err
    assert not [p for p in tmp_path.iterdir() if ".tmp-" in p.name]
    render(*args, "--resume")
    assert len(list_shards(tmp_path)) == 8


def test_cluster_split_covers_every_shard_once(tmp_path):
    """Jobs of an array job share --out and start in any order, without --resume."""
    for job in (1, 0):
        render("--n", 3, "--shard-size", 1, "--shard-index", job, "--num-shards", 2, "--out", tmp_path, *SMALL)
    assert [p.name for p in list_shards(tmp_path)] == ["shard-00000.h5", "shard-00001.h5", "shard-00002.h5"]
    again = render("--n", 3, "--shard-size", 1, "--shard-index", 1, "--num-shards", 2, "--out", tmp_path, *SMALL, check=False)
    assert again.returncode == 2 and "--resume" in again.stderr


def test_cli_rejects_bad_arguments(tmp_path):
    bad = render("--n", 0, "--out", tmp_path, check=False)
    assert bad.returncode == 2 and "--n must be >= 1" in bad.stderr
    bad = render("--shard-index", 2, "--num-shards", 2, "--out", tmp_path, check=False)
    assert bad.returncode == 2 and "--shard-index" in bad.stderr
    if not any(Path("/dev").glob("nvidia*")):
        bad = render("--n", 1, "--device", "gpu", "--out", tmp_path / "gpu", *SMALL, check=False)
        assert bad.returncode == 2 and "--device cpu" in bad.stderr and not list((tmp_path / "gpu").glob("*.h5"))
    (tmp_path / "board.json").write_text('{"squares_x": 2}')
    bad = render("--board", tmp_path / "board.json", "--out", tmp_path / "x", check=False)
    assert bad.returncode == 2 and "squares_x" in bad.stderr


def test_shadow_probability_sets_the_cast_shadows_and_is_part_of_the_run(tmp_path):
    from datagen.render import RenderJob, scene_config

    board = BoardSpec()

    def shadowed(probability):
        job = RenderJob(n=1, out=str(tmp_path), seed=0, board=board, width=160, height=120, samples=None, shard_size=1,
                        clean=False, device="cpu", threads=1, shadow_p=probability)
        config = scene_config(job)
        scenes = [sample_scene(frame_rng(0, i), board.size_m, config) for i in range(60)]
        lit = [s for s in scenes if any(light.kind != "SUN" for light in s.lights)]  # a shadow needs a lamp
        return config.shadow_p, len(lit), sum(any(shape.role == "shadow-caster" for shape in s.shapes) for s in lit)

    assert shadowed(None)[0] == SceneConfig().shadow_p  # not given: the scene's own
    probability, lit, cast = shadowed(1.0)
    assert probability == 1.0 and lit >= 20 and cast == lit
    assert shadowed(0.0)[2] == 0
    # A run rendered with another shadow probability is not resumed into.
    render("--n", 1, "--shard-size", 1, "--out", tmp_path / "run", *SMALL, "--shadow-probability", 0.9)
    other = render("--n", 1, "--shard-size", 1, "--out", tmp_path / "run", *SMALL, "--resume", check=False)
    assert other.returncode != 0 and "shadow_probability" in other.stderr
    bad = render("--shadow-probability", 1.5, "--out", tmp_path / "bad", check=False)
    assert bad.returncode == 2 and "--shadow-probability must be in [0, 1]" in bad.stderr


def test_inspect_writes_a_mosaic(reference, tmp_path, capsys):
    out, _ = reference
    assert inspect_main([str(out), "--out", str(tmp_path), "--frames", "4", "--columns", "2"]) == 0
    printed = capsys.readouterr().out
    assert "6 frames in 3 shard(s)" in printed and "lux" in printed
    import cv2

    mosaic = cv2.imread(str(tmp_path / "mosaic.png"))
    assert mosaic.shape == (240, 320, 3)
    assert (tmp_path / "histograms.png").stat().st_size > 1000
    assert inspect_main([str(tmp_path / "empty")]) == 2
