"""The printed-pattern corner fit (`deepcharuco.detection.corner_fit`): exact drawn views, every board layout's quadrant parity,
blur and noise, covariances that match the errors, refusals, and the detector and calibration that use them."""

import cv2
import numpy as np
import pytest

from deepcharuco import BoardSpec, Camera, Detector, project_corners
from deepcharuco.boards.print_face import canonical_view
from deepcharuco.boards.synthetic import look_at_pose, render_board_view
from deepcharuco.calibration.intrinsics import calibrate
from deepcharuco.calibration.views import FrameDetection, SelectionOptions
from deepcharuco.core.detection import Detection
from deepcharuco.detection.corner_fit import (FALLBACK_SIGMA_PX, _quadrant_signs, board_axes, fit_corners,
                                              view_homography)
from deepcharuco.detection.junction import printed_pattern
from deepcharuco.detection.markers.settling import neighbour_distances

CAMERA = Camera.from_fov(640, 480, hfov_deg=60.0)
BOARDS = {
    "paper": BoardSpec(),
    "6x6": BoardSpec(squares_x=7, squares_y=5, square_length=0.04, marker_length=0.03, dictionary="DICT_6X6_250"),
    "legacy": BoardSpec(squares_x=6, squares_y=8, square_length=0.03, marker_length=0.022, dictionary="DICT_4X4_50",
                        legacy=True),
    "inverted": BoardSpec(squares_x=4, squares_y=5, square_length=0.05, marker_length=0.0375,
                          dictionary="DICT_4X4_1000", inverted=True),
}


def view(board: BoardSpec, fill: float = 0.7, tilt=(25.0, -20.0, 12.0)):
    distance = CAMERA.K[0, 0] * max(board.size_m) / (fill * 480)
    rvec, tvec = look_at_pose(board, distance, *tilt)
    image = render_board_view(board, CAMERA.K, rvec, tvec, (640, 480))
    return image, project_corners(board, rvec, tvec, CAMERA.K)


def started(truth: np.ndarray, seed: int, spread: float = 0.4) -> np.ndarray:
    return truth + np.random.default_rng(seed).uniform(-spread, spread, truth.shape)


@pytest.mark.parametrize("name", list(BOARDS))
def test_quadrant_signs_match_the_printed_squares(name):
    board = BOARDS[name]
    texture = printed_pattern(board)
    ids = np.arange(board.num_corners)
    signs = _quadrant_signs(board, ids)
    # the square at (+X, +Y) of each corner, sampled at its centre: ink exactly where the sign says black
    centres = board.corner_points()[ids, :2] + 0.5 * board.square_length
    u, v = np.round(texture.board_to_texture(centres)).astype(int).T
    # a white square's centre holds a marker's bits: sample its edge's middle, inside the margin, instead
    edge = board.corner_points()[ids, :2] + np.array([0.5, 0.03]) * board.square_length
    ue, ve = np.round(texture.board_to_texture(edge)).astype(int).T
    black = texture.image[ve, ue] < 128
    assert np.array_equal(signs > 0, black)
    assert len(np.unique(signs)) == 2


@pytest.mark.parametrize("name", list(BOARDS))
def test_fit_finds_exact_corners_from_a_rough_start(name):
    board = BOARDS[name]
    image, truth = view(board)
    gray = canonical_view(image, board)
    start = started(truth, 0)
    fit = fit_corners(gray, board, view_homography(board, np.arange(board.num_corners), start),
                      np.arange(board.num_corners), start)
    errors = np.linalg.norm(fit.corners - truth, axis=1)
    assert fit.ok.all()
    assert np.median(errors) < 0.03 and errors.max() < 0.1, errors
    assert np.all(fit.contrast > 100)


def test_fit_through_blur_and_noise_and_its_covariance():
    board = BOARDS["6x6"]
    image, truth = view(board)
    rng = np.random.default_rng(3)
    errors, mahalanobis = [], []
    for trial in range(6):
        kernel = np.zeros((7, 7), np.float32)
        kernel[3, :] = 1.0 / 7  # a horizontal motion of 7 px: blurs the vertical lines only
        blurred = cv2.filter2D(image.astype(np.float32), -1, kernel, borderType=cv2.BORDER_REFLECT)
        dark = np.clip(np.rint(blurred * 0.1 + rng.normal(0, 1.5, image.shape)), 0, 255).astype(np.uint8)
        ids = np.arange(board.num_corners)
        start = started(truth, trial)
        fit = fit_corners(dark, board, view_homography(board, ids, start), ids, start)
        assert fit.ok.mean() > 0.9
        error = fit.corners[fit.ok] - truth[fit.ok]
        errors.extend(np.linalg.norm(error, axis=1))
        mahalanobis.extend(np.einsum("ni,nij,nj->n", error, np.linalg.inv(fit.covariances[fit.ok]), error))
        assert np.all(fit.noise > 1.0) and np.all(fit.noise < 3.0)  # 1.5 grey levels
    assert np.median(errors) < 0.15
    spread = np.sqrt(np.mean(mahalanobis) / 2)
    assert 0.6 < spread < 1.6, spread


@pytest.mark.parametrize("condition", ["sharp", "dark and blurred", "no pattern"])
def test_compiled_and_numpy_iterations_agree(condition):
    """`corner_fit_kernel` (numba) and the numpy path fit the same corners, covariances and refusals."""
    pytest.importorskip("numba")
    board = BOARDS["legacy"]
    image, truth = view(board)
    if condition == "dark and blurred":
        blurred = cv2.GaussianBlur(image.astype(np.float32), (0, 0), 1.5)
        image = np.clip(np.rint(blurred * 0.08 + np.random.default_rng(1).normal(0, 1.5, image.shape)), 0,
                        255).astype(np.uint8)
    elif condition == "no pattern":
        image = np.random.default_rng(2).integers(0, 255, image.shape, dtype=np.uint8)
    ids = np.arange(board.num_corners)
    start = started(truth, 5)
    fits = [fit_corners(canonical_view(image, board), board, view_homography(board, ids, start), ids, start,
                        compiled=compiled) for compiled in (False, True)]
    assert np.array_equal(fits[0].ok, fits[1].ok)
    assert fits[0].ok.mean() < 0.5 if condition == "no pattern" else fits[0].ok.mean() > 0.9
    assert np.allclose(fits[0].corners, fits[1].corners, atol=1e-9, rtol=0)
    ok = fits[0].ok
    assert np.allclose(fits[0].covariances[ok], fits[1].covariances[ok], rtol=1e-7, atol=0)
    assert np.allclose(fits[0].sigma, fits[1].sigma, rtol=1e-7) and np.allclose(fits[0].misfit, fits[1].misfit, rtol=1e-6)


def test_fit_refuses_where_there_is_no_pattern():
    board = BOARDS["paper"]
    image, truth = view(board)
    blank = np.full_like(image, 128)
    ids = np.arange(board.num_corners)
    fit = fit_corners(blank, board, view_homography(board, ids, truth), ids, truth)
    assert not fit.ok.any()
    assert np.array_equal(fit.corners, truth)  # the start kept
    assert np.isnan(fit.covariances).all()
    empty = fit_corners(image, board, view_homography(board, ids, truth), np.zeros(0, int), np.zeros((0, 2)))
    assert len(empty.corners) == 0
    # corners whose windows leave the image, wholly or in part (the report's synthetic protocol met one)
    outside = truth + np.array([-400.0, 0.0]) * (np.arange(len(truth)) % 2 == 0)[:, None]
    fit = fit_corners(image, board, view_homography(board, ids, truth), ids, outside)
    assert not fit.ok[::2].any() and fit.ok[1::2].all() and np.array_equal(fit.corners[::2], outside[::2])
    edge = np.array([[0.3, 100.0], [639.4, 200.0]])
    assert fit_corners(image, board, view_homography(board, ids, truth), ids[:2], edge).corners.shape == (2, 2)


def test_board_axes_are_the_homography_derivative():
    board = BOARDS["paper"]
    _, truth = view(board)
    homography = view_homography(board, np.arange(board.num_corners), truth)
    points = board.corner_points()[:, :2]
    axes = board_axes(homography, points, board.square_length)
    step = 1e-6
    moved = cv2.perspectiveTransform((points + [step, 0]).reshape(-1, 1, 2), homography).reshape(-1, 2)
    here = cv2.perspectiveTransform(points.reshape(-1, 1, 2), homography).reshape(-1, 2)
    assert np.allclose(axes[:, :, 0], (moved - here) / step * board.square_length, atol=1e-3)


def test_detector_places_corners_to_hundredths_and_reports_covariances():
    board = BOARDS["paper"]
    image, truth = view(board, fill=0.5)
    fitted = Detector(board=board).detect(image)
    plain = Detector(board=board, corner_fit=False).detect(image)
    assert len(fitted) >= board.num_corners - 2 and np.array_equal(fitted.ids, plain.ids)
    fitted_error = np.linalg.norm(fitted.corners - truth[fitted.ids], axis=1)
    plain_error = np.linalg.norm(plain.corners - truth[plain.ids], axis=1)
    assert np.median(fitted_error) < 0.5 * np.median(plain_error)
    assert np.median(fitted_error) < 0.03
    assert np.all(np.isfinite(fitted.covariances)) and np.all(fitted.sigmas < FALLBACK_SIGMA_PX)
    assert np.all(np.isnan(plain.covariances))
    assert fitted.to_dict()["covariances"][0] is not None and plain.to_dict()["covariances"][0] is None


def test_mirrored_board_covariances_follow_the_mirror():
    board = BoardSpec(mirrored=True)
    plain = BoardSpec()
    image, _ = view(plain, fill=0.5, tilt=(0.0, 35.0, 30.0))
    mirrored = Detector(board=board).detect(cv2.flip(image, 1))
    direct = Detector(board=plain).detect(image)
    assert np.array_equal(mirrored.ids, direct.ids)
    # A tilted, rolled view shears the covariances: x-y terms of 4e-7 to 3e-6 px^2 beside variances of 1-3e-5 px^2
    # (measured 2026-11-27), so a sign left unflipped, or a zero, is far outside the tolerance below.
    variances = direct.covariances[:, [0, 1], [0, 1]]
    assert np.all(np.abs(direct.covariances[:, 0, 1]) > 0.01 * variances.min(1))
    # the x-y term flips its sign with the image; the variances stay (the same pixels mirrored: equal to rounding)
    assert np.allclose(mirrored.covariances * np.array([[1, -1], [-1, 1]]), direct.covariances, rtol=1e-3,
                       atol=1e-3 * variances.min())
    assert np.allclose(mirrored.corners, [image.shape[1] - 1, 0] + [-1, 1] * direct.corners, atol=1e-3)


def test_detection_checks_covariances():
    with pytest.raises(ValueError, match="covariances"):
        Detection(np.arange(2), np.zeros((2, 2)), np.ones(2), np.zeros((3, 2, 2)))
    d = Detection(np.array([3, 1]), np.array([[0.0, 0], [1, 1]]), np.ones(2),
                  np.array([np.eye(2) * 4, np.diag([1.0, 9.0])]))
    assert np.allclose(d.sigmas, [3.0, 2.0])  # sorted with the IDs; the larger axis
    assert np.allclose(d.information()[0], np.diag([1.0, 1 / 9]))
    assert Detection(np.arange(1), np.zeros((1, 2)), np.ones(1)).information() is None


def test_calibration_weighs_corners_by_their_covariances():
    """Half of each view's corners are 10x noisier, and say so: the weighted calibration is nearer the truth."""
    board = BoardSpec(squares_x=9, squares_y=6, square_length=0.03, marker_length=0.022, dictionary="DICT_5X5_100")
    camera = Camera.from_fov(640, 480, hfov_deg=60.0)
    rng = np.random.default_rng(5)
    frames = []
    for index in range(24):
        rvec, tvec = look_at_pose(board, rng.uniform(0.35, 0.6), *rng.uniform(-35, 35, 2), rng.uniform(-30, 30),
                                  tuple(rng.uniform(-0.05, 0.05, 2)))
        corners = project_corners(board, rvec, tvec, camera.K)
        sigma = np.where(rng.random(len(corners)) < 0.5, 0.03, 0.3)
        noisy = corners + rng.normal(0, 1, corners.shape) * sigma[:, None]
        covariances = sigma[:, None, None] ** 2 * np.eye(2)
        frames.append(FrameDetection(index, str(index), np.arange(len(corners)), noisy, 1.0, covariances))
    errors = {}
    for weighted in (True, False):
        result = calibrate(frames, board, (640, 480), options=SelectionOptions(weight_corners=weighted))
        errors[weighted] = abs(result.camera.K[0, 0] / camera.K[0, 0] - 1)
    assert errors[True] < 0.6 * errors[False], errors


def test_corner_precision_experiment_scores_every_placer_on_the_same_corners():
    from evaluate.calibration import corner_precision

    results = corner_precision.run(seed=0, frames=1, boards=["paper 5x5 DICT_5X5_50"], conditions=["good", "lens"],
                                   quiet=True)
    for condition in ("good", "lens"):
        cell = results["conditions"][condition]
        counts = {summary["n"] for summary in cell["common"].values()}
        assert len(counts) == 1 and counts.pop() >= 8  # the same corners for every placer
        assert cell["common"]["deep (shipped)"]["median"] < cell["common"]["RefineNet"]["median"]
        # the covariances honest to the project's target (measured 0.90 good, 1.08 lens, 2026-11-27)
        assert corner_precision.SPREAD_RANGE[0] <= cell["spread"] <= corner_precision.SPREAD_RANGE[1]
        assert cell["sigma_bins"]
    rows = corner_precision.targets(results)
    assert any(r[0].startswith("corner error good, median") for r in rows)
    assert corner_precision.table(results).count("\n") == 3
    assert corner_precision.sigma_figure(results)[:4] == b"\x89PNG"
    frame = corner_precision.make_frame(corner_precision.BOARDS["paper 5x5 DICT_5X5_50"], "blur5",
                                        np.random.default_rng(0))
    again = corner_precision.make_frame(corner_precision.BOARDS["paper 5x5 DICT_5X5_50"], "blur5",
                                        np.random.default_rng(0))
    assert np.array_equal(frame.image, again.image)  # same seed, same bytes


@pytest.mark.parametrize("name", ["paper", "inverted"])
def test_hybrid_mode_fits_opencvs_corners_too(name):
    board = BOARDS[name]
    image, truth = view(board, fill=0.5)
    hybrid = Detector(board=board, mode="hybrid").detect(image)
    plain = Detector(board=board, mode="hybrid", corner_fit=False).detect(image)
    assert np.array_equal(hybrid.ids, plain.ids) and len(hybrid) >= board.num_corners - 2
    assert np.all(np.isnan(plain.covariances)) and np.all(np.isfinite(hybrid.covariances))
    fitted_error = np.median(np.linalg.norm(hybrid.corners - truth[hybrid.ids], axis=1))
    assert fitted_error < 0.5 * np.median(np.linalg.norm(plain.corners - truth[plain.ids], axis=1))


def test_neighbour_distances_find_the_corner_its_neighbours_disagree_with():
    board = BOARDS["6x6"]
    _, truth = view(board)
    ids = np.arange(board.num_corners)
    board_xy = board.corner_points()[:, :2]
    assert np.nanmax(neighbour_distances(board_xy, ids, truth)) < 0.05
    moved = truth.copy()
    moved[8] += [3.0, 4.0]  # an inner corner, 5 px off
    distance = neighbour_distances(board_xy, ids, moved)
    assert distance[8] == pytest.approx(5.0, abs=0.3)
    assert np.nanmax(np.delete(distance, 8)) < distance[8]


def test_a_corner_the_fit_cannot_place_carries_its_neighbours_disagreement_as_sigma():
    """Corners left where they are (the fit does not place them): one 4 px off where its neighbours put it gets a
    sigma of ~4 px, one where they put it the 0.5 px floor."""
    board = BOARDS["6x6"]
    image, truth = view(board)
    detector = Detector(board=board)
    ids = np.arange(board.num_corners)
    corners = truth.astype(np.float32).copy()
    corners[8] += [0.0, 4.0]
    keep = np.zeros(len(ids), bool)
    keep[[8, 9]] = True
    fitted, covariances = detector._fitted(canonical_view(image, board), ids, corners, keep=keep)
    sigmas = np.sqrt(np.linalg.eigvalsh(covariances)[:, -1])
    assert np.allclose(fitted[keep], corners[keep])
    assert sigmas[8] == pytest.approx(4.0, abs=0.4)
    assert sigmas[9] == pytest.approx(FALLBACK_SIGMA_PX)
    assert np.all(sigmas[~keep] < FALLBACK_SIGMA_PX)  # the fitted corners keep the fit's own
