"""Two calibrated views of a tube's tip (issue 16 item 2): the epipolar consistency of the two
tip pixels, and the end face's foreshortening in each view from the tube's 3-D direction.

A tube ends in a flat disc of radius ``r`` whose normal is the tube's axis ``u``. Seen along
the viewing ray ``v`` (orthographic approximation at the tip), the disc is an ellipse of
semi-axes ``r`` (across the tube) and ``r |u . v|`` (along it), so the silhouette runs
``a = R |u . v|`` beyond the end point, ``R`` the tube's projected half width. One view
cannot tell ``a`` from a longer tube (:func:`jaxcr.segmentation.foreground.refine_tip_details`
estimates it from the end's shape); two views can: each view's tip pixel and end direction
span a plane through its camera centre that holds the 3-D axis, and the two planes meet in
it (:func:`end_face_lengths`). The tip is then the silhouette's end moved back by ``a``
along the end direction.

Pixels are undistorted (a pinhole image; undistort with the calibration first). Poses are
``T_cam_world`` (4, 4), world any frame shared by both cameras. Pure numpy, no cv2.
"""

from __future__ import annotations

import numpy as np

__all__ = ["fundamental_from_poses", "epipolar_distances", "end_face_lengths"]


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def fundamental_from_poses(K1, T1, K2, T2) -> np.ndarray:
    """``F`` (3, 3) with ``x2^T F x1 = 0`` for pixels of the same point (homogeneous,
    undistorted): ``K2^-T [t]x R K1^-1`` of the relative pose ``X2 = R X1 + t``."""
    T21 = np.asarray(T2, np.float64) @ np.linalg.inv(np.asarray(T1, np.float64))
    E = _skew(T21[:3, 3]) @ T21[:3, :3]
    return np.linalg.inv(K2).T @ E @ np.linalg.inv(K1)


def epipolar_distances(F: np.ndarray, x1, x2) -> tuple[float, float]:
    """(distance (px) of ``x2`` to the epiline ``F x1`` in image 2, distance of ``x1`` to
    ``F^T x2`` in image 1); ``x1``, ``x2`` (u, v) undistorted pixels."""
    h1 = np.r_[np.asarray(x1, np.float64), 1.0]
    h2 = np.r_[np.asarray(x2, np.float64), 1.0]
    l2 = F @ h1
    l1 = F.T @ h2
    return (float(abs(l2 @ h2) / np.hypot(l2[0], l2[1])),
            float(abs(l1 @ h1) / np.hypot(l1[0], l1[1])))  # fmt: skip


def end_face_lengths(
    K1, T1, K2, T2, end1, dir1, end2, dir2, half_width1: float, half_width2: float,
    *, min_sin: float = 0.1,
) -> tuple[float, float, np.ndarray] | None:  # fmt: skip
    """The end face's foreshortened length ``a`` (px) in each view, from the tube's 3-D
    direction.

    ``end_i`` (u, v) a point on the tube's axis near its end in view ``i`` (undistorted
    pixels; the silhouette's end will do), ``dir_i`` the tube's direction there (unit, in
    the image, pointing out of the tip), ``half_width_i`` the tube's projected half width
    (px). The plane through camera ``i``'s centre and the image line ``end_i + s dir_i``
    holds the axis; the axis ``u`` is the intersection of the two planes (world frame), and
    ``a_i = half_width_i |u . v_i|`` with ``v_i`` the unit viewing ray through ``end_i``.
    Returns ``(a1, a2, u)`` or None when the planes are within ``asin(min_sin)`` of each
    other (the axis lies near an epipolar plane: two views do not fix it)."""
    normals, rays = [], []
    for K, T, x, dvec in ((K1, T1, end1, dir1), (K2, T2, end2, dir2)):
        Ki = np.linalg.inv(np.asarray(K, np.float64))
        R = np.asarray(T, np.float64)[:3, :3]
        x = np.asarray(x, np.float64)
        dvec = np.asarray(dvec, np.float64)
        r0 = Ki @ np.r_[x, 1.0]
        r1 = Ki @ np.r_[x + 10.0 * dvec / np.linalg.norm(dvec), 1.0]
        nrm = np.cross(r0, r1)
        normals.append(R.T @ (nrm / np.linalg.norm(nrm)))
        rays.append(R.T @ (r0 / np.linalg.norm(r0)))
    u = np.cross(normals[0], normals[1])
    s = float(np.linalg.norm(u))
    if s < min_sin:
        return None
    u = u / s
    a1 = float(half_width1 * abs(u @ rays[0]))
    a2 = float(half_width2 * abs(u @ rays[1]))
    return a1, a2, u
