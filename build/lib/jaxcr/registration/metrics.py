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


def rotation_angle(R: np.ndarray) -> float:
    """Angle (radians, in [0, pi]) of the rotation matrix ``R`` (3, 3), computed in float64.

    ``atan2(sin, cos)`` with sin = |vee(R - R^T)| / 2 and cos = (tr R - 1) / 2 (the norm of
    the SO(3) log map). ``arccos`` of the trace alone loses every angle below sqrt(2 eps)
    (2.4e-4 rad = 0.014 deg for float32 input, 1.5e-8 rad in float64) because the cosine
    rounds to 1; the skew part keeps full relative precision at small angles."""
    R = np.asarray(R, np.float64)
    v = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return float(np.arctan2(0.5 * np.linalg.norm(v), 0.5 * (np.trace(R) - 1.0)))


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """(rotation error in degrees, translation error in metres) of ``T_est`` vs ``T_true``:
    the angle of R_true^T R_est (:func:`rotation_angle`, exact at tiny angles) and
    |t_est - t_true|. Computed in float64."""
    T_est = np.asarray(T_est, np.float64)
    T_true = np.asarray(T_true, np.float64)
    E = np.linalg.inv(T_true) @ T_est
    return (
        float(np.degrees(rotation_angle(E[:3, :3]))),
        float(np.linalg.norm(T_est[:3, 3] - T_true[:3, 3])),
    )
