"""Deep ChArUco vs OpenCV on the paper's protocols: ``python -m evaluate.report`` -> report.html, report.md, results.json.

    python -m evaluate.report                       # shipped weights; renders the default test sets once
    python -m evaluate.report --weights runs/charuconet/best.pt --refine-weights runs/refinenet/best.pt
    python -m evaluate.report --captures realdata/*     # capture folders of real photos and videos (evaluate.captures)

Test sets (each a folder of shards, schema in docs/conventions.md):
  --sequences  rendered twins of the paper's 26 evaluation videos (python -m evaluate.paper.sequences);
               the per-sequence table, the pose-accuracy curve, and the 20 well-lit images of
               the synthetic blur/darkness tests (one per sequence, its first frame);
  --data       held-out random renders (python -m datagen.render --seed 1000): accuracy by lux;
  --captures   capture folders (photos and/or videos of a board, board.yaml: evaluate/captures/reader.py), the
               "Real captures" section; default: the shipped sample (evaluate/captures_sample); a folder of
               auto-labelled shards (python -m evaluate.paper.autolabel) gets the paper's per-video table.
The default folders are rendered when missing (a few minutes on 2 cores, once), unless --no-render
(then a missing default folder's section is left out); a folder given explicitly must hold shards.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.cli.common import output_folder, pick_device
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.core.files import write_atomic
from deepcharuco.core.platform import available_cpus, describe_os_error
from deepcharuco.detection.opencv_detector import OpenCVDetector
from deepcharuco.networks.shipped import NETWORKS
from evaluate import captures as real_captures
from evaluate import documents
from evaluate.calibration import calibration_eval, corner_precision
from evaluate.paper import experiments, false_positives, figures, unseen_boards
from evaluate.paper.data import TestSetError, board_of, load_frames, select_well_lit
from evaluate.paper.protocols import LEVELS
from evaluate.speed.machine import cpu_description

DEFAULT_SEQUENCES = Path("data/sequences")
DEFAULT_DATA = Path("data/test")
TEST_SEED = 1000  # held-out renders: training renders use other seeds (the sequences are evaluation-only scenes)
DEFAULT_TEST_FRAMES = 120
CORNER_PRECISION_FRAMES = 4  # drawn views per board and condition (2 with --quick): 180 frames, ~1.5 min
SYNTHETIC_IMAGES, QUICK_SYNTHETIC_IMAGES = 20, 6  # the paper's 20; --quick's fewer unless --synthetic-images says


def ensure_rendered(folder: Path, default: Path, command: list[str], allowed: bool, quiet: bool) -> bool:
    """Render the default test set ``default`` when it is missing; other folders must exist (TestSetError).
    Returns False when the default ``folder`` has no shards and may not be rendered."""
    if any(folder.glob("shard-*.h5")):
        return True
    if folder != default:
        raise TestSetError(f"{folder} {'holds no shard-*.h5 files' if folder.is_dir() else 'does not exist'}: give a "
                           f"folder of test shards (python -m datagen.render --seed {TEST_SEED} --out {folder}, or "
                           f"python -m evaluate.paper.sequences --out {folder}), or leave the option out")
    if not allowed:
        return False
    module = command[0]
    if not quiet:
        print(f"rendering the default test set {folder}: python -m {' '.join(command)}", file=sys.stderr, flush=True)
    if module == "datagen.render":
        from datagen.render import main as render_main
    else:
        from evaluate.paper.sequences import main as render_main
    if render_main(command[1:] + (["--quiet"] if quiet else [])) != 0:
        raise TestSetError(f"rendering {folder} failed (see above)")
    return True


def build_detectors(board: BoardSpec, weights: str | None, refine_weights: str | None, device: str,
                    notes: list[str], network: str = "lite") -> dict:
    """The five configurations of the paper's timing table (the three deep ones when weights exist), and the
    deep detector without its board-geometry check (the paper's decoding), to show what the check adds.
    ``network``: the three deep configurations' (`Detector`'s); the fast networks read every board by its markers,
    so with them the paper's decoding is not compared."""
    detectors = {"opencv": OpenCVDetector(board, refine="subpix"), "opencv_norefine": OpenCVDetector(board, refine="none")}
    from deepcharuco.detection.deep_detector import DEFAULT_WEIGHTS, Detector

    if weights is None and not DEFAULT_WEIGHTS.is_file():
        notes.append("**No deep detector**: this version ships no weights (deepcharuco/weights/detector.pt) and none "
                     "were given with --weights, so only OpenCV was evaluated.")
        return detectors
    # The paper's refinement comparison: its three configurations as the paper has them, with no printed-pattern fit
    # after them; the shipped detector ("deep") has it.
    for name, refine, fit in (("deep", "refinenet", True), ("deep_subpix", "subpix", False),
                              ("deep_norefine", "none", False)):
        detectors[name] = Detector(board=board, weights=weights, refine=refine, device=device,
                                   refine_weights=refine_weights, corner_fit=fit, network=network)
    if detectors["deep"].geometry == "markers":  # no ID head for this board: a family model, or another layout
        notes.append(f"**The deep detector reads {board} by its markers** ({detectors['deep'].weights} is a points-only "
                     f"family model, or was trained for another layout): the deep rows are the markers decoding; the "
                     f"paper's decoding (the ID head) is not evaluated.")
        return detectors
    detectors["deep_paper"] = Detector(board=board, weights=weights, device=device, refine_weights=refine_weights,
                                       geometry="none")
    # What a board the ID head never saw gets: the point head and the board's markers alone.
    detectors["deep_markers"] = Detector(board=board, weights=weights, device=device, refine_weights=refine_weights,
                                         geometry="markers")
    return detectors


def run_report(args: argparse.Namespace) -> dict:
    started = time.perf_counter()
    args.captures, capture_sets = real_captures.report_folders(args.captures, args.no_captures)
    pick_device(args.device)  # a bad --device, a file or an unwritable --out: refused before anything is made
    out = output_folder(args.out)
    quick = args.quick
    notes: list[str] = []
    render_allowed = not args.no_render
    sequences_dir, data_dir = Path(args.sequences), Path(args.data)
    have_sequences = ensure_rendered(sequences_dir, DEFAULT_SEQUENCES,
                                     ["evaluate.paper.sequences", "--out", str(sequences_dir)],  # its default seed
                                     render_allowed, args.quiet)
    have_data = ensure_rendered(data_dir, DEFAULT_DATA,
                                ["datagen.render", "--n", str(DEFAULT_TEST_FRAMES), "--seed", str(TEST_SEED),
                                 "--out", str(data_dir), "--shard-size", "60"], render_allowed, args.quiet)
    if not have_sequences and not have_data and not args.captures:
        raise TestSetError(f"no test data: {sequences_dir} and {data_dir} hold no shards (and --no-render was given or "
                           f"they are not the default folders). Render them with python -m evaluate.paper.sequences --out "
                           f"{sequences_dir} and python -m datagen.render --seed {TEST_SEED} --out {data_dir}")
    first = sequences_dir if have_sequences else data_dir if have_data else Path(args.captures)
    board = BoardSpec.load(args.board) if args.board else board_of(first)
    detectors = build_detectors(board, args.weights, args.refine_weights, args.device, notes, args.network)
    compared = {name: detectors[name] for name in ("deep", "deep_markers", "deep_paper", "deep_norefine", "opencv")
                if name in detectors}
    headline = {name: detectors[name] for name in ("deep", "deep_markers", "deep_paper", "opencv") if name in detectors}

    results: dict = {"command": "python -m evaluate.report " + " ".join(shlex.quote(a) for a in args.argv),
                     "board": board.to_dict(), "quick": quick,
                     "detectors": {name: experiments.LABELS[name] for name in detectors},
                     "weights": {"charuconet": str(args.weights or "shipped") if "deep" in detectors else None,
                                 "refinenet": args.refine_weights, "network": args.network}}
    pictures: dict[str, bytes] = {}
    sequence_frames = load_frames(sequences_dir, board) if have_sequences else []
    render_frames = load_frames(data_dir, board) if have_data else []
    # Synthetic blur / darkness on well-lit images with different static poses.
    # The paper's images are from its evaluation videos: take them from the sequences when there are any.
    pool = sequence_frames + render_frames
    synthetic_count = args.synthetic_images or (QUICK_SYNTHETIC_IMAGES if quick else SYNTHETIC_IMAGES)
    synthetic_frames = select_well_lit(sequence_frames or render_frames, synthetic_count, seed=args.seed)
    if quick:  # every 4th frame of each sequence, 40 renders
        sequence_frames = [f for f in sequence_frames if int(f.meta.get("sequence_frame", 0)) % 4 == 0]
        render_frames = render_frames[:40]
    synthetic = experiments.synthetic_experiment(headline, synthetic_frames, LEVELS, args.quiet)
    results["synthetic"] = {k: v for k, v in synthetic.items() if not k.startswith("_")}
    pictures["synthetic_blur"] = figures.synthetic_figure(results["synthetic"], "blur")
    pictures["synthetic_darkness"] = figures.synthetic_figure(results["synthetic"], "darkness")

    gallery_source = None
    for key, frames in (("sequences", sequence_frames),
                        ("captures", load_frames(args.captures, board) if args.captures else [])):
        if not frames:
            continue
        experiment = experiments.sequence_experiment(compared, frames, key, args.quiet)
        if key == "sequences" and args.autolabel_check:
            experiment["autolabel"] = autolabel_check(sequences_dir, board, args.quiet)
        results[key] = {k: v for k, v in experiment.items() if not k.startswith("_")}
        title = "Rendered capture sequences" if key == "sequences" else "Auto-labelled captures"
        pictures[f"{key}_threshold"] = figures.threshold_figure(
            results[key]["accuracy_vs_threshold"], f"{title}: {len(experiment['_frames'])} frames")
        gallery_source = gallery_source or experiment
    if render_frames:
        experiment = experiments.render_experiment(headline, render_frames, args.quiet)
        results["renders"] = {k: v for k, v in experiment.items() if not k.startswith("_")}
        gallery_source = gallery_source or experiment

    timing_pool = [f for f in pool if f.image.shape == (240, 320)] or pool
    timing_frames = timing_pool[:: max(1, len(timing_pool) // 40)][:40]
    results["timing"] = experiments.timing_experiment(detectors, timing_frames, 1.0 if quick else args.timing_seconds,
                                                      args.quiet)
    results["timing"]["machine"] = f"{cpu_description()}, {available_cpus()} cores"

    if gallery_source is not None:
        names = [n for n in ("deep", "opencv") if n in gallery_source["_scores"]]
        results["gallery_detectors"] = names
        results["gallery"] = []
        for i, (frame, scores) in enumerate(experiments.hardest_frames(gallery_source, names, 4 if quick else args.gallery)):
            name = f"gallery_{i:02d}"
            pictures[name] = figures.gallery_image(frame, [(s, experiments.LABELS[n]) for s, n in zip(scores, names)])
            results["gallery"].append({"figure": name, "frame": frame.name, "sequence": frame.meta.get("sequence"),
                                       "lux": _maybe_float(frame.meta.get("lux")),
                                       "blur_px": _maybe_float(frame.meta.get("blur_px")),
                                       **{n: s.to_dict() for s, n in zip(scores, names)}})

    if not args.no_calibration and calibration_eval.available(args.calibration):
        # Rendered calibration sequences (python -m evaluate.calibration.calibration_sequences), when there are any.
        results["calibration"] = calibration_eval.calibration_experiment(
            {n: detectors[n] for n in ("deep", "opencv") if n in detectors}, args.calibration, board, args.quiet)

    if not args.no_unseen_boards and unseen_boards.available(Path(args.unseen_boards)):
        # Boards the weights never saw (python -m evaluate.paper.unseen_boards renders them), when rendered.
        results["unseen_boards"] = unseen_boards.unseen_boards_experiment(
            Path(args.unseen_boards), args.weights, args.refine_weights, args.device,
            synthetic_images=synthetic_count, every=4 if quick else 1, seed=args.seed, quiet=args.quiet,
            network=args.network)
    elif not args.no_unseen_boards:
        notes.append(f"No boards-never-seen section: {args.unseen_boards} holds no rendered sets "
                     "(python -m evaluate.paper.unseen_boards renders them, ~10 min a board).")

    if capture_sets:  # real photos and videos (evaluate.captures): the shipped sample unless --captures names others
        results["real_captures"], real_pictures = real_captures.evaluate_captures(
            capture_sets, args.weights, args.refine_weights, args.device, quiet=args.quiet, network=args.network)
        pictures.update(real_pictures)

    if not args.no_false_positives:
        # Look-alike boards and photos without a board: the deep detector must give no pose on any.
        suspects = {n: detectors[n] for n in ("deep", "deep_markers", "deep_paper", "opencv") if n in detectors}
        results["false_positives"] = false_positives.false_positive_experiment(
            suspects, board, views=4 if quick else args.look_alike_views, seed=args.seed, quiet=args.quiet)

    if not args.no_corner_precision:
        # Sub-pixel error against exact truth by condition, every placer on the same drawn views; seed 1 (0 tuned).
        results["corner_precision"] = corner_precision.run(seed=1, frames=2 if quick else CORNER_PRECISION_FRAMES,
                                                           boards=list(corner_precision.BOARDS),
                                                           conditions=list(corner_precision.CONDITIONS), quiet=args.quiet)
        pictures["corner_sigma"] = corner_precision.sigma_figure(results["corner_precision"])

    results["targets"] = experiments.targets(results, [*false_positives.targets(results.get("false_positives", {})),
                                                       *corner_precision.targets(results.get("corner_precision")),
                                                       *unseen_boards.targets(results.get("unseen_boards", {}))])
    results["seconds"] = round(time.perf_counter() - started, 1)
    notes.append(_summary(results))
    results["notes"] = notes
    write_atomic(out / "results.json", json.dumps(results, indent=1, default=_json_default) + "\n")
    documents.write_markdown(out / "report.md", results, pictures)
    documents.write_html(out / "report.html", results, pictures)
    return results


def autolabel_check(sequences_dir: Path, board: BoardSpec, quiet: bool) -> dict:
    """The paper's auto-labelling recipe run on every rendered sequence, compared with the render truth."""
    from evaluate.paper.autolabel import autolabel_sequence_errors

    return autolabel_sequence_errors(sequences_dir, board, quiet=quiet)


def _summary(results: dict) -> str:
    parts = []
    sequences = results.get("sequences", {}).get("overall", {})
    for name in ("deep", "opencv"):
        if name in sequences:
            s = sequences[name]
            parts.append(f"{experiments.LABELS[name]}: pose accuracy {100 * s['pose_accuracy']:.1f}% over "
                         f"{s['frames']} sequence frames, {s['confidently_wrong']} confidently wrong poses.")
    fps = results.get("timing", {}).get("fps", {})
    if fps:
        parts.append("Speed (detect + pose): " + ", ".join(f"{experiments.LABELS[n]} {v:.0f} fps" for n, v in fps.items()) + ".")
    parts.append(f"The report took {results['seconds']:.0f} s.")
    return " ".join(parts)


def _maybe_float(value):
    return None if value is None else float(value)


def _json_default(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog="python -m evaluate.report", description=__doc__.split("\n\n")[0],
                                     epilog="\n\n".join(__doc__.split("\n\n")[1:]),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--weights", default=None, help="ChArUcoNet checkpoint or bundle, or a folder of them laid out as "
                                                         "deepcharuco/weights (default: the shipped weights)")
    parser.add_argument("--refine-weights", default=None, help="RefineNet checkpoint when --weights is not a bundle")
    parser.add_argument("--network", choices=NETWORKS, default="lite",
                        help="the deep detector's networks (Detector's network; default: %(default)s, the shipped "
                             "weights the model card describes; auto: deepcharuco detect's default)")
    parser.add_argument("--sequences", default=str(DEFAULT_SEQUENCES), help="rendered sequences (default: %(default)s)")
    parser.add_argument("--data", default=str(DEFAULT_DATA), help="held-out renders (default: %(default)s)")
    parser.add_argument("--captures", nargs="+", default=None, metavar="DIR",
                        help="capture folders: photos/videos + board.yaml (default: the shipped sample), or one "
                             "folder of auto-labelled shards")
    parser.add_argument("--no-captures", action="store_true", help="skip the real-captures section")
    parser.add_argument("--calibration", default="data/calibration",
                        help="calibration sequences (python -m evaluate.calibration.calibration_sequences), evaluated when present "
                             "(default: %(default)s)")
    parser.add_argument("--no-calibration", action="store_true", help="skip the calibration section")
    parser.add_argument("--unseen-boards", default=str(unseen_boards.DEFAULT_ROOT),
                        help="sequences of boards never seen in training (python -m evaluate.paper.unseen_boards), evaluated "
                             "when present (default: %(default)s)")
    parser.add_argument("--no-unseen-boards", action="store_true", help="skip the boards-never-seen section")
    parser.add_argument("--look-alike-views", type=int, default=10,
                        help="views of each look-alike board in the false-positive section (default: %(default)s, "
                             "--quick 4)")
    parser.add_argument("--no-false-positives", action="store_true", help="skip the false-positive section")
    parser.add_argument("--no-corner-precision", action="store_true",
                        help="skip the sub-pixel corner error section (evaluate.calibration.corner_precision)")
    parser.add_argument("--board", default=None, help="BoardSpec file (default: the test shards' board)")
    parser.add_argument("--out", default="report", help="output folder (default: %(default)s)")
    parser.add_argument("--quick", action="store_true",
                        help=f"{QUICK_SYNTHETIC_IMAGES} synthetic images (unless --synthetic-images is given), every 4th "
                             f"sequence frame, 40 renders")
    parser.add_argument("--synthetic-images", type=int, default=None,
                        help=f"images of the synthetic tests (default: {SYNTHETIC_IMAGES}, --quick {QUICK_SYNTHETIC_IMAGES})")
    parser.add_argument("--timing-seconds", type=float, default=3.0, help="timed seconds per configuration (default: 3)")
    parser.add_argument("--gallery", type=int, default=8, help="hardest frames shown (default: 8)")
    parser.add_argument("--autolabel-check", action=argparse.BooleanOptionalAction, default=True,
                        help="measure the auto-labelling recipe on the rendered sequences (default: on)")
    parser.add_argument("--no-render", action="store_true", help="never render missing default test sets")
    parser.add_argument("--device", default="cpu", help="torch device for the deep detector (default: cpu)")
    parser.add_argument("--seed", type=int, default=0, help="choice of the synthetic images (default: 0)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    args.argv = argv
    if (args.synthetic_images is not None and args.synthetic_images < 1) or args.gallery < 0 or args.timing_seconds <= 0:
        parser.error("--synthetic-images must be >= 1, --gallery >= 0, --timing-seconds > 0")
    if args.look_alike_views < 1:
        parser.error("--look-alike-views must be >= 1")
    try:
        results = run_report(args)
    except DeepCharucoError as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    except OSError as error:  # a full disk while writing the report
        print(f"error: {describe_os_error(error)}", file=sys.stderr)
        return 2
    print(results["notes"][-1])
    for target in results["targets"]:
        value = target["value"]
        shown = "nan" if value is None else f"{value:.3f}" if isinstance(value, float) else str(value)
        print(f"  {'MET ' if target['met'] else 'MISS'} {target['target']}: {shown} (goal {target['goal']})")
    print(f"wrote {Path(args.out) / 'report.html'}, report.md, results.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
