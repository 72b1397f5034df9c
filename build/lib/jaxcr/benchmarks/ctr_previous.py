"""The concentric-tube solvers as they were before issue 18, kept as the reference that
``jaxcr bench fk`` and experiments/kinematics/profile_ctr.py time in the same run.

:class:`PreviousCTR` is :class:`jaxcr.kinematics.ctr.ConcentricTubeRobot` with the old solvers:
the residual scan on the full grid, ``optx.LevenbergMarquardt`` (``optx.least_squares``, at most
20 iterations, ``throw=False``) from every start, and 5 fixed Newton iterations with a
``jax.jacfwd`` Jacobian (:func:`jaxcr.kinematics.newton.fixed_newton`) for the warm path and the
polish. Same mechanics, same grid, same results up to the solver tolerance.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optimistix as optx

from jaxcr.kinematics.ctr import TEST_CTR, ConcentricTubeRobot
from jaxcr.kinematics.newton import fixed_newton, implicit_solution


def _shooting_fn(x, args):
    model, q = args
    return model._residual_and_energy(q, x)


class PreviousCTR(ConcentricTubeRobot):
    """The pre-issue-18 solvers (see the module docstring); build with :func:`make_previous`."""

    def _cold_solve(self, q, guesses):
        q = jax.lax.stop_gradient(q)
        tol = self._solver_tol(guesses.dtype)
        solver = optx.LevenbergMarquardt(rtol=tol, atol=tol)

        def one(g):
            sol = optx.least_squares(
                _shooting_fn, solver, g, args=(self, q), has_aux=True,
                max_steps=self.cold_steps, throw=False,
            )  # fmt: skip
            r, energy = self._residual_and_energy(q, sol.value)
            return sol.value, jnp.max(jnp.abs(r), initial=0.0), energy, sol.stats["num_steps"]

        return jax.vmap(one)(guesses)

    def _warm_solve(self, q, guess):
        qs = jax.lax.stop_gradient(q)
        res = fixed_newton(
            lambda x: self._residual_and_energy(qs, x), guess, steps=self.warm_steps,
            tol=self._solver_tol(guess.dtype), max_step=0.5,
        )  # fmt: skip
        x = implicit_solution(
            lambda p, z: p[0].shooting_residual(p[1], z), (self, q), res.x, res.jac
        )
        return x, res.num_steps, jnp.asarray(True)


def make_previous(**kwargs) -> PreviousCTR:
    """TEST_CTR with the previous solvers and their defaults (5 warm Newton iterations, at most
    20 LM iterations per start, the residual scan on the full 97-sample grid)."""
    n_points = kwargs.pop("n_points", 97)
    opts = {"warm_steps": 5, "cold_steps": 20, "scan_n_points": n_points} | kwargs
    return PreviousCTR.from_dict(TEST_CTR, n_points=n_points, **opts)


__all__ = ["PreviousCTR", "make_previous"]
