"""The rig calibration's report (``deepcharuco.cli.calibrate`` with several sources writes it): one HTML page.

Per camera its RMS, views and parameters with their standard deviations; the views each pair of cameras shared;
a 3-D plot of the cameras and the board's poses; every camera's residuals; the views dropped and why. Built with
`deepcharuco.calibration.html_page` (its figures need matplotlib: the ``eval`` extra).
"""

from __future__ import annotations

from collections import Counter

import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.calibration.html_page import html_page, png, pyplot
from deepcharuco.calibration.rig_model import RigResult, distortion_names, rotations_from_vectors
from deepcharuco.calibration.time_sync import Alignment

MAX_LISTED = 200


def layout_figure(result: RigResult, boards: list[BoardSpec]) -> bytes:
    """The cameras (centre and viewing direction) and each board's outline at every instant, in the rig's frame."""
    plt = pyplot()
    figure = plt.figure(figsize=(6.4, 5.2))
    axis = figure.add_subplot(projection="3d")
    for (_, b), (rvec, tvec) in result.board_poses.items():
        width, height = boards[b].size_m
        outline = np.array([[0, 0, 0], [width, 0, 0], [width, height, 0], [0, height, 0], [0, 0, 0]], np.float64)
        points = outline @ rotations_from_vectors(rvec)[0].T + tvec
        axis.plot(points[:, 0], points[:, 2], -points[:, 1], color="tab:gray" if b == 0 else f"C{b + 4}", lw=0.6,
                  alpha=0.6)
    reach = 0.25 * max(max(np.linalg.norm(result.centre(c) - result.centre(0)) for c in range(len(result.cameras))),
                       max(max(board.size_m) for board in boards))
    for c, name in enumerate(result.names):
        centre, axis_z = result.centre(c), result.rotations[c][2]
        tip = centre + reach * axis_z
        axis.scatter([centre[0]], [centre[2]], [-centre[1]], color=f"C{c}", s=30)
        axis.plot([centre[0], tip[0]], [centre[2], tip[2]], [-centre[1], -tip[1]], color=f"C{c}", lw=2)
        axis.text(centre[0], centre[2], -centre[1], f" {name}", color=f"C{c}", fontsize=8)
    axis.set_xlabel("x (m)")
    axis.set_ylabel("z (m)")
    axis.set_zlabel("-y (m)")
    axis.set_title(f"{len(result.cameras)} cameras, {len(result.board_poses)} board poses")
    try:
        axis.set_aspect("equal")
    except NotImplementedError:  # matplotlib < 3.6
        pass
    return png(figure)


def residual_figure(result: RigResult) -> bytes:
    """Every used corner's residual (x, y) per camera: a cloud centred on 0 means the model fits."""
    plt = pyplot()
    n = len(result.cameras)
    figure, axes = plt.subplots(1, n, figsize=(2.6 * n, 2.8), squeeze=False)
    for c, axis in enumerate(axes[0]):
        r = [res for v, res in zip(result.views, result.residuals) if v.camera == c]
        stacked = np.concatenate(r) if r else np.zeros((0, 2))
        axis.scatter(stacked[:, 0], stacked[:, 1], s=2, alpha=0.4, color=f"C{c}")
        limit = max(float(np.percentile(np.abs(stacked), 99)) if len(stacked) else 1.0, 0.1)
        axis.set_xlim(-limit, limit)
        axis.set_ylim(-limit, limit)
        axis.set_aspect("equal")
        axis.axhline(0, color="gray", lw=0.5)
        axis.axvline(0, color="gray", lw=0.5)
        axis.set_title(f"{result.names[c]}: RMS {result.camera_rms(c):.3f} px", fontsize=9)
        axis.set_xlabel("dx (px)")
    axes[0][0].set_ylabel("dy (px)")
    return png(figure)


def alignment_figure(alignment: Alignment) -> bytes:
    """The evidence of ``--sync auto``: every source's board rotation speed on the first source's clock after its
    delay is taken off (the curves should lie on each other), and each source's correlation over whole-frame
    delays (one clear peak)."""
    plt = pyplot()
    figure, (signals, scores) = plt.subplots(2, 1, figsize=(7.5, 5.6))
    for c, (name, signal, delay) in enumerate(zip(alignment.names, alignment.signals, alignment.delays)):
        times = (np.arange(len(signal.values)) + 0.5) * signal.interval - delay.delay_s
        signals.plot(times, signal.values[:, 0], ".-", color=f"C{c}", lw=0.8, ms=2.5,
                     label=name if c == 0 else f"{name} (delay {delay.frames:+.2f} frames)")
        if c and len(delay.lags):
            scores.plot(delay.lags, delay.scores, ".-", color=f"C{c}", lw=0.8, ms=3, label=name)
            scores.axvline(delay.frames, color=f"C{c}", lw=0.6, ls=":")
    signals.set_xlabel(f"time on {alignment.names[0]}'s clock (s)")
    signals.set_ylabel("board rotation speed (deg/s)")
    signals.legend(fontsize=7)
    scores.set_xlabel("delay (frames of each source)")
    scores.set_ylabel("correlation")
    scores.legend(fontsize=7)
    figure.tight_layout()
    return png(figure)


def parameter_rows(result: RigResult) -> list[list[str]]:
    """One row per camera: intrinsics, distortion and pose, each with its standard deviation where solved."""
    rows = [["camera", "fx", "fy", "cx", "cy", "distortion (k1 k2 p1 p2 k3 ...; fisheye: k1..k4)", "centre (m)", "rotation sd (deg)",
             "translation sd (mm)"]]
    for c, camera in enumerate(result.cameras):
        std = result.std[c]
        values = dict(zip(("fx", "fy", "cx", "cy", *distortion_names(camera)),
                          [camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2], *camera.dist]))

        def cell(name: str) -> str:
            return f"{values[name]:.2f}" + (f" +- {std[name]:.2f}" if name in std else " (given)")

        translation = (f"{1000 * max(std['tx'], std['ty'], std['tz']):.2f}" if "tx" in std else "origin")
        rows.append([result.names[c], cell("fx"), cell("fy"), cell("cx"), cell("cy"),
                     ("fisheye: " if camera.model == "fisheye" else "") + " ".join(f"{v:.4g}" for v in camera.dist), " ".join(f"{v:+.3f}" for v in result.centre(c)),
                     f"{std['rotation_deg']:.3f}" if "rotation_deg" in std else "origin", translation])
    return rows


def alignment_section(alignment: Alignment) -> tuple:
    """The time alignment's section: each source's delay with its deviation and the peaks behind it."""
    rows = [["source", "delay (frames)", "delay (ms)", "correlation", "next peak", "frame pairs shared"]] + [
        [name, f"{d.frames:+.3f} +- {d.std_frames:.3f}", f"{1000 * d.delay_s:+.1f} +- {1000 * d.std_s:.1f}",
         f"{d.peak:.3f}", f"{d.second:.3f}", str(d.overlap)]
        for name, d in zip(alignment.names[1:], alignment.delays[1:])]
    return ("Time alignment", f"The sources were lined up in time from the board's motion (rotation and centre speed "
            f"from its poses, which every camera sees alike), each against {alignment.names[0]}: delay = frames to "
            f"skip at the source's start, refined to a fraction of a frame; each frame was then paired with the "
            f"nearest instant of {alignment.names[0]}.", rows, ["alignment"])


def report_sections(result: RigResult, boards: list[BoardSpec], frame: str) -> list:
    n = len(result.cameras)
    summary = (f"**{n} cameras, RMS {result.rms:.3f} px** over {sum(len(v.ids) for v in result.views)} corners of "
               f"{len(result.views)} views at {len({i for i, _ in result.board_poses})} instants; the rig's frame is "
               f"{frame}. Bundle "
               f"adjustment (scipy least_squares, Huber loss) of every camera's intrinsics and pose and every instant's "
               f"board pose, solved {result.rounds} time(s) with outliers dropped in between; "
               + ("each corner weighed by its detector's covariance and its view's spread beyond it. "
                  if result.corners_weighed else "every corner weighed alike. ")
               + ("Board" if len(boards) == 1 else "Boards") + ": " + "; ".join(
                   f"{b.squares_x}x{b.squares_y} {b.dictionary}" + (f" from marker {b.first_marker_id}" if b.first_marker_id
                                                                    else "") + f", {b.square_length * 1000:g} mm squares"
                   for b in boards) + "."
               + "".join(f" {note[0].upper()}{note[1:]}." for note in result.notes))
    cameras = [["camera", "views used", "RMS (px)", "distortion terms solved"]] + [
        [result.names[c], str(result.camera_views(c)), f"{result.camera_rms(c):.3f}", result.terms[c] or "held (the camera's own calibration, or --camera)"]
        for c in range(n)]
    pairs = [["pair", "instants both saw the board"]] + [
        [f"{result.names[i]} - {result.names[j]}", str(result.shared.get((i, j), 0))]
        for i in range(n) for j in range(i + 1, n)]
    counts = Counter((result.names[d.camera], d.stage, d.reason.split(" (")[0].split(" px")[0].rstrip("0123456789. "))
                     for d in result.dropped)
    dropped = [["camera", "stage", "reason", "views"]] + [[c, s, r, str(k)] for (c, s, r), k in sorted(counts.items())]
    listed = [["camera", "frame", "corners", "stage", "reason"]] + [
        [result.names[d.camera], d.name, str(d.corners), d.stage, d.reason] for d in result.dropped[:MAX_LISTED]]
    return [("Summary", summary, cameras, []),
            ("Parameters", "Values with their standard deviations (the Gauss-Newton covariance scaled by the "
             "residuals; the board poses eliminated). Centre: the camera's position in the rig's frame.",
             parameter_rows(result), []),
            ("Shared views", "Instants at which both cameras of a pair saw the board (the views used).", pairs, ["layout"]),
            ("Residuals", "Detected minus reprojected corner, per camera.", None, ["residuals"]),
            ("Views dropped", "Views with corners that were not used, by reason.", dropped, []),
            ("Dropped views, one by one", f"The first {MAX_LISTED} at most.", listed, [])]


def report_html(result: RigResult, boards: list[BoardSpec], frame: str, *, title: str = "Rig calibration",
                command: str = "", alignment: Alignment | None = None) -> str:
    """The page (figures inlined) of ``result``, calibrated with ``boards``; ``alignment``: the sources' time
    alignment (``--sync auto``) and its evidence."""
    figures = {"layout": layout_figure(result, boards), "residuals": residual_figure(result)}
    sections = report_sections(result, boards, frame)
    if alignment is not None:
        figures["alignment"] = alignment_figure(alignment)
        sections.insert(1, alignment_section(alignment))
    return html_page(title, command, sections, figures)
