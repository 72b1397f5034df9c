"""Small dense nonlinear solves inside kinematics: damped Newton (Levenberg-Marquardt) with a
bounded iteration count, and an implicit-function step that makes the solution differentiable.

Written for square systems of a handful of unknowns (e.g. CTR shooting): the Jacobian is formed
with forward-mode AD (one pass per unknown) and solved densely. Inside ``jax.vmap`` the loop
runs until the slowest batch member stops, so the iteration bound is the cost bound; it never
raises (see docs/ARCHITECTURE.md and /work/shared/PERFORMANCE-NOTES.md "Batching on CPU").
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jaxcr._types import Array, Float, Int


class NewtonResult(NamedTuple):
    x: Float[Array, " n"]  # best iterate (no gradient flows through it)
    residual: Float[Array, ""]  # ||r(x)||_2
    jac: Float[Array, "n n"]  # dr/dx at x
    num_steps: Int[Array, ""]  # iterations taken until ||r|| <= tol (or the bound)
    aux: Float[Array, ""]  # the scalar auxiliary output of ``fun`` at x


def _residual_and_jacobian(fun, x):
    def both(z):
        r, aux = fun(z)
        return r, (r, aux)

    jac, (r, aux) = jax.jacfwd(both, has_aux=True)(x)
    return r, jac, aux


def damped_newton(
    fun: Callable[[Array], tuple[Array, Array]],
    x0: Float[Array, " n"],
    *,
    max_steps: int,
    tol: float,
    damping: float = 1e-6,
    max_step: float = jnp.inf,
) -> NewtonResult:
    """Minimise ``||r(x)||^2``, ``(r, aux) = fun(x)``, from ``x0`` by Levenberg-Marquardt with Marquardt scaling.

    Each iteration evaluates ``fun`` and its Jacobian once at a trial point; the trial is
    accepted if it lowers the residual (then the damping shrinks by 3), otherwise the damping
    grows by 8. With small ``damping`` and a good ``x0`` this is plain Newton (quadratic
    convergence); with larger ``damping`` it is the safer cold-start variant. Stops when
    ``||r|| <= tol`` or after ``max_steps`` iterations. Non-finite trials are rejected, and
    steps are shortened to at most ``max_step`` in every component.
    """
    x0 = jax.lax.stop_gradient(x0)
    dtype = x0.dtype
    n = x0.shape[0]
    tol2 = jnp.asarray(tol, dtype) ** 2

    def propose(x, r, J, mu):
        A = J.T @ J
        A = A + mu * (jnp.diag(jnp.diag(A)) + jnp.eye(n, dtype=dtype) * 1e-12)
        dx = jnp.linalg.solve(A, J.T @ r)
        dx = jnp.where(jnp.isfinite(dx), dx, 0.0)
        # Trust region in the max norm: a near-singular Jacobian must not throw x far away.
        big = jnp.max(jnp.abs(dx), initial=0.0)
        scale = jnp.minimum(1.0, max_step / jnp.where(big > 0, big, 1.0))
        return x - scale * dx

    def cond(state):
        k, _, _, _, _, cost, _, _ = state
        return (k <= max_steps) & (cost > tol2)

    def body(state):
        # Evaluate the trial point (x0 itself on the first pass), accept it if it lowers the
        # residual, then propose the next trial. One residual + Jacobian evaluation per pass.
        k, xt, x, r, J, cost, mu, aux = state
        rt, Jt, auxt = _residual_and_jacobian(fun, xt)
        ct = jnp.sum(rt**2)
        accept = jnp.isfinite(ct) & jnp.all(jnp.isfinite(Jt)) & (ct < cost)
        x = jnp.where(accept, xt, x)
        r = jnp.where(accept, rt, r)
        J = jnp.where(accept, Jt, J)
        cost = jnp.where(accept, ct, cost)
        aux = jnp.where(accept, auxt, aux)
        mu = jnp.where(k == 0, mu, jnp.clip(jnp.where(accept, mu / 3.0, mu * 8.0), 1e-12, 1e12))
        return k + 1, propose(x, r, J, mu), x, r, J, cost, mu, aux

    init = (
        jnp.zeros((), jnp.int32),
        x0,
        x0,
        jnp.full((n,), jnp.inf, dtype),
        jnp.zeros((n, n), dtype),
        jnp.asarray(jnp.inf, dtype),
        jnp.asarray(damping, dtype),
        jnp.asarray(jnp.nan, dtype),
    )
    k, _, x, _, J, cost, _, aux = jax.lax.while_loop(cond, body, init)
    # k counts evaluations; the first one is at x0, so k - 1 Newton iterations were taken.
    return NewtonResult(
        x=x, residual=jnp.sqrt(cost), jac=J, num_steps=jnp.maximum(k - 1, 0), aux=aux
    )


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def implicit_solution(
    fun: Callable[[Any, Array], Array], params: Any, x_star: Array, jac: Array
) -> Array:
    """``x_star``, a root of ``fun(params, x)``, with the implicit-function derivative.

    The value is ``x_star`` (already solved, e.g. by :func:`damped_newton`); the tangent with
    respect to ``params`` is ``dx = -J^{-1} (d fun / d params) dparams`` with ``J = jac``, the
    Jacobian at the root, so no derivative flows through the solver iterations, and the residual
    is only differentiated when a derivative is asked for. ``x_star`` and ``jac`` get no tangent.
    Works in forward and reverse mode (the tangent rule is linear).
    """
    del fun, params, jac
    return x_star


@implicit_solution.defjvp
def _implicit_solution_jvp(fun, primals, tangents):
    params, x_star, jac = primals
    dparams = tangents[0]
    x_star = jax.lax.stop_gradient(x_star)
    jac = jax.lax.stop_gradient(jac)
    _, dr = jax.jvp(lambda p: fun(p, x_star), (params,), (dparams,))
    return x_star, -jnp.linalg.solve(jac, dr)


__all__ = ["NewtonResult", "damped_newton", "implicit_solution"]
