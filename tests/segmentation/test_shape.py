"""jaxcr.segmentation.shape: Chebyshev delta-u basis and its regularisation."""

import jax
import jax.numpy as jnp
import numpy as np
from numpy.polynomial import chebyshev as C

from jaxcr.segmentation.shape import (
    chebyshev_matrix,
    delta_u_steps,
    perturbed_centreline,
    regularisation,
)
from tests.helpers.jitted import integrate_centreline  # compiled: input construction only


def _base(n=33, length=0.1):
    s = jnp.linspace(0.0, length, n)
    u = jnp.tile(jnp.array([5.0, -2.0, 0.0]), (n - 1, 1))
    return integrate_centreline(s, u, jnp.full(n, 1e-3))


def test_chebyshev_matches_numpy():
    x = np.linspace(-1, 1, 17)
    T = np.asarray(chebyshev_matrix(jnp.asarray(x), 6))
    for k in range(6):
        ref = C.chebval(x, np.eye(6)[k])
        np.testing.assert_allclose(T[:, k], ref, atol=1e-5)


def test_zero_coefficients_reproduce_base():
    base = _base()
    cl = perturbed_centreline(base, jnp.zeros((2, 4)))
    np.testing.assert_allclose(cl.p, base.p, atol=1e-7)
    np.testing.assert_allclose(cl.R, base.R, atol=1e-6)


def test_delta_u_constant_term_and_torsion_flag():
    base = _base()
    L = float(base.s[-1])
    c = jnp.zeros((2, 3)).at[0, 0].set(0.5).at[1, 0].set(-0.25)
    du = np.asarray(delta_u_steps(c, base.s))
    np.testing.assert_allclose(du[:, 0], 0.5 / L, rtol=1e-5)
    np.testing.assert_allclose(du[:, 1], -0.25 / L, rtol=1e-5)
    np.testing.assert_allclose(du[:, 2], 0.0)
    c3 = jnp.zeros((3, 2)).at[2, 0].set(1.0)
    np.testing.assert_allclose(
        np.asarray(delta_u_steps(c3, base.s, torsion=True))[:, 2], 1 / L, rtol=1e-5
    )


def test_regularisation_closed_form():
    base = _base()
    # constant delta-u = c / L over length L: L * int (c/L)^2 ds = c^2
    c = jnp.zeros((2, 4)).at[0, 0].set(0.3).at[1, 0].set(0.4)
    np.testing.assert_allclose(float(regularisation(c, base.s)), 0.25, rtol=1e-5)
    # T_1(x) = x: L * int_0^L (x/L)^2 ds with x = 2s/L - 1 -> mean of x^2 = 1/3 (midpoint rule)
    c = jnp.zeros((2, 4)).at[0, 1].set(1.0)
    np.testing.assert_allclose(float(regularisation(c, base.s)), 1 / 3, rtol=2e-3)


def test_jit_vmap_grad():
    base = _base()
    cs = jax.random.normal(jax.random.PRNGKey(0), (5, 2, 4)) * 0.1
    f = jax.jit(lambda c: perturbed_centreline(base, c).p[-1])
    batched = jax.vmap(f)(cs)
    loop = np.stack([np.asarray(perturbed_centreline(base, c).p[-1]) for c in cs])
    np.testing.assert_allclose(batched, loop, atol=1e-6)
    g = jax.jit(jax.grad(lambda c: jnp.sum(perturbed_centreline(base, c).p[-1] ** 2)))(cs[0])
    eps = 1e-3
    e = jnp.zeros((2, 4)).at[1, 2].set(eps)
    fd = (jnp.sum(f(cs[0] + e) ** 2) - jnp.sum(f(cs[0] - e) ** 2)) / (2 * eps)
    np.testing.assert_allclose(float(g[1, 2]), float(fd), rtol=2e-2, atol=1e-6)
