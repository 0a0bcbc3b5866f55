"""Sub-pixel corners by fitting the board's printed pattern, blurred, to the pixels around each corner.

Around an inner corner of a ChArUco board the print is known exactly: two black squares meeting at the corner and,
in the two white squares, each marker's black border starting ``margin`` from the square's edges. Within
``margin + part of a border bit`` of the corner (in squares, along the board's axes) nothing else is printed, so
the pixels there, smoothed a little (`PRE_BLUR_PX`), follow

    value(p) = alpha - beta * ink(p - c)        ink: the pattern's ink (1 ink, 0 paper), blurred

whose unknowns are the corner ``c`` (2), the blur across each of the board's two lines through it (2: the lens's,
the motion's, the pixel's and the smoothing's together; a motion blurs one line more than the other), the paper's
level ``alpha`` and the contrast ``beta``. Each quadrant of ink (a black square, a marker's border) is blurred as
the product of two blurred edges: exact for a square view, and for an oblique one a shape error that is
point-symmetric about the corner like the pattern itself, so it does not move ``c``. Levenberg-Marquardt fits the
six per corner, every corner at once; the board's lines' directions come from a homography of the view.

Each corner's covariance is the inverse normal matrix's corner block times a per-pixel variance: the sensor noise
measured around the corners (`image_noise`) and the fit's residual variance (what the model does not explain),
plus a small floor, with gains chosen so that error / sigma has a spread of 1 on validation views with exact
truth (`NOISE_GAIN`).

Pixels are the OpenCV convention (the centre of the top-left pixel is (0, 0)); the image is the board's canonical
view (black ink on white paper: `print_face.canonical_view`).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from deepcharuco.boards.board import BoardSpec
from deepcharuco.detection.junction import printed_pattern

try:  # the compiled windows and iterations (pip install deepcharuco[fast]); else numpy's, the same arithmetic
    from deepcharuco.detection.corner_fit_kernel import fit_windows
except ImportError:
    fit_windows = None

MARKER_BORDER_SHARE = 0.6  # the window reaches this far into the markers' black border (of a bit's width)
# Pixels beyond this many from the starting pixel are left out (a large view's corner): 7 gave the same corners in
# good light and 0.072 px against 0.088 at darkness k = 7 (validation views), for 1.6x the time.
MAX_HALF_WINDOW_PX = 5
MIN_PIXELS = 12  # a window of fewer pixels is not fitted
ITERATIONS = 6
PARAMETERS = 6  # the shift (x, y), the log blur across each line, alpha, beta
CONVERGED_PX = 3e-3  # the fit stops when every corner's last step was shorter than this
DAMPING = 1e-3  # Levenberg's damping, relative to the normal matrix's diagonal
MAX_STEP_PX = 0.5  # one step moves a corner at most this far ...
MAX_LOG_BLUR_STEP = 0.4  # ... and changes a blur by at most this factor's log
START_SIGMA_PX = 1.0
PRE_BLUR_PX = 0.7  # the image is blurred by this much before the fit
SIGMA_RANGE_PX = (0.15, 10.0)  # a fit whose blur leaves this range has not found the pattern
LOG_BLUR_LIMITS = (float(np.log(0.5 * SIGMA_RANGE_PX[0])), float(np.log(2 * SIGMA_RANGE_PX[1])))  # the fit's bounds
MAX_MOVE_PX = 1.5  # a corner the fit moves farther than this from its start keeps its start
# A corner's covariance: (NOISE_GAIN * noise^2 + MISFIT_GAIN * misfit) * spread + FLOOR_PX^2 (`CornerFit`), chosen on
# the validation views (python -m evaluate.calibration.corner_precision --seed 0, docs/detector.md): the spread of error / sigma
# is 0.91-1.12 in good light, darkness (k = 5, 7) and motion blur (k = 5, 9) there.
NOISE_GAIN = 1.5
MISFIT_GAIN = 0.5
FLOOR_PX = 0.003
# The least sigma of a corner the fit cannot place: RefineNet's RMS error there (validation, small squares). The
# detector gives such a corner its distance from where its neighbours put it where that is larger (`Detector._fitted`).
FALLBACK_SIGMA_PX = 0.5


@dataclass(frozen=True)
class CornerFit:
    """The fit of (N,) corners.

    Attributes:
        corners: (N, 2) float64 fitted pixels (the start where ``ok`` is False).
        covariances: (N, 2, 2) float64 px^2, calibrated (`NOISE_GAIN`); NaN where ``ok`` is False.
        sigma: (N, 2) the fitted blur (px) across each of the board's two lines; contrast: (N,) ``beta`` (grey
            levels); pixels: (N,) the pixels fitted.
        ok: (N,) bool: the fit found the pattern (positive contrast, blurs in `SIGMA_RANGE_PX`, a move within
            `MAX_MOVE_PX`, at least `MIN_PIXELS` pixels, a residual no larger than at the start).
        noise: (N,) the sensor noise (grey levels) measured around the corners (`image_noise`); misfit: (N,) the
            fit's residual variance (grey levels^2, of the smoothed pixels); spread: (N, 2, 2) the corner's
            covariance per unit noise variance (the inverse normal matrix's corner block, px^2).
    """

    corners: np.ndarray
    covariances: np.ndarray
    sigma: np.ndarray
    contrast: np.ndarray
    pixels: np.ndarray
    ok: np.ndarray
    noise: np.ndarray
    misfit: np.ndarray
    spread: np.ndarray


def board_axes(homography: np.ndarray, points: np.ndarray, square: float) -> np.ndarray:
    """(N, 2, 2) columns: the image vectors (px) of one square along the board's X and Y at board ``points``
    (N, 2) metres, from the view ``homography`` (board metres -> pixels)."""
    H = np.asarray(homography, np.float64)
    xy1 = np.column_stack([points, np.ones(len(points))])
    projected = xy1 @ H.T  # (N, 3)
    w = projected[:, 2:3]
    # d(p/w)/d(x, y) = (H[:2, :2] - p H[2, :2]) / w
    p = projected[:, :2] / w
    jacobian = (H[None, :2, :2] - p[:, :, None] * H[None, 2:3, :2]) / w[:, :, None]
    return jacobian * square


def _quadrant_signs(board: BoardSpec, ids: np.ndarray) -> np.ndarray:
    """(N,) +1 where the squares at (+X, +Y) and (-X, -Y) of each corner are black, -1 where the other two are:
    read from the printed pattern (`junction.printed_pattern`), whatever the board's layout."""
    return _board_quadrant_signs(board)[np.asarray(ids, np.int64)]


@lru_cache(maxsize=8)
def _board_quadrant_signs(board: BoardSpec) -> np.ndarray:
    """`_quadrant_signs` of every corner of ``board`` (read-only: shared between calls)."""
    texture = printed_pattern(board)
    inside = 0.5 * _window_reach(board)[0] * board.square_length  # within the margin: a marker's ink starts beyond
    points = board.corner_points()[:, :2] + inside
    u, v = np.round(texture.board_to_texture(points)).astype(np.int64).T
    signs = np.where(texture.image[v, u] < 128, 1.0, -1.0)
    signs.flags.writeable = False
    return signs


def _window_reach(board: BoardSpec) -> tuple[float, float]:
    """(margin, reach) in squares: where the markers' ink starts from a corner, and how far the window goes."""
    margin = 0.5 * (board.square_length - board.marker_length) / board.square_length
    bit = board.marker_length / (board.cv_dictionary().markerSize + 2) / board.square_length
    return margin, margin + MARKER_BORDER_SHARE * bit


def fit_corners(gray: np.ndarray, board: BoardSpec, homography: np.ndarray, ids: np.ndarray,
                corners: np.ndarray, compiled: bool | None = None) -> CornerFit:
    """The printed-pattern fit of corners ``ids`` (N,) started at ``corners`` (N, 2) in ``gray`` (H, W) uint8, the
    board's canonical view, seen through ``homography`` (board metres -> pixels; it gives the window's shape
    and the pattern's directions, so a rough one serves). ``compiled``: the windows and iterations by
    `corner_fit_kernel` (numba) or by numpy (False); None: compiled where numba is installed."""
    ids = np.asarray(ids, np.int64)
    start = np.asarray(corners, np.float64).reshape(-1, 2)
    n = len(ids)
    if n == 0:
        nothing = np.zeros((0, 2, 2))
        return CornerFit(start.copy(), nothing, np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64), np.zeros(0, bool),
                         np.zeros(0), np.zeros(0), nothing)
    margin, reach = _window_reach(board)
    axes = board_axes(homography, board.corner_points()[ids, :2], board.square_length)  # (N, 2, 2)
    to_board = _inverse_2x2(axes)  # (N, 2, 2): pixels -> squares
    usable = np.all(np.isfinite(to_board), axis=(1, 2)) & np.all(np.isfinite(start), axis=1)
    to_board[~usable] = 0.0
    # Each corner's window: the pixels of a common grid about its nearest pixel whose board offsets (from the start)
    # lie within the reach.
    extent = np.abs(axes).sum(axis=2).max(axis=1) * reach  # (N,) px: the window's half-size along x or y
    half = int(np.clip(np.ceil(np.max(np.where(usable, extent, 0.0))), 1, MAX_HALF_WINDOW_PX))
    height, width = gray.shape
    origin = np.round(np.where(usable[:, None], start, 0.0))  # each start's nearest pixel
    # The region every window lies in, and the pre-blur's reach (3 px at PRE_BLUR_PX) around it.
    inside = np.clip(origin, 0, [width - 1, height - 1]).astype(np.int64)
    x0, y0 = np.maximum(inside.min(axis=0) - half - 4, 0)
    x1, y1 = np.minimum(inside.max(axis=0) + half + 5, [width, height])
    # A little blur first: a pixel averages light over its area, which a sharp Gaussian edge sampled at the pixel's
    # centre models badly (the fit then crawls over a faceted surface); blurred, both are smooth, and a symmetric
    # blur moves no corner.
    raw = gray[y0:y1, x0:x1].astype(np.float32)
    smooth = cv2.GaussianBlur(raw, (0, 0), PRE_BLUR_PX)
    noise = np.full(n, image_noise(raw))

    # Unit normals of the board's two lines through the corner, and the markers' margin along each in px.
    row_norms = np.linalg.norm(to_board, axis=2)  # (N, 2)
    normals = to_board / np.where(row_norms > 0, row_norms, 1.0)[..., None]  # (N, 2, 2): rows n_s, n_t
    margins = margin / np.where(row_norms > 0, row_norms, 1.0)
    black = _quadrant_signs(board, ids)
    if compiled is None:
        compiled = fit_windows is not None
    elif compiled and fit_windows is None:
        raise ImportError("compiled=True needs numba: pip install 'deepcharuco[fast]'")
    # Gauss-Newton, lightly damped, each step's shift capped: the start is within a pixel or so, where the model is
    # smooth (`PRE_BLUR_PX`); a fit that ends worse than it began is refused below.
    if compiled:
        params, start_cost, cost, inverse, count = fit_windows(
            smooth, int(x0), int(y0), width, height, origin, start, to_board, normals, margins, black, usable,
            reach, half, float(np.log(START_SIGMA_PX)), ITERATIONS, DAMPING, MAX_STEP_PX, MAX_LOG_BLUR_STEP,
            *LOG_BLUR_LIMITS, CONVERGED_PX)
    else:
        values, weight, along = _windows(smooth, (int(x0), int(y0)), (width, height), origin, start, to_board, normals,
                                         usable, reach, half)
        params = _start_params(values, weight)
        start_cost, cost, inverse = _iterate(values, weight, _Pattern(along, normals, margins, black), params)
        count = weight.sum(axis=1)
    misfit = cost / np.maximum(count - PARAMETERS, 1)  # the smoothed pixels' residual variance
    # ``inverse`` is the covariance per unit noise variance. The sensor's noise, and what the model does not explain
    # (a shadow's edge, a motion's box-shaped blur, a neighbour's ink), each taken as noise of its variance; and a
    # floor for what neither shows.
    covariances = (NOISE_GAIN * noise ** 2 + MISFIT_GAIN * misfit)[:, None, None] * inverse + FLOOR_PX ** 2 * np.eye(2)
    fitted, sigma, contrast = start + params[:, :2], np.exp(params[:, 2:4]), params[:, 5]
    ok = (usable & (count >= MIN_PIXELS) & (contrast > 0) & (cost <= start_cost) & np.isfinite(params).all(axis=1)
          & np.all((sigma >= SIGMA_RANGE_PX[0]) & (sigma <= SIGMA_RANGE_PX[1]), axis=1)
          & (np.linalg.norm(fitted - start, axis=1) <= MAX_MOVE_PX) & np.all(np.isfinite(covariances), axis=(1, 2)))
    return CornerFit(np.where(ok[:, None], fitted, start), np.where(ok[:, None, None], covariances, np.nan),
                     sigma, contrast, count.astype(np.int64), ok, noise, misfit, inverse)


def _windows(smooth: np.ndarray, corner: tuple[int, int], size: tuple[int, int], origin: np.ndarray,
             start: np.ndarray, to_board: np.ndarray, normals: np.ndarray, usable: np.ndarray, reach: float, half: int
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The corners' windows in an image of ``size`` (W, H) (see `corner_fit_kernel.fit_windows`, which builds the
    same) -> (values (N, M) from ``smooth``, the blurred region of the image whose top-left pixel is ``corner``;
    weights (N, M), 1 in the window and 0 after its pixels; each pixel's px from the board's two lines through the
    start (N, M, 2))."""
    x0, y0 = corner
    width, height = size
    side = 2 * half + 1
    gy, gx = np.divmod(np.arange(side * side), side)
    grid = np.column_stack([gx, gy]).astype(np.float64) - half  # (M, 2), rows of x fastest: the kernel's order
    where = origin[:, None] + grid[None]  # (N, M, 2)
    inside = (where[..., 0] >= 0) & (where[..., 0] < width) & (where[..., 1] >= 0) & (where[..., 1] < height)
    offsets = where - start[:, None]
    board_offsets = np.einsum("nij,nmj->nmi", to_board, offsets)  # (N, M, 2) squares
    weight = (inside & (np.abs(board_offsets).max(axis=2) <= reach) & usable[:, None]).astype(np.float64)
    # Only the window's pixels: each corner's first `count` columns, the rest weighed 0.
    order = np.argsort(-weight, axis=1, kind="stable")[:, : max(int(weight.sum(axis=1).max()), 1)]
    where, weight = np.take_along_axis(where, order[..., None], 1), np.take_along_axis(weight, order, 1)
    offsets = np.take_along_axis(offsets, order[..., None], 1)
    xs = np.clip(where[..., 0] - x0, 0, smooth.shape[1] - 1).astype(np.int64)
    ys = np.clip(where[..., 1] - y0, 0, smooth.shape[0] - 1).astype(np.int64)
    values = np.where(weight > 0, smooth[ys, xs], 0.0).astype(np.float64)
    return values, weight, np.einsum("nij,nmj->nmi", normals, offsets)


def _start_params(values: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """(N, 6) starting parameters: no shift, blurs of `START_SIGMA_PX`, the paper's level and the contrast from the
    window's extremes (0 and 0 for an empty window: nothing to fit)."""
    n = len(values)
    window = weight > 0
    filled = window.any(axis=1)
    brightest = np.where(filled, np.where(window, values, -np.inf).max(axis=1, initial=-np.inf), 0.0)
    darkest = np.where(filled, np.where(window, values, np.inf).min(axis=1, initial=np.inf), 0.0)
    return np.column_stack([np.zeros((n, 2)), np.full((n, 2), np.log(START_SIGMA_PX)), brightest,
                            brightest - darkest])


def _iterate(values: np.ndarray, weight: np.ndarray, pattern: "_Pattern", params: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gauss-Newton over (N,) corners' ``params`` (N, 6), updated in place, each corner until its step was shorter
    than `CONVERGED_PX` (or `ITERATIONS`). Returns (the cost at the start (N,), at the end (N,), and the shift's
    block (N, 2, 2) of the inverse normal matrix J^T W J there, `_corner_block`). numpy over every corner at once;
    `corner_fit_kernel.fit_windows` takes the same steps compiled."""
    residual, jacobian = _residual(values, params, pattern, derivatives=True)
    start_cost = (weight * residual ** 2).sum(axis=1)
    moving = np.ones(len(params), bool)
    for _ in range(ITERATIONS):
        jw = np.swapaxes(jacobian * weight[..., None], 1, 2)  # (N, P, M)
        normal = jw @ jacobian  # (N, P, P)
        gradient = (jw @ residual[..., None])[..., 0]
        diagonal = np.einsum("nii->ni", normal)
        damped = normal + (DAMPING * np.maximum(diagonal, 1e-9))[:, :, None] * np.eye(PARAMETERS)
        step = _solve(damped, -gradient)
        length = np.linalg.norm(step[:, :2], axis=1)
        step *= np.minimum(1.0, MAX_STEP_PX / np.maximum(length, 1e-12))[:, None]
        step[:, 2:4] = np.clip(step[:, 2:4], -MAX_LOG_BLUR_STEP, MAX_LOG_BLUR_STEP)
        params[moving] += step[moving]
        params[:, 2:4] = np.clip(params[:, 2:4], *LOG_BLUR_LIMITS)
        residual, jacobian = _residual(values, params, pattern, derivatives=True)
        moving &= ~(length < CONVERGED_PX)  # a NaN step keeps its corner moving, as in the kernel
        if not moving.any():
            break
    jw = jacobian * weight[..., None]
    return start_cost, (weight * residual ** 2).sum(axis=1), _corner_block(np.einsum("nmi,nmj->nij", jw, jacobian))


def _corner_block(normal: np.ndarray) -> np.ndarray:
    """(N, 2, 2): the shift's block of the inverse of each normal matrix (N, 6, 6); NaN where one is singular or not
    finite (a diverged fit, an empty window: refused anyway)."""
    block = np.full((len(normal), 2, 2), np.nan)
    for i, matrix in enumerate(normal):
        if np.isfinite(matrix).all():
            try:
                block[i] = np.linalg.solve(matrix, np.eye(PARAMETERS)[:, :2])[:2]
            except np.linalg.LinAlgError:
                pass
    return block


def _inverse_2x2(matrices: np.ndarray) -> np.ndarray:
    """(N, 2, 2) inverses in closed form (NaN where singular): LAPACK's batched inverse costs more than the
    arithmetic for so small a matrix, and may wake BLAS threads."""
    with np.errstate(all="ignore"):
        determinant = matrices[:, 0, 0] * matrices[:, 1, 1] - matrices[:, 0, 1] * matrices[:, 1, 0]
        scale = np.where(determinant != 0, 1.0 / determinant, np.nan)
    inverse = np.swapaxes(matrices[:, ::-1, ::-1], 1, 2) * scale[:, None, None]  # [[d, b], [c, a]] / det ...
    inverse[:, 0, 1] *= -1  # ... with the off-diagonal negated: [[d, -b], [-c, a]] / det
    inverse[:, 1, 0] *= -1
    return inverse


# Immerkaer's noise operator: the difference of two Laplacians, blind to a flat patch, a ramp and an edge along a
# pixel axis; its response to white noise of deviation s has deviation 6 s.
_NOISE_KERNEL = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)


def image_noise(raw: np.ndarray) -> float:
    """The sensor noise (grey levels, per pixel) of an image region ``raw`` (H, W) float32: the lower quartile of
    `_NOISE_KERNEL`'s absolute response, as a Gaussian's deviation. The operator is blind to flat patches, ramps and
    edges along a pixel axis; the lower quartile also ignores the pattern's other edges and corners, which can be
    most of the pixels of a board of small squares."""
    if min(raw.shape) < 3:
        return 0.0
    # every other row and column: a quartile needs no more, and a large board's region is most of the frame
    response = np.abs(cv2.filter2D(raw, cv2.CV_32F, _NOISE_KERNEL)[1:-1:2, 1:-1:2]).ravel()
    # np.percentile(response, 25) by one partition: the same value, a fifth of the time
    rank = 0.25 * (response.size - 1)
    below = int(rank)
    above = min(below + 1, response.size - 1)
    ordered = np.partition(response, [below, above])
    low, high, t = float(ordered[below]), float(ordered[above]), rank - below
    quartile = low + (high - low) * t if t < 0.5 else high - (high - low) * (1 - t)  # numpy's linear interpolation
    # |N(0, 1)|'s lower quartile is 0.3186; the kernel's response to unit white noise has deviation 6
    return quartile / (0.3186 * 6.0)


def _solve(matrices: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Batched solve; a singular system gives a zero step."""
    try:
        return np.linalg.solve(matrices, vectors[..., None])[..., 0]
    except np.linalg.LinAlgError:
        out = np.zeros_like(vectors)
        for i, (a, b) in enumerate(zip(matrices, vectors)):
            try:
                out[i] = np.linalg.solve(a, b)
            except np.linalg.LinAlgError:
                pass
        return out


# The standard normal's cdf by erfc's approximation 7.1.26 of Abramowitz & Stegun (|error| <= 1.5e-7, a 4e-5 grey
# level change of the model at full contrast) on the pdf's own exponential: one exp for both, where an exact cdf
# doubles the compiled fit's time.
NDTR_P = 0.3275911 * np.sqrt(0.5)
NDTR_A = (0.254829592, -0.284496736, 1.421413741, -1.453152027, 1.061405429)


def _cdf_pdf(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the standard normal's cdf, its pdf) at ``z`` (any shape); `corner_fit_kernel._cdf_pdf` compiled."""
    e = np.exp(-0.5 * z * z)
    t = 1.0 / (1.0 + NDTR_P * np.abs(z))
    a1, a2, a3, a4, a5 = NDTR_A
    tail = 0.5 * t * (a1 + t * (a2 + t * (a3 + t * (a4 + t * a5)))) * e
    return np.where(z < 0.0, tail, 1.0 - tail), e * (1.0 / np.sqrt(2 * np.pi))


@dataclass(frozen=True)
class _Pattern:
    """The windows' geometry: ``along`` (N, M, 2) each pixel's signed px from the board's two lines through the
    starting corner (along their unit ``normals`` (N, 2, 2), rows n_s, n_t), the markers' ``margins`` (N, 2) px
    along each, and ``black`` (N,) (`_quadrant_signs`)."""

    along: np.ndarray
    normals: np.ndarray
    margins: np.ndarray
    black: np.ndarray

    def ink(self, params: np.ndarray, derivatives: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """The blurred pattern's ink (N, M) for corners moved by ``params[:, :2]`` px from the start and blurred by
        exp(``params[:, 2]``) px across the first line and exp(``params[:, 3]``) across the second, and, with
        ``derivatives``, its derivatives (N, M, 4) by those four.

        Four quadrants of ink: the two black squares (signs (1, b) and (-1, -b) along the normals, b = ``black``)
        and the two markers' borders in the white squares (signs (1, -b) and (-1, b)), ``margins`` out."""
        sigma = np.exp(params[:, None, 2:4])  # (N, 1, 2)
        # px from each line, the second's sign flipped where the black squares are at (+1, -1), so that the black
        # squares are the quadrants (+, +) and (-, -) and the markers' borders (+ margin, - margin) and (-, +) for all
        shift = np.einsum("nij,nj->ni", self.normals, params[:, :2])[:, None]
        flip = np.stack([np.ones_like(self.black), self.black], axis=1)[:, None]  # (N, 1, 2)
        along = (self.along - shift) * flip
        margins = self.margins[:, None]
        z0, zp, zm = along / sigma, (along - margins) / sigma, (-along - margins) / sigma  # each (N, M, 2)
        (f0, p0), (fp, pp), (fm, pm) = _cdf_pdf(z0), _cdf_pdf(zp), _cdf_pdf(zm)
        ink = (f0[..., 0] * f0[..., 1] + (1 - f0[..., 0]) * (1 - f0[..., 1])
               + fp[..., 0] * fm[..., 1] + fm[..., 0] * fp[..., 1])
        if not derivatives:
            return ink, None
        other = (2 * f0[..., ::-1] - 1, fm[..., ::-1], fp[..., ::-1])  # the other line's factors, for each line
        # d ink / d along (per line, times sigma) and d ink / d log sigma (per line)
        d_along = (p0 * other[0] + pp * other[1] - pm * other[2]) / sigma
        d_sigma = -(p0 * z0 * other[0] + pp * zp * other[1] + pm * zm * other[2])
        axes = flip[:, 0, :, None] * self.normals  # (N, 2, 2): d along / d shift = -flip n
        d_shift = -(d_along[..., 0:1] * axes[:, None, 0] + d_along[..., 1:2] * axes[:, None, 1])
        return ink, np.concatenate([d_shift, d_sigma], axis=2)


def _residual(values: np.ndarray, params: np.ndarray, pattern: _Pattern, derivatives: bool):
    """Model minus ``values`` (N, M), and with ``derivatives`` the Jacobian (N, M, 6) by the shift x, y, the two log
    blurs, alpha and beta (``params`` (N, 6))."""
    ink, d_ink = pattern.ink(params, derivatives)
    alpha, beta = params[:, 4:5], params[:, 5:6]
    residual = alpha - beta * ink - values
    if not derivatives:
        return residual, None
    jacobian = np.concatenate([-beta[..., None] * d_ink, np.ones_like(ink)[..., None], -ink[..., None]], axis=2)
    return residual, jacobian


def view_homography(board: BoardSpec, ids: np.ndarray, corners: np.ndarray) -> np.ndarray | None:
    """Board metres -> pixels fitted to detected ``corners`` (N, 2) of ``ids`` (N,) (least squares), or None for
    fewer than 4."""
    if len(ids) < 4:
        return None
    homography, _ = cv2.findHomography(board.corner_points()[np.asarray(ids, np.int64), :2],
                                       np.asarray(corners, np.float64).reshape(-1, 2), 0)
    return homography
