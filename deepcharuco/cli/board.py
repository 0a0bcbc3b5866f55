"""``deepcharuco board``: a board to print at true size (vector PDF; SVG and PNG on request), with a ruler.

    deepcharuco board board.yaml --out board.pdf [--paper A4|letter|A3|WxHmm]
    deepcharuco board --squares 7x5 --dictionary DICT_6X6_250 --square 30mm --marker 22mm --out my_board

The second form describes a new board and writes its board file beside the sheet (``my_board.yaml``
and ``my_board.pdf``): the file that `detect` and `calibrate` take as ``--board``. Exit code 0, or 2
with one line naming the problem (a board that does not fit the paper, an unknown paper, an output
that cannot be written) and nothing written.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
from pathlib import Path

from deepcharuco.boards.board import BOARD_FILE_MARK, BoardSpec
from deepcharuco.boards.printing import (
    PAPERS_MM, SHEET_MARK, board_sheet, check_png_resolution, check_png_size, check_printable, paper_size, pdf_bytes,
    png_bytes, svg_text,
)
from deepcharuco.cli.common import check_output_folder, load_board, run_command
from deepcharuco.core.errors import BoardSpecError, DeepCharucoError
from deepcharuco.core.files import contains, png_mark, refuse_foreign, starts_with, write_together

FORMATS = {".pdf": b"%PDF-", ".svg": b"<?xml", ".png": b"\x89PNG"}  # each format and how its files begin
# How each format's sheet is known as one this command wrote (`printing.SHEET_MARK` inside it), and may be replaced
# without --force: a user's own PNG, PDF or SVG is not.
OURS = {".pdf": lambda path: starts_with(FORMATS[".pdf"])(path) and contains(f"/Creator ({SHEET_MARK})".encode(),
                                                                             1 << 26)(path),
        ".svg": contains(f"<!-- {SHEET_MARK} -->".encode(), 256), ".png": png_mark(SHEET_MARK)}
UNITS_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}


def parse_length(text: str, option: str) -> float:
    """A length with its unit (``30mm``, ``3cm``, ``0.03m``, ``1.2in``) in metres."""
    match = re.fullmatch(r"\s*(\d+(?:\.\d*)?|\.\d+)\s*(mm|cm|m|in)\s*", text.lower())
    if not match or float(match[1]) <= 0:
        raise DeepCharucoError(f"{option} {text!r}: give a positive length with its unit, e.g. 30mm, 3cm or 0.03m")
    # To the nanometre: 0.75in is 0.01905 m in the board file, not float's 0.019049999999999997.
    return round(float(match[1]) * UNITS_MM[match[2]] / 1000.0, 9)


def board_from_args(args: argparse.Namespace) -> tuple[BoardSpec, bool]:
    """(the board, whether it was described by options: then its board file is written too)."""
    described = any(getattr(args, name) is not None for name in ("squares", "dictionary", "square", "marker"))
    if args.board and described:
        raise DeepCharucoError("give a board file or describe the board with --squares, --dictionary, --square and "
                               "--marker, not both")
    if args.board:
        return load_board(args.board), False
    missing = [f"--{name}" for name in ("squares", "dictionary", "square", "marker") if getattr(args, name) is None]
    if missing:
        raise DeepCharucoError(f"give a board file, or describe the board: {', '.join(missing)} missing (e.g. "
                               f"--squares 7x5 --dictionary DICT_6X6_250 --square 30mm --marker 22mm)")
    match = re.fullmatch(r"\s*(\d+)\s*x\s*(\d+)\s*", args.squares.lower())
    if not match:
        raise DeepCharucoError(f"--squares {args.squares!r}: give columns x rows, e.g. 7x5")
    try:
        board = BoardSpec(int(match[1]), int(match[2]), parse_length(args.square, "--square"),
                          parse_length(args.marker, "--marker"), args.dictionary, legacy=args.legacy,
                          inverted=args.inverted, mirrored=args.mirrored, first_marker_id=args.first_marker_id)
    except BoardSpecError as error:
        raise DeepCharucoError(str(error).replace("square_length", "--square").replace("marker_length", "--marker")
                               ) from None
    return board, True


def outputs(out: Path, formats: list[str], with_board_file: bool) -> tuple[list[Path], Path | None]:
    """(the sheets to write, the board file to write or None) for ``--out`` and ``--format``."""
    suffix = out.suffix.lower()
    if suffix in FORMATS:
        stem, chosen = out.with_suffix(""), [suffix] + [f".{f}" for f in formats if f".{f}" != suffix]
    elif suffix in (".yaml", ".yml", ".json"):
        raise DeepCharucoError(f"--out {out} names a board file: give the sheet's name (board.pdf, .svg, .png) or a "
                               f"name without suffix for both")
    elif re.fullmatch(r"\.[a-z]{2,4}", suffix):  # another file type (board.tiff): it was written as board.tiff.pdf
        raise DeepCharucoError(f"--out {out}: a sheet is written as PDF, SVG or PNG, not {suffix[1:].upper()}: give "
                               f"{out.with_suffix('.pdf').name} (--format png for a raster), or a name without suffix")
    else:
        stem, chosen = out, [".pdf"] + [f".{f}" for f in formats if f != "pdf"]
    return [stem.with_name(stem.name + s) for s in chosen], stem.with_name(stem.name + ".yaml") if with_board_file else None


def run(args: argparse.Namespace) -> list[Path]:
    board, described = board_from_args(args)
    paper_size(args.paper)  # an unknown paper is refused before anything else
    sheets, board_file = outputs(Path(args.out), args.format, described)
    for path in sheets + ([board_file] if board_file else []):
        check_output_folder(path.parent, "--out's folder")
        if path.suffix in FORMATS:
            refuse_foreign(path, OURS[path.suffix], "sheet written by deepcharuco board", args.force)
        else:
            refuse_foreign(path, contains(f"# {BOARD_FILE_MARK}".encode(), 256), "board file written by deepcharuco "
                           "board", args.force)
    check_printable(board)
    sheet = board_sheet(board, args.paper)
    if any(path.suffix == ".png" for path in sheets):
        check_png_resolution(board, args.dpi)
        check_png_size(sheet.size, args.dpi)
    render = {".pdf": pdf_bytes, ".svg": svg_text, ".png": lambda s: png_bytes(s, args.dpi)}
    files = {}
    for path in sheets:
        try:
            files[path] = render[path.suffix](sheet)
        except ImportError as error:  # a runtime dependency missing from a broken or --no-deps install
            top = (error.name or "a library").split(".")[0]
            package = PACKAGES.get(top, top)
            raise DeepCharucoError(f"a {path.suffix[1:].upper()} sheet needs {package}, which is not installed: pip "
                                   f"install {package}, or write another format (--out board.svg)") from error
    if board_file is not None:
        files[board_file] = board.file_text(board_file.suffix)
    sheets[0].parent.mkdir(parents=True, exist_ok=True)
    written = write_together(files)
    w, h = sheet.size
    print(f"{board.squares_x}x{board.squares_y} {board.dictionary} board, {board.squares_x * board.square_length * 1000:g}"
          f" x {board.squares_y * board.square_length * 1000:g} mm, on {args.paper} ({w:g} x {h:g} mm, "
          f"{'portrait' if h >= w else 'landscape'}): {', '.join(str(p) for p in written)}. Print at 100 % (actual "
          f"size) and check the ruler.")
    return written


# A sheet format's package whose import name is not what pip installs (ReportLab's is).
PACKAGES = {"PIL": "pillow"}


def build_parser(prog: str = "deepcharuco board") -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog=prog, formatter_class=argparse.ArgumentDefaultsHelpFormatter,
        description="Write a ChArUco board to print at true size: a vector PDF (SVG and PNG with --format) centred on "
                    "the paper, with a 100 mm ruler to check the printer's scale and the board's description. Give a "
                    "board file, or describe a new board (its board file is written beside the sheet).")
    parser.add_argument("board", nargs="?", help="board file (.yaml/.json), as detect and calibrate take it")
    parser.add_argument("--squares", help="a new board's squares, columns x rows, e.g. 7x5")
    parser.add_argument("--dictionary", help="a new board's ArUco dictionary, e.g. DICT_6X6_250")
    parser.add_argument("--square", help="a new board's square side with its unit, e.g. 30mm")
    parser.add_argument("--marker", help="a new board's marker side with its unit, e.g. 22mm")
    parser.add_argument("--legacy", action="store_true", help="a new board in OpenCV's pre-4.6 layout")
    parser.add_argument("--inverted", action="store_true", help="a new board printed white on black")
    parser.add_argument("--mirrored", action="store_true", help="a new board to be seen from its mirror-printed back")
    parser.add_argument("--first-marker-id", type=int, default=0, help="a new board's first marker ID")
    parser.add_argument("--paper", default="A4", help=f"paper: {', '.join(PAPERS_MM)}, or WxHmm (e.g. 500x700mm)")
    parser.add_argument("--out", required=True,
                        help="the sheet: board.pdf / .svg / .png, or a name without suffix for NAME.pdf (and "
                             "NAME.yaml for a new board)")
    parser.add_argument("--format", action="append", default=[], choices=["pdf", "svg", "png"],
                        help="also write this format (repeat for more)")
    parser.add_argument("--dpi", type=float, default=300.0, help="PNG resolution (dots per inch)")
    parser.add_argument("--force", action="store_true", help="overwrite files that deepcharuco board did not write")
    return parser


def main(argv: list[str] | None = None, prog: str = "deepcharuco board") -> int:
    parser = build_parser(prog)
    args = parser.parse_args(argv)
    if not (math.isfinite(args.dpi) and args.dpi > 0):
        parser.error(f"--dpi must be a positive number, got {args.dpi:g}")

    def body() -> None:
        run(args)

    return run_command(body)


if __name__ == "__main__":
    sys.exit(main())
