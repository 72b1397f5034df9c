"""Pinhole cameras with OpenCV distortion, projection of robot-frame points, and the tube
surface of a centreline (Watson et al. eqs. 3-4 and 7).

Conventions
-----------
* Camera frame is OpenCV's: x right, y down, z forward (optical axis). ``T_cam_robot`` maps a
  robot-frame point (metres) to the camera frame: ``X_cam = R X_robot + t``.
* Pixel coordinates follow OpenCV: the centre of pixel (column 0, row 0) is at ``(u, v) =
  (0, 0)``, so the image covers ``[-0.5, width - 0.5) x [-0.5, height - 0.5)``; ``u`` is the
  column (x), ``v`` the row (y).
* Distortion is OpenCV's 5-parameter model ``(k1, k2, p1, p2, k3)``; with ``x' = X/Z``,
  ``y' = Y/Z``, ``r^2 = x'^2 + y'^2``::

      x'' = x' (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x'y' + p2 (r^2 + 2 x'^2)
      y'' = y' (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y'^2) + 2 p2 x'y'
      u = fx x'' + s y'' + cx,   v = fy y'' + cy

  (the skew ``s = K[0, 1]`` is honoured, as in ``cv2.projectPoints``).

Validity and clamping (no NaN, no wrap-around)
----------------------------------------------
A projected point is ``valid`` when it is in front of the camera (``Z > near``), its radius
lies inside the region where the radial distortion is monotonic (so that a point far
outside the field of view can never fold back into the image, which a negative ``k1``
otherwise causes), and its pixel lies inside the image extent above. Invalid points still
get finite coordinates: depth is clamped to ``near``, the radius used by the distortion
polynomial is clamped to the monotonic limit, and ``(u, v)`` is clamped to the box
``[-width, 2 width] x [-height, 2 height]``. Their values carry no meaning: always use
``valid``.

All functions take one camera and a set of points (no batch axis over cameras); use
``jax.vmap`` over cameras or point sets.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from jaxcr._types import Array, Bool, Float, Mat4, Points
from jaxcr.kinematics.cosserat import Centreline

DEFAULT_NEAR = 1e-4  # metres: points closer to the camera plane than this are invalid

# r^2 grid (normalised image plane) on which the radial distortion's monotonic range is
# found: up to r = 10 (84 degrees off-axis), geometrically spaced.
_R2_GRID = np.concatenate([[0.0], np.geomspace(1e-4, 100.0, 255)])


def _float_dtype():
    return jnp.result_type(float)


class Camera(eqx.Module):
    """A calibrated camera (one view).

    Parameters
    ----------
    K : float array (3, 3)
        (3, 3) intrinsic matrix ``[[fx, s, cx], [0, fy, cy], [0, 0, 1]]`` in pixels.
    dist : float array (5,)
        (5,) OpenCV distortion ``(k1, k2, p1, p2, k3)`` (dimensionless).
    T_cam_robot : float array (4, 4)
        (4, 4) rigid transform mapping robot-frame points (metres) to the camera
        frame (OpenCV axes: x right, y down, z forward).
    width, height : int
        image size in pixels (static).

    Examples
    --------
    >>> import jax.numpy as jnp
    >>> import jaxcr as jcr
    >>> K = jnp.array([[100.0, 0.0, 79.5], [0.0, 100.0, 59.5], [0.0, 0.0, 1.0]])
    >>> T = jnp.eye(4).at[2, 3].set(0.5)  # the robot frame 0.5 m in front of the camera
    >>> cam = jcr.Camera(K=K, dist=jnp.zeros(5), T_cam_robot=T, width=160, height=120)
    >>> cam.width, cam.height
    (160, 120)
    """

    K: Float[Array, "3 3"]
    dist: Float[Array, "5"]
    T_cam_robot: Float[Array, "4 4"]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    @property
    def R(self) -> Float[Array, "3 3"]:
        """Rotation robot frame -> camera frame."""
        return self.T_cam_robot[:3, :3]

    @property
    def t(self) -> Float[Array, "3"]:
        """Translation of the robot->camera transform (metres)."""
        return self.T_cam_robot[:3, 3]

    @property
    def centre(self) -> Float[Array, "3"]:
        """Optical centre in the robot frame (metres)."""
        return -self.R.T @ self.t

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return (self.width, self.height)

    @classmethod
    def look_at(
        cls,
        eye,
        target,
        up,
        fx: float,
        size: tuple[int, int],
        fy: float | None = None,
        cx: float | None = None,
        cy: float | None = None,
        dist=None,
    ) -> Camera:
        """Camera at ``eye`` (robot frame, metres) looking at ``target``, with ``up`` (robot
        frame) appearing upwards in the image (i.e. image rows run along ``-up``).

        ``fx``/``fy`` in pixels (``fy`` defaults to ``fx``); principal point defaults to the
        image centre ``((w - 1) / 2, (h - 1) / 2)`` (OpenCV pixel-centre convention).
        """
        eye = np.asarray(eye, np.float64)
        target = np.asarray(target, np.float64)
        up = np.asarray(up, np.float64)
        z = target - eye
        nz = np.linalg.norm(z)
        if not nz > 0:
            raise ValueError("look_at: eye and target coincide")
        z = z / nz
        x = np.cross(z, up)
        nx = np.linalg.norm(x)
        if not nx > 1e-9:
            raise ValueError("look_at: 'up' is parallel to the viewing direction")
        x = x / nx
        y = np.cross(z, x)
        R = np.stack([x, y, z])
        T = np.eye(4)
        T[:3, :3] = R
        T[:3, 3] = -R @ eye
        w, h = int(size[0]), int(size[1])
        fy = fx if fy is None else fy
        cx = (w - 1) / 2.0 if cx is None else cx
        cy = (h - 1) / 2.0 if cy is None else cy
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        return camera_from_arrays(K, np.zeros(5) if dist is None else dist, T, w, h)


def camera_from_arrays(K, dist, T_cam_robot, width: int, height: int) -> Camera:
    """Build a :class:`Camera` from array-likes (numpy or lists).

    ``dist`` may have 4, 5 or 8 entries in OpenCV order; 4 means ``k3 = 0``; 8 is accepted only
    if the rational terms ``k4, k5, k6`` are zero (they are not modelled). ``T_cam_robot``
    ``None`` means identity (camera frame == robot frame). Uses the default float dtype
    (float32 unless x64 is enabled).
    """
    dtype = _float_dtype()
    d = np.asarray(dist, np.float64).reshape(-1)
    if d.size == 4:
        d = np.concatenate([d, [0.0]])
    elif d.size == 8:
        if np.any(d[5:] != 0):
            raise ValueError("rational distortion terms k4, k5, k6 are not supported")
        d = d[:5]
    elif d.size != 5:
        raise ValueError(f"distortion must have 4, 5 or 8 entries, got {d.size}")
    T = np.eye(4) if T_cam_robot is None else np.asarray(T_cam_robot, np.float64)
    K = np.asarray(K, np.float64)
    if K.shape != (3, 3) or T.shape != (4, 4):
        raise ValueError(f"K must be 3x3 and T_cam_robot 4x4, got {K.shape} and {T.shape}")
    return Camera(
        K=jnp.asarray(K, dtype),
        dist=jnp.asarray(d, dtype),
        T_cam_robot=jnp.asarray(T, dtype),
        width=int(width),
        height=int(height),
    )


def _radial(dist: Float[Array, "5"], r2):
    k1, k2, k3 = dist[0], dist[1], dist[4]
    return 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))


def monotonic_r2_limit(camera: Camera) -> Float[Array, ""]:
    """Largest ``r^2`` (normalised image plane) up to which the radial distortion
    ``r (1 + k1 r^2 + k2 r^4 + k3 r^6)`` is increasing, searched on a fixed grid up to
    ``r = 10``. Beyond it, projection would fold back towards the centre."""
    dist = camera.dist
    r2 = jnp.asarray(_R2_GRID, dist.dtype)
    k1, k2, k3 = dist[0], dist[1], dist[4]
    deriv = 1.0 + r2 * (3.0 * k1 + r2 * (5.0 * k2 + r2 * 7.0 * k3))
    bad = deriv <= 0.0
    first_bad = jnp.argmax(bad)  # 0 if none (deriv at r=0 is 1 so index 0 is never bad)
    return jnp.where(jnp.any(bad), r2[jnp.maximum(first_bad - 1, 0)], r2[-1])


def _distort(dist, x, y, r2_limit):
    r2 = x * x + y * y
    in_range = r2 <= r2_limit
    # Beyond the monotonic range, scale the point back to the limit radius and keep its
    # direction, so invalid points stay outside the image instead of folding inwards.
    scale = jnp.where(in_range, 1.0, jnp.sqrt(r2_limit / jnp.where(in_range, 1.0, r2)))
    x = x * scale
    y = y * scale
    r2 = x * x + y * y
    p1, p2 = dist[2], dist[3]
    radial = _radial(dist, r2)
    xy = x * y
    xd = x * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * xy
    return xd, yd, in_range


def project_xy(
    camera: Camera, points_robot: Points, near: float = DEFAULT_NEAR
) -> tuple[Float[Array, " n"], Float[Array, " n"], Bool[Array, " n"]]:
    """Project robot-frame points (metres) to pixels; returns ``(u, v, valid)`` as separate
    (n,) arrays (faster on CPU than a trailing (n, 2) axis). See the module docstring for
    the model, the pixel convention and what ``valid`` means."""
    P = points_robot @ camera.R.T + camera.t
    X, Y, Z = P[:, 0], P[:, 1], P[:, 2]
    in_front = Z > near
    Zc = jnp.where(in_front, Z, near)
    xd, yd, in_range = _distort(camera.dist, X / Zc, Y / Zc, monotonic_r2_limit(camera))
    K = camera.K
    u = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
    v = K[1, 1] * yd + K[1, 2]
    w, h = camera.width, camera.height
    inside = (u >= -0.5) & (u < w - 0.5) & (v >= -0.5) & (v < h - 0.5)
    valid = in_front & in_range & inside
    u = jnp.clip(u, -float(w), 2.0 * w)
    v = jnp.clip(v, -float(h), 2.0 * h)
    return u, v, valid


def project_points(
    camera: Camera, points_robot: Points, *, near: float = DEFAULT_NEAR
) -> tuple[Float[Array, "n 2"], Bool[Array, " n"]]:
    """Project robot-frame points (n, 3) to pixels (n, 2) ``(u, v)`` and a validity mask (n,).

    Pinhole + OpenCV radial/tangential distortion (Watson et al. eqs. 3-4); agrees with
    ``cv2.projectPoints``. See the module docstring for conventions and clamping.

    Parameters
    ----------
    camera : Camera
        the view (intrinsics, distortion, robot-to-camera transform, image size).
    points_robot : float array (n, 3)
        points in the robot frame, metres.
    near : float
        points with camera-frame depth ``Z <= near`` (metres) are behind the camera:
        invalid, projected as if at ``near``.

    Returns
    -------
    uv : float array (n, 2)
        pixel coordinates ``(u, v)`` (pixel centres at integers), clamped to a few image
        sizes around the image.
    valid : bool array (n,)
        in front of the camera, inside the distortion model's monotone range and inside
        the image.

    Examples
    --------
    >>> import jax.numpy as jnp
    >>> import jaxcr as jcr
    >>> K = jnp.array([[100.0, 0.0, 79.5], [0.0, 100.0, 59.5], [0.0, 0.0, 1.0]])
    >>> cam = jcr.Camera(K=K, dist=jnp.zeros(5), T_cam_robot=jnp.eye(4).at[2, 3].set(0.5),
    ...                  width=160, height=120)
    >>> uv, valid = jcr.project_points(cam, jnp.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0]]))
    >>> import numpy as np
    >>> np.asarray(uv, np.float64).round(3).tolist(), valid.tolist()  # u = fx X / Z + cx
    ([[79.5, 59.5], [89.5, 59.5]], [True, True])
    """
    u, v, valid = project_xy(camera, points_robot, near)
    return jnp.stack([u, v], axis=-1), valid


def undistort_normalized(
    camera: Camera, uv: Float[Array, "n 2"], iterations: int = 20
) -> Float[Array, "n 2"]:
    """Undistorted normalised image coordinates ``(x', y') = (X/Z, Y/Z)`` of pixels ``uv``.

    Inverts the distortion by the fixed-point iteration OpenCV's ``undistortPoints`` uses,
    with a fixed number of iterations (exact for zero distortion; converges for the
    moderate distortion of real lenses inside the image).
    """
    K = camera.K
    yd = (uv[:, 1] - K[1, 2]) / K[1, 1]
    xd = (uv[:, 0] - K[0, 2] - K[0, 1] * yd) / K[0, 0]
    k = camera.dist
    p1, p2 = k[2], k[3]

    def body(_, xy):
        x, y = xy
        r2 = x * x + y * y
        icdist = 1.0 / _radial(k, r2)
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        return ((xd - dx) * icdist, (yd - dy) * icdist)

    x, y = jax.lax.fori_loop(0, iterations, body, (xd, yd))
    return jnp.stack([x, y], axis=-1)


def pixel_rays(
    camera: Camera, uv: Float[Array, "n 2"], iterations: int = 20
) -> tuple[Float[Array, "3"], Float[Array, "n 3"]]:
    """Viewing rays of pixels ``uv`` in the robot frame: ``(origin (3,), unit directions
    (n, 3))``. The origin is the optical centre; distortion is removed first."""
    xy = undistort_normalized(camera, uv, iterations)
    d_cam = jnp.concatenate([xy, jnp.ones_like(xy[:, :1])], axis=-1)
    d_cam = d_cam / jnp.linalg.norm(d_cam, axis=-1, keepdims=True)
    return camera.centre, d_cam @ camera.R  # R^T d for each row


def unproject(
    camera: Camera, uv: Float[Array, "n 2"], depth: Float[Array, " n"], iterations: int = 20
) -> Points:
    """Robot-frame points (metres) seen at pixels ``uv`` with camera-frame depth ``Z = depth``
    (inverse of :func:`project_points` for valid points)."""
    xy = undistort_normalized(camera, uv, iterations)
    P_cam = jnp.concatenate([xy * depth[:, None], depth[:, None]], axis=-1)
    return (P_cam - camera.t) @ camera.R  # R^T (P - t) for each row


def transform_camera(camera: Camera, T_robot_new: Mat4) -> Camera:
    """The same camera expressed for points given in a new frame: ``T_cam_new =
    T_cam_robot @ T_robot_new``."""
    return eqx.tree_at(lambda c: c.T_cam_robot, camera, camera.T_cam_robot @ T_robot_new)


def surface_points(centreline: Centreline, n_phi: int) -> Float[Array, "n n_phi 3"]:
    """Points on the tube surface, Watson et al. eq. 7:

        S(s, phi) = p(s) + R(s) Rz(phi) [rho(s), 0, 0]^T
                  = p(s) + rho(s) (cos(phi) R(s) e1 + sin(phi) R(s) e2),

    at ``phi = 2 pi k / n_phi``, ``k = 0..n_phi-1``. Robot frame, metres. Shape (N, n_phi, 3).
    """
    dtype = centreline.p.dtype
    phi = jnp.arange(n_phi, dtype=dtype) * (2.0 * jnp.pi / n_phi)
    e1 = centreline.R[:, :, 0]  # (N, 3)
    e2 = centreline.R[:, :, 1]
    ring = (
        jnp.cos(phi)[None, :, None] * e1[:, None, :] + jnp.sin(phi)[None, :, None] * e2[:, None, :]
    )
    return centreline.p[:, None, :] + centreline.rho[:, None, None] * ring
