"""How far apart, epipolarly, two right tips can be under a rig's calibration uncertainty
(issue 16 item 2, docs/decisions.md S37).

Two views' tips of the same 3-D point lie on each other's epipolar lines only when the
cameras are known exactly. With a calibration error ``delta`` the pixels the cameras record
are those of the true cameras, and the calibrated fundamental matrix puts each on a line a
distance ``d(delta)`` off. To first order ``d`` is linear in ``delta``: for the tip's point
``X`` (triangulated from the two tips with the calibrated cameras), each calibration
parameter ``p_i`` of either camera moved by its stated standard deviation ``s_i`` moves the
projection of ``X`` and gives a signed distance ``d_i`` in each image; with independent
errors the distance's standard deviation is ``sqrt(sum_i d_i^2)`` (one per image). The tips'
own placement error (``tip_px`` per coordinate and view) adds ``2 tip_px^2`` to its
variance: a tip error across the epipolar line moves the distance one for one. The
tolerance is ``z`` standard deviations of the larger image's distance.

Numpy float64 on one frame, host side, as the rest of the tips' two-view step.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from jaxcr.stereo.tip_consistency import undistort_pixels
from jaxcr.stereo.tip_geometry import fundamental_from_poses

__all__ = [
    "CalibrationUncertainty",
    "REAL_LIKE_CALIBRATION",
    "epipolar_sigma_px",
    "tip_epipolar_tolerance_px",
]


@dataclass(frozen=True)
class CalibrationUncertainty:
    """Standard deviations of one camera's calibration error, each component independent
    (the same for both cameras): ``focal_rel`` of ``fx`` and ``fy`` (relative),
    ``principal_px`` of ``cx`` and ``cy`` (px), ``rotation_rad`` of the pose's rotation
    about each camera axis (rad), ``translation_m`` of its translation along each camera
    axis (m); ``tip_px`` of a tip's placement per image coordinate (px)."""

    focal_rel: float
    principal_px: float
    rotation_rad: float
    translation_m: float
    tip_px: float = 0.5


def _rms_of_limit(limit: float, dims: int) -> float:
    """Per-component standard deviation of a vector of norm ``U(0.5, 1) * limit`` in a
    uniformly random direction of ``dims`` dimensions (E[U^2] = 7/12)."""
    return float(limit * np.sqrt(7.0 / 12.0 / dims))


#: The ``real_like`` preset's stated calibration error (jaxcr/synth/real_like.py: focal
#: lengths 0.15-0.3 %, principal point 0.75-1.5 px, pose 0.04-0.08 deg and 0.2-0.4 mm, each
#: ``U(0.5, 1)`` times its limit in a random direction or sign) as standard deviations; the
#: tips' placement 0.5 px (the pipeline's tips on right views: median error 0.56 px,
#: docs/decisions.md S27).
REAL_LIKE_CALIBRATION = CalibrationUncertainty(
    focal_rel=_rms_of_limit(0.003, 1),
    principal_px=_rms_of_limit(1.5, 2),
    rotation_rad=_rms_of_limit(np.radians(0.08), 3),
    translation_m=_rms_of_limit(4e-4, 3),
)


def _triangulate(P1: np.ndarray, P2: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Linear (DLT) triangulation of undistorted pixels ``x1``, ``x2`` (2,) with projection
    matrices (3, 4); the point (3,)."""
    A = np.stack([x1[0] * P1[2] - P1[0], x1[1] * P1[2] - P1[1],
                  x2[0] * P2[2] - P2[0], x2[1] * P2[2] - P2[1]])  # fmt: skip
    X = np.linalg.svd(A)[2][-1]
    return X[:3] / X[3]


def _project(K: np.ndarray, T: np.ndarray, X: np.ndarray) -> np.ndarray:
    x = K @ (T[:3, :3] @ X + T[:3, 3])
    return x[:2] / x[2]


def _signed(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Signed distances (px) of ``x2`` to ``F x1`` (image 2) and of ``x1`` to ``F^T x2``."""
    h1, h2 = np.r_[x1, 1.0], np.r_[x2, 1.0]
    l2, l1 = F @ h1, F.T @ h2
    return np.array([l2 @ h2 / np.hypot(l2[0], l2[1]), l1 @ h1 / np.hypot(l1[0], l1[1])])


def _perturbations(unc: CalibrationUncertainty):
    """(name, function (K, T) -> (K', T')) per calibration component, each moved by its
    standard deviation."""
    out = []
    for i in range(2):

        def focal(K, T, i=i):
            K = K.copy()
            K[i, i] *= 1.0 + unc.focal_rel
            return K, T

        def principal(K, T, i=i):
            K = K.copy()
            K[i, 2] += unc.principal_px
            return K, T

        out += [focal, principal]
    for a in range(3):

        def rotation(K, T, a=a):
            w = np.zeros(3)
            w[a] = unc.rotation_rad
            c, s = np.cos(unc.rotation_rad), np.sin(unc.rotation_rad)
            Kx = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) / max(
                unc.rotation_rad, 1e-300
            )
            dR = np.eye(3) + s * Kx + (1 - c) * Kx @ Kx
            T = T.copy()
            T[:3, :3] = dR @ T[:3, :3]
            T[:3, 3] = dR @ T[:3, 3]
            return K, T

        def translation(K, T, a=a):
            T = T.copy()
            T[a, 3] += unc.translation_m
            return K, T

        out += [rotation, translation]
    return out


def epipolar_sigma_px(cams, tips, unc: CalibrationUncertainty) -> np.ndarray | None:
    """Standard deviation (px) of each image's epipolar distance of two right tips (image
    2's distance of tip 2 to tip 1's line, image 1's of tip 1 to tip 2's line) under the
    calibration uncertainty ``unc`` (module docstring), tips' placement included; shape
    (2,). ``cams``: the two calibrated cameras (``K``, ``dist``, ``T_cam_robot``);
    ``tips``: the two tips (distorted (u, v)) from which the point is triangulated. None
    when a tip is not finite or the point is not in front of both cameras."""
    if not all(np.all(np.isfinite(np.asarray(t, np.float64))) for t in tips):
        return None
    Ks = [np.asarray(c.K, np.float64) for c in cams]
    Ts = [np.asarray(c.T_cam_robot, np.float64) for c in cams]
    x = [undistort_pixels(c, t)[0] for c, t in zip(cams, tips, strict=True)]
    P = [K @ T[:3] for K, T in zip(Ks, Ts, strict=True)]
    X = _triangulate(P[0], P[1], x[0], x[1])
    if not all((T[:3, :3] @ X + T[:3, 3])[2] > 0 for T in Ts):
        return None
    F = fundamental_from_poses(Ks[0], Ts[0], Ks[1], Ts[1])
    base = [_project(K, T, X) for K, T in zip(Ks, Ts, strict=True)]
    var = np.zeros(2)
    for k in range(2):
        for move in _perturbations(unc):
            K, T = move(Ks[k], Ts[k])
            moved = list(base)
            moved[k] = _project(K, T, X)
            var += _signed(F, moved[0], moved[1]) ** 2
    var += 2.0 * unc.tip_px**2
    return np.sqrt(var)


def tip_epipolar_tolerance_px(
    cams, tips, unc: CalibrationUncertainty, *, z: float = 3.0, floor_px: float = 5.0
) -> float:
    """The epipolar distance (px) above which two tips are not of the same point: ``z``
    standard deviations (:func:`epipolar_sigma_px`) of the larger image's, and at least
    ``floor_px`` (the fixed flag it replaces: a precise calibration does not make the
    tips' two-view step act on smaller gaps); ``floor_px`` when the sigma is undefined."""
    sig = epipolar_sigma_px(cams, tips, unc)
    if sig is None:
        return float(floor_px)
    return float(max(floor_px, z * float(np.max(sig))))
