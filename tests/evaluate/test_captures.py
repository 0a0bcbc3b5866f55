"""Real capture sets (evaluate.captures): the folder reader's refusals, lazy video frames, the metrics on a
synthetic capture folder whose answers are known, truth from labels and auto-labelling, the report section."""

import csv
from pathlib import Path

import cv2
import numpy as np
import pytest

from deepcharuco import BoardSpec, Camera, Detection, OpenCVDetector, project_corners, write_camera
from deepcharuco.boards.synthetic import look_at_pose, render_board_view
from evaluate import documents
from evaluate.captures import (
    CaptureError, evaluate_capture_set, evaluate_captures, open_capture_set, report_folders, sample_folders,
)
from evaluate.captures import reader
from evaluate.captures.truth import build_truth
from evaluate.paper.protocols import motion_blur
from conftest import VIEW_POSES

BOARD = BoardSpec()
CAMERA = Camera.from_fov(320, 240, hfov_deg=60.0)
BLUR_PX = 14  # a horizontal blur OpenCV finds no board in (it fails from k = 8 on the paper's board)


def view(board, pose):
    rvec, tvec = look_at_pose(board, **pose)
    return render_board_view(board, CAMERA.K, rvec, tvec, CAMERA.image_size), project_corners(board, rvec, tvec, CAMERA.K)


class Oracle:
    """Returns the true corners of the images it was given (by content), nothing for any other image."""

    def __init__(self, truth: dict[bytes, np.ndarray]):
        self.truth = truth

    def detect(self, image):
        corners = self.truth.get(image.tobytes())
        if corners is None:
            return Detection.empty()
        ids = np.arange(len(corners))
        return Detection(ids, corners, np.ones(len(ids), np.float32))


class Edited:
    """OpenCV's detection, edited: every other corner dropped (``drop``) or two far-apart IDs swapped."""

    def __init__(self, board, how):
        self.opencv, self.how = OpenCVDetector(board), how

    def detect(self, image):
        d = self.opencv.detect(image)
        if len(d) < 2:
            return d
        if self.how == "drop":
            return Detection(d.ids[::2], d.corners[::2], d.scores[::2])
        ids = d.ids.copy()
        ids[[0, -1]] = ids[[-1, 0]]
        return Detection(ids, d.corners, d.scores)


@pytest.fixture(scope="module")
def capture_folder(tmp_path_factory):
    """3 clean views, 1 strongly blurred view (OpenCV misses it), 1 blank frame, board.yaml; the true corners
    by image content."""
    folder = tmp_path_factory.mktemp("captures") / "desk"
    folder.mkdir()
    truth, names = {}, {}
    for i, pose in enumerate(VIEW_POSES[:4]):
        image, corners = view(BOARD, pose)
        if i == 3:
            image = motion_blur(image, BLUR_PX)[0]  # a box blur centred on each pixel: corners stay put
        name = f"view{i}.png"
        cv2.imwrite(str(folder / name), image)
        truth[cv2.imread(str(folder / name), cv2.IMREAD_GRAYSCALE).tobytes()] = corners.astype(np.float32)
        names[name] = corners
    cv2.imwrite(str(folder / "zblank.png"), np.full((240, 320), 90, np.uint8))
    BOARD.save(folder / "board.yaml")
    return folder, truth, names


def test_refuses_a_folder_without_board_yaml(tmp_path):
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((20, 20), np.uint8))
    with pytest.raises(CaptureError, match="has no board.yaml: write the board there"):
        open_capture_set(tmp_path)
    with pytest.raises(CaptureError, match="does not exist"):
        open_capture_set(tmp_path / "nowhere")


def test_refuses_unreadable_media(tmp_path):
    BOARD.save(tmp_path / "board.yaml")
    (tmp_path / "clip.mp4").write_bytes(b"not a video at all" * 100)
    with pytest.raises(CaptureError, match=r"cannot read the video .*clip.mp4: .*re-encode it"):
        open_capture_set(tmp_path)
    (tmp_path / "clip.mp4").unlink()
    (tmp_path / "photo.png").write_bytes(b"\x89PNG broken")
    with pytest.raises(CaptureError, match=r"cannot read the photo .*photo.png"):
        open_capture_set(tmp_path)


@pytest.mark.parametrize("written, hint", [
    (dict(inverted=True), "with inverted: false it finds it in 2 of the first 2"),
    (dict(squares_x=7, squares_y=5), "with squares_x: 5, squares_y: 7 it finds it in 2 of the first 2"),
])
def test_refuses_a_board_no_frame_matches_and_names_the_one_that_does(tmp_path, written, hint):
    board = BoardSpec(squares_x=5, squares_y=7, square_length=0.03, marker_length=0.022, dictionary="DICT_4X4_50")
    for i, pose in enumerate(VIEW_POSES[:2]):
        cv2.imwrite(str(tmp_path / f"v{i}.png"), view(board, dict(pose, distance=pose["distance"] * 1.4))[0])
    BoardSpec(**{**board.to_dict(), **written}).save(tmp_path / "board.yaml")
    with pytest.raises(CaptureError) as error:
        open_capture_set(tmp_path)
    message = str(error.value)
    assert "none of the first 2 frames" in message and hint in message and "\n" not in message, message
    # Nothing OpenCV can find: still refused, and the message says what to check.
    BoardSpec(**{**board.to_dict(), "dictionary": "DICT_6X6_50"}).save(tmp_path / "board.yaml")
    with pytest.raises(CaptureError, match="check its dictionary, squares and marker_length"):
        open_capture_set(tmp_path)


def test_video_frames_are_read_lazily(tmp_path, monkeypatch):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 48), False)
    for i in range(20):
        writer.write(np.full((48, 64), 10 * i, np.uint8))  # frame i is grey 10 i
    writer.release()
    calls = {"read": 0, "grab": 0}

    opened = cv2.VideoCapture

    class Counting:  # wraps OpenCV's capture (a subclass of it crashes the interpreter at exit)
        def __init__(self, *args):
            self.capture = opened(*args)

        def isOpened(self):
            return self.capture.isOpened()

        def read(self):
            calls["read"] += 1
            return self.capture.read()

        def grab(self):
            calls["grab"] += 1
            return self.capture.grab()

        def get(self, prop):
            return self.capture.get(prop)

        def release(self):
            self.capture.release()

    monkeypatch.setattr(reader.cv2, "VideoCapture", Counting)
    frames = reader.video_frames(path, step=3, limit=4)
    assert calls == {"read": 0, "grab": 0}  # nothing read before the first frame is asked for
    index, first = next(frames)
    assert index == 0 and calls == {"read": 1, "grab": 0} and first.shape == (48, 64)
    rest = list(frames)
    assert [i for i, _ in rest] == [3, 6, 9] and calls == {"read": 4, "grab": 6}  # frames 1, 2, 4, 5, 7, 8 skipped
    assert [round(float(f.mean()) / 10) for _, f in rest] == [3, 6, 9]


def test_metrics_on_a_synthetic_capture_folder(capture_folder):
    folder, truth, _ = capture_folder
    captures = open_capture_set(folder)
    detectors = {"opencv": OpenCVDetector(BOARD), "oracle": Oracle(truth), "drop": Edited(BOARD, "drop"),
                 "swap": Edited(BOARD, "swap")}
    result, gallery = evaluate_capture_set(captures, detectors, gallery=2)
    assert result["truth"] == "none" and [f["frame"] for f in result["frames"]] == [
        "view0.png", "view1.png", "view2.png", "view3.png", "zblank.png"]
    found = [OpenCVDetector(BOARD).detect(cv2.imread(str(folder / f"view{i}.png"), 0)) for i in range(3)]
    assert all(len(d) >= 6 for d in found)
    cv, oracle, drop, swap = (result["detectors"][n] for n in ("opencv", "oracle", "drop", "swap"))
    assert (cv["frames"], cv["found"], cv["verified"], cv["reference_frames"]) == (5, 3, 3, 3)
    assert cv["corners"] == sum(len(d) for d in found) and oracle["corners"] == sum(len(c) for c in truth.values())
    assert cv["accuracy_vs_opencv"] == 1.0 and cv["wrong_ids"] == 0 and cv["mean_eps_re"] is None  # no camera
    # The true corners: every frame with a board found and verified, one that OpenCV misses, all within 3 px.
    assert (oracle["found"], oracle["verified"], oracle["only_this"], oracle["only_opencv"]) == (4, 4, 1, 0)
    assert oracle["accuracy_vs_opencv"] == 1.0 and oracle["wrong_ids"] == 0 and oracle["median_px_vs_opencv"] < 0.2
    # Every other corner dropped: half of OpenCV's corners (rounded up) agree.
    expected = np.mean([len(d.ids[::2]) / len(d) for d in found])
    assert drop["accuracy_vs_opencv"] == pytest.approx(expected) and drop["wrong_ids"] == 0
    assert drop["verified"] == sum(len(d.ids[::2]) >= 6 for d in found)
    # Two IDs swapped in each frame: 2 wrong IDs a frame, the rest agree, the view still verified by the others.
    assert (swap["wrong_ids"], swap["wrong_id_frames"], swap["verified"]) == (6, 3, 3)
    assert swap["accuracy_vs_opencv"] == pytest.approx(np.mean([(len(d) - 2) / len(d) for d in found]))
    # The gallery: the frames where they disagree most, reduced no further than the frame, drawn per detector.
    assert len(gallery) == 2 and gallery[0].score >= gallery[1].score > 0 and "view3.png" in [g.name for g in gallery]
    assert gallery[0].image.shape == (240, 320) and set(gallery[0].detections) == set(detectors)


def test_camera_labels_and_review(capture_folder, tmp_path):
    """With camera.yaml a verified view is a PnP pose; labels.csv is the truth (the paper's metrics); the review
    counts the frames OpenCV missed per verdict."""
    source, truth, names = capture_folder
    folder = tmp_path / "labelled"
    folder.mkdir()
    for path in source.iterdir():
        (folder / path.name).write_bytes(path.read_bytes())
    write_camera(folder / "camera.yaml", CAMERA)
    with open(folder / "labels.csv", "w", newline="") as handle:
        rows = csv.writer(handle)
        rows.writerow(["frame", "id", "x", "y"])
        for name, corners in names.items():
            rows.writerows([name, i, x, y] for i, (x, y) in enumerate(corners))
    (folder / "frames_review.csv").write_text("# by eye\nframe,board_visible,note\nview3.png,yes,blurred\n"
                                              "zblank.png,no,empty desk\n")
    result, _ = evaluate_capture_set(open_capture_set(folder), {"opencv": OpenCVDetector(BOARD), "oracle": Oracle(truth)})
    cv, oracle = result["detectors"]["opencv"], result["detectors"]["oracle"]
    assert result["truth"] == "labels" and result["camera"]
    assert oracle["verified"] == 4 and oracle["mean_eps_re"] < 0.01 and cv["verified"] == 3 and cv["mean_eps_re"] < 0.2
    assert oracle["truth"] == {"frames": 4, "corner_accuracy": 1.0, "pose_accuracy": 1.0, "confidently_wrong": 0}
    assert cv["truth"] == {"frames": 4, "corner_accuracy": 0.75, "pose_accuracy": 0.75, "confidently_wrong": 0}
    assert cv["review"] == {"no": [0, 1], "yes": [0, 1]} and oracle["review"] == {"no": [0, 1], "yes": [1, 1]}


def test_a_still_video_is_auto_labelled(tmp_path):
    image, corners = view(BOARD, VIEW_POSES[1])
    rng = np.random.default_rng(3)
    writer = cv2.VideoWriter(str(tmp_path / "still.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 10, CAMERA.image_size, False)
    for _ in range(32):
        writer.write(np.clip(image + rng.normal(0, 4, image.shape), 0, 255).astype(np.uint8))
    writer.release()
    BOARD.save(tmp_path / "board.yaml")
    write_camera(tmp_path / "camera.yaml", CAMERA)
    truth = build_truth(open_capture_set(tmp_path))
    assert truth.kind == "autolabel" and "still.avi: auto-labelled" in truth.description
    labels = truth.by_medium["still.avi"]
    assert np.abs(labels.corners[labels.visible] - corners[labels.visible]).max() < 0.3
    (tmp_path / "camera.yaml").unlink()  # no camera: no pose, so no auto-labels, and the report says why
    truth = build_truth(open_capture_set(tmp_path))
    assert truth.kind == "none" and "still.avi: no camera file" in truth.description


def test_the_report_section_and_the_shipped_sample(capture_folder, tmp_path, capsys):
    folder = tmp_path / "desk"  # two frames of the synthetic folder: the deep detectors run on each
    folder.mkdir()
    for name in ("board.yaml", "view0.png", "zblank.png"):
        (folder / name).write_bytes((capture_folder[0] / name).read_bytes())
    (tmp_path / "README.md").write_text("a file a shell glob picks up")
    results, pictures = evaluate_captures([folder, tmp_path / "README.md"], gallery=1)
    assert "skipping" in capsys.readouterr().err and results["skipped"] == [str(tmp_path / "README.md")]
    [entry] = results["sets"]
    assert set(entry["detectors"]) >= {"opencv", "deep"} and len(pictures) == 1
    jpeg = next(iter(pictures.values()))
    assert jpeg[:3] == b"\xff\xd8\xff" and cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR).shape[1] >= 640
    page = documents.html_page("r", "cmd", documents.sections({"real_captures": results, "notes": []}), pictures)
    assert "Real captures" in page and page.count("data:image/jpeg;base64,") == 1
    (tmp_path / "r").mkdir()
    documents.write_markdown(tmp_path / "r" / "report.md", {"real_captures": results, "notes": []}, pictures)
    assert f"| desk | OpenCV + cornerSubPix | 2 | {entry['detectors']['opencv']['corners']} | 1 | 1 |" in (tmp_path / "r" / "report.md").read_text()
    assert list((tmp_path / "r" / "figures").glob("*.jpg"))
    # The shipped sample: what `make demo` shows with no other captures at hand; every set opens, with its licence notice.
    assert report_folders(None) == (None, sample_folders()) and len(sample_folders()) >= 2
    for sample in sample_folders():
        open_capture_set(sample)
        assert (sample / "SOURCE.txt").is_file() and "licen" in (sample / "SOURCE.txt").read_text().lower()
    assert report_folders(["x"], disabled=False) == (None, [Path("x")])
    with pytest.raises(CaptureError, match="contradict"):
        report_folders(["x"], disabled=True)


def _labelled_copy(source: Path, folder: Path, rows: list[list]) -> Path:
    folder.mkdir()
    for path in source.iterdir():
        (folder / path.name).write_bytes(path.read_bytes())
    with open(folder / "labels.csv", "w", newline="") as handle:
        csv.writer(handle).writerows([["frame", "id", "x", "y"], *rows])
    return folder


def test_labels_of_frames_that_are_not_in_the_set_are_refused_or_said(capture_folder, tmp_path, capsys):
    source, _, names = capture_folder
    corners = names["view0.png"]
    only_foreign = _labelled_copy(source, tmp_path / "a", [["view9.png", i, x, y] for i, (x, y) in enumerate(corners)])
    with pytest.raises(CaptureError, match=r"labels 1 frame\(s\), none of them in .*'view9.png'.*<video file name>#"):
        build_truth(open_capture_set(only_foreign))
    mixed = _labelled_copy(source, tmp_path / "b", [[name, i, x, y] for name in ("view0.png", "view9.png", "clip.mp4#3")
                                                    for i, (x, y) in enumerate(corners)])
    truth = build_truth(open_capture_set(mixed))
    assert truth.notes[0] == "labels.csv: 1 labelled frames" and list(truth.by_frame) == ["view0.png"]
    assert truth.notes[1].startswith("2 labelled frame(s) are not in the set and are ignored")
    assert "warning:" in capsys.readouterr().err


def test_a_capture_photo_is_read_as_detect_reads_it(tmp_path):
    from deepcharuco.cli.sources import eight_bits
    from evaluate.captures.reader import CaptureError, read_image

    twelve = np.random.default_rng(0).integers(0, 4001, (24, 32), dtype=np.uint16)  # a 12-bit sensor's data as it comes
    cv2.imwrite(str(tmp_path / "a.png"), twelve)
    np.testing.assert_array_equal(read_image(tmp_path / "a.png"), eight_bits(twelve, "a.png"))
    assert read_image(tmp_path / "a.png").max() > 200  # not its top 8 of 16 bits (<= 15)
    cv2.imwrite(str(tmp_path / "b.tiff"), twelve.astype(np.float32))
    with pytest.raises(CaptureError, match="b.tiff is a float32 image .* or remove it from the folder"):
        read_image(tmp_path / "b.tiff")
