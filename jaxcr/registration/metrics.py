"""Model and pose quality: the paper's Fig. 13 statistics (mean distance to the K nearest
neighbours, number of neighbours within a radius) and pose errors against ground truth."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree


def knn_mean_distance(points: np.ndarray, k: int = 100, idx=None) -> np.ndarray:
    """Per point: mean distance (m) to its ``k`` nearest other points (paper Fig. 13a);
    with ``idx`` only for ``points[idx]`` (their neighbours still come from all points)."""
    k = min(k, len(points) - 1)
    q = points if idx is None else points[idx]
    d, _ = cKDTree(points).query(q, k + 1)
    return d[:, 1:].mean(axis=1)


def neighbour_counts(points: np.ndarray, radius: float = 0.003, idx=None) -> np.ndarray:
    """Per point: number of other points within ``radius`` (m) (paper Fig. 13b); with
    ``idx`` only for ``points[idx]``."""
    tree = cKDTree(points)
    q = points if idx is None else points[idx]
    return np.asarray(tree.query_ball_point(q, radius, return_length=True)) - 1


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(rotation error in degrees, translation error in metres) of ``T_est`` vs ``T_true``."""
    E = np.linalg.inv(T_true) @ T_est
    c = np.clip((np.trace(E[:3, :3]) - 1) / 2, -1, 1)
    return float(np.degrees(np.arccos(c))), float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3]))
