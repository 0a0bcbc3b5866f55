"""The calibration report (``deepcharuco.cli.calibrate`` writes it): one self-contained HTML page.

RMS and per-view errors, the coverage of the image by the views' corners, their residual
vectors, the distortion field of the solved model, every frame's fate (kept, or dropped and
why) and the parameters with their standard deviations. Built with `deepcharuco.calibration.html_page` (the page and
its matplotlib figures: the ``eval`` extra).
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.calibration.html_page import html_page, png, pyplot
from deepcharuco.calibration.intrinsics import CalibrationResult
from deepcharuco.core.files import write_atomic
from deepcharuco.core.opencv_api import undistort_points

MAX_LISTED = 200  # rows of the per-frame table; the counts by reason cover every frame


def ideal_pixels(result: CalibrationResult, pixels: np.ndarray) -> np.ndarray:
    """(N, 2) where the solved camera without distortion (its K alone) would put the rays of the (N, 2)
    distorted ``pixels``."""
    K, dist = result.camera.K, result.camera.dist
    points = np.asarray(pixels, np.float64).reshape(-1, 1, 2)
    if result.model == "fisheye":
        rays = cv2.fisheye.undistortPoints(points, K, dist)
    else:
        criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 200, 1e-12)
        rays = undistort_points(points, K, dist, None, criteria)
    rays = rays.reshape(-1, 2)
    return np.stack([K[0, 0] * rays[:, 0] + K[0, 1] * rays[:, 1] + K[0, 2], K[1, 1] * rays[:, 1] + K[1, 2]], axis=1)


def coverage_figure(result: CalibrationResult, bins: tuple[int, int] = (16, 12)) -> bytes:
    """Heat map of the kept views' corners over the image: where the calibration has evidence."""
    plt = pyplot()
    width, height = result.image_size
    corners = np.concatenate([v.corners for v in result.views]) if result.views else np.zeros((0, 2))
    counts, _, _ = np.histogram2d(corners[:, 0], corners[:, 1], bins=bins, range=[[-0.5, width - 0.5], [-0.5, height - 0.5]])
    figure, axis = plt.subplots(figsize=(5.2, 5.2 * height / width + 0.6))
    shown = axis.imshow(counts.T, extent=(-0.5, width - 0.5, height - 0.5, -0.5), cmap="viridis", interpolation="nearest")
    figure.colorbar(shown, ax=axis, fraction=0.046, pad=0.04, label="corners")
    empty = int((counts == 0).sum())
    axis.set_title(f"Coverage: {len(corners)} corners of {len(result.views)} views\n{empty} of {counts.size} cells empty")
    axis.set_xlabel("x (px)")
    axis.set_ylabel("y (px)")
    return png(figure)


def residual_figure(result: CalibrationResult) -> bytes:
    """Each used corner's residual (detected minus reprojected) as an arrow from the corner, magnified."""
    plt = pyplot()
    width, height = result.image_size
    corners = np.concatenate([v.corners for v in result.views])
    residuals = np.concatenate(result.residuals)
    norms = np.linalg.norm(residuals, axis=1)
    gain = 0.04 * max(width, height) / max(float(np.percentile(norms, 95)), 1e-6)  # the p95 arrow: 4 % of the image
    figure, axis = plt.subplots(figsize=(5.2, 5.2 * height / width + 0.6))
    axis.quiver(corners[:, 0], corners[:, 1], residuals[:, 0] * gain, residuals[:, 1] * gain, norms, angles="xy",
                scale_units="xy", scale=1.0, cmap="plasma", width=0.003)
    axis.set_xlim(-0.5, width - 0.5)
    axis.set_ylim(height - 0.5, -0.5)
    axis.set_aspect("equal")
    axis.set_title(f"Residuals x {gain:.0f} (RMS {result.rms:.3f} px, max {norms.max():.2f} px)")
    axis.set_xlabel("x (px)")
    axis.set_ylabel("y (px)")
    return png(figure)


def distortion_figure(result: CalibrationResult, step: int | None = None) -> bytes:
    """The solved distortion: how far it moves each pixel from where the undistorted camera would put it
    (contours of the magnitude in px, arrows for the direction)."""
    plt = pyplot()
    width, height = result.image_size
    step = step or max(width, height) // 24
    xs, ys = np.meshgrid(np.arange(0, width, step, dtype=np.float64), np.arange(0, height, step, dtype=np.float64))
    pixels = np.stack([xs.ravel(), ys.ravel()], axis=1)
    displacement = pixels - ideal_pixels(result, pixels)
    magnitude = np.linalg.norm(displacement, axis=1).reshape(xs.shape)
    figure, axis = plt.subplots(figsize=(5.2, 5.2 * height / width + 0.6))
    levels = axis.contourf(xs, ys, magnitude, levels=12, cmap="magma_r")
    figure.colorbar(levels, ax=axis, fraction=0.046, pad=0.04, label="displacement (px)")
    axis.quiver(pixels[:, 0], pixels[:, 1], displacement[:, 0], displacement[:, 1], angles="xy", scale_units="xy",
                scale=max(float(magnitude.max()) / step, 1e-6) * 1.2, width=0.002, color="white")
    axis.set_xlim(0, xs.max())
    axis.set_ylim(ys.max(), 0)
    axis.set_aspect("equal")
    axis.set_title(f"Distortion field ({result.model}): up to {magnitude.max():.1f} px")
    return png(figure)


def view_error_figure(result: CalibrationResult) -> bytes:
    """RMS of each kept view against its frame number, and the frames dropped as outliers."""
    plt = pyplot()
    figure, axis = plt.subplots(figsize=(6.4, 2.8))
    frames = [v.index for v in result.views]
    axis.bar(frames, result.per_view_rms, width=max(1.0, (max(frames) - min(frames) + 1) / 150), color="tab:blue",
             label="kept view")
    outliers = [d for d in result.decisions if d.stage == "outlier"]
    if outliers:
        axis.scatter([d.index for d in outliers], [float(d.reason.split("RMS ")[1].split(" px")[0]) for d in outliers],
                     color="tab:red", marker="x", label="dropped: outlier")
    axis.axhline(result.rms, color="gray", ls=":", lw=1, label=f"overall RMS {result.rms:.3f} px")
    axis.set_xlabel("frame")
    axis.set_ylabel("view RMS (px)")
    axis.legend(fontsize=8)
    axis.grid(alpha=0.3)
    return png(figure)


def parameter_rows(result: CalibrationResult) -> list[list[str]]:
    """Table rows (header first): each intrinsic parameter, its value and standard deviation."""
    K, dist = result.camera.K, result.camera.dist
    names = ["fx", "fy", "cx", "cy"] + (["k1", "k2", "k3", "k4"] if result.model == "fisheye"
                                        else ["k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"][:len(dist)])
    values = [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist]
    rows = [["parameter", "value", "std dev"]]
    for name, value in zip(names, values):
        deviation = result.std.get(name)
        rows.append([name, f"{value:.6g}", "n/a" if deviation is None else f"{deviation:.3g}"])
    return rows


def _category(reason: str) -> str:
    """A reason without its numbers, to count frames by."""
    for prefix in ("near-duplicate", "not needed", "blurred", "outlier", "calibration view"):
        if reason.startswith(prefix):
            return prefix
    if "corners (fewer" in reason:
        return "too few corners"
    return reason


def report_sections(result: CalibrationResult, board: BoardSpec) -> list[tuple[str, str, list[list[str]] | None, list[str]]]:
    """The page's (title, text, rows, figure names)."""
    width, height = result.image_size
    kept = len(result.views)
    with_corners = sum(d.corners > 0 for d in result.decisions)
    summary = (f"**RMS reprojection error {result.rms:.3f} px** over {sum(len(v.ids) for v in result.views)} corners of "
               f"{kept} views, {result.model} model, {width}x{height} images; per-corner uncertainty (one corner's "
               f"standard deviation per axis, the fit's degrees of freedom taken out) {result.corner_sigma:.3f} px. "
               f"{result.frames} frames read, {with_corners} "
               f"with board corners; " + (f"solved {result.rounds} times, outliers rejected in between. " if result.rounds > 1
                                          else "solved once (no outliers). ") + "Board: "
               f"{board.squares_x}x{board.squares_y} {board.dictionary}, {board.num_corners} corners."
               + "".join(f" {note[0].upper()}{note[1:]}." for note in result.notes))
    terms = ""
    if result.terms:
        held = [name for name in ("p1", "p2", "k3") if name not in result.terms.split()]
        terms = f" Distortion terms solved: {result.terms}" + (f" ({' '.join(held)} held at 0)" if held else "") + "."
    if result.held_out:
        terms += (" Chosen by 5-fold cross-validation over the views (held-out views' RMS per axis, their poses' "
                  "6 degrees of freedom taken out): " + "; ".join(f"{name}: {score:.4f} px" for name, score in
                                                                  result.held_out.items()) + ".")
    weighed = ""
    if len(result.view_weights):
        terms += (" Views weighed by their residuals' spread (calibration.weigh_views; --equal-weights: all alike): "
                  f"{int(np.sum(result.view_weights < 1.0))} of {kept} weigh less along their noisiest direction, "
                  f"{int(np.sum(result.view_weights < 0.5))} less than half; the standard deviations are the weighted "
                  "fit's.")
        weighed = "the views weighed as below"
    source = weighed or "OpenCV's calibrateCameraExtended; the fisheye solver gives none"
    out = [("Summary", summary, None, []),
           ("Parameters", f"Values and standard deviations ({source}; n/a: held at 0 or not solved)." + terms,
            parameter_rows(result), ["distortion"]),
           ("Coverage and residuals", "Where the kept views' corners fall in the image (a calibration is trustworthy "
            "where it has corners, most of all for distortion near the edges and corners), and each corner's residual "
            "magnified: a pattern in the arrows means the model does not fit.", None, ["coverage", "residuals"]),
           ("Per-view errors", "RMS of each kept view; red crosses: views dropped as outliers before the last solve.",
            None, ["view_errors"])]
    counts = Counter((d.status, _category(d.reason)) for d in result.decisions)
    rows = [["status", "reason", "frames"]] + [[status, reason, str(n)] for (status, reason), n in
                                                sorted(counts.items(), key=lambda item: (item[0][0] != "kept", -item[1]))]
    out.append(("Views kept and dropped", "Every frame read, by what became of it.", rows, []))
    listed = [d for d in result.decisions if d.corners > 0]
    weights = dict(zip((v.index for v in result.views), result.view_weights))  # empty with equal weights
    rows = [["frame", "corners", "status", "reason", "RMS px", "weight"]]
    rows += [[d.name, str(d.corners), d.status, d.reason, "" if d.rms is None else f"{d.rms:.3f}",
              f"{weights[d.index]:.2f}" if d.index in weights else ""] for d in listed[:MAX_LISTED]]
    more = f" (the first {MAX_LISTED} of {len(listed)})" if len(listed) > MAX_LISTED else ""
    out.append(("Frames with corners", f"Each frame where the detector found corners{more}.", rows, []))
    return out


def report_html(result: CalibrationResult, board: BoardSpec, *, title: str = "Calibration report",
                command: str = "") -> str:
    """The HTML report of ``result``: one self-contained page (figures inlined)."""
    figures = {"coverage": coverage_figure(result), "residuals": residual_figure(result),
               "distortion": distortion_figure(result), "view_errors": view_error_figure(result)}
    return html_page(title, command, report_sections(result, board), figures)


def write_report(path: str | Path, result: CalibrationResult, board: BoardSpec, *, title: str = "Calibration report",
                 command: str = "") -> Path:
    """Write the HTML report of ``result`` to ``path`` (whole or not at all: `write_atomic`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_atomic(path, report_html(result, board, title=title, command=command))
