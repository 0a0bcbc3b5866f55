"""How this sample was made from the published captures (``python -m evaluate.captures_sample.make_sample
REALDATA``, where REALDATA holds the folders described in each set's SOURCE.txt; not needed to use it).

caliscope_cam1: frames of caliscope's cam_1.mp4 decoded by OpenCV, converted to grey and saved as JPEG
(quality 90), with camera_cam_1.yaml as camera.yaml and the by-eye verdicts of those frames; opencv_tutorial:
the photos as published (choriginal.jpg is left out: it is calib_img_01.jpg byte for byte);
``evaluate/calibration/caliscope_rig`` (beside the rig's evaluations, not a capture set: it holds no frames): the
deep detector's corners (shipped weights, refinenet) in every frame of caliscope's four synchronised videos
(``detections.npz``: per camera c, ``counts_c`` corners per frame, ``ids_c`` and ``corners_c`` concatenated) with
their camera files, for the time alignment's tests (the videos themselves are 11 MB).
"""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import cv2
import numpy as np

from evaluate.captures.reader import video_frames

HERE = Path(__file__).resolve().parent
# Frames of cam_1 (6 fps): the board lying clipped at the image edge (40), found by OpenCV (64, 86, 104),
# hand-held in glare where OpenCV finds nothing though the board is visible by eye (66, 82), and found in
# part (80, 84). Few, so that the default report's real-captures section costs well under a minute.
CAM1_FRAMES = (40, 64, 66, 80, 82, 84, 86, 104)
TUTORIAL_PHOTOS = ("calib_img_00.jpg", "calib_img_01.jpg", "calib_img_03.jpg", "chocclusion_original.jpg")


def main(realdata: Path) -> None:
    for old in HERE.glob("*/*.jpg"):  # SOURCE.txt and LICENCE stay
        old.unlink()
    source, out = realdata / "caliscope_calibration", HERE / "caliscope_cam1"
    out.mkdir(exist_ok=True)
    shutil.copyfile(source / "board.yaml", out / "board.yaml")
    shutil.copyfile(source / "camera_cam_1.yaml", out / "camera.yaml")
    for index, image in video_frames(source / "cam_1.mp4", 1, max(CAM1_FRAMES) + 1):
        if index in CAM1_FRAMES:
            cv2.imwrite(str(out / f"cam_1_f{index:05d}.jpg"), image, [cv2.IMWRITE_JPEG_QUALITY, 90])
    wanted = {f"cam1_f{i:05d}.png": f"cam_1_f{i:05d}.jpg" for i in CAM1_FRAMES}
    lines = (source / "frames_review.csv").read_text().splitlines()
    kept = [line for line in lines if line.startswith("#") or line.startswith("frame,")]
    kept += [wanted[line.split(",")[0]] + line[line.index(","):] for line in lines if line.split(",")[0] in wanted]
    (out / "frames_review.csv").write_text("\n".join(kept) + "\n")
    source, out = realdata / "opencv_tutorial", HERE / "opencv_tutorial"
    out.mkdir(exist_ok=True)
    for name in TUTORIAL_PHOTOS + ("board.yaml", "camera.yaml"):
        shutil.copyfile(source / name, out / name)

    rig_detections(realdata / "caliscope_calibration", HERE.parent / "calibration" / "caliscope_rig")


def rig_detections(source: Path, out: Path) -> None:
    """caliscope_rig (module docstring): every frame of cam_0..cam_3.mp4 through the deep detector."""
    from deepcharuco.boards.board import BoardSpec
    from deepcharuco.detection.deep_detector import Detector

    out.mkdir(exist_ok=True)
    detector = Detector(board=BoardSpec.load(source / "board.yaml"), refine="refinenet")
    arrays = {}
    for c in range(4):
        found = [detector.detect(image) for _, image in video_frames(source / f"cam_{c}.mp4", 1, None)]
        arrays[f"counts_{c}"] = np.array([len(d.ids) for d in found], np.int32)
        arrays[f"ids_{c}"] = np.concatenate([np.asarray(d.ids, np.int16) for d in found])
        arrays[f"corners_{c}"] = np.concatenate([np.asarray(d.corners, np.float32).reshape(-1, 2) for d in found])
        shutil.copyfile(source / f"camera_cam_{c}.yaml", out / f"camera_cam_{c}.yaml")
    shutil.copyfile(source / "board.yaml", out / "board.yaml")
    np.savez_compressed(out / "detections.npz", **arrays)


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python -m evaluate.captures_sample.make_sample REALDATA (the folder of the published sets)")
    main(Path(sys.argv[1]))
