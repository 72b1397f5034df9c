"""Plane and circular-arc fits to the 3-D backbone points of one segment.

Plane (stereo report sec. 5.4): total least squares, the normal ``n`` is the right
singular vector of the centred points with the smallest singular value. The angle between
the fitted plane and a coordinate plane is the angle between their normals:
``phi_XY = arccos|n . e_z|``, ``phi_ZX = arccos|n . e_y|``, ``phi_YZ = arccos|n . e_x|``
(degrees in [0, 90]).

Circular arc (beyond the report): the points are projected into the fitted plane, a circle
is fitted algebraically (Kasa: ``x^2 + y^2 + D x + E y + F = 0`` by linear least squares on
centred, scaled coordinates) and refined by Gauss-Newton on the geometric distance
``|p - c| - R``. Curvature ``kappa = 1 / R``; arc length ``R * (angle swept from the first
to the last point)``. Nearly straight segments give tiny curvatures, never NaN.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxcr._types import Array, Float

__all__ = ["fit_plane", "plane_angles", "fit_arc", "ArcFit"]


def _weights(points, weights):
    if weights is None:
        return jnp.ones(points.shape[0], points.dtype)
    return jnp.asarray(weights, points.dtype)


def fit_plane(
    points: Float[Array, "n 3"], weights: Float[Array, " n"] | None = None
) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
    """Total-least-squares plane: ``(centroid (3,), unit normal (3,))``; the normal's sign
    is chosen with a non-negative largest-magnitude component (deterministic). Optional
    ``weights`` (n,) >= 0 (zero weights let callers pad to a fixed shape)."""
    w = _weights(points, weights)
    c = jnp.sum(w[:, None] * points, axis=0) / jnp.sum(w)
    _, _, vt = jnp.linalg.svd(jnp.sqrt(w)[:, None] * (points - c), full_matrices=False)
    n = vt[-1]
    k = jnp.argmax(jnp.abs(n))
    return c, n * jnp.sign(n[k])


def plane_angles(normal: Float[Array, "3"]) -> Float[Array, "3"]:
    """Angles (degrees) of the plane with unit ``normal`` with the X-Y, Z-X and Y-Z planes."""
    n = normal / jnp.linalg.norm(normal)
    cosines = jnp.clip(jnp.abs(jnp.stack([n[2], n[1], n[0]])), 0.0, 1.0)
    return jnp.degrees(jnp.arccos(cosines))


class ArcFit(dict):
    """Result of :func:`fit_arc` (a plain dict of arrays: ``centre`` (3,), ``radius``,
    ``curvature`` (1/m), ``arc_length`` (m), ``normal`` (3,), ``rms`` (m))."""


def _basis(n):
    a = jnp.where(jnp.abs(n[0]) < 0.9, jnp.array([1.0, 0.0, 0.0]), jnp.array([0.0, 1.0, 0.0]))
    u = jnp.cross(n, a.astype(n.dtype))
    u = u / jnp.linalg.norm(u)
    return u, jnp.cross(n, u)


def _hyper_circle(q: Float[Array, "n 2"], w: Float[Array, " n"]) -> Float[Array, "4"]:
    """Al-Sharadqah & Chernov's "hyper" algebraic circle fit: coefficients ``a`` of
    ``a0 (x^2 + y^2) + a1 x + a2 y + a3 = 0`` (lines have ``a0 = 0``), essentially unbiased.
    ``q`` should be centred and scaled to unit RMS radius."""
    z = jnp.sum(q * q, axis=1)
    Z = jnp.sqrt(w)[:, None] * jnp.stack([z, q[:, 0], q[:, 1], jnp.ones_like(z)], axis=1)
    _, S, vt = jnp.linalg.svd(Z, full_matrices=False)
    V = vt.T
    Sg = jnp.maximum(S, 1e-12 * S[0])
    Y = V @ jnp.diag(Sg) @ V.T
    zm = jnp.sum(w * z) / jnp.sum(w)
    Ninv = jnp.array(
        [
            [0.0, 0.0, 0.0, 0.5],
            [0.0, 1.0, 0.0, 0.0],
            [0.0, 0.0, 1.0, 0.0],
            [0.5, 0.0, 0.0, -2.0 * zm],
        ],
        q.dtype,
    )
    _, U = jnp.linalg.eigh(Y @ Ninv @ Y)
    # The hyper fit is the eigenvector of the smallest positive eigenvalue; for nearly
    # straight or exact data that eigenvalue is ~0 and its sign is not reliable in float32
    # (batched and unbatched solvers disagree). So every candidate (the four eigenvectors
    # mapped back, and the null vector of Z) is scored by its first-order geometric
    # residual and the best is kept.
    cands = jnp.concatenate([(V @ ((V.T @ U) / Sg[:, None])).T, V[:, 3][None]], axis=0)

    def geometric_cost(a):
        g = a[0] * z + a[1] * q[:, 0] + a[2] * q[:, 1] + a[3]
        gx = 2 * a[0] * q[:, 0] + a[1]
        gy = 2 * a[0] * q[:, 1] + a[2]
        return jnp.sum(w * g * g / (gx * gx + gy * gy + 1e-30))

    costs = jax.vmap(geometric_cost)(cands)
    return cands[jnp.argmin(jnp.where(jnp.isfinite(costs), costs, jnp.inf))]


@jax.jit
def fit_arc(points: Float[Array, "n 3"], weights: Float[Array, " n"] | None = None) -> dict:
    """Circular arc through ordered 3-D points (n >= 3) of one segment (see module
    docstring). Returns a dict with ``centre`` (may be very far for straight points),
    ``radius``, ``curvature`` (>= 0, 1/m), ``arc_length`` (m), ``normal`` (of the arc's
    plane) and ``rms`` (geometric residual, m). Points with zero ``weights`` are ignored
    (padding); the arc's ends are the first and last points with positive weight."""
    w = _weights(points, weights)
    sw = jnp.sum(w)
    c0, n = fit_plane(points, w)
    u, v = _basis(n)
    rel = points - c0
    xy = jnp.stack([rel @ u, rel @ v], axis=1)
    scale = jnp.sqrt(jnp.sum(w * jnp.sum(xy**2, axis=1)) / sw) + 1e-12
    q = xy / scale
    a = _hyper_circle(q, w)
    disc = jnp.maximum(a[1] ** 2 + a[2] ** 2 - 4 * a[0] * a[3], 1e-30)
    kq = 2 * jnp.abs(a[0]) / jnp.sqrt(disc)  # curvature in scaled units
    # Double where: the centre only where the circle is not (numerically) a line.
    curved = kq > 1e-6
    a0 = jnp.where(curved, a[0], 1.0)
    cq = jnp.where(curved, -a[1:3] / (2 * a0), 0.0)
    Rq = jnp.where(curved, 1.0 / jnp.where(curved, kq, 1.0), jnp.inf)
    # Arc length: swept angle about the centre (any sweep, also > pi); for a line, the
    # extent of the points along it.
    ang = jnp.arctan2(q[:, 1] - cq[1], q[:, 0] - cq[0])
    used = w > 0
    pair = used[1:] & used[:-1]
    dang = (jnp.diff(ang) + jnp.pi) % (2 * jnp.pi) - jnp.pi
    arc_curved = Rq * jnp.abs(jnp.sum(jnp.where(pair, dang, 0.0)))
    line_dir = jnp.array([a[2], -a[1]]) / jnp.sqrt(a[1] ** 2 + a[2] ** 2 + 1e-30)
    first = jnp.argmax(used)
    last = q.shape[0] - 1 - jnp.argmax(used[::-1])
    arc_line = jnp.abs((q[last] - q[first]) @ line_dir)
    arc = jnp.where(curved, jnp.where(curved, arc_curved, 0.0), arc_line)
    dist = jnp.where(
        curved,
        jnp.sqrt(jnp.sum((q - cq) ** 2, axis=1)) - jnp.where(curved, Rq, 0.0),
        (q @ jnp.array([a[1], a[2]]) + a[3]) / jnp.sqrt(a[1] ** 2 + a[2] ** 2 + 1e-30),
    )
    out_of_plane = rel @ n
    rms = jnp.sqrt((jnp.sum(w * dist**2) * scale**2 + jnp.sum(w * out_of_plane**2)) / sw)
    centre = c0 + scale * (cq[0] * u + cq[1] * v)
    return {
        "centre": centre,
        "radius": Rq * scale,
        "curvature": kq / scale,
        "arc_length": arc * scale,
        "normal": n,
        "rms": rms,
    }
