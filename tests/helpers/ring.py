"""Camera poses on a ring, for the pose-graph tests of tests/registration."""

from __future__ import annotations

import numpy as np


def ring_pose(a: float, radius: float = 0.3) -> np.ndarray:
    """(4, 4) world <- camera pose of a camera at angle ``a`` (rad) on a circle of ``radius``
    (m) in the z = 0 plane, looking at the centre (x along the circle, z inwards)."""
    c = np.array([radius * np.cos(a), radius * np.sin(a), 0.0])
    z = -c / np.linalg.norm(c)
    x = np.array([-np.sin(a), np.cos(a), 0.0])
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], 1)
    T[:3, 3] = c
    return T
