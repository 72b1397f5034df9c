"""The robot's base frame without markers: from a given pose or from the entry pixels.

``stereo.json``'s ``"base"`` gives the base frame in one of three forms (see
:func:`jaxcr.cli.stereo.load_stereo_dataset` for the file syntax):

* ``markers`` (the default): four ArUco markers on the base plate (:mod:`jaxcr.stereo.aruco`);
* ``T_cam_base``: the base frame in camera 1's frame (4x4, metres), fixed for the dataset;
* ``entry_px``: the pixel (u, v) where the robot enters each view. The base origin is that
  point triangulated (:func:`triangulate_entry`); the base z axis is the tube's initial
  direction, estimated per frame from the triangulated backbone near the entry
  (:func:`initial_direction`); x and y follow the convention of :func:`frame_from_direction`.

Pixels follow OpenCV's convention (the centre of pixel (0, 0) is at (0, 0)), in the
distorted image as the camera records it. Numpy float64 at the edge (per dataset / per
frame, no JAX).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from jaxcr.camera import Camera

__all__ = [
    "BaseSpec",
    "relative_pose",
    "triangulate_entry",
    "initial_direction",
    "frame_from_direction",
]


@dataclass
class BaseSpec:
    """How a dataset gives its base frame. ``mode``: ``"markers"``, ``"T_cam_base"`` or
    ``"entry_px"``; ``T_cam1_base`` (4x4, base -> camera 1, metres) for ``"T_cam_base"``;
    ``entry_px`` ((u, v) per camera, in the dataset's camera order) for ``"entry_px"``;
    ``direction_length`` (m): the backbone length near the entry used for the z axis."""

    mode: str = "markers"
    T_cam1_base: np.ndarray | None = None
    entry_px: tuple[tuple[float, float], ...] | None = None
    direction_length: float = 12e-3


def relative_pose(cam1: Camera, cam2: Camera) -> np.ndarray:
    """``T_cam2_cam1`` (4x4 float64): camera 1's frame -> camera 2's frame, from the two
    cameras' extrinsics in their common (calibration) frame."""
    T1 = np.asarray(cam1.T_cam_robot, np.float64)
    T2 = np.asarray(cam2.T_cam_robot, np.float64)
    return T2 @ np.linalg.inv(T1)


def _normalised(cam: Camera, uv) -> np.ndarray:
    return cv2.undistortPoints(
        np.asarray(uv, np.float64).reshape(-1, 1, 2),
        np.asarray(cam.K, np.float64),
        np.asarray(cam.dist, np.float64),
    ).reshape(-1, 2)


def triangulate_entry(
    cam1: Camera, cam2: Camera, uv1, uv2
) -> tuple[np.ndarray, float, tuple[float, float]]:
    """The 3-D point (camera 1's frame, metres) seen at pixel ``uv1`` in view 1 and ``uv2``
    in view 2 (distorted pixels; undistorted with each camera's model, then linear DLT on
    normalised coordinates, Hartley & Zisserman sec. 12.2). Returns ``(X (3,), the larger
    of the two reprojection errors (px), (depth in camera 1, depth in camera 2) (m))``;
    a point behind a camera has a negative depth."""
    P1 = np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = relative_pose(cam1, cam2)[:3]
    x1, x2 = _normalised(cam1, uv1)[0], _normalised(cam2, uv2)[0]
    A = np.stack(
        [x1[0] * P1[2] - P1[0], x1[1] * P1[2] - P1[1], x2[0] * P2[2] - P2[0], x2[1] * P2[2] - P2[1]]
    )
    Xh = np.linalg.svd(A)[2][-1]
    X = Xh[:3] / Xh[3]
    errs, depths = [], []
    for cam, P, uv in ((cam1, P1, uv1), (cam2, P2, uv2)):
        Xc = P[:, :3] @ X + P[:, 3]
        depths.append(float(Xc[2]))
        proj, _ = cv2.projectPoints(
            Xc.reshape(1, 1, 3), np.zeros(3), np.zeros(3),
            np.asarray(cam.K, np.float64), np.asarray(cam.dist, np.float64),
        )  # fmt: skip
        errs.append(float(np.linalg.norm(proj.reshape(2) - np.asarray(uv, np.float64))))
    return X, max(errs), (depths[0], depths[1])


def initial_direction(
    s: np.ndarray, p: np.ndarray, length: float, *, origin: np.ndarray | None = None
) -> np.ndarray | None:
    """Unit tangent (3,) at the start of an ordered backbone ``p`` (n, 3) with arclengths
    ``s`` (n,): the slope of a least-squares quadratic ``p(s)`` over the first ``length``
    metres (a chord over that length would tilt by half the turning angle on a curved
    tube; the quadratic's slope is exact for a circular arc to second order). With
    ``origin`` (3,), the quadratic passes through it at arclength 0 (``s`` then counts
    from the origin; the points start ``|p[0] - origin|`` along, the part hidden at the
    entry assumed straight). ``None`` with fewer than 4 samples there."""
    s = np.asarray(s, np.float64)
    p = np.asarray(p, np.float64)
    if origin is not None:
        s = s - s[0] + np.linalg.norm(p[0] - origin)
        sel = s <= length
        if sel.sum() < 4:
            return None
        ds = s[sel]
        A = np.stack([ds, ds**2], axis=1)
        coef, *_ = np.linalg.lstsq(A, p[sel] - origin, rcond=None)
        t = coef[0]
    else:
        sel = s <= s[0] + length
        if sel.sum() < 4:
            return None
        ds = s[sel] - s[0]
        A = np.stack([np.ones_like(ds), ds, ds**2], axis=1)
        coef, *_ = np.linalg.lstsq(A, p[sel], rcond=None)
        t = coef[1]
    n = np.linalg.norm(t)
    return t / n if n > 1e-12 else None


def frame_from_direction(origin: np.ndarray, z: np.ndarray) -> np.ndarray:
    """``T_cam1_base`` (4x4): origin ``origin`` and z axis ``z`` (camera 1's frame). The
    convention for x and y: x is camera 1's x axis (image right) made perpendicular to z
    (so x points right in view 1), y = z x x; when z is within 18 deg of camera 1's x axis,
    x is camera 1's y axis (image down) made perpendicular to z instead."""
    z = np.asarray(z, np.float64)
    z = z / np.linalg.norm(z)
    e = np.array([1.0, 0.0, 0.0])
    if abs(z @ e) > np.cos(np.radians(18.0)):
        e = np.array([0.0, 1.0, 0.0])
    x = e - (e @ z) * z
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, np.cross(z, x), z], axis=1)
    T[:3, 3] = origin
    return T
