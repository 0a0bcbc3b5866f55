"""report.md (figures as files beside it) and report.html (self-contained: figures inlined) from the results."""

from __future__ import annotations

from pathlib import Path

from deepcharuco.calibration.html_page import html_page
from deepcharuco.core.files import write_atomic
from evaluate.paper.experiments import LABELS
from evaluate.paper.figures import figure_file_name

PAPER_FPS = {"deep": 66.5, "deep_subpix": 98.6, "deep_norefine": 100.7, "opencv": 99.4, "opencv_norefine": 101.5}


def _number(value, digits: int = 3, percent: bool = False) -> str:
    if value is None:
        return "nan"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int):
        return str(value)
    return f"{100 * value:.1f}" if percent else f"{value:.{digits}f}"


def sections(results: dict) -> list[tuple[str, str, list[list[str]] | None, list[str]]]:
    """(title, text, table rows (first = header) or None, figure names) for each section of the report."""
    out = []
    deep = "deep" in results.get("detectors", {})
    notes = results.get("notes", [])
    out.append(("Summary", " ".join(notes), None, []))
    if results.get("targets"):
        rows = [["target", "value", "goal", "met"]]
        for t in results["targets"]:
            rows.append([t["target"], _number(t["value"]), t["goal"], "n/a" if t["met"] is None else ("**yes**" if t["met"] else "no")])
        out.append(("Targets", "The project's targets, measured by this report.", rows, []))
    synthetic = results.get("synthetic")
    if synthetic:
        names = list(synthetic["blur"])
        rows = [["k"] + [f"blur: {LABELS.get(n, n)}" for n in names] + [f"darkness: {LABELS.get(n, n)}" for n in names]]
        for i, k in enumerate(synthetic["levels"]):
            rows.append([str(k)] + [_number(synthetic["blur"][n]["accuracy"][i], 2) for n in names]
                        + [_number(synthetic["darkness"][n]["accuracy"][i], 2) for n in names])
        text = (f"The paper's synthetic tests on {len(synthetic['images'])} well-lit images with different static poses: "
                "a horizontal motion-blur kernel of size k, and the image multiplied by 0.6^k. Mean corner detection "
                "accuracy (right ID within 3 px, over the 16 corners).")
        out.append(("Synthetic motion blur and darkness", text, rows, ["synthetic_blur", "synthetic_darkness"]))
    for key, title in (("sequences", "Rendered capture sequences"), ("captures", "Auto-labelled captures")):
        experiment = results.get(key)
        if not experiment:
            continue
        has = lambda name: name in experiment["overall"]  # noqa: E731
        header = ["sequence", "frames"]
        header += ["deep acc %"] if has("deep") else []
        header += ["by markers acc %"] if has("deep_markers") else []
        header += ["paper decoding acc %"] if has("deep_paper") else []
        header += ["cv acc %"]
        header += ["deep eps_re (no RefineNet)"] if has("deep") else []
        header += ["cv eps_re", "wrong poses deep / cv" if has("deep") else "wrong poses cv"]
        rows = [header]
        for row in experiment["table"] + [{"sequence": "**all**", "frames": sum(r["frames"] for r in experiment["table"]),
                                           **experiment["overall"]}]:
            cells = [row["sequence"], str(row["frames"])]
            if has("deep"):
                cells.append(_number(row["deep"]["pose_accuracy"], percent=True))
            if has("deep_markers"):
                cells.append(_number(row["deep_markers"]["pose_accuracy"], percent=True))
            if has("deep_paper"):
                cells.append(_number(row["deep_paper"]["pose_accuracy"], percent=True))
            cells.append(_number(row["opencv"]["pose_accuracy"], percent=True))
            if has("deep"):
                norefine = row.get("deep_norefine", {}).get("mean_eps_re")
                cells.append(f"{_number(row['deep']['mean_eps_re'])} ({_number(norefine)})")
            cells.append(_number(row["opencv"]["mean_eps_re"]))
            wrong = [str(row["deep"]["confidently_wrong"])] if has("deep") else []
            cells.append(" / ".join(wrong + [str(row["opencv"]["confidently_wrong"])]))
            rows.append(cells)
        text = ("The paper's per-video table: acc = % of frames whose pose has eps_re < 3 px (frames without a pose "
                "count as failures); eps_re = mean reprojection error over the frames with a pose (nan: none). "
                "Wrong poses: poses returned more than 10 degrees or 10 % of the distance from the truth.")
        if key == "sequences":
            text += (" Each rendered sequence films a static board with a still camera: 30 well-lit frames, then "
                     "the condition (illuminance in lux, a moving shadow, or camera shake).")
        out.append((title, text, rows, [f"{key}_threshold"]))
        if experiment.get("autolabel"):
            a = experiment["autolabel"]
            still = a.get("still_camera", {})
            rows = [["frames", "corners", "median px", "p95 px", "max px", "rotation deg (median / max)"]]
            for label, part in (("still camera (lux, shadow)", still), ("all, camera shake included", a)):
                if part.get("corners"):
                    rows.append([label, str(part["corners"]), _number(part.get("median_px")), _number(part.get("p95_px")),
                                 _number(part.get("max_px")),
                                 f"{_number(part.get('rotation_deg_median'))} / {_number(part.get('rotation_deg_max'))}"])
            refused = a.get("refused", {})
            text = ("The paper's recipe for real captures (OpenCV + cornerSubPix on the average of the first 30 frames, "
                    "those corners and their PnP pose as every frame's truth) applied to the rendered sequences and "
                    f"compared with the render truth, over {a.get('sequences', 0)} sequences. With a still camera the "
                    "recipe's premise holds; in the shake sequences the camera moves after the averaged frames and the "
                    "static labels are off by the shake.")
            if refused:
                text += f" Refused by the recipe: {', '.join(sorted(refused))}."
            out.append(("The auto-labelling recipe, measured on renders", text, rows, []))
    renders = results.get("renders")
    if renders:
        names = list(renders["overall"])
        rows = [["lux", "frames"] + [f"{LABELS.get(n, n)}: corners / pose acc % / wrong" for n in names]]
        for b in renders["by_lux"] + [{"lux_from": None, "lux_to": None, "frames": renders["frames"], **renders["overall"]}]:
            span = "**all**" if b["lux_from"] is None else f"{b['lux_from']:g}-{b['lux_to']:g}" if b["lux_to"] else f">= {b['lux_from']:g}"
            rows.append([span, str(b["frames"])] + [
                f"{_number(b[n]['corner_accuracy'], 2)} / {_number(b[n]['pose_accuracy'], percent=True)} / {b[n]['confidently_wrong']}"
                for n in names])
        out.append(("Held-out renders", "Random frames of the training distribution rendered with a held-out seed "
                    "(shake, shadows, clutter, distractor boards, 0.2-1000 lux), by illuminance at the board: mean "
                    "corner accuracy, pose accuracy (eps_re < 3 px), confidently wrong poses.", rows, []))
    if results.get("false_positives"):
        from evaluate.paper.false_positives import sections as false_positive_sections

        out += false_positive_sections(results["false_positives"], LABELS)
    if results.get("unseen_boards"):
        from evaluate.paper.unseen_boards import sections as unseen_sections

        out += unseen_sections(results["unseen_boards"], LABELS)
    if results.get("corner_precision"):
        from evaluate.calibration.corner_precision import sections as precision_sections

        out += precision_sections(results["corner_precision"])
    if results.get("calibration"):
        from evaluate.calibration.calibration_eval import calibration_sections

        out += calibration_sections(results["calibration"], LABELS)
    if results.get("real_captures"):
        from evaluate.captures import capture_sections

        out += capture_sections(results["real_captures"])
    timing = results.get("timing")
    if timing:
        rows = [["configuration", "fps here (detect + pose)", "paper (GTX 1080)"]]
        for name, fps in timing["fps"].items():
            rows.append([LABELS.get(name, name), f"{fps:.1f}", f"{PAPER_FPS.get(name, float('nan')):.1f}"])
        w, h = timing["image_size"]
        out.append(("Timing", f"Frames per second at {w}x{h} on {timing.get('machine', 'this machine')}, every "
                    f"configuration in one run on the same {timing['frames']} frames, interleaved. The paper's "
                    "numbers are on a GPU.", rows, []))
    if results.get("gallery"):
        shown = " (left) and ".join(LABELS.get(n, n) for n in results["gallery_detectors"])
        shown += " (right)" if len(results["gallery_detectors"]) > 1 else ""
        out.append(("Hardest frames", f"The frames where {shown} did worst. Red dots: the truth; green circles and "
                    "yellow numbers: detections. Images are contrast-stretched for viewing only.", None,
                    [g["figure"] for g in results["gallery"]]))
    return out


def write_markdown(path: Path, results: dict, figures: dict[str, bytes]) -> Path:
    lines = ["# Deep ChArUco evaluation report", "", f"`{results.get('command', '')}`", ""]
    for title, text, rows, names in sections(results):
        lines += [f"## {title}", "", text, ""]
        if rows:
            lines.append("| " + " | ".join(rows[0]) + " |")
            lines.append("|" + "---|" * len(rows[0]))
            lines += ["| " + " | ".join(r) + " |" for r in rows[1:]]
            lines.append("")
        for name in names:
            lines += [f"![{name}](figures/{figure_file_name(name, figures.get(name, b''))})", ""]
    (path.parent / "figures").mkdir(exist_ok=True)
    for name, data in figures.items():
        write_atomic(path.parent / "figures" / figure_file_name(name, data), data)
    write_atomic(path, "\n".join(lines))
    return path


def write_html(path: Path, results: dict, figures: dict[str, bytes]) -> Path:
    write_atomic(path, html_page("Deep ChArUco evaluation report", results.get("command", ""), sections(results), figures))
    return path
