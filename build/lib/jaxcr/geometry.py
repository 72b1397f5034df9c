"""SO(3)/SE(3) helpers: hat/vee, exponential and logarithm maps, rigid transforms, alignment.

All functions are pure JAX, act on a single element (no batch axis; use ``jax.vmap``) and
have NaN-free gradients at the singular points (zero rotation angle), using the
"double where" trick: the unsafe branch is evaluated on a substituted safe argument.
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxcr._types import Array, Float, Mat3, Mat4, Points, Vec3

_SMALL_ANGLE = 1e-4


def hat(w: Vec3) -> Mat3:
    """Skew-symmetric matrix of ``w`` such that ``hat(w) @ v == cross(w, v)``."""
    wx, wy, wz = w[0], w[1], w[2]
    zero = jnp.zeros_like(wx)
    return jnp.stack(
        [
            jnp.stack([zero, -wz, wy]),
            jnp.stack([wz, zero, -wx]),
            jnp.stack([-wy, wx, zero]),
        ]
    )


def vee(W: Mat3) -> Vec3:
    """Inverse of :func:`hat` (uses the antisymmetric part of ``W``)."""
    return 0.5 * jnp.stack([W[2, 1] - W[1, 2], W[0, 2] - W[2, 0], W[1, 0] - W[0, 1]])


def _safe_angle(w: Vec3) -> tuple[Array, Array, Array]:
    theta2 = jnp.dot(w, w)
    small = theta2 < _SMALL_ANGLE**2
    safe_theta2 = jnp.where(small, 1.0, theta2)
    safe_theta = jnp.sqrt(safe_theta2)
    return small, safe_theta, theta2


def _one_minus_cos_over_t2(small, t, theta2):
    """(1 - cos t) / t^2, written as (sin(t/2) / (t/2))^2 / 2: no cancellation in float32."""
    half = 0.5 * t
    sinc_half = jnp.sin(half) / half
    return jnp.where(small, 0.5 - theta2 / 24.0 + theta2**2 / 720.0, 0.5 * sinc_half * sinc_half)


def so3_exp(w: Vec3) -> Mat3:
    """Rotation matrix exp(hat(w)) (Rodrigues), NaN-free gradient at ``w = 0``."""
    small, t, theta2 = _safe_angle(w)
    a = jnp.where(small, 1.0 - theta2 / 6.0 + theta2**2 / 120.0, jnp.sin(t) / t)
    b = _one_minus_cos_over_t2(small, t, theta2)
    W = hat(w)
    return jnp.eye(3, dtype=w.dtype) + a * W + b * (W @ W)


# (t - sin t) / t^3 cancels badly in float32 for small t (t - sin t ~ t^3 / 6): below this
# angle use its Taylor series, whose first omitted term t^10 / 13! is < 1e-12 here.
_SERIES_ANGLE = 0.5


def so3_left_jacobian(w: Vec3) -> Mat3:
    """Left Jacobian of SO(3): ``integral_0^1 exp(t hat(w)) dt``.

    For a rod with constant body curvature ``u`` over a step ``h`` the position increment is
    ``R0 @ so3_left_jacobian(h u) @ (h e3)``, exact for piecewise-constant curvature.
    """
    small, t, theta2 = _safe_angle(w)
    b = _one_minus_cos_over_t2(small, t, theta2)
    series = theta2 < _SERIES_ANGLE**2
    t_c = jnp.where(series, 1.0, t)
    c_series = (
        1.0 / 6.0
        - theta2 / 120.0
        + theta2**2 / 5040.0
        - theta2**3 / 362880.0
        + theta2**4 / 39916800.0
    )
    c = jnp.where(series, c_series, (t_c - jnp.sin(t_c)) / (t_c**3))
    W = hat(w)
    return jnp.eye(3, dtype=w.dtype) + b * W + c * (W @ W)


def so3_log(R: Mat3) -> Vec3:
    """Rotation vector ``w`` with ``so3_exp(w) == R`` (angle in [0, pi]).

    NaN-free gradient at the identity. Near ``pi`` it falls back to the symmetric part.
    """
    cos_t = jnp.clip(0.5 * (jnp.trace(R) - 1.0), -1.0, 1.0)
    v = vee(R)  # = sin(t) * axis
    # |v| with a finite gradient where v = 0 (identity, exactly pi). Earlier this zeroed sin_t
    # whenever |cos| > 0.999999, which snapped every angle within 1.4e-3 rad of pi to pi.
    n2 = jnp.dot(v, v)
    zero_v = n2 < 1e-30
    sin_t = jnp.where(zero_v, 0.0, jnp.sqrt(jnp.where(zero_v, 1.0, n2)))
    theta = jnp.arctan2(sin_t, cos_t)
    small = theta < _SMALL_ANGLE
    near_pi = cos_t < -0.99
    # General case.
    safe_sin = jnp.where(small | near_pi, 1.0, sin_t)
    w_general = theta / safe_sin * v
    # Small angle: theta/sin(theta) ~ 1 + theta^2/6.
    w_small = (1.0 + theta**2 / 6.0) * v
    # Near pi: axis from the largest column of (R + I) / 2 = a a^T (1 - cos) / 2 + cos I ...
    # Double where: evaluate this branch on a safe rotation (pi about x) unless near pi.
    R_pi = jnp.where(near_pi, R, jnp.diag(jnp.array([1.0, -1.0, -1.0], R.dtype)))
    cos_pi = jnp.where(near_pi, cos_t, -1.0)
    B = 0.5 * (R_pi + R_pi.T) - cos_pi * jnp.eye(3, dtype=R.dtype)
    i = jnp.argmax(jnp.diag(B))
    col = B[:, i]
    axis = col / jnp.sqrt(jnp.maximum(B[i, i], 1e-12))
    axis = axis / jnp.linalg.norm(axis)
    axis = jnp.where(jnp.dot(axis, v) < 0.0, -axis, axis)
    w_pi = theta * axis
    return jnp.where(small, w_small, jnp.where(near_pi, w_pi, w_general))


def rot_x(a: Float[Array, ""]) -> Mat3:
    """Rotation by angle ``a`` (rad) about x."""
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack([jnp.stack([o, z, z]), jnp.stack([z, c, -s]), jnp.stack([z, s, c])])


def rot_y(a: Float[Array, ""]) -> Mat3:
    """Rotation by angle ``a`` (rad) about y."""
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack([jnp.stack([c, z, s]), jnp.stack([z, o, z]), jnp.stack([-s, z, c])])


def rot_z(a: Float[Array, ""]) -> Mat3:
    """Rotation by angle ``a`` (rad) about z."""
    c, s = jnp.cos(a), jnp.sin(a)
    o, z = jnp.ones_like(a), jnp.zeros_like(a)
    return jnp.stack([jnp.stack([c, -s, z]), jnp.stack([s, c, z]), jnp.stack([z, z, o])])


def orthonormalize(R: Mat3) -> Mat3:
    """Nearest rotation to ``R`` via one Gram-Schmidt pass on its columns (cheap, smooth)."""
    x = R[:, 0] / jnp.linalg.norm(R[:, 0])
    y = R[:, 1] - jnp.dot(x, R[:, 1]) * x
    y = y / jnp.linalg.norm(y)
    z = jnp.cross(x, y)
    return jnp.stack([x, y, z], axis=1)


def make_transform(R: Mat3, t: Vec3) -> Mat4:
    """4x4 homogeneous transform from rotation ``R`` and translation ``t``."""
    T = jnp.eye(4, dtype=R.dtype)
    return T.at[:3, :3].set(R).at[:3, 3].set(t)


def invert_transform(T: Mat4) -> Mat4:
    """Inverse of a rigid 4x4 transform (uses the rotation transpose)."""
    R, t = T[:3, :3], T[:3, 3]
    return make_transform(R.T, -R.T @ t)


def transform_points(T: Mat4, points: Points) -> Points:
    """Apply the rigid transform ``T`` (4x4) to ``points`` (n, 3)."""
    return points @ T[:3, :3].T + T[:3, 3]


def se3_exp(xi: Float[Array, "6"]) -> Mat4:
    """SE(3) exponential of the twist ``xi = (rho, w)`` (translation part first)."""
    rho, w = xi[:3], xi[3:]
    return make_transform(so3_exp(w), so3_left_jacobian(w) @ rho)


def umeyama(
    source: Points,
    target: Points,
    weights: Float[Array, " n"] | None = None,
    with_scale: bool = False,
) -> tuple[Mat3, Vec3, Float[Array, ""]]:
    """Weighted least-squares similarity (or rigid) alignment ``target ~ c R source + t``.

    Kabsch when ``with_scale`` is False (c = 1), Umeyama (1991) otherwise. Returns (R, t, c);
    ``R`` is a proper rotation (det +1).
    """
    n = source.shape[0]
    w = jnp.ones(n, source.dtype) if weights is None else weights
    w = w / jnp.sum(w)
    mu_s = w @ source
    mu_t = w @ target
    xs = source - mu_s
    xt = target - mu_t
    cov = (xt * w[:, None]).T @ xs
    U, S, Vt = jnp.linalg.svd(cov)
    d = jnp.sign(jnp.linalg.det(U) * jnp.linalg.det(Vt))
    d = jnp.where(d == 0, 1.0, d)
    D = jnp.diag(jnp.array([1.0, 1.0, 1.0], source.dtype).at[2].set(d))
    R = U @ D @ Vt
    var_s = jnp.sum(w * jnp.sum(xs * xs, axis=1))
    c = jnp.where(with_scale, jnp.trace(jnp.diag(S) @ D) / var_s, 1.0)
    t = mu_t - c * R @ mu_s
    return R, t, c


def kabsch(source: Points, target: Points, weights: Float[Array, " n"] | None = None) -> Mat4:
    """Rigid transform (4x4) minimising sum w |T source - target|^2 (Kabsch/SVD)."""
    R, t, _ = umeyama(source, target, weights, with_scale=False)
    return make_transform(R, t)
