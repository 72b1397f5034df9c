"""Small dense nonlinear solves inside kinematics: fixed-iteration Newton for warm starts, and an
implicit-function step that makes the solution differentiable (cold starts use Optimistix, see
:mod:`jaxcr.kinematics.ctr`).

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


def fixed_newton(
    fun: Callable[[Array], tuple[Array, Array]],
    x0: Float[Array, " n"],
    *,
    steps: int,
    tol: float,
    max_step: float = jnp.inf,
) -> NewtonResult:
    """Newton's method on a square system ``(r, aux) = fun(x)`` for exactly ``steps`` passes.

    A ``fori_loop`` with a static trip count, so a vmapped batch costs ``steps`` residual +
    Jacobian evaluations per member whatever the members do (no while loop waiting for the
    slowest one). Once ``||r|| <= tol`` the iterate is frozen; ``num_steps`` counts the
    iterations taken before that. Steps are shortened to at most ``max_step`` in every
    component (a near-singular Jacobian must not throw x far away), non-finite steps are
    dropped. Meant for warm starts; from a poor start use a globalised solver.
    """
    x0 = jax.lax.stop_gradient(x0)
    dtype = x0.dtype

    def body(_, state):
        x, k = state
        r, J, _ = _residual_and_jacobian(fun, x)
        done = jnp.sqrt(jnp.sum(r**2)) <= tol
        dx = jnp.linalg.solve(J, r)
        dx = jnp.where(jnp.all(jnp.isfinite(dx)), dx, 0.0)
        big = jnp.max(jnp.abs(dx), initial=0.0)
        scale = jnp.minimum(1.0, max_step / jnp.where(big > 0, big, 1.0))
        x = jnp.where(done, x, x - scale * dx)
        return x, k + jnp.where(done, 0, 1).astype(jnp.int32)

    x, k = jax.lax.fori_loop(0, steps, body, (x0, jnp.zeros((), jnp.int32)))
    r, J, aux = _residual_and_jacobian(fun, x)
    return NewtonResult(
        x=x, residual=jnp.sqrt(jnp.sum(r**2)).astype(dtype), jac=J, num_steps=k, aux=aux
    )


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def implicit_solution(
    fun: Callable[[Any, Array], Array], params: Any, x_star: Array, jac: Array
) -> Array:
    """``x_star``, a root of ``fun(params, x)``, with the implicit-function derivative.

    The value is ``x_star`` (already solved, e.g. by :func:`fixed_newton`); the tangent with
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


__all__ = ["NewtonResult", "fixed_newton", "implicit_solution"]
