"""Robot-to-image calibration (M-L paper section 4.1): the 3x4 projection P from end-effector
positions and their image positions, and the end-effector image position h(x) = pi(P g(x))
(eq. 3).

P is estimated by the normalised direct linear transform (Hartley & Zisserman, Alg. 7.1:
points translated to zero mean and scaled to mean distance sqrt(3) in 3-D and sqrt(2) in 2-D,
SVD null vector of the 2n x 12 system, denormalised) and refined by Gauss-Newton on the
reprojection error in pixels (fixed iteration count; ||P||_F = 1 is re-imposed after each
step since P is defined up to scale).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from jaxcr.motion.arm import ArmModel, end_effector


def project_homogeneous(
    P: Float[Array, "3 4"], X: Float[Array, "n 3"]
) -> tuple[Float[Array, "n 2"], Bool[Array, " n"]]:
    """pi(P X): pixel positions of robot-frame points and whether they lie in front (w > 0).
    Points at w <= 0 get finite (unused) positions via a double where."""
    Xh = jnp.concatenate([X, jnp.ones(X.shape[:-1] + (1,), X.dtype)], axis=-1)
    x = Xh @ P.T
    w = x[..., 2]
    front = w > 1e-9
    w_safe = jnp.where(front, w, 1.0)
    return x[..., :2] / w_safe[..., None], front


def end_effector_image(
    P: Float[Array, "3 4"], arm: ArmModel, x: Float[Array, "5"]
) -> tuple[Float[Array, "2"], Bool[Array, ""]]:
    """h(x) = pi(P g(x)) (M-L eq. 3): the end-effector pixel position and 'in front'."""
    uv, front = project_homogeneous(P, end_effector(arm, x)[None])
    return uv[0], front[0]


def _normaliser(pts: Float[Array, "n d"]) -> Float[Array, "d+1 d+1"]:
    d = pts.shape[1]
    c = jnp.mean(pts, axis=0)
    dist = jnp.mean(jnp.linalg.norm(pts - c, axis=1))
    s = jnp.sqrt(float(d)) / jnp.maximum(dist, 1e-12)
    T = jnp.eye(d + 1, dtype=pts.dtype) * s
    T = T.at[:d, d].set(-s * c).at[d, d].set(1.0)
    return T


def projection_dlt(X: Float[Array, "n 3"], uv: Float[Array, "n 2"]) -> Float[Array, "3 4"]:
    """Normalised DLT estimate of P (n >= 6 points in general position), ||P||_F = 1, sign
    chosen so that the points are in front (mean w > 0)."""
    T3, T2 = _normaliser(X), _normaliser(uv)
    Xn = (jnp.concatenate([X, jnp.ones((X.shape[0], 1), X.dtype)], 1)) @ T3.T
    un = (jnp.concatenate([uv, jnp.ones((uv.shape[0], 1), uv.dtype)], 1)) @ T2.T
    u, v = un[:, 0:1] / un[:, 2:3], un[:, 1:2] / un[:, 2:3]
    z = jnp.zeros_like(Xn)
    rows1 = jnp.concatenate([Xn, z, -u * Xn], axis=1)
    rows2 = jnp.concatenate([z, Xn, -v * Xn], axis=1)
    A = jnp.concatenate([rows1, rows2], axis=0)
    _, _, vt = jnp.linalg.svd(A, full_matrices=False)
    Pn = vt[-1].reshape(3, 4)
    P = jnp.linalg.inv(T2) @ Pn @ T3
    P = P / jnp.linalg.norm(P)
    Xh = jnp.concatenate([X, jnp.ones((X.shape[0], 1), X.dtype)], 1)
    return P * jnp.sign(jnp.mean(Xh @ P[2]))


def reprojection_residual(
    P: Float[Array, "3 4"], X: Float[Array, "n 3"], uv: Float[Array, "n 2"]
) -> Float[Array, " 2n"]:
    """Pixel residuals pi(P X) - uv, flattened."""
    return (project_homogeneous(P, X)[0] - uv).reshape(-1)


def refine_projection(
    P0: Float[Array, "3 4"], X: Float[Array, "n 3"], uv: Float[Array, "n 2"], n_iter: int = 10
) -> Float[Array, "3 4"]:
    """Gauss-Newton refinement of P on the reprojection error (geometric error, pixels), with a
    small Levenberg damping for the scale direction (the Jacobian has a null vector along P)."""

    def step(_, p):
        r = reprojection_residual(p.reshape(3, 4), X, uv)
        J = jax.jacfwd(lambda q: reprojection_residual(q.reshape(3, 4), X, uv))(p)
        H = J.T @ J
        H = H + 1e-9 * jnp.trace(H) * jnp.eye(12, dtype=p.dtype) + jnp.outer(p, p) * jnp.trace(H)
        dp = -jnp.linalg.solve(H, J.T @ r)
        q = p + dp
        return q / jnp.linalg.norm(q)

    p = jax.lax.fori_loop(0, n_iter, step, P0.reshape(-1) / jnp.linalg.norm(P0))
    return p.reshape(3, 4)


@jax.jit
def estimate_projection(X: Float[Array, "n 3"], uv: Float[Array, "n 2"]) -> Float[Array, "3 4"]:
    """P from robot-frame end-effector positions and their pixels: DLT then refinement."""
    return refine_projection(projection_dlt(X, uv), X, uv)
