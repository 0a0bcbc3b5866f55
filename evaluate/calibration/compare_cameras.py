"""Camera files side by side: ``python -m evaluate.calibration.compare_cameras REFERENCE.yaml OTHER.yaml ...``.

For real captures there is no true camera, only calibrations to compare (e.g. this project's
`deepcharuco.cli.calibrate` with each detector against another tool's file). Each row: the intrinsics,
the RMS the file states (``avg_reprojection_error``, or a "reproj error X" in its ``note``), the
views used, and how far the file's camera puts the REFERENCE camera's rays: at the image's four
corners (worst) and at its centre, in pixels. OpenCV's standard model (4-14 coefficients) and its fisheye
model (a fisheye file's k1..k4 are listed under k1 k2 p1 p2, its name marked "(fisheye)").
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

import cv2
import numpy as np

from datagen.lens import LensError, pixels_to_rays
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.geometry.camera import Camera, read_camera


def stated_rms(path: str | Path) -> float | None:
    """The RMS reprojection error a camera file states, if any."""
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        node = storage.getNode("avg_reprojection_error")
        if not node.empty():
            return float(node.real())
        note = storage.getNode("note")
        match = re.search(r"reproj(?:ection)? error ([0-9.]+)", note.string() if not note.empty() else "")
        return float(match.group(1)) if match else None
    finally:
        storage.release()


def stated_views(path: str | Path) -> int | None:
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        node = storage.getNode("nr_of_frames")
        return None if node.empty() else int(node.real())
    finally:
        storage.release()


def ray_disagreement(reference: Camera, other: Camera) -> tuple[float, float]:
    """(worst over the image's four corners, at the principal point) distance in px between a pixel of
    ``reference`` and where ``other`` images that pixel's ray; ``other`` is scaled to reference's size."""
    width, height = reference.image_size
    other = other.for_image_size(width, height)
    pixels = np.array([[0.0, 0.0], [width - 1.0, 0.0], [0.0, height - 1.0], [width - 1.0, height - 1.0],
                       [reference.K[0, 2], reference.K[1, 2]]])
    if reference.model == "fisheye":
        rays = (reference.undistort_points(pixels) - reference.K[:2, 2]) / reference.K[[0, 1], [0, 1]]
    else:
        rays = pixels_to_rays(pixels, reference.K, reference.dist)  # Newton, and refuses a lens that folds
    mapped = other.project(np.column_stack([rays, np.ones(len(rays))]), np.zeros(3), np.zeros(3))
    distance = np.linalg.norm(mapped - pixels, axis=1)
    return float(distance[:4].max()), float(distance[4])


def comparison_rows(paths: list[str | Path], names: list[str] | None = None) -> list[list[str]]:
    """Markdown-ready rows (header first), the first file the reference."""
    names = names or [Path(p).stem for p in paths]
    cameras = [read_camera(p) for p in paths]
    rows = [["camera file", "fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "RMS px", "views",
             "vs first: corners px", "centre px"]]
    for name, path, camera in zip(names, paths, cameras):
        dist = np.concatenate([camera.dist, np.zeros(5)])[:5]
        rms, views = stated_rms(path), stated_views(path)
        try:
            corners, centre = ray_disagreement(cameras[0], camera)
            spread = [f"{corners:.1f}", f"{centre:.1f}"]
        except (LensError, DeepCharucoError) as error:
            spread = [f"n/a ({error.__class__.__name__})", ""]
        rows.append([name + (" (fisheye)" if camera.model == "fisheye" else ""), *(f"{v:.1f}" for v in (camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2])),
                     *(f"{v:.4f}" for v in dist), "" if rms is None else f"{rms:.3f}",
                     "" if views is None else str(views), *spread])
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m evaluate.calibration.compare_cameras", description=__doc__.split("\n\n")[0])
    parser.add_argument("cameras", nargs="+", help="camera files; the first is the reference")
    parser.add_argument("--names", nargs="+", default=None, help="a name for each file (default: the file names)")
    args = parser.parse_args(argv)
    if args.names and len(args.names) != len(args.cameras):
        parser.error(f"--names needs one name per camera file ({len(args.cameras)})")
    try:
        rows = comparison_rows(args.cameras, args.names)
    except DeepCharucoError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print("| " + " | ".join(rows[0]) + " |\n|" + "---|" * len(rows[0]))
    for row in rows[1:]:
        print("| " + " | ".join(row) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
