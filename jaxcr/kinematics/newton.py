"""Small dense nonlinear solves inside kinematics: fixed-iteration Newton (exact or
forward-difference Jacobian), chord iterations that stop at convergence for warm starts, and an
implicit-function step that makes the solution differentiable.

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


def fd_jacobian(
    fun: Callable[[Array], tuple[Array, Array]], x: Float[Array, " n"], step: float
) -> tuple[Array, Array, Array]:
    """Residual, forward-difference Jacobian and aux of ``(r, aux) = fun(x)`` at ``x``.

    The ``n + 1`` residuals (at ``x`` and at ``x + step e_j``) are one ``vmap``-ed evaluation,
    which on CPU costs about as much as three residuals for n = 2, against several times more
    for ``jax.jacfwd`` through a ``lax.scan`` (experiments/results/kinematics/profile_ctr.md).
    The error of J is ``O(step)`` (truncation) plus ``O(eps |r| / step)`` (rounding): with
    ``step = sqrt(eps)``-ish both are ~1e-3 relative in float32, which only turns Newton's
    quadratic convergence into a linear one of rate ~1e-3. Used for iterating, never for
    derivatives (:func:`implicit_root` forms the exact Jacobian when one is asked for).
    """
    n = x.shape[0]
    pts = jnp.concatenate([x[None], x[None] + step * jnp.eye(n, dtype=x.dtype)])
    r_all, aux_all = jax.vmap(fun)(pts)
    r = r_all[0]
    J = (r_all[1:] - r[None]).T / step
    return r, J, aux_all[0]


def clipped_newton_step(J: Array, r: Array, max_step: float) -> Array:
    """``J^{-1} r``, scaled so that no component exceeds ``max_step``; 0 if not finite."""
    dx = jnp.linalg.solve(J, r)
    dx = jnp.where(jnp.all(jnp.isfinite(dx)), dx, 0.0)
    big = jnp.max(jnp.abs(dx), initial=0.0)
    return jnp.minimum(1.0, max_step / jnp.where(big > 0, big, 1.0)) * dx


def fd_newton(
    fun: Callable[[Array], tuple[Array, Array]],
    x0: Float[Array, " n"],
    *,
    steps: int,
    tol: float,
    fd_step: float,
    max_step: float = jnp.inf,
) -> NewtonResult:
    """Newton with a forward-difference Jacobian (:func:`fd_jacobian`) for exactly ``steps``
    passes (``fori_loop``: fixed cost inside ``vmap``, e.g. over the cold starts of a branch
    search). Like :func:`fixed_newton`: frozen once ``||r|| <= tol``, steps clipped to
    ``max_step`` per component, non-finite steps dropped. The returned ``jac`` is the
    difference Jacobian at the last iterate before the final residual (not at ``x``)."""
    x0 = jax.lax.stop_gradient(x0)
    dtype = x0.dtype

    def body(_, state):
        x, k, _, _ = state
        r, J, _ = fd_jacobian(fun, x, fd_step)
        done = jnp.sqrt(jnp.sum(r**2)) <= tol
        x = jnp.where(done, x, x - clipped_newton_step(J, r, max_step))
        return x, k + jnp.where(done, 0, 1).astype(jnp.int32), J, done

    n = x0.shape[0]
    init = (x0, jnp.zeros((), jnp.int32), jnp.eye(n, dtype=dtype), jnp.asarray(False))
    x, k, J, _ = jax.lax.fori_loop(0, steps, body, init)
    r, aux = fun(x)
    return NewtonResult(
        x=x, residual=jnp.sqrt(jnp.sum(r**2)).astype(dtype), jac=J, num_steps=k, aux=aux
    )


def chord_newton(
    fun: Callable[[Array], tuple[Array, Array]],
    x0: Float[Array, " n"],
    *,
    max_steps: int,
    tol: float,
    fd_step: float,
    max_step: float = jnp.inf,
    jac0: Array | None = None,
) -> NewtonResult:
    """Quasi-Newton iterations that stop at convergence, for warm starts.

    The Jacobian is formed once, at ``x0``, by forward differences (:func:`fd_jacobian`),
    then ``x <- x - J^{-1} r(x)`` costs one residual per iteration, with Broyden's rank-one
    update of J after every step (``J += (dr - J dx) dx^T / |dx|^2``; superlinear, where plain
    chord iterations with a fixed J converge only linearly: in a 1024-member batch one member
    needing 8 chord iterations made the whole vmapped loop run 8, see
    experiments/results/kinematics/profile_ctr.md). A ``while_loop`` stops as soon as
    ``||r|| <= tol`` or after ``max_steps`` iterations (inside ``vmap``: when every member has
    stopped). ``num_steps`` = iterations taken; ``jac`` = the last J. ``jac0``: a Jacobian
    to start from instead of the difference one (e.g. from iterations on a coarser model).
    """
    x0 = jax.lax.stop_gradient(x0)
    dtype = x0.dtype
    if jac0 is None:
        r0, J0, aux0 = fd_jacobian(fun, x0, fd_step)
    else:
        (r0, aux0), J0 = fun(x0), jax.lax.stop_gradient(jac0)

    def norm(r):
        return jnp.sqrt(jnp.sum(r**2))

    def cond(state):
        _, r, _, _, k = state
        return (norm(r) > tol) & (k < max_steps)

    def body(state):
        x, r, J, _, k = state
        dx = -clipped_newton_step(J, r, max_step)
        x = x + dx
        r_new, aux = fun(x)
        dx2 = jnp.sum(dx**2)
        upd = jnp.outer(r_new - r - J @ dx, dx) / jnp.where(dx2 > 0, dx2, 1.0)
        J = jnp.where((dx2 > 0) & jnp.all(jnp.isfinite(upd)), J + upd, J)
        return x, r_new, J, aux, k + 1

    init = (x0, r0, J0, aux0, jnp.zeros((), jnp.int32))
    x, r, J, aux, k = jax.lax.while_loop(cond, body, init)
    return NewtonResult(x=x, residual=norm(r).astype(dtype), jac=J, num_steps=k, aux=aux)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def implicit_root(fun: Callable[[Any, Array], Array], params: Any, x_star: Array) -> Array:
    """``x_star``, a root of ``fun(params, x)``, with the implicit-function derivative.

    As :func:`implicit_solution`, but the Jacobian ``d fun / d x`` at the root is formed
    (``jax.jacfwd``) only when a derivative is asked for, so a solve that is never
    differentiated does not pay for it.
    """
    del fun, params
    return x_star


@implicit_root.defjvp
def _implicit_root_jvp(fun, primals, tangents):
    params, x_star = primals
    dparams = tangents[0]
    x_star = jax.lax.stop_gradient(x_star)
    params_const = jax.lax.stop_gradient(params)
    jac = jax.jacfwd(lambda z: fun(params_const, z))(x_star)
    _, dr = jax.jvp(lambda p: fun(p, x_star), (params,), (dparams,))
    return x_star, -jnp.linalg.solve(jac, dr)


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


__all__ = [
    "NewtonResult",
    "chord_newton",
    "clipped_newton_step",
    "fd_jacobian",
    "fd_newton",
    "fixed_newton",
    "implicit_root",
    "implicit_solution",
]
