"""Boards the networks never saw: cells from corners, markers read and matched, the view they agree on,
inverted and mirrored prints, look-alike boards refused, large images searched coarse to fine."""

import cv2
import numpy as np
import pytest

from deepcharuco import BoardSpec, Camera, Detector, OpenCVDetector, project_corners
from deepcharuco.boards.synthetic import look_at_pose, render_board_view, texture_homography
from deepcharuco.detection import deep_detector
from deepcharuco.detection.markers import lattice as lattice_module, placement
from deepcharuco.detection.markers.lattice import cell_homographies, find_cells, squarest_cells
from deepcharuco.detection.markers.marker_reader import MIN_NCC, board_markers, correlate, match_markers, read_squares
from deepcharuco.detection.markers.verification import marker_agreement

# Boards of other layouts than the shipped weights' 5x5 DICT_5X5_50 (none of them seen in training).
UNSEEN = [
    BoardSpec(squares_x=7, squares_y=5, square_length=0.04, marker_length=0.03, dictionary="DICT_6X6_250"),
    BoardSpec(squares_x=11, squares_y=8, square_length=0.03, marker_length=0.022, dictionary="DICT_5X5_1000"),
    BoardSpec(squares_x=4, squares_y=5, square_length=0.054, marker_length=0.0405, dictionary="DICT_4X4_1000",
              inverted=True),
    BoardSpec(squares_x=6, squares_y=6, square_length=0.04, marker_length=0.03, dictionary="DICT_APRILTAG_36h11",
              mirrored=True),
    BoardSpec(squares_x=6, squares_y=4, square_length=0.04, marker_length=0.025, dictionary="DICT_7X7_50",
              legacy=True),
]
POSES = [dict(tilt_x_deg=25, tilt_y_deg=-15, roll_deg=10), dict(tilt_x_deg=-20, tilt_y_deg=30, roll_deg=200)]


@pytest.fixture(scope="module")
def camera() -> Camera:
    return Camera.from_fov(320, 240, hfov_deg=60.0)


def distance_for(board: BoardSpec, camera: Camera, fill: float) -> float:
    """The distance at which the board's longer side spans ``fill`` of the image's shorter side."""
    return camera.K[0, 0] * max(board.size_m) / (fill * min(camera.image_size))


def view_of(board: BoardSpec, camera: Camera, fill: float = 0.8, **pose):
    """(image, true corners (C, 2)) of ``board`` spanning about ``fill`` of the image's shorter side."""
    rvec, tvec = look_at_pose(board, distance_for(board, camera, fill), **pose)
    image = render_board_view(board, camera.K, rvec, tvec, camera.image_size)
    return image, project_corners(board, rvec, tvec, camera.K)


def test_cells_of_a_perspective_lattice_each_once_right_handed():
    homography = np.array([[30.0, 6.0, 40.0], [-4.0, 28.0, 30.0], [0.01, 0.02, 1.0]])
    grid = np.stack(np.meshgrid(np.arange(6.0), np.arange(5.0)), axis=-1).reshape(-1, 2)
    mapped = np.c_[grid, np.ones(len(grid))] @ homography.T
    pixels = mapped[:, :2] / mapped[:, 2:]
    outliers = np.array([[5.0, 5.0], [300.0, 10.0]])
    cells = find_cells(np.r_[pixels, outliers])
    real = {frozenset((r * 6 + c, r * 6 + c + 1, (r + 1) * 6 + c + 1, (r + 1) * 6 + c)) for r in range(4) for c in range(5)}
    found = [frozenset(quad.tolist()) for quad in cells]
    assert real <= set(found)
    assert len(found) == len(set(found))  # each cell once
    points = np.r_[pixels, outliers]
    for a, b, d, c in cells:
        ab, ac = points[b] - points[a], points[c] - points[a]
        assert ab[0] * ac[1] - ab[1] * ac[0] > 0
        assert np.allclose(points[b] + points[c] - points[a], points[d], atol=0.25 * min(np.hypot(*ab), np.hypot(*ac)))


@pytest.mark.parametrize("compiled", [True, False])  # numba's every pair, and numpy's
@pytest.mark.parametrize("count", [40, 300])  # numpy: measured against each other, and through the k-d tree
def test_nearest_candidates_are_nearest_first_and_equal_distances_by_index(count, compiled, monkeypatch):
    """`lattice._nearest` gives what measuring every pair and a stable sort give, on whole pixels (many equal
    distances), and where more points are equally near than its tree was asked for: twenty points 25 px from one."""
    if compiled:
        pytest.importorskip("numba")
    else:
        monkeypatch.setattr(lattice_module, "compiled_kernel", None)
    rng = np.random.default_rng(3)
    ring = np.array([(x, y) for x in range(-25, 26) for y in range(-25, 26) if x * x + y * y == 625], np.float64)
    rng.shuffle(ring)
    points = np.r_[np.rint(rng.uniform(0, 640, (count - 21, 2))), [[700.0, 700.0]], ring + 700]
    difference = points[:, None] - points[None]
    squared = (difference ** 2).sum(axis=-1)
    np.fill_diagonal(squared, np.inf)
    expected = np.argsort(squared, axis=1, kind="stable")[:, :lattice_module.NEIGHBOURS]
    near = lattice_module._nearest(points, lattice_module.NEIGHBOURS)
    assert len(ring) == 20 and np.array_equal(near, expected)
    assert near[count - 21].tolist() == list(range(count - 20, count - 12))  # the ring's first eight, by index


def test_cell_maps_carry_the_unit_square_onto_each_quad_as_opencv_does():
    rng = np.random.default_rng(7)
    centres = rng.uniform(20, 300, (200, 1, 2))
    # Convex quads, perspective-distorted squares of 5-40 px with corners jittered, (a, b, d, c) order.
    unit = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float64)
    pixels = (centres + rng.uniform(5, 40, (200, 1, 1)) * (unit - 0.5) + rng.normal(0, 1.5, (200, 4, 2))).reshape(-1, 2)
    quads = np.arange(800).reshape(200, 4)
    maps = cell_homographies(pixels.astype(np.float32), quads)
    mapped = np.c_[unit, np.ones(4)] @ np.transpose(maps, (0, 2, 1))  # (Q, 4, 3)
    assert np.allclose(mapped[:, :, :2] / mapped[:, :, 2:], pixels.astype(np.float32).reshape(-1, 4, 2), atol=1e-6)
    for quad, found in zip(quads[:20], maps):
        opencv = cv2.getPerspectiveTransform(unit.astype(np.float32), pixels[quad].astype(np.float32))
        assert np.allclose(found, opencv, rtol=1e-9, atol=1e-9)
    assert cell_homographies(pixels, np.zeros((0, 4), np.int64)).shape == (0, 3, 3)


def lattice(homography: np.ndarray, columns: int = 6, rows: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """(lattice points (N, 2) integer grid coordinates, their pixels (N, 2) through ``homography``)."""
    grid = np.stack(np.meshgrid(np.arange(float(columns)), np.arange(float(rows))), axis=-1).reshape(-1, 2)
    mapped = np.c_[grid, np.ones(len(grid))] @ homography.T
    return grid, mapped[:, :2] / mapped[:, 2:]


def grid_area(grid: np.ndarray, quad: np.ndarray) -> float:
    x, y = grid[quad, 0], grid[quad, 1]
    return 0.5 * abs(float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)))


@pytest.mark.parametrize("shear_deg", [90, 75, 65])
def test_squarest_cells_keep_the_real_cells_and_drop_their_sheared_rivals(shear_deg):
    # The lattice's columns turned by shear_deg from its rows in the image (a steeper view shears more).
    angle = np.radians(shear_deg)
    homography = np.array([[30.0, 30.0 * np.cos(angle), 40.0], [0.0, 30.0 * np.sin(angle), 30.0], [0.0, 1e-4, 1.0]])
    grid, pixels = lattice(homography)
    every, squarest = find_cells(pixels), squarest_cells(pixels, find_cells(pixels))
    real = {frozenset((r * 6 + c, r * 6 + c + 1, (r + 1) * 6 + c + 1, (r + 1) * 6 + c)) for r in range(4) for c in range(5)}
    sheared = [quad for quad in every if grid_area(grid, quad) == 1.0 and frozenset(quad.tolist()) not in real]
    assert len(sheared) >= 2 * len(real)  # what the filter is for: find_cells closes them all
    kept = {frozenset(quad.tolist()) for quad in squarest}
    assert real <= kept
    kept_sheared = [quad for quad in sheared if frozenset(quad.tolist()) in kept]
    if shear_deg >= 75:
        assert not kept_sheared
        assert len(squarest) < 0.4 * len(every)
    else:  # as square as the real cells, nearly: kept beside them, for the markers to tell apart
        assert kept_sheared


def test_a_view_too_steep_for_the_squarest_cells_is_found_from_every_cell(camera, monkeypatch):
    # Tilted 65 degrees: the real cells' image angles near 55 degrees, their sheared rivals squarer.
    board = UNSEEN[0]
    rvec, tvec = look_at_pose(board, distance_for(board, camera, 0.8), tilt_x_deg=65, tilt_y_deg=20, roll_deg=30)
    image = render_board_view(board, camera.K, rvec, tvec, camera.image_size)
    truth = project_corners(board, rvec, tvec, camera.K)
    searches = []
    find_marker_view = placement.find_marker_view

    def spy(*args, **kwargs):
        found = find_marker_view(*args, **kwargs)
        searches.append((len(args[3]), found is not None))
        return found

    monkeypatch.setattr(placement, "find_marker_view", spy)
    detection = Detector(board).detect(image)
    assert len(searches) == 2 and searches[0][0] < searches[1][0]  # the squarest cells, then every cell
    assert not searches[0][1] and searches[1][1]
    assert len(detection.ids) >= 20
    assert np.linalg.norm(detection.corners - truth[detection.ids], axis=1).max() < 1.0


@pytest.mark.parametrize("board", UNSEEN[:3], ids=lambda b: b.dictionary)
def test_every_marker_reads_as_itself_through_the_exact_view(board, camera):
    image, _ = view_of(board, camera, **POSES[0])
    rvec, tvec = look_at_pose(board, distance_for(board, camera, 0.8), **POSES[0])
    rotation, _ = cv2.Rodrigues(rvec)
    homography = camera.K @ np.c_[rotation[:, :2], tvec]  # board metres -> pixels
    gray = 255 - image if board.inverted else image
    agreeing, readable = marker_agreement(gray, board, homography)
    assert readable == board.num_markers and agreeing == readable
    # The same squares read a quarter turn off match the same markers one turn on.
    markers = board_markers(board)
    turn = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 1.0], [0.0, 0.0, 1.0]])  # square frame -> turned by 3
    squares = np.stack([homography @ np.diag([board.square_length] * 2 + [1.0]) @ np.array(
        [[1, 0, sx], [0, 1, sy], [0, 0, 1.0]]) @ np.linalg.inv(turn) for sx, sy in markers.squares])
    bits, contrast = read_squares(gray, squares, markers.size, markers.ratio)
    ncc = correlate(bits, markers)
    assert np.all(contrast > 0)
    assert [np.unravel_index(row.argmax(), row.shape) for row in ncc] == [(m, 3) for m in range(len(markers.ids))]


@pytest.mark.parametrize("compiled", [True, False])
def test_marker_matches_are_each_reads_best_pairs_in_order_and_none_below_the_floor(compiled, monkeypatch):
    if compiled:
        pytest.importorskip("numba")
    else:
        monkeypatch.setattr("deepcharuco.detection.markers.marker_reader.compiled_kernel", None)
    board = UNSEEN[0]
    markers = board_markers(board)
    rng = np.random.default_rng(3)
    exact = markers.bits[[0, 5, 2], [1, 0, 3]].astype(np.float32)  # three markers read in some turn
    blurred = 0.5 + 0.2 * (exact[:1] - 0.5) + rng.normal(0.0, 0.08, exact[:1].shape).astype(np.float32)
    clutter = rng.uniform(0.0, 1.0, (20, markers.size, markers.size)).astype(np.float32)  # some pair often >= the floor
    flat = np.full((5, markers.size, markers.size), 0.6, np.float32)  # correlates with nothing: below the floor
    bits = np.concatenate([exact, blurred, clutter, flat])
    contrast = np.ones(len(bits), np.float32)
    contrast[1] = 0.0  # unreadable: proposes nothing
    matches = match_markers(bits, contrast, markers, per_read=2)
    # Reference: every readable read's pairs ranked by score, best first, the first two kept if >= MIN_NCC.
    ncc = correlate(bits, markers).reshape(len(bits), -1)
    expected = [(r, int(p)) for r in np.flatnonzero(contrast > 0)
                for p in np.argsort(-ncc[r], kind="stable")[:2] if ncc[r, p] >= MIN_NCC]
    assert list(zip(matches.read.tolist(), (4 * matches.marker + matches.turn).tolist())) == expected
    np.testing.assert_allclose(matches.ncc, [ncc[r, p] for r, p in expected], rtol=1e-12)
    assert (matches.read[0], matches.marker[0], matches.turn[0]) == (0, 0, 1) and 1 not in matches.read
    assert set(range(4, 24)) & set(matches.read.tolist()) and not set(range(24, 29)) & set(matches.read.tolist())


@pytest.mark.parametrize("board", UNSEEN, ids=lambda b: f"{b.dictionary}-{b.squares_x}x{b.squares_y}")
def test_unseen_boards_found_with_right_ids(board, camera, backend):
    detector = Detector(board=board, backend=backend)
    assert detector.runner.name == backend
    assert detector.geometry == "markers"
    for pose in POSES:
        image, truth = view_of(board, camera, **pose)
        found = detector.detect(image)
        inside = (truth[:, 0] > 2) & (truth[:, 0] < 317) & (truth[:, 1] > 2) & (truth[:, 1] < 237)
        error = np.linalg.norm(found.corners - truth[found.ids], axis=1)
        assert error.max() < 1.0, (board, pose, error.max())  # no wrong ID, sub-pixel once refined
        assert len(found.ids) >= 0.85 * inside.sum()
        pose_found = detector.estimate_pose(found, camera.K)
        assert pose_found is not None and pose_found.reprojection_error < 1.0


def test_unseen_board_in_the_dark_and_blurred(camera):
    board = UNSEEN[0]
    detector, opencv = Detector(board=board), OpenCVDetector(board)
    image, truth = view_of(board, camera, **POSES[0])
    dark = np.round(image * 0.6 ** 9).astype(np.uint8)  # the paper's darkness k = 9
    blurred = cv2.filter2D(image, -1, np.ones((1, 10)) / 10)  # the paper's blur k = 10
    for degraded in (dark, blurred):
        assert len(opencv.detect(degraded).ids) == 0
        found = detector.detect(degraded)
        assert len(found.ids) >= 0.8 * board.num_corners
        assert np.linalg.norm(found.corners - truth[found.ids], axis=1).max() < 3.0


LOOK_ALIKES = [
    BoardSpec(squares_x=7, squares_y=5, dictionary="DICT_5X5_250"),  # same grid, other dictionaries
    BoardSpec(squares_x=7, squares_y=5, dictionary="DICT_4X4_250"),
    BoardSpec(squares_x=7, squares_y=5, dictionary="DICT_6X6_250", mirrored=True),  # the target mirrored
    BoardSpec(squares_x=5, squares_y=5, dictionary="DICT_6X6_250"),  # same dictionary, markers elsewhere
]


@pytest.mark.parametrize("look_alike", LOOK_ALIKES, ids=lambda b: f"{b.dictionary}-{b.squares_x}-m{b.mirrored}")
def test_look_alike_boards_give_nothing(look_alike, camera):
    detector = Detector(board=UNSEEN[0])
    for pose in POSES:
        image, _ = view_of(look_alike, camera, **pose)
        assert len(detector.detect(image).ids) == 0


CALISCOPE_LOOK_ALIKES = [  # the inverted 4x5 DICT_4X4_1000 board (UNSEEN[2], read with the shipped DICT_4X4 model)
    BoardSpec(**{**UNSEEN[2].to_dict(), "dictionary": "DICT_5X5_250"}),
    BoardSpec(**{**UNSEEN[2].to_dict(), "mirrored": True}),
    BoardSpec(**{**UNSEEN[2].to_dict(), "first_marker_id": 10}),  # the next ten markers of the dictionary
]


@pytest.mark.parametrize("look_alike", CALISCOPE_LOOK_ALIKES, ids=["other-dictionary", "mirrored", "other-ids"])
def test_look_alikes_of_an_inverted_dict_4x4_board_give_nothing(look_alike, camera):
    detector = Detector(board=UNSEEN[2])
    assert detector.weights.name == "DICT_4X4.pt"
    for pose in POSES:
        image, _ = view_of(look_alike, camera, **pose)
        assert len(detector.detect(image).ids) == 0
        assert len(detector.detect(view_of(UNSEEN[2], camera, **pose)[0]).ids) > 0  # the board itself is found


def test_paper_board_detector_refuses_look_alikes_and_plain_chessboards(camera):
    detector = Detector()  # the board-specific ID head, geometry "repair", checked against the markers
    assert detector.geometry == "repair"
    for look_alike in (BoardSpec(dictionary="DICT_6X6_250"), BoardSpec(dictionary="DICT_5X5_50", mirrored=True),
                       BoardSpec(dictionary="DICT_4X4_50")):
        for pose in POSES:
            image, _ = view_of(look_alike, camera, fill=0.6, **pose)
            assert len(detector.detect(image).ids) == 0
    # A chessboard without markers: the paper board's texture with its marker squares painted white.
    board = BoardSpec()
    texture = board.render_texture(2000.0, margin=0.02)
    plain = texture.image.copy()
    _, marker_corners = board.marker_corners()
    for corners in marker_corners:
        (u0, v0), (u1, v1) = texture.board_to_texture(corners[[0, 2], :2]).round().astype(int)
        plain[v0 - 2:v1 + 3, u0 - 2:u1 + 3] = 255
    rvec, tvec = look_at_pose(board, distance_for(board, camera, 0.6), **POSES[0])
    image = cv2.warpPerspective(plain, texture_homography(texture, camera.K, rvec, tvec), camera.image_size,
                                flags=cv2.INTER_AREA, borderValue=90)
    assert len(detector.detect(image).ids) == 0


def test_paper_board_at_another_size_keeps_the_id_head_and_scales_the_pose(camera):
    small = BoardSpec(square_length=0.02, marker_length=0.015)
    detector = Detector(board=small)
    assert detector.geometry == "repair" and detector.board == small
    image, truth = view_of(small, camera, **POSES[0])
    found = detector.detect(image)
    assert len(found.ids) == small.num_corners
    pose = detector.estimate_pose(found, camera.K)
    _, true_tvec = look_at_pose(small, distance_for(small, camera, 0.8), **POSES[0])
    assert np.linalg.norm(pose.tvec.ravel() - true_tvec) < 0.02 * np.linalg.norm(true_tvec)
    with pytest.raises(Exception, match="geometry='markers'"):
        Detector(board=UNSEEN[0], geometry="repair")


@pytest.mark.parametrize("flags", [dict(inverted=True), dict(mirrored=True), dict(inverted=True, mirrored=True)])
def test_inverted_and_mirrored_round_trip_through_both_detectors(flags, camera):
    board = BoardSpec(squares_x=7, squares_y=5, dictionary="DICT_6X6_250", **flags)
    plain = BoardSpec(squares_x=7, squares_y=5, dictionary="DICT_6X6_250")
    image, truth = view_of(board, camera, **POSES[0])
    assert len(OpenCVDetector(plain).detect(image).ids) == 0  # OpenCV alone does not see such a print
    for detector in (OpenCVDetector(board), Detector(board=board)):
        found = detector.detect(image)
        assert len(found.ids) >= 20
        assert np.linalg.norm(found.corners - truth[found.ids], axis=1).max() < 1.0
        pose = detector.estimate_pose(found, camera.K)
        assert pose is not None and pose.reprojection_error < 1.0


def test_large_image_searched_at_working_size_refined_at_full_resolution():
    board = UNSEEN[0]
    camera = Camera.from_fov(1920, 1080, hfov_deg=60.0)
    image, truth = view_of(board, camera, fill=0.9, **POSES[0])  # squares ~140 px: too large for the network
    # The paper's weights: the search is what is tested (the DICT_6X6 family model finds these squares natively too).
    weights = deep_detector.DEFAULT_WEIGHTS
    native = Detector(board=board, weights=weights, working_size=None).detect(image)
    found = Detector(board=board, weights=weights).detect(image)
    assert len(native.ids) < 0.5 * board.num_corners
    assert len(found.ids) >= 0.9 * board.num_corners
    assert np.median(np.linalg.norm(found.corners - truth[found.ids], axis=1)) < 0.5
    with pytest.raises(ValueError, match="working_size"):
        Detector(board=board, working_size=4)


def test_hybrid_keeps_verified_opencv_corners_and_falls_back_to_the_networks(camera):
    board = UNSEEN[0]
    hybrid, opencv = Detector(board=board, mode="hybrid"), OpenCVDetector(board)
    image, truth = view_of(board, camera, **POSES[0])
    lit = hybrid.detect(image)
    reference = opencv.detect(image)
    unfitted = Detector(board=board, mode="hybrid", corner_fit=False).detect(image)
    assert np.array_equal(unfitted.ids, reference.ids) and np.allclose(unfitted.corners, reference.corners)
    # OpenCV's corners, placed by the printed-pattern fit: the same corners, nearer the truth
    assert np.array_equal(lit.ids, reference.ids) and np.abs(lit.corners - reference.corners).max() < 0.5
    assert (np.median(np.linalg.norm(lit.corners - truth[lit.ids], axis=1))
            < np.median(np.linalg.norm(reference.corners - truth[reference.ids], axis=1)))
    dark = np.round(image * 0.6 ** 9).astype(np.uint8)
    assert len(opencv.detect(dark).ids) == 0
    found = hybrid.detect(dark)
    assert len(found.ids) >= 0.8 * board.num_corners and np.all(found.scores < 1.0)  # the networks' scores
    assert np.linalg.norm(found.corners - truth[found.ids], axis=1).max() < 3.0
    with pytest.raises(ValueError, match="mode"):
        Detector(board=board, mode="fast")


def test_huge_images_are_never_searched_above_the_cap():
    from deepcharuco.detection.deep_detector import MAX_SEARCH_SIZE

    # an 8000x6000 photo: the network at full size took 9.5 GB
    sides = [round(scale * 8000) for scale in Detector._level_scales(8000, 320)]
    assert sides == [320, 640, 1280, MAX_SEARCH_SIZE]
    assert Detector._level_scales(8000, None) == [1.0]


def test_a_level_a_pixel_or_two_short_of_the_full_image_is_the_full_image():
    """A tracked crop's working size is its frame's scale rounded (157 px at a quarter: 39, doubled by the tracker to
    78): its doubled level fell a pixel short of the crop, and a board too narrow at 156 px was searched again at 157."""
    def sides(longest, working_size):
        return [round(scale * longest) for scale in Detector._level_scales(longest, working_size)]

    assert sides(157, 78) == [78, 157] and sides(1001, 250) == [250, 500, 1001]
    assert sides(1280, 320) == [320, 640, 1280] and sides(1920, 320) == [320, 640, 1280, 1920]
    assert sides(1366, 320) == [320, 640, 1280, 1366] and sides(340, 320) == [320, 340]


def test_inverted_print_negated_about_its_local_white(camera):
    """A dim inverted board in a frame whose white is a lamp (caliscope's board across the room): negated about the
    frame's white it is pale grey on white; about its local white it is a dim board, found by its markers."""
    from deepcharuco.boards import print_face

    board = UNSEEN[2]  # 4x5 DICT_4X4_1000, inverted
    image, truth = view_of(board, camera, fill=0.6, **POSES[0])
    dim = np.round(image * 0.15).astype(np.uint8)  # the board's white print at ~38 / 255: negated about 255, no corner
    dim[:12, :12] = 255  # a lamp in the corner of the frame
    plain = print_face.canonical_view(dim, board)
    local = print_face.canonical_view_local_white(dim, board)
    inside = cv2.fillConvexPoly(np.zeros_like(dim), cv2.convexHull(truth.astype(np.int32)), 1).astype(bool)
    # The board's contrast is kept, on a dark level (black ink on dim paper), not on the frame's white.
    assert np.percentile(local[inside], 95) - np.percentile(local[inside], 5) >= 0.8 * (
        np.percentile(dim[inside], 95) - np.percentile(dim[inside], 5))
    assert np.median(local[inside]) < 128 < np.median(plain[inside])
    # Prints that are not inverted keep `canonical_view`.
    normal = BoardSpec(squares_x=4, squares_y=5, dictionary="DICT_4X4_1000")
    assert np.array_equal(print_face.canonical_view_local_white(dim, normal), print_face.canonical_view(dim, normal))
    found = Detector(board=board).detect(dim)
    assert len(found.ids) == board.num_corners
    assert np.linalg.norm(found.corners - truth[found.ids], axis=1).max() < 1.0


def test_marker_family_of_dictionaries():
    from deepcharuco.boards.dictionaries import MARKER_FAMILIES, marker_family

    for family, dictionaries in MARKER_FAMILIES.items():
        assert {marker_family(name) for name in dictionaries} == {family}
    assert marker_family("dict_4x4_250") == "DICT_4X4"
    assert marker_family("DICT_ARUCO_ORIGINAL") is None and marker_family("DICT_APRILTAG_16h5") is None


def test_detector_loads_the_shipped_weights_of_the_board_family(tmp_path, monkeypatch):
    import shutil

    from deepcharuco.detection import deep_detector
    from deepcharuco.networks.checkpoint import load_charuconet

    paper = BoardSpec()
    assert load_charuconet(deep_detector.DEFAULT_WEIGHTS)[1].same_layout(paper)  # BoardSpec() is the shipped board
    monkeypatch.setattr(deep_detector, "FAMILY_WEIGHTS_DIR", tmp_path)
    shutil.copy(deep_detector.DEFAULT_WEIGHTS, tmp_path / "DICT_6X6.pt")
    six = BoardSpec(squares_x=7, squares_y=5, square_length=0.04, marker_length=0.03, dictionary="DICT_6X6_250")
    seven = BoardSpec(squares_x=6, squares_y=4, square_length=0.04, marker_length=0.025, dictionary="DICT_7X7_50")
    assert deep_detector.shipped_weights(six) == tmp_path / "DICT_6X6.pt"
    assert deep_detector.shipped_weights(seven) == deep_detector.DEFAULT_WEIGHTS  # no DICT_7X7 model here
    assert deep_detector.shipped_weights(BoardSpec(inverted=True, square_length=0.02, marker_length=0.015)) \
        == deep_detector.DEFAULT_WEIGHTS  # the paper's board at another size keeps its own model and ID head
    assert deep_detector.shipped_weights(None) == deep_detector.DEFAULT_WEIGHTS
    detector = Detector(board=six)
    assert detector.weights == tmp_path / "DICT_6X6.pt" and detector.geometry == "markers"
    assert Detector(board=paper).weights == deep_detector.DEFAULT_WEIGHTS
    assert Detector(board=six, weights=deep_detector.DEFAULT_WEIGHTS).weights == deep_detector.DEFAULT_WEIGHTS


def test_shipped_family_models_are_point_heads_named_for_their_family():
    from pathlib import Path

    from deepcharuco.boards.dictionaries import MARKER_FAMILIES
    from deepcharuco.detection import deep_detector
    from deepcharuco.networks.checkpoint import load_charuconet

    for path in sorted(Path(deep_detector.FAMILY_WEIGHTS_DIR).glob("*.pt")):
        assert path.stem in MARKER_FAMILIES, f"{path.name} names no marker family"
        checkpoint = load_charuconet(path)[2]
        assert checkpoint.get("heads") == "points", f"{path.name} is not a family (points-only) model"
    shipped = sum(p.stat().st_size for p in Path(deep_detector.WEIGHTS_DIR).rglob("*") if p.is_file())
    assert shipped < 30e6  # every shipped weight together
    # This version ships DICT_4X4 and DICT_6X6 (chosen on validation boards, README "Family models"), each with
    # its model card; DICT_5X5 boards other than the paper's layout keep the paper's weights.
    six = BoardSpec(squares_x=5, squares_y=7, square_length=0.04, marker_length=0.03, dictionary="DICT_6X6_250")
    four = BoardSpec(squares_x=4, squares_y=5, square_length=0.054, marker_length=0.0405, dictionary="DICT_4X4_1000",
                     inverted=True)  # caliscope's board
    five = BoardSpec(squares_x=11, squares_y=8, square_length=0.022, marker_length=0.016, dictionary="DICT_5X5_1000")
    for board, family in ((six, "DICT_6X6"), (four, "DICT_4X4")):
        assert Detector(board=board).weights == Path(deep_detector.FAMILY_WEIGHTS_DIR) / f"{family}.pt"
        assert (Path(deep_detector.FAMILY_WEIGHTS_DIR) / f"{family}.md").is_file()
    assert Detector(board=five).weights == deep_detector.DEFAULT_WEIGHTS


def test_hybrid_keeps_opencvs_corners_of_a_board_too_small_for_the_geometry_check():
    """A 3x3 board has 4 corners, fewer than any view check needs: hybrid returns OpenCV's when it finds all 4."""
    board = BoardSpec(squares_x=3, squares_y=3, square_length=0.04, marker_length=0.03, dictionary="DICT_5X5_100")
    camera = Camera.from_fov(640, 480, hfov_deg=60.0)
    rvec, tvec = look_at_pose(board, 0.35, tilt_x_deg=20, tilt_y_deg=-10, roll_deg=15)
    image = render_board_view(board, camera.K, rvec, tvec, camera.image_size)
    reference = OpenCVDetector(board, refine="subpix").detect(image)
    assert len(reference.ids) == board.num_corners == 4
    found = Detector(board=board, mode="hybrid", corner_fit=False).detect(image)
    assert np.array_equal(found.ids, reference.ids) and np.allclose(found.corners, reference.corners)
    truth = project_corners(board, rvec, tvec, camera.K)
    assert np.linalg.norm(found.corners - truth[found.ids], axis=1).max() < 0.5
    fitted = Detector(board=board, mode="hybrid").detect(image)  # four corners: the fit's homography still holds
    assert np.array_equal(fitted.ids, reference.ids) and np.all(np.isfinite(fitted.covariances))
    assert np.linalg.norm(fitted.corners - truth[fitted.ids], axis=1).max() < 0.1


def test_a_degenerate_cell_maps_to_non_finite_values_without_a_warning():
    import warnings

    pixels = np.array([[10, 5], [0, 0], [0, 10], [0, 20]], np.float32)  # three corners on a line at pixel x = 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy's RuntimeWarning reached the user's terminal from a dark video
        maps = cell_homographies(pixels, np.array([[0, 1, 2, 3]]))
    assert not np.isfinite(maps).all()


def test_a_weights_folder_is_chosen_from_as_the_shipped_one_is(tmp_path, camera):
    """`Detector(weights=FOLDER)`: a folder laid out as deepcharuco/weights (a candidate set of networks for every
    family, e.g. distilled ones) gives each board its model as the shipped folder would."""
    import shutil

    from deepcharuco.core.errors import DeepCharucoError
    from deepcharuco.detection import deep_detector

    shutil.copytree(deep_detector.DEFAULT_WEIGHTS.with_suffix(".onnx"), tmp_path / "detector.onnx")
    shutil.copytree(deep_detector.FAMILY_WEIGHTS_DIR / "DICT_4X4.onnx", tmp_path / "families" / "DICT_4X4.onnx")
    four = BoardSpec(squares_x=4, squares_y=5, square_length=0.05, marker_length=0.0375, dictionary="DICT_4X4_1000",
                     inverted=True)
    six = BoardSpec(squares_x=7, squares_y=5, square_length=0.04, marker_length=0.03, dictionary="DICT_6X6_250")
    assert deep_detector.is_weights_folder(tmp_path) and not deep_detector.is_weights_folder(tmp_path / "families")
    assert Detector(weights=tmp_path).weights == tmp_path / "detector.onnx"
    assert Detector(board=four, weights=tmp_path).weights == tmp_path / "families" / "DICT_4X4.onnx"
    assert Detector(board=six, weights=tmp_path).weights == tmp_path / "detector.onnx"  # no DICT_6X6 model there
    # the same detections as the files named directly
    image, _ = view_of(four, camera, 0.7, tilt_x_deg=20, tilt_y_deg=-10, roll_deg=5)
    from_folder = Detector(board=four, weights=tmp_path).detect(image)
    direct = Detector(board=four, weights=deep_detector.FAMILY_WEIGHTS_DIR / "DICT_4X4.onnx").detect(image)
    assert len(from_folder) >= 10 and np.array_equal(from_folder.ids, direct.ids)
    assert np.array_equal(from_folder.corners, direct.corners)
    # a checkpoint beside a bundle is preferred, as in the shipped folder
    shutil.copy(deep_detector.DEFAULT_WEIGHTS, tmp_path / "detector.pt")
    assert deep_detector.shipped_weights(None, tmp_path) == tmp_path / "detector.pt"
    with pytest.raises(DeepCharucoError, match="weights folder"):
        Detector(weights=tmp_path / "families")


def test_network_fast_picks_the_shipped_fast_networks_as_a_weights_folder(camera):
    """`Detector(network="fast")`: the distilled fast networks (ONNX bundles of the fast architecture, one per
    shipped family), chosen per board as the lite ones are; refused with weights, on a GPU, or by another name."""
    from deepcharuco.core.errors import OptionError
    from deepcharuco.networks.onnx_bundle import read_bundle
    from deepcharuco.networks.shipped import FAST_WEIGHTS_DIR

    four = BoardSpec(squares_x=4, squares_y=5, square_length=0.054, marker_length=0.0405, dictionary="DICT_4X4_1000",
                     inverted=True)  # caliscope's board
    six = BoardSpec(squares_x=7, squares_y=5, square_length=0.04, marker_length=0.03, dictionary="DICT_6X6_250")
    assert Detector(network="fast").weights == FAST_WEIGHTS_DIR / "detector.onnx"
    for board, family in ((four, "DICT_4X4"), (six, "DICT_6X6")):
        fast = Detector(board=board, network="fast")
        assert fast.weights == FAST_WEIGHTS_DIR / "families" / f"{family}.onnx"
        # the fast network is the smaller: its point model is under half the lite one's file
        lite = read_bundle(Detector(board=board).weights.with_suffix(".onnx")).models["charuconet_points.onnx"]
        assert len(read_bundle(fast.weights).models["charuconet_points.onnx"]) < 0.5 * len(lite)
    image, truth = view_of(four, camera, 0.7, tilt_x_deg=20, tilt_y_deg=-10, roll_deg=5)
    found = Detector(board=four, network="fast").detect(image)
    assert len(found) >= 10
    assert np.linalg.norm(found.corners - truth[found.ids], axis=1).max() < 1.0  # every ID right
    with pytest.raises(OptionError, match="not both"):
        Detector(network="fast", weights=deep_detector.DEFAULT_WEIGHTS)
    with pytest.raises(OptionError, match="CPU"):
        Detector(network="fast", device="cuda")
    with pytest.raises(OptionError, match="network"):
        Detector(network="turbo")
