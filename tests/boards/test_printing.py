"""Printable boards (deepcharuco.boards.printing, `deepcharuco board`) and the `deepcharuco` command."""

import io
import re
import sys
from xml.etree import ElementTree

import cv2
import numpy as np
import pytest
from PIL import Image

from conftest import ROOT

from deepcharuco import BoardSpec, OpenCVDetector
from deepcharuco.boards.printing import (MM_PER_POINT, PrintError, board_sheet, paper_size, pdf_bytes, png_bytes,
                                         raster, svg_text)
from deepcharuco.cli.board import main as board_main
from deepcharuco.cli.main import main as deepcharuco_main

BOARDS = [BoardSpec(7, 5, 0.03, 0.022, "DICT_6X6_250"),
          BoardSpec(4, 5, 0.03, 0.022, "DICT_4X4_1000", inverted=True),
          BoardSpec(6, 8, 0.025, 0.018, "DICT_4X4_50", legacy=True, first_marker_id=10),
          BoardSpec(5, 5, 0.03, 0.022, "DICT_5X5_50", mirrored=True),
          BoardSpec()]


@pytest.mark.parametrize("board", BOARDS, ids=lambda b: f"{b.squares_x}x{b.squares_y}-{b.dictionary}")
def test_the_printed_sheet_is_the_board_at_true_size(board):
    """Drawn at 8 px/mm and halved, OpenCV finds every corner where the sheet's geometry puts it (1 mm =
    4 px exactly): the sheet is the board the detectors look for, at its size."""
    sheet = board_sheet(board, "A4")
    image = cv2.resize(raster(sheet, 25.4 * 8), None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA)
    found = OpenCVDetector(board).detect(image)
    assert len(found) == board.num_corners
    where = (np.array(sheet.board_box[:2]) + board.object_points()[found.ids, :2] * 1000.0) * 4.0 - 0.5
    assert np.abs(found.corners - where).max() < 0.05
    assert sheet.board_box[2:] == pytest.approx((board.size_m[0] * 1000, board.size_m[1] * 1000))


def test_pdf_svg_and_png_carry_the_same_sheet():
    board = BOARDS[0]
    sheet = board_sheet(board, "A4")
    assert sheet.size == (297.0, 210.0)  # 210 mm wide: landscape is what fits
    pdf = pdf_bytes(sheet, compress=False)
    box = [float(v) for v in re.search(rb"/MediaBox \[([^\]]*)\]", pdf)[1].split()]
    assert box[2] * MM_PER_POINT == pytest.approx(297.0, abs=1e-3) and box[3] * MM_PER_POINT == pytest.approx(210.0, abs=1e-3)
    assert pdf.count(b" re f") == len(sheet.rects) + len(sheet.holes)
    assert pdf_bytes(sheet) == pdf_bytes(sheet) and pdf_bytes(sheet).startswith(b"%PDF-")  # same sheet, same bytes
    svg = ElementTree.fromstring(svg_text(sheet))
    assert svg.get("width") == "297mm" and svg.get("height") == "210mm"
    rects = [e for e in svg if e.tag.endswith("rect")]
    assert len(rects) == 1 + len(sheet.rects) + len(sheet.holes)
    png = Image.open(io.BytesIO(png_bytes(sheet, 300)))
    assert png.size == (round(297 / 25.4 * 300), round(210 / 25.4 * 300))
    assert png.info["dpi"] == pytest.approx((300, 300), abs=0.01)


def test_a_board_that_does_not_fit_names_a_paper_that_does():
    with pytest.raises(PrintError, match=r"needs 240 x 202 mm .* use --paper letter"):
        board_sheet(BoardSpec(8, 6, 0.03, 0.022, "DICT_6X6_250"), "A4")
    with pytest.raises(PrintError, match=r"use --paper \d+x\d+mm"):
        board_sheet(BoardSpec(30, 20, 0.03, 0.022, "DICT_6X6_1000"), "A3")
    assert paper_size("500x700mm") == (500.0, 700.0) and paper_size("Letter") == (215.9, 279.4)
    with pytest.raises(PrintError, match="unknown paper 'B7'"):
        paper_size("B7")


def test_board_command_writes_the_sheet_and_the_new_board_file(tmp_path, capsys):
    out = tmp_path / "prints" / "my_board"
    assert board_main(["--squares", "7x5", "--dictionary", "DICT_6X6_250", "--square", "30mm", "--marker", "2.2cm",
                       "--out", str(out), "--format", "png", "--dpi", "100"]) == 0
    assert "Print at 100 %" in capsys.readouterr().out
    assert BoardSpec.load(out.with_suffix(".yaml")) == BoardSpec(7, 5, 0.03, 0.022, "DICT_6X6_250")
    assert out.with_suffix(".pdf").read_bytes().startswith(b"%PDF-")
    png = cv2.imread(str(out.with_suffix(".png")), cv2.IMREAD_GRAYSCALE)
    assert len(OpenCVDetector(BoardSpec.load(out.with_suffix(".yaml"))).detect(png)) == 24
    # From a board file: the sheet only, in the format --out names.
    assert board_main([str(out.with_suffix(".yaml")), "--out", str(tmp_path / "sheet.svg")]) == 0
    assert (tmp_path / "sheet.svg").read_text().startswith("<?xml")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["prints", "sheet.svg"]


@pytest.mark.parametrize("argv, message", [
    (["--squares", "12x9", "--dictionary", "DICT_6X6_250", "--square", "30mm", "--marker", "22mm"], "needs 360 x 292 mm"),
    (["--squares", "7x5", "--dictionary", "DICT_6X6_250", "--square", "30", "--marker", "22mm"], "with its unit"),
    (["--squares", "7x5", "--dictionary", "DICT_6X6_250", "--square", "30mm"], "--marker missing"),
    (["--squares", "7x5", "--dictionary", "DICT_6X6_250", "--square", "20mm", "--marker", "22mm"],
     "--marker (0.022 m) must be smaller than --square"),
    (["--squares", "7x5", "--dictionary", "DICT_6X6_250", "--square", "30mm", "--marker", "22mm", "--paper", "B7"],
     "unknown paper 'B7'"),
    # A PNG at 20000 dpi was a numpy MemoryError after asking for 36 GiB; a huge paper as PNG the same.
    (["--squares", "7x5", "--dictionary", "DICT_6X6_250", "--square", "30mm", "--marker", "22mm", "--format", "png",
      "--dpi", "20000"], "at 20000 dpi is 38,669 megapixels (at most 600): give --dpi 2491 or less"),
    (["--squares", "7x5", "--dictionary", "DICT_6X6_250", "--square", "30mm", "--marker", "22mm", "--format", "png",
      "--paper", "3000x4000mm"], "give --dpi 179 or less, or write the sheet as PDF or SVG"),
    # A PNG whose marker bits are under 2 px (0.54 px at 5 dpi): written, exit 0, and no detector read it.
    (["--squares", "7x5", "--dictionary", "DICT_6X6_250", "--square", "30mm", "--marker", "22mm", "--format", "png",
      "--dpi", "5"], "at 5 dpi the markers' bits are 0.54 px wide in the PNG"),
    # Written without a word before: an 80 m "paper", markers whose bits no printer draws.
    (["--squares", "7x5", "--dictionary", "DICT_6X6_250", "--square", "30mm", "--marker", "22mm", "--paper",
      "80000x1000mm"], "is 80 m long: no printer takes a sheet over 5 m"),
    (["--squares", "7x5", "--dictionary", "DICT_6X6_250", "--square", "0.007mm", "--marker", "0.005mm"],
     "markers of 0.005 mm have bits of 0.000625 mm"),
])
def test_board_command_refuses_in_one_line_and_writes_nothing(tmp_path, capsys, argv, message):
    assert board_main([*argv, "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and message in err[0]
    assert list(tmp_path.iterdir()) == []


def test_another_file_types_suffix_is_refused_and_inches_are_stored_to_the_nanometre(tmp_path, capsys):
    """--out board.tiff was written as board.tiff.pdf without a word; --marker 0.75in was stored as
    0.019049999999999997 m."""
    args = ["--squares", "7x5", "--dictionary", "DICT_6X6_250", "--square", "1in", "--marker", "0.75in"]
    assert board_main([*args, "--out", str(tmp_path / "board.tiff")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "a sheet is written as PDF, SVG or PNG, not TIFF: give board.pdf" in err[0]
    assert list(tmp_path.iterdir()) == []
    assert board_main([*args, "--out", str(tmp_path / "board_v1.2")]) == 0  # a dot in a name is not a file type
    text = (tmp_path / "board_v1.2.yaml").read_text()
    assert "square_length: 0.0254\n" in text and "marker_length: 0.01905\n" in text


def test_a_missing_sheet_library_is_one_line_and_writes_nothing(tmp_path, capsys, monkeypatch):
    """A PDF without ReportLab (an install made with --no-deps, a distribution's packages) is refused in one line
    naming the package and another format; no sheet and no board file are written, and SVG still works."""
    monkeypatch.setitem(sys.modules, "reportlab.pdfgen", None)  # import of it raises ImportError
    args = ["--squares", "5x7", "--dictionary", "DICT_4X4_50", "--square", "30mm", "--marker", "22mm"]
    assert board_main([*args, "--out", str(tmp_path / "new")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "a PDF sheet needs reportlab, which is not installed: pip install reportlab," in err
    assert list(tmp_path.iterdir()) == []
    assert board_main([*args, "--out", str(tmp_path / "new.svg")]) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["new.svg", "new.yaml"]


def test_board_command_keeps_foreign_files_and_unwritable_outputs_are_errors(tmp_path, capsys, unwritable_dir):
    board = BOARDS[0].save(tmp_path / "board.yaml")
    notes = tmp_path / "notes.pdf"
    notes.write_text("my notes")
    assert board_main([str(board), "--out", str(notes)]) == 2
    assert "exists and is not a sheet written by deepcharuco board" in capsys.readouterr().err
    assert notes.read_text() == "my notes"
    assert board_main([str(board), "--out", str(unwritable_dir / "b.pdf")]) == 2
    assert "error: " in capsys.readouterr().err
    assert board_main([str(board), "--squares", "7x5", "--out", str(tmp_path / "x")]) == 2
    assert "not both" in capsys.readouterr().err


def test_the_deepcharuco_command_dispatches_and_names_missing_extras(tmp_path, capsys, monkeypatch):
    assert deepcharuco_main(["--help"]) == 0
    listed = capsys.readouterr().out
    assert all(name in listed for name in ("detect", "calibrate", "board", "report", "train"))
    assert deepcharuco_main(["frobnicate"]) == 2 and "unknown subcommand 'frobnicate'" in capsys.readouterr().err
    board = BOARDS[0].save(tmp_path / "board.yaml")
    assert deepcharuco_main(["board", str(board), "--out", str(tmp_path / "b.pdf")]) == 0
    assert (tmp_path / "b.pdf").is_file()
    import importlib

    real = importlib.import_module

    def without_matplotlib(name, *args):
        if name == "evaluate.report":
            raise ModuleNotFoundError("No module named 'matplotlib'", name="matplotlib")
        return real(name, *args)

    monkeypatch.setattr(importlib, "import_module", without_matplotlib)
    assert deepcharuco_main(["report"]) == 2
    assert "deepcharuco report needs matplotlib" in capsys.readouterr().err


def test_the_commands_and_both_detectors_run_without_torch(tmp_path):
    """With PyTorch unimportable, detect (OpenCV's detector and the deep one, from the shipped ONNX bundles),
    calibrate's imports and the board sheets work; weights with no bundle say what to do in one line."""
    import subprocess
    import sys

    examples = ROOT / "deepcharuco" / "examples"
    image, camera = examples / "board_320x240.png", examples / "webcam_320x240.yaml"
    (tmp_path / "lonely.pt").write_bytes(b"a PyTorch checkpoint without its ONNX bundle")
    code = f"""
import json, sys
sys.modules["torch"] = None  # any import of torch fails
from deepcharuco.cli.main import main
for detector in ("opencv", "deep"):
    assert main(["detect", r"{image}", "--camera", r"{camera}", "--detector", detector,
                 "--out", r"{tmp_path}" + "/" + detector]) == 0
    frame = json.load(open(r"{tmp_path}" + "/" + detector + "/board_320x240.json"))["frames"][0]
    assert frame["num_corners"] >= 15 and frame["pose"]["reprojection_error"] < 0.3, frame
assert main(["board", "--squares", "5x5", "--dictionary", "DICT_5X5_50", "--square", "35mm", "--marker", "26mm",
             "--out", r"{tmp_path / 'b'}"]) == 0
assert main(["detect", r"{image}", "--detector", "deep", "--weights", r"{tmp_path / 'lonely.pt'}",
             "--out", r"{tmp_path / 'x'}"]) == 2
import deepcharuco.cli.calibrate

assert "torch" not in {{name.split(".")[0] for name, module in sys.modules.items() if module is not None}}
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "lonely.pt is a PyTorch checkpoint and PyTorch is not installed" in done.stderr
    assert "deepcharuco export --bundle" in done.stderr and "Traceback" not in done.stderr
    assert (tmp_path / "b.pdf").is_file()


def pdf_fills(path) -> tuple[tuple[float, float], list[tuple[float, float, float, float, float]]]:
    """The page size (w, h) mm and the filled rectangles (grey 0-1, x, y, w, h in mm from the page's top-left) of a
    one-page PDF as written: its content stream decoded (ASCII85 and Flate, as ReportLab writes it) and its
    operators run (q Q cm g re f f*): what a printer draws, not what the sheet asked for."""
    import base64
    import zlib

    data = path.read_bytes()
    box = [float(v) for v in re.search(rb"/MediaBox \[([^\]]*)\]", data)[1].split()]
    page = ((box[2] - box[0]) * MM_PER_POINT, (box[3] - box[1]) * MM_PER_POINT)
    contents = re.search(rb"/Contents (\d+) 0 R", data)[1]
    stream = re.search(rb"\n" + contents + rb" 0 obj\s*<<(.*?)>>\s*stream\r?\n(.*?)endstream", data, re.S)
    body = stream[2]
    for name in re.findall(rb"/(\w+)", stream[1].split(b"/Filter", 1)[1]) if b"/Filter" in stream[1] else []:
        if name == b"ASCII85Decode":
            body = base64.a85decode(body.strip().removesuffix(b"~>"))
        elif name == b"FlateDecode":
            body = zlib.decompress(body)
        elif name != b"Length":
            raise AssertionError(f"a filter this test does not read: {name}")
    ctm, saved, grey, path_rects, fills, operands = np.eye(3), [], 0.0, [], [], []
    for token in re.findall(rb"\((?:\\.|[^\\)])*\)|[^\s()]+", body):
        if re.fullmatch(rb"[-+]?(\d+\.?\d*|\.\d+)", token):
            operands.append(float(token))
            continue
        op = token.decode("latin-1")
        if op == "cm":
            a, b, c, d, e, f = operands[-6:]
            ctm = np.array([[a, b, 0], [c, d, 0], [e, f, 1]]) @ ctm
        elif op == "q":
            saved.append((ctm.copy(), grey))
        elif op == "Q":
            ctm, grey = saved.pop()
        elif op == "g":
            grey = operands[-1]
        elif op == "re":
            x, y, w, h = operands[-4:]
            assert abs(ctm[0, 1]) < 1e-12 and abs(ctm[1, 0]) < 1e-12, "a rotated page: not read here"
            (x0, y0, _), (x1, y1, _) = np.array([[x, y, 1], [x + w, y + h, 1]]) @ ctm
            path_rects.append((min(x0, x1), max(y0, y1), abs(x1 - x0), abs(y1 - y0)))  # top-left corner, in points
        elif op in ("f", "f*", "F"):
            fills += [(grey, x * MM_PER_POINT, page[1] - top * MM_PER_POINT, w * MM_PER_POINT, h * MM_PER_POINT)
                      for x, top, w, h in path_rects]
            path_rects = []
        elif op == "n":
            path_rects = []
        operands = []
    return page, fills


def test_the_written_pdf_draws_the_board_at_its_true_size(tmp_path):
    """Measured in the PDF file `deepcharuco board` writes (its drawing operators, not the sheet in memory): the
    page is A4, every chessboard square is 30.000 mm and lies on a 30 mm grid, every marker's outline is 22.000 mm
    (to 0.005 mm: the 7 significant digits ReportLab writes), and drawn from those operators OpenCV finds the
    board's 24 corners 30 mm apart to 0.01 mm."""
    board = BOARDS[0]
    assert board_main([str(board.save(tmp_path / "board.yaml")), "--out", str(tmp_path / "board.pdf")]) == 0
    page, fills = pdf_fills(tmp_path / "board.pdf")
    assert page == pytest.approx((297.0, 210.0), abs=1e-3)
    square, marker = board.square_length * 1000, board.marker_length * 1000
    black = np.array([f[1:] for f in fills if f[0] == 0])
    squares = black[(np.abs(black[:, 2:] - square) < 0.5).all(1)]
    assert len(squares) == (board.squares_x * board.squares_y + 1) // 2, len(squares)  # the black squares
    assert np.abs(squares[:, 2:] - square).max() < 0.005
    origin = squares[:, :2].min(0)
    steps = (squares[:, :2] - origin) / square
    assert np.abs(steps - np.round(steps)).max() * square < 0.005  # on the square grid
    bits = black[(black[:, 2:] < square - 0.5).all(1)]
    cells = np.floor((bits[:, :2] + bits[:, 2:] / 2 - origin) / square).astype(int)
    outlines = []
    for cell in np.unique(cells, axis=0):  # each white square's marker: the extent of its black bits
        inside = bits[(cells == cell).all(1)]
        outlines.append((inside[:, :2] + inside[:, 2:]).max(0) - inside[:, :2].min(0))
    assert len(outlines) == board.squares_x * board.squares_y // 2
    assert np.abs(np.array(outlines) - marker).max() < 0.005, outlines
    # Drawn from the PDF's rectangles at 8 px/mm and halved (1 mm = 4 px), OpenCV finds the board.
    image = np.full((round(page[1] * 8), round(page[0] * 8)), 255, np.uint8)
    for grey, x, y, w, h in fills:
        image[round(y * 8):round((y + h) * 8), round(x * 8):round((x + w) * 8)] = round(grey * 255)
    found = OpenCVDetector(board).detect(cv2.resize(image, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA))
    assert len(found) == board.num_corners
    mm = (found.corners + 0.5) / 4.0
    expected = board.object_points()[found.ids, :2] * 1000.0
    offset = (mm - expected).mean(0)
    assert np.abs(mm - expected - offset).max() < 0.01
def test_board_command_replaces_only_the_files_it_wrote(tmp_path, capsys):
    """A camera frame saved as photo.png, a user's PDF and SVG, and the user's own commented board file are each
    of the format a sheet or board file has, and kept: refused in one line naming --force, nothing written. What
    the command wrote (a mark inside each file: the PDF's creator, an SVG comment, a PNG text chunk, the board
    file's first comment) it replaces unasked; --force replaces the user's."""
    describe = ["--squares", "5x7", "--dictionary", "DICT_4X4_50", "--square", "30mm", "--marker", "22mm"]
    board = BOARDS[0].save(tmp_path / "board.yaml")
    frame = cv2.imencode(".png", np.random.default_rng(0).integers(0, 256, (48, 64), dtype=np.uint8))[1].tobytes()
    theirs = {"photo.png": frame, "user.pdf": b"%PDF-1.4\n% a user's document\n%%EOF\n",
              "user.svg": b'<?xml version="1.0"?>\n<svg xmlns="http://www.w3.org/2000/svg"/>\n',
              "myboard.yaml": b"%YAML:1.0\n---\n# my board, measured with calipers\nsquares_x: 5\nsquares_y: 7\n"
                              b"square_length: 0.0301\nmarker_length: 0.022\ndictionary: DICT_4X4_50\n"}
    for name, data in theirs.items():
        (tmp_path / name).write_bytes(data)
        argv = [*describe, "--out", str(tmp_path / "myboard")] if name == "myboard.yaml" else \
            [str(board), "--out", str(tmp_path / name)]
        assert board_main(argv) == 2, name
        error = capsys.readouterr().err.strip().splitlines()
        assert len(error) == 1 and "written by deepcharuco board" in error[0] and "--force" in error[0], error
        assert (tmp_path / name).read_bytes() == data
        assert not (tmp_path / "myboard.pdf").exists()
        assert board_main([*argv, "--force"]) == 0 and (tmp_path / name).read_bytes() != data
        assert board_main(argv) == 0, name  # now the command's own: replaced unasked
    assert BoardSpec.load(tmp_path / "myboard.yaml") == BoardSpec(5, 7, 0.03, 0.022, "DICT_4X4_50")


@pytest.mark.parametrize("dpi", ["nan", "inf", "-3"])
def test_a_dpi_that_is_not_a_positive_number_is_refused(tmp_path, capsys, dpi):
    """--dpi nan and inf ended in tracebacks (numpy casting them to a size)."""
    with pytest.raises(SystemExit) as stop:
        board_main([str(BOARDS[0].save(tmp_path / "board.yaml")), "--out", str(tmp_path / "b.png"), "--dpi", dpi])
    assert stop.value.code == 2 and "--dpi must be a positive number" in capsys.readouterr().err
    assert not (tmp_path / "b.png").exists()
