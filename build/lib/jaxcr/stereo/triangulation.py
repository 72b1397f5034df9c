"""Linear (DLT) triangulation of stereo correspondences and the epipolar geometry of a
calibrated pair.

Hartley & Zisserman (2003) sec. 12.2: for projection matrices ``P1``, ``P2`` and pixels
``x1``, ``x2`` the point ``X`` (homogeneous) is the right singular vector of

    A = [x1 P1[2] - P1[0];  y1 P1[2] - P1[1];  x2 P2[2] - P2[0];  y2 P2[2] - P2[1]]

with the smallest singular value, as ``cv2.triangulatePoints`` computes it. Here the pixels
are first undistorted to normalised coordinates, so ``P = [R | t]`` of each camera (base
frame -> camera frame, metres), which also conditions ``A`` well.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxcr._types import Array, Float, Mat3

__all__ = [
    "triangulate_point",
    "triangulate_points",
    "essential_matrix",
    "fundamental_matrix",
    "sampson_distance",
    "sampson_distance_np",
]


def triangulate_point(
    P1: Float[Array, "3 4"], P2: Float[Array, "3 4"], x1: Float[Array, "2"], x2: Float[Array, "2"]
) -> Float[Array, "3"]:
    """One 3-D point from one correspondence (DLT, see module docstring).

    ``P1``, ``P2`` map homogeneous points of the output frame to homogeneous image points
    of ``x1``/``x2`` (normalised coordinates with ``P = [R | t]``, or pixels with
    ``K [R | t]``)."""
    A = jnp.stack(
        [
            x1[0] * P1[2] - P1[0],
            x1[1] * P1[2] - P1[1],
            x2[0] * P2[2] - P2[0],
            x2[1] * P2[2] - P2[1],
        ]
    )
    _, _, vt = jnp.linalg.svd(A)
    X = vt[-1]
    return X[:3] / X[3]


def triangulate_points(
    P1: Float[Array, "3 4"],
    P2: Float[Array, "3 4"],
    x1: Float[Array, "n 2"],
    x2: Float[Array, "n 2"],
) -> Float[Array, "n 3"]:
    """Triangulate n correspondences (vmap of :func:`triangulate_point`)."""
    return jax.vmap(triangulate_point, in_axes=(None, None, 0, 0))(P1, P2, x1, x2)


def _skew(t):
    return jnp.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]], t.dtype)


def essential_matrix(T_cam1: Float[Array, "4 4"], T_cam2: Float[Array, "4 4"]) -> Mat3:
    """``E = [t]x R`` of the relative pose ``X2 = R X1 + t`` (cameras' ``T_cam_world``), so
    that ``x2n^T E x1n = 0`` for normalised coordinates."""
    T21 = T_cam2 @ jnp.linalg.inv(T_cam1)
    return _skew(T21[:3, 3]) @ T21[:3, :3]


def fundamental_matrix(
    K1: Mat3, K2: Mat3, T_cam1: Float[Array, "4 4"], T_cam2: Float[Array, "4 4"]
) -> Mat3:
    """``F = K2^-T E K1^-1`` (pixels, no distortion), as ``cv2.stereoCalibrate`` reports."""
    E = essential_matrix(T_cam1, T_cam2)
    return jnp.linalg.inv(K2).T @ E @ jnp.linalg.inv(K1)


def sampson_distance(
    E: Mat3, x1: Float[Array, "n 2"], x2: Float[Array, "m 2"]
) -> Float[Array, "n m"]:
    """First-order geometric (Sampson) epipolar distance of every pair ``(x1[i], x2[j])``
    (same units as the coordinates; for normalised coordinates multiply by f for pixels).
    Hartley & Zisserman eq. 11.9, returned as a distance (square root)."""
    h1 = jnp.concatenate([x1, jnp.ones_like(x1[:, :1])], axis=1)
    h2 = jnp.concatenate([x2, jnp.ones_like(x2[:, :1])], axis=1)
    Ex1 = h1 @ E.T  # (n, 3): epilines in image 2
    Etx2 = h2 @ E  # (m, 3): epilines in image 1
    num = Ex1 @ h2.T  # (n, m)
    den = Ex1[:, 0:1] ** 2 + Ex1[:, 1:2] ** 2 + (Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2)[None, :]
    return jnp.abs(num) / jnp.sqrt(den + 1e-30)


def sampson_distance_np(E: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """:func:`sampson_distance` in numpy float64 (for the per-frame driver)."""
    h1 = np.concatenate([x1, np.ones((len(x1), 1))], axis=1)
    h2 = np.concatenate([x2, np.ones((len(x2), 1))], axis=1)
    Ex1 = h1 @ E.T
    Etx2 = h2 @ E
    num = Ex1 @ h2.T
    den = Ex1[:, 0:1] ** 2 + Ex1[:, 1:2] ** 2 + (Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2)[None, :]
    return np.abs(num) / np.sqrt(den + 1e-300)
