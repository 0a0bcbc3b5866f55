"""A board as a printable sheet at true size: its shapes in millimetres, and that sheet as PDF, SVG or PNG.

`board_sheet` lays the board out on a paper size (portrait or landscape, whichever fits inside the
printer's margin) as filled rectangles: the black squares and each marker's black cells, from the
board's own OpenCV layout (`BoardSpec.cv_board`), so the print is the board the detectors look for.
An inverted board is drawn as its negative with a black quiet zone half a square wide (so that the
negated photo shows OpenCV's white margin); a mirrored board is drawn left-right mirrored. Below the
board: a 100 mm ruler (to check that the printer kept the scale) and the board's description. The
renderers draw one `Sheet`: `pdf_bytes` (vector, ReportLab), `svg_text` (vector) and `png_bytes`
(raster at a DPI, which the PNG records).

Coordinates: millimetres, origin at the paper's top-left corner, x to the right, y down.
"""

from __future__ import annotations

import io
import math
import re
from dataclasses import dataclass, field
from xml.etree import ElementTree

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.core.errors import DeepCharucoError
from deepcharuco.core.files import png_marked

PAPERS_MM = {"A4": (210.0, 297.0), "A3": (297.0, 420.0), "A5": (148.0, 210.0), "letter": (215.9, 279.4),
             "legal": (215.9, 355.6), "tabloid": (279.4, 431.8)}
MARGIN_MM = 5.0  # what most printers cannot print near the paper's edge (4-5 mm)
RULER_MM = 100.0  # the ruler's length: long enough to show a 1 % scaling error (1 mm)
CAPTION_MM = 22.0  # room below the board for the ruler and the description
MM_PER_POINT = 25.4 / 72.0
MAX_PAPER_MM = 5000.0  # the widest roll printers print 5 m: a larger "paper" is a typing slip
# A marker's bit cell under this cannot be printed: a 600 dpi printer's dot is 0.042 mm, and a bit needs a few.
MIN_BIT_MM = 0.1
# A PNG sheet's pixels (one byte each, and the encoder's copies): A0 at 600 dpi is 0.56 G. Beyond, a vector format.
MAX_PNG_PIXELS = 600_000_000
# Inside every sheet written (PDF creator, SVG comment, PNG text chunk): `deepcharuco board` replaces only such files.
SHEET_MARK = "deepcharuco board"


class PrintError(DeepCharucoError):
    """A board that does not fit the paper, an unknown paper size, or an output format this cannot write."""


@dataclass
class Sheet:
    """A page of ``size`` (width, height) mm: black ``rects`` (x, y, w, h), a white ``holes`` list drawn over
    them (x, y, w, h; the white cells of an inverted board), ruler ``lines`` (x0, y0, x1, y1, width) and
    ``texts`` (x, y, size in points, text); ``board_box`` is where the square grid lies (x, y, w, h)."""

    size: tuple[float, float]
    board_box: tuple[float, float, float, float]
    rects: list[tuple[float, float, float, float]] = field(default_factory=list)
    holes: list[tuple[float, float, float, float]] = field(default_factory=list)
    lines: list[tuple[float, float, float, float, float]] = field(default_factory=list)
    texts: list[tuple[float, float, float, str]] = field(default_factory=list)


def paper_size(name: str) -> tuple[float, float]:
    """(width, height) mm of a paper name (A4, A3, A5, letter, legal, tabloid; any case) or of ``WxHmm``
    (e.g. ``500x700mm``). `PrintError` otherwise."""
    for paper, size in PAPERS_MM.items():
        if name.lower() == paper.lower():
            return size
    match = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*x\s*(\d+(?:\.\d+)?)\s*mm\s*", name.lower())
    if match and float(match[1]) > 0 and float(match[2]) > 0:
        size = float(match[1]), float(match[2])
        if max(size) > MAX_PAPER_MM:
            raise PrintError(f"paper {name!r} is {max(size) / 1000:g} m long: no printer takes a sheet over "
                             f"{MAX_PAPER_MM / 1000:g} m; give the paper the printer takes (a roll's width x length)")
        return size
    raise PrintError(f"unknown paper {name!r}: use {', '.join(PAPERS_MM)} or a size such as 500x700mm")


def check_printable(board: BoardSpec) -> None:
    """`PrintError` where the board's marker bits are under `MIN_BIT_MM`: no printer draws them."""
    bits = board.cv_dictionary().markerSize + 2  # the code and its black border
    bit_mm = board.marker_length * 1000.0 / bits
    if bit_mm < MIN_BIT_MM:
        raise PrintError(f"markers of {board.marker_length * 1000:g} mm have bits of {bit_mm:.3g} mm ({bits} a side): "
                         f"a printer's dot is ~0.04 mm, so no printer draws them; give markers of "
                         f"{MIN_BIT_MM * bits:g} mm or more")


# A PNG's marker bit cell under this many pixels: its edges fall anywhere in a pixel (no anti-aliasing), so bits merge
# and split (at 5 dpi, 0.84 px a bit, no detector found the board; at 20 dpi, 3.4 px, it was found).
MIN_BIT_PX = 2.0


def check_png_resolution(board: BoardSpec, dpi: float) -> None:
    """`PrintError` where a PNG at ``dpi`` draws the board's marker bits under `MIN_BIT_PX` pixels, naming the
    lowest dpi that draws them."""
    bits = board.cv_dictionary().markerSize + 2
    bit_px = board.marker_length * 1000.0 / bits * dpi / 25.4
    if bit_px < MIN_BIT_PX:
        lowest = math.ceil(MIN_BIT_PX * bits * 25.4 / (board.marker_length * 1000.0))
        raise PrintError(f"at {dpi:g} dpi the markers' bits are {bit_px:.2g} px wide in the PNG: they blur into each "
                         f"other and no detector reads them; give --dpi {lowest} or more (300 for printing), or write "
                         f"the sheet as PDF or SVG")


def check_png_size(paper_mm: tuple[float, float], dpi: float) -> None:
    """`PrintError` where a PNG of ``paper_mm`` at ``dpi`` would exceed `MAX_PNG_PIXELS` (memory: one byte a
    pixel and the encoder's copies), naming the largest dpi that fits and the vector formats."""
    pixels = paper_mm[0] * paper_mm[1] * (dpi / 25.4) ** 2
    if pixels > MAX_PNG_PIXELS:
        largest = int(25.4 * math.sqrt(MAX_PNG_PIXELS / (paper_mm[0] * paper_mm[1])))
        raise PrintError(f"a PNG of {paper_mm[0]:g} x {paper_mm[1]:g} mm at {dpi:g} dpi is {pixels / 1e6:,.0f} megapixels "
                         f"(at most {MAX_PNG_PIXELS / 1e6:,.0f}): give --dpi {largest} or less, or write the sheet as "
                         f"PDF or SVG (vector: sharp at any size)")


def board_shapes(board: BoardSpec) -> list[tuple[float, float, float, float]]:
    """The board's black rectangles (x, y, w, h) in mm from the grid's top-left corner, as OpenCV prints it
    (black squares, and each marker's black cells), before inversion or mirroring."""
    square = board.square_length * 1000.0
    ids, corners = board.marker_corners()
    dictionary = board.cv_dictionary()
    cells = dictionary.markerSize + 2  # the marker's bits and its one-cell black border
    holds_marker = set()
    rects = []
    for marker_id, quad in zip(ids, corners):
        x0, y0 = quad[0, :2] * 1000.0  # top-left corner (board frame: x right, y down, metres)
        holds_marker.add((int((quad[:, 0].mean() * 1000.0) // square), int((quad[:, 1].mean() * 1000.0) // square)))
        cell = board.marker_length * 1000.0 / cells
        bits = cv2.aruco.generateImageMarker(dictionary, int(marker_id), cells, borderBits=1)
        for row, col in zip(*np.nonzero(bits == 0)):
            rects.append((x0 + col * cell, y0 + row * cell, cell, cell))
    squares = [(col * square, row * square, square, square)
               for row in range(board.squares_y) for col in range(board.squares_x) if (col, row) not in holds_marker]
    return squares + rects


def board_sheet(board: BoardSpec, paper: str = "A4") -> Sheet:
    """``board`` at true size, centred on ``paper`` (portrait or landscape, whichever fits inside
    `MARGIN_MM` with room for the ruler and caption below); `PrintError` naming what would fit otherwise."""
    width_mm, height_mm = (v * 1000.0 for v in board.size_m)
    zone = board.square_length * 500.0 if board.inverted else 0.0  # an inverted print's black quiet zone: half a square
    need = (width_mm + 2 * zone, height_mm + 2 * zone + CAPTION_MM)
    paper_w, paper_h = paper_size(paper)
    fits = _orientations_that_fit(need, (paper_w, paper_h))
    if not fits:
        larger = next((name for name, size in sorted(PAPERS_MM.items(), key=lambda item: item[1][0] * item[1][1])
                       if _orientations_that_fit(need, size)), None)
        custom = f"{math.ceil(need[0] + 2 * MARGIN_MM)}x{math.ceil(need[1] + 2 * MARGIN_MM)}mm"
        raise PrintError(
            f"a {board.squares_x}x{board.squares_y} board of {board.square_length * 1000:g} mm squares needs "
            f"{need[0]:.0f} x {need[1]:.0f} mm (with {'its quiet zone, ' if zone else ''}the ruler and caption) but "
            f"{paper} holds {paper_w - 2 * MARGIN_MM:.0f} x {paper_h - 2 * MARGIN_MM:.0f} mm inside its "
            f"{MARGIN_MM:g} mm margins: use --paper {larger or custom}, smaller squares or fewer of them")
    size = fits[0]
    left = (size[0] - need[0]) / 2.0 + zone
    top = (size[1] - need[1]) / 2.0 + zone
    sheet = Sheet(size=size, board_box=(left, top, width_mm, height_mm))
    shapes = board_shapes(board)
    if board.mirrored:
        shapes = [(width_mm - x - w, y, w, h) for x, y, w, h in shapes]
    shapes = [(left + x, top + y, w, h) for x, y, w, h in shapes]
    if board.inverted:  # the negative: black everywhere (quiet zone included), the black shapes white
        sheet.rects.append((left - zone, top - zone, width_mm + 2 * zone, height_mm + 2 * zone))
        sheet.holes.extend(shapes)
    else:
        sheet.rects.extend(shapes)
    _add_caption(sheet, board, top + height_mm + zone + 6.0, paper)
    return sheet


def _orientations_that_fit(need: tuple[float, float], paper: tuple[float, float]) -> list[tuple[float, float]]:
    """The paper's (width, height) portrait then landscape, where ``need`` (w, h mm) fits inside the margins."""
    return [size for size in (paper, paper[::-1])
            if need[0] <= size[0] - 2 * MARGIN_MM and need[1] <= size[1] - 2 * MARGIN_MM]


def _add_caption(sheet: Sheet, board: BoardSpec, y: float, paper: str) -> None:
    """The ruler (`RULER_MM` long, a tick every mm, longer every 5 and 10) and the board's description."""
    ruler = min(RULER_MM, sheet.size[0] - 2 * MARGIN_MM)
    x0 = (sheet.size[0] - ruler) / 2.0
    sheet.lines.append((x0, y, x0 + ruler, y, 0.2))
    for mm in range(int(ruler) + 1):
        length = 4.0 if mm % 10 == 0 else 2.5 if mm % 5 == 0 else 1.5
        sheet.lines.append((x0 + mm, y, x0 + mm, y + length, 0.15))
        if mm % 10 == 0:
            sheet.texts.append((x0 + mm - 1.0, y + 7.0, 6.0, str(mm // 10)))
    flags = [name for name in ("legacy", "inverted", "mirrored") if getattr(board, name)]
    first = f", markers from ID {board.first_marker_id}" if board.first_marker_id else ""
    sheet.texts.append((x0, y + 11.5, 7.0, f"this ruler is {ruler:g} mm (cm marked): print at 100 % / actual size, "
                                           f"then check it"))
    sheet.texts.append((x0, y + 15.0, 7.0, f"{board.squares_x}x{board.squares_y} {board.dictionary}{first}, squares "
                                           f"{board.square_length * 1000:g} mm, markers {board.marker_length * 1000:g} mm"
                                           + (f", {', '.join(flags)}" if flags else "") + f" ({paper})"))


# ------------------------------------------------------------------------------------------------ renderers

def pdf_bytes(sheet: Sheet, compress: bool = True) -> bytes:
    """The sheet as a one-page vector PDF (ReportLab; page size = the sheet's; the same bytes for the same
    sheet). ``compress=False`` leaves the drawing operators readable."""
    from reportlab.pdfgen import canvas

    buffer = io.BytesIO()
    pt = 1.0 / MM_PER_POINT
    page = canvas.Canvas(buffer, pagesize=(sheet.size[0] * pt, sheet.size[1] * pt), invariant=1,
                         pageCompression=int(compress))
    page.setCreator(SHEET_MARK)  # the document information (uncompressed): how a rerun knows the file as its own
    height = sheet.size[1]
    for colour, boxes in ((0, sheet.rects), (1, sheet.holes)):
        page.setFillGray(colour)
        for x, y, w, h in boxes:
            page.rect(x * pt, (height - y - h) * pt, w * pt, h * pt, stroke=0, fill=1)
    for x0, y0, x1, y1, width in sheet.lines:
        page.setLineWidth(width * pt)
        page.line(x0 * pt, (height - y0) * pt, x1 * pt, (height - y1) * pt)
    page.setFillGray(0)
    for x, y, size, text in sheet.texts:
        page.setFont("Helvetica", size)
        page.drawString(x * pt, (height - y) * pt, text)
    page.showPage()
    page.save()
    return buffer.getvalue()


def svg_text(sheet: Sheet) -> str:
    """The sheet as an SVG document whose width and height are in mm (user units: mm)."""
    w, h = sheet.size
    svg = ElementTree.Element("svg", xmlns="http://www.w3.org/2000/svg", width=f"{w:g}mm", height=f"{h:g}mm",
                              viewBox=f"0 0 {w:g} {h:g}")
    ElementTree.SubElement(svg, "rect", x="0", y="0", width=f"{w:g}", height=f"{h:g}", fill="white")
    for colour, boxes in (("black", sheet.rects), ("white", sheet.holes)):
        for x, y, bw, bh in boxes:
            ElementTree.SubElement(svg, "rect", x=f"{x:.4f}", y=f"{y:.4f}", width=f"{bw:.4f}", height=f"{bh:.4f}",
                                   fill=colour)
    for x0, y0, x1, y1, width in sheet.lines:
        ElementTree.SubElement(svg, "line", x1=f"{x0:.4f}", y1=f"{y0:.4f}", x2=f"{x1:.4f}", y2=f"{y1:.4f}",
                               stroke="black", **{"stroke-width": f"{width:g}"})
    for x, y, size, text in sheet.texts:
        label = ElementTree.SubElement(svg, "text", x=f"{x:.3f}", y=f"{y:.3f}", fill="black",
                                       **{"font-family": "Helvetica, Arial, sans-serif",
                                          "font-size": f"{size * MM_PER_POINT:.3f}"})
        label.text = text
    return (f'<?xml version="1.0" encoding="UTF-8"?>\n<!-- {SHEET_MARK} -->\n'
            + ElementTree.tostring(svg, encoding="unicode") + "\n")


def raster(sheet: Sheet, dpi: float) -> np.ndarray:
    """The sheet as an (H, W) uint8 image at ``dpi``; a pixel covers [x, x + 1) in its scale (no anti-aliasing:
    edges fall on whole pixels, rounded)."""
    scale = dpi / 25.4
    image = np.full((round(sheet.size[1] * scale), round(sheet.size[0] * scale)), 255, np.uint8)
    for value, boxes in ((0, sheet.rects), (255, sheet.holes)):
        for x, y, w, h in boxes:
            image[round(y * scale):round((y + h) * scale), round(x * scale):round((x + w) * scale)] = value
    for x0, y0, x1, y1, width in sheet.lines:
        cv2.line(image, (round(x0 * scale), round(y0 * scale)), (round(x1 * scale), round(y1 * scale)), 0,
                 max(1, round(width * scale)))
    for x, y, size, text in sheet.texts:
        height_px = size * MM_PER_POINT * scale
        cv2.putText(image, text, (round(x * scale), round(y * scale)), cv2.FONT_HERSHEY_SIMPLEX, height_px / 30.0, 0,
                    max(1, round(height_px / 15)), cv2.LINE_AA)
    return image


def png_bytes(sheet: Sheet, dpi: float = 300.0) -> bytes:
    """The sheet as a PNG at ``dpi``, which the file records (so that printing programs size it right)."""
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(raster(sheet, dpi)).save(buffer, format="PNG", dpi=(dpi, dpi))
    return png_marked(buffer.getvalue(), SHEET_MARK)
