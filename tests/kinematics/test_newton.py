"""Tests of the small dense solvers in jaxcr.kinematics.newton used by the CTR model.

Reference: a 2x2 system with a closed-form root, r(x; p) = (x0^2 + x1 - p, x0 - x1), whose
positive root is x0 = x1 = (sqrt(1 + 4 p) - 1) / 2 (and scipy.optimize.root for a second
check). Tolerances: float64 throughout, so the solvers' own tolerance (1e-12) bounds the
error; the difference Jacobian (step 1e-6) is off by O(step) = 1e-6 relative, which only slows
the convergence (chord/Newton rate ~1e-6), never moves the root.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import root

from jaxcr.kinematics.newton import chord_newton, fd_jacobian, fd_newton, implicit_root


def _r(p, x):
    return jnp.stack([x[0] ** 2 + x[1] - p, x[0] - x[1]])


def _fun(p):
    return lambda x: (_r(p, x), jnp.sum(x**2))


def _root(p):
    a = (np.sqrt(1.0 + 4.0 * p) - 1.0) / 2.0
    return np.array([a, a])


@pytest.fixture(scope="module", autouse=True)
def _x64():
    with jax.enable_x64(True):
        yield


# every solver call is jitted (eager while loops dispatch op by op: tens of seconds)
FD_NEWTON = jax.jit(lambda p, x0: fd_newton(_fun(p), x0, steps=12, tol=1e-12, fd_step=1e-6))
CHORD = jax.jit(lambda p, x0: chord_newton(_fun(p), x0, max_steps=50, tol=1e-12, fd_step=1e-6))


def test_fd_jacobian_matches_jacfwd():
    x = jnp.array([0.7, -0.2])
    r, J, aux = jax.jit(lambda z: fd_jacobian(_fun(2.0), z, 1e-6))(x)
    np.testing.assert_allclose(J, jax.jacfwd(lambda z: _r(2.0, z))(x), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(r, _r(2.0, x), rtol=0, atol=0)
    assert float(aux) == pytest.approx(0.53)


@pytest.mark.parametrize("p", [2.0, 6.0])
def test_fd_newton_and_chord_find_the_closed_form_root(p):
    ref = root(lambda x: np.asarray(_r(p, jnp.asarray(x))), [1.0, 1.0], tol=1e-14).x
    np.testing.assert_allclose(ref, _root(p), atol=1e-10)
    res = FD_NEWTON(p, jnp.array([1.0, 1.0]))
    np.testing.assert_allclose(res.x, _root(p), atol=1e-11)
    # chord from a warm start near the root: stops at convergence, long before the bound
    warm = CHORD(p, jnp.asarray(_root(p) + 0.01))
    np.testing.assert_allclose(warm.x, _root(p), atol=1e-11)
    assert 1 <= int(warm.num_steps) <= 8
    assert float(warm.residual) <= 1e-12


def test_chord_under_vmap_equals_loop():
    starts = jnp.array([[1.01, 0.99], [1.05, 1.0], [0.98, 1.02]])
    batch = jax.jit(jax.vmap(lambda g: CHORD(2.0, g).x))(starts)
    for k, g in enumerate(starts):
        one = CHORD(2.0, g).x
        np.testing.assert_allclose(batch[k], one, atol=1e-12)


def test_implicit_root_derivative_is_the_closed_form():
    # d x0 / d p = 1 / sqrt(1 + 4 p) at the root
    def solve(p):
        x = chord_newton(_fun(p), jnp.array([1.0, 1.0]), max_steps=60, tol=1e-13,
                         fd_step=1e-6).x  # fmt: skip
        return implicit_root(lambda pp, z: _r(pp, z), p, x)

    p = 2.0
    d = jax.jit(jax.jacfwd(solve))(p)
    np.testing.assert_allclose(d, [1.0 / np.sqrt(9.0)] * 2, rtol=1e-9)
    g = jax.jit(jax.grad(lambda pp: solve(pp)[0]))(p)
    assert float(g) == pytest.approx(1.0 / 3.0, rel=1e-9)
