"""Low-dimensional curvature perturbation delta-u(s) (the unknown of Watson et al. eq. 5).

Watson et al. refine the robot shape by a curvature change u'(s) = u(s) + delta-u(s), with u(s)
= f(q) from the kinematic model, re-integrated from the same base pose with eq. 1. Here
delta-u lives in a Chebyshev basis over normalised arclength x = 2 s / L - 1 in [-1, 1]:

    delta-u_a(s) = (1 / L) * sum_k c[a, k] T_k(x(s)),     a in {x, y} (bending) [, z (torsion)]

The coefficients ``c`` are dimensionless (a coefficient of 1 on T_0 bends the whole robot by
about one radian), which keeps the solver well scaled for robots of any length. Chebyshev
polynomials are orthogonal, bounded by 1 on [-1, 1], and T_0 is a constant offset, so
``n_coeffs = 1`` is a constant-curvature correction.
"""

from __future__ import annotations

import jax.numpy as jnp

from jaxcr._types import Array, Float
from jaxcr.kinematics.cosserat import Centreline, integrate_steps_doubling


def n_axes(torsion: bool) -> int:
    """Number of perturbed curvature axes: 2 (bending x, y) or 3 (with torsion z)."""
    return 3 if torsion else 2


def chebyshev_matrix(x: Float[Array, " m"], n_coeffs: int) -> Float[Array, "m k"]:
    """Chebyshev polynomials of the first kind T_0..T_{n-1} at ``x`` (clipped to [-1, 1])."""
    x = jnp.clip(x, -1.0, 1.0)
    cols = [jnp.ones_like(x)]
    if n_coeffs > 1:
        cols.append(x)
    for _ in range(2, n_coeffs):
        cols.append(2.0 * x * cols[-1] - cols[-2])
    return jnp.stack(cols[:n_coeffs], axis=-1)


def step_midpoints(s: Float[Array, " n"]) -> Float[Array, " n-1"]:
    """Arclength (m) of the midpoint of each integration step."""
    return 0.5 * (s[1:] + s[:-1])


def delta_u_steps(
    coeffs: Float[Array, "a k"], s: Float[Array, " n"], torsion: bool = False
) -> Float[Array, "n-1 3"]:
    """Per-step body-frame curvature change delta-u (1/m) at the step midpoints of ``s``.

    Args:
        coeffs: (a, k) dimensionless coefficients, a = 2 (bending about x, y) or 3 (with
            torsion about z), k Chebyshev terms.
        s: (n,) arclength samples of the centreline (m), increasing.
        torsion: whether ``coeffs`` has a third (torsion) row.

    Returns:
        (n-1, 3) curvature change per step; the torsion column is zero unless ``torsion``.
    """
    length = jnp.maximum(s[-1] - s[0], jnp.finfo(s.dtype).tiny)
    mid = step_midpoints(s)
    x = 2.0 * (mid - s[0]) / length - 1.0
    T = chebyshev_matrix(x, coeffs.shape[-1])
    du = (T @ coeffs.T) / length  # (m, a)
    if not torsion:
        du = jnp.concatenate([du[:, :2], jnp.zeros_like(du[:, :1])], axis=1)
    return du


def perturbed_centreline(
    base: Centreline, coeffs: Float[Array, "a k"], torsion: bool = False
) -> Centreline:
    """Watson et al. eq. 1 re-integrated with u + delta-u(coeffs) from the base pose of ``base``.

    As :func:`jaxcr.kinematics.cosserat.perturb_centreline`, integrated by
    :func:`~jaxcr.kinematics.cosserat.integrate_steps_doubling` (equal up to float rounding;
    about half the XLA operations to compile, and the refinement compiles this in every
    differentiated copy of its objective)."""
    u_steps = base.u[1:] + delta_u_steps(coeffs, base.s, torsion)
    p, R = integrate_steps_doubling(u_steps, jnp.diff(base.s), base.p[0], base.R[0])
    u = jnp.concatenate([u_steps[:1], u_steps])
    return Centreline(s=base.s, p=p, R=R, u=u, rho=base.rho)


def regularisation(
    coeffs: Float[Array, "a k"], s: Float[Array, " n"], torsion: bool = False
) -> Float[Array, ""]:
    """Dimensionless E_reg of Watson et al. eq. 5: L * integral_0^L |delta-u|^2 ds.

    Multiplying the integral (units 1/m) by the length L makes it independent of the robot's
    size: it is the mean squared bending change in radians^2 over the whole length.
    """
    du = delta_u_steps(coeffs, s, torsion)
    ds = jnp.diff(s)
    length = s[-1] - s[0]
    return length * jnp.sum(jnp.sum(du * du, axis=-1) * ds)
