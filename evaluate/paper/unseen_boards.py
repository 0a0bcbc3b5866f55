"""Boards the detector was never trained on: the paper's protocols re-run on other boards.

    python -m evaluate.paper.unseen_boards                # render the sets once (~10 min a board on 2 cores), evaluate
    python -m evaluate.report                       # shows the section whenever data/unseen holds the sets

The shipped weights were trained on renders of the paper's 5x5 DICT_5X5_50 board only. Each
board below differs in grid, dictionary, marker/square ratio or print polarity, and is found
by its markers (`Detector` geometry "markers"). For each board the rendered twins of the
paper's 26 videos are made again with that board printed in the scene (`evaluate.paper.sequences
--board`, 40 frames a sequence), and the report's experiments run on them: the synthetic
blur/darkness protocol on 20 well-lit first frames, and pose accuracy over the sequences,
next to OpenCV + cornerSubPix on the same frames.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from deepcharuco.boards.board import BoardSpec
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.core.files import write_atomic
from deepcharuco.detection.opencv_detector import OpenCVDetector
from evaluate.paper import experiments
from evaluate.paper.data import frames_fingerprint, load_frames, select_well_lit
from evaluate.paper.protocols import LEVELS

DEFAULT_ROOT = Path("data/unseen")
SEQUENCE_FRAMES = 40  # 30 well-lit static frames, then 10 of the sequence's condition
# Named as the report shows them. None is the paper's board; each is printed in a way the training renders never were.
UNSEEN_BOARDS: dict[str, BoardSpec] = {
    "7x5 DICT_6X6_250": BoardSpec(squares_x=7, squares_y=5, square_length=0.04, marker_length=0.03,
                                  dictionary="DICT_6X6_250"),
    "11x8 DICT_5X5_1000": BoardSpec(squares_x=11, squares_y=8, square_length=0.022, marker_length=0.016,
                                    dictionary="DICT_5X5_1000"),
    "4x5 DICT_4X4_1000 inverted": BoardSpec(squares_x=4, squares_y=5, square_length=0.05, marker_length=0.0375,
                                            dictionary="DICT_4X4_1000", inverted=True),
}
TARGETS = {"blur10": 0.90, "dark9": 0.90, "k0": 0.99, "pose_accuracy": 0.97}


def folder_of(root: Path, name: str) -> Path:
    """data/unseen/7x5-dict_6x6_250 ...: one folder of sequence shards per board."""
    return Path(root) / name.lower().replace(" ", "-")


def render_sets(root: Path = DEFAULT_ROOT, frames: int = SEQUENCE_FRAMES, quiet: bool = False) -> None:
    """Render (or finish rendering) every board's sequences under ``root``; finished sets are kept."""
    from evaluate.paper.sequences import main as render_sequences

    for name, board in UNSEEN_BOARDS.items():
        folder = folder_of(root, name)
        folder.mkdir(parents=True, exist_ok=True)
        board_file = board.save(folder / "board.yaml")
        arguments = ["--board", str(board_file), "--out", str(folder), "--frames", str(frames)]
        if any(folder.glob("shard-*.h5")):
            arguments.append("--resume")
        if not quiet:
            print(f"rendering {name}: python -m evaluate.paper.sequences {' '.join(arguments)}", file=sys.stderr, flush=True)
        if render_sequences(arguments + (["--quiet"] if quiet else [])) != 0:
            raise DeepCharucoError(f"rendering the sequences of {name} into {folder} failed (see above)")


def available(root: Path = DEFAULT_ROOT) -> list[str]:
    """The boards whose sequences are rendered under ``root``."""
    return [name for name in UNSEEN_BOARDS if any(folder_of(root, name).glob("shard-*.h5"))]


def board_summary(detectors: list[str], synthetic: dict, sequences: dict) -> dict:
    """Each detector's numbers the any-board targets are judged on, from `experiments.synthetic_experiment` and
    `experiments.sequence_experiment` results: accuracy at k=0, blur k=10, darkness k=9, pose accuracy,
    confidently wrong poses, mean eps_re over the well-lit (>= 100 lux) sequences."""
    levels = synthetic["levels"]
    summary = {}
    for detector in detectors:
        blur, dark = synthetic["blur"][detector]["accuracy"], synthetic["darkness"][detector]["accuracy"]
        overall = sequences["overall"][detector]
        good = [row[detector]["mean_eps_re"] for row in sequences["table"]
                if (row.get("lux") or 0) >= 100 and row[detector]["mean_eps_re"] is not None]
        summary[detector] = {
            "k0": dark[levels.index(0)], "blur10": blur[levels.index(10)], "dark9": dark[levels.index(9)],
            "pose_accuracy": overall["pose_accuracy"], "confidently_wrong": overall["confidently_wrong"],
            "mean_eps_re_good_light": sum(good) / len(good) if good else None,
        }
    return summary


def _shown(path: Path) -> str:
    """A weights path as the report shows it: inside the package from the package's folder, else as given."""
    from deepcharuco.detection.deep_detector import WEIGHTS_DIR

    path = Path(path).resolve()
    return str(path.relative_to(WEIGHTS_DIR.parent.parent)) if path.is_relative_to(WEIGHTS_DIR) else str(path)


def unseen_boards_experiment(root: Path = DEFAULT_ROOT, weights: str | None = None, refine_weights: str | None = None,
                             device: str = "cpu", synthetic_images: int = 20, every: int = 1, seed: int = 0,
                             quiet: bool = False, only: list[str] | None = None, network: str = "lite") -> dict:
    """Per rendered board: the synthetic protocol and the sequences, deep (by markers) vs OpenCV.

    ``every``: keep every n-th frame of each sequence (the report's --quick uses 4); ``only``: these boards
    (names of `UNSEEN_BOARDS`, any case) among the rendered ones; ``network``: the deep detector's (`Detector`'s)."""
    from deepcharuco.detection.deep_detector import DEFAULT_WEIGHTS, Detector

    boards = {}
    wanted = None if only is None else {name.lower() for name in only}
    for name in available(root):
        if wanted is not None and name.lower() not in wanted:
            continue
        board = UNSEEN_BOARDS[name]
        frames = load_frames(folder_of(root, name), board)
        detectors = {"deep": Detector(board=board, weights=weights, refine_weights=refine_weights, device=device,
                                      network=network)}
        if weights is None and network == "lite" and detectors["deep"].weights != DEFAULT_WEIGHTS:
            # The board's family model, side by side with the paper's weights, whose point head finds it too.
            detectors["deep_paper_weights"] = Detector(board=board, weights=DEFAULT_WEIGHTS, device=device)
        detectors["opencv"] = OpenCVDetector(board, refine="subpix")
        well_lit = select_well_lit(frames, synthetic_images, seed=seed)
        synthetic = experiments.synthetic_experiment(detectors, well_lit, LEVELS, quiet)
        kept = [f for f in frames if int(f.meta.get("sequence_frame", 0)) % every == 0]
        sequences = experiments.sequence_experiment(detectors, kept, f"sequences {name}", quiet)
        summary = board_summary(list(detectors), synthetic, sequences)
        boards[name] = {"board": board.to_dict(), "geometry": detectors["deep"].geometry,
                        "weights": _shown(detectors["deep"].weights),
                        "frames": len(kept), "data_fingerprint": frames_fingerprint(frames), "summary": summary,
                        "synthetic": {k: v for k, v in synthetic.items() if not k.startswith("_")},
                        "sequences": {k: v for k, v in sequences.items() if not k.startswith("_")}}
    return {"boards": boards, "targets": TARGETS}


def targets(unseen: dict) -> list[tuple[str, float | None, str, bool]]:
    """(what, value, goal, met) for issue 13's targets on each unseen board."""
    rows = []
    for name, result in unseen.get("boards", {}).items():
        deep, cv = result["summary"]["deep"], result["summary"]["opencv"]
        for key, label in (("blur10", "synthetic blur k=10"), ("dark9", "synthetic darkness k=9"), ("k0", "synthetic k=0")):
            rows.append((f"unseen {name}: {label}", deep[key], f">= {TARGETS[key]}", deep[key] >= TARGETS[key]))
        rows.append((f"unseen {name}: pose accuracy over the sequences", deep["pose_accuracy"],
                     f">= {TARGETS['pose_accuracy']} (OpenCV {cv['pose_accuracy']:.3f})",
                     deep["pose_accuracy"] >= TARGETS["pose_accuracy"]))
        rows.append((f"unseen {name}: confidently wrong poses", deep["confidently_wrong"], "0",
                     deep["confidently_wrong"] == 0))
        if deep["mean_eps_re_good_light"] is not None and cv["mean_eps_re_good_light"] is not None:
            rows.append((f"unseen {name}: mean eps_re in good light, px", deep["mean_eps_re_good_light"],
                         f"<= OpenCV ({cv['mean_eps_re_good_light']:.3f})",
                         deep["mean_eps_re_good_light"] <= cv["mean_eps_re_good_light"]))
    return rows


def sections(unseen: dict, labels: dict) -> list[tuple[str, str, list[list[str]], list[str]]]:
    """The report's "Boards never seen in training" section: one row per board and detector."""
    if not unseen.get("boards"):
        return []
    header = ["board", "detector", "k=0", "blur k=10", "darkness k=9", "pose acc %", "confidently wrong",
              "eps_re good light"]
    rows = [header]
    for name, result in unseen["boards"].items():
        for detector, summary in result["summary"].items():
            label = labels.get(detector, detector)
            if detector == "deep" and "weights" in result:
                label = f"{label} ({result['weights']})"
            rows.append([name, label, f"{summary['k0']:.2f}", f"{summary['blur10']:.2f}",
                         f"{summary['dark9']:.2f}", f"{100 * summary['pose_accuracy']:.1f}",
                         str(summary["confidently_wrong"]),
                         "nan" if summary["mean_eps_re_good_light"] is None else f"{summary['mean_eps_re_good_light']:.3f}"])
    text = ("No training frame showed these boards: the paper's weights were trained on its 5x5 DICT_5X5_50 board "
            "alone, and a family model (deepcharuco/weights/families/, which `Detector()` loads for a board of its "
            "family) on random boards of its family whose grid is never one of these. They differ from the paper's "
            "in grid, dictionary, marker/square ratio or print polarity; the deep detector finds them by their "
            "markers (geometry \"markers\") with no training by the user, with the weights named in brackets (and the "
            "paper's weights beside a family model). Each board's 26 rendered sequences (40 frames each) give the "
            "synthetic protocol (20 well-lit images: corner accuracy over all the board's corners) and the pose "
            "accuracy (eps_re < 3 px); OpenCV + cornerSubPix runs on the same frames.")
    prints = [f"{name} {result['data_fingerprint']}" for name, result in unseen["boards"].items()
              if result.get("data_fingerprint")]
    if prints:
        text += (" The frames' fingerprints (`evaluate.paper.data.frames_fingerprint`: the same on a re-render from the "
                 "same seed on one machine; another CPU may render other pixels): " + ", ".join(prints) + ".")
    return [("Boards never seen in training", text, rows, [])]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m evaluate.paper.unseen_boards", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--root", default=str(DEFAULT_ROOT), help="folder of the boards' sequence sets")
    parser.add_argument("--frames", type=int, default=SEQUENCE_FRAMES, help="frames per rendered sequence")
    parser.add_argument("--no-render", action="store_true", help="evaluate only the sets already rendered")
    parser.add_argument("--weights", default=None, help="ChArUcoNet checkpoint or bundle (default: shipped)")
    parser.add_argument("--only", nargs="+", default=None, metavar="NAME",
                        help=f"evaluate these boards only, e.g. --only \"{next(iter(UNSEEN_BOARDS))}\" (default: all)")
    parser.add_argument("--out", default=None, help="write the results as JSON here (default: print a table)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    try:
        unknown = sorted(set(n.lower() for n in args.only or ()) - {n.lower() for n in UNSEEN_BOARDS})
        if unknown:
            raise DeepCharucoError(f"--only names no unseen board: {', '.join(unknown)}; use one of: "
                                   + ", ".join(f'"{n}"' for n in UNSEEN_BOARDS))
        if not args.no_render:
            render_sets(Path(args.root), args.frames, args.quiet)
        if not available(Path(args.root)):
            raise DeepCharucoError(f"no unseen-board sequences under {args.root}: run without --no-render")
        result = unseen_boards_experiment(Path(args.root), args.weights, quiet=args.quiet, only=args.only)
    except DeepCharucoError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    for row in sections(result, experiments.LABELS)[0][2]:
        print(" | ".join(row))
    for name, board_result in result["boards"].items():
        print(f"{name}: {board_result['frames']} frames from {folder_of(Path(args.root), name)}, data fingerprint "
              f"{board_result['data_fingerprint']}")
    for what, value, goal, met in targets(result):
        print(f"{what}: {value:.3f} (goal {goal}) {'MET' if met else 'not met'}")
    if args.out:
        write_atomic(Path(args.out), json.dumps(result, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
