"""The report's experiments: the protocols run over the test sets for every detector, as plain results.

Detectors are named; the report's names are

    deep            ChArUcoNet + RefineNet           opencv           OpenCV detector + cornerSubPix
    deep_subpix     ChArUcoNet + cornerSubPix        opencv_norefine  OpenCV detector alone
    deep_norefine   ChArUcoNet, cell pixels
    deep_paper      ChArUcoNet + RefineNet, the paper's decoding (no board-geometry check)
    deep_markers    ChArUcoNet's point head + the board's markers (what any other board gets) + RefineNet

Each experiment returns a JSON-ready dict (NaN/inf as null) and keeps what the figures and
the gallery need under keys starting with "_" (dropped from results.json).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from tqdm import tqdm

from evaluate.paper.data import group_by_sequence
from evaluate.paper.protocols import (
    LEVELS, POSE_THRESHOLD_PX, THRESHOLDS_PX, DetectorLike, PoseScore, TestFrame, accuracy_vs_threshold, score_pose,
    summarize_poses, synthetic_curve, time_pipelines,
)

LABELS = {
    "deep": "ChArUcoNet + RefineNet + pattern fit", "deep_subpix": "ChArUcoNet + cornerSubPix", "deep_norefine": "ChArUcoNet + NoRefine",
    "deep_paper": "ChArUcoNet + RefineNet, paper's decoding",
    "deep_markers": "ChArUcoNet points + markers (any board) + RefineNet",
    "deep_paper_weights": "ChArUcoNet + RefineNet, the paper board's weights",
    "opencv": "OpenCV detector + cornerSubPix", "opencv_norefine": "OpenCV detector + NoRefine",
}
LUX_BINS = (0.0, 1.0, 3.0, 10.0, 30.0, 100.0, 300.0, float("inf"))


def synthetic_experiment(detectors: dict[str, DetectorLike], frames: list[TestFrame], levels=LEVELS,
                         quiet: bool = False) -> dict:
    """Both synthetic protocols for each detector on the same ``frames``."""
    result = {"images": [f.name for f in frames], "levels": list(levels), "blur": {}, "darkness": {}, "_curves": {}}
    total = len(detectors) * 2 * len(levels) * len(frames)
    with tqdm(total=total, desc="synthetic blur/darkness", unit="image", disable=quiet) as bar:
        for name, detector in detectors.items():
            for effect in ("blur", "darkness"):
                curve = synthetic_curve(detector, frames, effect, levels, progress=lambda: bar.update(1))
                result[effect][name] = curve.to_dict()
                result["_curves"][effect, name] = curve
    return result


def score_frames(detectors: dict[str, DetectorLike], frames: list[TestFrame], desc: str,
                 quiet: bool = False) -> dict[str, list[PoseScore]]:
    scores: dict[str, list[PoseScore]] = {name: [] for name in detectors}
    with tqdm(total=len(detectors) * len(frames), desc=desc, unit="frame", disable=quiet) as bar:
        for name, detector in detectors.items():
            for frame in frames:
                scores[name].append(score_pose(detector, frame))
                bar.update(1)
    return scores


def sequence_experiment(detectors: dict[str, DetectorLike], frames: list[TestFrame], desc: str = "sequences",
                        quiet: bool = False) -> dict:
    """The paper's per-video table and accuracy-vs-threshold curve over frames grouped by sequence."""
    groups = group_by_sequence(frames)
    ordered = [f for group in groups.values() for f in group]
    scores = score_frames(detectors, ordered, desc, quiet)
    table, start = [], 0
    for sequence, group in groups.items():
        row = {"sequence": sequence, "frames": len(group), "lux": _condition_lux(group)}
        for name in detectors:
            row[name] = summarize_poses(scores[name][start:start + len(group)]).to_dict()
        table.append(row)
        start += len(group)
    return {
        "table": table,
        "overall": {name: summarize_poses(scores[name]).to_dict() for name in detectors},
        "accuracy_vs_threshold": {"thresholds_px": list(THRESHOLDS_PX),
                                  **{name: [float(v) for v in accuracy_vs_threshold([s.eps_re for s in scores[name]])]
                                     for name in detectors}},
        "_frames": ordered, "_scores": scores,
    }


def _condition_lux(group: list[TestFrame]) -> float | None:
    """The lux of a sequence's last frame: its condition (its first 30 frames are well lit)."""
    lux = group[-1].meta.get("lux")
    return None if lux is None else float(lux)


def render_experiment(detectors: dict[str, DetectorLike], frames: list[TestFrame], quiet: bool = False) -> dict:
    """Held-out renders: corner and pose accuracy overall and per illuminance bin."""
    scores = score_frames(detectors, frames, "held-out renders", quiet)
    lux = np.array([float(f.meta.get("lux", np.nan)) for f in frames])
    by_lux = []
    for low, high in zip(LUX_BINS[:-1], LUX_BINS[1:]):
        chosen = np.flatnonzero((lux >= low) & (lux < high))
        if len(chosen) == 0:
            continue
        by_lux.append({"lux_from": low, "lux_to": None if high == float("inf") else high, "frames": int(len(chosen)),
                       **{name: summarize_poses([scores[name][i] for i in chosen]).to_dict() for name in detectors}})
    return {"frames": len(frames), "overall": {name: summarize_poses(scores[name]).to_dict() for name in detectors},
            "by_lux": by_lux, "_frames": frames, "_scores": scores}


def timing_experiment(pipelines: dict[str, DetectorLike], frames: list[TestFrame], seconds: float,
                      quiet: bool = False) -> dict:
    """fps of each whole pipeline (detect + pose) on the same frames, interleaved in one run."""
    if not quiet:
        print(f"timing {len(pipelines)} pipelines on {len(frames)} frames ...", flush=True)
    fps = time_pipelines(pipelines, frames, rounds=3, min_seconds=seconds)
    height, width = frames[0].image.shape
    return {"image_size": [width, height], "frames": len(frames), "fps": fps,
            "labels": {name: LABELS.get(name, name) for name in pipelines}}


def hardest_frames(experiment: dict, names: list[str], count: int) -> list[tuple[TestFrame, list[PoseScore]]]:
    """The ``count`` frames where the detectors ``names`` together did worst (lowest summed corner accuracy),
    at most two per sequence so the gallery shows different scenes."""
    frames, scores = experiment["_frames"], experiment["_scores"]
    order = np.argsort([sum(scores[n][i].accuracy for n in names) for i in range(len(frames))], kind="stable")
    chosen, per_sequence = [], {}
    for i in order:
        key = str(frames[i].meta.get("sequence", frames[i].name))
        if per_sequence.get(key, 0) >= 2:
            continue
        per_sequence[key] = per_sequence.get(key, 0) + 1
        chosen.append((frames[i], [scores[n][i] for n in names]))
        if len(chosen) == count:
            break
    return chosen


def targets(results: dict, more: Iterable[tuple[str, float | None, str, bool]] = ()) -> list[dict]:
    """The project's targets (issue 6; docs/conventions.md "Targets") against this report's numbers; ``more``:
    other experiments' (what, value, goal, met) rows (the look-alike boards', the unseen boards'), listed
    before the speed target."""
    rows = []

    def add(what: str, value, target: str, met) -> None:
        rows.append({"target": what, "value": value, "goal": target, "met": None if value is None else bool(met)})

    synthetic = results.get("synthetic", {})
    if "deep" in synthetic.get("blur", {}):
        levels = synthetic["levels"]
        blur, dark = synthetic["blur"]["deep"]["accuracy"], synthetic["darkness"]["deep"]["accuracy"]
        if 10 in levels:
            add("synthetic blur k=10, corner accuracy", blur[levels.index(10)], ">= 0.94 (paper 0.94)",
                blur[levels.index(10)] >= 0.94)
        if 9 in levels:
            add("synthetic darkness k=9, corner accuracy", dark[levels.index(9)], ">= 0.50 (paper > 0.5)",
                dark[levels.index(9)] >= 0.5)
        if 0 in levels:
            add("synthetic k=0, corner accuracy", dark[levels.index(0)], ">= 0.99", dark[levels.index(0)] >= 0.99)
    sequences = results.get("sequences", {}).get("overall", {})
    if "deep" in sequences:
        deep = sequences["deep"]
        add(f"pose accuracy (eps_re < {POSE_THRESHOLD_PX:g} px) over the sequences", deep["pose_accuracy"],
            ">= 0.97 (paper 0.974)", deep["pose_accuracy"] >= 0.97)
        add("confidently wrong poses over the sequences", deep["confidently_wrong"], "0", deep["confidently_wrong"] == 0)
    good = [row for row in results.get("sequences", {}).get("table", []) if (row.get("lux") or 0) >= 100]
    if good and "deep" in good[0] and "opencv" in good[0]:
        deep_eps = _mean([row["deep"]["mean_eps_re"] for row in good])
        cv_eps = _mean([row["opencv"]["mean_eps_re"] for row in good])
        add("mean eps_re in good light (>= 100 lux sequences), px", deep_eps,
            f"<= OpenCV + cornerSubPix ({cv_eps:.3f})" if cv_eps is not None else "<= OpenCV",
            deep_eps is not None and cv_eps is not None and deep_eps <= cv_eps)
    if "deep_markers" in synthetic.get("blur", {}) and "deep" in synthetic.get("blur", {}):
        for effect, k in (("blur", 10), ("darkness", 9), ("darkness", 0)):
            if k in synthetic["levels"]:
                i = synthetic["levels"].index(k)
                family, own = synthetic[effect]["deep_markers"]["accuracy"][i], synthetic[effect]["deep"]["accuracy"][i]
                add(f"paper's board, {effect} k={k}: by markers (any board) vs the board's own ID head", family,
                    f">= {own:.3f} (own ID head)", family >= own)
    for what, value, goal, met in more:
        add(what, value, goal, met)
    fps = results.get("timing", {}).get("fps", {})
    if "deep" in fps:
        add("speed, ChArUcoNet + RefineNet + PnP at 320x240, fps", fps["deep"],
            f">= 30 (OpenCV + cornerSubPix here: {fps.get('opencv', float('nan')):.0f})", fps["deep"] >= 30)
    return rows


def _mean(values) -> float | None:
    values = [v for v in values if v is not None]
    return float(np.mean(values)) if values else None
