"""One training frame: sample a scene, render it, expose it through the sensor, label it.

Frame ``index`` of a run is a pure function of (seed, index, board, config): its generator is
``np.random.default_rng([seed, index])``, which draws the scene (and from it the Cycles seed)
and then the sensor noise.

Light level. Cycles renders in arbitrary radiance units; light transport is linear, so scaling
the radiance is the same as scaling every light in the scene. Each frame is scaled so that the
board's white paper has the luminance of paper of its albedo under the sampled illuminance,
``L = albedo * lux / pi`` (median over the white pixels the camera sees; a monitor counts as
paper of albedo 0.8). That is the ``lux`` recorded: the illuminance at the board, shadows and
spotlights included in the median. Negatives (no board) are scaled so that their 90th
percentile pixel has that luminance.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from blender_scenes.conversions import board_pose_in_camera
from blender_scenes.textures import board_texture
from datagen.scene import SceneConfig, SceneSpec, sample_scene
from datagen.sensor import REC709_LUMA, auto_gain, capture, sensor_record
from datagen.shards import FrameLabels
from deepcharuco.board import BoardSpec
from deepcharuco.pose import project_corners
from deepcharuco.synthetic import texture_homography

MONITOR_EQUIVALENT_ALBEDO = 0.8


def frame_rng(seed: int, index: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), int(index)])


def white_paper_mask(board: BoardSpec, spec: SceneSpec, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels lying wholly on the board's white paper (eroded by a pixel)."""
    texture = board_texture(board, spec.margin_m)
    white = (texture.image == 255).astype(np.uint8) * 255
    homography = texture_homography(texture, spec.K, rvec, tvec)
    warped = cv2.warpPerspective(white, homography, (spec.width, spec.height), flags=cv2.INTER_AREA,
                                 borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return cv2.erode((warped >= 250).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)


def luminance_scale(luminance: np.ndarray, spec: SceneSpec, white_mask: np.ndarray | None) -> float:
    """Factor taking rendered luminance to cd/m^2 at the spec's lux (see the module docstring)."""
    look = spec.board_look
    albedo = MONITOR_EQUIVALENT_ALBEDO if look.kind == "monitor" else look.white
    target = albedo * spec.lux / math.pi
    if white_mask is not None and white_mask.sum() >= 20:
        reference = float(np.median(luminance[white_mask]))
    else:
        reference = float(np.percentile(luminance, 90))
    return target / max(reference, 1e-12)


def blur_extent_px(board: BoardSpec, spec: SceneSpec) -> float:
    """Longest image path of a board corner over the shutter (px): the shake blur's length."""
    if not spec.shaken:
        return 0.0
    tracks = []
    for pose in spec.trajectory:
        rvec, tvec = board_pose_in_camera(pose, spec.board_matrix)
        tracks.append(project_corners(board, rvec, tvec, spec.K))
    tracks = np.stack(tracks)  # (3, C, 2)
    return float(np.nanmax(np.linalg.norm(np.diff(tracks, axis=0), axis=2).sum(axis=0)))


def make_frame(index: int, seed: int, board: BoardSpec, config: SceneConfig = SceneConfig(), *,
               threads: int = 0, device: str = "cpu") -> FrameLabels:
    """Render, expose and label frame ``index`` of the run with ``seed``."""
    from blender_scenes import render_scene

    rng = frame_rng(seed, index)
    spec = sample_scene(rng, board.size_m, config)
    rendered = render_scene(spec, board, threads=threads, device=device)
    luminance = rendered.radiance @ REC709_LUMA

    rvec, tvec = board_pose_in_camera(spec.camera_matrix, spec.board_matrix)
    corners = project_corners(board, rvec, tvec, spec.K).astype(np.float32)
    in_front = ((board.corner_points() @ cv2.Rodrigues(rvec)[0].T)[:, 2] + tvec[2]) > 1e-6
    corners[~in_front] = np.nan
    inside = (in_front & (corners[:, 0] >= -0.5) & (corners[:, 0] < spec.width - 0.5)
              & (corners[:, 1] >= -0.5) & (corners[:, 1] < spec.height - 0.5))
    if spec.board_present:
        mask = white_paper_mask(board, spec, rvec, tvec)
        visible = inside & rendered.unoccluded
    else:
        mask = None
        corners[:] = np.nan
        visible = np.zeros(board.num_corners, dtype=bool)

    luminance = luminance.astype(np.float64) * luminance_scale(luminance, spec, mask)
    exposure = auto_gain(luminance, spec.exposure_s, config.sensor)
    image, exposure = capture(luminance, rng, config.sensor, exposure)

    meta = {
        "seed": int(seed), "frame": int(index), "render_seed": spec.render_seed, "has_board": spec.board_present,
        "lux": float(spec.lux), "blur_px": blur_extent_px(board, spec), "visible_count": int(visible.sum()),
        "focal_px": float(spec.K[0, 0]), "samples": int(spec.samples),
        **{k: v for k, v in spec.tags.items() if k != "negative"},
        **sensor_record(config.sensor, exposure),
    }
    return FrameLabels(
        image=image, corners=corners, visible=visible, K=spec.K.astype(np.float32),
        rvec=(rvec if spec.board_present else np.zeros(3)).astype(np.float32),
        tvec=(tvec if spec.board_present else np.zeros(3)).astype(np.float32), meta=meta,
    )
