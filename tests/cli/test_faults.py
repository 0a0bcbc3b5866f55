"""Faults a user meets with `detect` and `calibrate`: a full disk, a foreign --out, two runs on one file, Ctrl-C,
a video damaged mid-stream, impossible options. Each: one clear line, the right exit code, and no file lost."""

import json
import resource
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

import deepcharuco.cli.calibrate as calibrate_cli
import deepcharuco.cli.detect as detect_cli
from conftest import ROOT, VIEW_POSES, make_view
from deepcharuco import BoardSpec, read_camera
from deepcharuco.cli.video import VideoFrames
from deepcharuco.core.files import OutputError, OutputLock, write_atomic
from test_calibrate import SIZE, waved  # noqa: F401 (the waved-board video's frames, a fixture)

EXAMPLES = ROOT / "deepcharuco" / "examples"


def _limited(limit: int):
    """A child's preexec_fn: files it writes may not grow past ``limit`` bytes (a full disk, as a write sees it;
    Python ignores SIGXFSZ, so the write fails with EFBIG)."""
    return lambda: resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))


def _command(module: str, *args: str, limit: int | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", module, *args], capture_output=True, text=True, cwd=ROOT,
                          preexec_fn=_limited(limit) if limit else None)


def _write_video(path: Path, images: list[np.ndarray], fourcc: str = "mp4v") -> Path:
    height, width = images[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 30.0, (width, height))
    for image in images:
        writer.write(image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR))
    writer.release()
    return path


def _damage(path: Path, start: float = 0.35, stop: float = 0.38, seed: int = 5) -> Path:
    """Overwrite bytes ``start``..``stop`` of the file (shares of its length) with seeded noise: a stretch of frames
    in the middle that no decoder reads, the container (at the ends) intact."""
    data = bytearray(path.read_bytes())
    a, b = int(len(data) * start), int(len(data) * stop)
    data[a:b] = np.random.default_rng(seed).integers(0, 256, b - a, dtype=np.uint8).tobytes()
    damaged = path.with_name(f"damaged_{path.name}")
    damaged.write_bytes(bytes(data))
    return damaged


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if ".tmp-" in p.name or p.name.endswith(".lock"))


# ------------------------------------------------------------------------------------------ atomic files

def test_a_failed_write_leaves_the_previous_file_and_no_temporary(tmp_path):
    path = tmp_path / "results.json"
    path.write_text("the previous results")
    code = ("import sys; from deepcharuco.core.files import write_atomic\n"
            "try:\n    write_atomic(sys.argv[1], 'x' * 100_000)\n"
            "except Exception as error:\n    print(type(error).__name__, error); sys.exit(2)\n")
    done = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, text=True, cwd=ROOT,
                          preexec_fn=_limited(10_000))
    assert done.returncode == 2 and done.stdout.startswith("OutputError could not write")
    assert "the previous file is unchanged" in done.stdout
    assert path.read_text() == "the previous results" and _leftovers(tmp_path) == []


def test_an_output_lock_refuses_a_second_writer_and_is_released(tmp_path):
    target = tmp_path / "cam.yaml"
    with OutputLock(target, "another calibrate"):
        with pytest.raises(OutputError, match=r"another calibrate is writing .*cam.yaml now \(process \d+\)"):
            with OutputLock(target, "another calibrate"):
                pass
    assert _leftovers(tmp_path) == []
    with OutputLock(target):  # free again
        write_atomic(target, "ok")
    assert target.read_text() == "ok"


# ------------------------------------------------------------------------------------------ calibrate

@pytest.fixture(scope="module")
def wave_video(tmp_path_factory, waved):  # noqa: F811
    return _write_video(tmp_path_factory.mktemp("wave") / "wave.mp4", waved[0])


@pytest.fixture(scope="module")
def short_video(tmp_path_factory, waved):  # noqa: F811
    """Every third frame of the waved board (20 of 60, spread over its path): a calibration of its own in a third of
    the time, for the tests of what is written, not of the numbers."""
    return _write_video(tmp_path_factory.mktemp("short") / "short.mp4", waved[0][::3])


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory, short_video):
    """A finished calibration: (folder, camera file, report), made by the command itself."""
    folder = tmp_path_factory.mktemp("calibrated")
    out = folder / "cam.yaml"
    assert calibrate_cli.main([str(short_video), "--out", str(out), "--quiet"]) == 0
    return folder, out, folder / "cam_report.html"


def test_calibrate_onto_a_full_disk_keeps_the_previous_camera_file_and_report(calibrated, short_video):
    folder, out, report = calibrated
    before = out.read_bytes(), report.read_bytes()
    # 10 kB: the camera file (21 kB from the 20-frame clip, 2026-11-28) cannot be written, nor the report (200 kB)
    done = _command("deepcharuco.cli.calibrate", str(short_video), "--out", str(out), "--quiet", limit=10_000)
    assert done.returncode == 2, done.stderr
    assert "error: could not write" in done.stderr and "Traceback" not in done.stderr
    assert "the previous file is unchanged" in done.stderr
    assert (out.read_bytes(), report.read_bytes()) == before and _leftovers(folder) == []


def test_calibrate_without_report_onto_a_full_disk_writes_nothing(tmp_path, short_video):
    out = tmp_path / "new.yaml"
    done = _command("deepcharuco.cli.calibrate", str(short_video), "--out", str(out), "--no-report", "--quiet", limit=4_000)
    assert done.returncode == 2 and "nothing was written" in done.stderr and "Traceback" not in done.stderr
    assert not out.exists() and _leftovers(tmp_path) == []


def test_calibrate_refuses_to_overwrite_a_file_that_is_not_a_camera_file(tmp_path, short_video, capsys):
    notes = tmp_path / "notes.txt"
    notes.write_text("my notes")
    assert calibrate_cli.main([str(short_video), "--out", str(notes), "--no-report", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: --out {notes} exists and is not a camera file: choose another --out, or pass --force to "
                   f"overwrite it"]
    assert notes.read_text() == "my notes"
    report = tmp_path / "page.html"
    report.write_text("<html>my page</html>")
    assert calibrate_cli.main([str(short_video), "--out", str(tmp_path / "c.yaml"), "--report", str(report),
                               "--quiet"]) == 2
    assert "--report" in capsys.readouterr().err and report.read_text() == "<html>my page</html>"
    assert not (tmp_path / "c.yaml").exists()
    assert calibrate_cli.main([str(short_video), "--out", str(notes), "--no-report", "--quiet", "--force"]) == 0
    assert read_camera(notes).image_size == SIZE


def test_calibrate_refuses_a_report_named_as_the_camera_file(tmp_path, short_video, capsys):
    out = tmp_path / "cam.yaml"
    assert calibrate_cli.main([str(short_video), "--out", str(out), "--report", str(out), "--quiet"]) == 2
    assert "--report and --out both name" in capsys.readouterr().err and not out.exists()


def test_calibrate_may_overwrite_its_own_camera_file(calibrated, short_video):
    _, out, report = calibrated
    assert calibrate_cli.main([str(short_video), "--out", str(out), "--quiet"]) == 0
    assert read_camera(out).image_size == SIZE and report.read_bytes().startswith(calibrate_cli.REPORT_START)


def test_two_calibrations_onto_one_file_the_second_is_refused(tmp_path, short_video, capsys):
    out = tmp_path / "cam.yaml"
    with OutputLock(out, "another calibrate"):  # the first run, still writing
        assert calibrate_cli.main([str(short_video), "--out", str(out), "--quiet"]) == 2
    assert "another calibrate is writing" in capsys.readouterr().err and not out.exists()


def test_calibrate_stopped_by_ctrl_c_says_so_without_a_traceback(calibrated, short_video, monkeypatch, capsys):
    _, out, _ = calibrated
    before = out.read_bytes()

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(calibrate_cli, "calibrate", interrupted)  # Ctrl-C during the solve
    assert calibrate_cli.main([str(short_video), "--out", str(out), "--quiet"]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("stopped: nothing written") and len(err) == 1
    assert out.read_bytes() == before and _leftovers(out.parent) == []


def test_calibrate_reads_past_a_damaged_stretch_of_video(tmp_path, wave_video, capsys):
    damaged = _damage(wave_video, 0.30, 0.36)
    out = tmp_path / "cam.yaml"
    assert calibrate_cli.main([str(damaged), "--out", str(out), "--no-report", "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "could not be decoded and were skipped" in err
    storage = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    frames = storage.getNode("view_frames").mat().ravel()
    storage.release()
    assert frames.max() > 45  # views from past the damage (about frames 18-22 of 60)
    # ... named by their numbers in the recording: none of them is a frame the decoder skipped (they were renumbered
    # from the results' order, so frames after the damage took the skipped frames' numbers)
    skipped = VideoFrames(cv2.VideoCapture(str(damaged)))
    list(skipped)
    lost = {i for first, last in skipped.skipped for i in range(first, last + 1)}
    assert lost and not lost & set(frames.astype(int).tolist())


@pytest.mark.parametrize("module", ["deepcharuco.cli.detect", "deepcharuco.cli.calibrate"])
def test_negative_max_frames_is_refused(module):
    done = _command(module, str(EXAMPLES / "board_320x240.png"), "--max-frames", "-3")
    assert done.returncode == 2 and "--max-frames must be >= 1" in done.stderr


# ------------------------------------------------------------------------------------------ detect

@pytest.fixture(scope="module")
def board_video(tmp_path_factory, camera):
    """111 frames of the default board, slowly moving, as mp4v (inter-frame coded, as phones and webcams write)."""
    board = BoardSpec()
    poses = [VIEW_POSES[i % 3] for i in range(111)]
    images = [make_view(board, camera, **pose)[0] for pose in poses]
    return _write_video(tmp_path_factory.mktemp("video") / "clip.mp4", images)


def test_video_frames_skip_a_damaged_stretch_and_keep_the_frame_numbers(board_video):
    damaged = _damage(board_video)
    frames = VideoFrames(cv2.VideoCapture(str(damaged)))
    numbers = [index for index, _ in frames]
    assert frames.skipped, "the damage must cost frames, or this test tests nothing"
    lost = {i for first, last in frames.skipped for i in range(first, last + 1)}
    assert sorted(set(numbers) | lost) == list(range(111)) and not set(numbers) & lost
    assert numbers[-1] == 110 and len(numbers) == 111 - frames.skipped_frames
    assert "could not be decoded and were skipped" in frames.describe_skipped("clip.mp4")
    whole = VideoFrames(cv2.VideoCapture(str(board_video)))
    assert [i for i, _ in whole] == list(range(111)) and not whole.skipped and whole.describe_skipped("x") == ""


def test_detect_reads_past_a_damaged_stretch_and_says_how_many_frames_it_skipped(tmp_path, board_video, capsys):
    damaged = _damage(board_video)
    out = tmp_path / "out"
    assert detect_cli.main([str(damaged), "--out", str(out), "--no-overlay", "--quiet"]) == 0
    captured = capsys.readouterr()
    result = json.loads((out / f"{damaged.stem}.json").read_text())
    skipped = 111 - len(result["frames"])
    assert 0 < skipped < 20 and result["frames"][-1]["source"] == "110"
    # each frame keeps its number in the recording past the damage, in the JSON and the CSV
    assert [f["frame"] for f in result["frames"]] == [int(f["source"]) for f in result["frames"]]
    rows = (out / f"{damaged.stem}.csv").read_text().splitlines()[1:]
    assert [row.split(",")[0] for row in rows] == [f["source"] for f in result["frames"]]
    assert f"{skipped} undecodable frame(s) skipped" in captured.out
    assert "warning:" in captured.err and result["problems"] and result["complete"]


def test_detect_stopped_by_ctrl_c_writes_what_it_did_marked_incomplete(tmp_path, board_video, monkeypatch, capsys):
    made = detect_cli.make_detector

    class StopsAtThird:
        def __init__(self, detector):
            self.detector, self.board, self.calls = detector, detector.board, 0

        def detect(self, image):
            self.calls += 1
            if self.calls == 3:
                raise KeyboardInterrupt
            return self.detector.detect(image)

        def estimate_pose(self, *args):
            return self.detector.estimate_pose(*args)

    monkeypatch.setattr(detect_cli, "make_detector", lambda *args, **kwargs: StopsAtThird(made(*args, **kwargs)))
    out = tmp_path / "out"
    assert detect_cli.main([str(board_video), "--out", str(out), "--refresh-every", "1", "--quiet"]) == 130
    captured = capsys.readouterr()
    assert "interrupted after 2 frames" in captured.err and "(incomplete: interrupted)" in captured.out
    result = json.loads((out / "clip.json").read_text())
    assert result["complete"] is False and len(result["frames"]) == 2
    assert len((out / "clip.csv").read_text().splitlines()) == 3
    assert cv2.VideoCapture(str(out / "clip_overlay.mp4")).get(cv2.CAP_PROP_FRAME_COUNT) == 2
    assert _leftovers(out) == []


def test_detect_onto_a_full_disk_keeps_the_previous_results(tmp_path):
    image = str(EXAMPLES / "board_320x240.png")
    assert detect_cli.main([image, "--out", str(tmp_path), "--no-overlay", "--quiet"]) == 0
    before = {name: (tmp_path / name).read_bytes() for name in ("board_320x240.csv", "board_320x240.json")}
    done = _command("deepcharuco.cli.detect", image, "--out", str(tmp_path), "--no-overlay", "--quiet", limit=200)
    assert done.returncode == 2 and "error: could not write" in done.stderr and "Traceback" not in done.stderr
    assert {name: (tmp_path / name).read_bytes() for name in before} == before and _leftovers(tmp_path) == []


def test_detect_refuses_to_overwrite_results_it_did_not_write(tmp_path, capsys):
    image = str(EXAMPLES / "board_320x240.png")
    (tmp_path / "board_320x240.csv").write_text("my,own,table\n1,2,3\n")
    assert detect_cli.main([image, "--out", str(tmp_path), "--no-overlay", "--quiet"]) == 2
    assert "exists and is not a detection CSV" in capsys.readouterr().err
    assert (tmp_path / "board_320x240.csv").read_text() == "my,own,table\n1,2,3\n"
    assert not (tmp_path / "board_320x240.json").exists()
    assert detect_cli.main([image, "--out", str(tmp_path), "--no-overlay", "--quiet", "--force"]) == 0
    assert detect_cli.main([image, "--out", str(tmp_path), "--no-overlay", "--quiet"]) == 0  # its own: overwritten


def test_detect_replaces_only_the_overlays_it_wrote(tmp_path, capsys):
    """A user's own frame_overlay.png in --out (any PNG, here a camera frame) is kept: refused naming --force, and
    nothing written; an overlay detect wrote (its PNG text chunk says so) is replaced by a rerun."""
    image = tmp_path / "frame.png"
    image.write_bytes((EXAMPLES / "board_320x240.png").read_bytes())
    out = tmp_path / "out"
    out.mkdir()
    theirs = cv2.imencode(".png", np.full((40, 60), 128, np.uint8))[1].tobytes()
    (out / "frame_overlay.png").write_bytes(theirs)
    assert detect_cli.main([str(image), "--out", str(out), "--quiet"]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "frame_overlay.png exists and is not a PNG overlay written by deepcharuco detect" in error[0]
    assert "--force" in error[0] and (out / "frame_overlay.png").read_bytes() == theirs
    assert sorted(p.name for p in out.iterdir()) == ["frame_overlay.png"]
    assert detect_cli.main([str(image), "--out", str(out), "--quiet", "--force"]) == 0
    ours = (out / "frame_overlay.png").read_bytes()
    assert ours != theirs and cv2.imdecode(np.frombuffer(ours, np.uint8), cv2.IMREAD_COLOR).shape == (240, 320, 3)
    assert detect_cli.main([str(image), "--out", str(out), "--quiet"]) == 0  # its own overlay: replaced unasked


def test_detect_replaces_only_the_overlay_video_it_wrote(tmp_path, camera, capsys):
    """The overlay MP4 carries the command's mark (a top-level ``free`` box, which players skip: every frame still
    reads back); a user's own clip_overlay.mp4 in --out is kept, refused naming --force, as any PNG overlay is."""
    from deepcharuco.cli.outputs import OVERLAY_MARK
    from deepcharuco.core.files import mp4_mark

    clip = _write_video(tmp_path / "clip.mp4", [make_view(BoardSpec(), camera, **VIEW_POSES[i % 3])[0] for i in range(4)])
    out = tmp_path / "out"
    out.mkdir()
    theirs = clip.read_bytes()  # any MP4 of the user's: here the input itself under the overlay's name
    (out / "clip_overlay.mp4").write_bytes(theirs)
    assert not mp4_mark(OVERLAY_MARK)(out / "clip_overlay.mp4")
    assert detect_cli.main([str(clip), "--out", str(out), "--quiet"]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "clip_overlay.mp4 exists and is not a video overlay written by deepcharuco detect" in error[0]
    assert "--force" in error[0] and (out / "clip_overlay.mp4").read_bytes() == theirs
    assert sorted(p.name for p in out.iterdir()) == ["clip_overlay.mp4"]
    assert detect_cli.main([str(clip), "--out", str(out), "--quiet", "--force"]) == 0
    ours = out / "clip_overlay.mp4"
    assert mp4_mark(OVERLAY_MARK)(ours) and cv2.VideoCapture(str(ours)).get(cv2.CAP_PROP_FRAME_COUNT) == 4
    assert detect_cli.main([str(clip), "--out", str(out), "--quiet"]) == 0  # its own overlay: replaced unasked


def test_mp4_marks_are_read_from_the_box_structure(tmp_path):
    """Only a well-formed MP4 is marked, and only a free box whose whole payload is the mark counts: the mark's text
    elsewhere (inside another box) or a file cut short is not ours."""
    from deepcharuco.core.files import mp4_mark, mp4_marked

    box = lambda kind, payload: (8 + len(payload)).to_bytes(4, "big") + kind + payload  # noqa: E731
    video = tmp_path / "v.mp4"
    video.write_bytes(box(b"ftyp", b"isom0000") + box(b"mdat", b"made by me"))
    mp4_marked(video, "made by me")
    assert mp4_mark("made by me")(video) and not mp4_mark("made by you")(video)
    video.write_bytes(box(b"ftyp", b"isom0000") + box(b"mdat", b"made by me"))  # the text, in another box
    assert not mp4_mark("made by me")(video)
    video.write_bytes(box(b"ftyp", b"isom0000")[:10])
    with pytest.raises(ValueError):
        mp4_marked(video, "made by me")


@pytest.mark.parametrize("hidden, argv, message", [
    ("torch", ["train.charuconet", "--data", "nowhere", "--out", "run"],
     "training needs torch, which is not installed: pip install 'deepcharuco[train]'"),
    ("torch", ["train.pipeline", "--help"], "training needs torch, which is not installed"),
    ("bpy", ["datagen.render", "--n", "2", "--out", "renders", "--quiet"],
     "python -m datagen.render needs bpy, which is not installed: pip install 'deepcharuco[render]'"),
])
def test_a_missing_extra_is_named_before_any_work(tmp_path, hidden, argv, message):
    """``python -m train.X`` with h5py but no torch, ``python -m datagen.render`` with h5py but no bpy (the render
    extra on a Python other than 3.11): one line naming the package and the extra, exit code 2, nothing written
    (they ended in a traceback, the renderer's after its workers had started and told to rerun with --resume)."""
    (tmp_path / "sitecustomize.py").write_text(f"import sys\nsys.modules[{hidden!r}] = None  # as if not installed\n")
    env = {**__import__("os").environ, "PYTHONPATH": f"{tmp_path}:{ROOT}"}
    done = subprocess.run([sys.executable, "-m", *argv], capture_output=True, text=True, cwd=tmp_path, env=env)
    assert done.returncode == 2 and "Traceback" not in done.stderr, done.stderr[-2000:]
    assert done.stderr.strip().splitlines() == [f"error: {done.stderr.strip()[7:]}"] and message in done.stderr
    assert sorted(p.name for p in tmp_path.iterdir() if p.name != "__pycache__") == ["sitecustomize.py"]


def test_calibrate_stopped_by_sigterm_says_so_and_leaves_no_lock(calibrated, short_video, monkeypatch, capsys):
    """SIGTERM during the solve (kill, a scheduler's stop) exited 143 without the ``stopped:`` line the docs promise
    and left the output's .lock file; now it is taken as Ctrl-C is: one line, the camera file as it was, exit 143."""
    import os
    import signal

    _, out, _ = calibrated
    before = out.read_bytes()

    def terminated(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr(calibrate_cli, "calibrate", terminated)
    assert calibrate_cli.main([str(short_video), "--out", str(out), "--quiet"]) == 143
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("stopped (SIGTERM): nothing written")
    assert out.read_bytes() == before and _leftovers(out.parent) == []
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # the command's handler is gone again
