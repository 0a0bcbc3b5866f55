"""The compiled decoding (`decode_kernel`, numba) and its numpy path give the same corners; the search's second pass
reuses the first pass's reads (`placement.CellReads`) without changing them."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import ROOT

from deepcharuco import BoardSpec, Camera, Detector
from deepcharuco.boards.synthetic import look_at_pose, render_board_view
from deepcharuco.detection.markers import lattice, marker_reader, placement


SAMPLES = ROOT / "evaluate" / "captures_sample"


def photos() -> list[tuple[str, Path, Path]]:
    """(name, image, board.yaml) of the shipped real photos and the example frame."""
    found = [(f"{folder.name}/{image.name}", image, folder / "board.yaml")
             for folder in sorted(SAMPLES.iterdir()) if (folder / "board.yaml").is_file()
             for image in sorted(folder.glob("*.jpg"))]
    return found + [("example", ROOT / "deepcharuco" / "examples" / "board_320x240.png", None)]


def drawn(condition: str) -> tuple[np.ndarray, BoardSpec]:
    """The paper's board drawn at 640x480 under a tilted view: sharp, dark (3 % of the light, sensor noise) or
    motion-blurred (k = 9) and dim."""
    board = BoardSpec()
    camera = Camera.from_fov(640, 480, hfov_deg=60.0)
    rvec, tvec = look_at_pose(board, distance=0.35, tilt_x_deg=25, tilt_y_deg=-20, roll_deg=15)
    image = render_board_view(board, camera.K, rvec, tvec, camera.image_size).astype(np.float32)
    rng = np.random.default_rng(51)
    if condition == "dark":
        image = image * 0.03 + rng.normal(0, 0.6, image.shape)
    elif condition == "blurred":
        image = cv2.blur(image, (9, 1)) * 0.3 + rng.normal(0, 1.0, image.shape)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8), board


def detect_both(monkeypatch, image: np.ndarray, board: BoardSpec):
    """The deep detector's detection of ``image`` with the compiled decoding, then with numpy's."""
    detector = Detector(board)
    compiled = detector.detect(image)
    with monkeypatch.context() as patch:
        patch.setattr(marker_reader, "compiled_kernel", None)
        patch.setattr(lattice, "compiled_kernel", None)
        patch.setattr(placement, "compiled_kernel", None)
        plain = detector.detect(image)
    return compiled, plain


def assert_same(compiled, plain) -> None:
    assert np.array_equal(compiled.ids, plain.ids)
    assert np.array_equal(compiled.corners, plain.corners)  # bit for bit
    assert np.array_equal(compiled.scores, plain.scores)


@pytest.mark.parametrize("name,image,board", photos(), ids=[p[0] for p in photos()])
def test_compiled_and_numpy_decoding_agree_on_real_photos(monkeypatch, name, image, board):
    pytest.importorskip("numba")
    gray = cv2.imread(str(image), cv2.IMREAD_GRAYSCALE)
    board = BoardSpec() if board is None else BoardSpec.load(board)
    compiled, plain = detect_both(monkeypatch, gray, board)
    assert_same(compiled, plain)


def test_the_real_photos_hold_boards_the_detector_finds(monkeypatch):
    """The agreement above is on found boards, not on empty detections alike."""
    pytest.importorskip("numba")
    found = 0
    for _, image, board in photos():
        board = BoardSpec() if board is None else BoardSpec.load(board)
        found += len(Detector(board).detect(cv2.imread(str(image), cv2.IMREAD_GRAYSCALE))) >= 4
    assert found >= len(photos()) // 2


@pytest.mark.parametrize("condition", ["sharp", "dark", "blurred"])
def test_compiled_and_numpy_decoding_agree_on_drawn_views(monkeypatch, condition):
    pytest.importorskip("numba")
    image, board = drawn(condition)
    compiled, plain = detect_both(monkeypatch, image, board)
    assert len(compiled) >= 6  # found in every condition: the comparison is of corners
    assert_same(compiled, plain)


def random_squares(rng: np.random.Generator, count: int, size: tuple[int, int]) -> np.ndarray:
    """(count, 3, 3) float32 unit square -> image maps of random quads inside an image of ``size`` (w, h)."""
    quads = []
    for _ in range(count):
        centre = rng.uniform(20, np.array(size) - 20)
        corners = centre + rng.uniform(4, 15) * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) \
            + rng.normal(0, 2, (4, 2))
        unit = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
        quads.append(cv2.getPerspectiveTransform(unit, corners.astype(np.float32)))
    return np.asarray(quads, np.float32)


def test_kernels_compute_the_numpy_paths_values():
    kernel = pytest.importorskip("deepcharuco.detection.markers.decode_kernel")
    rng = np.random.default_rng(7)
    size, ratio = 6, 0.7
    homographies = random_squares(rng, 300, (640, 480))
    local = marker_reader._local_points(size, ratio)
    maps = kernel.square_maps(homographies, local)
    plain_maps = marker_reader._square_maps(homographies, local)
    for compiled, plain in zip(maps, plain_maps):
        assert compiled.dtype == plain.dtype == np.float32 and np.array_equal(compiled, plain)
    image = cv2.GaussianBlur(rng.integers(0, 256, (480, 640), dtype=np.uint8), (0, 0), 2)
    values = marker_reader.sample_maps(image, *maps)
    samples = marker_reader._sample_grid(size, ratio)[0].shape[1]
    for compiled, plain in zip(kernel.reduce_reads(values, size + 2, samples),
                               marker_reader._reduce_reads(values, size + 2, samples)):
        assert compiled.dtype == plain.dtype and np.array_equal(compiled, plain)


def test_squares_inside_kernel_decides_as_numpy():
    """Squares inside a 640x480 image, across its edges, beyond it, behind the camera and degenerate: the same
    decisions, corners exactly on the image's last pixel among them."""
    kernel = pytest.importorskip("deepcharuco.detection.markers.decode_kernel")
    rng = np.random.default_rng(8)
    width, height = 640, 480
    squares = random_squares(rng, 400, (width, height)).astype(np.float64)
    near_edges = rng.uniform(-30, 30, (100, 2)) + rng.choice([0, 1], (100, 2)) * [width, height]
    squares[100:200, :2] -= squares[100:200, 2:, :] * (squares[100:200, :2, 2:] / squares[100:200, 2:, 2:])
    squares[100:200, :2] += squares[100:200, 2:, :] * near_edges[:, :, None]  # moved onto the edges
    squares[200:220] *= -1  # w < 0: behind the camera
    squares[220:230, 2] = 0  # w = 0: the corners at infinity
    edge = np.array([[width - 11.0, 0.0, 10.0], [0.0, height - 11.0, 10.0], [0.0, 0.0, 1.0]])  # a corner on (W - 1, H - 1)
    squares = np.concatenate([squares, edge[None], (edge + np.diag([1e-9, 0, 0]))[None]])
    compiled = kernel.squares_inside(np.ascontiguousarray(squares), width, height)
    plain = marker_reader._squares_inside(squares, width, height)
    assert compiled.dtype == plain.dtype == bool and np.array_equal(compiled, plain)
    assert 100 < plain.sum() < len(squares) - 100 and plain[-2] and not plain[-1]  # 30 % outside


def test_squarest_cells_kernel_keeps_the_same_cells(monkeypatch):
    kernel = pytest.importorskip("deepcharuco.detection.markers.decode_kernel")
    rng = np.random.default_rng(3)
    # a sheared, jittered lattice and clutter: many quads, rivals on shared sides
    x, y = np.meshgrid(np.arange(12), np.arange(9))
    lattice_points = np.stack([x.ravel() * 20 + y.ravel() * 6, y.ravel() * 17], axis=1) + rng.normal(0, 1.5, (108, 2))
    pixels = np.concatenate([lattice_points + 40, rng.uniform(0, 320, (40, 2))]).astype(np.float32)
    quads = lattice.find_cells(pixels)
    kept = lattice.squarest_cells(pixels, quads)
    assert 0 < len(kept) < len(quads)
    points = pixels.astype(np.float64)[quads]
    ahead, behind = np.roll(points, -1, axis=1) - points, np.roll(points, 1, axis=1) - points
    cosine = (np.abs(np.sum(ahead * behind, axis=2)) / np.maximum(
        np.linalg.norm(ahead, axis=2) * np.linalg.norm(behind, axis=2), 1e-12)).max(axis=1)
    area = lattice.quad_areas(points)
    sides = quads * (int(quads.max()) + 1) + np.roll(quads, -1, axis=1)
    order = np.argsort(cosine, kind="stable")
    _, compact = np.unique(sides, return_inverse=True)
    compiled = kernel.squarest_keep(compact.reshape(sides.shape).astype(np.int64), cosine, area, order,
                                    lattice.SQUARER_BY, lattice.SAME_AREA, lattice.CONTAINED_AREA)
    plain = lattice._squarest_keep(sides, cosine, area, order)
    assert np.array_equal(compiled, plain)
    assert np.array_equal(quads[plain], kept)
    # the whole choice compiled (angles, areas, side IDs, order: `squarest_cells_keep`) keeps the same quads
    with monkeypatch.context() as patch:
        patch.setattr(lattice, "compiled_kernel", None)
        assert np.array_equal(lattice.squarest_cells(pixels, quads), kept)


@pytest.mark.parametrize("integer", [False, True], ids=["subpixel", "integer pixels (ties)"])
def test_find_cells_kernel_finds_the_same_cells(integer):
    """`decode_kernel.cell_quads` makes `lattice._cell_quads`' quads, in their order, on a jittered lattice among
    clutter; integer pixels (a search level's cell pixels) tie many distances."""
    kernel = pytest.importorskip("deepcharuco.detection.markers.decode_kernel")
    rng = np.random.default_rng(11)
    x, y = np.meshgrid(np.arange(10), np.arange(8))
    lattice_points = np.stack([x.ravel() * 18 + y.ravel() * 5, y.ravel() * 15], axis=1) + rng.normal(0, 1.0, (80, 2))
    pixels = np.concatenate([lattice_points + 30, rng.uniform(0, 260, (60, 2))])
    points = np.rint(pixels) if integer else pixels
    near = lattice._nearest(points, lattice.NEIGHBOURS)
    compiled = kernel.cell_quads(points, near, lattice.MIN_SIDE_PX, lattice.MAX_SIDE_RATIO, lattice.MIN_SINE,
                                 lattice.CLOSURE_TOLERANCE)
    plain = lattice._cell_quads(points, near)
    assert len(plain) > 100 and np.array_equal(compiled, plain)
    cells = lattice.find_cells(points)
    assert 50 <= len(cells) < len(plain)  # de-duplicated: each cell found from several of its corners once


def test_cell_homographies_kernel_maps_as_numpy(monkeypatch):
    """The compiled closed form gives numpy's maps bit for bit, a degenerate quad (three corners on a line) alike."""
    pytest.importorskip("deepcharuco.detection.markers.decode_kernel")
    rng = np.random.default_rng(9)
    pixels = rng.uniform(0, 640, (60, 2)).astype(np.float32)
    pixels[1:4] = [[10, 10], [30, 30], [20, 20]]  # on one line: b, d and c of the last quad
    quads = np.array([rng.choice(60, 4, replace=False) for _ in range(200)] + [[0, 1, 2, 3]])
    compiled = lattice.cell_homographies(pixels, quads)
    with monkeypatch.context() as patch:
        patch.setattr(lattice, "compiled_kernel", None)
        plain = lattice.cell_homographies(pixels, quads)
    assert np.array_equal(compiled, plain, equal_nan=True)
    assert not np.isfinite(plain[-1]).all() and np.isfinite(plain[:-1]).all(axis=(1, 2)).mean() > 0.9


def test_square_sides_kernel_measures_as_numpy(monkeypatch):
    pytest.importorskip("deepcharuco.detection.markers.decode_kernel")
    squares = random_squares(np.random.default_rng(13), 300, (640, 480)).astype(np.float64)
    squares[5, 2] = [0.0, 0.0, 0.0]  # a frame sending the square to infinity
    compiled = placement._square_sides(squares)
    with monkeypatch.context() as patch:
        patch.setattr(placement, "compiled_kernel", None)
        with np.errstate(divide="ignore", invalid="ignore"):
            plain = placement._square_sides(squares)
    assert np.array_equal(compiled, plain, equal_nan=True) and np.isfinite(plain).sum() == 299


def test_agreement_kernel_decides_as_numpy():
    """`decode_kernel.agreement` gives `placement._agreement`'s (H, K) decisions: proposals of one view (which agree)
    among random ones, a proposal sending points to infinity, and one that is not finite."""
    kernel = pytest.importorskip("deepcharuco.detection.markers.decode_kernel")
    rng = np.random.default_rng(5)
    view = np.array([[30.0, 4.0, 100.0], [-3.0, 28.0, 80.0], [1e-3, 2e-3, 1.0]])
    square_xy = rng.integers(0, 8, (400, 2)).astype(np.float64)
    proposals = np.repeat(view[None], 400, axis=0) + rng.normal(0, 0.05, (400, 3, 3)) * [[1, 1, 10], [1, 1, 10],
                                                                                         [0, 0, 0]]
    proposals[::3] = rng.normal(0, 20, (134, 3, 3))  # a third of them random
    proposals[7, 2] = [0.0, 0.0, 0.0]  # w = 0 everywhere: at infinity
    proposals[11, 0, 0] = np.nan
    hypotheses = np.argsort(rng.random(400), kind="stable")[:128].astype(np.int64)
    reach = rng.uniform(3, 12, 400)
    compiled = kernel.agreement(proposals, square_xy, hypotheses, reach)
    plain = placement._agreement(proposals, square_xy, hypotheses, reach)
    assert np.array_equal(compiled, plain)
    assert 0.1 < plain.mean() < 0.9  # both outcomes are decided, not all alike
    assert not plain[:, [7, 11]].any() and not plain[np.isin(hypotheses, [7, 11])].any()


@pytest.mark.parametrize("distinct", [5, 40, 200, 300])  # numpy's pairwise sum: in order, 8 running sums, halves
def test_support_kernel_sums_as_numpy(distinct):
    """`decode_kernel.support` gives `placement._support`'s evidence to the last bit (so the same hypothesis wins,
    ties included): proposals of ``distinct`` markers out of 400, with negative correlations (counted as 0)."""
    kernel = pytest.importorskip("deepcharuco.detection.markers.decode_kernel")
    rng = np.random.default_rng(distinct)
    marker = rng.choice(rng.permutation(400)[:distinct], 3 * distinct).astype(np.int64)
    ncc = rng.uniform(-0.3, 1.0, len(marker))
    agrees = rng.random((64, len(marker))) < 0.6
    agrees[5] = agrees[3]  # two hypotheses with one support: the first must win in both
    compiled = kernel.support(marker, ncc, agrees, 400)
    plain = placement._support(marker, ncc, agrees)
    assert np.array_equal(compiled, plain) and np.argmax(compiled) == np.argmax(plain)
    assert compiled[5] == compiled[3]


def test_best_pairs_kernel_ranks_as_a_stable_sort():
    """`decode_kernel.best_pairs` keeps each read's best (marker, turn) columns as a stable sort of the scores ranks
    them (equal scores: the lower column first), those at or above the floor: ties at every place, and reads whose
    second best is below it."""
    kernel = pytest.importorskip("deepcharuco.detection.markers.decode_kernel")
    rng = np.random.default_rng(9)
    ncc = np.round(rng.uniform(-1, 1, (300, 48)), 1)  # one decimal: many equal scores in a row
    ncc[0] = 0.9  # all equal
    ncc[1, [3, 7, 40]] = 0.95  # three equal bests
    for per_read in (1, 2, 3):
        rows, columns, scores = kernel.best_pairs(ncc, per_read, 0.3)
        order = np.argsort(-ncc, axis=1, kind="stable")[:, :per_read]
        expected = [(r, int(c)) for r in range(len(ncc)) for c in order[r] if ncc[r, c] >= 0.3]
        assert list(zip(rows.tolist(), columns.tolist())) == expected
        assert np.array_equal(scores, ncc[rows, columns])
    rows, columns, _ = kernel.best_pairs(ncc, 2, 0.3)
    assert columns[rows == 0].tolist() == [0, 1] and columns[rows == 1].tolist() == [3, 7]
    assert len(kernel.best_pairs(np.zeros((0, 48)), 2, 0.3)[0]) == 0


def test_cell_reads_reuse_reads_and_read_only_new_cells():
    rng = np.random.default_rng(11)
    image, board = drawn("sharp")
    markers = marker_reader.board_markers(board)
    squares = random_squares(rng, 40 * 5, (640, 480)).astype(np.float64).reshape(40, 5, 3, 3)

    read_rows = []

    def read(rows):
        read_rows.append(int(rows.sum()))
        return marker_reader.read_squares(image, squares[rows].reshape(-1, 3, 3), markers.size, markers.ratio)

    direct = marker_reader.read_squares(image, squares.reshape(-1, 3, 3), markers.size, markers.ratio)
    assert (direct[1] > 0).sum() >= 10  # readable squares among them (19): the reads compared are not all zero
    reads = placement.CellReads(40)
    first = rng.permutation(40)[:25]
    bits, contrast = reads.read(first, lambda new: marker_reader.read_squares(
        image, squares[first][new].reshape(-1, 3, 3), markers.size, markers.ratio))
    assert np.array_equal(bits, direct[0].reshape(40, 5, *bits.shape[1:])[first].reshape(bits.shape))
    bits, contrast = reads.read(np.arange(40), read)
    assert read_rows == [15]  # only the cells the first call did not read
    assert np.array_equal(bits, direct[0]) and np.array_equal(contrast, direct[1])
    bits, contrast = reads.read(first[::-1], read)  # all kept: nothing read, in the rows' order
    assert read_rows == [15] and np.array_equal(bits, direct[0].reshape(40, 5, -1)[first[::-1]].reshape(bits.shape))
