"""A calibrated rig's files: one OpenCV FileStorage camera file per camera and a TOML of the whole rig.

Each camera file holds `write_camera`'s nodes (``camera_matrix``, ``distortion_coefficients``, ``image_width``,
``image_height``: what `read_camera` and OpenCV read), then the camera's pose in the rig's frame
(``rotation_matrix`` R and ``translation_vector`` t in metres, x_cam = R X + t), its RMS, the parameters'
standard deviations and the views used. The TOML (`rig_toml`) has anipose's and caliscope's layout: one
``[cam_N]`` table per camera with ``name``, ``size``, ``matrix``, ``distortions``, ``rotation`` (a rotation
vector, ``cv2.Rodrigues``) and ``translation`` (metres), the same x_cam = R X + t convention; a camera of OpenCV's
fisheye model has ``fisheye = true`` (anipose's key) and its k1..k4 as ``distortions``.
"""

from __future__ import annotations

import json

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.calibration.rig_model import RigResult
from deepcharuco.geometry.camera import camera_file_text

TOML_START = "# deepcharuco rig calibration"


def rig_camera_text(result: RigResult, camera: int, boards: list[BoardSpec], detector: str, frame: str,
                    name: str = "camera.yaml", network: str | None = None) -> str:
    """Camera ``camera``'s file. ``frame`` says what the rig's frame is (e.g. "camera cam_0"); ``boards``: the
    board (a list of the boards, where several are); ``network``: the deep or hybrid detector's networks."""
    std = result.std[camera]

    def nodes(storage: cv2.FileStorage) -> None:
        if result.cameras[camera].model == "pinhole":  # camera_file_text names the fisheye model itself
            storage.write("distortion_model", "pinhole" if result.cameras[camera].dist.size <= 5 else "rational")
        storage.write("rotation_matrix", result.rotations[camera])
        storage.write("translation_vector", result.translations[camera].reshape(3, 1))
        storage.write("rig_frame", frame)
        storage.write("rig_cameras", " ".join(result.names))
        storage.write("avg_reprojection_error", float(result.camera_rms(camera)))
        storage.write("nr_of_frames", result.camera_views(camera))
        if std:
            storage.write("std_names", " ".join(std))
            storage.write("std_values", np.array(list(std.values()), np.float64).reshape(-1, 1))
        storage.write("distortion_terms", result.terms[camera] or "held (the camera's own calibration, or --camera)")
        storage.write("view_frames", np.array([v.instant for v in result.views if v.camera == camera],
                                              np.int32).reshape(-1, 1))
        storage.write("detector", detector)
        if network:
            storage.write("network", network)
        storage.write("board", json.dumps(boards[0].to_dict() if len(boards) == 1 else [b.to_dict() for b in boards]))

    return camera_file_text(result.cameras[camera], name, extra=nodes)


def _numbers(values) -> str:
    return "[" + ", ".join(repr(float(v)) for v in values) + "]"


def rig_toml(result: RigResult, frame: str) -> str:
    """The whole rig as TOML (module docstring): readable by anipose/caliscope-style tools and ``tomllib``."""
    lines = [f"{TOML_START}: x_cam = R X + t, rotation = cv2.Rodrigues(R), translation in metres,",
             f"# X in the rig's frame ({frame}); OpenCV pixels and distortion (k1 k2 p1 p2 k3 [k4 k5 k6]; a camera",
             "# with fisheye = true: cv2.fisheye's k1 k2 k3 k4, as anipose writes it).", ""]
    for c, camera in enumerate(result.cameras):
        rotation = cv2.Rodrigues(result.rotations[c])[0].ravel()
        lines += [f"[cam_{c}]", f'name = "{result.names[c]}"', f"size = [{camera.image_size[0]}, {camera.image_size[1]}]",
                  "matrix = [" + ", ".join(_numbers(row) for row in camera.K) + "]",
                  f"distortions = {_numbers(camera.dist)}", f"rotation = {_numbers(rotation)}",
                  f"translation = {_numbers(result.translations[c])}",
                  *(["fisheye = true"] if camera.model == "fisheye" else []),
                  f"error = {float(result.camera_rms(c))!r}", f"views = {result.camera_views(c)}", ""]
    lines += ["[metadata]", f'frame = "{frame}"', f"rms_px = {result.rms!r}", f"instants = {len(result.board_poses)}", ""]
    return "\n".join(lines)


def is_rig_toml(path) -> bool:
    with open(path, encoding="utf-8") as handle:
        return handle.read(len(TOML_START)) == TOML_START
