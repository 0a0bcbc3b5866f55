"""deepcharuco.calibration's choice of the tangential terms p1 p2 by held-out views (`select_terms`) and its
weighing of views by their residuals (`weigh_views`), on exact projections through a known camera (OpenCV's
model) plus Gaussian corner noise (and blur-like errors): no rendering, no detector."""

import math

import cv2
import numpy as np
import pytest

from deepcharuco import BoardSpec
from deepcharuco.calibration.intrinsics import calibrate
from deepcharuco.calibration.terms import bootstrap_std, terms_name
from deepcharuco.calibration.views import FrameDetection, SelectionOptions
from evaluate.calibration.calibration_sequences import WavingPath, frame_times, hand_waved_pose, pose_of

BOARD = BoardSpec()
SIZE = (320, 240)
# The kind of camera that missed the principal point on the rendered test set: 55 degrees of field, k1 +0.1,
# the principal point off centre.
FOCAL = 160 / math.tan(math.radians(27.5))
K = np.array([[FOCAL, 0, 162.0], [0, FOCAL, 114.0], [0, 0, 1]])


def _views(dist: np.ndarray, seed: int, count: int = 30, noise_px: float = 0.1) -> list[FrameDetection]:
    """A hand-waved board (evaluate.calibration.calibration_sequences' waving, its own path per seed) seen through (K, dist):
    the corners inside the image, exactly where cv2.projectPoints puts them, + ``noise_px`` Gaussian noise."""
    path_rng, noise = np.random.default_rng(3 + seed), np.random.default_rng(seed)
    path = WavingPath.draw(path_rng)
    frames = []
    for index, t in enumerate(frame_times(count, path_rng)):
        rvec, tvec = pose_of(hand_waved_pose(path, t, BOARD, K, dist, SIZE))
        corners = cv2.projectPoints(BOARD.object_points(), rvec, tvec, K, dist)[0].reshape(-1, 2)
        ids = np.flatnonzero((corners[:, 0] > 0) & (corners[:, 1] > 0) & (corners[:, 0] < SIZE[0] - 1)
                             & (corners[:, 1] < SIZE[1] - 1))
        frames.append(FrameDetection(index, str(index), ids, corners[ids] + noise.normal(0, noise_px, (len(ids), 2)), 1.0))
    return frames


def _centre_error(result) -> np.ndarray:
    return result.camera.K[:2, 2] - K[:2, 2]


def test_a_lens_without_tangential_terms_gets_a_steadier_principal_point(without_bootstrap):
    # p1 p2 move the image much as a shift of (cx, cy) does: solved where the lens has none they only add noise
    # to the principal point. Over 6 noise draws (and waving paths) the held-out views keep them at 0 in most,
    # and the principal point's error shrinks (measured: RMS 0.83 -> 0.53 px over these 6 seeds; at 0 in 5).
    dist = np.array([0.1, 0.01, 0.0, 0.0, 0.0])
    chosen, everything, zero_tangent = [], [], 0
    for seed in range(6):
        frames = _views(dist, seed)
        selected = calibrate(frames, BOARD, SIZE)
        full = calibrate(frames, BOARD, SIZE, options=SelectionOptions(select_terms=False))
        assert full.terms == "k1 k2 p1 p2 k3" and not full.held_out
        assert set(selected.held_out) == {"k1 k2 k3", "k1 k2 p1 p2 k3"}
        zero_tangent += selected.terms == "k1 k2 k3"
        if selected.terms == "k1 k2 k3":
            assert np.all(selected.camera.dist[2:4] == 0.0) and "p1" not in selected.std
            assert selected.held_out["k1 k2 k3"] <= selected.held_out["k1 k2 p1 p2 k3"]
        chosen.append(_centre_error(selected))
        everything.append(_centre_error(full))
    chosen_rms, full_rms = (float(np.sqrt(np.mean(np.square(e)))) for e in (chosen, everything))
    assert zero_tangent >= 5
    assert chosen_rms < 0.75 * full_rms, (chosen_rms, full_rms)


def test_a_lens_with_tangential_terms_keeps_them(without_bootstrap):
    # Where the lens has p1 p2 of a few 1e-3, holding them at 0 would move the principal point by pixels;
    # the held-out views see that and keep them.
    dist = np.array([0.1, 0.01, 0.006, -0.005, 0.0])
    for seed in range(3):
        result = calibrate(_views(dist, seed), BOARD, SIZE)
        assert result.terms == "k1 k2 p1 p2 k3"
        assert result.held_out["k1 k2 p1 p2 k3"] < result.held_out["k1 k2 k3"]
        assert np.abs(_centre_error(result)).max() < 2.0
        # p1 p2 and the principal point trade against each other, so only roughly (measured 0.004-0.007 / -0.003).
        assert result.camera.dist[2] > 0.003 and result.camera.dist[3] < -0.002


def test_few_views_solve_every_term_and_names_are_the_models():
    result = calibrate(_views(np.array([0.1, 0.01, 0.0, 0.0, 0.0]), 0, count=8), BOARD, SIZE)
    assert result.terms == "k1 k2 p1 p2 k3" and result.held_out == {}  # too few views to hold any out
    # The bootstrap's deviations are of the terms solved alone: none for p1 p2 held at 0 (the tests that choose
    # the terms leave the bootstrap out: `without_bootstrap`).
    objects = [BOARD.object_points()[v.ids] for v in result.views]
    solution = type("S", (), {"K": result.camera.K, "dist": result.camera.dist})()
    spread = bootstrap_std(objects, [v.corners for v in result.views], SIZE, "pinhole", "k1 k2 k3", solution, rounds=4)
    assert set(spread) == {"fx", "fy", "cx", "cy", "k1", "k2", "k3"}
    assert terms_name("pinhole", True, True) == "k1 k2"
    assert terms_name("rational", False, False) == "k1 k2 p1 p2 k3 k4 k5 k6"
    assert terms_name("fisheye", False, False) == "k1 k2 k3 k4"


def test_fix_k3_and_the_rational_model_choose_the_tangential_terms_too():
    frames = _views(np.array([0.1, 0.01, 0.0, 0.0, 0.0]), 3, count=20)
    fixed = calibrate(frames, BOARD, SIZE, fix_k3=True)
    assert set(fixed.held_out) == {"k1 k2", "k1 k2 p1 p2"} and fixed.camera.dist[4] == 0.0
    rational = calibrate(frames, BOARD, SIZE, "rational")
    assert set(rational.held_out) == {"k1 k2 k3 k4 k5 k6", "k1 k2 p1 p2 k3 k4 k5 k6"}
    assert rational.camera.dist.shape == (8,)


def _blurred(frames: list[FrameDetection], seed: int, along_px: float = 0.3, stretch: float = 0.03
             ) -> tuple[list[FrameDetection], set[int]]:
    """Every third view smeared as motion blur smears a deep detector's corners (the rendered shake videos): along
    one direction d of the image only, Gaussian noise of ``along_px`` and a stretch of the view along d by
    +-``stretch`` (a tilt the view does not have). Returns (the frames, the smeared ones' indices)."""
    rng = np.random.default_rng(100 + seed)
    out, smeared = [], set()
    for frame in frames:
        if frame.index % 3 == 0:
            angle = rng.uniform(0, math.pi)
            d = np.array([math.cos(angle), math.sin(angle)])
            along = (frame.corners - frame.corners.mean(0)) @ d
            shift = rng.choice([-1.0, 1.0]) * stretch * along + rng.normal(0.0, along_px, len(along))
            frame = FrameDetection(frame.index, frame.name, frame.ids, frame.corners + np.outer(shift, d), frame.sharpness)
            smeared.add(frame.index)
        out.append(frame)
    return out, smeared


def test_views_smeared_along_one_direction_weigh_less_and_the_camera_comes_closer(without_bootstrap):
    # 10 of 30 views smeared (0.3 px along one direction, a 3 % stretch along it): within the outlier rule's 0.5 px,
    # so OpenCV's equal weights let them pull the camera. Weighed by their residuals' spread, they count less only
    # along their smear. Measured over these 4 seeds: fx RMS error 0.70 -> 0.46 %, cx 2.4 -> 0.5 px.
    dist = np.array([0.1, 0.01, 0.0, 0.0, 0.0])
    focal, centre = {True: [], False: []}, {True: [], False: []}
    for seed in range(4):
        frames, smeared = _blurred(_views(dist, seed), seed)
        for weighted in (True, False):
            result = calibrate(frames, BOARD, SIZE, options=SelectionOptions(weight_views=weighted))
            assert len(result.views) >= 29  # (nearly) none dropped: the weights do the work
            focal[weighted].append(100 * (result.camera.K[0, 0] / K[0, 0] - 1))
            centre[weighted].append(_centre_error(result))
            if weighted:
                weights = dict(zip((v.index for v in result.views), result.view_weights))
                kept = [weights[i] for i in smeared if i in weights]
                assert max(kept) < 0.8 and np.mean(kept) < 0.5, weights
                assert all(w > 0.8 for i, w in weights.items() if i not in smeared), weights
            else:
                assert len(result.view_weights) == 0
    rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in focal.items()}
    centre_rms = {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in centre.items()}
    assert rms[True] < 0.8 * rms[False], rms
    assert centre_rms[True] < 0.5 * centre_rms[False], centre_rms


def test_views_alike_keep_equal_weights():
    # Plain noise, every view alike (good light): the weighed solution is OpenCV's, to 0.01 %.
    dist = np.array([0.1, 0.01, 0.0, 0.0, 0.0])
    frames = _views(dist, 1)
    weighted = calibrate(frames, BOARD, SIZE)
    equal = calibrate(frames, BOARD, SIZE, options=SelectionOptions(weight_views=False))
    assert weighted.view_weights.min() > 0.8
    np.testing.assert_allclose(weighted.camera.K, equal.camera.K, rtol=1e-4, atol=0.02)
    for name in ("fx", "cx"):
        assert weighted.std[name] == pytest.approx(equal.std[name], rel=0.1)


def test_weighing_with_equal_weights_is_opencvs_solution(without_bootstrap):
    # weigh_views' solver (Levenberg-Marquardt, poses eliminated) finds OpenCV's solution when nothing is weighed:
    # a spread so large that every view keeps its full weight.
    dist = np.array([0.1, 0.01, 0.0, 0.0, 0.0])
    frames, _ = _blurred(_views(dist, 2), 2)
    equal = calibrate(frames, BOARD, SIZE, options=SelectionOptions(weight_views=False))
    wide = calibrate(frames, BOARD, SIZE, options=SelectionOptions(weight_spread=1e6))
    assert np.all(wide.view_weights > 1 - 1e-9)
    np.testing.assert_allclose(wide.camera.K, equal.camera.K, rtol=1e-6, atol=1e-4)
    np.testing.assert_allclose(wide.camera.dist, equal.camera.dist, atol=1e-6)
