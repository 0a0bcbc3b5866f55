"""The edge of a cast shadow laid across an image near a corner, for both networks' training.

Rendered frames seldom put a shadow's edge on a corner, and where one falls there the networks
that never saw it fail: ChArUcoNet's point head goes silent, RefineNet places the corner pixels
off. A straight edge is what a lamp makes of an object's straight side; its penumbra is the
lamp's size over its distance. Used by `datagen.patches --shadow-edges` (RefineNet's patches) and
`train.augment` (ChArUcoNet's crops, ``--shadow-edges``).
"""

from __future__ import annotations

import numpy as np

SHADOW_EDGE_REACH_PX = 2.0  # the edge passes this close to the corner at most
SHADOW_LEVELS = (0.1, 0.6)  # the shadowed side keeps this share of its light
PENUMBRA_PX = (0.3, 4.0)  # width of the soft edge (a lamp's size over its distance)


def shadow_edge_gain(height: int, width: int, through: np.ndarray, angle: float, penumbra: float, level: float
                     ) -> np.ndarray:
    """(height, width) float64 light gain: ``level`` on one side of the straight line through ``through``
    (x, y in OpenCV's pixel convention) at ``angle`` (radians from the x axis), 1 on the other, through a
    logistic penumbra ``penumbra`` px wide."""
    normal = np.array([-np.sin(angle), np.cos(angle)])
    across = ((np.arange(width, dtype=np.float64)[None, :] - through[0]) * normal[0]
              + (np.arange(height, dtype=np.float64)[:, None] - through[1]) * normal[1])
    lit = 0.5 * (1.0 + np.tanh(across / penumbra))  # 0 in the shadow, 1 in the light
    return level + (1.0 - level) * lit


def random_shadow_edge(image: np.ndarray, corner: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """``image`` (H, W) float32 under a random cast shadow's edge passing within `SHADOW_EDGE_REACH_PX` of
    ``corner`` (x, y): a random angle, darkness in `SHADOW_LEVELS`, penumbra in `PENUMBRA_PX`."""
    angle = rng.uniform(0.0, np.pi)
    through = np.asarray(corner, np.float64) + rng.uniform(-SHADOW_EDGE_REACH_PX, SHADOW_EDGE_REACH_PX, 2)
    penumbra, level = rng.uniform(*PENUMBRA_PX), rng.uniform(*SHADOW_LEVELS)
    gain = shadow_edge_gain(*image.shape, through, angle, penumbra, level)
    return (image * gain).astype(np.float32)
