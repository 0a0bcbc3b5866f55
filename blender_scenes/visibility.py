"""Which board corners the camera actually sees: ray casts against the built scene."""

from __future__ import annotations

import bpy
import numpy as np
from mathutils import Vector


def unoccluded(points_world: np.ndarray, eye: np.ndarray, tolerance_m: float = 1e-3) -> np.ndarray:
    """(N,) bool: True where nothing lies on the segment from ``eye`` to the world point
    (ending ``tolerance_m`` short of it, so the surface the point lies on does not count)."""
    bpy.context.view_layer.update()
    depsgraph = bpy.context.evaluated_depsgraph_get()
    scene = bpy.context.scene
    origin = Vector(map(float, eye))
    result = np.zeros(len(points_world), dtype=bool)
    for i, point in enumerate(np.asarray(points_world, dtype=np.float64)):
        ray = point - eye
        length = float(np.linalg.norm(ray))
        if length <= tolerance_m:
            continue
        hit, *_ = scene.ray_cast(depsgraph, origin, Vector(map(float, ray / length)), distance=length - tolerance_m)
        result[i] = not hit
    return result
