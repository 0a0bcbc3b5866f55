"""One training frame: sample a scene, render it, expose it through the sensor, label it.

Frame ``index`` of a run is a pure function of (seed, index, board, config): its generator is
``np.random.default_rng([seed, index])``, which draws the scene (and from it the Cycles seed)
and then the sensor noise. Two more streams of the same frame draw what older runs did not
have, so that their frames stay as they were: ``[seed, index, BOARD_STREAM]`` the frame's
random board (``--family``, `datagen.family`) and ``[seed, index, LENS_STREAM]`` its lens
distortion (`datagen.lens.sample_distortion`).

Lens distortion. A distorted frame (K, dist) is rendered through `datagen.lens.wide_camera`,
the pinhole camera that sees every ray of the distorted image, and resampled into it
(`datagen.lens.distort_image`) before the sensor adds its noise; labels are
``cv2.projectPoints`` with (K, dist) (`datagen.labels`).

Light level. Cycles renders in arbitrary radiance units; light transport is linear, so scaling
the radiance is the same as scaling every light in the scene. Each frame is scaled so that the
board's white paper has the luminance of paper of its albedo under the sampled illuminance,
``L = albedo * lux / pi`` (median over the white pixels the camera sees; a monitor counts as
paper of albedo 0.8). That is the ``lux`` recorded: the illuminance at the board, shadows and
spotlights included in the median. Negatives (no board) are scaled so that their 90th
percentile pixel has that luminance.

The steps are separate functions — `render_labelled` (Cycles + labels), `luminance_scale` (to
cd/m^2 at a lux), `expose` (the sensor) — so that a frame's render can be exposed many times:
`evaluate.paper.sequences` films a static scene under changing light from one render.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from blender_scenes.conversions import board_pose_in_camera
from blender_scenes.textures import board_texture
from datagen.family import FamilySampling, sample_board
from datagen.labels import label_corners, label_markers, no_markers
from datagen.lens import distort_image, distortion_maps, sample_distortion, wide_camera
from datagen.scene import SceneConfig, SceneSpec, fitted_diag_frac, sample_scene
from datagen.sensor import REC709_LUMA, Exposure, SensorParams, auto_gain, capture, sensor_record
from datagen.shards import FrameLabels, MarkerLabels
from deepcharuco.boards.board import BoardSpec
from deepcharuco.boards.synthetic import texture_homography
from deepcharuco.geometry.pose import project_corners

MONITOR_EQUIVALENT_ALBEDO = 0.8
BOARD_STREAM, LENS_STREAM = 1, 2


def frame_rng(seed: int, index: int, stream: int | None = None) -> np.random.Generator:
    """Frame ``index``'s generator (scene, then sensor noise), or one of its other streams
    (``BOARD_STREAM``, ``LENS_STREAM``)."""
    key = [int(seed), int(index)] if stream is None else [int(seed), int(index), int(stream)]
    return np.random.default_rng(key)


def frame_board(seed: int, index: int, families: tuple[str, ...], sampling: FamilySampling = FamilySampling()) -> BoardSpec:
    """The random board of frame ``index`` of a ``--family`` run (its BOARD_STREAM)."""
    return sample_board(frame_rng(seed, index, BOARD_STREAM), families, sampling)


def frame_distortion(seed: int, index: int, probability: float) -> np.ndarray | None:
    """The lens distortion (5,) of frame ``index`` (its LENS_STREAM), or None for a pinhole frame."""
    return sample_distortion(frame_rng(seed, index, LENS_STREAM), probability)


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


@dataclass
class LabelledRender:
    """One Cycles render of a scene and its true labels, before any sensor: several frames can share it
    (a still camera filming a static board under changing light is one render, exposed many times).

    Attributes:
        spec: the scene rendered.
        luminance: (H, W) float32 luminance in the renderer's arbitrary radiance units (Rec.709 luma
            of linear RGB); `luminance_scale` takes it to cd/m^2.
        white_mask: (H, W) bool white-paper pixels (`white_paper_mask`), None without a board.
        corners: (C, 2) float32 true positions at the shutter centre, NaN behind the camera (all NaN
            for negatives).
        visible: (C,) bool, inside the image and not occluded.
        rvec, tvec: (3,) float32 board -> camera at the shutter centre (zeros for negatives).
        markers: the board's marker labels (`datagen.labels.label_markers`).
        dist: (5,) OpenCV distortion the render was resampled through, or None (pinhole).
    """

    spec: SceneSpec
    luminance: np.ndarray
    white_mask: np.ndarray | None
    corners: np.ndarray
    visible: np.ndarray
    rvec: np.ndarray
    tvec: np.ndarray
    markers: MarkerLabels | None = None
    dist: np.ndarray | None = None


def label_scene(board: BoardSpec, spec: SceneSpec, unoccluded: np.ndarray,
                dist: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """True labels of a scene: (corners (C, 2) float32, visible (C,) bool, rvec (3,), tvec (3,) float64).

    ``unoccluded``: (C,) bool from the renderer's ray casts; ``dist``: the lens's distortion (None:
    pinhole). Corners lie on the sheet as rendered (bent or flat), projected with spec.K and ``dist``;
    behind the camera they are NaN. A negative (no board) has all corners NaN, none visible, and
    its board pose is returned unused (callers store zeros)."""
    rvec, tvec = board_pose_in_camera(spec.camera_matrix, spec.board_matrix)
    corners, visible = label_corners(board, spec, rvec, tvec, unoccluded, dist)
    if not spec.board_present:
        corners[:] = np.nan
        visible = np.zeros(board.num_corners, dtype=bool)
    return corners, visible, rvec, tvec


def render_labelled(spec: SceneSpec, board: BoardSpec, *, threads: int = 0, device: str = "cpu",
                    dist: np.ndarray | None = None) -> LabelledRender:
    """Render ``spec`` with Cycles (`blender_scenes.render_scene`) and label it; with ``dist`` (OpenCV's
    k1 k2 p1 p2 k3), through that lens: the render is made by `datagen.lens.wide_camera` and resampled
    to ``spec``'s K and size, which the returned luminance, mask and labels all refer to."""
    from blender_scenes import render_scene

    rendered_spec = spec
    if dist is not None:
        K_wide, (wide_width, wide_height) = wide_camera(spec.K, dist, (spec.width, spec.height))
        rendered_spec = replace(spec, K=K_wide, width=wide_width, height=wide_height)
    rendered = render_scene(rendered_spec, board, threads=threads, device=device)
    luminance = rendered.radiance @ REC709_LUMA
    corners, visible, rvec, tvec = label_scene(board, spec, rendered.unoccluded, dist)
    if spec.board_present:
        markers = label_markers(board, spec, rvec, tvec, rendered.marker_unoccluded, dist)
    else:
        markers = no_markers(board)
    mask = white_paper_mask(board, rendered_spec, rvec, tvec) if spec.board_present else None
    if dist is not None:
        size = (spec.width, spec.height)
        maps = distortion_maps(spec.K, dist, size, rendered_spec.K)
        luminance = distort_image(luminance.astype(np.float32), spec.K, dist, size, rendered_spec.K, maps=maps)
        if mask is not None:  # still pixels wholly on white paper after resampling
            mask = distort_image(mask.astype(np.float32), spec.K, dist, size, rendered_spec.K, maps=maps) >= 0.999
    zeros = np.zeros(3)
    return LabelledRender(spec=spec, luminance=luminance, white_mask=mask, corners=corners, visible=visible,
                          rvec=(rvec if spec.board_present else zeros).astype(np.float32),
                          tvec=(tvec if spec.board_present else zeros).astype(np.float32), markers=markers,
                          dist=None if dist is None else np.asarray(dist, np.float64))


def expose(luminance: np.ndarray, exposure_s: float, rng: np.random.Generator, sensor: SensorParams) -> tuple[np.ndarray, Exposure]:
    """A (H, W) uint8 frame of ``luminance`` (cd/m^2) taken with the exposure time fixed and the gain
    set by auto-exposure (`auto_gain`), with the noise drawn from ``rng``; and the exposure used."""
    exposure = auto_gain(luminance, exposure_s, sensor)
    return capture(luminance, rng, sensor, exposure)


def scene_meta(board: BoardSpec, spec: SceneSpec, visible: np.ndarray, sensor: SensorParams, exposure: Exposure) -> dict:
    """Per-frame meta of a frame of ``spec``: render seed, has_board, lux, blur, view, scene tags, exposure, sensor."""
    return {
        "render_seed": spec.render_seed, "has_board": spec.board_present,
        "lux": float(spec.lux), "blur_px": blur_extent_px(board, spec), "visible_count": int(visible.sum()),
        "focal_px": float(spec.K[0, 0]), "samples": int(spec.samples),
        **{k: v for k, v in spec.tags.items() if k != "negative"},
        **sensor_record(sensor, exposure),
    }


def board_meta(board: BoardSpec) -> dict:
    """Per-frame meta of a random board (the full spec is in the shard's ``boards``): for histograms."""
    return {"dictionary": board.dictionary, "squares_x": board.squares_x, "squares_y": board.squares_y,
            "marker_ratio": round(board.marker_length / board.square_length, 4), "legacy": board.legacy,
            "inverted": board.inverted, "mirrored": board.mirrored, "first_marker_id": board.first_marker_id}


def make_frame(index: int, seed: int, board: BoardSpec | None, config: SceneConfig = SceneConfig(), *,
               threads: int = 0, device: str = "cpu", families: tuple[str, ...] = (),
               sampling: FamilySampling = FamilySampling(), distortion_p: float = 0.0) -> FrameLabels:
    """Render, expose and label frame ``index`` of the run with ``seed``.

    ``board``: the board of every frame; None with ``families``: the frame draws its own (`frame_board`)
    and the scene places it so its squares have ``config.square_frac`` of the image width
    (`fitted_diag_frac`). ``distortion_p``: probability that the frame is taken through a distorting
    lens (`frame_distortion`); the returned FrameLabels then carries ``dist`` (zeros when pinhole)."""
    if board is None:
        board = frame_board(seed, index, families, sampling)
        config = replace(config, board_diag_frac=fitted_diag_frac((board.squares_x, board.squares_y), config))
    rng = frame_rng(seed, index)
    spec = sample_scene(rng, board.size_m, config)
    dist = frame_distortion(seed, index, distortion_p) if distortion_p > 0 else None
    shot = render_labelled(spec, board, threads=threads, device=device, dist=dist)
    luminance = shot.luminance.astype(np.float64) * luminance_scale(shot.luminance, spec, shot.white_mask)
    image, exposure = expose(luminance, spec.exposure_s, rng, config.sensor)
    meta = {"seed": int(seed), "frame": int(index), **scene_meta(board, spec, shot.visible, config.sensor, exposure)}
    if families:
        meta.update(board_meta(board))
    stored_dist = None
    if distortion_p > 0:
        stored_dist = np.zeros(5) if dist is None else dist
        meta["dist_k1"] = float(stored_dist[0])
    return FrameLabels(image=image, corners=shot.corners, visible=shot.visible, K=spec.K.astype(np.float32),
                       rvec=shot.rvec, tvec=shot.tvec, meta=meta, board=board, markers=shot.markers,
                       dist=None if stored_dist is None else stored_dist.astype(np.float32))
