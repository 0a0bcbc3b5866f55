"""A calibration in the files the next tool reads: Kalibr's camchain YAML, one ROS ``camera_info`` YAML per camera,
COLMAP's ``cameras.txt`` with a ``rig_config.json`` for its rig tools, and OpenCV's rectification (`stereo`).

Each writer takes an `ExportRig` (the cameras and their poses x_cam = R X + t, metres, in one frame) and returns the
file's text; a camera a format cannot hold raises `ExportError` naming the camera, the format and the fix
(`check_cameras`). Conventions of each format, and how this project's map onto them:

- Kalibr (``kalibr/camchain.yaml``): ``camera_model: pinhole`` with ``distortion_model: radtan`` (k1 k2 p1 p2: OpenCV's
  with k3 = 0) or ``equidistant`` (OpenCV's fisheye k1..k4); ``intrinsics`` [fu, fv, pu, pv]; ``T_cn_cnm1`` (camera 1
  on) the 4 x 4 transform taking a point in camera n-1's frame into camera n's; OpenCV's pixels.
- ROS (``ros/<name>.yaml``, camera_calibration_parsers' layout): ``plumb_bob`` (k1 k2 p1 p2 k3),
  ``rational_polynomial`` (+ k4 k5 k6) or ``equidistant``; R and P the stereo rectification's for a pair of one model
  and size (``stereo_image_proc``'s input), else R = I and P = [K | 0] (a mono camera); OpenCV's pixels.
- COLMAP (``colmap/cameras.txt``, ``colmap/rig_config.json``): ``OPENCV`` (k1 k2 p1 p2), ``FULL_OPENCV`` (k1 k2 p1 p2
  k3 k4 k5 k6) or ``OPENCV_FISHEYE``; COLMAP puts the centre of the top-left pixel at (0.5, 0.5), so cx and cy are
  OpenCV's + 0.5. ``rig_config.json`` is what ``colmap rig_configurator`` reads: camera 0 the reference sensor, every
  other ``cam_from_rig`` (quaternion [w, x, y, z], translation) from camera 0's frame to its own.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.spatial.transform import Rotation

from deepcharuco.calibration import stereo
from deepcharuco.core.errors import ExportError
from deepcharuco.core.files import contains
from deepcharuco.geometry.camera import Camera

EXPORT_FORMATS = ("kalibr", "ros", "colmap", "opencv")
MARK = "# deepcharuco calibrate --export"
COLMAP_HEADER = ("# Camera list with one line of data per camera:\n#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
                 "# Number of cameras: {count}\n")


@dataclass
class ExportRig:
    """The cameras to export: ``cameras``, ``names``, ``rotations`` (C, 3, 3) and ``translations`` (C, 3) with
    x_cam = R X + t (metres) in one frame, and ``overlaps[c]`` the cameras that shared views with camera c."""

    cameras: list[Camera]
    names: list[str]
    rotations: np.ndarray
    translations: np.ndarray
    overlaps: list[list[int]] = field(default_factory=list)

    @classmethod
    def from_result(cls, result) -> "ExportRig":
        """A solved `RigResult`'s cameras, poses and the pairs that shared instants."""
        overlaps = [sorted({j for pair in result.shared for j in pair if c in pair and j != c})
                    for c in range(len(result.cameras))]
        return cls(list(result.cameras), list(result.names), np.asarray(result.rotations, np.float64),
                   np.asarray(result.translations, np.float64), overlaps)

    @classmethod
    def single(cls, camera: Camera, name: str) -> "ExportRig":
        return cls([camera], [name], np.eye(3)[None], np.zeros((1, 3)), [[]])

    def relative(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) from camera a's frame to camera b's: x_b = R x_a + t."""
        return stereo.relative_pose(self.rotations[a], self.translations[a], self.rotations[b], self.translations[b])


def parse_exports(values: list[str] | None) -> list[str]:
    """The formats ``--export`` names (given any number of times, each one name or a comma list), in
    `EXPORT_FORMATS` order; `ExportError` for a name that is none of them."""
    named = [part.strip().lower() for value in values or [] for part in value.split(",") if part.strip()]
    unknown = [name for name in named if name not in EXPORT_FORMATS]
    if unknown:
        raise ExportError(f"--export {unknown[0]} is not a format written here: give {', '.join(EXPORT_FORMATS)} "
                          f"(any number of them, e.g. --export kalibr,ros)")
    return [name for name in EXPORT_FORMATS if name in named]


# ------------------------------------------------------------------------------------------ each format's model
def _beyond(camera: Camera, count: int) -> bool:
    """Whether any distortion coefficient past the first ``count`` is not 0."""
    return bool(np.any(camera.dist[count:] != 0))


def _refuse(fmt: str, name: str, why: str, fix: str) -> ExportError:
    return ExportError(f"--export {fmt}: {name} {why}; {fix}")


def _no_skew(fmt: str, camera: Camera, name: str) -> None:
    if camera.K[0, 1] != 0:
        raise _refuse(fmt, name, f"has a skewed camera matrix (K[0, 1] = {camera.K[0, 1]:g}), which {fmt} has no "
                      "term for", "calibrate without skew or leave it out")


def kalibr_model(camera: Camera, name: str) -> tuple[str, np.ndarray]:
    """(Kalibr's distortion_model, its coefficients) of the camera: equidistant (fisheye k1..k4) or radtan (k1 k2
    p1 p2, where every further term is 0)."""
    _no_skew("kalibr", camera, name)
    if camera.model == "fisheye":
        return "equidistant", camera.dist
    if _beyond(camera, 4):
        terms = "k3" if not _beyond(camera, 5) else "k3..k6 (the rational model)"
        raise _refuse("kalibr", name, f"has {terms}, which Kalibr's radtan model (k1 k2 p1 p2) has no term for",
                      "calibrate with --model pinhole --fix-k3 (or --model fisheye: Kalibr's equidistant), or leave "
                      "out kalibr")
    return "radtan", np.pad(camera.dist, (0, 4 - min(4, camera.dist.size)))[:4]


def ros_model(camera: Camera, name: str) -> tuple[str, np.ndarray]:
    """(ROS's distortion_model, its coefficients): equidistant, plumb_bob (5) or rational_polynomial (8)."""
    if camera.model == "fisheye":
        return "equidistant", camera.dist
    if _beyond(camera, 8):
        raise _refuse("ros", name, f"has {camera.dist.size} distortion coefficients (thin prism or tilt terms), which "
                      "ROS's models (plumb_bob, rational_polynomial) cannot hold", "calibrate with --model pinhole or "
                      "rational")
    if not _beyond(camera, 5):
        return "plumb_bob", np.pad(camera.dist, (0, 5 - min(5, camera.dist.size)))[:5]
    return "rational_polynomial", np.pad(camera.dist, (0, 8 - camera.dist.size))[:8]


def colmap_model(camera: Camera, name: str) -> tuple[str, np.ndarray]:
    """(COLMAP's model, its parameters) with COLMAP's principal point (OpenCV's + 0.5): OPENCV_FISHEYE, OPENCV
    (no term past p2) or FULL_OPENCV."""
    _no_skew("colmap", camera, name)
    K = camera.K
    start = [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5]
    if camera.model == "fisheye":
        return "OPENCV_FISHEYE", np.array([*start, *camera.dist])
    if _beyond(camera, 8):
        raise _refuse("colmap", name, f"has {camera.dist.size} distortion coefficients (thin prism or tilt terms), "
                      "which COLMAP's FULL_OPENCV cannot hold", "calibrate with --model pinhole or rational")
    if not _beyond(camera, 4):
        return "OPENCV", np.array([*start, *np.pad(camera.dist, (0, 4 - min(4, camera.dist.size)))[:4]])
    return "FULL_OPENCV", np.array([*start, *np.pad(camera.dist, (0, 8 - camera.dist.size))[:8]])


MODELS: dict[str, Callable[[Camera, str], tuple[str, np.ndarray]]] = {
    "kalibr": kalibr_model, "ros": ros_model, "colmap": colmap_model}


def check_cameras(formats: list[str], cameras: list[Camera], names: list[str]) -> None:
    """`ExportError` for the first camera one of ``formats`` cannot hold, or an OpenCV rectification of cameras that
    are not one camera or a pair of one model and size."""
    for fmt in formats:
        for camera, name in zip(cameras, names):
            if fmt in MODELS:
                MODELS[fmt](camera, name)
    if "opencv" in formats:
        if len(cameras) > 2:
            raise ExportError(f"--export opencv is a stereo pair's rectification (or one camera's undistortion); this "
                              f"rig has {len(cameras)} cameras (their OpenCV camera files are written anyway): leave "
                              f"out opencv")
        if len(cameras) == 2:
            stereo.check_pair(cameras[0], cameras[1], (names[0], names[1]))


# ----------------------------------------------------------------------------------------------- the writers
def _number(value: float) -> str:
    """A float every YAML reader reads back as this float (YAML 1.1 wants a '.' before an exponent: 1.0e-05)."""
    text = repr(float(value))
    mantissa, _, exponent = text.partition("e")
    return f"{mantissa}.0e{exponent}" if exponent and "." not in mantissa else text


def _flow(values) -> str:
    return "[" + ", ".join(_number(v) for v in np.asarray(values, np.float64).ravel()) + "]"


def ros_name(name: str) -> str:
    """``name`` as ROS takes a camera name or topic part: letters, digits and underscores."""
    cleaned = re.sub(r"\W", "_", name, flags=re.ASCII)
    return cleaned if cleaned[:1].isalpha() else f"cam_{cleaned}"


def kalibr_camchain(rig: ExportRig) -> str:
    """Kalibr's camchain YAML (module docstring): ``cam0``.. with the camera model, intrinsics, distortion,
    resolution, rostopic ``/<name>/image_raw``, and from ``cam1`` on ``T_cn_cnm1`` and ``cam_overlaps``."""
    lines = [f"{MARK} kalibr: Kalibr's camchain layout; T_cn_cnm1 takes camera n-1's frame to camera n's (x_n = T "
             f"x_nm1), metres"]
    for c, (camera, name) in enumerate(zip(rig.cameras, rig.names)):
        model, coefficients = kalibr_model(camera, name)
        K = camera.K
        lines += [f"cam{c}:", "  camera_model: pinhole", f"  intrinsics: {_flow([K[0, 0], K[1, 1], K[0, 2], K[1, 2]])}",
                  f"  distortion_model: {model}", f"  distortion_coeffs: {_flow(coefficients)}"]
        if c > 0:
            R, t = rig.relative(c - 1, c)
            T = np.vstack([np.column_stack([R, t]), [0.0, 0.0, 0.0, 1.0]])
            lines += ["  T_cn_cnm1:"] + [f"  - {_flow(row)}" for row in T]
        if len(rig.cameras) > 1:
            lines.append(f"  cam_overlaps: [{', '.join(str(o) for o in rig.overlaps[c])}]")
        width, height = camera.image_size
        lines += [f"  rostopic: /{ros_name(name)}/image_raw", f"  resolution: [{width}, {height}]"]
    return "\n".join(lines) + "\n"


def _matrix(key: str, values: np.ndarray) -> list[str]:
    values = np.atleast_2d(np.asarray(values, np.float64))
    return [f"{key}:", f"  rows: {values.shape[0]}", f"  cols: {values.shape[1]}", f"  data: {_flow(values)}"]


def ros_camera_info(camera: Camera, name: str, R: np.ndarray | None = None, P: np.ndarray | None = None) -> str:
    """One ROS camera_info YAML (camera_calibration_parsers' layout). ``R`` (3, 3) and ``P`` (3, 4): a stereo pair's
    rectification (`stereo.Rectification`); None: a mono camera's R = I, P = [K | 0]."""
    model, coefficients = ros_model(camera, name)
    R = np.eye(3) if R is None else R
    P = np.column_stack([camera.K, np.zeros(3)]) if P is None else P
    lines = [f"{MARK} ros: ROS camera_info (camera_calibration_parsers' layout), OpenCV's pixels",
             f"image_width: {camera.image_size[0]}", f"image_height: {camera.image_size[1]}",
             f"camera_name: {ros_name(name)}", *_matrix("camera_matrix", camera.K), f"distortion_model: {model}",
             *_matrix("distortion_coefficients", coefficients.reshape(1, -1)), *_matrix("rectification_matrix", R),
             *_matrix("projection_matrix", P)]
    return "\n".join(lines) + "\n"


def colmap_cameras(rig: ExportRig) -> str:
    """COLMAP's cameras.txt: its header, then ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS...``, camera c as ID c + 1."""
    lines = [COLMAP_HEADER.format(count=len(rig.cameras)).rstrip("\n"),
             f"{MARK} colmap: COLMAP pixels (top-left pixel centre at 0.5, 0.5): cx, cy are OpenCV's + 0.5"]
    for c, (camera, name) in enumerate(zip(rig.cameras, rig.names)):
        model, params = colmap_model(camera, name)
        lines.append(f"{c + 1} {model} {camera.image_size[0]} {camera.image_size[1]} "
                     + " ".join(repr(float(p)) for p in params))
    return "\n".join(lines) + "\n"


def colmap_rig_config(rig: ExportRig) -> str:
    """The rig as ``colmap rig_configurator --rig_config_path`` reads it (module docstring); each camera's images
    under ``<name>/``, its model and parameters as in cameras.txt."""
    cameras = []
    for c, (camera, name) in enumerate(zip(rig.cameras, rig.names)):
        model, params = colmap_model(camera, name)
        entry: dict = {"image_prefix": f"{name}/"}
        if c == 0:
            entry["ref_sensor"] = True
        else:
            R, t = rig.relative(0, c)
            x, y, z, w = Rotation.from_matrix(R).as_quat()
            quaternion = [w, x, y, z] if w >= 0 else [-w, -x, -y, -z]
            entry["cam_from_rig_rotation"] = [float(q) for q in quaternion]
            entry["cam_from_rig_translation"] = [float(v) for v in t]
        entry["camera_model_name"] = model
        entry["camera_params"] = [float(p) for p in params]
        cameras.append(entry)
    return json.dumps([{"generator": MARK.lstrip("# ") + " colmap", "cameras": cameras}], indent=2) + "\n"


# ----------------------------------------------------------------------------------------------- the files
def export_layout(formats: list[str], names: list[str], folder: Path, maps: bool = False
                  ) -> dict[Path, tuple[Callable[[Path], bool], str]]:
    """Every file ``formats`` write into ``folder`` (module docstring's names), each with the test of a file it may
    overwrite and what it is called (`deepcharuco.core.files.refuse_foreign`)."""
    ours = contains(MARK.encode())
    files: dict[Path, tuple[Callable[[Path], bool], str]] = {}
    if "kalibr" in formats:
        files[folder / "kalibr" / "camchain.yaml"] = (ours, "Kalibr camchain it wrote")
    if "ros" in formats:
        files.update({folder / "ros" / f"{name}.yaml": (ours, "ROS camera_info it wrote") for name in names})
    if "colmap" in formats:
        files[folder / "colmap" / "cameras.txt"] = (ours, "COLMAP cameras.txt it wrote")
        if len(names) > 1:
            files[folder / "colmap" / "rig_config.json"] = (contains(b"deepcharuco calibrate --export colmap"),
                                                            "COLMAP rig config it wrote")
    if "opencv" in formats:
        opencv = contains(stereo.GENERATOR.encode())
        name = "stereo.yaml" if len(names) == 2 else "undistort.yaml"
        files[folder / "opencv" / name] = (opencv, "rectification it wrote")
        if maps:
            files[folder / "opencv" / "rectify_maps.npz"] = (stereo.is_maps_npz, "rectify maps file it wrote")
    return files


def export_files(formats: list[str], rig: ExportRig, folder: Path, maps: bool = False) -> dict[Path, str | bytes]:
    """{path: contents} of every file of `export_layout` (composed in its order); `ExportError` (`check_cameras`)
    before any is composed."""
    check_cameras(formats, rig.cameras, rig.names)
    pair = None
    if len(rig.cameras) == 2 and ("opencv" in formats or "ros" in formats):
        try:
            pair = stereo.stereo_rectify(rig.cameras[0], rig.cameras[1], *rig.relative(0, 1), tuple(rig.names))
        except ExportError:  # ROS alone: two cameras of two sizes or models are two mono cameras
            pair = None
    contents: list[str | bytes] = []
    if "kalibr" in formats:
        contents.append(kalibr_camchain(rig))
    if "ros" in formats:
        for c, (camera, name) in enumerate(zip(rig.cameras, rig.names)):
            rectified = (None, None) if pair is None else ((pair.R1, pair.P1) if c == 0 else (pair.R2, pair.P2))
            contents.append(ros_camera_info(camera, name, *rectified))
    if "colmap" in formats:
        contents += [colmap_cameras(rig)] + ([colmap_rig_config(rig)] if len(rig.cameras) > 1 else [])
    if "opencv" in formats:
        if pair is not None:
            contents.append(stereo.stereo_text(rig.cameras[0], rig.cameras[1], tuple(rig.names), pair))
            rectified = [(pair.R1, pair.P1), (pair.R2, pair.P2)]
        else:
            contents.append(stereo.undistort_text(rig.cameras[0], rig.names[0]))
            rectified = [(np.eye(3), stereo.undistorted_matrix(rig.cameras[0]))]
        if maps:
            contents.append(stereo.maps_npz({name: stereo.rectify_maps(camera, R, P) for camera, name, (R, P)
                                             in zip(rig.cameras, rig.names, rectified)}))
    return dict(zip(export_layout(formats, rig.names, folder, maps), contents, strict=True))
