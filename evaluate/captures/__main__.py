"""``python -m evaluate.captures DIR [DIR ...]``: the real-captures section alone -> OUT/captures.md, .html, .json."""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from pathlib import Path

from deepcharuco.calibration.html_page import html_page
from deepcharuco.cli.common import output_folder, run_command
from deepcharuco.core.files import write_atomic
from deepcharuco.networks.shipped import NETWORKS
from evaluate.captures.present import DEFAULT_GALLERY, DEFAULT_STEP, capture_sections, evaluate_captures, sample_folders
from evaluate.paper.figures import figure_file_name


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m evaluate.captures", description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", nargs="*", metavar="DIR",
                        help="capture folders: photos and/or videos of a board and its board.yaml (default: the "
                             "shipped sample, evaluate/captures_sample)")
    parser.add_argument("--step", type=int, default=DEFAULT_STEP,
                        help="every STEP-th frame of each video (default: %(default)s)")
    parser.add_argument("--limit", type=int, default=None, help="at most LIMIT frames a video (default: all)")
    parser.add_argument("--gallery", type=int, default=DEFAULT_GALLERY,
                        help="frames a set where the detectors disagree most, drawn (default: %(default)s)")
    parser.add_argument("--weights", default=None, help="deep detector weights (default: the shipped bundle)")
    parser.add_argument("--refine-weights", default=None, help="RefineNet checkpoint when --weights is not a bundle")
    parser.add_argument("--network", choices=NETWORKS, default="lite",
                        help="the deep and hybrid detectors' networks (Detector's network; default: %(default)s, the "
                             "shipped weights the model card describes)")
    parser.add_argument("--device", default="cpu", help="torch device (default: %(default)s)")
    parser.add_argument("--out", default="report", help="output folder (default: %(default)s)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    return parser


def _write_markdown(path: Path, command: str, page: list, pictures: dict[str, bytes]) -> None:
    """The sections as markdown, the gallery's JPEGs in figures/ beside it (as `evaluate.documents.write_markdown`)."""
    lines = ["# Real captures", "", f"`{command}`", ""]
    (path.parent / "figures").mkdir(exist_ok=True)
    for title, text, rows, names in page:
        lines += [f"## {title}", "", text, ""]
        if rows:
            lines += ["| " + " | ".join(rows[0]) + " |", "|" + "---|" * len(rows[0])]
            lines += ["| " + " | ".join(r) + " |" for r in rows[1:]] + [""]
        for name in names:
            file_name = figure_file_name(name, pictures[name])
            write_atomic(path.parent / "figures" / file_name, pictures[name])
            lines += [f"![{name}](figures/{file_name})", ""]
    write_atomic(path, "\n".join(lines))


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    if args.step < 1 or (args.limit is not None and args.limit < 1) or args.gallery < 0:
        build_parser().error("--step and --limit must be >= 1, --gallery >= 0")

    def body() -> None:
        out = output_folder(args.out)
        results, pictures = evaluate_captures(args.folders or sample_folders(), args.weights, args.refine_weights,
                                              args.device, args.step, args.limit, args.gallery, args.quiet,
                                              args.network)
        results["command"] = "python -m evaluate.captures " + " ".join(shlex.quote(a) for a in argv)
        write_atomic(out / "captures.json", json.dumps(results, indent=1) + "\n")
        page = capture_sections(results)
        _write_markdown(out / "captures.md", results["command"], page, pictures)
        write_atomic(out / "captures.html", html_page("Real captures", results["command"], page, pictures))
        for title, _, rows, _ in page[:1]:
            print("\n".join(" | ".join(r) for r in rows))
        print(f"{results['seconds']:.0f} s; wrote {out / 'captures.html'}, captures.md, captures.json")

    return run_command(body)


if __name__ == "__main__":
    sys.exit(main())
