"""Blender scene building — the only package that imports bpy.

`render_scene(spec, board, threads=..., device=...)` builds the scene a
`datagen.scene.SceneSpec` describes in an empty Blender file, renders it with Cycles and
returns linear radiance plus which board corners are unoccluded. Submodules, one concern each:

- `conversions`: OpenCV K / pose <-> Blender camera (plain numpy, importable without bpy)
- `textures`: board, distractor and poster images (plain numpy)
- `render_setup`: scene reset, Cycles settings, radiance read-back
- `objects`: board, shapes, lamps, HDRI world, camera with its shake trajectory
- `visibility`: ray-cast occlusion of the board's corners

Importing this package does not import bpy; `render_scene` does, on first call.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np


@dataclass
class SceneRender:
    """radiance: (H, W, 3) float32 linear, row 0 at the top; unoccluded: (C,) bool per board corner;
    marker_unoccluded: (M, 5) bool per marker of the board, its four corners then its centre
    (`datagen.labels.marker_points`)."""

    radiance: np.ndarray
    unoccluded: np.ndarray
    marker_unoccluded: np.ndarray | None = None


def render_scene(spec, board, threads: int = 0, device: str = "cpu") -> SceneRender:
    """Build ``spec`` (a `datagen.scene.SceneSpec`) for ``board`` (a `BoardSpec`) and render it.

    ``threads``: Cycles render threads (0: all cores). ``device``: "cpu" or "gpu".
    """
    from blender_scenes import objects, render_setup, visibility
    from blender_scenes.conversions import blender_camera_from_K
    from datagen.labels import marker_points
    from datagen.scene import bent_points

    scene = render_setup.reset()
    params = blender_camera_from_K(spec.K, spec.width, spec.height)
    render_setup.configure_cycles(scene, spec.width, spec.height, (params.pixel_aspect_x, params.pixel_aspect_y),
                                  spec.samples, spec.render_seed, threads or os.cpu_count() or 1, device,
                                  denoise=spec.denoise)
    objects.set_world(spec.world)
    # Fireflies (rare paths finding a small bright source) would read as salt noise at a few
    # samples per pixel. Clamp each sample at a few times the radiance of white paper in this
    # light: brighter pixels saturate the sensor anyway.
    white_paper = objects.white_paper_radiance(spec)
    scene.cycles.sample_clamp_direct = 4.0 * white_paper
    scene.cycles.sample_clamp_indirect = 2.0 * white_paper
    if spec.board_present:
        objects.add_board(board, spec)
    for i, distractor in enumerate(spec.distractors):
        objects.add_distractor(i, distractor)
    for i, shape in enumerate(spec.shapes):
        objects.add_shape(i, shape)
    for i, light in enumerate(spec.lights):
        objects.add_light(i, light)
    objects.add_camera(spec)

    def world(points: np.ndarray) -> np.ndarray:
        """Board-frame points of the flat board -> world points on the (possibly bent) sheet."""
        points = bent_points(points, spec, board.size_m)
        return (spec.board_matrix[:3, :3] @ points.T).T + spec.board_matrix[:3, 3]

    _, markers = marker_points(board)
    if spec.board_present:
        unoccluded = visibility.unoccluded(world(board.object_points()), spec.camera_matrix[:3, 3])
        marker_unoccluded = visibility.unoccluded(world(markers.reshape(-1, 3)), spec.camera_matrix[:3, 3])
    else:
        unoccluded = np.zeros(board.num_corners, dtype=bool)
        marker_unoccluded = np.zeros(markers.shape[0] * 5, dtype=bool)
    radiance = render_setup.render_radiance(scene)
    return SceneRender(radiance=radiance, unoccluded=unoccluded, marker_unoccluded=marker_unoccluded.reshape(-1, 5))

