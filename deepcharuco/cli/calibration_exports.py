"""``calibrate --export kalibr|ros|colmap|opencv [--rectify-maps]``: the options, their checks before any work, and
the files (`deepcharuco.calibration.exports`) beside one camera's file (``<stem>_exports/``) or in a rig's folder."""

from __future__ import annotations

import argparse
from pathlib import Path

from deepcharuco.calibration.exports import (EXPORT_FORMATS, ExportRig, check_cameras, export_files, export_layout,
                                             parse_exports)
from deepcharuco.calibration.rig_model import RigResult
from deepcharuco.core.errors import CameraFileError, ExportError
from deepcharuco.core.files import refuse_foreign
from deepcharuco.geometry.camera import read_camera


def add_export_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--export", action="append", default=None, metavar="FORMATS",
                        help=f"also write the calibration for another tool, any of {', '.join(EXPORT_FORMATS)} "
                             "(repeat or comma list): kalibr/camchain.yaml (Kalibr; radtan needs --fix-k3), "
                             "ros/<camera>.yaml (ROS camera_info), colmap/cameras.txt (+ rig_config.json for a rig), "
                             "opencv/stereo.yaml (a two-camera rig's rectification) or opencv/undistort.yaml (one "
                             "camera); into the rig's folder, or <out stem>_exports/ beside one camera's file")
    parser.add_argument("--rectify-maps", action="store_true",
                        help="--export opencv: also the undistort-rectify maps, opencv/rectify_maps.npz "
                             "(<camera>_map_x, <camera>_map_y for cv2.remap)")


def export_problems(args: argparse.Namespace, rig: bool) -> list[str]:
    """What is wrong with the export options, found before any work (``args.export`` becomes the list of formats)."""
    try:
        args.export = parse_exports(args.export)
    except ExportError as error:
        args.export = []
        return [str(error)]
    problems = []
    if args.rectify_maps and "opencv" not in args.export:
        problems.append("--rectify-maps writes the maps of --export opencv's rectification: add --export opencv")
    if "opencv" in args.export and rig and len(args.source) > 2:
        problems.append(f"--export opencv is a stereo pair's rectification (or one camera's undistortion); "
                        f"{len(args.source)} sources are not a pair (their OpenCV camera files are written anyway): "
                        f"leave out opencv")
    given = [path for path in (args.camera or []) if path != "-"] if rig else []
    solved = not rig or not args.camera or len(given) < len(args.camera)
    if "kalibr" in args.export and solved:
        if args.model == "rational":
            problems.append("--export kalibr: a rational model (k4 k5 k6) cannot be written in Kalibr's radtan model "
                            "(k1 k2 p1 p2): calibrate with --model pinhole --fix-k3, or leave out kalibr")
        elif args.model == "pinhole" and not args.fix_k3:
            problems.append("--export kalibr: Kalibr's radtan model has k1 k2 p1 p2 and no k3: add --fix-k3 (k3 held "
                            "at 0), or leave out kalibr")
    for path in given:  # cameras held at their files: are they writable in every format asked for?
        try:
            check_cameras([f for f in args.export if f != "opencv"], [read_camera(path)], [path])
        except CameraFileError:
            continue  # the rig's own reading of --camera says what is wrong with the file
        except ExportError as error:
            problems.append(str(error))
    return problems


def export_folder(out: Path, rig: bool) -> Path:
    """Where the exports go: the rig's folder, or ``<stem>_exports/`` beside one camera's file."""
    return out if rig else out.parent / f"{out.stem}_exports"


def refuse_foreign_exports(args: argparse.Namespace, folder: Path, names: list[str]) -> None:
    """Before any work: an export file in the way that this command did not write is refused (unless --force)."""
    for path, (is_ours, what) in export_layout(args.export, names, folder, args.rectify_maps).items():
        refuse_foreign(path, is_ours, what, args.force)


def export_outputs(args: argparse.Namespace, folder: Path, rig: ExportRig | RigResult) -> dict[Path, str | bytes]:
    """The export files' {path: contents} of one camera (`ExportRig.single`) or a solved rig, their folders made;
    `ExportError` (nothing made) for a camera a format cannot hold."""
    if not args.export:
        return {}
    rig = rig if isinstance(rig, ExportRig) else ExportRig.from_result(rig)
    files = export_files(args.export, rig, folder, args.rectify_maps)
    for path in files:
        path.parent.mkdir(parents=True, exist_ok=True)
    return files
