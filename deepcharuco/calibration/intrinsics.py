"""One camera's calibration from its ChArUco detections: `calibrate` runs the steps below in order and rejects
outliers between solves; each step lives in its own module (`views`: 0-2, `solve`: 3, `terms`: 5, `weighting`: 6).

The steps:

0. `within_border`: corners nearer the image's border than ``border_px`` are not used (RefineNet's,
   `border_margin`: its patch reaches past the border there);
1. `usable_reason`: a frame is a candidate view when it has at least ``min_corners`` corners
   that do not lie along one line of the board (one line leaves the tilt about it unobservable);
2. `select_views`: candidates blurred well below the others (`sharpness`, less than
   ``blur_ratio`` x the median) are dropped, then near-duplicates (most corners shared, the
   shared ones within ``duplicate_px``; the sharper, fuller view stays), then at most
   ``max_views`` views are picked by farthest-point sampling over where the board is in the
   image, how large, and how it is tilted (`view_features`), each view's distance weighted by
   its share of the board's corners: coverage of the image and of tilt, not 40 copies of one pose;
3. `solve`: ``cv2.calibrateCameraExtended`` on the corners (ID i at ``board.object_points()[i]``)
   for the ``pinhole`` (k1 k2 p1 p2 k3) and ``rational`` (+ k4 k5 k6) models, with the parameters'
   standard deviations; ``cv2.fisheye.calibrate`` for ``fisheye`` (k1..k4, no deviations), started from a first
   solve (`solve.fisheye_start`) and without the corners beyond `solve.FISHEYE_MAX_DEG` off the lens's axis under it,
   which OpenCV's fisheye solve cannot start a pose from;
4. outliers: the worst corner of each view, when its residual exceeds ``corner_outlier`` x the
   RMS (and 1 px), is dropped, then views whose RMS exceeds ``view_outlier`` x the median view RMS (and `MIN_OUTLIER_PX`), and
   it is solved again, until nothing changes (at most `MAX_ROUNDS`). The pinhole and rational
   models go through this twice: first with k3 (k4..k6) held at 0 (`STIFF`), then free, started
   from the first stage's solution;
5. `select_terms` (pinhole and rational, ``select_terms``, at least `MIN_SELECTION_VIEWS` views): the
   tangential terms p1 p2 are held at 0 when that predicts views left out of the fit (5-fold
   cross-validation over the kept views) at least as well as solving them; they trade against the
   principal point, so where the views cannot tell the two apart they only add noise to cx and cy;
6. `weigh_views` (pinhole and rational, ``weight_views``): the last solve weighs each view by the spread of its
   own residuals: a view whose residuals spread more than `VIEW_WEIGHT_SPREAD` x the median view's, in some
   direction, counts less in that direction (motion blur smears a view's corners along the blur, and the views
   of a shaken video differ by far more than their corner counts);
7. `bootstrap_std` (pinhole and rational, at least `MIN_BOOTSTRAP_VIEWS` views): each deviation is raised to the
   spread of the solution over views resampled with replacement, where that is larger.

Bad input raises `CalibrationError` with one line saying what to capture instead: no board in any
frame, fewer usable views than ``min_views``, all views at one tilt (the focal length is then not
observable), or a solution whose focal length is uncertain by more than `MAX_RELATIVE_STD`.

Pixels: OpenCV's convention (centre of the top-left pixel at (0, 0)).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.calibration.solve import (FISHEYE_MAX_DEG, MODELS, STIFF, Solution, beyond_fisheye_reach,
                                           fisheye_start, residuals_of, solve)
from deepcharuco.calibration.terms import (MIN_BOOTSTRAP_VIEWS, MIN_SELECTION_VIEWS, bootstrap_std, select_terms,
                                           terms_name)
from deepcharuco.calibration.views import (CalibrationError, FrameDetection, SelectionOptions, ViewDecision, coverage,
                                           coverage_notes, select_views, within_border)
from deepcharuco.calibration.weighting import MIN_WEIGHTED_VIEWS, weigh_views
from deepcharuco.core.checks import check_choice
from deepcharuco.core.errors import OptionError
from deepcharuco.geometry.camera import Camera


MAX_ROUNDS = 6  # solves per stage; outliers are rejected between them
MIN_OUTLIER_PX = 0.5  # a view within this RMS is never an outlier: cornerSubPix noise alone reaches it
MAX_RELATIVE_STD = 0.05  # a focal length less certain than 5 % is not a calibration


@dataclass
class CalibrationResult:
    """A solved calibration.

    Attributes:
        model: "pinhole" | "rational" | "fisheye".
        camera: the intrinsics (K, dist (5, 8 or 4 fisheye coefficients), image size).
        rms: RMS reprojection error (px) over every corner used.
        std: standard deviation of each intrinsic parameter by name (`STD_NAMES`), empty for fisheye.
        views: the kept views, in frame order, with per_view_rms (V,), rvecs/tvecs (V, 3), and
            residuals: per view (N_v, 2) float64 detected minus reprojected pixels of its used corners.
        decisions: one `ViewDecision` per frame of the source.
        frames: frames read; image_size: (width, height).
    """

    model: str
    camera: Camera
    rms: float
    std: dict[str, float]
    views: list[FrameDetection]
    per_view_rms: np.ndarray
    rvecs: np.ndarray
    tvecs: np.ndarray
    residuals: list[np.ndarray]
    decisions: list[ViewDecision]
    frames: int
    rounds: int = 1
    notes: list[str] = field(default_factory=list)
    terms: str = ""  # the distortion terms solved, e.g. "k1 k2 p1 p2 k3" (the others held at 0)
    held_out: dict[str, float] = field(default_factory=dict)  # `select_terms`' score of each candidate (terms -> px)
    # `weigh_views`: per kept view, its weight along its noisiest direction (1: a full view; empty: equal weights)
    view_weights: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def image_size(self) -> tuple[int, int]:
        return self.camera.image_size

    @property
    def corner_sigma(self) -> float:
        """Per-corner uncertainty: the standard deviation (px, per axis) of one detected corner about where the
        solved camera puts it, from the residuals with the solved parameters' degrees of freedom taken out
        (2N measurements, 6 per view and the intrinsics solved). The residual RMS alone understates it: the
        fit absorbs part of the noise, most where a view has few corners. Assumes every corner of a detector
        is alike; a detector's bad corners show in `residuals`."""
        count = sum(len(r) for r in self.residuals)
        # `std` names exactly the intrinsics that were solved (not a fixed k3); the fisheye solver gives none.
        solved = 6 * len(self.residuals) + (len(self.std) if self.std else 4 + len(self.camera.dist))
        freedom = 2 * count - solved
        if freedom <= 0:
            return math.nan
        return math.sqrt(float(sum(np.sum(r ** 2) for r in self.residuals)) / freedom)

    def summary(self) -> dict:
        """JSON-ready numbers: intrinsics, deviations, RMS, view counts."""
        K = self.camera.K
        return {"model": self.model, "image_size": list(self.image_size), "rms_px": self.rms,
                "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "dist": self.camera.dist.tolist(),
                "std": self.std, "corner_sigma_px": self.corner_sigma, "frames": self.frames, "views_kept": len(self.views),
                "frames_with_corners": sum(d.corners > 0 for d in self.decisions), "rounds": self.rounds,
                "terms": self.terms, "held_out_px": self.held_out,
                "views_weighed_down": int(np.sum(self.view_weights < 0.5))}  # less than half


def calibrate(frames: list[FrameDetection], board: BoardSpec, image_size: tuple[int, int], model: str = "pinhole",
              options: SelectionOptions | None = None, *, fix_k3: bool = False) -> CalibrationResult:
    """Select views from ``frames``, solve, reject outliers and re-solve (module docstring). ``fix_k3``:
    keep k3 at 0 (not for fisheye).

    Raises:
        OptionError: ``model`` not one of `MODELS`, or ``fix_k3`` with the fisheye model.
        CalibrationError: frames that cannot give a calibration (no board, too few distinct views, one tilt, a
            focal length uncertain by more than `MAX_RELATIVE_STD`, a diverged or folding solution), saying what to
            capture instead.
    """
    if fix_k3 and model == "fisheye":
        raise OptionError("fix_k3 applies to the pinhole and rational models, not fisheye")
    check_choice("model", model, MODELS)
    options = options or SelectionOptions()
    trimmed = [within_border(f, image_size, options.border_px) for f in frames]
    at_border = {f.index: len(f.ids) - len(t.ids) for f, t in zip(frames, trimmed) if len(f.ids) > len(t.ids)}
    views, reasons = select_views(trimmed, board, image_size, options)
    for index, count in at_border.items():
        if index in reasons and reasons[index][0] == "detection":
            reasons[index] = ("detection", f"{reasons[index][1]} after {count} within {options.border_px:g} px of the "
                                           f"border")
    # Per view: the mask of its corners still in use.
    masks = {v.index: np.ones(len(v.ids), bool) for v in views}
    outliers: dict[int, str] = {}
    dropped_corners: dict[int, int] = {}
    stages = [(model, fix_k3)] if model == "fisheye" or (model, fix_k3) == STIFF else [STIFF, (model, fix_k3)]
    solution, rounds = None, 0
    rim: dict[int, int] = {}  # fisheye: per view, its corners beyond FISHEYE_MAX_DEG (left out)
    if model == "fisheye" and views:
        solution = fisheye_start([board.object_points()[v.ids] for v in views], [v.corners for v in views], image_size)
        for v, beyond in zip(views, beyond_fisheye_reach([v.corners for v in views], solution)):
            if beyond.any():
                masks[v.index] &= ~beyond
                rim[v.index] = int(beyond.sum())
                if masks[v.index].sum() < options.min_corners:
                    outliers[v.index] = (f"{masks[v.index].sum()} corners within {FISHEYE_MAX_DEG:g} degrees of the "
                                         f"lens's axis (fewer than {options.min_corners}); the rest are near the image "
                                         f"circle's rim")
    for stage_model, stage_fix_k3 in stages:
        for stage_round in range(1, MAX_ROUNDS + 1):
            rounds += 1
            active = [v for v in views if v.index not in outliers]
            objects = [board.object_points()[v.ids[masks[v.index]]] for v in active]
            images = [v.corners[masks[v.index]] for v in active]
            solution = solve(objects, images, image_size, stage_model, stage_fix_k3, guess=solution)
            residuals, norms, rms, view_rms = residuals_of(objects, images, solution, stage_model)
            if stage_round == MAX_ROUNDS or not _reject_outliers(active, norms, view_rms, rms, masks, outliers,
                                                                 dropped_corners, options):
                break
    terms, held_out = terms_name(model, fix_k3, False), {}
    if model != "fisheye" and options.select_terms and len(active) >= MIN_SELECTION_VIEWS:
        zero_tangent, scores = select_terms(objects, images, image_size, model, fix_k3, solution)
        held_out = {terms_name(model, fix_k3, zt): score for zt, score in scores.items()}
        if zero_tangent:
            terms = terms_name(model, fix_k3, True)
            solution = solve(objects, images, image_size, model, fix_k3, guess=solution, zero_tangent=True)
            residuals, norms, rms, view_rms = residuals_of(objects, images, solution, model)
    view_weights = np.zeros(0)
    if model != "fisheye" and options.weight_views and len(active) >= MIN_WEIGHTED_VIEWS:
        covariances = [v.covariances[masks[v.index]] for v in active] \
            if options.weight_corners and all(v.covariances is not None for v in active) else None
        solution, view_weights = weigh_views(objects, images, solution, model, terms, options.weight_spread,
                                             corner_covariances=covariances)
        residuals, norms, rms, view_rms = residuals_of(objects, images, solution, model)
    if model != "fisheye" and len(active) >= MIN_BOOTSTRAP_VIEWS:
        solution.std.update({name: value for name, value in
                             bootstrap_std(objects, images, image_size, model, terms, solution).items()
                             if value > solution.std.get(name, 0.0)})
    _check_solution(solution, model, image_size)
    decisions = []
    kept_rms = dict(zip((v.index for v in active), view_rms))
    for frame in frames:
        if frame.index in kept_rms:
            extra = f"; {dropped_corners[frame.index]} outlier corner(s) dropped" if frame.index in dropped_corners else ""
            if frame.index in rim:
                extra += f"; {rim[frame.index]} corner(s) beyond {FISHEYE_MAX_DEG:g} degrees off the lens's axis unused"
            if frame.index in at_border:
                extra += f"; {at_border[frame.index]} corner(s) within {options.border_px:g} px of the border unused"
            decisions.append(ViewDecision(frame.index, frame.name, len(frame.ids), "kept", "solution",
                                          "calibration view" + extra, float(kept_rms[frame.index])))
        elif frame.index in outliers:
            decisions.append(ViewDecision(frame.index, frame.name, len(frame.ids), "dropped", "outlier", outliers[frame.index]))
        else:
            stage, reason = reasons[frame.index]
            decisions.append(ViewDecision(frame.index, frame.name, len(frame.ids), "dropped", stage, reason))
    used_views = [v.subset(masks[v.index]) for v in active]
    camera = Camera(K=solution.K, dist=solution.dist, image_size=image_size,
                    model="fisheye" if model == "fisheye" else "pinhole")
    fold = fold_share(camera)
    fold_notes = []
    if fold is not None:
        where = (f"the solved distortion folds back {100 * fold:.0f} % of the way out to the image's farthest corner, "
                 f"so the image beyond cannot be undistorted")
        if fold >= MIN_FOLD_SHARE or model == "rational":  # rational: k3 alone is not what folds it, a note only
            fold_notes.append(f"{where}" + (" (the corners' tips only)" if fold >= MIN_FOLD_SHARE else
                                            ": do not undistort beyond it; capture the board near the image's edges "
                                            "and corners too"))
        elif not fix_k3:  # a free k3 is what bends the model where the views have no corners: solve without it
            result = calibrate(frames, board, image_size, model, options, fix_k3=True)
            result.notes.insert(0, f"with k3 free {where}: solved again with k3 fixed at 0")
            return result
        else:
            raise CalibrationError(f"{where}: capture the board near the image's edges and corners too "
                                   f"({100 * coverage(used_views, image_size):.0f} % of the image is covered)")
    return CalibrationResult(model=model, camera=camera, rms=rms, std=solution.std, views=used_views,
                             per_view_rms=view_rms, rvecs=solution.rvecs, tvecs=solution.tvecs, residuals=residuals,
                             decisions=decisions, frames=len(frames), rounds=rounds,
                             notes=(["k3 fixed at 0"] if fix_k3 else []) + coverage_notes(used_views, image_size)
                             + fold_notes,
                             terms=terms, held_out=held_out, view_weights=view_weights)


def _reject_outliers(active: list[FrameDetection], norms: list[np.ndarray], view_rms: np.ndarray, rms: float,
                     masks: dict[int, np.ndarray], outliers: dict[int, str], dropped_corners: dict[int, int],
                     options: SelectionOptions) -> bool:
    """Mark outlier corners (in ``masks``) and outlier views (in ``outliers``) of one solution; True when
    anything changed. Corners first: one wrong corner should cost itself, not its whole view."""
    changed = False
    corner_limit = max(options.corner_outlier * rms, 1.0)
    # A view that just lost corners is judged again after the re-solve: its pose was pulled by them.
    remaining_rms = view_rms.copy()
    for i, (view, norm) in enumerate(zip(active, norms)):
        bad = norm > corner_limit
        # The worst corner only, one a round: a wrong corner pulls its view's pose, and with it its neighbours'
        # residuals past the limit too. A view with many bad corners is judged whole, as a view, below.
        if bad.any() and bad.sum() <= max(1, len(norm) // 3) and masks[view.index].sum() > options.min_corners:
            used = np.flatnonzero(masks[view.index])
            masks[view.index][used[int(np.argmax(norm))]] = False
            dropped_corners[view.index] = dropped_corners.get(view.index, 0) + 1
            remaining_rms[i] = 0.0
            changed = True
    view_limit = max(options.view_outlier * float(np.median(view_rms)), MIN_OUTLIER_PX)
    remaining = len(active)
    for i in np.argsort(-remaining_rms):
        if remaining_rms[i] <= view_limit or remaining <= options.min_views:
            break
        outliers[active[i].index] = (f"outlier: RMS {remaining_rms[i]:.2f} px > {view_limit:.2f} px "
                                     f"({options.view_outlier:g} x the median view)")
        remaining -= 1
        changed = True
    return changed


# A model that folds back this far out or farther (as a share of the way to the image's farthest corner) is kept,
# with a note: only the corners' tips are lost. Nearer in, k3 is fixed at 0 and the camera solved again, or the
# calibration refused. Set by geometry, then checked on real cameras: caliscope's own four webcam calibrations and
# OpenCV's tutorial camera do not fold; the deep detector's calibration of caliscope's cam_1 folds at 97 %, and
# OpenCV's corners of a damaged copy of it gave k3 = -0.42, a fold at 81 % (the k3 = -1.20: 65 %).
MIN_FOLD_SHARE = 0.9


def fold_share(camera: Camera, samples: int = 20000) -> float | None:
    """Where a pinhole camera's radial distortion stops growing with the radius before it reaches the image's
    farthest corner, as a share of that corner's (distorted, normalised) radius; None when the mapping increases
    all the way there, as a lens's does (mrcal flags such models too). A fold means two radii image to one and the
    pixels beyond cannot be undistorted: a k3 solved from views that leave the image's corners empty can do this
    (seen on a real 1280x720 webcam: k3 = -1.20, a fold at normalised radius 0.57). Fisheye models: None."""
    if camera.model == "fisheye":
        return None
    k1, k2, _, _, k3, k4, k5, k6 = np.pad(camera.dist, (0, max(0, 8 - camera.dist.size)))[:8]
    (fx, _, cx), (_, fy, cy), _ = camera.K
    width, height = camera.image_size
    corners = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [-0.5, height - 0.5], [width - 0.5, height - 0.5]])
    reach = float(np.max(np.hypot((corners[:, 0] - cx) / fx, (corners[:, 1] - cy) / fy)))
    r = np.linspace(0.0, 5.0 * reach, samples)  # undistorted radii; barrel distortion needs them beyond the reach
    r2 = r * r
    distorted = r * (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    falling = np.flatnonzero(np.diff(distorted) <= 0)
    upto = distorted if len(falling) == 0 else distorted[:falling[0] + 1]
    if np.any(upto >= reach):
        return None
    return float(upto.max() / reach)


def _check_solution(solution: Solution, model: str, image_size: tuple[int, int]) -> None:
    K = solution.K
    if not np.all(np.isfinite(K)) or not np.all(np.isfinite(solution.dist)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError(f"the {model} calibration diverged: capture more views covering the whole image at varied tilts")
    for name in ("fx", "fy"):
        deviation = solution.std.get(name)
        value = K[0, 0] if name == "fx" else K[1, 1]
        if deviation is not None and deviation > MAX_RELATIVE_STD * value:
            raise CalibrationError(
                f"{name} = {value:.1f} +- {deviation:.1f} px is too uncertain (> {100 * MAX_RELATIVE_STD:.0f} %): the views "
                f"do not pin the focal length down; capture the board tilted 20-40 degrees in several directions, near "
                f"the image's edges and corners too")
