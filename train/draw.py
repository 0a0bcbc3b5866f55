"""Training frames drawn in torch: boards through random camera poses and lenses onto varied backgrounds, with
exact corner labels (`python -m train.distill`'s frames; no renderer, any device).

A frame (``size`` = (W, H) pixels, pixel centres at integers as everywhere in the project) is drawn at
``supersample`` times the resolution and box-filtered down (a sensor's pixel area):

- the board: its area-exact texture (`BoardSpec.render_texture`) at ``TEXELS_PER_SQUARE`` texels a square and at
  every halving of that (mip levels, each rendered area-exact, so none is aliased or shifted), seen by a pinhole
  camera (focal length, principal point) from a random pose (`deepcharuco.boards.synthetic.look_at_pose`: tilts, roll,
  distance from the square's size in pixels, anywhere in and around the frame), through a radial lens (below),
  sampled by ``grid_sample`` from the level whose texels are about a fine pixel;
- printed with random paper and ink levels under a linear light gradient, on a background: one of
  scikit-image's bundled photographs under a random affine map, or smooth random noise, plus a few random
  grey rectangles (clutter); ``negative_p`` of the frames hold no board;
- then the paper's photometric augmentations (`train.augment`, in numpy: noise, blur, motion blur, speckle,
  darkness, shadows and spotlights);
- ``inverted_p`` of the frames are a board file's ``inverted: true`` print (white squares and markers on black
  paper) as the detector sees it: drawn so, lit and augmented as any frame, then the whole frame inverted (the
  detector's canonical view, `print_face.canonical_view`): the board reads as a normal print in a negative scene,
  and a dark frame becomes a bright, washed-out one;
- with ``bits`` (8), every frame rounded to 2^bits - 1 grey levels as a camera's frame is, before any inversion: in
  the dark a white paper is then a few grey levels (the paper's darkness k = 9 leaves 3 of 255), as the detector
  meets it.

The lens: a drawn pixel p is the ideal (pinhole) pixel ``c + f x (1 + k |x|^2)`` with ``x = (p - c) / f``
(k > 0: barrel, k < 0: pincushion), so the image is sampled without inverting anything; a corner's label is
the pinhole projection moved through the inverse of that radial polynomial (Newton's method, to 1e-9 px).

Every random choice comes from the numpy Generator passed to `FrameDrawer.draw`, so a batch is a pure function
of its seed; torch only computes (the same frames on a CPU and, to float rounding, on a GPU).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from deepcharuco.boards.board import BoardSpec, BoardTexture
from deepcharuco.boards.synthetic import look_at_pose, texture_homography
from train.augment import AugmentConfig, augment

TEXELS_PER_SQUARE = 64  # the finest mip level; boards are drawn with squares of at most ~ 60 fine pixels
LEVELS = 6  # 64, 32, ..., 2 texels a square
PHOTO_SIZE = 256  # backgrounds are resampled to this square size once
# scikit-image's bundled photographs (no download): scenes, materials, text, microscopy. Its checkerboard is left
# out: unlabelled chessboard corners would teach the point head to miss corners.
PHOTOS = ("camera", "astronaut", "coffee", "chelsea", "rocket", "brick", "grass", "gravel", "text", "page", "moon",
          "coins", "horse", "hubble_deep_field", "immunohistochemistry", "cell", "retina", "clock", "colorwheel",
          "shepp_logan_phantom")
CLUTTER = 6  # rectangles at most on a background
COARSE = 8  # fine pixels between the points where the sampling map is computed exactly


@dataclass(frozen=True)
class DrawConfig:
    """What `FrameDrawer.draw` varies, and how much. Pixel sizes are of the drawn (W, H) frame."""

    size: tuple[int, int] = (160, 120)
    supersample: int = 2
    square_px: tuple[float, float] = (6.0, 40.0)  # a square's side near the board's centre (log-uniform), at 160 px wide
    max_tilt_deg: float = 55.0
    focal: tuple[float, float] = (0.8, 1.4)  # focal length in frame widths
    lens_p: float = 0.5  # share of frames through a radial lens
    lens_k: tuple[float, float] = (-0.12, 0.25)
    negative_p: float = 0.1  # share of frames without a board
    photo_p: float = 0.6  # share of backgrounds that are photographs (the rest smooth noise)
    inverted_p: float = 0.0  # share of frames of an inverted print, inverted whole (module docstring)
    bits: int = 0  # frames rounded to this many bits, as a camera's (0: not rounded)
    augmentation: AugmentConfig = AugmentConfig(homography_p=0.0)  # photometric only: the pose is drawn here


@dataclass
class Frames:
    """A drawn batch. ``image`` (B, 1, H, W) float32 in [0, 1] on the drawer's device; ``corners`` (B, C, 2)
    float64 pixels (NaN where the board is behind the camera or absent); ``visible`` (B, C) bool (inside the
    frame); ``board`` (B,) index into the drawer's boards (-1: no board); ``params``: the geometry of each frame,
    for `FrameDrawer.texture_points`; ``inverted`` (B,) bool: an inverted print, the frame inverted whole."""

    image: torch.Tensor
    corners: np.ndarray
    visible: np.ndarray
    board: np.ndarray
    params: list[dict]
    inverted: np.ndarray | None = None


def load_photos() -> np.ndarray:
    """(P, PHOTO_SIZE, PHOTO_SIZE) float32 grey photographs in [0, 1] (scikit-image's bundled data)."""
    import skimage.data

    photos = []
    for name in PHOTOS:
        image = np.asarray(getattr(skimage.data, name)())
        if image.ndim == 3:
            image = cv2.cvtColor(image[..., :3].astype(np.uint8), cv2.COLOR_RGB2GRAY)
        image = image.astype(np.float32)
        image = (image - image.min()) / max(float(image.max() - image.min()), 1e-6)
        photos.append(cv2.resize(image, (PHOTO_SIZE, PHOTO_SIZE), interpolation=cv2.INTER_AREA))
    return np.stack(photos)


class FrameDrawer:
    """Draws `Frames` of ``boards`` on ``device``; the textures and photographs are made once here."""

    def __init__(self, boards: list[BoardSpec], config: DrawConfig = DrawConfig(), device: str | torch.device = "cpu"):
        self.boards, self.config, self.device = list(boards), config, torch.device(device)
        self.textures: list[list[BoardTexture]] = []
        self.levels: list[list[torch.Tensor]] = []
        for board in self.boards:
            px_per_m = TEXELS_PER_SQUARE / board.square_length
            margin = 0.5 * board.square_length
            textures = [board.render_texture(px_per_m / 2**k, margin) for k in range(LEVELS)]
            self.textures.append(textures)
            # each level with a channel of ones: one grid_sample gives the print and its coverage
            self.levels.append([torch.from_numpy(np.stack([t.image.astype(np.float32) / 255.0,
                                                           np.ones(t.image.shape, np.float32)]))[None].to(self.device)
                                for t in textures])
        self.photos = torch.from_numpy(load_photos())[:, None].to(self.device)

    # ------------------------------------------------------------------ geometry
    def _geometry(self, rng: np.random.Generator, size: tuple[int, int], board_index: int) -> dict:
        """One frame's camera, lens and board pose; ``H``: level-0 texture pixels -> ideal image pixels."""
        config = self.config
        width, height = size
        f = width * rng.uniform(*config.focal)
        c = np.array([(width - 1) / 2 + rng.uniform(-0.04, 0.04) * width,
                      (height - 1) / 2 + rng.uniform(-0.04, 0.04) * height])
        k = rng.uniform(*config.lens_k) if rng.random() < config.lens_p else 0.0
        params = {"f": f, "c": c, "k": k, "board": board_index}
        if board_index < 0:
            return params
        board = self.boards[board_index]
        scale = width / 160.0
        square_px = math.exp(rng.uniform(math.log(config.square_px[0] * scale), math.log(config.square_px[1] * scale)))
        distance = f * board.square_length / square_px
        centre = rng.uniform([-0.2 * width, -0.2 * height], [1.2 * width, 1.2 * height])
        offset = ((centre - c) / f * distance).tolist()
        tilt = rng.uniform(-config.max_tilt_deg, config.max_tilt_deg, 2)
        roll = rng.uniform(-180.0, 180.0)
        rvec, tvec = look_at_pose(board, distance, float(tilt[0]), float(tilt[1]), roll, tuple(offset))
        K = np.array([[f, 0.0, c[0]], [0.0, f, c[1]], [0.0, 0.0, 1.0]])
        params.update(rvec=rvec, tvec=tvec, K=K, H=texture_homography(self.textures[board_index][0], K, rvec, tvec),
                      square_px=square_px)
        return params

    @staticmethod
    def lens(points: np.ndarray | torch.Tensor, params: dict):
        """Drawn pixels (..., 2) -> ideal pinhole pixels (module docstring); numpy or torch."""
        c, f, k = params["c"], params["f"], params["k"]
        if k == 0:
            return points
        if isinstance(points, torch.Tensor):
            c = torch.as_tensor(c, dtype=points.dtype, device=points.device)
        x = (points - c) / f
        r2 = (x**2).sum(-1, keepdims=True) if not isinstance(points, torch.Tensor) else (x**2).sum(-1, keepdim=True)
        return c + f * x * (1 + k * r2)

    @staticmethod
    def unlens(ideal: np.ndarray, params: dict) -> np.ndarray:
        """Ideal pixels (N, 2) -> drawn pixels: `lens` inverted by Newton's method on the radius. NaN where the
        radial map folds over (1 + 3 k r^2 <= 0: no drawn pixel shows that point)."""
        c, f, k = params["c"], params["f"], params["k"]
        x = (np.asarray(ideal, np.float64) - c) / f
        r_ideal = np.linalg.norm(x, axis=-1)
        r = r_ideal.copy()
        for _ in range(50):
            step = (r * (1 + k * r**2) - r_ideal) / (1 + 3 * k * r**2)
            r = r - step
            if np.all(np.abs(step) < 1e-13):
                break
        ratio = np.divide(r, r_ideal, out=np.ones_like(r), where=r_ideal > 0)
        drawn = c + f * x * ratio[:, None]
        bad = (1 + 3 * k * r**2 <= 0) | (r < 0) | ~np.isfinite(r)
        drawn[bad] = np.nan
        return drawn

    def texture_points(self, points: np.ndarray, params: dict) -> np.ndarray:
        """Drawn pixels (N, 2) of a frame -> level-0 texture pixels of its board: the map the image is sampled by."""
        ideal = self.lens(np.asarray(points, np.float64), params)
        uv = np.c_[ideal, np.ones(len(ideal))] @ cv2.invert(params["H"])[1].T
        return uv[:, :2] / uv[:, 2:]

    def labels(self, params: dict, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """(corners (C, 2) drawn pixels by corner ID, visible (C,) inside the frame) of a frame's board."""
        board = self.boards[params["board"]]
        rotation, _ = cv2.Rodrigues(params["rvec"])
        camera = board.object_points() @ rotation.T + params["tvec"]
        ideal = camera @ params["K"].T
        ideal = ideal[:, :2] / ideal[:, 2:]
        drawn = self.unlens(ideal, params)
        drawn[camera[:, 2] <= 0] = np.nan
        width, height = size
        with np.errstate(invalid="ignore"):
            visible = (np.isfinite(drawn).all(axis=1) & (drawn[:, 0] >= -0.5) & (drawn[:, 0] < width - 0.5)
                       & (drawn[:, 1] >= -0.5) & (drawn[:, 1] < height - 0.5))
        return drawn, visible

    # ------------------------------------------------------------------ drawing
    def _fine_pixels(self, size: tuple[int, int]) -> torch.Tensor:
        """(Hs, Ws, 2) float32: the drawn frame's pixel coordinates of every supersampled pixel's centre (float32
        is exact to ~1e-4 px at 1280 px, far below what the labels are checked to)."""
        s = self.config.supersample
        width, height = size
        ys, xs = torch.meshgrid(torch.arange(height * s, dtype=torch.float32, device=self.device),
                                torch.arange(width * s, dtype=torch.float32, device=self.device), indexing="ij")
        return torch.stack([(xs + 0.5) / s - 0.5, (ys + 0.5) / s - 0.5], dim=-1)

    def _board_layers(self, fine: torch.Tensor, params: list[dict]) -> tuple[torch.Tensor, torch.Tensor]:
        """(printed reflectance, paper coverage), each (n, H, W) after the box filter, of the boards of the n
        frames ``params`` (all with a board). The maps are computed for all frames at once; each samples its own
        board's texture at its own mip level."""
        s = self.config.supersample
        tensor = lambda a: torch.as_tensor(np.asarray(a, np.float32), device=self.device)  # noqa: E731
        # The map is computed on a grid of every COARSE-th fine pixel and interpolated: the homogeneous texture
        # coordinates are affine in the ideal pixel, so only the lens's cubic is interpolated (< 1e-3 px off).
        fine_h, fine_w = fine.shape[:2]
        rows = torch.linspace(0, fine_h - 1, (fine_h - 1) // COARSE + 2, device=self.device)
        cols = torch.linspace(0, fine_w - 1, (fine_w - 1) // COARSE + 2, device=self.device)
        rows, cols = torch.meshgrid((rows + 0.5) / s - 0.5, (cols + 0.5) / s - 0.5, indexing="ij")
        coarse = torch.stack([cols, rows], dim=-1)  # evenly spaced frame pixels, from the first fine one to the last
        c = tensor([p["c"] for p in params])[:, None, None]  # (n, 1, 1, 2)
        f = tensor([p["f"] for p in params])[:, None, None, None]
        k = tensor([p["k"] for p in params])[:, None, None, None]
        x = (coarse[None] - c) / f
        ideal = c + f * x * (1 + k * (x**2).sum(-1, keepdim=True))  # `lens`, for every frame at once
        Hinv = tensor([cv2.invert(p["H"])[1] for p in params])  # (n, 3, 3)
        uvw = torch.einsum("nhwj,nij->nihw", ideal, Hinv[:, :, :2]) + Hinv[:, :, 2, None, None]
        uvw = F.interpolate(uvw, size=(fine_h, fine_w), mode="bilinear", align_corners=True).permute(0, 2, 3, 1)
        in_front = uvw[..., 2:] > 0
        uv = uvw[..., :2] / uvw[..., 2:].clamp_min(1e-12)
        # The mip level whose texels are about one fine pixel at each board's centre.
        levels = [int(np.clip(math.floor(math.log2(max(TEXELS_PER_SQUARE / (p["square_px"] * s), 1.0))), 0, LEVELS - 1))
                  for p in params]
        textures = [self.levels[p["board"]][level] for p, level in zip(params, levels)]  # (1, 2, h, w): print, ones
        per_frame = lambda values: tensor(values)[:, None, None]  # noqa: E731
        at = (uv + 0.5) / per_frame([2**level for level in levels])[..., None] - 0.5  # level-k texels: area-exact halvings
        grid = torch.stack([(2 * at[..., 0] + 1) / per_frame([t.shape[-1] for t in textures]) - 1,
                            (2 * at[..., 1] + 1) / per_frame([t.shape[-2] for t in textures]) - 1], dim=-1)
        grid = torch.where(in_front, grid, torch.full_like(grid, -4.0))
        sampled = torch.cat([F.grid_sample(texture, grid[i:i + 1], mode="bilinear", padding_mode="zeros",
                                           align_corners=False) for i, texture in enumerate(textures)])
        printed, coverage = sampled[:, 0], sampled[:, 1]
        pooled = F.avg_pool2d(torch.stack([printed * coverage, coverage], dim=1), s)
        return pooled[:, 0] / pooled[:, 1].clamp_min(1e-6), pooled[:, 1]

    def _backgrounds(self, rng: np.random.Generator, count: int, size: tuple[int, int]) -> torch.Tensor:
        """(count, H, W) backgrounds in [0, 1]: photographs under random affine maps or smooth noise, plus clutter.
        Drawn at the frame's resolution: only the board's edges and corners need the supersampling."""
        fine_w, fine_h = size
        photo = rng.random(count) < self.config.photo_p
        index = rng.integers(len(self.photos), size=count)
        angle = rng.uniform(-math.pi, math.pi, count)
        zoom = np.exp(rng.uniform(math.log(0.3), math.log(1.5), count))
        shift = rng.uniform(-0.6, 0.6, (count, 2))
        flip = np.where(rng.random(count) < 0.5, -1.0, 1.0)
        aspect = fine_h / fine_w
        theta = np.zeros((count, 2, 3))
        theta[:, 0, 0], theta[:, 0, 1] = zoom * np.cos(angle) * flip, -zoom * np.sin(angle) * aspect
        theta[:, 1, 0], theta[:, 1, 1] = zoom * np.sin(angle) * flip, zoom * np.cos(angle) * aspect
        theta[:, :, 2] = shift
        grid = F.affine_grid(torch.as_tensor(theta, dtype=torch.float32, device=self.device), [count, 1, fine_h, fine_w],
                             align_corners=False)
        photos = F.grid_sample(self.photos[torch.as_tensor(index, device=self.device)], grid, mode="bilinear",
                               padding_mode="reflection", align_corners=False)[:, 0]
        coarse = torch.as_tensor(rng.random((count, 1, 6, 8)), dtype=torch.float32, device=self.device)
        fine_noise = torch.as_tensor(rng.random((count, 1, 24, 32)), dtype=torch.float32, device=self.device)
        weight = torch.as_tensor(rng.uniform(0, 0.6, (count, 1, 1)), dtype=torch.float32, device=self.device)
        noise = ((1 - weight) * F.interpolate(coarse, (fine_h, fine_w), mode="bicubic", align_corners=False)[:, 0]
                 + weight * F.interpolate(fine_noise, (fine_h, fine_w), mode="bicubic", align_corners=False)[:, 0])
        is_photo = torch.as_tensor(photo, device=self.device)[:, None, None]
        background = torch.where(is_photo, photos, noise.clamp(0, 1))
        # Clutter: rotated rectangles of random grey with soft edges.
        ys, xs = torch.meshgrid(torch.arange(fine_h, dtype=torch.float32, device=self.device),
                                torch.arange(fine_w, dtype=torch.float32, device=self.device), indexing="ij")
        shown = rng.random((count, CLUTTER)) < 0.4
        centre = rng.uniform(0, 1, (count, CLUTTER, 2)) * (fine_w, fine_h)
        half = np.exp(rng.uniform(math.log(0.03), math.log(0.3), (count, CLUTTER, 2))) * max(fine_w, fine_h)
        turn = rng.uniform(0, math.pi, (count, CLUTTER))
        grey = rng.uniform(0, 1, (count, CLUTTER))
        for j in range(CLUTTER):
            t = lambda a: torch.as_tensor(a, dtype=torch.float32, device=self.device)[:, None, None]  # noqa: E731
            dx, dy = xs - t(centre[:, j, 0]), ys - t(centre[:, j, 1])
            cos, sin = t(np.cos(turn[:, j])), t(np.sin(turn[:, j]))
            u, v = (cos * dx + sin * dy).abs(), (-sin * dx + cos * dy).abs()
            mask = torch.sigmoid(t(half[:, j, 0]) - u) * torch.sigmoid(t(half[:, j, 1]) - v) * t(shown[:, j])
            background = background * (1 - mask) + t(grey[:, j]) * mask
        return background

    def draw(self, rng: np.random.Generator, count: int, size: tuple[int, int] | None = None,
             augment_frames: bool = True) -> Frames:
        """``count`` frames of ``size`` (W, H; default the config's), every choice from ``rng``."""
        size = tuple(size or self.config.size)
        width, height = size
        s = self.config.supersample
        has_board = rng.random(count) >= self.config.negative_p
        boards = np.where(has_board, rng.integers(len(self.boards), size=count), -1)
        params = [self._geometry(rng, size, int(b)) for b in boards]
        background = self._backgrounds(rng, count, size)
        # Drawn only when asked for: frames of runs without inverted prints stay those of their seed.
        inverted = rng.random(count) < self.config.inverted_p if self.config.inverted_p > 0 else np.zeros(count, bool)
        fine = self._fine_pixels(size)
        pixels = F.avg_pool2d(fine.permute(2, 0, 1)[None], s)[0].permute(1, 2, 0)  # the frame's own pixel centres
        num_corners = max(b.num_corners for b in self.boards)
        corners = np.full((count, num_corners, 2), np.nan)
        visible = np.zeros((count, num_corners), bool)
        image = background.clone()
        shown = [i for i, p in enumerate(params) if p["board"] >= 0]
        if shown:
            printed, coverage = self._board_layers(fine, [params[i] for i in shown])
            for j, i in enumerate(shown):
                ink, paper = rng.uniform(0.0, 0.3), rng.uniform(0.55, 1.0)
                gradient = rng.normal(0, 0.4, 2) / max(width, height)
                light = 1 + gradient[0] * (pixels[..., 0] - width / 2) + gradient[1] * (pixels[..., 1] - height / 2)
                shade = 1 - printed[j] if inverted[i] else printed[j]  # an inverted print: white on black paper
                board = (ink + (paper - ink) * shade) * light.clamp(0.3, 1.7)
                image[i] = coverage[j] * board + (1 - coverage[j]) * background[i]
                c, v = self.labels(params[i], size)
                corners[i, :len(c)], visible[i, :len(v)] = c, v
        image = image[:, None].clamp(0, 1)
        if augment_frames:
            host = image.cpu().numpy()
            for i in range(count):
                host[i, 0], _, _ = augment(host[i, 0], corners[i], visible[i], False, rng, self.config.augmentation)
            image = torch.from_numpy(host).to(self.device)
        if self.config.bits:  # a camera's grey levels
            levels = float(2 ** self.config.bits - 1)
            image = torch.round(image * levels) / levels
        if inverted.any():  # the detector's canonical view of an inverted print: the whole frame inverted
            flip = torch.as_tensor(inverted, device=self.device)[:, None, None, None]
            image = torch.where(flip, 1 - image, image)
        return Frames(image.contiguous(), corners, visible, boards, params, inverted)
