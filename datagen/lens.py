"""Lens distortion for rendered frames: OpenCV's distortion model applied to an undistorted render.

A renderer (Blender, or `deepcharuco.boards.synthetic.render_board_view`) draws a pinhole image. A
distorted camera (K, dist) at W x H is made from one by rendering a *wider* pinhole view
(`wide_camera`: square pixels, covering every ray the distorted image sees) and resampling it
(`distort_image`): the output pixel p shows what the pinhole render shows at the ray
``undistort(p)``. `undistort_normalized` inverts OpenCV's model to 1e-12 (Newton's method), so a
feature that the render puts at ray x appears where ``cv2.projectPoints`` with (K, dist) puts x:
labels are ``cv2.projectPoints`` with the distorted camera, nothing else.

Supported coefficients: OpenCV's 4, 5, 8 or 12 (k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4]]]), the
model of ``cv2.calibrateCamera`` (the thin-prism terms included; no tilted sensor). The radial
part must be monotonic over the image (`check_monotonic`), as it is for any real lens: where it
folds, one pixel would see two rays.

Pixel convention: OpenCV's (the centre of the top-left pixel is (0, 0)).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

NEWTON_ITERATIONS = 30
NEWTON_TOLERANCE = 1e-12  # normalised units: ~1e-9 px at any focal length used here


class LensError(ValueError):
    """A distortion model this module cannot render (unsupported coefficients, folding)."""


def _coefficients(dist: np.ndarray | None) -> np.ndarray:
    """(12,) float64 k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4 from an OpenCV vector of 0/4/5/8/12 values."""
    values = np.zeros(12) if dist is None else np.asarray(dist, np.float64).ravel()
    if values.size == 14:
        if np.any(values[12:] != 0):
            raise LensError("tilted-sensor coefficients (tau_x, tau_y) are not supported; give 4, 5, 8 or 12 values")
        values = values[:12]
    if values.size not in (0, 4, 5, 8, 12):
        raise LensError(f"distortion must have 4, 5, 8 or 12 coefficients (OpenCV's order), got {values.size}")
    return np.concatenate([values, np.zeros(12 - values.size)])


def distort_normalized(xy: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    """(..., 2) ideal normalised coordinates (X/Z, Y/Z) -> (..., 2) distorted ones, OpenCV's model
    exactly (``cv2.projectPoints`` = K applied to this)."""
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = _coefficients(dist)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r2 * r2
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r2 * r2
    return np.stack([xd, yd], axis=-1)


def undistort_normalized(xy_distorted: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    """(..., 2) distorted normalised coordinates -> (..., 2) ideal ones: the inverse of
    `distort_normalized`, by Newton's method from OpenCV's own estimate (``cv2.undistortPoints``,
    a fixed-point iteration that stops short near strong distortion). Raises LensError where it
    does not converge (a point beyond the fold of a non-monotonic model)."""
    target = np.asarray(xy_distorted, np.float64)
    shape = target.shape
    target = target.reshape(-1, 2)
    if target.size == 0:
        return target.reshape(shape)
    coefficients = _coefficients(dist)
    start = cv2.undistortPoints(target.reshape(-1, 1, 2), np.eye(3), coefficients).reshape(-1, 2)
    x = start.copy()
    step = 1e-7
    for _ in range(NEWTON_ITERATIONS):
        residual = distort_normalized(x, coefficients) - target
        if np.abs(residual).max() < NEWTON_TOLERANCE:
            break
        # 2x2 Jacobian by central differences, one per point.
        jx = (distort_normalized(x + [step, 0.0], coefficients) - distort_normalized(x - [step, 0.0], coefficients)) / (2 * step)
        jy = (distort_normalized(x + [0.0, step], coefficients) - distort_normalized(x - [0.0, step], coefficients)) / (2 * step)
        det = jx[:, 0] * jy[:, 1] - jy[:, 0] * jx[:, 1]
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        x = x - np.stack([(jy[:, 1] * residual[:, 0] - jy[:, 0] * residual[:, 1]) / det,
                          (-jx[:, 1] * residual[:, 0] + jx[:, 0] * residual[:, 1]) / det], axis=1)
    residual = np.abs(distort_normalized(x, coefficients) - target).max()
    if not np.isfinite(residual) or residual > 1e-9:
        raise LensError(f"the distortion model cannot be inverted here (residual {residual:.2g}): it folds inside the "
                        f"image; use coefficients whose radial part is monotonic (k2 >= k1^2 / 2 when k1 < 0)")
    return x.reshape(shape)


def pixel_grid(width: int, height: int, supersample: int = 1) -> np.ndarray:
    """(H*s, W*s, 2) float64 positions, in output pixels, of the centres of an s x s subsampling of each
    pixel (s = ``supersample``): subpixel i of pixel u is at u + (i + 0.5) / s - 0.5."""
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    xs = (np.arange(width)[:, None] + offsets[None, :]).ravel()
    ys = (np.arange(height)[:, None] + offsets[None, :]).ravel()
    grid_x, grid_y = np.meshgrid(xs, ys)
    return np.stack([grid_x, grid_y], axis=-1)


def pixels_to_rays(pixels: np.ndarray, K: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    """(..., 2) distorted pixels of the camera (K, dist) -> (..., 2) ideal normalised coordinates (X/Z, Y/Z)."""
    K = np.asarray(K, np.float64)
    pixels = np.asarray(pixels, np.float64)
    y = (pixels[..., 1] - K[1, 2]) / K[1, 1]
    x = (pixels[..., 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return undistort_normalized(np.stack([x, y], axis=-1), dist)


def check_monotonic(K: np.ndarray, dist: np.ndarray | None, image_size: tuple[int, int]) -> None:
    """Raise LensError unless the model maps rays to the image one to one: along every direction, the
    distorted radius must grow with the ideal one until it passes the image's farthest corner (+20 %)."""
    width, height = image_size
    K = np.asarray(K, np.float64)
    corners = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [-0.5, height - 0.5], [width - 0.5, height - 0.5]])
    seen = 1.2 * float(np.linalg.norm((corners - K[:2, 2]) / np.diag(K)[:2], axis=1).max())
    radii = np.linspace(0.0, 4.0 * seen, 4000)  # ideal radii: a barrel lens needs more than `seen`
    for angle in np.linspace(0.0, 2 * math.pi, 16, endpoint=False):
        direction = np.array([math.cos(angle), math.sin(angle)])
        distorted = distort_normalized(radii[:, None] * direction, dist) @ direction
        beyond = np.flatnonzero(distorted >= seen)
        reach = int(beyond[0]) if beyond.size else len(radii) - 1
        if not beyond.size or not np.all(np.diff(distorted[: reach + 1]) > 0):
            raise LensError(f"the distortion folds inside the image (distorted radius stops growing before "
                            f"{seen:.3f}, the image corner's): one pixel would see two rays; make the radial part "
                            f"monotonic (k2 >= k1^2 / 2 when k1 < 0)")


def wide_camera(K: np.ndarray, dist: np.ndarray | None, image_size: tuple[int, int], *, scale: float = 1.0,
                pad_px: int = 3) -> tuple[np.ndarray, tuple[int, int]]:
    """The undistorted pinhole camera to render for the distorted camera (K, dist) at ``image_size``.

    Returns (K_wide (3, 3), (width, height)): square pixels with focal length ``scale`` * max(fx, fy),
    just covering the rays of every output pixel (the whole pixel area, plus ``pad_px`` render pixels so
    bilinear sampling never reads outside). Its principal point is generally off-centre."""
    width, height = image_size
    check_monotonic(K, dist, image_size)
    # The extreme rays lie on the border for monotonic radial distortion; sample the interior coarsely
    # too, which costs little and covers tangential terms.
    border = np.concatenate([
        np.stack([np.linspace(-0.5, width - 0.5, 4 * width), np.full(4 * width, -0.5)], 1),
        np.stack([np.linspace(-0.5, width - 0.5, 4 * width), np.full(4 * width, height - 0.5)], 1),
        np.stack([np.full(4 * height, -0.5), np.linspace(-0.5, height - 0.5, 4 * height)], 1),
        np.stack([np.full(4 * height, width - 0.5), np.linspace(-0.5, height - 0.5, 4 * height)], 1),
        pixel_grid(width // 8 + 1, height // 8 + 1).reshape(-1, 2) * 8.0,
    ])
    rays = pixels_to_rays(border, K, dist)
    focal = scale * max(float(K[0, 0]), float(K[1, 1]))
    low, high = rays.min(axis=0) * focal, rays.max(axis=0) * focal
    wide_width = int(math.ceil(high[0] - low[0])) + 2 * pad_px + 1
    wide_height = int(math.ceil(high[1] - low[1])) + 2 * pad_px + 1
    K_wide = np.array([[focal, 0.0, pad_px - low[0]], [0.0, focal, pad_px - low[1]], [0.0, 0.0, 1.0]])
    return K_wide, (wide_width, wide_height)


def distortion_maps(K: np.ndarray, dist: np.ndarray | None, image_size: tuple[int, int], K_wide: np.ndarray,
                    supersample: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """``cv2.remap`` maps (map_x, map_y), each (H*s, W*s) float32: where, in the pinhole render of K_wide,
    each subpixel of the distorted image (s x s per pixel, `pixel_grid`) looks."""
    rays = pixels_to_rays(pixel_grid(*image_size, supersample), K, dist)
    K_wide = np.asarray(K_wide, np.float64)
    map_x = K_wide[0, 0] * rays[..., 0] + K_wide[0, 1] * rays[..., 1] + K_wide[0, 2]
    map_y = K_wide[1, 1] * rays[..., 1] + K_wide[1, 2]
    return map_x.astype(np.float32), map_y.astype(np.float32)


def distort_image(wide: np.ndarray, K: np.ndarray, dist: np.ndarray | None, image_size: tuple[int, int],
                  K_wide: np.ndarray, supersample: int = 2, maps: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """The (H, W) image the distorted camera (K, dist) sees, from ``wide``, the pinhole render of K_wide
    (uint8 or float32, (H', W') or (H', W', C)). Each output pixel is the mean of s x s bilinear samples
    (s = ``supersample``): the pixel's area, so minified edges of a barrel lens do not alias.
    ``maps``: `distortion_maps` computed once for many frames of one camera."""
    map_x, map_y = maps if maps is not None else distortion_maps(K, dist, image_size, K_wide, supersample)
    fine = cv2.remap(wide, map_x, map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    if supersample == 1:
        return fine
    return cv2.resize(fine, tuple(image_size), interpolation=cv2.INTER_AREA)


def distortion_displacement(K: np.ndarray, dist: np.ndarray | None, pixels: np.ndarray) -> np.ndarray:
    """(N, 2) how far the distortion moves each of the (N, 2) distorted ``pixels``: the pixel minus where the
    pinhole camera K would put its ray. The distortion field that calibration reports draw."""
    rays = pixels_to_rays(pixels, K, dist)
    K = np.asarray(K, np.float64)
    pinhole = np.stack([K[0, 0] * rays[:, 0] + K[0, 1] * rays[:, 1] + K[0, 2], K[1, 1] * rays[:, 1] + K[1, 2]], axis=1)
    return np.asarray(pixels, np.float64) - pinhole


def monotonic_k2(k1: float) -> float:
    """A k2 that keeps r (1 + k1 r^2 + k2 r^4) monotonic for every r (derivative 1 + 3 k1 r^2 + 5 k2 r^4 > 0
    needs 9 k1^2 < 20 k2 when k1 < 0): k1^2, as real barrel lenses pair a negative k1 with a positive k2."""
    return float(k1 * k1)


# Training-frame lenses (datagen.render --distortion-probability): k1 from a webcam's strong barrel
# (the real sets' 1280x720 webcams calibrate at k1 = -0.33) to a mild pincushion.
K1_RANGE = (-0.4, 0.1)


def sample_distortion(rng: np.random.Generator, probability: float,
                      k1_range: tuple[float, float] = K1_RANGE) -> np.ndarray | None:
    """With ``probability``, OpenCV's (5,) k1 k2 p1 p2 k3 of a random lens: k1 uniform in ``k1_range``,
    k2 = `monotonic_k2` (k1^2: one to one at every radius, as real lenses pair them), no tangential or k3
    term; else None (a pinhole frame). Draws the same two numbers either way."""
    chance, k1 = rng.random(), float(rng.uniform(*k1_range))
    if chance >= probability:
        return None
    return np.array([k1, monotonic_k2(k1), 0.0, 0.0, 0.0])
