import contextlib
import importlib.util
import os
import re
import signal
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from deepcharuco import BoardSpec, Camera, project_corners
from deepcharuco.boards.synthetic import look_at_pose, render_board_view
from deepcharuco.core.detection import Detection
from deepcharuco.detection.tracking import search_region

ROOT = Path(__file__).resolve().parents[1]  # the repository; tests sit in tests/<subpackage>/

def shipped_backends() -> list[str]:
    """The backends the shipped weights run on: PyTorch, ONNX Runtime (their bundles), and int8 ONNX Runtime
    where the shipped checkpoints carry an accepted int8 ChArUcoNet (none in this version)."""
    from deepcharuco.networks.runtime import int8_model
    from deepcharuco.networks.shipped import DEFAULT_WEIGHTS, FAMILY_WEIGHTS_DIR

    weights = [DEFAULT_WEIGHTS, *sorted(FAMILY_WEIGHTS_DIR.glob("*.pt"))]
    int8 = any(int8_model(torch.load(path, map_location="cpu", weights_only=False)) for path in weights)
    return ["torch", "onnx"] + (["onnx-int8"] if int8 else [])


@pytest.fixture(params=shipped_backends())
def backend(request) -> str:
    """Runs a detector test once per backend of the shipped weights (as Kornia's BaseTester runs per device)."""
    return request.param


# Tests that render with Blender: skipped where the [render] extra (bpy, Python 3.11 only) is not installed.
needs_bpy = pytest.mark.skipif(importlib.util.find_spec("bpy") is None,
                               reason="renders with Blender: needs the [render] extra (bpy)")

# The packages the [dev] extra installs that some tests skip without (as named in the skips' reasons). Where they
# are meant to be there (`make test` and CI set DEEPCHARUCO_REQUIRE_ALL=1), such a skip fails instead: a run on a
# Python where one is missing (bpy has wheels for 3.11 only) must not pass green with the renders untested.
REQUIRE_ALL = os.environ.get("DEEPCHARUCO_REQUIRE_ALL", "") == "1"
DEPENDENCY_SKIP = re.compile(r"\b(bpy|blender|numba|onnxruntime|onnx runtime|onnx|torch|pytorch|reportlab|h5py|skimage|"
                             r"scikit-image|matplotlib|scipy|pillow|PIL|pycolmap|yaml|kubernetes-validate)\b|\bshipped\b.*\bweights\b", re.IGNORECASE)


def _dependency_skip(report) -> str | None:
    """The reason of ``report``'s skip where it is for a missing dependency CI installs (or shipped weights), else
    None."""
    if not (REQUIRE_ALL and report.skipped and isinstance(report.longrepr, tuple)) or hasattr(report, "wasxfail"):
        return None
    reason = str(report.longrepr[2])
    return reason.removeprefix("Skipped: ") if DEPENDENCY_SKIP.search(reason) else None


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    reason = _dependency_skip(report)
    if reason is not None:
        report.outcome = "failed"
        report.longrepr = (f"DEEPCHARUCO_REQUIRE_ALL=1 and this test skipped for a missing dependency: {reason} "
                           f"(install the dev extra: make venv; or unset DEEPCHARUCO_REQUIRE_ALL to allow the skip)")


@pytest.hookimpl(hookwrapper=True)
def pytest_make_collect_report(collector):
    outcome = yield
    report = outcome.get_result()
    reason = _dependency_skip(report)  # a module-level importorskip skips the whole file at collection
    if reason is not None:
        report.outcome = "failed"
        report.longrepr = (f"DEEPCHARUCO_REQUIRE_ALL=1 and {collector.nodeid} skipped for a missing dependency: "
                           f"{reason} (install the dev extra: make venv; or unset DEEPCHARUCO_REQUIRE_ALL)")

@contextlib.contextmanager
def process_group(command: list[str], **popen):
    """``subprocess.Popen(command, **popen)`` in a process group of its own, which is killed (SIGKILL: the process
    and every child it started, DataLoader and render workers included) when the block ends, however it ends: a
    failed assertion, an exception or Ctrl-C leaves no trainer or renderer running after the test."""
    process = subprocess.Popen(command, start_new_session=True, **popen)
    try:
        yield process
    finally:
        try:
            os.killpg(process.pid, signal.SIGKILL)
        except ProcessLookupError:  # the group is gone: it ended, children and all
            pass
        process.wait()
        for stream in (process.stdin, process.stdout, process.stderr):
            if stream is not None:
                stream.close()


NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")


def assert_same_but_rounding(first: str, second: str, rtol: float = 1e-4, atol: float = 1e-8) -> None:
    """Asserts that two texts (camera and rig files) are the same but for the last digits of their numbers.

    Why: work split over worker processes runs ONNX Runtime on fewer threads than one process does, and its
    convolutions' sums then add in another order. On a 16-core machine (2026-11-26) a calibration from `--jobs 2`
    differed from one process's in fx's 9th significant digit, and 2 of its 769 numbers in their 5th, where a
    solver stops a step sooner or later (one view less would move fx by ~1e-3)."""
    words = NUMBER.split(first), NUMBER.split(second)
    assert words[0] == words[1], f"the texts differ beyond their numbers: {set(words[0]) ^ set(words[1])}"
    a, b = (np.array([float(x) for x in NUMBER.findall(t)]) for t in (first, second))
    off = np.flatnonzero(np.abs(a - b) > atol + rtol * np.abs(b))
    if len(off):
        worst = off[np.argmax(np.abs(a - b)[off])]
        at = list(NUMBER.finditer(first))[worst].start()
        line = first.count("\n", 0, at)
        raise AssertionError(f"{len(off)} of {len(a)} numbers differ, the most {a[worst]} against {b[worst]} "
                             f"(line {line + 1}: {first.splitlines()[line].strip()[:80]})")


# Moderate, varied views: fronto-parallel, tilted both ways, rolled, off-centre.
VIEW_POSES = [
    dict(distance=0.35),
    dict(distance=0.33, tilt_x_deg=30, tilt_y_deg=10, roll_deg=15),
    dict(distance=0.40, tilt_x_deg=-25, tilt_y_deg=30, roll_deg=-40, offset=(0.02, 0.01)),
    dict(distance=0.30, tilt_x_deg=10, tilt_y_deg=-35, roll_deg=90),
    dict(distance=0.45, tilt_x_deg=35, tilt_y_deg=-5, roll_deg=170, offset=(-0.03, 0.0)),
]


@pytest.fixture(scope="session")
def camera() -> Camera:
    return Camera.from_fov(320, 240, hfov_deg=60.0)


def make_view(board: BoardSpec, camera: Camera, **pose):
    """(image, rvec, tvec, true corners (C, 2)) of a synthetic view."""
    rvec, tvec = look_at_pose(board, **pose)
    image = render_board_view(board, camera.K, rvec, tvec, camera.image_size)
    return image, rvec, tvec, project_corners(board, rvec, tvec, camera.K)


@pytest.fixture(scope="session")
def default_views(camera):
    board = BoardSpec()
    return [make_view(board, camera, **pose) for pose in VIEW_POSES]


def network_widths(detector, image: np.ndarray):
    """``detector.detect(image)``, and the widths of the images ChArUcoNet saw for it, in order."""
    widths, run = [], detector.runner.charuconet

    def recording(batch):
        widths.append(batch.shape[-1])
        return run(batch)

    detector.runner.charuconet = recording
    try:
        return detector.detect(image), widths
    finally:
        detector.runner.charuconet = run


def rotation_error_deg(rvec_a: np.ndarray, rvec_b: np.ndarray) -> float:
    ra, _ = cv2.Rodrigues(np.asarray(rvec_a, np.float64))
    rb, _ = cv2.Rodrigues(np.asarray(rvec_b, np.float64))
    cos = (np.trace(ra.T @ rb) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def _can_write(folder) -> bool:
    import tempfile

    try:
        tempfile.TemporaryFile(dir=folder).close()
        return True
    except OSError:
        return False


@pytest.fixture
def unwritable_dir(tmp_path):
    """A folder no file can be created in: a read-only (0o555) folder, or, for root (whom permissions do
    not stop), /proc (nothing can be created there)."""
    from pathlib import Path

    folder = tmp_path / "read-only"
    folder.mkdir()
    folder.chmod(0o555)
    try:
        for candidate in (folder, Path("/proc")):
            if candidate.is_dir() and not _can_write(candidate):
                yield candidate
                break
        else:
            pytest.skip("no folder here refuses writes")
    finally:
        folder.chmod(0o755)


@pytest.fixture
def without_bootstrap(monkeypatch):
    """`calibrate` without its last step, `calibration.terms.bootstrap_std` (20 OpenCV solves: ~60-70 % of a call's
    time), for tests that assert nothing of the deviations. That step only raises `CalibrationResult.std`: the
    camera, terms, weights, views and decisions are bit for bit a full call's (checked 2026-11-28). The tests of the
    deviations keep it (test_calibrate: test_calibration_recovers_the_true_camera,
    test_deviations_are_at_least_the_view_bootstrap_spread; test_calibration_terms: test_views_alike_keep_equal_weights,
    the rational model's test)."""
    monkeypatch.setattr("deepcharuco.calibration.intrinsics.bootstrap_std", lambda *args, **kwargs: {})


@pytest.fixture
def torch_threads():
    """``torch_threads(n)`` sets torch's thread count for one test (ONNX Runtime runners take theirs from it when
    made); the suite's count is restored after the test."""
    before = torch.get_num_threads()
    yield torch.set_num_threads
    torch.set_num_threads(before)


class TrackedOnly:
    """A detector stand-in for a board that only tracking keeps: frame n is an image filled with n; the whole-frame
    search finds the board in frame 1 alone, a crop around it (the frame before's board) in frames 1-20."""

    CORNERS = np.array([[500, 200], [540, 200], [500, 240], [540, 240]], np.float32)

    def detect(self, image, working_size=None, levels=None):
        n, whole = int(image.flat[0]), image.shape == (720, 1280)
        if not 1 <= n <= 20 or (whole and n != 1):
            return Detection.empty()
        origin = np.zeros(2, np.float32) if whole else np.array(search_region(self.CORNERS, (1280, 720))[:2], np.float32)
        return Detection(np.arange(4), self.CORNERS - origin, np.ones(4))


class Numbered:
    """A coarse-to-fine detector's stand-in for a whole video: frame n is an image filled with n (so are its crops);
    the board is in the frames ``present`` and the coarse level alone never reads it (a small board)."""

    CORNERS = np.array([[500, 200], [540, 200], [500, 240], [540, 240]], np.float32)

    def __init__(self, present):
        self.present, self.calls = set(present), []

    def detect(self, image, working_size=None, levels=None):
        n, whole = int(image.flat[0]), image.shape == (720, 1280)
        self.calls.append((n, "coarse" if whole and levels == 1 else "full" if whole else "crop"))
        if n not in self.present or levels == 1:
            return Detection.empty()
        corners = self.CORNERS if whole else self.CORNERS - np.array(search_region(self.CORNERS, (1280, 720))[:2],
                                                                     np.float32)
        return Detection(np.arange(4), corners, np.ones(4))


def video(count):
    """``count`` 1280x720 frames for `Numbered` and `TrackedOnly`: frame n filled with n."""
    return [np.full((720, 1280), n, np.uint8) for n in range(count)]


def moving_video(count):
    """``count`` 1280x720 frames whose pixel (y, x) of frame n is (n, x, y) (uint16): a crop knows its frame and
    origin (`Racing`, test_tracking's `Moving`)."""
    y, x = np.mgrid[0:720, 0:1280].astype(np.uint16)
    return [np.dstack([np.full_like(x, n), x, y]) for n in range(count)]


class Racing:
    """A detector stand-in for a board that moves farther each frame than a crop's margin (`moving_video`'s frames):
    found in whole frames 0 and 1 only, and in a crop only where the crop holds all of it, so a tracker keeps it only
    where it expects the board where it moves on to."""

    CORNERS = np.array([[100, 200], [140, 200], [100, 240], [140, 240], [180, 240]], np.float32)
    STEP = np.array([90, 20], np.float32)  # a crop's margin is 2 corner spacings (80 px) here

    def board(self, n):
        return self.CORNERS + n * self.STEP

    def detect(self, image, expected=None):
        n, x0, y0 = (int(v) for v in image[0, 0])
        corners = self.board(n) - np.array([x0, y0], np.float32)
        inside = (corners >= 0).all() and (corners < [image.shape[1], image.shape[0]]).all()
        if (image.shape[:2] == (720, 1280) and n > 1) or not inside:
            return Detection.empty()
        return Detection(np.arange(5), corners, np.ones(5))
