"""Small dense nonlinear solves inside kinematics: damped Newton (Levenberg-Marquardt) with a
bounded iteration count, and an implicit-function step that makes the solution differentiable.

Written for square systems of a handful of unknowns (e.g. CTR shooting): the Jacobian is formed
with forward-mode AD (one pass per unknown) and solved densely. Inside ``jax.vmap`` the loop
runs until the slowest batch member stops, so the iteration bound is the cost bound; it never
raises (see docs/ARCHITECTURE.md and /work/shared/PERFORMANCE-NOTES.md "Batching on CPU").
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp

from jaxcr._types import Array, Float, Int


class NewtonResult(NamedTuple):
    x: Float[Array, " n"]  # best iterate (no gradient flows through it)
    residual: Float[Array, ""]  # ||r(x)||_2
    jac: Float[Array, "n n"]  # dr/dx at x
    num_steps: Int[Array, ""]  # iterations taken until ||r|| <= tol (or the bound)


def _residual_and_jacobian(fun, x):
    jac, r = jax.jacfwd(lambda z: (fun(z), fun(z)), has_aux=True)(x)
    return r, jac


def damped_newton(
    fun: Callable[[Array], Array],
    x0: Float[Array, " n"],
    *,
    max_steps: int,
    tol: float,
    damping: float = 1e-6,
    max_step: float = jnp.inf,
) -> NewtonResult:
    """Minimise ``||fun(x)||^2`` from ``x0`` by Levenberg-Marquardt with Marquardt scaling.

    Each iteration evaluates ``fun`` and its Jacobian once at a trial point; the trial is
    accepted if it lowers the residual (then the damping shrinks by 3), otherwise the damping
    grows by 8. With small ``damping`` and a good ``x0`` this is plain Newton (quadratic
    convergence); with larger ``damping`` it is the safer cold-start variant. Stops when
    ``||r|| <= tol`` or after ``max_steps`` iterations. Non-finite trials are rejected, and
    steps are shortened to at most ``max_step`` in every component.
    """
    x0 = jax.lax.stop_gradient(x0)
    r0, J0 = _residual_and_jacobian(fun, x0)
    c0 = jnp.sum(r0**2)
    c0 = jnp.where(jnp.isfinite(c0), c0, jnp.inf)
    dtype = x0.dtype
    tol2 = jnp.asarray(tol, dtype) ** 2

    def propose(x, r, J, mu):
        A = J.T @ J
        A = A + mu * (jnp.diag(jnp.diag(A)) + jnp.eye(x.shape[0], dtype=dtype) * 1e-12)
        dx = jnp.linalg.solve(A, J.T @ r)
        dx = jnp.where(jnp.isfinite(dx), dx, 0.0)
        # Trust region in the max norm: a near-singular Jacobian must not throw x far away.
        big = jnp.max(jnp.abs(dx), initial=0.0)
        scale = jnp.minimum(1.0, max_step / jnp.where(big > 0, big, 1.0))
        return x - scale * dx

    def cond(state):
        k, _, _, _, cost, _, _ = state
        return (k < max_steps) & (cost > tol2)

    def body(state):
        k, x, r, J, cost, mu, _ = state
        xt = propose(x, r, J, mu)
        rt, Jt = _residual_and_jacobian(fun, xt)
        ct = jnp.sum(rt**2)
        accept = jnp.isfinite(ct) & jnp.all(jnp.isfinite(Jt)) & (ct < cost)
        x = jnp.where(accept, xt, x)
        r = jnp.where(accept, rt, r)
        J = jnp.where(accept, Jt, J)
        cost = jnp.where(accept, ct, cost)
        mu = jnp.clip(jnp.where(accept, mu / 3.0, mu * 8.0), 1e-12, 1e12)
        return k + 1, x, r, J, cost, mu, accept

    init = (jnp.zeros((), jnp.int32), x0, r0, J0, c0, jnp.asarray(damping, dtype), True)
    k, x, r, J, cost, _, _ = jax.lax.while_loop(cond, body, init)
    return NewtonResult(x=x, residual=jnp.sqrt(cost), jac=J, num_steps=k)


def implicit_newton_step(
    fun: Callable[[Array], Array], x_star: Float[Array, " n"], jac: Float[Array, "n n"]
) -> Float[Array, " n"]:
    """One Newton step from the converged ``x_star`` with the Jacobian held constant.

    ``fun`` closes over the parameters to differentiate with respect to. At a root, the value
    is ``x_star`` (refined by one more Newton step) and the derivative is the implicit-function
    one, ``dx/dp = -J^{-1} dr/dp``, without differentiating through the iterations.
    """
    x_star = jax.lax.stop_gradient(x_star)
    jac = jax.lax.stop_gradient(jac)
    r = fun(x_star)
    dx = jnp.linalg.solve(jac, r)
    return x_star - jnp.where(jnp.isfinite(dx), dx, 0.0)


__all__ = ["NewtonResult", "damped_newton", "implicit_newton_step"]
